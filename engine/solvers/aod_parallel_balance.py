"""Horizontal phase of the AOD-parallel planner: give every target column enough atoms, by hops (a bucket
brigade along rows) or row relays, whichever needs fewer slots. Frame and records: ``aod_parallel_records``."""

from __future__ import annotations

import numpy as np
from numba import njit

from engine.solvers.aod_parallel_records import (
    K_HOP,
    OK,
    OVERFLOW,
    STUCK,
    _close_batch,
    _flat,
    _put_tone,
)


@njit(cache=True, nogil=True)
def _sort_desc(idx: np.ndarray, n: int, score: np.ndarray) -> None:
    """Sort ``idx[:n]`` in place by descending ``score[idx]`` (insertion sort: a handful of candidates)."""
    for i in range(1, n):
        v = idx[i]
        s = score[v]
        j = i - 1
        while j >= 0 and score[idx[j]] < s:
            idx[j + 1] = idx[j]
            j -= 1
        idx[j + 1] = v

@njit(cache=True, nogil=True)
def _relay_cost(g: np.ndarray, a: int, c: int, r: int) -> int:
    """Slots of a row relay from column ``a`` to ``c`` along row ``r`` (2 + the longest gap the atoms on
    the way have to close), or -1 if ``(r, a)`` holds no atom or ``(r, c)`` is not free."""
    if not g[a, r] or g[c, r]:
        return -1
    s = 1 if c > a else -1
    last = a
    gap = 0
    x = a + s
    while x != c:
        if g[x, r]:
            d = x - last if s > 0 else last - x
            if d > gap:
                gap = d
            last = x
        x += s
    d = c - last if s > 0 else last - c
    if d > gap:
        gap = d
    return gap + 2


@njit(cache=True, nogil=True)
def _relay(
    g: np.ndarray, a: int, c: int, r: int, cand: np.ndarray, transposed: bool, nx_real: int,
    bmeta: np.ndarray, nb: int, brow: np.ndarray, brs: np.ndarray, brm: np.ndarray, nrr: int,
    bcol: np.ndarray, bcs: np.ndarray, bcm: np.ndarray, ncr: int, steps: np.ndarray, n_steps: int,
) -> tuple[int, int, int, int]:
    """One batch that moves an atom's worth from column ``a`` to column ``c`` along row ``r``: every atom on
    the way (from ``a``) moves to the next one's trap, the last into ``(r, c)``. All tones start together and
    each stops where its successor started, so tones never meet and every trap entered is free or was just
    left; the columns in between keep their occupancy. Returns new counts, nb = -1 on overflow."""
    s = 1 if c > a else -1
    m = 0
    x = a
    while x != c:
        if g[x, r]:
            cand[m] = x
            m += 1
        x += s
    dist = c - a if s > 0 else a - c
    if nb >= bmeta.shape[0] or nrr + 1 > brow.shape[0] or ncr + m > bcol.shape[0]:
        return -1, nrr, ncr, n_steps
    if n_steps + dist > steps.shape[0]:
        return -1, nrr, ncr, n_steps
    first_row, first_col = nrr, ncr
    nrr = _put_tone(brow, brs, brm, nrr, r, 0, 0)
    dmax = 0
    for q in range(m):  # ascending column order
        i = q if s > 0 else m - 1 - q
        nxt = cand[i + 1] if i + 1 < m else c
        d = nxt - cand[i] if s > 0 else cand[i] - nxt
        ncr = _put_tone(bcol, bcs, bcm, ncr, cand[i], s, d)
        if d > dmax:
            dmax = d
    _close_batch(bmeta, nb, first_row, nrr, first_col, ncr, dmax, K_HOP)
    for i in range(m - 1, -1, -1):  # the atom nearest the receiver first
        nxt = cand[i + 1] if i + 1 < m else c
        x = cand[i]
        while x != nxt:
            steps[n_steps, 0] = _flat(x, r, transposed, nx_real)
            steps[n_steps, 1] = _flat(x + s, r, transposed, nx_real)
            n_steps += 1
            x += s
    g[a, r] = False
    g[c, r] = True
    return nb + 1, nrr, ncr, n_steps


@njit(cache=True, nogil=True)
def _balance(
    g: np.ndarray, nc: int, nr: int, r0: int, r1: int, c0: int, c1: int, cnt: np.ndarray, cand: np.ndarray,
    key: np.ndarray, carried: np.ndarray, transposed: bool, nx_real: int,
    bmeta: np.ndarray, nb: int, brow: np.ndarray, brs: np.ndarray, brm: np.ndarray, nrr: int,
    bcol: np.ndarray, bcs: np.ndarray, bcm: np.ndarray, ncr: int, steps: np.ndarray, n_steps: int,
) -> tuple[int, int, int, int, int]:
    """Give every target column at least ``r1 - r0`` atoms (status, nb, nrr, ncr, n_steps).

    Repeatedly the target column with the largest deficit takes atoms from the nearest column with atoms
    to spare (one that can reach it along some row). Two ways, whichever needs fewer slots:

    - hops (a bucket brigade): each batch picks some atoms of one column (one x tone and their rows' y
      tones, so nothing else is picked up) and carries them along their rows as far as every one of them
      has free traps, preferring the atoms just carried in (the columns in between keep their own atoms),
      reservoir atoms of the donor and target rows of the receiver;
    - row relays (``_relay``): one batch per atom, any distance, columns in between untouched."""
    h_rows = r1 - r0
    for c in range(nc):
        n = 0
        for r in range(nr):
            if g[c, r]:
                n += 1
        cnt[c] = n
    guard = 0
    while True:
        recv = int(-1)  # noqa: UP018  # a call, not a literal: see plan_rect's counters
        worst = 0
        for x in range(c0, c1):
            d = h_rows - cnt[x]
            if d > worst:
                worst = d
                recv = x
        if recv < 0:
            return OK, nb, nrr, ncr, n_steps
        guard += 1
        if guard > 4 * nc * nr:
            return STUCK, nb, nrr, ncr, n_steps
        # nearest donor that has a relay row to the receiver (ties: more to spare)
        donor = -1
        best_dist = 1 << 30
        best_sur = 0
        for x in range(nc):
            sur = cnt[x] - h_rows if c0 <= x < c1 else cnt[x]
            if sur <= 0 or x == recv:
                continue
            dist = x - recv if x > recv else recv - x
            if dist > best_dist or (dist == best_dist and sur <= best_sur):
                continue
            ok = False
            for r in range(nr):
                if g[x, r] and not g[recv, r]:
                    ok = True
                    break
            if ok:
                donor = x
                best_dist = dist
                best_sur = sur
        if donor >= 0:
            m = min(worst, best_sur)
            s = 1 if recv > donor else -1
            # relay plan: the m cheapest rows (target rows of the receiver first on ties)
            n_rel = 0
            for r in range(nr):
                cost = _relay_cost(g, donor, recv, r)
                if cost > 0:
                    key[r] = cost * 2 + (0 if r0 <= r < r1 else 1)
                    cand[n_rel] = r
                    n_rel += 1
            for i in range(1, n_rel):  # ascending cost
                v = cand[i]
                q = i - 1
                while q >= 0 and key[cand[q]] > key[v]:
                    cand[q + 1] = cand[q]
                    q -= 1
                cand[q + 1] = v
            n_rel = min(n_rel, m)
            relay_slots = 0
            for i in range(n_rel):
                relay_slots += key[cand[i]] >> 1
            hop_slots = 3 * best_dist  # at best one 3-slot hop per column
            if n_rel == m and relay_slots <= hop_slots:
                for i in range(n_rel):
                    carried[i] = cand[i]
                for i in range(n_rel):
                    nb, nrr, ncr, n_steps = _relay(
                        g, donor, recv, carried[i], cand, transposed, nx_real,
                        bmeta, nb, brow, brs, brm, nrr, bcol, bcs, bcm, ncr, steps, n_steps,
                    )  # fmt: skip
                    if nb < 0:
                        return OVERFLOW, nb, nrr, ncr, n_steps
                cnt[donor] -= n_rel
                cnt[recv] += n_rel
                continue
            j = donor
            for r in range(nr):
                carried[r] = 0
            while j != recv and m > 0:
                remaining = recv - j if recv > j else j - recv
                n_cand = 0
                for r in range(nr):
                    if g[j, r] and not g[j + s, r]:
                        ln = 1
                        while ln < remaining and not g[j + (ln + 1) * s, r]:
                            ln += 1
                        bonus = 0
                        if carried[r]:
                            bonus += 4
                        if ln == remaining and r0 <= r < r1:
                            bonus += 2
                        if j == donor and not (r0 <= r < r1):
                            bonus += 1
                        key[r] = ln * 8 + bonus
                        cand[n_cand] = r
                        n_cand += 1
                if n_cand == 0:
                    # this hop is blocked: bring the rest by relays on the next round (the receiver still lacks)
                    break
                _sort_desc(cand, n_cand, key)
                take = min(m, n_cand)
                d = remaining
                for i in range(take):
                    ln = key[cand[i]] >> 3
                    if ln < d:
                        d = ln
                for i in range(1, take):  # ascending rows for the tone list
                    v = cand[i]
                    q = i - 1
                    while q >= 0 and cand[q] > v:
                        cand[q + 1] = cand[q]
                        q -= 1
                    cand[q + 1] = v
                if nb >= bmeta.shape[0] or nrr + take > brow.shape[0] or ncr + 1 > bcol.shape[0]:
                    return OVERFLOW, nb, nrr, ncr, n_steps
                if n_steps + take * d > steps.shape[0]:
                    return OVERFLOW, nb, nrr, ncr, n_steps
                first_row, first_col = nrr, ncr
                for i in range(take):
                    nrr = _put_tone(brow, brs, brm, nrr, cand[i], 0, 0)
                ncr = _put_tone(bcol, bcs, bcm, ncr, j, s, d)
                _close_batch(bmeta, nb, first_row, nrr, first_col, ncr, d, K_HOP)
                nb += 1
                for t in range(d):
                    for i in range(take):
                        r = cand[i]
                        steps[n_steps, 0] = _flat(j + t * s, r, transposed, nx_real)
                        steps[n_steps, 1] = _flat(j + (t + 1) * s, r, transposed, nx_real)
                        n_steps += 1
                for r in range(nr):
                    carried[r] = 0
                for i in range(take):
                    r = cand[i]
                    g[j, r] = False
                    g[j + d * s, r] = True
                    carried[r] = 1
                cnt[j] -= take
                cnt[j + d * s] += take
                j += d * s
                m = take
            if j == recv:
                continue
        # no straight row (no donor): a vertical move in a donor first; a blocked chain: the next round
        # prefers a relay (hops into this receiver failed)
        nb, nrr, ncr, n_steps, ok = _relay_one(
            g, cnt, nr, recv, h_rows, c0, c1, nc, cand, transposed, nx_real,
            bmeta, nb, brow, brs, brm, nrr, bcol, bcs, bcm, ncr, steps, n_steps,
        )  # fmt: skip
        if nb < 0:
            return OVERFLOW, nb, nrr, ncr, n_steps
        if not ok:
            return STUCK, nb, nrr, ncr, n_steps


@njit(cache=True, nogil=True)
def _relay_one(
    g: np.ndarray, cnt: np.ndarray, nr: int, recv: int, h_rows: int, c0: int, c1: int, nc: int,
    cand: np.ndarray, transposed: bool, nx_real: int,
    bmeta: np.ndarray, nb: int, brow: np.ndarray, brs: np.ndarray, brm: np.ndarray, nrr: int,
    bcol: np.ndarray, bcs: np.ndarray, bcm: np.ndarray, ncr: int, steps: np.ndarray, n_steps: int,
) -> tuple[int, int, int, int, bool]:
    """The cheapest single relay into ``recv`` from any column with atoms to spare (ok = False if none)."""
    best = -1
    best_a = int(-1)  # noqa: UP018  # a call, not a literal: see plan_rect's counters
    best_r = int(-1)  # noqa: UP018  # (the same)
    for a in range(nc):
        sur = cnt[a] - h_rows if c0 <= a < c1 else cnt[a]
        if sur <= 0 or a == recv:
            continue
        for r in range(nr):
            cost = _relay_cost(g, a, recv, r)
            if cost > 0 and (best < 0 or cost < best):
                best = cost
                best_a = a
                best_r = r
    if best < 0:
        # every free trap of the receiver is free in the donor too: first move one donor atom straight
        # along its column (no atom in between: it is the nearest one) into such a row, then relay
        for a in range(nc):
            sur = cnt[a] - h_rows if c0 <= a < c1 else cnt[a]
            if sur <= 0 or a == recv:
                continue
            da = a - recv if a > recv else recv - a
            db = best_a - recv if best_a > recv else recv - best_a
            if best_a < 0 or da < db:
                best_a = a
        if best_a < 0:
            return nb, nrr, ncr, n_steps, False
        a = best_a
        best = -1
        y_best = -1
        for r in range(nr):
            if g[recv, r] or g[a, r]:
                continue
            for y in range(nr):
                if g[a, y]:
                    d = y - r if y > r else r - y
                    clear = True
                    lo = min(y, r) + 1
                    hi = max(y, r)
                    for q in range(lo, hi):
                        if g[a, q]:
                            clear = False
                            break
                    if clear and (best < 0 or d < best):
                        best = d
                        best_r = r
                        y_best = y
        if best < 0:
            return nb, nrr, ncr, n_steps, False
        if nb >= bmeta.shape[0] or nrr + 1 > brow.shape[0] or ncr + 1 > bcol.shape[0]:
            return -1, nrr, ncr, n_steps, True
        if n_steps + best > steps.shape[0]:
            return -1, nrr, ncr, n_steps, True
        sy = 1 if best_r > y_best else -1
        first_row, first_col = nrr, ncr
        nrr = _put_tone(brow, brs, brm, nrr, y_best, sy, best)
        ncr = _put_tone(bcol, bcs, bcm, ncr, a, 0, 0)
        _close_batch(bmeta, nb, first_row, nrr, first_col, ncr, best, K_HOP)
        nb += 1
        y = y_best
        while y != best_r:
            steps[n_steps, 0] = _flat(a, y, transposed, nx_real)
            steps[n_steps, 1] = _flat(a, y + sy, transposed, nx_real)
            n_steps += 1
            y += sy
        g[a, y_best] = False
        g[a, best_r] = True
    nb, nrr, ncr, n_steps = _relay(
        g, best_a, recv, best_r, cand, transposed, nx_real,
        bmeta, nb, brow, brs, brm, nrr, bcol, bcs, bcm, ncr, steps, n_steps,
    )  # fmt: skip
    if nb >= 0:
        cnt[best_a] -= 1
        cnt[recv] += 1
    return nb, nrr, ncr, n_steps, True
