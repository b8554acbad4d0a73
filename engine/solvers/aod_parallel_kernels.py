"""Entry kernels of the AOD-parallel planner (see ``aod_parallel`` for the idea and the planner class): the
target's rectangle, one instance planned (horizontal phase ``aod_parallel_balance``, then vertical phase
``aod_parallel_fill``), and the batches written as waveform slots. The internal frame and the batch records
are described in ``aod_parallel_records``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from engine.operations import SHIFT, batch_slot_kind, make_room
from engine.solvers.aod_parallel_balance import _balance
from engine.solvers.aod_parallel_fill import _fill_phase
from engine.solvers.aod_parallel_records import OK, OVERFLOW, STUCK, UNSOLVABLE

__all__ = ["OK", "UNSOLVABLE", "OVERFLOW", "STUCK", "emit_batches", "plan_rect", "find_rect"]


@njit(cache=True, nogil=True)
def find_rect(target: np.ndarray) -> tuple[int, int, int, int, int]:
    """``(r0, r1, c0, c1, ok)``: the bounding box of ``target`` and whether it is exactly that rectangle
    (ok = 1), has holes (0) or is empty (-1)."""
    ny, nx = target.shape
    r0 = ny
    r1 = -1
    c0 = nx
    c1 = -1
    n = 0
    for y in range(ny):
        for x in range(nx):
            if target[y, x]:
                n += 1
                if y < r0:
                    r0 = y
                if y > r1:
                    r1 = y
                if x < c0:
                    c0 = x
                if x > c1:
                    c1 = x
    if n == 0:
        return 0, 0, 0, 0, -1
    ok = 1 if n == (r1 - r0 + 1) * (c1 - c0 + 1) else 0
    return r0, r1 + 1, c0, c1 + 1, ok


@njit(cache=True, nogil=True)
def plan_rect(
    occ: np.ndarray, transposed: bool, r0: int, r1: int, c0: int, c1: int, dyn: bool, dedicated: bool,
    k_best: int, g: np.ndarray, cnt: np.ndarray, cand: np.ndarray, key: np.ndarray, carried: np.ndarray,
    ob: np.ndarray, prow: np.ndarray, st: np.ndarray, pos: np.ndarray, cm: np.ndarray,
    vt: np.ndarray, ut: np.ndarray, vb: np.ndarray, ub: np.ndarray,
    sct: np.ndarray, scb: np.ndarray, it: np.ndarray, ib: np.ndarray, tv: np.ndarray, bv: np.ndarray,
    ptop: np.ndarray, pbot: np.ndarray, cols: np.ndarray,
    bmeta: np.ndarray, brow: np.ndarray, brs: np.ndarray, brm: np.ndarray,
    bcol: np.ndarray, bcs: np.ndarray, bcm: np.ndarray, steps: np.ndarray,
) -> tuple[int, int, int, int]:
    """Plan one instance in the internal frame: (status, batches, one-site steps, waveform slots).

    ``occ`` is the array's ``bool[ny, nx]``; the target rectangle is given in internal coordinates."""
    ny, nx = occ.shape
    if transposed:
        nc, nr = ny, nx
        for c in range(nc):
            for r in range(nr):
                g[c, r] = occ[c, r]
    else:
        nc, nr = nx, ny
        for c in range(nc):
            for r in range(nr):
                g[c, r] = occ[r, c]
    total = 0
    for c in range(nc):
        for r in range(nr):
            if g[c, r]:
                total += 1
    if total < (r1 - r0) * (c1 - c0):
        return UNSOLVABLE, 0, 0, 0
    # The counters start as int(0), a call, not as literal 0s. numba types a literal as a type of its own
    # (Literal[int](0)), and while it infers a loop that grows a counter it meets the counter with that type
    # first and compiles a copy of every callee for it: ~30 s of the planner's cold compilation went to such
    # copies. Initialisers that reach a call (the -1s and 0s in _balance, _relay_one, _fill_phase) do the same.
    zero = int(0)  # noqa: UP018  # a call, not a literal
    status, nb, nrr, ncr, n_steps = _balance(
        g, nc, nr, r0, r1, c0, c1, cnt, cand, key, carried, transposed, nx,
        bmeta, zero, brow, brs, brm, zero, bcol, bcs, bcm, zero, steps, zero,
    )  # fmt: skip
    if status != OK:
        return status, 0, 0, 0
    status, nb, nrr, ncr, n_steps = _fill_phase(
        g, nr, r0, r1, c0, c1, dyn, dedicated, k_best, ob, prow, st, pos, cm, vt, ut, vb, ub, sct, scb, it, ib,
        tv, bv, ptop, pbot, cols, transposed, nx, bmeta, nb, brow, brs, brm, nrr, bcol, bcs, bcm, ncr, steps, n_steps,
    )  # fmt: skip
    if status != OK:
        return status, 0, 0, 0
    n_slots = 0
    for b in range(nb):
        n_slots += bmeta[b, 4] + 2
    return OK, nb, n_steps, n_slots



@njit(cache=True, nogil=True)
def _write_tones(n, t, shift, i0, i1, start, sign, moves, site, delta):
    """Tones ``i0..i1-1`` of batch slot ``t`` into row ``n``: each started at ``start[i]`` and moves one site
    per SHIFT slot in direction ``sign[i]`` for ``moves[i]`` slots, then waits. Returns the tone count."""
    for i in range(i0, i1):
        moved = min(t - 1, moves[i]) if t > 0 else 0
        if moved < 0:
            moved = 0
        site[n, i - i0] = start[i] + sign[i] * moved
        delta[n, i - i0] = sign[i] if (shift and t <= moves[i]) else 0
    return i1 - i0

@njit(cache=True, nogil=True)
def emit_batches(
    bmeta: np.ndarray, nb: int, brow: np.ndarray, brs: np.ndarray, brm: np.ndarray,
    bcol: np.ndarray, bcs: np.ndarray, bcm: np.ndarray, transposed: bool, n_prev: int,
    kind: np.ndarray, y_site: np.ndarray, y_delta: np.ndarray, x_site: np.ndarray, x_delta: np.ndarray,
    y_used: np.ndarray, x_used: np.ndarray,
) -> int:
    """Write the batches as waveform slots (EXTRACT, SHIFTs, IMPLANT) into an ``Operations`` table, after
    clearing the ``n_prev`` slots of the previous plan. Returns the number of slots, or minus the number
    needed if the table is too small (then nothing is written)."""
    need = 0
    for b in range(nb):
        need += bmeta[b, 4] + 2
    if not make_room(need, n_prev, kind, y_site, y_delta, x_site, x_delta, y_used, x_used):
        return -need
    n = 0
    for b in range(nb):
        a0, a1, b0, b1, n_shift = bmeta[b, 0], bmeta[b, 1], bmeta[b, 2], bmeta[b, 3], bmeta[b, 4]
        for t in range(n_shift + 2):
            kind[n] = batch_slot_kind(t, n_shift)
            # internal rows -> y (x if transposed), internal columns -> x (y if transposed)
            shift = kind[n] == SHIFT
            if transposed:
                x_used[n] = _write_tones(n, t, shift, a0, a1, brow, brs, brm, x_site, x_delta)
                y_used[n] = _write_tones(n, t, shift, b0, b1, bcol, bcs, bcm, y_site, y_delta)
            else:
                y_used[n] = _write_tones(n, t, shift, a0, a1, brow, brs, brm, y_site, y_delta)
                x_used[n] = _write_tones(n, t, shift, b0, b1, bcol, bcs, bcm, x_site, x_delta)
            n += 1
    return n
