"""The REST API and the live websocket, through HTTP (FastAPI's TestClient), on the stand-in engine."""

from __future__ import annotations

import asyncio
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest
from fastapi.testclient import TestClient

from engine.engine import EngineThread
from engine.psf import frame_shape
from server.app import create_app
from server.hub import LiveHub
from server.runstore import RunStore
from server.service import LabService
from server_fakes import FakeEngine, example_config, png_pixels


def make_service(tmp_path: Path, **engine_kw: object) -> tuple[LabService, FakeEngine]:
    holder: list[FakeEngine] = []

    def build() -> FakeEngine:
        holder.append(FakeEngine(example_config(), **engine_kw))
        return holder[0]

    service = LabService(
        engine_thread=EngineThread(build),  # type: ignore[arg-type]
        store=RunStore(tmp_path / "runs"),
        pause_s=0.005,
    ).start()
    return service, holder[0]


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[tuple[LabService, FakeEngine]]:
    service, engine = make_service(tmp_path, keep_images=True)
    yield service, engine
    service.close()


@pytest.fixture
def client(lab: tuple[LabService, FakeEngine]) -> Iterator[TestClient]:
    with TestClient(create_app(service=lab[0], dashboard_port=8080)) as c:
        yield c


def test_index_links_dashboard_and_docs(client: TestClient) -> None:
    r = client.get("/")
    assert r.status_code == 200
    assert 'href="http://testserver:8080/"' in r.text and "/docs" in r.text
    assert client.get("/openapi.json").json()["info"]["title"] == "LLRS lab server"


def test_status_idle_then_after_a_shot(client: TestClient) -> None:
    s = client.get("/api/status").json()
    assert s["state"] == "idle" and s["shots_done"] == 0 and s["last_shot"] is None
    assert s["devices"] == {"camera": "sim", "awg": "sim", "time": "simulated"}
    shot = client.post("/api/shots").json()
    s = client.get("/api/status").json()
    assert s["shots_done"] == 1 and s["last_shot"]["shot_id"] == shot["shot_id"]
    assert s["success_rate"] == (1.0 if shot["outcome"] == "success" else 0.0)


def test_post_shot_returns_record_and_is_listed(client: TestClient) -> None:
    shot = client.post("/api/shots").json()
    assert shot["target"] == ["0" * 16 + "1" * 32 + "0" * 16]
    assert shot["cycles"][0]["occupancy"][0].count("1") == shot["atoms_loaded"]
    listed = client.get("/api/shots").json()
    assert listed["total"] == 1 and listed["shots"][0]["shot_id"] == shot["shot_id"]
    assert client.get(f"/api/shots/{shot['shot_id']}").json() == shot


def test_list_shots_paginates_newest_first(client: TestClient) -> None:
    ids = [client.post("/api/shots").json()["shot_id"] for _ in range(5)]
    page = client.get("/api/shots", params={"limit": 2, "offset": 1}).json()
    assert page["total"] == 5 and [s["shot_id"] for s in page["shots"]] == ids[::-1][1:3]
    assert client.get("/api/shots", params={"limit": 0}).status_code == 422
    assert client.get("/api/shots", params={"offset": -1}).status_code == 422


def test_unknown_shot_and_image_are_404(client: TestClient) -> None:
    assert client.get("/api/shots/12345").status_code == 404
    assert client.get("/api/shots/12345/image/0").status_code == 404
    shot = client.post("/api/shots").json()
    assert client.get(f"/api/shots/{shot['shot_id']}/image/99").status_code == 404
    assert client.get(f"/api/shots/{shot['shot_id']}/image/-1").status_code == 422


def test_image_is_lossless_png(client: TestClient) -> None:
    shot = client.post("/api/shots").json()
    r = client.get(f"/api/shots/{shot['shot_id']}/image/0")
    assert r.status_code == 200 and r.headers["content-type"] == "image/png"
    pixels = png_pixels(r.content)
    assert pixels.shape == frame_shape(example_config().camera) and (pixels == 500).all()


def test_get_put_patch_config(client: TestClient, lab: tuple[LabService, FakeEngine]) -> None:
    cfg = client.get("/api/config").json()
    assert cfg["name"] == "chain-1x64"
    cfg["sim"]["loading_probability"] = 0.9
    r = client.put("/api/config", json=cfg)
    assert r.status_code == 200 and r.json()["sim"]["loading_probability"] == 0.9
    assert lab[1].config.sim.loading_probability == 0.9  # applied in the engine
    r = client.patch("/api/config", json={"loop": {"max_cycles": 3}, "imaging": {"threshold": None}})
    assert r.status_code == 200
    got = client.get("/api/config").json()
    assert got["loop"]["max_cycles"] == 3 and got["sim"]["loading_probability"] == 0.9


@pytest.mark.parametrize(
    ("method", "body", "field"),
    [
        ("patch", {"sim": {"loading_probability": 1.5}}, ["body", "sim", "loading_probability"]),
        ("patch", {"waveforms": {"shape": "square"}}, ["body", "waveforms", "shape"]),
        ("patch", {"nonsense": 1}, ["body", "nonsense"]),
        ("patch", {"array": {"ny": 2}}, ["body", "array"]),  # a chain needs one row
        ("patch", {"solver": {"algorithm": "refuse"}}, ["body"]),  # the engine refuses it when applying
        ("put", {"sim": {"loading_probability": -1}}, ["body", "sim", "loading_probability"]),
        ("put", {"loop": {"max_cycles": "many"}}, ["body", "loop", "max_cycles"]),
    ],
)
def test_bad_config_is_422_and_changes_nothing(
    client: TestClient, lab: tuple[LabService, FakeEngine], method: str, body: dict, field: list
) -> None:
    before = client.get("/api/config").json()
    applied = len(lab[1].applied)
    r = client.request(method.upper(), "/api/config", json=body)
    assert r.status_code == 422
    detail = r.json()["detail"]
    assert any(d["loc"][: len(field)] == field and d["msg"] for d in detail), detail
    assert client.get("/api/config").json() == before
    assert lab[1].config.model_dump(mode="json") == before
    assert len(lab[1].applied) <= applied + 1  # at most the refused attempt reached the engine


def test_malformed_json_is_a_declared_client_error(client: TestClient) -> None:
    r = client.patch("/api/config", content=b"{not json", headers={"content-type": "application/json"})
    assert r.status_code in (400, 422)
    r = client.patch("/api/config", json=[1, 2])
    assert r.status_code == 422


def test_shot_with_override_applies_for_that_shot_only(client: TestClient, lab: tuple[LabService, FakeEngine]) -> None:
    before = client.get("/api/config").json()
    r = client.post("/api/shots", json={"config": {"sim": {"loading_probability": 1.0}}})
    assert r.status_code == 200
    shot = r.json()
    assert shot["atoms_loaded"] == 64 and shot["config_digest"] != lab[0].config.digest()
    assert client.get("/api/config").json() == before
    assert lab[1].config.model_dump(mode="json") == before
    r = client.post("/api/shots", json={"config": {"sim": {"loading_probability": 2}}})
    assert r.status_code == 422 and client.get("/api/config").json() == before


def test_two_concurrent_shots_are_serialized(tmp_path: Path) -> None:
    service, engine = make_service(tmp_path, shot_s=0.1)
    try:
        with TestClient(create_app(service=service)) as c:
            results: list[dict] = []
            threads = [threading.Thread(target=lambda: results.append(c.post("/api/shots").json())) for _ in range(2)]
            t0 = time.monotonic()
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            assert time.monotonic() - t0 >= 0.2
            assert sorted(r["shot_id"] for r in results) == [0, 1]
            assert engine.max_in_shot == 1
    finally:
        service.close()


def test_run_and_stop(client: TestClient, wait_until: Callable[..., None]) -> None:
    r = client.post("/api/run")
    assert r.status_code == 200 and r.json()["running"] is True
    wait_until(lambda: client.get("/api/status").json()["shots_done"] >= 3, timeout_s=5, what="three shots")
    assert client.get("/api/status").json()["state"] == "running"
    assert client.post("/api/stop").json()["running"] is False
    wait_until(lambda: client.get("/api/status").json()["state"] == "idle", what="the shot in progress to end")
    done = client.get("/api/status").json()["shots_done"]
    time.sleep(0.1)  # a window for a shot that must not start: its absence has no event to wait on
    s = client.get("/api/status").json()
    assert s["shots_done"] == done and s["state"] == "idle"


def test_fault_shows_in_status_and_stops_continuous_shots(
    client: TestClient, lab: tuple[LabService, FakeEngine], wait_until: Callable[..., None]
) -> None:
    lab[1].fault = "DeviceError: AWG underrun"
    client.post("/api/run")
    wait_until(lambda: client.get("/api/status").json()["state"] == "fault", timeout_s=5, what="the fault state")
    s = client.get("/api/status").json()
    assert s["reason"] == "DeviceError: AWG underrun" and s["running"] is False
    client.post("/api/run")  # a person restarts: the fault is cleared
    assert client.get("/api/status").json()["state"] == "running"
    client.post("/api/stop")


def test_live_websocket_sends_each_cycle(client: TestClient) -> None:
    with client.websocket_connect("/api/live") as ws:
        shot = client.post("/api/shots").json()
        messages = [ws.receive_json() for _ in range(len(shot["cycles"]))]
    assert [m["cycle"] for m in messages] == list(range(len(shot["cycles"])))
    assert all(m["type"] == "cycle" and m["shot_id"] == shot["shot_id"] for m in messages)
    assert messages[-1]["last"] and messages[-1]["outcome"] == shot["outcome"]
    assert messages[0]["occupancy"] == shot["cycles"][0]["occupancy"] and messages[0]["target"] == shot["target"]
    assert set(messages[0]["stage_us"]) >= {"I.acquire", "II.detect"}


def test_live_websocket_starts_with_the_last_shot(client: TestClient) -> None:
    shot = client.post("/api/shots").json()
    with client.websocket_connect("/api/live") as ws:
        first = ws.receive_json()
    assert first["shot_id"] == shot["shot_id"] and first["cycle"] == 0


def test_stalled_live_subscriber_drops_oldest_and_never_blocks(lab: tuple[LabService, FakeEngine]) -> None:
    """A subscriber that never reads: the publishing (engine) thread never waits, the queue keeps the newest."""
    hub = LiveHub(maxsize=8)
    records = lab[0].shot(), lab[0].shot()

    async def scenario() -> asyncio.Queue:
        hub.bind(asyncio.get_running_loop())
        q = hub.subscribe()
        t0 = time.perf_counter()
        publisher = threading.Thread(target=lambda: [hub.publish_record(records[i % 2]) for i in range(200)])
        publisher.start()
        await asyncio.to_thread(publisher.join)
        assert time.perf_counter() - t0 < 1.0
        await asyncio.sleep(0.05)  # let the loop run the scheduled fan-outs
        return q

    q = asyncio.run(scenario())
    assert q.qsize() == 8 and hub.dropped > 0
    newest = [q.get_nowait() for _ in range(8)]
    assert newest[-1]["shot_id"] == records[1].shot_id and newest[-1]["last"]


@pytest.fixture
def secured(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Iterator[TestClient]:
    service, _ = make_service(tmp_path)
    try:
        with TestClient(create_app(service=service, token="s3cret")) as c:
            yield c
    finally:
        service.close()


@pytest.mark.parametrize(
    ("method", "path", "body", "authorized"),
    [
        ("POST", "/api/shots", None, 200),
        ("POST", "/api/run", None, 200),
        ("POST", "/api/stop", None, 200),
        ("PATCH", "/api/config", {"sim": {"loading_probability": 0.5}}, 200),
        ("PUT", "/api/config", {}, 200),
        ("POST", "/api/arm", None, 200),
        ("POST", "/api/trigger", None, 409),  # authorized, but not armed
        ("POST", "/api/calibrate/threshold", {"images": 10}, 200),
        ("POST", "/api/calibrate/psf", {"images": 10}, 200),
        ("POST", "/api/calibrate/apply", {"id": "psf-9"}, 404),  # authorized, no such calibration
    ],
)
def test_mutations_need_the_token(
    secured: TestClient, method: str, path: str, body: dict | None, authorized: int
) -> None:
    before = secured.get("/api/config").json()
    for headers in ({}, {"Authorization": "Bearer wrong"}, {"Authorization": "Basic czNjcmV0"}):
        r = secured.request(method, path, json=body, headers=headers)
        assert r.status_code == 401, (headers, r.text)
        assert r.headers["www-authenticate"] == "Bearer"
    assert secured.get("/api/config").json() == before
    status = secured.get("/api/status").json()
    assert status["shots_done"] == 0 and status["state"] == "idle"
    assert secured.get("/api/calibrate").json() == []
    r = secured.request(method, path, json=body, headers={"Authorization": "Bearer s3cret"})
    assert r.status_code == authorized, r.text


def test_reads_need_no_token(secured: TestClient) -> None:
    for path in ("/", "/api/status", "/api/config", "/api/shots", "/api/calibrate", "/openapi.json"):
        assert secured.get(path).status_code == 200


def test_cors_closed_by_default(client: TestClient) -> None:
    r = client.options(
        "/api/shots", headers={"Origin": "http://evil.example", "Access-Control-Request-Method": "POST"}
    )
    assert "access-control-allow-origin" not in r.headers
    r = client.get("/api/status", headers={"Origin": "http://evil.example"})
    assert "access-control-allow-origin" not in r.headers


def test_every_shot_lands_in_the_run_file(client: TestClient, lab: tuple[LabService, FakeEngine]) -> None:
    ids = [client.post("/api/shots").json()["shot_id"] for _ in range(3)]
    client.patch("/api/config", json={"sim": {"loading_probability": 0.7}})
    ids.append(client.post("/api/shots").json()["shot_id"])
    store = lab[0]._store
    assert store is not None
    store.flush()
    files = sorted(store.directory.glob("*.h5"))
    assert len(files) == 2  # a new configuration starts a new run file
    with h5py.File(files[0], "r", swmr=True) as f:
        assert list(f["shot_id"][:]) == ids[:3]
        assert f["occupancy"].shape[1:] == (6, 1, 64)
        assert '"loading_probability":0.6' in f.attrs["config_json"]
    with h5py.File(files[1], "r", swmr=True) as f:
        assert list(f["shot_id"][:]) == ids[3:]


# -- strict config validation -----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "patch",
    [
        {"sim": {"lossless": 0}},  # a number is not a boolean
        {"loop": {"max_cycles": "5"}},  # a string is not a number
        {"camera": {"exposure_s": "0.02"}},
    ],
)
def test_config_is_validated_strictly(client: TestClient, patch: dict) -> None:
    before = client.get("/api/config").json()
    r = client.patch("/api/config", json=patch)
    assert r.status_code == 422, r.text
    section, field = next(iter(patch.items()))
    assert any(d["loc"] == ["body", section, next(iter(field))] for d in r.json()["detail"])
    full = {**before, section: {**before[section], **field}}
    assert client.put("/api/config", json=full).status_code == 422
    assert client.get("/api/config").json() == before


def test_put_config_not_an_object_or_not_json(client: TestClient) -> None:
    before = client.get("/api/config").json()
    assert client.put("/api/config", json=[1]).status_code == 422
    r = client.put("/api/config", content=b"{nope", headers={"content-type": "application/json"})
    assert r.status_code == 400 and "not valid JSON" in r.json()["detail"]
    assert client.get("/api/config").json() == before


# -- arm and trigger --------------------------------------------------------------------------------------------


def test_trigger_without_arm_is_409_and_runs_nothing(client: TestClient) -> None:
    r = client.post("/api/trigger")
    assert r.status_code == 409 and "arm" in r.json()["detail"]
    assert client.get("/api/status").json()["shots_done"] == 0


def test_arm_then_trigger_runs_one_shot_each(client: TestClient) -> None:
    r = client.post("/api/arm")
    assert r.status_code == 200 and r.json() == {"armed": True, "trigger": "rest", "shots_left": None}
    s = client.get("/api/status").json()
    assert s["state"] == "armed" and s["armed"] and s["activity"] == "waiting for the trigger"
    time.sleep(0.05)  # a window for a shot that must not start: its absence has no event to wait on
    assert client.get("/api/status").json()["shots_done"] == 0  # armed does not run shots by itself
    first = client.post("/api/trigger").json()
    second = client.post("/api/trigger").json()
    assert second["shot_id"] == first["shot_id"] + 1
    s = client.get("/api/status").json()
    assert s["state"] == "armed" and s["shots_done"] == 2
    client.post("/api/stop")
    assert client.get("/api/status").json()["state"] == "idle"
    assert client.post("/api/trigger").status_code == 409


def test_arm_for_n_shots_disarms_after_them(client: TestClient) -> None:
    assert client.post("/api/arm", json={"shots": 2}).json()["shots_left"] == 2
    assert client.post("/api/trigger").status_code == 200
    assert client.get("/api/status").json()["state"] == "armed"
    assert client.post("/api/trigger").status_code == 200
    assert client.get("/api/status").json()["state"] == "idle"
    assert client.post("/api/trigger").status_code == 409


@pytest.mark.parametrize("body", [{"shots": 0}, {"shots": "two"}, {"shots": 1.5}, [1]])
def test_bad_arm_is_422_and_leaves_state(client: TestClient, body: object) -> None:
    r = client.post("/api/arm", json=body)
    assert r.status_code == 422 and r.json()["detail"][0]["loc"][0] == "body"
    assert client.get("/api/status").json()["state"] == "idle"


def test_arm_stops_continuous_shots_and_run_disarms(client: TestClient, wait_until: Callable[..., None]) -> None:
    client.post("/api/run")
    client.post("/api/arm")
    wait_until(lambda: client.get("/api/status").json()["activity"] == "waiting for the trigger",
               what="the shot in progress to end")
    done = client.get("/api/status").json()["shots_done"]
    time.sleep(0.1)  # a window for a shot that must not start: its absence has no event to wait on
    s = client.get("/api/status").json()
    assert s["state"] == "armed" and s["running"] is False and s["shots_done"] == done
    client.post("/api/run")
    s = client.get("/api/status").json()
    assert s["armed"] is False and s["state"] == "running"
    client.post("/api/stop")


def test_hardware_trigger_without_a_trigger_input_is_refused(client: TestClient) -> None:
    client.patch("/api/config", json={"loop": {"trigger": "hardware"}})
    r = client.post("/api/arm")
    assert r.status_code == 409 and "trigger input" in r.json()["detail"]
    assert client.get("/api/status").json()["state"] == "idle"


def test_two_triggers_at_once_are_serialized(tmp_path: Path) -> None:
    service, engine = make_service(tmp_path, shot_s=0.05)
    try:
        with TestClient(create_app(service=service)) as c:
            c.post("/api/arm")
            codes: list[int] = []
            threads = [
                threading.Thread(target=lambda: codes.append(c.post("/api/trigger").status_code)) for _ in range(2)
            ]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            assert codes == [200, 200] and engine.max_in_shot == 1
    finally:
        service.close()


def test_status_shows_running_during_a_shot(tmp_path: Path, wait_until: Callable[..., None]) -> None:
    service, engine = make_service(tmp_path, shot_s=0.3)
    try:
        with TestClient(create_app(service=service)) as c:
            t = threading.Thread(target=lambda: c.post("/api/shots"))
            t.start()
            wait_until(lambda: engine.in_shot > 0, what="the shot to start")
            s = c.get("/api/status").json()
            t.join()
            assert s["state"] == "running" and s["activity"] == "one shot"
            assert c.get("/api/status").json()["state"] == "idle"
    finally:
        service.close()


# -- calibration ------------------------------------------------------------------------------------------------


@pytest.fixture
def optics_lab(tmp_path: Path) -> Iterator[tuple[LabService, TestClient]]:
    """The stand-in engine's camera sees a wider PSF, displaced by 0.6 px, than the configuration says."""
    service, _ = make_service(tmp_path, optics={"psf_sigma_px": 1.6, "origin_px": (8.6, 8.0)})
    try:
        with TestClient(create_app(service=service)) as c:
            yield service, c
    finally:
        service.close()


def test_calibrate_threshold_returns_fit_without_applying(optics_lab: tuple[LabService, TestClient]) -> None:
    _, c = optics_lab
    before = c.get("/api/config").json()
    r = c.post("/api/calibrate/threshold", json={"images": 20})
    assert r.status_code == 200, r.text
    cal = r.json()
    assert cal["kind"] == "threshold" and cal["images"] == 20 and cal["applied"] is False
    assert cal["mean_empty"] < cal["threshold"] < cal["mean_atom"]
    assert 0.9 < cal["fidelity"] <= 1.0 and cal["fidelity"] >= cal["current_fidelity"] - 1e-9
    assert 0.4 < cal["fraction_filled"] < 0.8  # sim.loading_probability 0.6
    assert cal["apply_patch"] == {"imaging": {"threshold": round(cal["threshold"], 3)}}
    assert c.get("/api/config").json() == before  # nothing applied
    assert [x["id"] for x in c.get("/api/calibrate").json()] == [cal["id"]]
    r = c.post("/api/calibrate/apply", json={"id": cal["id"]})
    assert r.status_code == 200, r.text
    assert r.json()["applied"]["applied"] is True
    cfg = c.get("/api/config").json()
    assert cfg["imaging"]["threshold"] == round(cal["threshold"], 3)
    digest = r.json()["config_digest"]
    assert digest != before and c.get("/api/status").json()["config_digest"] == digest


def test_calibrate_psf_finds_the_true_optics(optics_lab: tuple[LabService, TestClient]) -> None:
    _, c = optics_lab
    before = c.get("/api/config").json()
    cal = c.post("/api/calibrate/psf", json={"images": 20}).json()
    assert cal["kind"] == "psf" and cal["current_sigma_px"] == 1.2
    assert abs(cal["sigma_px"] - 1.6) < 0.1
    assert abs(cal["origin_px"][0] - 8.6) < 0.15 and abs(cal["col_step_px"][0] - 16.0) < 0.01
    assert cal["row_step_px"] == [0.0, 16.0]  # a chain cannot show its row step: kept
    assert cal["lattice_rms_px"] < 0.2 and cal["traps_fitted"] > 50
    assert cal["fidelity"] >= cal["current_fidelity"]
    assert c.get("/api/config").json() == before
    applied = c.post("/api/calibrate/apply", json={"id": cal["id"]}).json()["applied"]
    cam = c.get("/api/config").json()["camera"]
    assert cam["psf_sigma_px"] == applied["apply_patch"]["camera"]["psf_sigma_px"]
    assert cam["origin_px"] == applied["apply_patch"]["camera"]["origin_px"]


def test_calibration_apply_refuses_a_stale_or_unknown_one(optics_lab: tuple[LabService, TestClient]) -> None:
    _, c = optics_lab
    cal = c.post("/api/calibrate/threshold", json={"images": 10}).json()
    c.patch("/api/config", json={"sim": {"loading_probability": 0.5}})
    before = c.get("/api/config").json()
    r = c.post("/api/calibrate/apply", json={"id": cal["id"]})
    assert r.status_code == 409 and "calibrate again" in r.json()["detail"]
    r = c.post("/api/calibrate/apply", json={"id": "threshold-999"})
    assert r.status_code == 404
    assert c.post("/api/calibrate/apply", json={}).status_code == 422
    assert c.get("/api/config").json() == before


@pytest.mark.parametrize("body", [{"images": 1}, {"images": 100000}, {"images": "many"}, {"frames": 10}])
def test_bad_calibration_request_is_422(optics_lab: tuple[LabService, TestClient], body: dict) -> None:
    _, c = optics_lab
    for path in ("/api/calibrate/threshold", "/api/calibrate/psf"):
        r = c.post(path, json=body)
        assert r.status_code == 422, (path, body, r.text)
        assert r.json()["detail"][0]["loc"][:2] == ["body", next(iter(body))]
    assert c.get("/api/calibrate").json() == []


def test_calibration_of_an_empty_array_is_409(optics_lab: tuple[LabService, TestClient]) -> None:
    _, c = optics_lab
    c.patch("/api/config", json={"sim": {"loading_probability": 0.0}})
    r = c.post("/api/calibrate/threshold", json={"images": 10})
    assert r.status_code == 409 and "single population" in r.json()["detail"]


def test_live_websocket_sends_frames_on_request(client: TestClient) -> None:
    with client.websocket_connect("/api/live") as ws:
        ws.send_text("not json")  # ignored
        ws.send_json({"images": True})
        time.sleep(0.05)  # let the server read the request before the shot's messages go out
        shot = client.post("/api/shots").json()
        cycle = ws.receive_json()
        header = ws.receive_json()
        pixels = np.frombuffer(ws.receive_bytes(), dtype="<u2").reshape(header["shape"])
    assert cycle["type"] == "cycle" and cycle["shot_id"] == shot["shot_id"]
    shape = list(frame_shape(example_config().camera))
    assert header == {"type": "image", "shot_id": shot["shot_id"], "cycle": 0, "shape": shape, "dtype": "<u2"}
    assert (pixels == 500).all()  # the stand-in's cycle-0 frame


def test_live_websocket_sends_no_frames_unasked(client: TestClient) -> None:
    with client.websocket_connect("/api/live") as ws:
        first = client.post("/api/shots").json()
        kinds = [ws.receive_json()["type"] for _ in first["cycles"]]
        second = client.post("/api/shots").json()
        after = ws.receive_json()
    assert kinds == ["cycle"] * len(first["cycles"])
    assert after["type"] == "cycle" and after["shot_id"] == second["shot_id"] and after["cycle"] == 0
