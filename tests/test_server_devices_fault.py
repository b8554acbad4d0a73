"""Devices that cannot be opened do not take the server down: it serves status, config and history, says why
no shot can run (503), and opens the devices again when a configuration whose devices open is applied."""

from __future__ import annotations

import pytest
from fastapi.testclient import TestClient

from engine.config import SystemConfig
from engine.engine import EngineThread
from server.app import create_app
from server.service import LabService
from server_fakes import FakeEngine, example_config


def factory(config: SystemConfig) -> EngineThread:
    def build() -> FakeEngine:
        if config.devices.awg == "spectrum":
            # what drivers.factory.open_devices raises with spcm installed but no driver library
            from engine.devices import DeviceError

            raise DeviceError("Spectrum AWG: the spcm package is installed but the Spectrum driver library is not")
        return FakeEngine(config)

    return EngineThread(build)  # type: ignore[arg-type, return-value]  # a FakeEngine stands in for Engine


@pytest.fixture()
def client() -> TestClient:
    good = example_config()
    data = good.model_dump()
    data["devices"]["awg"] = "spectrum"
    broken = SystemConfig.model_validate(data)
    service = LabService(engine_thread=factory(broken), engine_factory=factory, config=broken, pause_s=0.01)
    service.start()
    with TestClient(create_app(service=service)) as c:
        yield c
    service.close()


def test_server_reports_the_devices_and_keeps_serving(client: TestClient) -> None:
    status = client.get("/api/status").json()
    assert status["state"] == "fault" and "driver library" in status["reason"] and "llrs devices" in status["reason"]
    assert client.get("/api/config").json()["devices"]["awg"] == "spectrum"
    for method, path in (("post", "/api/shots"), ("post", "/api/run"), ("post", "/api/arm")):
        r = getattr(client, method)(path)
        assert r.status_code == 503 and "could not be opened" in r.json()["detail"], (path, r.text)
    assert client.get("/api/shots").status_code == 200


def test_a_config_with_working_devices_recovers(client: TestClient) -> None:
    r = client.patch("/api/config", json={"devices": {"awg": "sim"}})
    assert r.status_code == 200, r.text
    assert client.get("/api/status").json()["state"] != "fault"
    shot = client.post("/api/shots")
    assert shot.status_code == 200
    # switching back to devices that do not open is refused, and the working engine stays
    r = client.patch("/api/config", json={"devices": {"awg": "spectrum"}})
    assert r.status_code == 422 and "could not be opened" in str(r.json()["detail"])
    assert client.get("/api/config").json()["devices"]["awg"] == "sim"
    assert client.post("/api/shots").status_code == 200
