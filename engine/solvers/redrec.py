"""red-rec on a 2D grid with a full-width target band (``trap_source = "slm"``, crossed AODs).

``RedRecPlanner`` owns every buffer for one array size; ``solve_moves`` + ``batch`` allocate nothing in
the steady state (the plan's arrays are views of the planner's buffers, valid until the next solve).
The algorithm lives in ``redrec_solve`` (segments) and ``column_batching`` (waveform slots):

- ``red-rec``: the reference's column-block batching (one batch per column and direction, one batch per
  horizontally moved atom); close to the published stream lengths.
- ``red-rec-wide``: the same moves, with each column's down- and up-movers in one batch and each
  redistribution transfer's atoms travelling together.
"""

from __future__ import annotations

import numpy as np

from engine.operations import Operations, Plan, grown_table, write_slots
from engine.solvers.base import UnsolvableError
from engine.solvers.column_batching import batch_segments
from engine.solvers.redrec_solve import UNSOLVABLE, band_rows, solve_band

__all__ = ["BATCHINGS", "RedRecPlanner"]

BATCHINGS = ("red-rec", "red-rec-wide")

_BAND_PROBLEMS = {
    1: "row {lo} is only partly in the target",
    2: "the target rows are not contiguous (rows {lo}..{hi} break the band)",
    3: "the target selects no trap",
}


class RedRecPlanner:
    """red-rec for an ``ny x nx`` grid; ``batching`` is ``"red-rec"`` or ``"red-rec-wide"``.

    Compiles (or loads the cached) kernels in the constructor by planning one small instance.
    """

    def __init__(self, nx: int, ny: int, *, batching: str = "red-rec") -> None:
        if batching not in BATCHINGS:
            raise ValueError(f"batching must be one of {BATCHINGS} (got {batching!r})")
        if nx < 1 or ny < 2:
            raise ValueError(f"red-rec needs a grid with ny >= 2 rows (got ny = {ny}, nx = {nx})")
        self.nx = nx
        self.ny = ny
        self.batching = batching
        self._wide = batching == "red-rec-wide"
        n_traps = nx * ny
        self._work = np.zeros((ny, nx), dtype=np.bool_)
        self._surplus = np.zeros(nx, dtype=np.int64)
        self._nxt = np.zeros(nx, dtype=np.int64)
        self._prv = np.zeros(nx, dtype=np.int64)
        self._tr = np.zeros((nx, 4), dtype=np.int64)
        self._rows = np.zeros(n_traps, dtype=np.int64)
        self._recv = np.zeros((nx, 7), dtype=np.int64)
        self._slide = np.zeros((nx, ny + 1), dtype=np.int64)
        self._pos = np.zeros(ny, dtype=np.int64)
        self._scratch = np.zeros((3, ny), dtype=np.int64)
        self._seg = np.zeros((8 * nx + 8, 5), dtype=np.int64)
        self._mv = np.zeros((3 * n_traps, 2), dtype=np.int64)
        self._steps = np.zeros((n_traps * (nx + ny), 2), dtype=np.int32)
        self.operations = Operations(nx=nx, ny=ny, capacity=4 * (nx + ny + 2) * nx)
        self._y_used = np.zeros(self.operations.capacity, dtype=np.int64)
        self._x_used = np.zeros(self.operations.capacity, dtype=np.int64)
        self._n_seg = 0
        self._n_steps = 0
        self._solved = False
        self._warm_up()

    def _warm_up(self) -> None:
        occ = np.zeros((self.ny, self.nx), dtype=bool)
        occ[::2] = True
        occ[1, ::2] = True
        target = np.zeros_like(occ)
        rows = max(1, self.ny // 4)
        target[(self.ny - rows) // 2 : (self.ny + rows) // 2] = True
        self.solve_moves(occ, target)
        self.batch()
        self.operations.clear()
        self._y_used[:] = 0
        self._x_used[:] = 0
        self._solved = False

    def check_target(self, target: np.ndarray) -> None:
        """Raise ``ValueError`` unless ``target`` is a full-width band of contiguous rows."""
        if target.shape != (self.ny, self.nx):
            raise ValueError(f"target shape {target.shape} must be (ny, nx) = {(self.ny, self.nx)}")
        lo, hi, problem = band_rows(target)
        if problem:
            raise ValueError(
                "red-rec needs a target that is a full-width band of contiguous rows: "
                + _BAND_PROBLEMS[problem].format(lo=lo, hi=hi - 1)
            )

    def solve_moves(self, occupancy: np.ndarray, target: np.ndarray) -> int:
        """Plan the one-site moves for ``occupancy`` (``bool[ny, nx]``); returns their number.

        Raises ``ValueError`` if ``target`` is not a full-width band of contiguous rows (the only target
        red-rec handles) and ``engine.solvers.UnsolvableError`` if there are fewer atoms than target traps.
        """
        if occupancy.shape != (self.ny, self.nx) or target.shape != (self.ny, self.nx):
            raise ValueError(
                f"occupancy {occupancy.shape} and target {target.shape} must both be (ny, nx) = {(self.ny, self.nx)}"
            )
        lo, hi, problem = band_rows(target)
        if problem:
            self.check_target(target)
        self._solved = False
        status, self._n_seg, self._n_steps = solve_band(
            occupancy, lo, hi, self._work, self._surplus, self._nxt, self._prv, self._tr, self._rows,
            self._recv, self._slide, self._pos, self._seg, self._mv, self._steps,
        )  # fmt: skip
        if status == UNSOLVABLE:
            raise UnsolvableError(
                f"{int(occupancy.sum())} atoms cannot fill {int(target.sum())} target traps"
            )
        self._solved = True
        return self._n_steps

    def batch(self) -> Plan:
        """Batch the last solve into waveform slots (a view of the planner's table, reused next time)."""
        write_slots(self.operations, self._batch, self._grow, solved=self._solved)
        return Plan(steps=self._steps[: self._n_steps], operations=self.operations, algorithm=self.batching)

    def _batch(self) -> int:
        ops = self.operations
        return batch_segments(
            self._seg, self._n_seg, self._mv, self._wide, ops.n, ops.kind, ops.y_site, ops.y_delta,
            ops.x_site, ops.x_delta, self._y_used, self._x_used, self._scratch,
        )  # fmt: skip

    def _grow(self, need: int) -> None:
        self._y_used, self._x_used = grown_table(self.operations, need)
