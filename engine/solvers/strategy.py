"""A per-cycle strategy: a bulk planner while the target has many holes, a repair planner when few.

The first cycle of a shot finds ~40 % of the target empty: a bulk planner (red-rec, aod-parallel) fills it in
few slots by moving whole columns. Later cycles find a handful of holes (atoms lost in the last cycle): a bulk
re-plan would pick up tens of atoms per hole, each pick-up risking the atom, where the repair planner moves
one spare atom per hole (and the atoms on its path). ``StrategyPlanner`` counts the holes each cycle and hands
the cycle to one of the two; the plan's ``algorithm`` names the planner that made it, and the engine records
it per cycle.
"""

from __future__ import annotations

import numpy as np

from engine.operations import Plan
from engine.solvers.base import Planner

__all__ = ["StrategyPlanner"]


class StrategyPlanner:
    """``bulk`` while the target has more than ``repair_at_defects`` empty traps, ``repair`` from then on."""

    def __init__(self, bulk: Planner, repair: Planner, *, repair_at_defects: int) -> None:
        if bulk.nx != repair.nx or bulk.ny != repair.ny:
            raise ValueError(f"bulk ({bulk.ny}x{bulk.nx}) and repair ({repair.ny}x{repair.nx}) planners differ")
        if repair_at_defects < 0:
            raise ValueError(f"repair_at_defects must be >= 0 (got {repair_at_defects})")
        self.nx = bulk.nx
        self.ny = bulk.ny
        self.bulk = bulk
        self.repair = repair
        self.repair_at_defects = repair_at_defects
        self.active: Planner = bulk

    def check_target(self, target: np.ndarray) -> None:
        self.bulk.check_target(target)
        self.repair.check_target(target)

    def solve_moves(self, occupancy: np.ndarray, target: np.ndarray) -> int:
        holes = int(np.count_nonzero(target & ~occupancy))
        self.active = self.repair if holes <= self.repair_at_defects else self.bulk
        return self.active.solve_moves(occupancy, target)

    def batch(self) -> Plan:
        return self.active.batch()
