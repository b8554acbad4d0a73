"""Faults through the whole server on the real simulated lab: each is injected over the API, the shot ends in
a defined state and says why, the server stays up and reports it, earlier shots stay recorded, and the next
shot works once the fault is cleared."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import h5py
import pytest
from fastapi.testclient import TestClient

from conftest import INJECTED_FAULTS
from drivers.sim.lab import build_sim_lab
from engine.engine import Engine, EngineThread
from server.app import create_app
from server.runstore import RunStore
from server.service import LabService
from sim_signals import chain_config

NO_FAULTS = {"camera": "none", "awg_upload": "none", "upload_delay_s": 0.0, "solver": "none", "disk_full": False}


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[TestClient, Path, LabService]]:
    # a 24-trap chain: every config change rebuilds the waveform table, so a small array keeps this file fast
    config = chain_config(24, sim={"lossless": True, "seed": 3}, awg={"waveforms_per_segment": 2})

    def build() -> Engine:
        devices, lab = build_sim_lab(config)
        return Engine(config, devices, lab=lab)

    runs = tmp_path_factory.mktemp("runs")
    service = LabService(
        engine_thread=EngineThread(build), store=RunStore(runs), pause_s=0.0, shot_dir=tmp_path_factory.mktemp("shots")
    )
    service.start()
    with TestClient(create_app(service=service)) as client:
        yield client, runs, service
    service.close()


def set_faults(client: TestClient, **faults: object) -> None:
    r = client.patch("/api/config", json={"sim": {"faults": {**NO_FAULTS, **faults}}})
    assert r.status_code == 200, r.text


def shots_on_disk(runs: Path) -> int:
    total = 0
    for path in runs.glob("*.h5"):
        with h5py.File(path, "r", swmr=True) as f:
            total += int(f["shot_id"].shape[0])
    return total


def good_shot(client: TestClient) -> dict:
    for _ in range(5):
        shot = client.post("/api/shots").json()
        assert shot["outcome"] in ("success", "unsolvable"), shot
        if shot["outcome"] == "success":
            return shot
    raise AssertionError("no solvable shot in 5 tries")


@pytest.mark.parametrize(
    ("faults", "reason"),
    INJECTED_FAULTS,
)
def test_fault_is_reported_and_clears(api, faults: dict, reason: str) -> None:
    client, runs, service = api
    set_faults(client)
    good_shot(client)
    service._store.flush()  # noqa: SLF001
    recorded = shots_on_disk(runs)
    set_faults(client, **faults)
    shot = client.post("/api/shots").json()
    assert shot["outcome"] == "fault" and reason in shot["fault"]
    status = client.get("/api/status").json()
    assert status["state"] == "fault" and reason in status["reason"]
    set_faults(client)
    good_shot(client)
    assert client.get("/api/status").json()["state"] != "fault"
    service._store.flush()  # noqa: SLF001
    assert shots_on_disk(runs) >= recorded + 2  # the faulted shot is on record too, and nothing earlier was lost


def test_late_uploads_show_as_underruns_not_losses(api) -> None:
    client, _, _ = api
    set_faults(client, upload_delay_s=200e-6)
    underruns = 0
    for _ in range(4):
        shot = client.post("/api/shots").json()
        assert shot["outcome"] in ("success", "unsolvable"), shot
        if shot["outcome"] == "success":
            assert shot["target_filled"] is True
        underruns += sum(c["underruns"] for c in client.get(f"/api/shots/{shot['shot_id']}").json()["cycles"])
    assert underruns > 0
    set_faults(client)


def test_full_disk_keeps_shots_running_and_says_so(api) -> None:
    client, runs, service = api
    set_faults(client)
    good_shot(client)
    service._store.flush()  # noqa: SLF001
    before = shots_on_disk(runs)
    set_faults(client, disk_full=True)
    shot = client.post("/api/shots").json()
    assert shot["outcome"] in ("success", "unsolvable")  # the experiment goes on
    service._store.flush()  # noqa: SLF001
    status = client.get("/api/status").json()
    assert status["unrecorded_shots"] >= 1 and "No space left" in status["recording_error"]
    assert shots_on_disk(runs) == before  # nothing half-written, earlier shots intact
    set_faults(client)
    good_shot(client)
    service._store.flush()  # noqa: SLF001
    assert shots_on_disk(runs) >= before + 1


def test_labscript_shot_file_over_rest(api) -> None:
    """The sequencer hands the server a shot file (in its --shot-dir); the shot's results land in that file, once."""
    client, _, service = api
    set_faults(client)
    shot_file = service.shot_dir / "0001_shot.h5"
    with h5py.File(shot_file, "w") as f:
        g = f.create_group("globals")
        g.attrs["llrs_max_cycles"] = 3
        g.attrs["llrs_loading_probability"] = 0.8
    r = client.post("/api/labscript", json={"path": str(shot_file)})
    assert r.status_code == 200, r.text
    shot = r.json()
    with h5py.File(shot_file, "r") as f:
        results = f["results/llrs"]
        assert results.attrs["shot_id"] == shot["shot_id"]
        outcome = results.attrs["outcome"]
        assert (outcome.decode() if isinstance(outcome, bytes) else outcome) == shot["outcome"]
    again = client.post("/api/labscript", json={"path": str(shot_file)})
    assert again.status_code == 409 and "already holds" in again.json()["detail"]
    missing = client.post("/api/labscript", json={"path": str(service.shot_dir / "nope.h5")})
    assert missing.status_code == 404 and "no such shot file" in missing.json()["detail"]
    assert client.get("/api/config").json()["loop"]["max_cycles"] != 3  # the shot's globals were for that shot only
