"""``llrs bench solvers``: the figures it reports on small seeded runs, zero invalid plans, the loss Monte
Carlo's per-atom replay, the JSON and table output, and clear errors for unknown names."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.solvers import PROBLEMS, _loss_trial, bench_solvers, format_row, plot_scaling, replay_counts
from engine.solvers import Solver, solve
from engine.solvers.validate import replay
from engine.targets import centre_target
from server.cli import main


@pytest.fixture(scope="module")
def small() -> dict:
    return bench_solvers(instances=4, problems=["1x64", "16x32"], repeats=1, mc_trials=3)


def test_every_planner_runs_and_validates(small) -> None:
    rows = {(r["problem"], r["planner"]): r for r in small["results"]}
    assert set(rows) == {
        ("1x64", "exact-1d"),
        *(("16x32", p) for p in ("red-rec", "red-rec-wide", "aod-parallel", "aod-parallel/transfers", "assignment")),
    }
    for r in rows.values():
        assert r["invalid"] == 0 and r["lossless_success"] == 1.0
        assert r["plan_us"]["median"] > 0 and r["slots"]["median"] > 0 and r["steps_median"] > 0
        # reconfiguration time = planning + 10 us per slot, instance by instance
        assert r["reconfiguration_us"]["median"] >= 0.9 * (10 * r["slots"]["median"] + r["plan_us"]["median"])
        assert set(r["loss_mc"]) == {"0.985/0.985", "0.995/0.999"}
        for mc in r["loss_mc"].values():
            assert 0.0 <= mc["success"] <= 1.0 and mc["trials"] == 3
    # the transfers objective picks atoms up fewer times than the slots objective
    assert rows[("16x32", "aod-parallel/transfers")]["max_pickups"]["max"] <= rows[("16x32", "aod-parallel")]["max_pickups"]["max"]
    assert "16x32" in format_row(rows[("16x32", "aod-parallel")])


def _one_atom_replays(plan, occ: np.ndarray, trap_source: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per atom, through the validator's public ``replay`` of the plan with only that atom loaded (a tweezer
    moves whether or not it holds anything, so each atom goes where it goes in the full replay): its final
    trap, pick-ups and one-site steps."""
    where, pickups, steps = [], [], []
    for trap in np.flatnonzero(occ.ravel()):
        alone = np.zeros(occ.size, dtype=bool)
        alone[trap] = True
        report = replay(plan.operations, alone.reshape(occ.shape), trap_source=trap_source)
        where.append(int(np.flatnonzero(report.occupancy.ravel())[0]))
        pickups.append(report.max_pickups_per_atom)
        steps.append(report.steps)
    return np.asarray(where), np.asarray(pickups), np.asarray(steps)


def test_replay_counts_follow_each_atom() -> None:
    target = centre_target(nx=8, ny=16, count=64)
    occ = np.random.default_rng(3).random((16, 8)) < 0.6
    plan = solve(occ, target, algorithm="aod-parallel")
    where, transfers, steps = replay_counts(plan, occ, "slm")
    assert where.size == occ.sum() and np.unique(where).size == where.size
    final = np.zeros(occ.size, dtype=bool)
    final[where] = True
    assert final.reshape(occ.shape)[target].all()
    assert steps.sum() == plan.n_steps and np.all(transfers % 2 == 0) and np.all((steps > 0) <= (transfers > 0))
    # the compiled counting replay agrees with the validator's replay atom by atom
    for algorithm in ("red-rec-wide", "assignment", "aod-parallel"):
        plan = solve(occ, target, algorithm=algorithm)
        where, transfers, steps = replay_counts(plan, occ, "slm")
        ref_where, ref_pickups, ref_steps = _one_atom_replays(plan, occ, "slm")
        assert np.array_equal(steps, ref_steps) and np.array_equal(transfers, 2 * ref_pickups)
        assert np.array_equal(where, ref_where)
        whole = replay(plan.operations, occ, trap_source="slm")
        assert whole.steps == steps.sum() and whole.max_pickups_per_atom == transfers.max() // 2


def test_replay_counts_on_a_chain_follow_the_slots() -> None:
    """On a chain the counts come from the plan's one-site steps; the slots must move each atom the same."""
    target = centre_target(nx=64, ny=1, count=32)
    for seed in range(5):
        occ = np.random.default_rng(seed).random((1, 64)) < 0.6
        plan = solve(occ, target, algorithm="exact-1d", trap_source="aod")
        where, transfers, steps = replay_counts(plan, occ, "aod")
        ref_where, ref_pickups, ref_steps = _one_atom_replays(plan, occ, "aod")
        assert np.array_equal(where, ref_where) and np.array_equal(steps, ref_steps)
        assert np.all(ref_pickups == 0) and np.array_equal(transfers, 2 * (steps > 0))
        assert steps.sum() == plan.n_steps > 0


def test_lossless_monte_carlo_always_succeeds_at_perfect_survival() -> None:
    target = centre_target(nx=8, ny=16, count=64)
    solver = Solver(nx=8, ny=16, algorithm="red-rec-wide")
    occ = np.random.default_rng(5).random((16, 8)) < 0.6
    ok, cycles = _loss_trial(solver, occ, target, "slm", 1.0, 1.0, 0.0, np.random.default_rng(0))
    assert ok and cycles == 1
    ok, _ = _loss_trial(solver, occ, target, "slm", 0.5, 0.5, 10e-6, np.random.default_rng(0))
    assert not ok


def test_cli_json_and_errors(capsys) -> None:
    assert main(["bench", "solvers", "--instances", "2", "--problems", "8x16", "--planners", "aod-parallel",
                 "--mc-trials", "0", "--repeats", "1", "--json"]) == 0  # fmt: skip
    data = json.loads(capsys.readouterr().out)
    assert data["benchmark"] == "solvers" and len(data["results"]) == 1
    assert data["results"][0]["planner"] == "aod-parallel" and "loss_mc" not in data["results"][0]
    with pytest.raises(ValueError, match="unknown problems"):
        bench_solvers(instances=1, problems=["3x3"])
    with pytest.raises(ValueError, match="unknown planners"):
        bench_solvers(instances=1, problems=["8x16"], planners=["teleport"])
    assert {p.name for p in PROBLEMS} >= {"1x64", "16x32", "32x64", "32x64@0.5", "64x128"}


def test_plots(tmp_path, small) -> None:
    pytest.importorskip("matplotlib")
    paths = plot_scaling(small, tmp_path)
    assert [p.name for p in paths] == ["solvers_slots.png", "solvers_planning.png"]
    assert all(p.stat().st_size > 1000 for p in paths)
