"""What every planner and the ``engine.solvers`` front both need: the ``Planner`` protocol and its errors.

A module of its own so that the planners import it and ``engine.solvers`` imports the planners, with no
circle between them (``tests/test_import_graph.py``).
"""

from __future__ import annotations

import math
from typing import Protocol, TypeVar

import numpy as np

from engine.operations import Plan

__all__ = ["LossWeights", "Planner", "PlannerError", "UnsolvableError"]

Num = TypeVar("Num", float, np.ndarray)


class UnsolvableError(RuntimeError):
    """Fewer atoms than target traps: no plan can fill the target (the shot ends, it is not a fault)."""


class PlannerError(ValueError):
    """A planner cannot handle this array, trap source or target; the message says which one can."""


class Planner(Protocol):
    nx: int
    ny: int

    def check_target(self, target: np.ndarray) -> None: ...

    def solve_moves(self, occupancy: np.ndarray, target: np.ndarray) -> int: ...

    def batch(self) -> Plan: ...


class LossWeights:
    """Expected atoms lost per transfer, per one-site step, and per slot per atom held in the array.

    From the loss model: ``-ln p_transfer``, ``-ln p_step`` and ``slot_duration_s / lifetime_s``. The
    defaults (0.985 / 0.985, 10 us slots, 60 s) are the simulated lab's defaults.
    """

    def __init__(
        self,
        *,
        survival_transfer: float = 0.985,
        survival_step: float = 0.985,
        slot_duration_s: float = 10e-6,
        vacuum_lifetime_s: float = 60.0,
    ) -> None:
        for name, p in (("survival_transfer", survival_transfer), ("survival_step", survival_step)):
            if not 0 < p <= 1:
                raise ValueError(f"{name} must be in (0, 1] (got {p})")
        if slot_duration_s <= 0 or vacuum_lifetime_s <= 0:
            raise ValueError(
                f"slot_duration_s and vacuum_lifetime_s must be > 0 (got {slot_duration_s}, {vacuum_lifetime_s})"
            )
        self.per_transfer = -math.log(survival_transfer)
        self.per_step = -math.log(survival_step)
        self.per_slot_atom = slot_duration_s / vacuum_lifetime_s

    def expected_loss(self, *, transfers: Num, steps: Num, slots: Num, atoms: float) -> Num:
        """Expected atoms lost by ``transfers`` transfers, ``steps`` steps and ``slots`` slots of ``atoms``
        (numbers or arrays of them)."""
        return transfers * self.per_transfer + steps * self.per_step + slots * atoms * self.per_slot_atom
