"""red-rec for a full-width target band: numba kernels that turn an occupancy grid into move segments.

The solve runs in three passes over preallocated buffers (see ``RedRecBuffers``):

1. **Pairing** (counts only). surplus[c] = atoms in column c - band height. While some column has a deficit,
   the adjacent pair of unbalanced columns with opposite signs that can exchange the most atoms is paired
   (ties: the closer pair, then the more balanced one) and that many atoms are booked from donor to
   receiver. Balanced columns drop out, so the columns between a paired donor and receiver are always
   balanced ones, which are compacted into the band by then: their reservoir rows are empty and the
   horizontal paths along reservoir rows are free.
2. **Selection**. For every transfer, which donor reservoir atoms travel. Within one reservoir side the
   atom closest to the band is always at least as good (the donor keeps its outer atoms at no extra
   total cost), so the only choice per atom is top or bottom; it is made greedily on the receiver's
   marginal cost (its own atoms slide down one row per atom arriving from the top). A receiver is
   normally left untouched until it is full and then compacted once; that needs every arrival to land
   on a reservoir trap that is empty in it. If a donor has no such atom the receiver is *pre-compacted*
   instead: its own atoms are packed into the band first (leaving room for the arrivals), and arrivals
   drop into the band right after each transfer.
3. **Emission**, in an order that is valid move by move: balanced columns compacted; then per transfer
   (pre-compaction, horizontal moves, arrivals dropped in) and every column compacted the moment it
   becomes balanced; donors with atoms to spare keep the best window of band-height consecutive atoms
   (exact for a contiguous band: an optimal kept set never skips an atom) at the end.

A **segment** is a set of moves that one batch can carry: ``VERTICAL`` (one column, order-preserving
moves ``src -> dst`` rows, ascending by ``src``) or ``HORIZONTAL`` (atoms in distinct rows of one donor
column travelling together to the receiver column). ``column_batching`` turns segments into waveform
slots; ``append_steps`` expands them into one-site steps.
"""

from __future__ import annotations

import numpy as np
from numba import njit

VERTICAL = 0
HORIZONTAL = 1

OK = 0
UNSOLVABLE = 1

__all__ = ["HORIZONTAL", "OK", "UNSOLVABLE", "VERTICAL", "append_steps", "band_rows", "redrec_segments", "solve_band"]


@njit(cache=True, nogil=True)
def _column_atoms(occ: np.ndarray, c: int) -> int:
    """Atoms in column ``c`` of ``occ``."""
    n = 0
    for y in range(occ.shape[0]):
        if occ[y, c]:
            n += 1
    return n


@njit(cache=True, nogil=True)
def band_rows(target: np.ndarray) -> tuple[int, int, int]:
    """``(lo, hi, problem)``: the band is rows ``lo..hi-1``; problem 0 = a full-width band, 1 = some row is
    partly filled, 2 = the full rows are not contiguous, 3 = no row is filled."""
    ny, nx = target.shape
    lo = -1
    hi = -1
    for y in range(ny):
        n = 0
        for x in range(nx):
            if target[y, x]:
                n += 1
        if n == 0:
            continue
        if n != nx:
            return y, y + 1, 1
        if lo < 0:
            lo = y
        elif hi != y:
            return lo, y, 2
        hi = y + 1
    if lo < 0:
        return 0, 0, 3
    return lo, hi, 0


@njit(cache=True, nogil=True, inline="always")
def _push_segment(seg: np.ndarray, n_seg: int, kind: int, a: int, b: int, m0: int, m1: int) -> int:
    if m1 > m0:
        seg[n_seg, 0] = kind
        seg[n_seg, 1] = a
        seg[n_seg, 2] = b
        seg[n_seg, 3] = m0
        seg[n_seg, 4] = m1
        n_seg += 1
    return n_seg


@njit(cache=True, nogil=True)
def _pack_column(
    work: np.ndarray, c: int, first: int, last: int, slot0: int, mv: np.ndarray, n_mv: int
) -> int:
    """Move the atoms of column ``c`` with sorted index ``first..last-1`` to rows ``slot0, slot0+1, ...``
    (order-preserving); append the movers ascending by source row and update ``work``."""
    ny = work.shape[0]
    m0 = n_mv
    i = 0
    for y in range(ny):
        if work[y, c]:
            if first <= i < last:
                dst = slot0 + i - first
                if dst != y:
                    mv[n_mv, 0] = y
                    mv[n_mv, 1] = dst
                    n_mv += 1
            i += 1
    for j in range(m0, n_mv):
        work[mv[j, 0], c] = False
    for j in range(m0, n_mv):
        work[mv[j, 1], c] = True
    return n_mv


@njit(cache=True, nogil=True)
def _best_window(work: np.ndarray, c: int, lo: int, hi: int, pos: np.ndarray) -> int:
    """Sorted index of the first atom of the cheapest window of ``hi - lo`` consecutive atoms of column ``c``."""
    ny = work.shape[0]
    k = 0
    for y in range(ny):
        if work[y, c]:
            pos[k] = y
            k += 1
    h = hi - lo
    best = 0
    best_cost = -1
    for first in range(k - h + 1):
        cost = 0
        for i in range(h):
            cost += abs(pos[first + i] - lo - i)
        if best_cost < 0 or cost < best_cost:
            best_cost = cost
            best = first
    return best


@njit(cache=True, nogil=True)
def _pair_columns(surplus: np.ndarray, nxt: np.ndarray, prv: np.ndarray, tr: np.ndarray) -> int:
    """Greedy donor/receiver pairing on column surpluses (mutated to all >= 0); fills ``tr[t] = (d, r, k, .)``."""
    nx = surplus.shape[0]
    head = -1
    last = -1
    for c in range(nx):
        nxt[c] = -1
        prv[c] = -1
        if surplus[c] != 0:
            if last < 0:
                head = c
            else:
                nxt[last] = c
                prv[c] = last
            last = c
    n_tr = 0
    while True:
        best_a = -1
        best_ex = 0
        best_dist = 0
        best_bal = 0
        a = head
        while a >= 0:
            b = nxt[a]
            if b >= 0 and (surplus[a] > 0) != (surplus[b] > 0):
                sa = abs(surplus[a])
                sb = abs(surplus[b])
                ex = min(sa, sb)
                dist = b - a
                bal = abs(sa - sb)
                if (
                    best_a < 0
                    or ex > best_ex
                    or (ex == best_ex and (dist < best_dist or (dist == best_dist and bal < best_bal)))
                ):
                    best_a = a
                    best_ex = ex
                    best_dist = dist
                    best_bal = bal
            a = b
        if best_a < 0:
            return n_tr
        b = nxt[best_a]
        d, r = (best_a, b) if surplus[best_a] > 0 else (b, best_a)
        tr[n_tr, 0] = d
        tr[n_tr, 1] = r
        tr[n_tr, 2] = best_ex
        n_tr += 1
        surplus[d] -= best_ex
        surplus[r] += best_ex
        for c in (best_a, b):
            if surplus[c] == 0:
                p = prv[c]
                q = nxt[c]
                if p >= 0:
                    nxt[p] = q
                else:
                    head = q
                if q >= 0:
                    prv[q] = p


@njit(cache=True, nogil=True)
def _own_slide_counts(work: np.ndarray, r: int, lo: int, deficit: int, out: np.ndarray) -> int:
    """For receiver ``r``: ``out[u]`` = how many of its own atoms sit at or above their row in the band when
    ``u`` atoms arrive from the top (so the marginal cost of the next top arrival to its own atoms is
    ``2 * out[u] - n``). Returns ``n``, its own atom count."""
    ny = work.shape[0]
    for u in range(deficit + 1):
        out[u] = 0
    i = 0
    for y in range(ny):
        if work[y, r]:
            q = y - lo - i
            if q <= deficit:
                out[max(q, 0)] += 1
            i += 1
    for u in range(1, deficit + 1):
        out[u] += out[u - 1]
    return i


@njit(cache=True, nogil=True)
def _select_atoms(
    occ: np.ndarray,
    lo: int,
    hi: int,
    tr: np.ndarray,
    n_tr: int,
    work: np.ndarray,
    rows: np.ndarray,
    recv: np.ndarray,
    slide: np.ndarray,
) -> None:
    """Choose the travelling rows of every transfer (``rows[tr[t, 3] : tr[t, 3] + tr[t, 2]]``) and each
    receiver's mode. ``recv[r, :6] = (started, precompact, top arrivals, bottom arrivals, own atoms, deficit)``."""
    ny, nx = occ.shape
    h = hi - lo
    work[:, :] = occ
    for c in range(nx):
        recv[c, :] = 0
    n_rows = 0
    for t in range(n_tr):
        d = tr[t, 0]
        r = tr[t, 1]
        k = tr[t, 2]
        tr[t, 3] = n_rows
        if recv[r, 0] == 0:
            recv[r, 0] = 1
            recv[r, 5] = h - _column_atoms(occ, r)
            recv[r, 4] = _own_slide_counts(occ, r, lo, recv[r, 5], slide[r])
        for _ in range(k):
            direct = recv[r, 1] == 0
            yt = -1
            for y in range(lo - 1, -1, -1):
                if work[y, d] and not (direct and work[y, r]):
                    yt = y
                    break
            yb = -1
            for y in range(hi, ny):
                if work[y, d] and not (direct and work[y, r]):
                    yb = y
                    break
            if yt < 0 and yb < 0:
                recv[r, 1] = 1  # no free landing trap: pre-compact this receiver
                for y in range(lo - 1, -1, -1):
                    if work[y, d]:
                        yt = y
                        break
                for y in range(hi, ny):
                    if work[y, d]:
                        yb = y
                        break
            u = recv[r, 2]
            v = recv[r, 3]
            take_top = yt >= 0
            if yt >= 0 and yb >= 0:
                cost_top = (lo - 1 - yt) + (u + 1) + 2 * slide[r, u] - recv[r, 4]
                cost_bottom = (yb - hi) + (v + 1)
                take_top = cost_top <= cost_bottom
            y = yt if take_top else yb
            if take_top:
                recv[r, 2] = u + 1
            else:
                recv[r, 3] = v + 1
            work[y, d] = False
            work[y, r] = True
            rows[n_rows] = y
            n_rows += 1
        # ascending rows, so the batch lists its tones in order
        a = tr[t, 3]
        for i in range(a + 1, n_rows):
            y = rows[i]
            j = i - 1
            while j >= a and rows[j] > y:
                rows[j + 1] = rows[j]
                j -= 1
            rows[j + 1] = y


@njit(cache=True, nogil=True)
def redrec_segments(
    occ: np.ndarray,
    lo: int,
    hi: int,
    work: np.ndarray,
    surplus: np.ndarray,
    nxt: np.ndarray,
    prv: np.ndarray,
    tr: np.ndarray,
    rows: np.ndarray,
    recv: np.ndarray,
    slide: np.ndarray,
    pos: np.ndarray,
    seg: np.ndarray,
    mv: np.ndarray,
) -> tuple[int, int, int]:
    """Solve one instance: ``(status, n_segments, n_movers)``; ``seg[i] = (kind, a, b, m0, m1)`` with movers
    ``mv[m0:m1]``. VERTICAL: column ``a``, ``mv = (src row, dst row)``. HORIZONTAL: from column ``a`` to
    column ``b``, ``mv = (row, row)``."""
    ny, nx = occ.shape
    h = hi - lo
    total = 0
    for c in range(nx):
        n = _column_atoms(occ, c)
        surplus[c] = n - h
        total += n
    if total < h * nx:
        return UNSOLVABLE, 0, 0
    n_tr = _pair_columns(surplus, nxt, prv, tr)
    _select_atoms(occ, lo, hi, tr, n_tr, work, rows, recv, slide)

    # emission, in execution order
    work[:, :] = occ
    n_seg = 0
    n_mv = 0
    for c in range(nx):
        n = _column_atoms(occ, c)
        surplus[c] = n - h
        if n == h:
            m0 = n_mv
            n_mv = _pack_column(work, c, 0, h, lo, mv, n_mv)
            n_seg = _push_segment(seg, n_seg, VERTICAL, c, -1, m0, n_mv)
    for c in range(nx):
        recv[c, 0] = 0  # now: transfers into c emitted so far
        recv[c, 5] = 0  # now: top arrivals placed (pre-compacted receivers)
        recv[c, 6] = 0  # bottom arrivals placed
    for t in range(n_tr):
        d = tr[t, 0]
        r = tr[t, 1]
        k = tr[t, 2]
        a = tr[t, 3]
        precompact = recv[r, 1] == 1
        top_total = recv[r, 2]
        n_own = recv[r, 4]
        if precompact and recv[r, 0] == 0:
            m0 = n_mv
            n_mv = _pack_column(work, r, 0, n_own, lo + top_total, mv, n_mv)
            n_seg = _push_segment(seg, n_seg, VERTICAL, r, -1, m0, n_mv)
        recv[r, 0] += 1
        m0 = n_mv
        for i in range(a, a + k):
            y = rows[i]
            mv[n_mv, 0] = y
            mv[n_mv, 1] = y
            n_mv += 1
            work[y, d] = False
            work[y, r] = True
        n_seg = _push_segment(seg, n_seg, HORIZONTAL, d, r, m0, n_mv)
        if precompact:
            n_top = 0
            for i in range(a, a + k):
                if rows[i] < lo:
                    n_top += 1
            m0 = n_mv
            j = 0
            for i in range(a, a + k):
                y = rows[i]
                mv[n_mv, 0] = y
                if y < lo:
                    mv[n_mv, 1] = lo + top_total - recv[r, 5] - n_top + j
                    j += 1
                else:
                    mv[n_mv, 1] = lo + top_total + n_own + recv[r, 6]
                    recv[r, 6] += 1
                n_mv += 1
            recv[r, 5] += n_top
            for i in range(m0, n_mv):
                work[mv[i, 0], r] = False
            for i in range(m0, n_mv):
                work[mv[i, 1], r] = True
            n_seg = _push_segment(seg, n_seg, VERTICAL, r, -1, m0, n_mv)
        surplus[d] -= k
        surplus[r] += k
        if surplus[d] == 0:
            m0 = n_mv
            n_mv = _pack_column(work, d, 0, h, lo, mv, n_mv)
            n_seg = _push_segment(seg, n_seg, VERTICAL, d, -1, m0, n_mv)
        if surplus[r] == 0 and not precompact:
            m0 = n_mv
            n_mv = _pack_column(work, r, 0, h, lo, mv, n_mv)
            n_seg = _push_segment(seg, n_seg, VERTICAL, r, -1, m0, n_mv)
    for c in range(nx):
        if surplus[c] > 0:
            first = _best_window(work, c, lo, hi, pos)
            m0 = n_mv
            n_mv = _pack_column(work, c, first, first + h, lo, mv, n_mv)
            n_seg = _push_segment(seg, n_seg, VERTICAL, c, -1, m0, n_mv)
    return OK, n_seg, n_mv


@njit(cache=True, nogil=True)
def append_steps(seg: np.ndarray, n_seg: int, mv: np.ndarray, nx: int, steps: np.ndarray) -> int:
    """Expand segments into one-site steps (flat row-major indices) in a valid sequential order: in a
    column, atoms moving down go bottom-first and atoms moving up top-first; horizontal travellers one by one."""
    n = 0
    for s in range(n_seg):
        kind, a, b, m0, m1 = seg[s, 0], seg[s, 1], seg[s, 2], seg[s, 3], seg[s, 4]
        if kind == HORIZONTAL:
            step = 1 if b > a else -1
            for i in range(m0, m1):
                base = mv[i, 0] * nx
                x = a
                while x != b:
                    steps[n, 0] = base + x
                    steps[n, 1] = base + x + step
                    n += 1
                    x += step
            continue
        for i in range(m1 - 1, m0 - 1, -1):
            y = mv[i, 0]
            while y < mv[i, 1]:
                steps[n, 0] = y * nx + a
                steps[n, 1] = (y + 1) * nx + a
                n += 1
                y += 1
        for i in range(m0, m1):
            y = mv[i, 0]
            while y > mv[i, 1]:
                steps[n, 0] = y * nx + a
                steps[n, 1] = (y - 1) * nx + a
                n += 1
                y -= 1
    return n


@njit(cache=True, nogil=True)
def solve_band(
    occ: np.ndarray, lo: int, hi: int, work: np.ndarray, surplus: np.ndarray, nxt: np.ndarray,
    prv: np.ndarray, tr: np.ndarray, rows: np.ndarray, recv: np.ndarray, slide: np.ndarray,
    pos: np.ndarray, seg: np.ndarray, mv: np.ndarray, steps: np.ndarray,
) -> tuple[int, int, int]:
    """``redrec_segments`` then ``append_steps`` in one call: ``(status, n_segments, n_steps)``."""
    status, n_seg, _ = redrec_segments(occ, lo, hi, work, surplus, nxt, prv, tr, rows, recv, slide, pos, seg, mv)
    if status != OK:
        return status, 0, 0
    return status, n_seg, append_steps(seg, n_seg, mv, occ.shape[1], steps)
