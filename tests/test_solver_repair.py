"""The repair planner: spare atoms into holes, valid under the complete move model, no atom already in the
target moved unless a path needs it, the survival objective weighing what a move risks; the per-cycle
strategy handing few-defect cycles to it."""

from __future__ import annotations

import numpy as np
import pytest

from engine.operations import Plan
from engine.solvers import LossWeights, PlannerError, Solver, UnsolvableError, solve
from engine.solvers.repair import route_atoms
from engine.solvers.strategy import StrategyPlanner
from engine.solvers.validate import validate

NY, NX = 16, 32
BAND = np.zeros((NY, NX), dtype=bool)
BAND[:, 8:24] = True


def band_with_defects(rng: np.random.Generator, holes: int, spare_fill: float = 0.5) -> np.ndarray:
    """A filled band with ``holes`` empty target traps, spare atoms outside it."""
    occ = BAND.copy()
    occ[~BAND] = rng.random(int((~BAND).sum())) < spare_fill
    target_sites = np.flatnonzero(BAND)
    occ.flat[rng.choice(target_sites, size=holes, replace=False)] = False
    return occ


def _moved_target_atoms(report, occ: np.ndarray) -> int:
    started_in_target = BAND.ravel()[np.flatnonzero(occ.ravel())]
    return int(np.count_nonzero((report.atom_steps > 0) & started_in_target))


@pytest.mark.parametrize("objective", ["slots", "transfers", "survival"])
def test_fills_few_defects_legally_and_only_spare_atoms_leave_their_traps(objective: str) -> None:
    rng = np.random.default_rng(3)
    for holes in (1, 3, 8, 20):
        occ = band_with_defects(rng, holes)
        plan = solve(occ, BAND, algorithm="repair", objective=objective)
        assert plan.algorithm == "repair"
        report = validate(plan, occ, BAND, trap_source="slm")  # the complete move model: captures accounted
        after = report.occupancy
        assert after[BAND].all() and after.sum() == occ.sum()
        # outside the target: exactly `holes` spare atoms left, none arrived
        assert (occ & ~after).sum() == holes and not (after & ~occ & ~BAND).any()
        # each hop runs over empty traps: every step is one site, and no atom was taken more than the holes
        # whose paths cross it
        assert report.max_pickups_per_atom <= holes


def test_with_clear_paths_no_target_atom_moves_and_each_atom_is_picked_up_once() -> None:
    """Holes at the band's edge, spare atoms right beside them: nothing in the target needs to move."""
    occ = BAND.copy()
    holes = [(2, 8), (5, 23), (9, 8), (13, 23)]
    for r, c in holes:
        occ[r, c] = False
        occ[r, c - 2 if c == 8 else c + 2] = True  # a spare atom two sites out, the trap between empty
    for objective in ("slots", "transfers", "survival"):
        plan = solve(occ, BAND, algorithm="repair", objective=objective)
        report = validate(plan, occ, BAND, trap_source="slm")
        assert _moved_target_atoms(report, occ) == 0
        assert report.atoms_moved == len(holes)
        assert report.max_pickups_per_atom == 1
        assert report.steps == 2 * len(holes)
        # the four repairs line up in two columns: batched into shared slots, not 4 x (2 + 2) one by one
        assert report.slots < 4 * len(holes)


def test_deep_hole_relays_the_atoms_on_its_path_one_site_each() -> None:
    """In the lattice model a loaded tweezer may not cross an occupied trap: the atoms between the spare atom
    and a hole deep in the band each move one site toward it, picked up once."""
    occ = BAND.copy()
    occ[:, :8] = False
    occ[:, 24:] = False
    occ[7, 12] = False  # four filled traps between the hole and the band's left edge
    occ[7, 7] = True  # the only spare atom
    plan = solve(occ, BAND, algorithm="repair", objective="survival")
    report = validate(plan, occ, BAND, trap_source="slm")
    assert _moved_target_atoms(report, occ) == 4
    assert report.atoms_moved == 5 and report.steps == 5 and report.max_pickups_per_atom == 1
    assert report.max_steps_per_atom == 1


def test_route_atoms_counts_the_atoms_between_on_both_l_routes() -> None:
    rng = np.random.default_rng(8)
    occ = rng.random((9, 11)) < 0.5
    free = np.argwhere(occ)[:15]
    holes = np.argwhere(~occ)[:12]
    row_first, col_first = route_atoms(occ, free, holes)

    def on_path(r0: int, c0: int, r1: int, c1: int, rows_first: bool) -> int:
        sites = []
        if rows_first:  # along the spare atom's row, then the hole's column
            sites += [(r0, c) for c in range(min(c0, c1), max(c0, c1) + 1)]
            sites += [(r, c1) for r in range(min(r0, r1), max(r0, r1) + 1)]
        else:
            sites += [(r, c0) for r in range(min(r0, r1), max(r0, r1) + 1)]
            sites += [(r1, c) for c in range(min(c0, c1), max(c0, c1) + 1)]
        between = set(sites) - {(r0, c0), (r1, c1)}
        return sum(bool(occ[s]) for s in between)

    for i, (r0, c0) in enumerate(free):
        for j, (r1, c1) in enumerate(holes):
            assert row_first[i, j] == on_path(r0, c0, r1, c1, True)
            assert col_first[i, j] == on_path(r0, c0, r1, c1, False)


def test_survival_objective_prefers_a_longer_clear_path_to_a_short_crowded_one() -> None:
    """A hole with a spare atom 3 sites left (2 atoms between) and one 5 sites right (none between). Fewest
    steps takes the left one and relays 3 atoms (6 transfers, 3 steps); the survival objective weighs 2
    transfers + 5 steps as fewer expected losses at 0.985 / 0.985 and takes the right one."""
    occ = np.zeros((NY, NX), dtype=bool)
    target = np.zeros_like(occ)
    target[4, 10:13] = True
    occ[4, 10:12] = True  # target traps (4, 10) and (4, 11) filled, the hole at (4, 12)
    occ[4, 9] = True  # spare, 3 sites left of the hole, behind two atoms
    occ[4, 17] = True  # spare, 5 sites right, clear path
    losses = {}
    for objective in ("slots", "survival"):
        plan = solve(occ, target, algorithm="repair", objective=objective)
        report = validate(plan, occ, target, trap_source="slm")
        losses[objective] = (report.atoms_moved, report.steps)
    assert losses["slots"] == (3, 3)
    assert losses["survival"] == (1, 5)
    w = LossWeights(survival_transfer=0.985, survival_step=0.985)
    assert w.expected_loss(transfers=2, steps=5, slots=0, atoms=0) < w.expected_loss(
        transfers=6, steps=3, slots=0, atoms=0
    )


def test_loss_weights_are_the_loss_model() -> None:
    w = LossWeights(survival_transfer=0.99, survival_step=0.999, slot_duration_s=10e-6, vacuum_lifetime_s=100.0)
    # survival of 3 transfers, 4 steps and 5 slots of 200 atoms, multiplied out
    exact = 0.99**3 * 0.999**4 * np.exp(-5 * 10e-6 * 200 / 100.0)
    assert w.expected_loss(transfers=3, steps=4, slots=5, atoms=200) == pytest.approx(-np.log(exact))
    with pytest.raises(ValueError, match="survival_step"):
        LossWeights(survival_step=0.0)


def test_unsolvable_and_bad_objective_are_clear() -> None:
    occ = np.zeros((NY, NX), dtype=bool)
    with pytest.raises(UnsolvableError):
        solve(occ, BAND, algorithm="repair")
    with pytest.raises(PlannerError, match="objective"):
        Solver(nx=NX, ny=NY, algorithm="repair", objective="fastest")
    with pytest.raises(PlannerError, match="not known"):
        Solver(nx=NX, ny=NY, algorithm="red-rec", repair_algorithm="mend")


class _Named:
    """A stand-in planner that records being asked and returns an empty plan under its name."""

    def __init__(self, name: str) -> None:
        self.nx, self.ny, self.name, self.calls = NX, NY, name, 0

    def check_target(self, target: np.ndarray) -> None:
        pass

    def solve_moves(self, occupancy: np.ndarray, target: np.ndarray) -> int:
        self.calls += 1
        return 0

    def batch(self) -> Plan:
        from engine.operations import Operations

        return Plan(np.zeros((0, 2), dtype=np.int32), Operations(nx=NX, ny=NY), algorithm=self.name)


def test_strategy_switches_on_the_number_of_holes() -> None:
    bulk, repair = _Named("bulk"), _Named("repair")
    strategy = StrategyPlanner(bulk, repair, repair_at_defects=5)
    rng = np.random.default_rng(1)
    for holes, expect in ((40, "bulk"), (6, "bulk"), (5, "repair"), (1, "repair"), (0, "repair")):
        occ = band_with_defects(rng, holes)
        strategy.solve_moves(occ, BAND)
        assert strategy.batch().algorithm == expect
    assert bulk.calls == 2 and repair.calls == 3
    with pytest.raises(ValueError, match="repair_at_defects"):
        StrategyPlanner(bulk, repair, repair_at_defects=-1)


def test_solver_strategy_plans_are_valid_and_named_by_their_planner() -> None:
    solver = Solver(nx=NX, ny=NY, algorithm="red-rec", objective="survival", repair_algorithm="repair",
                    repair_at_defects=10)  # fmt: skip
    rows = np.zeros((NY, NX), dtype=bool)
    rows[4:12] = True  # red-rec fills a band of full rows
    solver.check_target(rows)
    rng = np.random.default_rng(4)
    for holes, expect in ((60, "red-rec"), (10, "repair"), (2, "repair")):
        occ = rows.copy()
        occ[~rows] = rng.random(int((~rows).sum())) < 0.9
        occ.flat[rng.choice(np.flatnonzero(rows), size=holes, replace=False)] = False
        solver.solve_moves(occ, rows)
        plan = solver.batch()
        assert plan.algorithm == expect
        validate(plan, occ, rows, trap_source="slm")
