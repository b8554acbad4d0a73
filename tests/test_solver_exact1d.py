"""Exact 1D solver: optimal against brute force, plans that replay legally on both trap sources, one slot
per parallel step, the public ``solve`` entry point, and its errors."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from engine.operations import EXTRACT, IMPLANT, SHIFT
from engine.solvers import ALGORITHMS, PlannerError, Solver, UnsolvableError, solve
from engine.solvers.exact1d import Exact1DPlanner, match_chain_reference
from engine.solvers.validate import validate
from engine.targets import centre_target


def brute_force_cost(occ: np.ndarray, target: np.ndarray) -> int:
    """Every choice of which atoms fill the targets; any assignment is checked, not only ordered ones."""
    atoms = np.flatnonzero(occ)
    sites = np.flatnonzero(target)
    best = None
    for chosen in itertools.combinations(atoms, sites.size):
        for perm in itertools.permutations(chosen):
            cost = int(np.abs(np.array(perm) - sites).sum())
            best = cost if best is None or cost < best else best
    assert best is not None
    return best


def random_chains(n: int, count: int, seed: int) -> list[tuple[np.ndarray, np.ndarray]]:
    rng = np.random.default_rng(seed)
    out = []
    while len(out) < count:
        occ = rng.random((1, n)) < rng.uniform(0.3, 0.8)
        target = rng.random((1, n)) < rng.uniform(0.2, 0.5)
        if 0 < target.sum() <= occ.sum():
            out.append((occ, target))
    return out


def test_total_displacement_equals_brute_force_optimum() -> None:
    planner = Exact1DPlanner(9)
    for occ, target in random_chains(9, 150, seed=1):
        if target.sum() > 5:
            continue
        n_steps = planner.solve_moves(occ, target)
        assert n_steps == brute_force_cost(occ[0], target[0])


@pytest.mark.parametrize("trap_source", ["aod", "slm"])
def test_plans_replay_legally_and_fill_any_target(trap_source: str) -> None:
    planner = Exact1DPlanner(24, trap_source=trap_source)
    for occ, target in random_chains(24, 300, seed=2):
        n_steps = planner.solve_moves(occ, target)
        plan = planner.batch()
        report = validate(plan, occ, target, trap_source=trap_source)
        assert report.steps == n_steps == plan.n_steps
        assert report.occupancy.sum() == occ.sum()
        ref = match_chain_reference(occ[0], target[0])
        assert ref is not None
        assert n_steps == int(np.abs(ref[0] - ref[1]).sum())


def test_one_slot_per_parallel_step_both_directions_together() -> None:
    occ = np.array([[0, 1, 1, 0, 0, 0, 0, 0, 1, 1]], dtype=bool)  # two blocks moving in
    target = np.array([[0, 0, 0, 1, 1, 1, 1, 0, 0, 0]], dtype=bool)
    plan = solve(occ, target)
    assert plan.n_slots == 3  # the longest displacement, not one slot per block or per direction
    assert np.all(plan.operations.kind[: plan.n_slots] == SHIFT)
    ys, _, xs, dxs = plan.operations.tones(0)
    assert ys.tolist() == [0]
    assert xs.tolist() == [1, 2, 8, 9] and dxs.tolist() == [1, 1, -1, -1]
    ys, _, xs, dxs = plan.operations.tones(2)
    assert xs.tolist() == [6, 7] and dxs.tolist() == [-1, -1]  # arrived tones drop out of the conveyor


def test_slm_chain_is_one_extract_shift_implant_batch() -> None:
    occ = np.array([[1, 0, 1, 0, 0, 0, 1, 1]], dtype=bool)
    target = np.array([[0, 0, 1, 1, 1, 0, 0, 0]], dtype=bool)
    plan = solve(occ, target, trap_source="slm")
    kinds = plan.operations.kind[: plan.n_slots].tolist()
    assert kinds[0] == EXTRACT and kinds[-1] == IMPLANT and set(kinds[1:-1]) == {SHIFT}
    report = validate(plan, occ, target, trap_source="slm")
    assert report.max_pickups_per_atom == 1 and report.batches == 1


def test_nothing_to_do_gives_an_empty_plan() -> None:
    target = centre_target(nx=16, ny=1, count=8)
    plan = solve(target.copy(), target)
    assert plan.n_slots == 0 and plan.n_steps == 0


def test_unsolvable_and_unsupported() -> None:
    target = centre_target(nx=16, ny=1, count=8)
    occ = np.zeros((1, 16), dtype=bool)
    occ[0, :3] = True
    with pytest.raises(UnsolvableError, match="3 atoms cannot fill 8"):
        solve(occ, target)
    with pytest.raises(PlannerError, match="single row"):
        Solver(nx=8, ny=4, algorithm="exact-1d", trap_source="slm")
    with pytest.raises(PlannerError, match="not known; choose one of"):
        Solver(nx=8, ny=1, algorithm="teleport")
    with pytest.raises(PlannerError, match="exact-1d"):
        Solver(nx=8, ny=4, algorithm="red-rec", trap_source="aod")
    assert {"exact-1d", "red-rec", "red-rec-wide"} <= set(ALGORITHMS)


def test_solve_returns_independent_copies() -> None:
    target = centre_target(nx=32, ny=1, count=16)
    rng = np.random.default_rng(5)
    a_occ, b_occ = (rng.random((1, 32)) < 0.7 for _ in range(2))
    a = solve(a_occ, target)
    a_steps = a.steps.copy()
    solve(b_occ, target)
    assert np.array_equal(a.steps, a_steps)
    validate(a, a_occ, target, trap_source="aod")


def test_planner_reuses_its_buffers() -> None:
    planner = Exact1DPlanner(64)
    target = centre_target(nx=64, ny=1, count=32)
    occ = np.random.default_rng(3).random((1, 64)) < 0.6
    planner.solve_moves(occ, target)
    first = planner.batch()
    planner.solve_moves(occ, target)
    second = planner.batch()
    assert first is second and first.operations is planner.operations
