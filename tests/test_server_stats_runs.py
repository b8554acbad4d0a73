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

from drivers.sim.lab import LOSS_CAUSES
from engine.psf import frame_shape
from engine.records import CycleRecord, Outcome, ShotRecord
from server.app import create_app
from server.runstore import FrameKeeping, RunStore
from server.service import LabService
from server_fakes import example_config, fake_lab_service, png_pixels

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


def test_run_file_keeps_counts_moved_atoms_and_their_routes(tmp_path: Path) -> None:
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
                        moves=np.array([[0, 1], [5, 2]], dtype=np.int32), pickups=3,
                        # routes on the half-site grid: 0 -> 1 straight; 5 -> 2 through the channel below row 0
                        paths=np.array([[0, 0, 0], [0, 0, 2], [5, 0, 10], [5, 1, 10], [5, 1, 4], [5, 0, 4]],
                                       dtype=np.int32)),
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
    assert shot["cycles"][0]["paths"] == [
        {"source": 0, "points": [[0, 0], [0, 1]]}, {"source": 5, "points": [[0, 5], [0.5, 5], [0.5, 2], [0, 2]]},
    ]  # in sites: 0.5 is the channel between rows 0 and 1
    assert shot["cycles"][1]["paths"] == []
    assert [c["pickups"] for c in shot["cycles"]] == [3, 0]
    np.testing.assert_array_equal(shot["cycles"][1]["counts"], counts + 1)
    reopened = RunStore(tmp_path)
    try:
        assert reopened.read_shot(name, 0)["cycles"][0]["moves"] == [[0, 1], [5, 2]]  # a closed file, from disk
    finally:
        reopened.close()


def _shot(config: object, shot_id: int, cycles: list[CycleRecord]) -> ShotRecord:
    occ = cycles[0].occupancy
    return ShotRecord(shot_id=shot_id, config_digest=config.digest(), algorithm="red-rec",  # type: ignore[attr-defined]
                      target=occ, outcome=Outcome.SUCCESS, cycles=cycles)


def test_run_file_keeps_the_lab_losses_per_cycle_by_cause(tmp_path: Path) -> None:
    """A historic shot keeps what the lab reported per cycle (atoms lost by cause): in the file as
    ``lost_by_cause[shot, cycle, cause]`` (-1: not reported), and read back as the cycle's ``truth``."""
    config = example_config()
    occ = np.zeros((config.array.ny, config.array.nx), dtype=bool)
    store = RunStore(tmp_path)
    store.note_config(config)
    reported = dict.fromkeys(LOSS_CAUSES, 0) | {"transfer": 2, "vacuum": 1}
    store.put(_shot(config, 3, [
        CycleRecord(index=0, occupancy=occ, atoms=0, defects=0, lab_report={"lost_by_cause": reported}),
        CycleRecord(index=1, occupancy=occ, atoms=0, defects=0),  # hardware: nothing reported
    ]))
    store.flush()
    name = store.runs()[0]["name"]
    store.close()
    with h5py.File(tmp_path / name, "r") as f:
        causes = __import__("json").loads(f.attrs["loss_causes"])
        assert causes == list(LOSS_CAUSES)
        assert f["lost_by_cause"][0, 0, causes.index("transfer")] == 2
        assert (f["lost_by_cause"][0, 1] == -1).all()
        assert "frames" not in f  # frames are kept only when asked
    reopened = RunStore(tmp_path)
    try:
        shot = reopened.read_shot(name, 0)
    finally:
        reopened.close()
    assert shot["cycles"][0]["truth"] == {"lost_by_cause": reported}
    assert shot["cycles"][1]["truth"] == {}
    assert [c["frame"] for c in shot["cycles"]] == [False, False]


def test_frames_of_every_nth_shot_are_kept_and_served(tmp_path: Path) -> None:
    """With every 2nd shot's frames kept, run-file shots 0 and 2 keep every cycle's frame (the engine kept
    them) and shot 1 none; each is served as a lossless PNG, a missing one is a 404 that says why."""
    config = example_config()
    frames = FrameKeeping(every_nth_shot=2)
    with fake_lab_service(tmp_path / "runs", engine_kw={"keep_images": True}, frames=frames) as service:
        records = [service.shot() for _ in range(3)]
        service.run_store.flush()  # type: ignore[union-attr]  # built with one
        with TestClient(create_app(service=service, token=TOKEN)) as client:
            name = client.get("/api/runs").json()[0]["name"]
            for index, record in enumerate(records):
                shot = client.get(f"/api/runs/{name}/shots/{index}").json()
                kept = index % 2 == 0
                assert [c["frame"] for c in shot["cycles"]] == [kept] * len(record.cycles)
                for cycle in range(len(record.cycles)):
                    r = client.get(f"/api/runs/{name}/shots/{index}/frames/{cycle}")
                    if kept:
                        assert r.status_code == 200 and r.headers["content-type"] == "image/png"
                        pixels = png_pixels(r.content)
                        assert pixels.shape == frame_shape(config.camera)
                        assert (pixels == 500 + 100 * cycle).all()  # the fake's frame of that cycle, exactly
                    else:
                        assert r.status_code == 404 and "frames of one shot in 2" in r.json()["detail"]
            beyond = len(records[0].cycles)
            assert client.get(f"/api/runs/{name}/shots/0/frames/{beyond}").status_code == 404
            assert client.get(f"/api/runs/{name}/shots/3/frames/0").status_code == 404
            assert client.get("/api/runs/20000101-000000-0.h5/shots/0/frames/0").status_code == 404
        with h5py.File(tmp_path / "runs" / name, "r", swmr=True) as f:
            assert f["frames"].compression == "gzip" and f["frames"].chunks == (1, *frame_shape(config.camera))
            assert f["frame_index"][:].tolist() == (
                [[0, c] for c in range(len(records[0].cycles))] + [[2, c] for c in range(len(records[2].cycles))]
            )


def test_frames_are_bounded_per_file_and_default_to_the_final_one(tmp_path: Path) -> None:
    """Without per-cycle images only the final frame (the last cycle's) is kept; a file keeps at most its
    ``max_mib`` of raw frames, later shots keep everything else."""
    config = example_config()
    shape = frame_shape(config.camera)
    one_frame_mib = 2 * shape[0] * shape[1] / (1 << 20)
    keeping = FrameKeeping(every_nth_shot=1, max_mib=2.5 * one_frame_mib)
    assert keeping.max_frames(shape) == 2
    occ = np.zeros((config.array.ny, config.array.nx), dtype=bool)
    store = RunStore(tmp_path, frames=keeping)
    store.note_config(config)
    for shot_id in range(3):
        cycles = [CycleRecord(index=i, occupancy=occ, atoms=0, defects=0) for i in range(2)]
        store.put(_shot(config, shot_id, cycles), np.full(shape, 7 + shot_id, dtype=np.uint16))
    store.flush()
    name = store.runs()[0]["name"]
    try:
        assert [c["frame"] for c in store.read_shot(name, 0)["cycles"]] == [False, True]
        assert (store.read_frame(name, 1, 1) == 8).all()
        assert store.read_shot(name, 2)["cycles"][1]["frame"] is False  # over the limit
        with pytest.raises(LookupError, match="no camera frame kept for shot 2 cycle 1"):
            store.read_frame(name, 2, 1)
    finally:
        store.close()


@pytest.mark.parametrize("bad", [{"every_nth_shot": -1}, {"max_mib": 0.0}])
def test_frame_keeping_refuses_nonsense(bad: dict[str, float]) -> None:
    with pytest.raises(ValueError, match="must be"):
        FrameKeeping(**bad)  # type: ignore[arg-type]


def test_a_link_named_like_a_run_file_is_not_followed(lab: LabService, client: TestClient, tmp_path: Path) -> None:
    """A symbolic link in the runs directory that looks like a run file (pointing outside, absolutely or
    relatively) is not a run file: every run route answers 404 and nothing outside the directory is read."""
    outside = tmp_path / "secret.h5"
    outside.write_bytes(b"not for clients")
    runs = lab.run_store.directory  # type: ignore[union-attr]  # built with one
    (runs / "20260101-120000-0.h5").symlink_to(outside)
    (runs / "20260101-120000-1.h5").symlink_to(Path("..") / "secret.h5")
    for name in ("20260101-120000-0.h5", "20260101-120000-1.h5"):
        for route in ("", "/shots/0", "/shots/0/frames/0"):
            r = client.get(f"/api/runs/{name}{route}")
            assert r.status_code == 404 and b"not for clients" not in r.content
    assert client.get("/api/runs").json() == []
