"""Turn move segments into crossed-AOD waveform slots (numba, writes an ``Operations`` table in place).

Every batch is EXTRACT, SHIFT slots, IMPLANT on one x tone (one column) and a set of y tones (rows):
the product set then holds exactly the atoms that move, so no bystander is picked up.

- ``wide=False`` (``red-rec``, the reference's column-block rule): in a vertical segment the atoms moving
  down form one batch and the atoms moving up another; every horizontal traveller is its own batch.
- ``wide=True`` (``red-rec-wide``): a vertical segment is one batch (down-movers shift +1, up-movers -1,
  each until it arrives), and all travellers of a horizontal segment move together.

Why this is legal: a vertical segment is an order-preserving matching, so a tone behind an arrived one
never reaches it (no merging) and no path crosses a static atom; down-movers lie above up-movers'
destinations and vice versa, so the two groups never meet. Horizontal travellers sit in distinct rows of
one column and their paths along reservoir rows are empty (``redrec_solve`` guarantees it). An arrived
tweezer keeps its atom with delta 0 until the batch's IMPLANT.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from engine.operations import SHIFT, batch_slot_kind, make_room
from engine.solvers.redrec_solve import HORIZONTAL

__all__ = ["batch_segments", "count_slots"]

_ALL = 0
_DOWN = 1
_UP = 2


@njit(cache=True, nogil=True, inline="always")
def _in_group(src: int, dst: int, group: int) -> bool:
    if group == _DOWN:
        return dst > src
    if group == _UP:
        return dst < src
    return dst != src


@njit(cache=True, nogil=True)
def _vertical_batch(
    c: int, mv: np.ndarray, m0: int, m1: int, group: int, n: int,
    kind: np.ndarray, y_site: np.ndarray, y_delta: np.ndarray, x_site: np.ndarray, x_delta: np.ndarray,
    y_used: np.ndarray, x_used: np.ndarray, scratch: np.ndarray,
) -> int:
    """One column batch of the movers ``mv[m0:m1]`` in ``group``; returns the next free slot.
    ``scratch`` rows: current row, steps left, direction of each tone."""
    cur = scratch[0]
    left = scratch[1]
    sign = scratch[2]
    m = 0
    dmax = 0
    for i in range(m0, m1):
        src = mv[i, 0]
        dst = mv[i, 1]
        if _in_group(src, dst, group):
            cur[m] = src
            left[m] = abs(dst - src)
            sign[m] = 1 if dst > src else -1
            dmax = max(dmax, left[m])
            m += 1
    if m == 0:
        return n
    for t in range(dmax + 2):
        ys = y_site[n]
        for j in range(m):
            ys[j] = cur[j]
        kind[n] = batch_slot_kind(t, dmax)
        if kind[n] == SHIFT:
            ds = y_delta[n]
            for j in range(m):
                d = sign[j] if left[j] > 0 else 0
                ds[j] = d
                cur[j] += d
                left[j] -= abs(d)
        y_used[n] = m
        x_site[n, 0] = c
        x_delta[n, 0] = 0
        x_used[n] = 1
        n += 1
    return n


@njit(cache=True, nogil=True)
def _horizontal_batch(
    d: int, r: int, mv: np.ndarray, m0: int, m1: int, n: int,
    kind: np.ndarray, y_site: np.ndarray, y_delta: np.ndarray, x_site: np.ndarray, x_delta: np.ndarray,
    y_used: np.ndarray, x_used: np.ndarray,
) -> int:
    """Travellers in rows ``mv[m0:m1, 0]`` (ascending) go together from column ``d`` to ``r``."""
    dist = abs(r - d)
    step = 1 if r > d else -1
    for t in range(dist + 2):
        kind[n] = batch_slot_kind(t, dist)
        for i in range(m0, m1):
            y_site[n, i - m0] = mv[i, 0]
            y_delta[n, i - m0] = 0
        y_used[n] = m1 - m0
        x_site[n, 0] = d + step * min(max(t - 1, 0), dist)
        x_delta[n, 0] = step if kind[n] == SHIFT else 0
        x_used[n] = 1
        n += 1
    return n


@njit(cache=True, nogil=True)
def count_slots(seg: np.ndarray, n_seg: int, mv: np.ndarray, wide: bool) -> int:
    """How many slots ``batch_segments`` will write (to size the table before writing)."""
    n = 0
    for s in range(n_seg):
        kind, a, b, m0, m1 = seg[s, 0], seg[s, 1], seg[s, 2], seg[s, 3], seg[s, 4]
        if kind == HORIZONTAL:
            n += (abs(b - a) + 2) * (1 if wide else m1 - m0)
            continue
        dn = 0
        up = 0
        for i in range(m0, m1):
            dn = max(dn, mv[i, 1] - mv[i, 0])
            up = max(up, mv[i, 0] - mv[i, 1])
        if wide:
            n += max(dn, up) + 2
        else:
            n += (dn + 2 if dn > 0 else 0) + (up + 2 if up > 0 else 0)
    return n


@njit(cache=True, nogil=True)
def batch_segments(
    seg: np.ndarray, n_seg: int, mv: np.ndarray, wide: bool, n_prev: int,
    kind: np.ndarray, y_site: np.ndarray, y_delta: np.ndarray, x_site: np.ndarray, x_delta: np.ndarray,
    y_used: np.ndarray, x_used: np.ndarray, scratch: np.ndarray,
) -> int:
    """Write the slots of all segments into the table; first resets the entries the previous plan wrote
    (``n_prev`` slots). Returns the number of slots, or minus the number needed if the table is too small
    (then nothing is written)."""
    need = count_slots(seg, n_seg, mv, wide)
    if not make_room(need, n_prev, kind, y_site, y_delta, x_site, x_delta, y_used, x_used):
        return -need
    n = 0
    for s in range(n_seg):
        k, a, b, m0, m1 = seg[s, 0], seg[s, 1], seg[s, 2], seg[s, 3], seg[s, 4]
        if k == HORIZONTAL:
            if wide:
                n = _horizontal_batch(a, b, mv, m0, m1, n, kind, y_site, y_delta, x_site, x_delta, y_used, x_used)
            else:
                for i in range(m0, m1):
                    n = _horizontal_batch(
                        a, b, mv, i, i + 1, n, kind, y_site, y_delta, x_site, x_delta, y_used, x_used
                    )
        elif wide:
            n = _vertical_batch(a, mv, m0, m1, _ALL, n, kind, y_site, y_delta, x_site, x_delta, y_used, x_used, scratch)
        else:
            n = _vertical_batch(
                a, mv, m0, m1, _DOWN, n, kind, y_site, y_delta, x_site, x_delta, y_used, x_used, scratch
            )
            n = _vertical_batch(
                a, mv, m0, m1, _UP, n, kind, y_site, y_delta, x_site, x_delta, y_used, x_used, scratch
            )
    return n
