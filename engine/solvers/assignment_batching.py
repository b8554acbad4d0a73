"""Parallel batching of single-atom hops and row/column relays (numba): many share one product set.

Input: hops in a valid *sequential* order (each runs over traps that are empty when its turn comes, as the
assignment planner's chains do), each a path of one-site steps from its source to its destination, grouped:
a *relay* is the run of a chain's hops along one row (or column), every atom moving to where the next one
starts; it shares one row (column) tone, so its atoms are exactly its product set, and all its atoms move
at once (each tone stops where its successor started, so tones never meet).

A batch takes groups whose atoms sit in **distinct rows and distinct columns** across groups: the product
set of all their tones then holds exactly those atoms (the other crossings must be empty traps at every
slot, checked: crossed AODs make a tweezer there too, which would capture an atom it arrives over).
Each slot every atom takes the next step of its path (its row tone moves for a vertical step, its column
tone for a horizontal one, never both), so a batch lasts 2 + the longest path. It is legal when

- across groups, row tones keep their order at every slot, and so do column tones (no crossing or merging),
  which also keeps two atoms of different groups out of each other's row and column, so they never meet;
- every trap a path enters is empty now or is the source of an atom in the batch (extracted), and no two
  hops end in the same trap;
- the group may run before the earlier groups it overtakes: its traps (sources, paths, destinations) are
  not touched by any of them.

Groups are taken greedily in order: a batch starts with the first group not yet run and adds every later
group (within a look-ahead window) that fits and does not make the batch longer than ``extend`` extra
slots. One-site steps are listed slot by slot, each relay front atom first, which is a valid sequential
order (atoms of different groups are never adjacent, and a source is left in the first slot).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from engine.operations import SHIFT, batch_slot_kind, make_room

__all__ = ["batch_hops", "count_batched_slots"]


@njit(cache=True, nogil=True)
def _pair_ok(a: int, b: int, hop_ptr: np.ndarray, cells: np.ndarray, occ: np.ndarray) -> bool:
    """Atoms of hops ``a`` and ``b`` (different groups) can share a product set: distinct rows and columns
    kept in the same order at every slot, and empty traps under the two crossings of their tones at every
    slot (the crossings are tweezers too: at the start one would pick up an atom, later an empty one would
    capture it). ``occ`` is the occupancy before the batch (a lifted source counts as occupied: safe)."""
    pa = hop_ptr[a]
    la = hop_ptr[a + 1] - pa - 1
    pb = hop_ptr[b]
    lb = hop_ptr[b + 1] - pb - 1
    ra = cells[pa, 0]
    ca = cells[pa, 1]
    rb = cells[pb, 0]
    cb = cells[pb, 1]
    if ra == rb or ca == cb or occ[ra, cb] or occ[rb, ca]:
        return False
    sr = ra > rb
    sc = ca > cb
    for t in range(1, max(la, lb) + 1):
        ra_t = cells[pa + min(t, la), 0]
        ca_t = cells[pa + min(t, la), 1]
        rb_t = cells[pb + min(t, lb), 0]
        cb_t = cells[pb + min(t, lb), 1]
        dr = ra_t - rb_t
        dc = ca_t - cb_t
        if dr == 0 or dc == 0 or (dr > 0) != sr or (dc > 0) != sc or occ[ra_t, cb_t] or occ[rb_t, ca_t]:
            return False
    return True


@njit(cache=True, nogil=True)
def batch_hops(
    occ0: np.ndarray, hop_ptr: np.ndarray, n_hops: int, cells: np.ndarray, group_ptr: np.ndarray, n_groups: int,
    window: int, extend: int, occ: np.ndarray, done: np.ndarray, blocked: np.ndarray, src_mark: np.ndarray,
    dst_mark: np.ndarray, members: np.ndarray, batch_ptr: np.ndarray, batch_hop: np.ndarray,
) -> int:
    """Group the hops into batches: ``batch_hop[batch_ptr[b]:batch_ptr[b + 1]]`` are batch ``b``'s hops.
    Returns the number of batches (-1 if the hops are not in a valid sequential order).

    ``cells[hop_ptr[k]:hop_ptr[k + 1]]`` is hop ``k``'s path (row, col) from source to destination. Hops
    come in *groups* ``group_ptr[g]:group_ptr[g + 1]`` that always run together: a relay along one row
    (or column), every atom moving to where the next one starts, the front one first in the list; such a
    group shares one row (column) tone, so its atoms are exactly its product set. ``members`` holds the
    hops taken into the current batch; the scratch arrays are ``occ``-shaped, ``blocked`` holds the number
    (from 1) of the batch that last blocked a trap, so it is cleared once per call, not once per batch.
    A group is tested cheaply first (rows and columns where the batch's atoms start, its sources, the
    pairwise checks); only one that passes needs the traps of the groups turned down before it blocked,
    so they are marked then, not as each is turned down: in a filled band almost every group is turned down
    and marking each one's traps made the scan quadratic in traps. The batches are the same either way."""
    ny, nx = occ.shape
    row_used = np.zeros(ny, dtype=np.bool_)
    col_used = np.zeros(nx, dtype=np.bool_)
    failed = np.empty(max(n_groups, 1), dtype=np.int64)  # groups this batch turned down, in scan order
    occ[:, :] = occ0
    blocked[:, :] = 0
    for g in range(n_groups):
        done[g] = False
    n_batches = 0
    n_taken = 0
    first = 0
    batch_ptr[0] = 0
    while first < n_groups:
        while first < n_groups and done[first]:
            first += 1
        if first >= n_groups:
            break
        stamp = n_batches + 1
        n_failed = 0
        n_marked = 0
        n_mem = 0
        l_max = 0
        scanned = 0
        g = first
        while g < n_groups and scanned < window:
            if done[g]:
                g += 1
                continue
            scanned += 1
            h0 = group_ptr[g]
            h1 = group_ptr[g + 1]
            length = 0
            for k in range(h0, h1):
                length = max(length, hop_ptr[k + 1] - hop_ptr[k] - 1)
            fits = n_mem == 0 or length <= max(l_max, 1) + extend
            for k in range(h0, h1):  # the cheap tests first: rows and columns, the sources, the pairs
                if not fits:
                    break
                p0 = hop_ptr[k]
                if row_used[cells[p0, 0]] or col_used[cells[p0, 1]] or not occ[cells[p0, 0], cells[p0, 1]]:
                    fits = False
                for i in range(n_mem):
                    if not fits:
                        break
                    fits = _pair_ok(k, members[i], hop_ptr, cells, occ)
            if fits:  # block the traps of the groups turned down so far (lazily: most groups never get here)
                for i in range(n_marked, n_failed):
                    f = failed[i]
                    for p in range(hop_ptr[group_ptr[f]], hop_ptr[group_ptr[f + 1]]):
                        blocked[cells[p, 0], cells[p, 1]] = stamp
                n_marked = n_failed
            for k in range(h0, h1):  # footprint untouched by the earlier groups this batch overtakes
                if not fits:
                    break
                for p in range(hop_ptr[k], hop_ptr[k + 1]):
                    if blocked[cells[p, 0], cells[p, 1]] == stamp:
                        fits = False
                        break
            if fits:
                for k in range(h0, h1):
                    src_mark[cells[hop_ptr[k], 0], cells[hop_ptr[k], 1]] = True
                for k in range(h0, h1):
                    p1 = hop_ptr[k + 1]
                    for p in range(hop_ptr[k] + 1, p1):
                        r = cells[p, 0]
                        c = cells[p, 1]
                        if occ[r, c] and not src_mark[r, c]:
                            fits = False
                            break
                    if not fits or dst_mark[cells[p1 - 1, 0], cells[p1 - 1, 1]]:
                        fits = False
                        break
                if not fits:
                    for k in range(h0, h1):
                        src_mark[cells[hop_ptr[k], 0], cells[hop_ptr[k], 1]] = False
            if fits:
                for k in range(h0, h1):
                    members[n_mem] = k
                    n_mem += 1
                    p1 = hop_ptr[k + 1]
                    dst_mark[cells[p1 - 1, 0], cells[p1 - 1, 1]] = True
                    row_used[cells[hop_ptr[k], 0]] = True
                    col_used[cells[hop_ptr[k], 1]] = True
                if length > l_max:
                    l_max = length
                done[g] = True
            else:
                failed[n_failed] = g
                n_failed += 1
            g += 1
        if n_mem == 0:
            return -1  # the first group left cannot run: the hops were not in a valid sequential order
        for i in range(n_mem):
            j = members[i]
            p0 = hop_ptr[j]
            p1 = hop_ptr[j + 1]
            src_mark[cells[p0, 0], cells[p0, 1]] = False
            dst_mark[cells[p1 - 1, 0], cells[p1 - 1, 1]] = False
            row_used[cells[p0, 0]] = False
            col_used[cells[p0, 1]] = False
            occ[cells[p0, 0], cells[p0, 1]] = False
        for i in range(n_mem):
            j = members[i]
            p1 = hop_ptr[j + 1]
            occ[cells[p1 - 1, 0], cells[p1 - 1, 1]] = True
            batch_hop[n_taken] = j
            n_taken += 1
        n_batches += 1
        batch_ptr[n_batches] = n_taken
    return n_batches


@njit(cache=True, nogil=True)
def count_batched_slots(hop_ptr: np.ndarray, batch_ptr: np.ndarray, n_batches: int, batch_hop: np.ndarray) -> int:
    n = 0
    for b in range(n_batches):
        l_max = 0
        for i in range(batch_ptr[b], batch_ptr[b + 1]):
            k = batch_hop[i]
            l_max = max(l_max, hop_ptr[k + 1] - hop_ptr[k] - 1)
        n += l_max + 2
    return n



@njit(cache=True, nogil=True)
def _axis_tones(n, t, at, shift, m, order, hop_ptr, cells, axis, site, delta):
    """The tones of one axis (``axis`` 0: rows, 1: columns) of batch slot ``t`` into row ``n``: one tone per
    distinct starting row (column) of the hops in ``order``; returns how many."""
    count = 0
    for i in range(m):
        k = order[i]
        p0 = hop_ptr[k]
        if i > 0 and cells[p0, axis] == cells[hop_ptr[order[i - 1]], axis]:
            continue
        ln = hop_ptr[k + 1] - p0 - 1
        q = min(at, ln)
        site[n, count] = cells[p0 + q, axis]
        delta[n, count] = cells[p0 + q + 1, axis] - cells[p0 + q, axis] if (shift and t <= ln) else 0
        count += 1
    return count

@njit(cache=True, nogil=True)
def _sort_by_start(order: np.ndarray, m: int, hop_ptr: np.ndarray, cells: np.ndarray, axis: int) -> None:
    """Insertion-sort the hops ``order[:m]`` by their start cell's row (``axis`` 0) or column (1)."""
    for i in range(1, m):
        v = order[i]
        j = i - 1
        while j >= 0 and cells[hop_ptr[order[j]], axis] > cells[hop_ptr[v], axis]:
            order[j + 1] = order[j]
            j -= 1
        order[j + 1] = v


@njit(cache=True, nogil=True)
def emit_hop_batches(
    hop_ptr: np.ndarray, cells: np.ndarray, batch_ptr: np.ndarray, n_batches: int, batch_hop: np.ndarray,
    nx: int, order_r: np.ndarray, order_c: np.ndarray, n_prev: int,
    kind: np.ndarray, y_site: np.ndarray, y_delta: np.ndarray, x_site: np.ndarray, x_delta: np.ndarray,
    y_used: np.ndarray, x_used: np.ndarray, steps: np.ndarray,
) -> tuple[int, int]:
    """Write the batches as slots (after clearing the previous plan's ``n_prev``) and the one-site steps
    slot by slot. Returns (slots, steps), or (-needed slots, 0) if the table is too small."""
    need = count_batched_slots(hop_ptr, batch_ptr, n_batches, batch_hop)
    if not make_room(need, n_prev, kind, y_site, y_delta, x_site, x_delta, y_used, x_used):
        return -need, 0
    n = 0
    n_steps = 0
    for b in range(n_batches):
        a0 = batch_ptr[b]
        a1 = batch_ptr[b + 1]
        m = a1 - a0
        l_max = 0
        for i in range(a0, a1):
            k = batch_hop[i]
            l_max = max(l_max, hop_ptr[k + 1] - hop_ptr[k] - 1)
        # tone order per axis: the members sorted by source row / column (the order never changes)
        for i in range(m):
            order_r[i] = batch_hop[a0 + i]
            order_c[i] = batch_hop[a0 + i]
        _sort_by_start(order_r, m, hop_ptr, cells, 0)
        _sort_by_start(order_c, m, hop_ptr, cells, 1)
        for t in range(l_max + 2):
            kind[n] = batch_slot_kind(t, l_max)
            at = t - 1 if t > 0 else 0  # cell index at the start of this slot
            if t == l_max + 1:
                at = l_max
            # atoms of a relay along a row share its row tone (and along a column its column tone): the
            # only atoms that start in the same row (column) are such partners
            shift = kind[n] == SHIFT
            ny_t = _axis_tones(n, t, at, shift, m, order_r, hop_ptr, cells, 0, y_site, y_delta)
            nx_t = _axis_tones(n, t, at, shift, m, order_c, hop_ptr, cells, 1, x_site, x_delta)
            y_used[n] = ny_t
            x_used[n] = nx_t
            if kind[n] == SHIFT:
                for i in range(a0, a1):
                    k = batch_hop[i]
                    p0 = hop_ptr[k]
                    if t <= hop_ptr[k + 1] - p0 - 1:
                        steps[n_steps, 0] = cells[p0 + t - 1, 0] * nx + cells[p0 + t - 1, 1]
                        steps[n_steps, 1] = cells[p0 + t, 0] * nx + cells[p0 + t, 1]
                        n_steps += 1
            n += 1
    return n, n_steps
