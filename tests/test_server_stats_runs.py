"""The statistics and run-file routes: what they return, the token rule, strict run names, and a run file's
per-cycle counts and moved atoms read back as they were recorded."""

from __future__ import annotations

import io
from collections.abc import Iterator
from pathlib import Path

import h5py
import numpy as np
import pytest
from fastapi.testclient import TestClient

from engine.records import CycleRecord, Outcome, ShotRecord
from server.app import create_app
from server.runstore import RunStore
from server.service import LabService
from server_fakes import example_config, fake_lab_service

TOKEN = "stats-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


@pytest.fixture
def lab(tmp_path: Path) -> Iterator[LabService]:
    with fake_lab_service(tmp_path / "runs") as service:
        yield service


@pytest.fixture
def client(lab: LabService) -> Iterator[TestClient]:
    with TestClient(create_app(service=lab, token=TOKEN)) as c:
        yield c


def test_stats_follow_the_shots_and_reset_needs_the_token(lab: LabService, client: TestClient) -> None:
    records = [lab.shot() for _ in range(4)]
    stats = client.get("/api/stats").json()
    ny, nx = lab.config.array.ny, lab.config.array.nx
    assert stats["shape"] == [ny, nx] and stats["shots"] == 4
    loading = np.array(stats["maps"]["loading_probability"], dtype=float)
    expected = np.mean([r.cycles[0].occupancy for r in records], axis=0)
    np.testing.assert_allclose(loading, expected)
    assert stats["assembly"]["shots"] == 4
    assert sum(stats["assembly"]["cycles_histogram"]) == 4
    planned = [c for r in records for c in r.cycles if c.n_slots > 0]
    assert planned  # (the fake lab's seeded loading: every shot rearranges)
    # the fake lab lets go of the atoms the target has no room for: its one loss, per cycle
    lost = [c.lab_report["lost_by_cause"]["released"] for c in planned]
    assert stats["assembly"]["lost_by_cause_per_cycle_mean"] == {"released": pytest.approx(np.mean(lost))}
    assert stats["assembly"]["pickups_per_cycle_mean"] == pytest.approx(np.mean([c.pickups for c in planned]))
    shot = client.get(f"/api/shots/{records[-1].shot_id}").json()
    assert all("pickups" in c and "truth" in c for c in shot["cycles"])
    assert client.post("/api/stats/reset").status_code == 401
    assert client.post("/api/stats/reset", headers=AUTH).json()["config_digest"] == lab.config.digest()
    assert client.get("/api/stats").json()["shots"] == 0


def test_run_files_are_listed_downloaded_and_read_back(lab: LabService, client: TestClient) -> None:
    records = [lab.shot() for _ in range(3)]
    lab.run_store.flush()  # type: ignore[union-attr]  # the run store exists: the service was built with one
    runs = client.get("/api/runs").json()
    assert len(runs) == 1 and runs[0]["shots"] == 3 and runs[0]["config_digest"] == lab.config.digest()
    name = runs[0]["name"]
    body = client.get(f"/api/runs/{name}")
    assert body.status_code == 200 and body.headers["content-type"] == "application/x-hdf5"
    with h5py.File(io.BytesIO(body.content), "r") as f:
        assert list(f["shot_id"][:]) == [r.shot_id for r in records]
    shot = client.get(f"/api/runs/{name}/shots/1").json()
    assert shot["shot_id"] == records[1].shot_id and shot["outcome"] == records[1].outcome.value
    assert [c["occupancy"] for c in shot["cycles"]] == [c["occupancy"] for c in records[1].to_dict()["cycles"]]
    assert client.get(f"/api/runs/{name}/shots/3").status_code == 404


@pytest.mark.parametrize("name", ["..%2F..%2Fetc%2Fpasswd", "x.h5", "20260101-120000-0.h5%00", "%2E%2E"])
def test_run_names_are_checked_strictly(client: TestClient, name: str) -> None:
    assert client.get(f"/api/runs/{name}").status_code in (404, 422)


def test_a_valid_name_that_is_not_there_is_404(client: TestClient) -> None:
    assert client.get("/api/runs/20000101-000000-0.h5").status_code == 404


def test_run_file_keeps_counts_and_moved_atoms(tmp_path: Path) -> None:
    config = example_config()
    ny, nx = config.array.ny, config.array.nx
    store = RunStore(tmp_path)
    store.note_config(config)
    occ = np.zeros((ny, nx), dtype=bool)
    occ[0, :3] = True
    counts = np.arange(ny * nx, dtype=np.float32)
    record = ShotRecord(
        shot_id=7, config_digest=config.digest(), algorithm=config.solver.algorithm, target=occ,
        outcome=Outcome.SUCCESS,
        cycles=[
            CycleRecord(index=0, occupancy=occ, atoms=3, defects=0, n_slots=4, counts=counts,
                        moves=np.array([[0, 1], [5, 2]], dtype=np.int32), pickups=3),
            CycleRecord(index=1, occupancy=occ, atoms=3, defects=0, counts=counts + 1),
        ],
    )
    store.put(record)
    store.flush()
    try:
        name = store.runs()[0]["name"]
        shot = store.read_shot(name, 0)  # the file being written, through the writer's handle
    finally:
        store.close()
    assert shot["cycles"][0]["moves"] == [[0, 1], [5, 2]] and shot["cycles"][0]["atoms_moved"] == 2
    assert shot["cycles"][1]["moves"] == []
    assert [c["pickups"] for c in shot["cycles"]] == [3, 0]
    np.testing.assert_array_equal(shot["cycles"][1]["counts"], counts + 1)
    reopened = RunStore(tmp_path)
    try:
        assert reopened.read_shot(name, 0)["cycles"][0]["moves"] == [[0, 1], [5, 2]]  # a closed file, from disk
    finally:
        reopened.close()
