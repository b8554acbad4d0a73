"""What every planner and the ``engine.solvers`` front both need: the ``Planner`` protocol and its errors.

A module of its own so that the planners import it and ``engine.solvers`` imports the planners, with no
circle between them (``tests/test_import_graph.py``).
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from engine.operations import Plan

__all__ = ["Planner", "PlannerError", "UnsolvableError"]


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
