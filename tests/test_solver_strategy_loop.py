"""The per-cycle strategy in the closed loop (simulated lab: real waveforms, decoded samples, the world's
truth): every cycle's record names the planner that made its plan, the switch follows the number of holes the
cycle saw, and lossless shots fill every solvable target within 2 rearrangements with no atom captured or
lost that a plan did not mean to move."""

from __future__ import annotations

from pathlib import Path

import pytest

from drivers.sim.lab import build_sim_lab
from engine.config import SystemConfig, load_config
from engine.engine import Engine
from engine.records import Outcome

GRID_16 = Path(__file__).resolve().parents[1] / "examples/grid-16x32.yaml"
REPAIR_AT = 24


def _config(*, lossless: bool, seed: int, repair_at: int = REPAIR_AT) -> SystemConfig:
    data = load_config(GRID_16).model_dump(mode="json")
    data["solver"].update(objective="survival", strategy={"repair": "repair", "repair_at_defects": repair_at})
    data["sim"].update(lossless=lossless, seed=seed, survival_transfer=0.985, survival_step=0.985)
    data["sim"]["vacuum_lifetime_s"] = 6000.0
    return SystemConfig.model_validate(data)


@pytest.fixture(scope="module")
def engine() -> Engine:
    config = _config(lossless=True, seed=3)
    devices, lab = build_sim_lab(config)
    return Engine(config, devices, lab=lab)


def test_lossless_strategy_fills_every_solvable_shot_and_disturbs_nothing_unplanned(engine: Engine) -> None:
    for repair_at in (REPAIR_AT, 10_000):  # bulk then repair; repair from the first cycle
        engine.apply(_config(lossless=True, seed=7, repair_at=repair_at))
        counters = engine.lab.world.counters
        captured, lost = counters.captured, counters.lost
        for _ in range(3):
            r = engine.run_shot()
            assert r.fault is None, r.fault
            if r.outcome == Outcome.UNSOLVABLE:
                continue
            assert r.outcome == Outcome.SUCCESS and r.lab_report["target_filled"]
            assert sum(1 for c in r.cycles if c.n_slots > 0) <= 2
            first = r.cycles[0]
            assert first.planner == ("repair" if first.defects <= repair_at else "red-rec")
        assert counters.captured == captured and counters.lost == lost, counters.as_dict()


def test_each_cycle_records_the_planner_the_strategy_chose(engine: Engine) -> None:
    engine.apply(_config(lossless=False, seed=11))
    seen = set()
    for _ in range(4):
        r = engine.run_shot()
        assert r.fault is None, r.fault
        for c in r.cycles:
            d = c.to_dict()
            if c.n_slots == 0:  # the last image (filled, unsolvable or out of cycles) plans nothing
                assert d["planner"] == ""
                continue
            expect = "repair" if c.defects <= REPAIR_AT else "red-rec"
            assert d["planner"] == expect, (c.index, c.defects)
            seen.add(expect)
    assert seen == {"red-rec", "repair"}  # the loading leaves many holes, the losses of a cycle few


def test_bench_planner_specs_set_the_strategy_and_refuse_bad_ones() -> None:
    from bench.assembly import Cell, cell_config

    cell = Cell(problem="16x32", planner="red-rec>repair@40:survival", loss="0.985/0.985", lifetime_s=6000.0,
                image_survival=1.0)  # fmt: skip
    solver = cell_config(cell).solver
    assert solver.algorithm == "red-rec" and solver.objective == "survival"
    assert solver.strategy is not None and (solver.strategy.repair, solver.strategy.repair_at_defects) == ("repair", 40)
    with pytest.raises(ValueError, match="BULK>REPAIR@DEFECTS"):
        cell_config(Cell(problem="16x32", planner="red-rec>repair", loss="0.985/0.985", lifetime_s=6000.0,
                         image_survival=1.0))  # fmt: skip


def test_the_run_file_keeps_each_cycles_planner(engine: Engine, tmp_path: Path) -> None:
    import h5py

    from server.runstore import _RunFile

    config = _config(lossless=False, seed=11)
    engine.apply(config)
    record = engine.run_shot()
    run = _RunFile(tmp_path / "run.h5", config)
    run.append(record)
    run.close()
    with h5py.File(tmp_path / "run.h5", "r") as f:
        stored = [p.decode() for p in f["planner"][0][: len(record.cycles)]]
    assert stored == [c.planner for c in record.cycles]
    assert any(stored)
