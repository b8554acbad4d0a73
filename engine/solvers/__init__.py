"""Module III: turn an occupancy and a target into a plan (one-site steps + the waveform slots that do them).

Every planner has the same two-stage shape, timed separately by the engine as the paper's Table 1 does:
``solve_moves(occupancy, target)`` (stage III.solve: which atom goes where, raising ``UnsolvableError``)
and ``batch()`` (stage III.batch: the ``Plan``, a view of the planner's own buffers, valid until the next
solve). A planner may batch inside ``solve_moves`` when one kernel call is cheaper than two (exact-1d: its
III.batch only hands out the filled table, and III.solve holds both). Planners allocate their buffers and
compile their kernels in the constructor, so the hot path does neither. ``check_target(target)`` says up
front, with a clear message, when a planner cannot handle a target, so a bad configuration is refused when
it is applied rather than failing mid-shot.

``solve(occupancy, target, algorithm=...)`` is the one-call convenience for scripts and tests.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from engine.operations import Operations, Plan
from engine.solvers.base import LossWeights, Planner, PlannerError, UnsolvableError

__all__ = ["ALGORITHMS", "LossWeights", "OBJECTIVES", "Planner", "PlannerError", "Solver", "UnsolvableError", "solve"]


# The factories import their planner's module when called, on purpose: only the configured planner loads
# (the assignment planner alone pulls in scipy.optimize, about 0.5 s), and its numba kernels with it.


def _exact_1d(nx: int, ny: int, trap_source: str) -> Planner:
    from engine.solvers.exact1d import Exact1DPlanner  # deferred on purpose, see above

    return Exact1DPlanner(nx, ny, trap_source=trap_source)


def _red_rec(batching: str) -> Callable[[int, int, str], Planner]:
    def build(nx: int, ny: int, trap_source: str) -> Planner:
        from engine.solvers.redrec import RedRecPlanner  # deferred on purpose, see above

        if trap_source != "slm":
            raise PlannerError(
                f"{batching} moves atoms between static SLM traps with crossed AODs; an AOD chain "
                "(trap_source 'aod') uses exact-1d"
            )
        return RedRecPlanner(nx, ny, batching=batching)

    return build


def _assignment(nx: int, ny: int, trap_source: str) -> Planner:
    from engine.solvers.assignment import AssignmentPlanner  # deferred on purpose, see above

    return AssignmentPlanner(nx, ny, trap_source=trap_source)


def _aod_parallel(nx: int, ny: int, trap_source: str, objective: str = "slots") -> Planner:
    from engine.solvers.aod_parallel import AODParallelPlanner  # deferred on purpose, see above

    if trap_source != "slm":
        raise PlannerError(
            "aod-parallel moves product sets of atoms between static SLM traps with crossed AODs; an AOD "
            "chain (trap_source 'aod') uses exact-1d"
        )
    return AODParallelPlanner(nx, ny, objective=objective)


def _repair(
    nx: int, ny: int, trap_source: str, objective: str = "survival", loss: LossWeights | None = None
) -> Planner:
    from engine.solvers.repair import RepairPlanner  # deferred on purpose, see above

    return RepairPlanner(nx, ny, trap_source=trap_source, objective=objective, loss=loss)


#: name -> factory(nx, ny, trap_source); the names ``solve`` and ``solver.algorithm`` accept.
_FACTORIES: dict[str, Callable[[int, int, str], Planner]] = {
    "exact-1d": _exact_1d,
    "red-rec": _red_rec("red-rec"),
    "red-rec-wide": _red_rec("red-rec-wide"),
    "assignment": _assignment,
    "aod-parallel": _aod_parallel,
    "repair": _repair,
}

ALGORITHMS: tuple[str, ...] = tuple(_FACTORIES)

#: Planning objectives (``solver.objective``): the fewest waveform slots, the fewest pick-ups per atom (every
#: transfer risks losing the atom), or the fewest atoms expected lost (``survival``: transfers, steps and
#: vacuum time weighed by the loss model, ``LossWeights``). Planners not listed in ``OBJECTIVE_AWARE`` have one
#: way to plan. aod-parallel weighs no costs: its plan for ``survival`` is its ``transfers`` plan (of its two,
#: the one that disturbs fewer atoms).
OBJECTIVES: tuple[str, ...] = ("slots", "transfers", "survival")
OBJECTIVE_AWARE: frozenset[str] = frozenset({"aod-parallel", "repair"})


def _build(
    algorithm: str, nx: int, ny: int, trap_source: str, objective: str, loss: LossWeights | None, routing: str
) -> Planner:
    factory = _FACTORIES.get(algorithm)
    if factory is None:
        raise PlannerError(f"solver.algorithm {algorithm!r} is not known; choose one of {', '.join(ALGORITHMS)}")
    if routing == "interstitial":
        # deferred: only interstitial routing needs it. The repair planner routes along the channels; any other
        # planner plans on the lattice and its plans are written on the grid of positions (engine.routing)
        from engine.solvers.interstitial import InterstitialRepairPlanner, LatticeOnPositions

        if algorithm == "repair":
            return InterstitialRepairPlanner(nx, ny)
        return LatticeOnPositions(_build(algorithm, nx, ny, trap_source, objective, loss, "lattice"))
    try:
        if algorithm == "repair":
            return _repair(nx, ny, trap_source, objective, loss)
        if algorithm in OBJECTIVE_AWARE:
            own = "transfers" if objective == "survival" else objective
            return factory(nx, ny, trap_source, own)  # type: ignore[call-arg]  # objective-aware factory
        return factory(nx, ny, trap_source)
    except PlannerError:
        raise
    except ValueError as err:
        raise PlannerError(f"solver.algorithm {algorithm!r}: {err}") from None


class Solver:
    """The engine's Module III: the configured planner behind one stable interface.

    With ``repair_algorithm`` set, a per-cycle strategy: ``algorithm`` (the bulk planner) while the target has
    more than ``repair_at_defects`` empty traps, ``repair_algorithm`` from then on (``StrategyPlanner``). The
    plan's ``algorithm`` names the planner that made it. ``loss`` weighs the ``survival`` objective.
    ``routing`` (``array.routing``): under ``interstitial`` the plans list positions (``engine.routing``).
    """

    def __init__(
        self,
        *,
        nx: int,
        ny: int,
        algorithm: str,
        trap_source: str = "slm",
        objective: str = "slots",
        loss: LossWeights | None = None,
        repair_algorithm: str | None = None,
        repair_at_defects: int = 0,
        routing: str = "lattice",
    ) -> None:
        if objective not in OBJECTIVES:
            raise PlannerError(f"solver.objective {objective!r} is not known; choose one of {', '.join(OBJECTIVES)}")
        self.nx, self.ny = nx, ny  # the array it plans for (``Planner``)
        self.planner = _build(algorithm, nx, ny, trap_source, objective, loss, routing)
        if repair_algorithm is not None:
            from engine.solvers.strategy import StrategyPlanner  # deferred: only a strategy needs it

            repair = _build(repair_algorithm, nx, ny, trap_source, objective, loss, routing)
            try:
                self.planner = StrategyPlanner(self.planner, repair, repair_at_defects=repair_at_defects)
            except ValueError as err:
                raise PlannerError(f"solver.strategy: {err}") from None
        self.algorithm = algorithm
        self.trap_source = trap_source
        self.objective = objective
        # the two hot-path stages are the planner's own bound methods: a forwarding method would add a
        # Python frame (~0.1 us) to each, against a ~5 us chain plan
        self.solve_moves: Callable[[np.ndarray, np.ndarray], int] = self.planner.solve_moves
        self.batch: Callable[[], Plan] = self.planner.batch

    def check_target(self, target: np.ndarray) -> None:
        try:
            self.planner.check_target(target)
        except ValueError as err:
            raise PlannerError(f"solver.algorithm {self.algorithm!r} cannot fill this target: {err}") from None


_cache: dict[tuple[int, int, str, str, str], Solver] = {}


def solve(
    occupancy: np.ndarray,
    target: np.ndarray,
    *,
    algorithm: str = "exact-1d",
    trap_source: str | None = None,
    objective: str = "slots",
) -> Plan:
    """Plan one cycle: ``occupancy`` and ``target`` are ``bool[ny, nx]`` (a 1D array is one row).

    ``trap_source`` defaults to ``"aod"`` (a chain) for one row and ``"slm"`` for a grid. The plan's arrays
    are copies, so it stays valid after later calls. Raises ``UnsolvableError`` or ``PlannerError``.
    """
    occupancy = np.atleast_2d(np.asarray(occupancy, dtype=bool))
    target = np.atleast_2d(np.asarray(target, dtype=bool))
    ny, nx = occupancy.shape
    if target.shape != occupancy.shape:
        raise ValueError(f"target shape {target.shape} differs from occupancy shape {occupancy.shape}")
    source = trap_source or ("aod" if ny == 1 else "slm")
    key = (nx, ny, algorithm, source, objective)
    solver = _cache.get(key)
    if solver is None:
        solver = _cache[key] = Solver(nx=nx, ny=ny, algorithm=algorithm, trap_source=source, objective=objective)
    solver.check_target(target)
    solver.solve_moves(occupancy, target)
    plan = solver.batch()
    return _copy_plan(plan)


def _copy_plan(plan: Plan) -> Plan:
    src = plan.operations
    ops = Operations(nx=src.nx, ny=src.ny, capacity=max(len(src), 1), half=src.half)
    n = len(src)
    for name in ("kind", "y_site", "y_delta", "x_site", "x_delta"):
        getattr(ops, name)[:n] = getattr(src, name)[:n]
    ops.n = n
    return Plan(steps=plan.steps.copy(), operations=ops, algorithm=plan.algorithm, notes=dict(plan.notes))
