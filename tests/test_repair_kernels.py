"""The repair planner's numba kernels against their references: the assignment against scipy's
``linear_sum_assignment`` (equal total cost), the pair costs against ``RepairPlanner._pair_costs``, and the whole
plan (hops and groups before batching) against the plain-Python planner (``reference_hops``)."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linear_sum_assignment

from engine.solvers import LossWeights
from engine.solvers.repair import RepairPlanner
from engine.solvers.repair_kernels import OBJECTIVE_CODES, assign, pair_costs
from engine.solvers.validate import validate


def _assign(cost: np.ndarray) -> np.ndarray:
    n_rows, n_cols = cost.shape
    lsa_f = np.zeros((3, n_cols))
    lsa_i = np.zeros((4, n_cols), dtype=np.int64)
    col4row = np.zeros(n_rows, dtype=np.int64)
    ok = assign(cost, n_rows, n_cols, lsa_f[0], lsa_f[1], lsa_f[2], lsa_i[0], lsa_i[1], col4row, lsa_i[2],
                np.zeros(n_rows, dtype=np.bool_), np.zeros(n_cols, dtype=np.bool_))  # fmt: skip
    assert ok
    return col4row


def test_assignment_matches_scipys_total_cost_on_many_instances() -> None:
    rng = np.random.default_rng(11)
    for trial in range(400):
        n_rows = int(rng.integers(1, 40))
        n_cols = n_rows + int(rng.integers(0, 60))
        if trial % 3 == 0:  # small integers: many ties
            cost = rng.integers(0, 5, size=(n_rows, n_cols)).astype(np.float64)
        elif trial % 3 == 1:  # Manhattan distances, as the slots objective
            a, b = rng.integers(0, 30, size=(n_rows, 2)), rng.integers(0, 30, size=(n_cols, 2))
            cost = np.abs(a[:, None] - b[None]).sum(axis=2).astype(np.float64)
        else:
            cost = rng.random((n_rows, n_cols)) * 10
        col4row = _assign(cost)
        assert len(set(col4row.tolist())) == n_rows and col4row.min() >= 0 and col4row.max() < n_cols
        rows, cols = linear_sum_assignment(cost)
        assert cost[np.arange(n_rows), col4row].sum() == pytest.approx(cost[rows, cols].sum(), abs=1e-9)


def _band_instance(rng: np.random.Generator, ny: int, nx: int) -> tuple[np.ndarray, np.ndarray]:
    target = np.zeros((ny, nx), dtype=bool)
    target[ny // 4 : 3 * ny // 4] = True
    occ = target.copy()
    occ[~target] = rng.random(int((~target).sum())) < rng.uniform(0.2, 0.7)
    holes = int(rng.integers(0, 70))
    occ.flat[rng.choice(np.flatnonzero(target), size=holes, replace=False)] = False
    return occ, target


@pytest.mark.parametrize("objective", ["slots", "transfers", "survival"])
def test_pair_costs_match_the_python_costs(objective: str) -> None:
    rng = np.random.default_rng(5)
    planner = RepairPlanner(32, 64, objective=objective, loss=LossWeights(survival_transfer=0.995, survival_step=0.999))
    w = planner.loss
    for _ in range(20):
        occ, target = _band_instance(rng, 64, 32)
        free, holes = np.argwhere(occ & ~target), np.argwhere(target & ~occ)
        cost = np.zeros((len(holes), len(free)))
        pair_costs(occ, np.ascontiguousarray(free), len(free), np.ascontiguousarray(holes), len(holes),
                   OBJECTIVE_CODES[objective], w.per_transfer, w.per_step, w.per_slot_atom,
                   np.zeros((64, 33), dtype=np.int64), np.zeros((65, 32), dtype=np.int64), cost)  # fmt: skip
        np.testing.assert_allclose(cost, planner._pair_costs(occ, free, holes).T, rtol=1e-12)


@pytest.mark.parametrize("objective", ["slots", "transfers", "survival"])
def test_kernel_plans_are_the_python_plans_and_valid(objective: str) -> None:
    """Same hops in the same groups as the plain-Python planner (scipy's assignment), on band instances of up
    to 70 holes at both example sizes; every plan valid under the complete move model and filling the target."""
    rng = np.random.default_rng(2)
    for ny, nx in ((16, 32), (64, 32)):
        planner = RepairPlanner(nx, ny, objective=objective,
                                loss=LossWeights(survival_transfer=0.995, survival_step=0.999))  # fmt: skip
        for _ in range(25):
            occ, target = _band_instance(rng, ny, nx)
            if occ.sum() < target.sum():
                continue
            reference = planner.reference_hops(occ, target)
            steps = planner.solve_moves(occ, target)
            assert planner.hop_groups() == reference
            assert steps == sum(len(hop) - 1 for group in reference for hop in group)
            report = validate(planner.batch(), occ, target, trap_source="slm")
            assert report.occupancy[target].all() and report.occupancy.sum() == occ.sum()


def test_kernel_grows_its_arrays_for_a_bulk_sized_problem() -> None:
    """Past its preallocated 64 holes / 256 free atoms (a freshly loaded array) it still plans, validly."""
    rng = np.random.default_rng(9)
    target = np.zeros((32, 32), dtype=bool)
    target[8:24] = True
    occ = rng.random(target.shape) < 0.6
    planner = RepairPlanner(32, 32, objective="survival")
    planner.solve_moves(occ, target)
    assert planner.hop_groups() == planner.reference_hops(occ, target)
    planner.solve_moves(occ, target)
    report = validate(planner.batch(), occ, target, trap_source="slm")
    assert report.occupancy[target].all()
