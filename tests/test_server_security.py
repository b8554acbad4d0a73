"""Safe on a lab network: each attack or fault a careless or hostile client tried, reproduced against the app
(FastAPI's TestClient on the stand-in engine), now refused or recovered from."""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from pathlib import Path

import h5py
import pytest
from fastapi.testclient import TestClient
from starlette.websockets import WebSocketDisconnect

from engine.config import SystemConfig
from engine.engine import EngineThread
from server.app import create_app
from server.service import LabService
from server_fakes import fake_engine_host, fake_lab_service

TOKEN = "lab-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def fake_factory(config: SystemConfig) -> EngineThread:
    return fake_engine_host(config, keep_images=True)


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[LabService]:
    (tmp_path / "tones").mkdir()
    (tmp_path / "shots").mkdir()
    with fake_lab_service(
        tmp_path / "runs",
        engine_kw={"keep_images": True},
        engine_factory=fake_factory,
        tone_dir=tmp_path / "tones",
        shot_dir=tmp_path / "shots",
    ) as service:
        yield service


@pytest.fixture
def secured(lab: LabService) -> Iterator[TestClient]:
    with TestClient(create_app(service=lab, token=TOKEN), headers=AUTH) as c:
        yield c


@pytest.fixture
def loopback(lab: LabService) -> Iterator[TestClient]:
    """No token: what ``llrs serve`` builds on 127.0.0.1."""
    app = create_app(service=lab, trusted_hosts=("127.0.0.1", "localhost", "::1"))
    with TestClient(app, base_url="http://127.0.0.1:8000") as c:
        yield c


# -- 2. files --------------------------------------------------------------------------------------------------

def tone_csv(path: Path, n: int = 64) -> Path:
    rows = "\n".join(f"0.015,{80e6 + k * 1e6:.1f},0.0" for k in range(n))
    path.write_text("alpha,nu,phi\n" + rows + "\n")
    return path


@pytest.mark.parametrize("where", ["/proc/self/environ", "/etc/passwd", "../outside.csv"])
def test_tone_file_outside_the_tone_dir_is_refused_without_reading_it(
    secured: TestClient, lab: LabService, where: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("LLRS_TEST_SECRET", "do-not-leak")
    before = secured.get("/api/config").json()
    r = secured.patch("/api/config", json={"array": {"x_tones": {"csv": where}}})
    assert r.status_code == 422
    assert "outside" in r.text and "--tone-dir" in r.text
    assert "do-not-leak" not in r.text and "root:" not in r.text
    assert secured.get("/api/config").json() == before


def test_special_and_oversize_tone_files_are_refused(secured: TestClient, lab: LabService) -> None:
    assert lab.tone_dir is not None
    fifo = lab.tone_dir / "fifo.csv"
    os.mkfifo(fifo)
    r = secured.patch("/api/config", json={"array": {"x_tones": {"csv": "fifo.csv"}}})  # would hang if opened
    assert r.status_code == 422 and "not a regular file" in r.text
    big = lab.tone_dir / "big.csv"
    big.write_text("alpha,nu,phi\n" + "1" * 300_000 + "\n")
    r = secured.patch("/api/config", json={"array": {"x_tones": {"csv": "big.csv"}}})
    assert r.status_code == 422 and "at most" in r.text and "111" not in r.text


def test_a_tone_file_in_the_tone_dir_is_used_by_its_resolved_path(secured: TestClient, lab: LabService) -> None:
    assert lab.tone_dir is not None
    tone_csv(lab.tone_dir / "x.csv")
    r = secured.patch("/api/config", json={"array": {"x_tones": {"csv": "x.csv"}}})
    assert r.status_code == 200, r.text
    assert Path(lab.config.array.x_tones.csv) == (lab.tone_dir / "x.csv").resolve()


def test_shot_files_come_only_from_the_shot_dir(secured: TestClient, lab: LabService, tmp_path: Path) -> None:
    outside = tmp_path / "elsewhere.h5"
    with h5py.File(outside, "w") as f:
        f.create_group("globals")
    r = secured.post("/api/labscript", json={"path": str(outside)})
    assert r.status_code == 422 and "--shot-dir" in r.text
    with h5py.File(outside, "r") as f:
        assert "results" not in f  # nothing was written into a file outside the shot dir
    assert lab.shot_dir is not None
    os.mkfifo(lab.shot_dir / "fifo.h5")
    r = secured.post("/api/labscript", json={"path": "fifo.h5"})  # would hang h5py if opened
    assert r.status_code == 422 and "not a regular file" in r.text
    (lab.shot_dir / "text.h5").write_text("not hdf5")
    r = secured.post("/api/labscript", json={"path": "text.h5"})
    assert r.status_code == 422 and "0x" not in r.text
    assert secured.post("/api/labscript", json={"path": "missing.h5"}).status_code == 404


# -- 3. bounded numbers; any error applying a config is a 422 --------------------------------------------------

@pytest.mark.parametrize(
    "patch",
    [
        {"awg": {"upload_jitter_s": 1e300}},
        {"awg": {"step_write_s": 1e300}},
        {"camera": {"read_noise_e": 1e300}},
        {"sim": {"seed": 2**80}},
        {"sim": {"seed": -1}},
        {"waveforms": {"table_max_bytes": 2**60}},
        {"name": "x" * 2_000},
        {"target": {"kind": "mask", "mask": ["1" * 2_000]}},
    ],
)
def test_unbounded_numbers_are_refused(secured: TestClient, patch: dict) -> None:
    before = secured.get("/api/config").json()
    r = secured.patch("/api/config", json=patch)
    assert r.status_code == 422, r.text
    assert secured.get("/api/config").json() == before


def test_any_engine_error_while_applying_is_a_422(secured: TestClient, lab: LabService) -> None:
    def overflow(config: SystemConfig) -> None:
        raise OverflowError("int too large to convert to float")

    engine = lab._et.engine  # type: ignore[union-attr]  # started above
    engine.apply = overflow
    before = secured.get("/api/config").json()
    r = secured.patch("/api/config", json={"loop": {"max_cycles": 4}})
    assert r.status_code == 422 and "OverflowError" in r.text
    assert secured.get("/api/config").json() == before


def test_calibration_frames_are_bounded(secured: TestClient) -> None:
    secured.patch("/api/config", json={"camera": {"roi_width_px": 4096, "roi_height_px": 4096}})
    r = secured.post("/api/calibrate/threshold", json={"images": 500})
    assert r.status_code == 422 and "at most" in r.text


# -- 4. denial of service without a token ----------------------------------------------------------------------

def test_token_is_checked_before_the_body_is_read(lab: LabService) -> None:
    with TestClient(create_app(service=lab, token=TOKEN)) as c:
        r = c.patch("/api/config", content=b"{" * 10_000_000, headers={"Content-Type": "application/json"})
        assert r.status_code == 401
        r = c.patch("/api/config", content=b"{" * 10_000_000, headers={**AUTH, "Content-Type": "application/json"})
        assert r.status_code == 413


def test_live_subscribers_are_capped(lab: LabService) -> None:
    with TestClient(create_app(service=lab, max_live=2)) as c:
        with c.websocket_connect("/api/live"), c.websocket_connect("/api/live"):
            with pytest.raises(WebSocketDisconnect):  # refused at the handshake
                with c.websocket_connect("/api/live"):
                    pass
        with c.websocket_connect("/api/live"):  # a slot is free again once one left
            pass


# -- 5. no-token mode: trusted hosts and origins, JSON only ----------------------------------------------------

def test_foreign_host_is_refused(loopback: TestClient) -> None:
    assert loopback.get("/api/status").status_code == 200
    assert loopback.get("/api/status", headers={"Host": "evil.example:8000"}).status_code == 400


def test_cross_origin_text_plain_put_is_refused(loopback: TestClient, lab: LabService) -> None:
    before = lab.config
    page = {"Origin": "http://localhost:3000", "Content-Type": "text/plain"}
    assert loopback.put("/api/config", content=b"{}", headers=page).status_code == 403
    assert loopback.post("/api/shots", headers={"Origin": "http://localhost:3000"}).status_code == 403
    assert loopback.put("/api/config", content=b"{}", headers={"Content-Type": "text/plain"}).status_code == 415
    assert lab.config == before and lab.status().shots_done == 0
    same_origin = {"Origin": "http://127.0.0.1:8000"}  # the API docs page of this server
    assert loopback.post("/api/shots", headers=same_origin).status_code == 200


# -- 6. state --------------------------------------------------------------------------------------------------

def test_shot_ids_keep_increasing_when_devices_are_reopened(secured: TestClient) -> None:
    first = [secured.post("/api/shots").json()["shot_id"] for _ in range(3)]
    r = secured.patch("/api/config", json={"devices": {"frame_source": "sim"}})  # a devices change re-opens
    assert r.status_code == 200, r.text
    later = [secured.post("/api/shots").json()["shot_id"] for _ in range(3)]
    ids = first + later
    assert ids == sorted(ids) and len(set(ids)) == 6
    assert secured.get(f"/api/shots/{first[1]}").json()["shot_id"] == first[1]


def test_one_shot_override_cannot_change_devices(secured: TestClient, lab: LabService) -> None:
    r = secured.post("/api/shots", json={"config": {"devices": {"frame_source": "sim"}}})
    assert r.status_code == 422 and "devices" in r.text
    assert lab.config.devices.frame_source == "auto"


def test_rejected_configs_are_not_kept(secured: TestClient, lab: LabService) -> None:
    assert lab._store is not None
    for n in range(5):
        secured.patch("/api/config", json={"solver": {"algorithm": "refuse"}, "loop": {"max_cycles": 1 + n}})
    assert all(c.solver.algorithm != "refuse" for c in lab._store._configs.values())


def test_recording_error_clears_once_the_disk_works_again(secured: TestClient, lab: LabService) -> None:
    assert lab._store is not None
    secured.patch("/api/config", json={"sim": {"faults": {"disk_full": True}}})
    secured.post("/api/shots")
    lab._store.flush()
    assert secured.get("/api/status").json()["recording_error"]
    secured.patch("/api/config", json={"sim": {"faults": {"disk_full": False}}})
    secured.post("/api/shots")
    lab._store.flush()
    status = secured.get("/api/status").json()
    assert status["recording_error"] is None and status["unrecorded_shots"] == 1


@pytest.mark.parametrize("method", ["put", "patch"])
def test_deeply_nested_body_is_a_400(secured: TestClient, method: str) -> None:
    body = b'{"a":' * 100_000 + b"1" + b"}" * 100_000
    r = getattr(secured, method)("/api/config", content=body, headers={"Content-Type": "application/json"})
    assert r.status_code in (400, 422), r.text


def test_psf_calibration_without_atoms_fails(secured: TestClient) -> None:
    secured.patch("/api/config", json={"sim": {"loading_probability": 0.0}})
    r = secured.post("/api/calibrate/psf", json={"images": 5})
    assert r.status_code == 409, r.text
    assert secured.get("/api/calibrate").json() == []


# -- 1. the dashboard's authority ------------------------------------------------------------------------------

def test_dashboard_is_read_only_until_logged_in(lab: LabService) -> None:
    pytest.importorskip("viser")
    from viser import GuiEvent

    from frontend.dashboard import Dashboard

    dashboard = Dashboard(lab, port=0, token=TOKEN, refresh_s=0.05)
    dashboard.start()
    try:
        def click(button, client_id: int) -> None:  # noqa: ANN001 - a viser button handle
            for callback in button._impl.update_cb:
                callback(GuiEvent(client=None, client_id=client_id, target=button))

        before = lab.config
        click(dashboard.b_once, client_id=7)
        click(dashboard.b_run, client_id=7)
        dashboard.s_loading.value = 0.9
        click(dashboard.b_sim, client_id=7)
        assert lab.status().shots_done == 0 and not lab.running and lab.config == before
        assert "read-only" in dashboard.h_message.content
        assert not dashboard.login(7, "wrong")
        assert dashboard.login(7, TOKEN)
        click(dashboard.b_once, client_id=7)
        assert lab.status().shots_done == 1
        click(dashboard.b_once, client_id=8)  # another tab is still read-only
        assert lab.status().shots_done == 1
    finally:
        dashboard.stop()


def test_a_command_waits_for_a_busy_engine_only_so_long(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A PATCH stuck behind a long shot is refused after COMMAND_WAIT_S, and is not applied afterwards."""
    import threading

    import server.service

    monkeypatch.setattr(server.service, "COMMAND_WAIT_S", 0.2)
    with fake_lab_service(None, engine_kw={"shot_s": 1.0}, pause_s=0.0) as service:
        with TestClient(create_app(service=service)) as c:
            shot = threading.Thread(target=service.shot)
            shot.start()
            deadline = time.monotonic() + 5
            while service.status().activity is None:
                assert time.monotonic() < deadline
                time.sleep(0.01)
            before = service.config
            r = c.patch("/api/config", json={"loop": {"max_cycles": 2}})
            assert r.status_code == 503 and "busy" in r.text and "one shot" in r.text
            shot.join()
            assert service.config == before
