"""red-rec on 2D grids: every plan replays legally under the crossed-AOD model and fills the band; move
quality against the L1 assignment bound; the errors; compiled kernels == the same kernels run as Python."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from bench.solvers import solvable_fillings
from engine.operations import EXTRACT, IMPLANT, SHIFT, Operations
from engine.solvers.redrec import BATCHINGS, RedRecPlanner
from engine.targets import centre_target
from numba_twins import assert_plans_agree

REPO = Path(__file__).resolve().parents[1]


def replay_operations(ops: Operations, occupancy: np.ndarray) -> np.ndarray:
    """Replay the slots under the crossed-AOD model (stand-in until ``engine.solvers.validate`` lands):
    tweezers at rows x columns; every atom under one moves with it; tones stay strictly ordered and on
    the grid; a loaded tweezer lands only on an empty trap; listed sites must be where the tones are."""
    grid = occupancy.copy()
    held = None
    ty = tx = np.zeros(0, dtype=int)
    for i in range(len(ops)):
        kind = int(ops.kind[i])
        ys, dys, xs, dxs = (a.astype(int) for a in ops.tones(i))
        assert np.all(np.diff(ys) > 0) and np.all(np.diff(xs) > 0), ops.describe(i)
        if kind == EXTRACT:
            assert held is None, ops.describe(i)
            ty, tx = ys, xs
            held = grid[np.ix_(ty, tx)].copy()
            grid[np.ix_(ty, tx)] = False
            continue
        assert held is not None and np.array_equal(ys, ty) and np.array_equal(xs, tx), ops.describe(i)
        if kind == SHIFT:
            ty, tx = ty + dys, tx + dxs
            assert np.all(np.diff(ty) > 0) and np.all(np.diff(tx) > 0), ops.describe(i)
            assert ty.min() >= 0 and ty.max() < grid.shape[0] and tx.min() >= 0 and tx.max() < grid.shape[1]
            moved = (dys[:, None] != 0) | (dxs[None, :] != 0)
            assert not np.any(grid[np.ix_(ty, tx)] & held & moved), ("lands on an atom", ops.describe(i))
        else:
            assert kind == IMPLANT, ops.describe(i)
            grid[np.ix_(ty, tx)] |= held
            held = None
    assert held is None, "atoms left in a tweezer"
    return grid


def replay_steps(steps: np.ndarray, occupancy: np.ndarray) -> np.ndarray:
    """Replay one-site steps in order: source occupied, destination an empty neighbour."""
    grid = occupancy.copy().ravel()
    nx = occupancy.shape[1]
    for src, dst in steps.tolist():
        assert grid[src] and not grid[dst], (src, dst)
        assert abs(src // nx - dst // nx) + abs(src % nx - dst % nx) == 1, (src, dst)
        grid[src] = False
        grid[dst] = True
    return grid.reshape(occupancy.shape)


def l1_bound(occupancy: np.ndarray, target: np.ndarray) -> int:
    ay, ax = np.nonzero(occupancy)
    ty, tx = np.nonzero(target)
    cost = np.abs(ay[:, None] - ty[None, :]) + np.abs(ax[:, None] - tx[None, :])
    rows, cols = linear_sum_assignment(cost)
    return int(cost[rows, cols].sum())


@pytest.fixture(scope="module")
def planners() -> dict[tuple[int, int, str], RedRecPlanner]:
    return {(ny, nx, b): RedRecPlanner(nx, ny, batching=b) for ny, nx in ((16, 8), (32, 16)) for b in BATCHINGS}


@pytest.mark.parametrize(("ny", "nx", "n"), [(16, 8, 40), (32, 16, 25)])
@pytest.mark.parametrize("batching", BATCHINGS)
def test_plans_replay_and_fill_the_band(planners, ny: int, nx: int, n: int, batching: str) -> None:
    planner = planners[(ny, nx, batching)]
    target = centre_target(nx=nx, ny=ny, count=nx * ny // 2)
    fillings, _ = solvable_fillings(ny, nx, n, loading=0.6, need=nx * ny // 2)
    for occ in fillings:
        n_steps = planner.solve_moves(occ, target)
        plan = planner.batch()
        assert plan.n_steps == n_steps and plan.algorithm == batching
        after_steps = replay_steps(plan.steps, occ)
        after_slots = replay_operations(plan.operations, occ)
        assert np.array_equal(after_steps, after_slots)
        assert after_slots[target].all()
        assert after_slots.sum() == occ.sum()


def test_wide_batching_is_shorter_with_the_same_moves(planners) -> None:
    target = centre_target(nx=16, ny=32, count=256)
    ref, wide = planners[(32, 16, "red-rec")], planners[(32, 16, "red-rec-wide")]
    for occ in solvable_fillings(32, 16, 10, loading=0.6, need=32 * 16 // 2)[0]:
        ref.solve_moves(occ, target)
        wide.solve_moves(occ, target)
        a, b = ref.batch(), wide.batch()
        assert np.array_equal(a.steps, b.steps)
        assert b.n_slots < a.n_slots


def test_few_atoms_per_column_and_dense_corners(planners) -> None:
    """Receivers with no free landing trap (pre-compacted) and donors far away."""
    planner = planners[(16, 8, "red-rec-wide")]
    target = centre_target(nx=8, ny=16, count=64)
    occ = np.zeros((16, 8), dtype=bool)
    occ[:, :4] = True  # all atoms on the left: every right column is an empty receiver
    planner.solve_moves(occ, target)
    assert replay_operations(planner.batch().operations, occ)[target].all()
    occ = np.zeros((16, 8), dtype=bool)
    occ[:4] = True
    occ[12:] = True  # full reservoirs, empty band: receivers cannot take arrivals without compacting
    occ[:, 0] = True
    planner.solve_moves(occ, target)
    assert replay_operations(planner.batch().operations, occ)[target].all()


def test_displacement_near_l1_bound_16x32(planners) -> None:
    planner = planners[(32, 16, "red-rec")]
    target = centre_target(nx=16, ny=32, count=256)
    occs = solvable_fillings(32, 16, 3, loading=0.6, need=32 * 16 // 2)[0]
    moves = sum(planner.solve_moves(occ, target) for occ in occs)
    bound = sum(l1_bound(occ, target) for occ in occs)
    assert moves <= 1.05 * bound


@pytest.mark.slow
def test_displacement_near_l1_bound_32x64() -> None:
    planner = RedRecPlanner(32, 64, batching="red-rec")
    target = centre_target(nx=32, ny=64, count=1024)
    for occ in solvable_fillings(64, 32, 20, loading=0.6, need=64 * 32 // 2)[0]:
        assert planner.solve_moves(occ, target) <= 1.05 * l1_bound(occ, target)


def test_target_must_be_a_full_width_band(planners) -> None:
    planner = planners[(16, 8, "red-rec")]
    occ = solvable_fillings(16, 8, 1, loading=0.6, need=16 * 8 // 2)[0][0]
    square = np.zeros((16, 8), dtype=bool)
    square[4:8, 2:6] = True
    with pytest.raises(ValueError, match="full-width band.*row 4 is only partly"):
        planner.solve_moves(occ, square)
    split = centre_target(nx=8, ny=16, count=64)
    split[8] = False
    with pytest.raises(ValueError, match="not contiguous"):
        planner.solve_moves(occ, split)
    with pytest.raises(ValueError, match="no trap"):
        planner.solve_moves(occ, np.zeros((16, 8), dtype=bool))
    with pytest.raises(RuntimeError):
        RedRecPlanner(8, 16).batch()


def test_unsolvable_raises(planners) -> None:
    solvers = pytest.importorskip("engine.solvers")
    if not hasattr(solvers, "UnsolvableError"):
        pytest.skip("engine.solvers.UnsolvableError has not landed yet")
    occ = np.zeros((16, 8), dtype=bool)
    occ[:7] = True  # 56 atoms < 64 target traps
    with pytest.raises(solvers.UnsolvableError):
        planners[(16, 8, "red-rec")].solve_moves(occ, centre_target(nx=8, ny=16, count=64))


_PLAN_SCRIPT = """
from engine.solvers.redrec import RedRecPlanner
from engine.targets import centre_target
for b in ("red-rec", "red-rec-wide"):
    p = RedRecPlanner(8, 16, batching=b)
    t = centre_target(nx=8, ny=16, count=64)
    for seed in range(6):
        occ = np.random.default_rng(seed).random((16, 8)) < 0.6
        if occ.sum() < 64:
            continue
        p.solve_moves(occ, t)
        out.append(plan_summary(p.batch()))
"""


def test_compiled_kernels_match_plain_python() -> None:
    """The numba kernels and the same source run as plain Python (NUMBA_DISABLE_JIT) give the same plans."""
    assert_plans_agree(_PLAN_SCRIPT, at_least=8)
