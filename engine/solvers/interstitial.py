"""Planning under interstitial routing (``array.routing: interstitial``, ``engine/routing.py``).

Two planners, both writing ``Operations`` on the grid of positions (``half = 2``):

- ``InterstitialRepairPlanner`` (``repair`` under interstitial routing): each spare atom goes straight to the
  hole it is assigned, passing occupied traps in the channels, so no atom but the spare one is touched and
  nothing is relayed. Its route: extract at its trap; half a site along y into the row channel next to it
  (towards the hole's row); along that channel to the column channel beside the hole's column (on the side
  facing the spare atom); along the column channel to the hole's row; half a site along x onto the hole;
  implant. Every position between the two half steps is odd on one axis at least, so the loaded tweezer ends
  no slot over a trap. The assignment is the minimum total Manhattan distance (scipy's Hungarian solver): with
  two transfers per moved atom whatever the pair, fewer sites travelled is also fewer expected losses, so
  every objective gives this plan. Routes run one after the other (a 1 x 1 product set, no empty tweezer
  anywhere), in ``2 d + 3`` to ``2 d + 7`` slots for a pair ``d`` sites apart.
- ``LatticeOnPositions``: any lattice planner (a strategy's bulk planner) with its plan written on the grid of
  positions (``engine.routing.lattice_to_positions``: every one-site shift as two half-site shifts).
"""

from __future__ import annotations

import numpy as np

from engine.operations import EXTRACT, IMPLANT, SHIFT, Operations, Plan
from engine.routing import lattice_to_positions, n_positions
from engine.solvers.base import Planner, UnsolvableError

__all__ = ["InterstitialRepairPlanner", "LatticeOnPositions"]


class InterstitialRepairPlanner:
    """Fills the holes of any target mask from the spare atoms, each moved once along the channels."""

    def __init__(self, nx: int, ny: int) -> None:
        if min(nx, ny) < 2:
            raise ValueError(f"interstitial routing needs channels on both axes: at least 2 x 2 traps, got {ny} x {nx}")
        self.nx, self.ny = nx, ny
        self.px, self.py = n_positions(nx, 2), n_positions(ny, 2)
        self.operations = Operations(nx=self.px, ny=self.py, capacity=4 * (nx + ny) + 256, half=2)
        self._steps = np.zeros((4 * (nx + ny) + 256, 2), dtype=np.int32)
        self._n_steps = 0
        self._plan = Plan(steps=self._steps[:0], operations=self.operations, algorithm="repair")

    def check_target(self, target: np.ndarray) -> None:
        if target.shape != (self.ny, self.nx):
            raise ValueError(f"target is {target.shape[0]}x{target.shape[1]}, the array {self.ny}x{self.nx}")

    def solve_moves(self, occupancy: np.ndarray, target: np.ndarray) -> int:
        """Assign spare atoms to holes (fewest sites travelled) and write each route; returns the half-site steps."""
        occ = np.asarray(occupancy, dtype=bool)
        holes = np.argwhere(target & ~occ)
        spare = np.argwhere(occ & ~target)
        if spare.shape[0] < holes.shape[0]:
            raise UnsolvableError(f"{holes.shape[0]} holes in the target but only {spare.shape[0]} spare atoms")
        self.operations.clear()
        self._n_steps = 0
        if holes.shape[0]:
            from scipy.optimize import linear_sum_assignment  # deferred: scipy loads with this planner only

            cost = np.abs(spare[:, None, :] - holes[None, :, :]).sum(axis=2)
            chosen, hole_of = linear_sum_assignment(cost.T)  # rows: holes
            for h, s in zip(chosen.tolist(), hole_of.tolist(), strict=True):
                self._route(int(spare[s, 0]), int(spare[s, 1]), int(holes[h, 0]), int(holes[h, 1]))
        self._plan.steps = self._steps[: self._n_steps]
        return self._n_steps

    def batch(self) -> Plan:
        return self._plan

    def _route(self, r0: int, c0: int, r1: int, c1: int) -> None:
        """Extract at trap (r0, c0), travel the channels, implant at trap (r1, c1) (see the module docstring)."""
        y, x = 2 * r0, 2 * c0
        sy = (1 if r1 > r0 else -1) if r1 != r0 else (1 if r0 < self.ny - 1 else -1)
        sx = (-1 if c0 < c1 else 1) if c1 != c0 else (1 if c1 < self.nx - 1 else -1)
        if not 0 <= 2 * c1 + sx < self.px:  # the hole is at an edge column: the channel on its inner side
            sx = -sx
        self.operations.append(EXTRACT, [y], [x])
        moves = [(sy, 0)]
        channel_x = 2 * c1 + sx
        moves += [(0, 1 if channel_x > x else -1)] * abs(channel_x - x)
        moves += [(1 if 2 * r1 > y + sy else -1, 0)] * abs(2 * r1 - (y + sy))
        moves += [(0, -sx)]
        for dy, dx in moves:
            self.operations.append(SHIFT, [y], [x], [dy], [dx])
            self._step(y * self.px + x, (y + dy) * self.px + x + dx)
            y, x = y + dy, x + dx
        self.operations.append(IMPLANT, [y], [x])

    def _step(self, src: int, dst: int) -> None:
        if self._n_steps == self._steps.shape[0]:
            self._steps = np.concatenate([self._steps, np.zeros_like(self._steps)])
        self._steps[self._n_steps] = (src, dst)
        self._n_steps += 1


class LatticeOnPositions:
    """A lattice planner whose plans play under interstitial routing: each plan copied onto the grid of
    positions, every one-site shift as two half-site shifts (``engine.routing.lattice_to_positions``)."""

    def __init__(self, planner: Planner) -> None:
        self.planner = planner
        self.nx, self.ny = planner.nx, planner.ny
        self.operations = Operations(nx=n_positions(self.nx, 2), ny=n_positions(self.ny, 2), capacity=512, half=2)
        self._steps = np.zeros((512, 2), dtype=np.int32)
        self._plan = Plan(steps=self._steps[:0], operations=self.operations)
        self.check_target = planner.check_target
        self.solve_moves = planner.solve_moves

    def batch(self) -> Plan:
        plan = self.planner.batch()
        src, out = plan.operations, self.operations
        out.clear()
        out.reserve(2 * len(src))
        if self._steps.shape[0] < 2 * plan.n_steps:
            self._steps = np.zeros((2 * plan.n_steps, 2), dtype=np.int32)
        out.n = lattice_to_positions(
            src.kind, src.y_site, src.y_delta, src.x_site, src.x_delta, len(src), plan.steps, plan.n_steps, self.nx,
            out.kind, out.y_site, out.y_delta, out.x_site, out.x_delta, self._steps,
        )  # fmt: skip
        self._plan.steps = self._steps[: 2 * plan.n_steps]
        self._plan.algorithm = plan.algorithm
        self._plan.notes = plan.notes
        return self._plan
