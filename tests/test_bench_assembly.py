"""``llrs bench assembly``: closed-loop figures, per-shot seeding that survives chunking, and a real dask cluster."""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from bench.assembly import (
    LOSS_CAUSES,
    Cell,
    CellResult,
    cell_config,
    format_table,
    run_cells,
    run_chunk,
    shot_seeds,
    summarize,
    wilson_interval,
)
from conftest import wait_until

LOSSLESS = Cell(problem="16x32", planner=None, loss="lossless", lifetime_s=6000.0)


def test_wilson_interval_matches_hand_values() -> None:
    lo, hi = wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(0.2775, abs=1e-4)
    lo, hi = wilson_interval(10, 10)
    assert hi == 1.0 and lo == pytest.approx(0.7225, abs=1e-4)
    lo, hi = wilson_interval(50, 100)
    assert (lo, hi) == (pytest.approx(0.4038, abs=1e-4), pytest.approx(0.5962, abs=1e-4))


def test_shot_seeds_do_not_depend_on_how_many_shots_are_asked_for() -> None:
    assert shot_seeds(7, 3) == shot_seeds(7, 10)[:3]
    assert len(set(shot_seeds(7, 100))) == 100
    assert shot_seeds(7, 3) != shot_seeds(8, 3)


def test_cell_config_applies_the_cell_and_refuses_unknown_names() -> None:
    cfg = cell_config(Cell("32x64", "aod-parallel", "0.985/0.985", 60.0), loading=0.5, max_cycles=3)
    assert cfg.solver.algorithm == "aod-parallel"
    assert (cfg.sim.survival_transfer, cfg.sim.survival_step, cfg.sim.vacuum_lifetime_s) == (0.985, 0.985, 60.0)
    assert cfg.sim.loading_probability == 0.5 and cfg.loop.max_cycles == 3 and not cfg.sim.lossless
    assert cell_config(LOSSLESS).sim.lossless and cell_config(LOSSLESS).sim.time == "replay"
    assert cell_config(LOSSLESS).sim.imaging.loss_rate_hz == 0.0
    lossy_image = cell_config(Cell("32x64", None, "lossless", 60.0, image_survival=0.99))
    assert math.exp(-lossy_image.sim.imaging.loss_rate_hz * lossy_image.camera.exposure_s) == pytest.approx(0.99)
    with pytest.raises(ValueError, match="unknown problem"):
        cell_config(Cell("8x8", None, "lossless", 1.0))
    with pytest.raises(ValueError, match="unknown loss model"):
        cell_config(Cell("16x32", None, "0.9/0.9", 1.0))


def test_summarize_counts_every_shot_by_hand() -> None:
    def shot(filled: bool, cycles: int, t: float | None, lost_step: int) -> dict:
        lost = dict.fromkeys(LOSS_CAUSES, 0)
        lost["step"] = lost_step
        return {
            "filled": filled, "engine_success": True, "outcome": "success", "rearrangements": cycles,
            "time_to_array_s": t, "t_last_s": 0.05, "vacuum_bound": 0.5, "lost": lost, "underruns": 0,
            "fault": None,
        }

    row = summarize(CellResult(LOSSLESS, [shot(True, 1, 0.010, 2), shot(True, 3, 0.030, 0), shot(False, 2, None, 4)]))
    assert row["shots"] == 3 and row["success"] == pytest.approx(2 / 3)
    assert row["engine_believed"] == 1.0  # the engine was wrong once: world truth decides
    assert row["cycles_mean"] == 2.0
    assert row["time_to_array_ms_median"] == pytest.approx(20.0)
    assert row["lost_per_cycle"]["step"] == 1.0  # 6 atoms over 6 rearrangement cycles
    assert "| 16x32 | example | lossless |" in format_table([row])


@pytest.fixture(scope="module")
def lossless_shots() -> list[dict]:
    return run_chunk(cell_config(LOSSLESS).model_dump_json(), shot_seeds(3, 4))


def test_lossless_shots_fill_the_target_and_time_it(lossless_shots: list[dict]) -> None:
    for s in lossless_shots:
        assert s["filled"] and s["engine_success"]
        assert 1 <= s["rearrangements"] <= 2
        assert sum(s["lost"].values()) == 0
        # first exposure to the final image: at least one exposure per image plus the rearrangement between
        cfg = cell_config(LOSSLESS)
        assert s["time_to_array_s"] > (s["rearrangements"] + 1) * cfg.camera.exposure_s
        assert s["vacuum_bound"] == 1.0  # a lossless world loses no atom to the vacuum either


def test_a_shot_depends_on_its_seed_not_on_its_chunk(lossless_shots: list[dict]) -> None:
    cfg = cell_config(LOSSLESS).model_dump_json()
    seeds = shot_seeds(3, 4)
    split = run_chunk(cfg, seeds[2:]) + run_chunk(cfg, seeds[:2])
    split = split[2:] + split[:2]
    timing = ("time_to_array_s", "t_last_s", "vacuum_bound")
    for a, b in zip(split, lossless_shots, strict=True):
        assert {k: v for k, v in a.items() if k not in timing} == {k: v for k, v in b.items() if k not in timing}
        # a shot starts wherever the card's idle loop is when the previous one ended: microseconds apart
        assert a["time_to_array_s"] == pytest.approx(b["time_to_array_s"], abs=50e-6)


def test_same_table_on_a_local_cluster_and_on_a_scheduler_started_here(tmp_path: Path) -> None:
    dask = Path(sys.executable).parent / "dask"
    scheduler_file = tmp_path / "scheduler.json"
    common = ["--scheduler-file", str(scheduler_file), "--no-dashboard"]
    repo = str(Path(__file__).resolve().parents[1])  # the processes unpickle tasks that name bench.assembly
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(filter(None, [repo, os.environ.get("PYTHONPATH")]))}
    procs = [subprocess.Popen([dask, "scheduler", "--host", "127.0.0.1", "--port", "0", *common], env=env)]

    def scheduler_address() -> str | None:
        """The address in the scheduler's file; ``None`` until the file exists and is whole (the scheduler
        creates it before it writes it, so a loaded machine can show an empty file)."""
        try:
            return json.loads(scheduler_file.read_text())["address"]
        except (FileNotFoundError, json.JSONDecodeError, KeyError):
            return None

    try:
        wait_until(scheduler_address, timeout_s=60, what=f"{scheduler_file} to hold the scheduler's address")
        procs.append(
            subprocess.Popen(
                [dask, "worker", "--nthreads", "1", "--nworkers", "1", "--host", "127.0.0.1", *common], env=env
            )
        )
        address = scheduler_address()
        cells = [LOSSLESS, Cell("16x32", "no-such-planner", "lossless", 6000.0)]
        remote = [summarize(r) for r in run_cells(cells, shots=4, seed=5, chunk=2, scheduler=address)]
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in procs:
            p.wait(timeout=30)
    local = [summarize(r) for r in run_cells(cells, shots=4, seed=5, chunk=2, workers=1)]
    assert local[0] == remote[0]  # replay time: the same seeds and chunks give the same row, timing included
    assert local[0]["success"] == 1.0
    assert "no-such-planner" in local[1]["error"] and "no-such-planner" in remote[1]["error"]
