"""AOD-parallel planner: product sets of rows x columns that move many columns' atoms in every slot.

Targets: any filled rectangle (a full-width band is the paper's case). The plan has two phases, both made
of *batches* (EXTRACT, SHIFT slots, IMPLANT on one product set of row tones x column tones):

1. **Balancing** (horizontal). Every target column needs at least as many atoms as it has target rows.
   The target column with the largest deficit takes atoms from the nearest column with atoms to spare,
   hop by hop: one batch picks some atoms of one column (one x tone, their rows' y tones, so nothing else is
   picked up) and carries them along their rows as far as they all have free traps.
2. **Fill** (vertical). Each target column keeps a *window* of consecutive atoms that will fill its target
   rows in order; its top need T is how many rows the top window atom still has to come down, its bottom
   need B the same upwards. A *Fill* batch picks every row above a barrier ``h`` and every row below a
   barrier ``h'`` in a set of columns, shifts the upper rows down and the lower rows up by one row, and
   implants (3 slots). For one column this deletes the hole at the barrier (every atom above it comes down
   one row, however far away the hole is), so it is legal when the column has a hole at ``h - 1`` or ``h``
   (and at ``h'`` or ``h' + 1``), harmless when no window atom passes its target, and useful when it
   lowers T or B. Each batch takes the barrier pair that helps the most columns, weighted by their
   remaining need (columns with the most left to do are on the critical path); the window of a column is
   re-chosen after each of its moves (the window that minimises max(T, B)).

This is the "shared-prefix hole deletion" greedy of the crossed-AOD study (``aod-parallel.md``), evaluated on
bit sets of columns per barrier with an upper-bound cut-off on barrier pairs, so a 32x64 instance plans in a
fraction of a millisecond. The alternative objective ``transfers`` replaces phase 2 by one compression batch
per column (each atom is picked up at most once there), trading slots for fewer pick-ups.

Rectangles that span every row are planned transposed (their columns become full-width rows); other
rectangles are planned in the orientation that needs less horizontal transport.

Crossed AODs make a tweezer at every intersection of the product set, loaded or not, and an empty one that
arrives over an atom captures it. Every row above a top barrier is picked in every column of a Fill, so the
only tweezer that can arrive over an unpicked atom is the one from row ``h - 1`` landing on row ``h`` (and
``h' + 1`` on ``h'``): a Fill is legal in a column only with a hole at the barrier row itself. Balancing
hops pick one column's atoms only. So every plan is legal under the complete move model by construction
(``tests/test_move_model.py`` replays random plans through it).
"""

from __future__ import annotations

import numpy as np

from engine.operations import Operations, Plan, grown_table, write_slots
from engine.solvers.aod_parallel_kernels import OK, OVERFLOW, STUCK, UNSOLVABLE, emit_batches, find_rect, plan_rect
from engine.solvers.base import PlannerError, UnsolvableError

__all__ = ["MAX_TONES", "OBJECTIVES", "AODParallelPlanner"]

OBJECTIVES = ("slots", "transfers")
MAX_TONES = 128  # rows and columns are kept as two 64-bit words


class AODParallelPlanner:
    """AOD-parallel planning for an ``ny x nx`` grid of static (SLM) traps and rectangular targets."""

    def __init__(
        self, nx: int, ny: int, *, objective: str = "slots", dynamic_windows: bool = True, k_best: int = 12
    ) -> None:
        if objective not in OBJECTIVES:
            raise ValueError(f"objective must be one of {OBJECTIVES} (got {objective!r})")
        if nx < 1 or ny < 1 or nx * ny < 2:
            raise ValueError(f"aod-parallel needs at least two traps (got {ny} x {nx})")
        if max(nx, ny) > MAX_TONES:
            raise ValueError(f"aod-parallel plans arrays of up to {MAX_TONES} rows and columns (got {ny} x {nx})")
        self.nx = nx
        self.ny = ny
        self.objective = objective
        self.dynamic_windows = dynamic_windows
        self.k_best = k_best
        m = max(nx, ny)
        n_traps = nx * ny
        self._g = np.zeros((m, m), dtype=np.bool_)
        # the column balance's scratch (atoms per column, candidate rows, their keys, rows carried in): one
        # block, each a C-contiguous row of it, as the kernels' signatures expect
        self._cnt, self._cand, self._key, self._carried = np.zeros((4, m), dtype=np.int64)
        self._st = np.zeros((m, 10), dtype=np.int64)
        self._pos = np.zeros(m, dtype=np.int64)
        self._ob = np.zeros((m, 2), dtype=np.uint64)
        self._prow = np.zeros((m, m), dtype=np.int64)
        self._cm = np.zeros((m, 8), dtype=np.uint64)
        # per-column scratch of the Fill scoring, top and bottom alike (one block, as above)
        self._vt, self._ut, self._vb, self._ub = np.zeros((4, m, 2), dtype=np.uint64)
        self._sct, self._scb, self._it, self._ib, self._tv, self._bv = np.zeros((6, m), dtype=np.int64)
        self._ptop = np.zeros((8, 2), dtype=np.uint64)
        self._pbot = np.zeros((8, 2), dtype=np.uint64)
        self._cols = np.zeros(m, dtype=np.int64)
        self._alloc_records(n_batches=8 * m + 64, n_tones=8 * m * m + 64, n_steps=6 * n_traps + 64)
        self.operations = Operations(nx=nx, ny=ny, capacity=24 * m + 64)
        self._y_used = np.zeros(self.operations.capacity, dtype=np.int64)
        self._x_used = np.zeros(self.operations.capacity, dtype=np.int64)
        self._frame = (False, 0, 0, 0, 0)
        self._nb = 0
        self._n_steps = 0
        self._n_slots = 0
        self._solved = False
        self._warm_up()

    # -- buffers ---------------------------------------------------------------------------------------
    def _alloc_records(self, *, n_batches: int, n_tones: int, n_steps: int) -> None:
        self._bmeta = np.zeros((n_batches, 6), dtype=np.int64)
        # the batches' tone lists (row: index, start, move; column: the same), one C-contiguous row each
        self._brow, self._brs, self._brm, self._bcol, self._bcs, self._bcm = np.zeros((6, n_tones), dtype=np.int64)
        self._steps = np.zeros((n_steps, 2), dtype=np.int32)

    def _warm_up(self) -> None:
        occ = np.zeros((self.ny, self.nx), dtype=bool)
        occ[::2] = True
        occ[1::4, ::2] = True
        target = np.zeros_like(occ)
        target[self.ny // 4 : max(self.ny // 4 + 1, self.ny // 2), :] = True
        if occ.sum() < target.sum():
            occ[:] = True
        self.solve_moves(occ, target)
        self.batch()
        self._solved = False

    # -- targets ---------------------------------------------------------------------------------------
    def _rect(self, target: np.ndarray) -> tuple[int, int, int, int]:
        if target.shape != (self.ny, self.nx):
            raise ValueError(f"target shape {target.shape} must be (ny, nx) = {(self.ny, self.nx)}")
        r0, r1, c0, c1, ok = find_rect(target)
        if ok < 0:
            raise ValueError("the target selects no trap")
        if ok == 0:
            missing = np.argwhere(~target[r0:r1, c0:c1])[0] + (r0, c0)
            raise ValueError(
                "aod-parallel fills rectangular targets (a full-width band or any filled rectangle); this "
                f"target's bounding box rows {r0}..{r1 - 1} x columns {c0}..{c1 - 1} leaves trap "
                f"(row {missing[0]}, col {missing[1]}) out. Use 'assignment' for arbitrary masks"
            )
        return r0, r1, c0, c1

    def check_target(self, target: np.ndarray) -> None:
        """Raise ``ValueError`` unless ``target`` is one filled rectangle of traps."""
        self._rect(target)

    def _choose_frame(self, occ: np.ndarray, r0: int, r1: int, c0: int, c1: int) -> tuple[bool, int, int, int, int]:
        full_rows = r0 == 0 and r1 == self.ny
        full_cols = c0 == 0 and c1 == self.nx
        if full_rows and not full_cols:
            return True, c0, c1, r0, r1
        if full_cols or full_rows:
            return False, r0, r1, c0, c1
        # both orientations possible: the one whose target columns lack fewer atoms (less horizontal transport)
        need_v = np.maximum(0, (r1 - r0) - occ[:, c0:c1].sum(axis=0)).sum()
        need_h = np.maximum(0, (c1 - c0) - occ[r0:r1, :].sum(axis=1)).sum()
        if need_h < need_v:
            return True, c0, c1, r0, r1
        return False, r0, r1, c0, c1

    # -- planning --------------------------------------------------------------------------------------
    def solve_moves(self, occupancy: np.ndarray, target: np.ndarray) -> int:
        """Plan the batches for ``occupancy`` (``bool[ny, nx]``); returns the number of one-site steps.

        Raises ``ValueError`` for a target that is not a rectangle and ``engine.solvers.UnsolvableError``
        when there are fewer atoms than target traps."""
        if occupancy.shape != (self.ny, self.nx):
            raise ValueError(f"occupancy shape {occupancy.shape} must be (ny, nx) = {(self.ny, self.nx)}")
        if target.shape != (self.ny, self.nx):
            self._rect(target)  # raises with the shape
        r0, r1, c0, c1, ok = find_rect(target)  # a compiled scan: cheaper than comparing with a cached copy
        if ok != 1:
            self._rect(target)  # raises, naming what is wrong
        self._solved = False
        frame = self._choose_frame(occupancy, r0, r1, c0, c1)
        self._frame = frame
        transposed, a0, a1, b0, b1 = frame
        dedicated = self.objective == "transfers"
        occ = occupancy if occupancy.dtype == np.bool_ else occupancy.astype(bool)
        while True:
            status, nb, n_steps, n_slots = plan_rect(
                occ, transposed, a0, a1, b0, b1, self.dynamic_windows, dedicated, self.k_best,
                self._g, self._cnt, self._cand, self._key, self._carried, self._ob, self._prow, self._st, self._pos,
                self._cm, self._vt, self._ut, self._vb, self._ub, self._sct, self._scb, self._it, self._ib, self._tv,
                self._bv, self._ptop, self._pbot, self._cols, self._bmeta, self._brow, self._brs, self._brm,
                self._bcol, self._bcs, self._bcm, self._steps,
            )  # fmt: skip
            if status != OVERFLOW:
                break
            self._alloc_records(
                n_batches=2 * self._bmeta.shape[0], n_tones=2 * self._brow.shape[0], n_steps=2 * self._steps.shape[0]
            )
        if status == UNSOLVABLE:
            raise UnsolvableError(f"{int(occupancy.sum())} atoms cannot fill {int(target.sum())} target traps")
        if status == STUCK:
            raise PlannerError("aod-parallel could not balance the target columns with horizontal hops")
        assert status == OK
        self._nb, self._n_steps, self._n_slots = nb, n_steps, n_slots
        self._solved = True
        return n_steps

    def batch(self) -> Plan:
        """The waveform slots of the last solve (a view of the planner's table, reused next time)."""
        write_slots(self.operations, self._emit, self._grow, solved=self._solved)
        return Plan(steps=self._steps[: self._n_steps], operations=self.operations, algorithm="aod-parallel")

    def _grow(self, need: int) -> None:
        self._y_used, self._x_used = grown_table(self.operations, need)

    def _emit(self) -> int:
        ops = self.operations
        return emit_batches(
            self._bmeta, self._nb, self._brow, self._brs, self._brm, self._bcol, self._bcs, self._bcm,
            self._frame[0], ops.n, ops.kind, ops.y_site, ops.y_delta, ops.x_site, ops.x_delta,
            self._y_used, self._x_used,
        )  # fmt: skip
