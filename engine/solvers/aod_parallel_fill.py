"""Vertical phase of the AOD-parallel planner: on the balanced target columns, greedy shared-prefix Fill
batches (every row above a barrier down one, every row below another up one, in every column where that is
legal), or one compression batch per column. Frame and records: ``aod_parallel_records``."""

from __future__ import annotations

import numpy as np
from numba import njit

from engine.solvers.aod_parallel_records import (
    K_COLUMN,
    K_FILL,
    OK,
    OVERFLOW,
    _close_batch,
    _flat,
    _lowbit_index,
    _popcount,
    _put_tone,
)

# column state columns
_N, _K, _T, _B, _WTOP, _WBOT = 0, 1, 2, 3, 8, 9


@njit(cache=True, nogil=True)
def _atom_rows(g: np.ndarray, c: int, nr: int, pos: np.ndarray) -> int:
    """The rows of column ``c``'s atoms, ascending, into ``pos``; returns how many."""
    n = 0
    for r in range(nr):
        if g[c, r]:
            pos[n] = r
            n += 1
    return n


@njit(cache=True, nogil=True)
def _column_batch(
    g: np.ndarray, c: int, nr: int, r0: int, h_rows: int, k: int, pos: np.ndarray, transposed: bool, nx_real: int,
    bmeta: np.ndarray, nb: int, brow: np.ndarray, brs: np.ndarray, brm: np.ndarray, nrr: int,
    bcol: np.ndarray, bcs: np.ndarray, bcm: np.ndarray, ncr: int, steps: np.ndarray, n_steps: int,
) -> tuple[int, int, int, int]:
    """Compress column ``c`` in one batch: window atom ``k + i`` goes straight to row ``r0 + i`` (an order-
    preserving matching, so tones never meet and no path crosses a surplus atom, which stays). Each atom is
    picked up once. Returns the new counts, nb = -1 on overflow; records nothing if nothing moves."""
    _atom_rows(g, c, nr, pos)  # the window is atoms k .. k + h_rows - 1 of these
    n_move = 0
    dmax = 0
    n_dist = 0
    for i in range(h_rows):
        d = r0 + i - pos[k + i]
        if d != 0:
            n_move += 1
            d = d if d > 0 else -d
            n_dist += d
            if d > dmax:
                dmax = d
    if n_move == 0:
        return nb, nrr, ncr, n_steps
    if nb >= bmeta.shape[0] or nrr + n_move > brow.shape[0] or ncr + 1 > bcol.shape[0]:
        return -1, nrr, ncr, n_steps
    if n_steps + n_dist > steps.shape[0]:
        return -1, nrr, ncr, n_steps
    first_row, first_col = nrr, ncr
    for i in range(h_rows):
        d = r0 + i - pos[k + i]
        if d != 0:
            nrr = _put_tone(brow, brs, brm, nrr, pos[k + i], 1 if d > 0 else -1, d if d > 0 else -d)
    ncr = _put_tone(bcol, bcs, bcm, ncr, c, 0, 0)
    _close_batch(bmeta, nb, first_row, nrr, first_col, ncr, dmax, K_COLUMN)
    for i in range(h_rows - 1, -1, -1):  # down-movers bottom-first
        d = r0 + i - pos[k + i]
        for s in range(d):
            steps[n_steps, 0] = _flat(c, pos[k + i] + s, transposed, nx_real)
            steps[n_steps, 1] = _flat(c, pos[k + i] + s + 1, transposed, nx_real)
            n_steps += 1
    for i in range(h_rows):  # up-movers top-first
        d = pos[k + i] - (r0 + i)
        for s in range(d):
            steps[n_steps, 0] = _flat(c, pos[k + i] - s, transposed, nx_real)
            steps[n_steps, 1] = _flat(c, pos[k + i] - s - 1, transposed, nx_real)
            n_steps += 1
    for i in range(h_rows):
        g[c, pos[k + i]] = False
    for i in range(h_rows):
        g[c, r0 + i] = True
    return nb + 1, nrr, ncr, n_steps

@njit(cache=True, nogil=True, inline="always")
def _range_word(a: int, b: int, w: int) -> np.uint64:
    """Bits ``a..b-1`` that fall in word ``w`` (bit ``64 w + i`` is bit ``i`` of word ``w``)."""
    lo = a - 64 * w
    hi = b - 64 * w
    if lo < 0:
        lo = 0
    if hi > 64:
        hi = 64
    if hi <= lo:
        return np.uint64(0)
    if hi - lo == 64:
        return ~np.uint64(0)
    return ((np.uint64(1) << np.uint64(hi - lo)) - np.uint64(1)) << np.uint64(lo)


@njit(cache=True, nogil=True, inline="always")
def _flip_bits(d: np.uint64, w: int, arr: np.ndarray, c: int) -> None:
    """For every set bit ``i`` of ``d`` (row ``64 w + i``) toggle column ``c`` in ``arr[row]``."""
    cw = c >> 6
    cb = np.uint64(1) << np.uint64(c & 63)
    while d:
        arr[(w << 6) + _lowbit_index(d), cw] ^= cb
        d &= d - np.uint64(1)


@njit(cache=True, nogil=True, inline="always")
def _add_bits(d: np.uint64, w: int, score: np.ndarray, v: int) -> None:
    while d:
        score[(w << 6) + _lowbit_index(d)] += v
        d &= d - np.uint64(1)


@njit(cache=True, nogil=True)
def _col_update(
    c: int, nr: int, nwr: int, r0: int, r1: int, dyn: bool, ob: np.ndarray, prow: np.ndarray, st: np.ndarray,
    cm: np.ndarray, vt: np.ndarray, ut: np.ndarray, vb: np.ndarray, ub: np.ndarray, sct: np.ndarray, scb: np.ndarray,
    ptop: np.ndarray, pbot: np.ndarray,
) -> None:
    """Recompute column ``c``'s window and needs from its occupancy bits ``ob[c]`` and bring its entries in
    the per-barrier column sets and scores up to date (only the bits that changed are touched).

    Window: the ``H = r1 - r0`` consecutive atoms that fill the target rows in order, chosen to minimise
    (max(T, B), |T - B|) where T = how many rows the top window atom still has to come down (the number of
    top Fills the column needs) and B the same for the bottom. A top Fill at barrier h (rows < h move
    down) is legal iff the column has a hole at h (the tweezer of row h - 1 arrives there, and would collide
    with or capture an atom there whether it is loaded or not), harmless iff h <= LT (the first window atom
    that must not move down), useful iff also T > 0 and the top window atom is above h. Bottom likewise.
    ``cm[c] = (vt0, vt1, ut0, ut1, vb0, vb1, ub0, ub1)``: the column's current bits over barriers;
    ``prow[c, :n]`` its atoms' rows, ascending; ``nwr`` words per bit set (1 if nr <= 64)."""
    h_rows = r1 - r0
    pos = prow[c]
    n = st[c, _N]
    old_t = st[c, _WTOP]
    old_b = st[c, _WBOT]
    k = st[c, _K]
    if dyn or k < 0 or k > n - h_rows:
        best = 0
        best_key = -1
        for kk in range(n - h_rows + 1):
            t = r0 - pos[kk]
            b = pos[kk + h_rows - 1] - (r1 - 1)
            if t < 0:
                t = 0
            if b < 0:
                b = 0
            key = (max(t, b) << 20) + (t - b if t > b else b - t)  # then balanced sides pair better
            if best_key < 0 or key < best_key:
                best = kk
                best_key = key
        k = best
    st[c, _K] = k
    t = r0 - pos[k]
    b = pos[k + h_rows - 1] - (r1 - 1)
    t = t if t > 0 else 0
    b = b if b > 0 else 0
    st[c, _T] = t
    st[c, _B] = b
    wt = pos[k]
    wb = pos[k + h_rows - 1]
    # D_i = r0 + i - pos[k + i] does not increase with i: binary searches for the first D <= 0 (LT) and
    # the last D >= 0 (LB)
    lo = 0
    hi = h_rows
    while lo < hi:
        mid = (lo + hi) >> 1
        if r0 + mid - pos[k + mid] <= 0:
            hi = mid
        else:
            lo = mid + 1
    lt = pos[k + lo] if lo < h_rows else nr
    lo = 0
    hi = h_rows
    while lo < hi:
        mid = (lo + hi) >> 1
        if r0 + mid - pos[k + mid] >= 0:
            lo = mid + 1
        else:
            hi = mid
    lb = pos[k + lo - 1] if lo > 0 else -1
    top_hi = min(nr - 1, lt) + 1
    bot_lo = max(lb, 0)
    # the column's new bits over barriers, word 0 and (rows > 64) word 1
    vt0, ut0, vb0, ub0 = _col_bits(ob, c, 0, nr, top_hi, bot_lo, wt, wb, t, b)
    vt1 = ut1 = vb1 = ub1 = np.uint64(0)
    if nwr > 1:
        vt1, ut1, vb1, ub1 = _col_bits(ob, c, 1, nr, top_hi, bot_lo, wt, wb, t, b)
    # weights: a run that helps a column counts the column's need on that side (the columns with the most
    # left to do are the critical path)
    wtop = t
    wbot = b
    st[c, _WTOP] = wtop
    st[c, _WBOT] = wbot
    cw = c >> 6
    cb = np.uint64(1) << np.uint64(c & 63)
    dt = wtop ^ old_t
    db = wbot ^ old_b
    q = 0
    while dt or db:
        if dt & 1:
            ptop[q, cw] ^= cb
        if db & 1:
            pbot[q, cw] ^= cb
        dt >>= 1
        db >>= 1
        q += 1
    _col_apply(c, 0, vt0, ut0, vb0, ub0, wtop, wbot, old_t, old_b, cm, vt, ut, vb, ub, sct, scb)
    if nwr > 1:
        _col_apply(c, 1, vt1, ut1, vb1, ub1, wtop, wbot, old_t, old_b, cm, vt, ut, vb, ub, sct, scb)


@njit(cache=True, nogil=True, inline="always")
def _col_bits(
    ob: np.ndarray, c: int, w: int, nr: int, top_hi: int, bot_lo: int, wt: int, wb: int, t: int, b: int
) -> tuple[np.uint64, np.uint64, np.uint64, np.uint64]:
    """Word ``w`` of column ``c``'s legal+harmless / useful bits for top and bottom barriers."""
    # the tweezer of row h - 1 (top run) or h + 1 (bottom run) arrives over row h, loaded or empty (crossed
    # AODs make a tweezer at every intersection), so the run is legal only where row h has no atom
    hole = ~ob[c, w]
    n_vt = hole & _range_word(1, top_hi, w)
    n_ut = n_vt & _range_word(wt + 1, nr, w) if t > 0 else np.uint64(0)
    n_vb = hole & _range_word(bot_lo, nr - 1, w)
    n_ub = n_vb & _range_word(0, wb, w) if b > 0 else np.uint64(0)
    return n_vt, n_ut, n_vb, n_ub


@njit(cache=True, nogil=True, inline="always")
def _rescore(o_u: np.uint64, n_u: np.uint64, w: int, score: np.ndarray, old_weight: int, weight: int) -> None:
    """Word ``w``'s entries go from set ``o_u`` at ``old_weight`` to set ``n_u`` at ``weight`` in ``score``:
    every entry moves where the weight changed, else only those that joined or left the set."""
    if weight != old_weight:
        _add_bits(o_u, w, score, -old_weight)
        _add_bits(n_u, w, score, weight)
    else:
        _add_bits(o_u & ~n_u, w, score, -weight)
        _add_bits(n_u & ~o_u, w, score, weight)


@njit(cache=True, nogil=True, inline="always")
def _col_apply(
    c: int, w: int, n_vt: np.uint64, n_ut: np.uint64, n_vb: np.uint64, n_ub: np.uint64, wtop: int, wbot: int,
    old_t: int, old_b: int, cm: np.ndarray, vt: np.ndarray, ut: np.ndarray, vb: np.ndarray, ub: np.ndarray,
    sct: np.ndarray, scb: np.ndarray,
) -> None:
    """Bring word ``w`` of column ``c``'s entries in the per-barrier sets and scores up to date."""
    _flip_bits(n_vt ^ cm[c, w], w, vt, c)
    _flip_bits(n_vb ^ cm[c, 4 + w], w, vb, c)
    o_ut = cm[c, 2 + w]
    o_ub = cm[c, 6 + w]
    _flip_bits(n_ut ^ o_ut, w, ut, c)
    _flip_bits(n_ub ^ o_ub, w, ub, c)
    _rescore(o_ut, n_ut, w, sct, old_t, wtop)
    _rescore(o_ub, n_ub, w, scb, old_b, wbot)
    cm[c, w] = n_vt
    cm[c, 2 + w] = n_ut
    cm[c, 4 + w] = n_vb
    cm[c, 6 + w] = n_ub


@njit(cache=True, nogil=True, inline="always")
def _pair_score(
    h: int, hp: int, nwc: int, n_planes: int, vt: np.ndarray, ut: np.ndarray, vb: np.ndarray, ub: np.ndarray,
    ptop: np.ndarray, pbot: np.ndarray,
) -> int:
    """Weighted gain of the Fill pair (top barrier h, bottom barrier hp): every column legal and harmless
    for both runs and useful for one takes part; each useful run counts the column's weight on that side
    (summed with popcounts over the weights' bit planes ``ptop``/``pbot``)."""
    s = 0
    for w in range(nwc):
        a = ut[h, w]
        b = ub[hp, w]
        cs = vt[h, w] & vb[hp, w] & (a | b)
        xa = cs & a
        xb = cs & b
        for q in range(n_planes):
            s += (_popcount(xa & ptop[q, w]) + _popcount(xb & pbot[q, w])) << q
    return s


@njit(cache=True, nogil=True)
def _top_k(score: np.ndarray, lo: int, hi: int, idx: np.ndarray, val: np.ndarray, k: int) -> int:
    """Indices of the ``k`` largest positive ``score[lo:hi]``, best first (ties: the lower index)."""
    n = 0
    floor = 0
    for h in range(lo, hi):
        s = score[h]
        if s <= floor:
            continue
        j = n if n < k else k - 1
        while j > 0 and val[j - 1] < s:
            idx[j] = idx[j - 1]
            val[j] = val[j - 1]
            j -= 1
        idx[j] = h
        val[j] = s
        if n < k:
            n += 1
        if n == k:
            floor = val[k - 1]
    return n


@njit(cache=True, nogil=True)
def _fill_batch(
    ob: np.ndarray, prow: np.ndarray, st: np.ndarray, nr: int, h: int, hp: int, cols: np.ndarray, n_cols: int,
    transposed: bool, nx_real: int,
    bmeta: np.ndarray, nb: int, brow: np.ndarray, brs: np.ndarray, brm: np.ndarray, nrr: int,
    bcol: np.ndarray, bcs: np.ndarray, bcm: np.ndarray, ncr: int, steps: np.ndarray, n_steps: int, nwr: int,
) -> tuple[int, int, int, int]:
    """Record one Fill batch (rows above barrier ``h`` down one row, rows below ``hp`` up one row, in columns
    ``cols[:n_cols]``) and apply it. ``h = 0``: no top run; ``hp = nr - 1``: no bottom run.
    Returns the new counts (nb, nrr, ncr, n_steps), nb = -1 on overflow."""
    if nb >= bmeta.shape[0] or nrr + nr > brow.shape[0] or ncr + n_cols > bcol.shape[0]:
        return -1, nrr, ncr, n_steps
    first_row, first_col = nrr, ncr
    for w in range(nwr):
        rows = np.uint64(0)
        for i in range(n_cols):
            rows |= ob[cols[i], w]
        x = rows & (_range_word(0, h, w) | _range_word(hp + 1, nr, w))
        while x:
            r = (w << 6) + _lowbit_index(x)
            nrr = _put_tone(brow, brs, brm, nrr, r, 1 if r < h else -1, 1)
            x &= x - np.uint64(1)
    for i in range(n_cols):
        ncr = _put_tone(bcol, bcs, bcm, ncr, cols[i], 0, 0)
    _close_batch(bmeta, nb, first_row, nrr, first_col, ncr, 1, K_FILL)
    for i in range(n_cols):
        c = cols[i]
        pos = prow[c]
        n = st[c, _N]
        n_top = 0
        while n_top < n and pos[n_top] < h:
            n_top += 1
        first_bot = n
        while first_bot > 0 and pos[first_bot - 1] > hp:
            first_bot -= 1
        if n_steps + n_top + (n - first_bot) > steps.shape[0]:
            return -1, nrr, ncr, n_steps
        # top run bottom-first (each atom steps into a trap just left), bottom run top-first
        for q in range(n_top - 1, -1, -1):
            r = pos[q]
            steps[n_steps, 0] = _flat(c, r, transposed, nx_real)
            steps[n_steps, 1] = _flat(c, r + 1, transposed, nx_real)
            n_steps += 1
            pos[q] = r + 1
        for q in range(first_bot, n):
            r = pos[q]
            steps[n_steps, 0] = _flat(c, r, transposed, nx_real)
            steps[n_steps, 1] = _flat(c, r - 1, transposed, nx_real)
            n_steps += 1
            pos[q] = r - 1
        # shift the bits: rows < h down one, rows > hp up one
        o0 = ob[c, 0]
        o1 = ob[c, 1]
        t0 = o0 & _range_word(0, h, 0)
        t1 = o1 & _range_word(0, h, 1)
        b0 = o0 & _range_word(hp + 1, nr, 0)
        b1 = o1 & _range_word(hp + 1, nr, 1)
        k0 = o0 & ~(t0 | b0)
        k1 = o1 & ~(t1 | b1)
        ob[c, 0] = k0 | (t0 << np.uint64(1)) | (b0 >> np.uint64(1)) | (b1 << np.uint64(63))
        ob[c, 1] = k1 | (t1 << np.uint64(1)) | (t0 >> np.uint64(63)) | (b1 >> np.uint64(1))
    return nb + 1, nrr, ncr, n_steps


@njit(cache=True, nogil=True)
def _compress_alone(
    g: np.ndarray, ob: np.ndarray, c: int, nr: int, r0: int, h_rows: int, k: int, pos: np.ndarray,
    transposed: bool, nx_real: int, bmeta: np.ndarray, nb: int, brow: np.ndarray, brs: np.ndarray,
    brm: np.ndarray, nrr: int, bcol: np.ndarray, bcs: np.ndarray, bcm: np.ndarray, ncr: int, steps: np.ndarray,
    n_steps: int,
) -> tuple[int, int, int, int]:
    """Compress column ``c`` on its own (``_column_batch``), its occupancy read back from the bit rows ``ob``
    into ``g`` first: the fallback when the greedy stops helping."""
    for r in range(nr):
        g[c, r] = (ob[c, r >> 6] >> np.uint64(r & 63)) & np.uint64(1)
    return _column_batch(
        g, c, nr, r0, h_rows, k, pos, transposed, nx_real,
        bmeta, nb, brow, brs, brm, nrr, bcol, bcs, bcm, ncr, steps, n_steps,
    )  # fmt: skip


@njit(cache=True, nogil=True)
def _short_column(st: np.ndarray, lo: int, hi: int, first: bool) -> int:
    """A column of ``lo..hi-1`` that still needs top or bottom Fills: the first, or the neediest (the largest
    of the two needs, the first on ties); -1 if none."""
    pick = int(-1)  # noqa: UP018  # a call, not a literal: see plan_rect's counters
    for c in range(lo, hi):
        if st[c, _T] > 0 or st[c, _B] > 0:
            if first:
                return c
            if pick < 0 or max(st[c, _T], st[c, _B]) > max(st[pick, _T], st[pick, _B]):
                pick = c
    return pick


@njit(cache=True, nogil=True)
def _load_column(g: np.ndarray, c: int, nr: int, ob: np.ndarray, prow: np.ndarray, st: np.ndarray) -> None:
    """Occupancy bits, sorted atom rows and atom count of column ``c`` from ``g``."""
    ob[c, 0] = 0
    ob[c, 1] = 0
    n = 0
    for r in range(nr):
        if g[c, r]:
            ob[c, r >> 6] |= np.uint64(1) << np.uint64(r & 63)
            prow[c, n] = r
            n += 1
    st[c, _N] = n


@njit(cache=True, nogil=True)
def _fill_phase(
    g: np.ndarray, nr: int, r0: int, r1: int, c0: int, c1: int, dyn: bool, dedicated: bool, k_best: int,
    ob: np.ndarray, prow: np.ndarray, st: np.ndarray, pos: np.ndarray, cm: np.ndarray,
    vt: np.ndarray, ut: np.ndarray, vb: np.ndarray, ub: np.ndarray, sct: np.ndarray, scb: np.ndarray,
    it: np.ndarray, ib: np.ndarray, tv: np.ndarray, bv: np.ndarray, ptop: np.ndarray, pbot: np.ndarray,
    cols: np.ndarray, transposed: bool, nx_real: int,
    bmeta: np.ndarray, nb: int, brow: np.ndarray, brs: np.ndarray, brm: np.ndarray, nrr: int,
    bcol: np.ndarray, bcs: np.ndarray, bcm: np.ndarray, ncr: int, steps: np.ndarray, n_steps: int,
) -> tuple[int, int, int, int, int]:
    """Vertical phase on the balanced target columns ``c0..c1-1``: greedy Fill batches, each the barrier pair
    (or single barrier) with the largest need-weighted gain among the ``k_best`` best single barriers per
    side; with ``dedicated``, one compression batch per column instead. Returns (status, nb, nrr, ncr, n_steps)."""
    h_rows = r1 - r0
    nwr = 1 if nr <= 64 else 2
    nwc = 1 if c1 <= 64 else 2
    n_planes = 1
    while (1 << n_planes) <= nr:
        n_planes += 1
    for q in range(ptop.shape[0]):
        for w in range(2):
            ptop[q, w] = 0
            pbot[q, w] = 0
    for h in range(nr):
        sct[h] = 0
        scb[h] = 0
        for w in range(2):
            vt[h, w] = 0
            ut[h, w] = 0
            vb[h, w] = 0
            ub[h, w] = 0
    for c in range(c0, c1):
        if dedicated:
            nb, nrr, ncr, n_steps = _column_batch(
                g, c, nr, r0, h_rows, _best_window(g, c, nr, r0, r1, pos), pos, transposed, nx_real,
                bmeta, nb, brow, brs, brm, nrr, bcol, bcs, bcm, ncr, steps, n_steps,
            )  # fmt: skip
            if nb < 0:
                return OVERFLOW, nb, nrr, ncr, n_steps
            continue
        _load_column(g, c, nr, ob, prow, st)
        for q in range(8):
            cm[c, q] = 0
        st[c, _K] = -1
        st[c, _T] = 0
        st[c, _B] = 0
        st[c, _WTOP] = 0
        st[c, _WBOT] = 0
        # bool(True), not True: a literal argument would compile a copy of _col_update of its own (plan_rect)
        dyn_all = bool(True)  # noqa: UP018  # a call, not a literal
        _col_update(c, nr, nwr, r0, r1, dyn_all, ob, prow, st, cm, vt, ut, vb, ub, sct, scb, ptop, pbot)
    if dedicated:
        return OK, nb, nrr, ncr, n_steps
    # re-chosen windows make the greedy's progress hard to bound, so cap its batches; past the cap (never
    # reached on random fillings) every column still short is compressed on its own, which always finishes
    budget = 2 * nr * (c1 - c0) + 64
    alone_from = c0  # once the budget is spent: the columns from here on are compressed on their own, in turn
    while True:
        budget -= 1
        spent = budget < 0
        n_t = int(0)  # noqa: UP018  # a call, not a literal: see plan_rect's counters
        n_b = int(0)  # noqa: UP018  # (the same)
        if not spent:
            n_t = _top_k(sct, 1, nr, it, tv, k_best)
            n_b = _top_k(scb, 0, nr - 1, ib, bv, k_best)
        if n_t == 0 and n_b == 0:
            # no Fill helps anyone (not seen in practice), or the budget is spent: compress a short column on
            # its own, the neediest (the greedy then goes on), or once spent each short column in turn
            c = _short_column(st, alone_from, c1, spent)
            if c < 0:
                return OK, nb, nrr, ncr, n_steps
            nb, nrr, ncr, n_steps = _compress_alone(
                g, ob, c, nr, r0, h_rows, st[c, _K], pos, transposed, nx_real,
                bmeta, nb, brow, brs, brm, nrr, bcol, bcs, bcm, ncr, steps, n_steps,
            )  # fmt: skip
            if nb < 0:
                return OVERFLOW, nb, nrr, ncr, n_steps
            if spent:
                alone_from = c + 1
            else:
                _load_column(g, c, nr, ob, prow, st)
                _col_update(c, nr, nwr, r0, r1, dyn, ob, prow, st, cm, vt, ut, vb, ub, sct, scb, ptop, pbot)
            continue
        best = 0
        best_h = 0
        best_hp = nr - 1
        if n_t > 0:
            best = sct[it[0]]
            best_h = it[0]
        if n_b > 0 and scb[ib[0]] > best:
            best = scb[ib[0]]
            best_h = 0
            best_hp = ib[0]
        top_b = scb[ib[0]] if n_b > 0 else 0
        for i in range(n_t):
            h = it[i]
            if sct[h] + top_b <= best:
                break
            for j in range(n_b):
                hp = ib[j]
                if sct[h] + scb[hp] <= best:
                    break
                if hp <= h:
                    continue
                s = _pair_score(h, hp, nwc, n_planes, vt, ut, vb, ub, ptop, pbot)
                if s > best:
                    best = s
                    best_h = h
                    best_hp = hp
        n_cols = int(0)  # noqa: UP018  # a call, not a literal: see plan_rect's counters
        for w in range(nwc):
            if best_h > 0 and best_hp < nr - 1:
                x = vt[best_h, w] & vb[best_hp, w] & (ut[best_h, w] | ub[best_hp, w])
            elif best_h > 0:
                x = ut[best_h, w]
            else:
                x = ub[best_hp, w]
            while x:
                cols[n_cols] = (w << 6) + _lowbit_index(x)
                n_cols += 1
                x &= x - np.uint64(1)
        nb, nrr, ncr, n_steps = _fill_batch(
            ob, prow, st, nr, best_h, best_hp, cols, n_cols, transposed, nx_real,
            bmeta, nb, brow, brs, brm, nrr, bcol, bcs, bcm, ncr, steps, n_steps, nwr,
        )  # fmt: skip
        if nb < 0:
            return OVERFLOW, nb, nrr, ncr, n_steps
        for i in range(n_cols):
            _col_update(cols[i], nr, nwr, r0, r1, dyn, ob, prow, st, cm, vt, ut, vb, ub, sct, scb, ptop, pbot)


@njit(cache=True, nogil=True)
def _best_window(g: np.ndarray, c: int, nr: int, r0: int, r1: int, pos: np.ndarray) -> int:
    """First atom (sorted index) of column ``c``'s best window of ``r1 - r0`` consecutive atoms for a one-batch
    compression: the fewest shift slots (the largest displacement, max(T, B)), then the fewest steps."""
    h_rows = r1 - r0
    n = _atom_rows(g, c, nr, pos)
    best = 0
    best_key = -1
    for k in range(n - h_rows + 1):
        cost = 0
        for i in range(h_rows):
            d = pos[k + i] - r0 - i
            cost += d if d >= 0 else -d
        t = max(r0 - pos[k], 0)
        b = max(pos[k + h_rows - 1] - (r1 - 1), 0)
        key = (max(t, b) << 20) + cost
        if best_key < 0 or key < best_key:
            best = k
            best_key = key
    return best
