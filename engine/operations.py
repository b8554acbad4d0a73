"""What the AODs do in each waveform slot, and a plan: the slots of one cycle plus the moves they realize.

The model (see ``docs/ARCHITECTURE.md``): crossed AODs make mobile tweezers at the product set of the
active y tones (rows) x the active x tones (columns). One waveform slot is one operation:

- ``EXTRACT``: the listed tones ramp up from zero over their sites; every atom in a static trap under a
  tweezer is taken into it.
- ``SHIFT``: every listed tone moves by its delta (-1, 0 or +1 site); tones keep their order and never merge.
  Every atom held by a tweezer moves with it.
- ``IMPLANT``: the listed tones ramp down to zero; held atoms are left in the static traps below.
- ``IDLE``: nothing moves (used for padding).

With ``trap_source = "aod"`` (a 1D chain made by one AOD) the static traps are themselves tones; a slot
is always a ``SHIFT`` whose listed x tones are the movers (conveyor-style block shifts) and whose single
y entry is row 0. The waveform stage adds the static tones of all other traps.

Tones are listed per axis by their site at the start of the slot, ascending, padded with -1, so the whole
table is a set of fixed-size numpy arrays that numba kernels can fill and read without allocating.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from numba import njit

__all__ = [
    "EXTRACT",
    "IDLE",
    "IMPLANT",
    "SHIFT",
    "OpKind",
    "Operations",
    "Plan",
    "batch_slot_kind",
    "clear_slots",
    "grown_table",
    "make_room",
    "write_slots",
]


class OpKind(IntEnum):
    IDLE = 0
    EXTRACT = 1
    SHIFT = 2
    IMPLANT = 3


IDLE, EXTRACT, SHIFT, IMPLANT = (int(k) for k in OpKind)


class Operations:
    """A growable table of waveform slots for an ``ny x nx`` array.

    Row ``i`` describes slot ``i``: ``kind[i]``, and per axis the start sites of the active tones
    (``y_site[i, :]``, ``x_site[i, :]``; ascending, -1 after the last) and their one-site deltas
    (``y_delta``, ``x_delta``). ``len(ops)`` is the number of waveform slots.

    ``half``: positions per site (``engine.routing``). 1: sites are traps (the lattice model). 2 (interstitial
    routing): ``nx`` and ``ny`` count positions, ``2 n - 1`` for ``n`` traps, the odd ones between traps, and a
    delta moves a tone half a site.
    """

    def __init__(self, *, nx: int, ny: int, capacity: int = 256, half: int = 1) -> None:
        self.nx = nx
        self.ny = ny
        self.half = half
        self.n = 0
        self._alloc(max(capacity, 1))

    def _alloc(self, capacity: int) -> None:
        self.kind = np.zeros(capacity, dtype=np.int8)
        self.y_site = np.full((capacity, self.ny), -1, dtype=np.int16)
        self.y_delta = np.zeros((capacity, self.ny), dtype=np.int8)
        self.x_site = np.full((capacity, self.nx), -1, dtype=np.int16)
        self.x_delta = np.zeros((capacity, self.nx), dtype=np.int8)

    @property
    def capacity(self) -> int:
        return self.kind.shape[0]

    def __len__(self) -> int:
        return self.n

    def clear(self) -> None:
        """Forget all slots, keeping the buffers (no allocation)."""
        self.y_site[: self.n] = -1
        self.y_delta[: self.n] = 0
        self.x_site[: self.n] = -1
        self.x_delta[: self.n] = 0
        self.kind[: self.n] = 0
        self.n = 0

    def reserve(self, capacity: int) -> None:
        """Grow the buffers to hold at least ``capacity`` slots (done when a configuration is applied)."""
        if capacity <= self.capacity:
            return
        old: tuple[np.ndarray, ...] = (self.kind, self.y_site, self.y_delta, self.x_site, self.x_delta)
        self._alloc(capacity)
        new: tuple[np.ndarray, ...] = (self.kind, self.y_site, self.y_delta, self.x_site, self.x_delta)
        for new_arr, old_arr in zip(new, old, strict=True):
            new_arr[: self.n] = old_arr[: self.n]

    def append(
        self,
        kind: int,
        y_sites: np.ndarray | list[int],
        x_sites: np.ndarray | list[int],
        y_deltas: np.ndarray | list[int] | None = None,
        x_deltas: np.ndarray | list[int] | None = None,
    ) -> None:
        """Add one slot (convenience for planners written in Python; numba planners fill the arrays)."""
        if self.n == self.capacity:
            self.reserve(2 * self.capacity)
        i = self.n
        ys = np.asarray(y_sites, dtype=np.int16)
        xs = np.asarray(x_sites, dtype=np.int16)
        self.kind[i] = kind
        self.y_site[i, : ys.size] = ys
        self.x_site[i, : xs.size] = xs
        if y_deltas is not None:
            self.y_delta[i, : ys.size] = np.asarray(y_deltas, dtype=np.int8)
        if x_deltas is not None:
            self.x_delta[i, : xs.size] = np.asarray(x_deltas, dtype=np.int8)
        self.n += 1

    def tones(self, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """``(y_sites, y_deltas, x_sites, x_deltas)`` of slot ``i`` as views without the padding."""
        ny_active = int(np.count_nonzero(self.y_site[i] >= 0))
        nx_active = int(np.count_nonzero(self.x_site[i] >= 0))
        return (
            self.y_site[i, :ny_active],
            self.y_delta[i, :ny_active],
            self.x_site[i, :nx_active],
            self.x_delta[i, :nx_active],
        )

    def describe(self, i: int) -> str:
        ys, dys, xs, dxs = self.tones(i)
        return (
            f"slot {i}: {OpKind(int(self.kind[i])).name} "
            f"y={list(zip(ys.tolist(), dys.tolist(), strict=True))} "
            f"x={list(zip(xs.tolist(), dxs.tolist(), strict=True))}"
        )


@dataclass
class Plan:
    """The solver's answer for one cycle.

    ``steps``: ``int32[m, 2]``, one row per one-site displacement of one atom (source and destination flat
    trap indices, row-major), in execution order. ``operations``: the waveform slots that realize them.
    """

    steps: np.ndarray
    operations: Operations
    algorithm: str = ""
    notes: dict[str, float] = field(default_factory=dict)

    @property
    def n_slots(self) -> int:
        return len(self.operations)

    @property
    def n_steps(self) -> int:
        return int(self.steps.shape[0])


def write_slots(ops: Operations, emit: Callable[[], int], grow: Callable[[int], None], *, solved: bool) -> None:
    """Write the last solve's plan into the reused table ``ops`` (a numba planner's ``batch``): ``emit()``
    returns the slots written, or minus the slots needed when the table is too small (nothing written,
    ``make_room``): then ``grow(need)`` and write again. ``solved``: whether there is a plan to write."""
    if not solved:
        raise RuntimeError("batch() needs a successful solve_moves() first")
    n = emit()
    if n < 0:
        grow(-n)
        n = emit()
    ops.n = n


def grown_table(ops: Operations, need: int) -> tuple[np.ndarray, np.ndarray]:
    """Rare: ``ops`` cleared and grown to twice ``need`` slots (a plan longer than the preallocated table;
    it allocates once, then stays), and fresh per-slot tone counts ``(y_used, x_used)`` to match it."""
    ops.clear()
    ops.reserve(2 * need)
    return np.zeros(ops.capacity, dtype=np.int64), np.zeros(ops.capacity, dtype=np.int64)


@njit(cache=True, nogil=True)
def batch_slot_kind(t: int, n_shift: int) -> int:
    """The kind of slot ``t`` of a batch with ``n_shift`` SHIFT slots: EXTRACT first, IMPLANT last, SHIFT
    between (every numba planner writes its batches in this order)."""
    if t == 0:
        return EXTRACT
    if t == n_shift + 1:
        return IMPLANT
    return SHIFT


@njit(cache=True, nogil=True)
def make_room(
    need: int, n_prev: int, kind: np.ndarray, y_site: np.ndarray, y_delta: np.ndarray, x_site: np.ndarray,
    x_delta: np.ndarray, y_used: np.ndarray, x_used: np.ndarray,
) -> bool:
    """Whether the table holds a plan of ``need`` slots; if it does, the previous plan's ``n_prev`` slots are
    cleared (``clear_slots``), else nothing is touched (the planner grows the table and writes again)."""
    if need > kind.shape[0]:
        return False
    clear_slots(n_prev, kind, y_site, y_delta, x_site, x_delta, y_used, x_used)
    return True


@njit(cache=True, nogil=True)
def clear_slots(
    n_prev: int, kind: np.ndarray, y_site: np.ndarray, y_delta: np.ndarray, x_site: np.ndarray,
    x_delta: np.ndarray, y_used: np.ndarray, x_used: np.ndarray,
) -> None:
    """Forget the previous plan's ``n_prev`` slots in place, touching only the tones they used (numba
    planners call this before writing a new plan into the same table, so no row is cleared twice)."""
    for i in range(n_prev):
        for j in range(y_used[i]):
            y_site[i, j] = -1
            y_delta[i, j] = 0
        for j in range(x_used[i]):
            x_site[i, j] = -1
            x_delta[i, j] = 0
        kind[i] = 0
        y_used[i] = 0
        x_used[i] = 0

