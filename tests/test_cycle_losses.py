"""Per-cycle diagnostics of a shot: the atoms the simulated world lost in each cycle, by cause, and the
pick-ups each cycle's plan made (``CycleRecord.lab_report``, ``CycleRecord.pickups``)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivers.sim.lab import LOSS_CAUSES, SimLab, build_sim_lab
from engine.config import load_config
from engine.engine import Engine, _pickups, _slot_table, _solver
from engine.solvers.validate import replay
from engine.targets import build_target
from server.models import shot_out
from sim_signals import grid_config


def _lossy_engine() -> tuple[Engine, SimLab]:
    """An 8x6 grid losing atoms to every cause the world models: transfers, steps, vacuum and imaging."""
    config = grid_config(
        8,
        6,
        target={"kind": "rectangle", "row0": 1, "col0": 1, "rows": 3, "cols": 5},
        solver={"algorithm": "aod-parallel"},
        sim={
            "seed": 3,
            "survival_transfer": 0.8,
            "survival_step": 0.9,
            "vacuum_lifetime_s": 0.5,
            "imaging": {"loss_rate_hz": 5.0},
            # replay time: the clock moves only by the modelled stages, so reading the world after the shot (the
            # test's own bound) is the same instant as the lab's end-of-shot report, however slow the machine
            "time": "replay",
        },
    )
    devices, lab = build_sim_lab(config)
    return Engine(config, devices, lab=lab), lab


def test_losses_by_cause_add_up_to_the_atoms_gone_between_images(monkeypatch: pytest.MonkeyPatch) -> None:
    engine, lab = _lossy_engine()
    world = lab.world
    atoms_at_exposure: list[int] = []
    expose = world.expose

    def counting_expose(t0_s: float, exposure_s: float) -> np.ndarray:
        atoms_at_exposure.append(world.n_atoms)  # the lab has applied the playback up to now
        return expose(t0_s, exposure_s)

    monkeypatch.setattr(world, "expose", counting_expose)  # a test's window on the world
    totals = dict.fromkeys(LOSS_CAUSES, 0)
    n_cycles = 0
    for _ in range(12):
        atoms_at_exposure.clear()
        record = engine.run_shot()
        lab.ground_truth()  # playback to the end of the shot
        bounds = [*atoms_at_exposure, world.n_atoms]
        assert len(record.cycles) == len(atoms_at_exposure)
        for cycle, before, after in zip(record.cycles, bounds[:-1], bounds[1:], strict=True):
            lost = cycle.lab_report["lost_by_cause"]
            assert set(lost) == set(LOSS_CAUSES)
            assert all(n >= 0 for n in lost.values())
            assert sum(lost.values()) == before - after  # no atom appears mid-shot; captures are not losses
            for cause, n in lost.items():
                totals[cause] += n
            n_cycles += 1
    assert n_cycles > 12  # some shots needed more than one cycle
    for cause in ("transfer", "step", "vacuum", "imaging"):
        assert totals[cause] > 0, totals


def test_pickups_per_cycle_and_the_rest_schema() -> None:
    engine, _ = _lossy_engine()
    records = [engine.run_shot() for _ in range(6)]
    planned = [c for r in records for c in r.cycles if c.n_slots > 0]
    assert planned
    for r in records:
        for c in r.cycles:
            if c.n_slots == 0:
                assert c.pickups == 0
            else:  # every moved atom was taken into a tweezer at least once, a tweezer holding nothing moves none
                assert c.pickups >= c.atoms_moved > 0
    shot = shot_out(records[0]).model_dump()
    cycle = shot["cycles"][0]
    assert cycle["pickups"] == records[0].cycles[0].pickups
    assert cycle["truth"]["lost_by_cause"] == records[0].cycles[0].lab_report["lost_by_cause"]


def test_pickups_match_the_validators_replay() -> None:
    """The engine's count (the move model's kernel alone) is the validator's per-atom pick-ups summed."""
    config = load_config(Path(__file__).resolve().parents[1] / "examples/grid-16x32.yaml")
    solver = _solver(config)
    target = build_target(config.target, nx=config.array.nx, ny=config.array.ny)
    rng = np.random.default_rng(7)
    for _ in range(5):
        occupancy = rng.random(target.shape) < 0.6
        solver.solve_moves(occupancy, target)
        plan = solver.batch()
        expected = int(replay(plan.operations, occupancy, trap_source="slm").atom_pickups.sum())
        assert expected > 0
        assert _pickups(_slot_table(plan.operations), occupancy, chain=False) == expected
