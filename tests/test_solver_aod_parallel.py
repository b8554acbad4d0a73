"""aod-parallel: every plan replays legally under the crossed-AOD model and fills the rectangle (band,
inner rectangles, full-height rectangles planned transposed, tiny arrays, both objectives); slot counts on
the paper's 32x64 problem; clear errors; compiled kernels == the same kernels run as plain Python."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from aod_parallel_golden import STORE, plan_digests
from bench.solvers import solvable_fillings
from engine.operations import EXTRACT
from engine.solvers import PlannerError, Solver, UnsolvableError, solve
from engine.solvers.aod_parallel import AODParallelPlanner
from engine.solvers.validate import validate
from engine.targets import centre_target, rectangle_target
from numba_twins import assert_plans_agree

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def planners() -> dict[tuple[int, int, str], AODParallelPlanner]:
    return {
        (ny, nx, obj): AODParallelPlanner(nx, ny, objective=obj)
        for ny, nx in ((32, 16), (24, 24), (64, 32))
        for obj in ("slots", "transfers")
    }


def _check(planner: AODParallelPlanner, occ: np.ndarray, target: np.ndarray) -> dict:
    n_steps = planner.solve_moves(occ, target)
    plan = planner.batch()
    report = validate(plan, occ, target, trap_source="slm")  # raises InvalidPlan on any broken rule
    assert plan.n_steps == n_steps and plan.algorithm == "aod-parallel"
    assert report.target_reached and report.occupancy.sum() == occ.sum() and report.captures == 0
    return {"slots": plan.n_slots, "pickups": report.max_pickups_per_atom}


@pytest.mark.parametrize("objective", ["slots", "transfers"])
def test_band_plans_replay_and_fill(planners, objective: str) -> None:
    ny, nx = 32, 16
    target = centre_target(nx=nx, ny=ny, count=nx * ny // 2)
    need = int(target.sum())
    dense, _ = solvable_fillings(ny, nx, 20, loading=0.6, need=need)
    sparse, _ = solvable_fillings(ny, nx, 10, loading=0.5, need=need)
    for occ in dense + sparse:
        _check(planners[(ny, nx, objective)], occ, target)


@pytest.mark.parametrize("objective", ["slots", "transfers"])
@pytest.mark.parametrize(
    "rect",
    [
        (4, 4, 16, 16),  # centred square
        (0, 6, 24, 12),  # full height: planned transposed
        (6, 0, 12, 24),  # full width: a band
        (2, 3, 20, 5),  # tall and narrow
        (10, 1, 4, 22),  # short and wide
    ],
)
def test_rectangles_replay_and_fill(planners, rect: tuple[int, int, int, int], objective: str) -> None:
    row0, col0, rows, cols = rect
    target = rectangle_target(nx=24, ny=24, row0=row0, col0=col0, rows=rows, cols=cols)
    fillings, _ = solvable_fillings(24, 24, 6, loading=0.6, need=int(target.sum()))
    for occ in fillings:
        _check(planners[(24, 24, objective)], occ, target)


def test_random_shapes_and_sizes() -> None:
    """Small and odd arrays, random rectangles and loadings, both objectives: zero invalid plans."""
    rng = np.random.default_rng(7)
    n_valid = 0
    for _ in range(120):
        ny, nx = (int(v) for v in rng.integers(1, 13, size=2))
        if nx * ny < 2:
            continue
        rows, cols = int(rng.integers(1, ny + 1)), int(rng.integers(1, nx + 1))
        target = rectangle_target(
            nx=nx, ny=ny, row0=int(rng.integers(0, ny - rows + 1)), col0=int(rng.integers(0, nx - cols + 1)),
            rows=rows, cols=cols,
        )  # fmt: skip
        occ = rng.random((ny, nx)) < rng.uniform(0.3, 0.9)
        for objective in ("slots", "transfers"):
            planner = AODParallelPlanner(nx, ny, objective=objective)
            if occ.sum() < target.sum():
                with pytest.raises(UnsolvableError):
                    planner.solve_moves(occ, target)
                continue
            _check(planner, occ, target)
            n_valid += 1
    assert n_valid > 100


def test_paper_problem_slots(planners) -> None:
    """32x64 -> 32x32 at loading 0.6: far fewer slots than the reference's ~826; transfers trade slots for pick-ups.

    (Under the complete move model a Fill needs a hole at the barrier row itself, not just next to it: 100
    instances gave 279 slots median, 309 max, where the incomplete model allowed 180 / 201.)"""
    target = centre_target(nx=32, ny=64, count=1024)
    fillings, _ = solvable_fillings(64, 32, 8, loading=0.6, need=int(target.sum()))
    fast = [_check(planners[(64, 32, "slots")], occ, target) for occ in fillings]
    few = [_check(planners[(64, 32, "transfers")], occ, target) for occ in fillings]
    assert np.median([f["slots"] for f in fast]) <= 290
    assert max(f["slots"] for f in fast) <= 310
    assert max(f["pickups"] for f in few) <= 4 < max(f["pickups"] for f in fast)
    assert np.median([f["slots"] for f in few]) < 500


@pytest.mark.slow
def test_paper_problem_slots_100_instances() -> None:
    planner = AODParallelPlanner(32, 64)
    target = centre_target(nx=32, ny=64, count=1024)
    fillings, _ = solvable_fillings(64, 32, 100, loading=0.6, need=int(target.sum()))
    slots = [_check(planner, occ, target)["slots"] for occ in fillings]
    assert np.median(slots) <= 290 and max(slots) <= 320


def test_batches_move_many_columns_at_once(planners) -> None:
    planner = planners[(64, 32, "slots")]
    target = centre_target(nx=32, ny=64, count=1024)
    occ = solvable_fillings(64, 32, 1, loading=0.6, need=int(target.sum()))[0][0]
    planner.solve_moves(occ, target)
    ops = planner.batch().operations
    extracts = [i for i in range(len(ops)) if ops.kind[i] == EXTRACT]
    columns = [int(np.count_nonzero(ops.x_site[i] >= 0)) for i in extracts]
    assert max(columns) >= 10 and np.mean(columns) > 4


def test_non_rectangular_targets_are_refused_clearly() -> None:
    solver = Solver(nx=8, ny=8, algorithm="aod-parallel")
    ring = np.zeros((8, 8), dtype=bool)
    ring[2:6, 2:6] = True
    ring[3:5, 3:5] = False
    with pytest.raises(PlannerError, match=r"rectangular targets.*rows 2\.\.5 x columns 2\.\.5.*'assignment'"):
        solver.check_target(ring)
    with pytest.raises(PlannerError, match="no trap"):
        solver.check_target(np.zeros((8, 8), dtype=bool))
    with pytest.raises(PlannerError, match="trap_source 'aod'"):
        Solver(nx=8, ny=1, algorithm="aod-parallel", trap_source="aod")
    with pytest.raises(PlannerError, match="objective"):
        Solver(nx=8, ny=8, algorithm="aod-parallel", objective="speed")
    with pytest.raises(ValueError, match="up to 128"):
        AODParallelPlanner(8, 200)
    with pytest.raises(RuntimeError):
        AODParallelPlanner(4, 4).batch()


def test_unsolvable_and_solve_entry_point() -> None:
    target = centre_target(nx=8, ny=16, count=64)
    occ = np.zeros((16, 8), dtype=bool)
    occ[:7] = True  # 56 atoms < 64 target traps
    with pytest.raises(UnsolvableError):
        solve(occ, target, algorithm="aod-parallel")
    occ = solvable_fillings(16, 8, 1, loading=0.6, need=int(target.sum()))[0][0]
    plan = solve(occ, target, algorithm="aod-parallel", objective="transfers")
    assert validate(plan, occ, target, trap_source="slm").target_reached


_PLAN_SCRIPT = """
from engine.solvers.aod_parallel import AODParallelPlanner
for ny, nx, rect in ((16, 8, (4, 12, 0, 8)), (12, 10, (3, 9, 2, 7)), (10, 12, (0, 10, 3, 8))):
    t = np.zeros((ny, nx), dtype=bool)
    t[rect[0]:rect[1], rect[2]:rect[3]] = True
    for objective in ("slots", "transfers"):
        p = AODParallelPlanner(nx, ny, objective=objective)
        for seed in range(4):
            occ = np.random.default_rng(seed).random((ny, nx)) < 0.6
            if occ.sum() < t.sum():
                continue
            p.solve_moves(occ, t)
            out.append(plan_summary(p.batch()))
"""


def test_compiled_kernels_match_plain_python() -> None:
    """The numba kernels and the same source run as plain Python (NUMBA_DISABLE_JIT) give the same plans."""
    assert_plans_agree(_PLAN_SCRIPT, at_least=12)


def test_plans_match_the_stored_reference_plans() -> None:
    """Byte for byte the plans stored before the kernels were last rewritten (``tests/aod_parallel_golden.py``):
    a readability rewrite of the kernels must not change a single slot or step."""
    stored = json.loads(STORE.read_text())
    now = plan_digests()
    changed = sorted(k for k in stored if now.get(k) != stored[k])
    assert now.keys() == stored.keys() and not changed, f"{len(changed)} plans changed, e.g. {changed[:3]}"
    assert sum(v != "unsolvable" for v in now.values()) >= 150  # the instances are mostly solvable
