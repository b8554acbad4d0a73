"""The repair planner's hot path in numba: pair costs, the assignment, L routes split into relays, merging.

``RepairPlanner`` plans a few holes between two images, on the engine's critical path: in Python + scipy it
took milliseconds (list building per hop, a scipy call, set unions per group). These kernels do the same
work over preallocated arrays, in the same order, so the plans are the same:

- ``pair_costs``: the ``[holes, free atoms]`` cost of each pair by objective (atoms on the L route with
  fewer atoms counted by prefix sums over the occupancy, as ``repair.route_atoms``);
- ``assign``: a minimum-cost assignment of holes to free atoms by shortest augmenting paths (Crouse's
  variant of Jonker-Volgenant, the algorithm ``scipy.optimize.linear_sum_assignment`` runs, with its
  tie-breaking); scipy stays its reference in the tests;
- ``route_pairs``: pairs by path length, each on the L route crossing fewer atoms, split at the atoms on it
  into hops nearest the hole first, straight runs along one line grouped as relays
  (``assignment._route``, ``_chain_hops``, ``_relay_groups``);
- ``merge_aligned``: straight single-hop groups that cover the same columns (rows) join an earlier such group
  when nothing in between touches their traps (``RepairPlanner._merge_aligned``).

``free_atoms_and_holes`` and ``assign`` serve the interstitial repair planner too (``interstitial.py``).

The output is the batching kernels' input: ``hop_ptr``, ``cells`` (row, col) and ``group_ptr``.
"""

from __future__ import annotations

import numpy as np
from numba import njit

__all__ = [
    "OBJECTIVE_CODES",
    "assign",
    "free_atoms_and_holes",
    "merge_aligned",
    "pair_costs",
    "plan_repair",
    "route_pairs",
]

#: ``RepairPlanner.objective`` -> the kernels' code
OBJECTIVE_CODES = {"slots": 0, "transfers": 1, "survival": 2}


@njit(cache=True, nogil=True)
def free_atoms_and_holes(
    occupancy: np.ndarray, target: np.ndarray, free: np.ndarray, holes: np.ndarray
) -> tuple[int, int]:
    """The free atoms (occupied outside the target) and the holes (empty in the target) as ``(row, col)``,
    row by row as ``np.argwhere`` lists them, into ``free`` and ``holes``; returns their counts."""
    ny, nx = occupancy.shape
    n_free = 0
    n_holes = 0
    for r in range(ny):
        for c in range(nx):
            if occupancy[r, c] and not target[r, c]:
                free[n_free, 0] = r
                free[n_free, 1] = c
                n_free += 1
            elif target[r, c] and not occupancy[r, c]:
                holes[n_holes, 0] = r
                holes[n_holes, 1] = c
                n_holes += 1
    return n_free, n_holes


@njit(cache=True, nogil=True)
def pair_costs(
    occ: np.ndarray, free: np.ndarray, n_free: int, holes: np.ndarray, n_holes: int, objective: int,
    per_transfer: float, per_step: float, per_slot_atom: float, row_cum: np.ndarray, col_cum: np.ndarray,
    cost: np.ndarray,
) -> None:
    """``cost[h, f]``: what filling hole ``h`` from free atom ``f`` risks (``objective`` 0: one-site steps, 1:
    atoms moved then steps, 2: expected atoms lost), computed as ``RepairPlanner._pair_costs`` does."""
    ny, nx = occ.shape
    atoms = 0
    for r in range(ny):
        row_cum[r, 0] = 0
        for c in range(nx):
            row_cum[r, c + 1] = row_cum[r, c] + occ[r, c]
            atoms += occ[r, c]
    for c in range(nx):
        col_cum[0, c] = 0
        for r in range(ny):
            col_cum[r + 1, c] = col_cum[r, c] + occ[r, c]
    max_steps = 0
    for h in range(n_holes):
        r1 = holes[h, 0]
        c1 = holes[h, 1]
        for f in range(n_free):
            r0 = free[f, 0]
            c0 = free[f, 1]
            steps = abs(r0 - r1) + abs(c0 - c1)
            max_steps = max(max_steps, steps)
            if objective == 0:
                cost[h, f] = steps
                continue
            lo_c = min(c0, c1)
            hi_c = max(c0, c1) + 1
            lo_r = min(r0, r1)
            hi_r = max(r0, r1) + 1
            # each segment counts its ends: take out the spare atom (occupied), the hole (empty) and the corner
            row_first = row_cum[r0, hi_c] - row_cum[r0, lo_c] + col_cum[hi_r, c1] - col_cum[lo_r, c1] - 1 - occ[r0, c1]
            col_first = col_cum[hi_r, c0] - col_cum[lo_r, c0] + row_cum[r1, hi_c] - row_cum[r1, lo_c] - 1 - occ[r1, c0]
            moved = 1.0 + min(row_first, col_first)
            if objective == 1:
                cost[h, f] = moved
            else:
                slots = steps + 2.0
                cost[h, f] = 2.0 * moved * per_transfer + steps * per_step + slots * atoms * per_slot_atom
    if objective == 1:  # fewest atoms moved, then the shortest
        for h in range(n_holes):
            for f in range(n_free):
                steps = abs(free[f, 0] - holes[h, 0]) + abs(free[f, 1] - holes[h, 1])
                cost[h, f] += steps / (max_steps + 1.0)


@njit(cache=True, nogil=True)
def assign(
    cost: np.ndarray, n_rows: int, n_cols: int, u: np.ndarray, v: np.ndarray, shortest: np.ndarray,
    path: np.ndarray, row4col: np.ndarray, col4row: np.ndarray, remaining: np.ndarray, in_sr: np.ndarray,
    in_sc: np.ndarray,
) -> bool:
    """Minimum-cost assignment of every row of ``cost[:n_rows, :n_cols]`` (``n_rows <= n_cols``) to a
    distinct column: ``col4row[i]``. Shortest augmenting paths with dual potentials ``u``, ``v``, one row
    added at a time; ``False`` if no finite assignment exists. The rest are scratch arrays of ``n_cols``
    (``in_sr``: ``n_rows``)."""
    for j in range(n_cols):
        v[j] = 0.0
        row4col[j] = -1
    for i in range(n_rows):
        u[i] = 0.0
        col4row[i] = -1
    for cur in range(n_rows):
        n_remaining = n_cols
        for it in range(n_cols):
            remaining[it] = n_cols - it - 1  # reverse order: a constant matrix gives the identity, as scipy
            shortest[it] = np.inf
            in_sc[it] = False
        for i in range(n_rows):
            in_sr[i] = False
        min_val = 0.0
        i = cur
        sink = -1
        while sink == -1:
            index = -1
            lowest = np.inf
            in_sr[i] = True
            for it in range(n_remaining):
                j = remaining[it]
                r = min_val + cost[i, j] - u[i] - v[j]
                if r < shortest[j]:
                    path[j] = i
                    shortest[j] = r
                # among equal costs take a free column: it ends the path (integer costs tie often)
                if shortest[j] < lowest or (shortest[j] == lowest and row4col[j] == -1):
                    lowest = shortest[j]
                    index = it
            min_val = lowest
            if min_val == np.inf:
                return False
            j = remaining[index]
            if row4col[j] == -1:
                sink = j
            else:
                i = row4col[j]
            in_sc[j] = True
            n_remaining -= 1
            remaining[index] = remaining[n_remaining]
        u[cur] += min_val
        for i in range(n_rows):
            if in_sr[i] and i != cur:
                u[i] += min_val - shortest[col4row[i]]
        for j in range(n_cols):
            if in_sc[j]:
                v[j] -= min_val - shortest[j]
        j = sink
        while True:
            i = path[j]
            row4col[j] = i
            k = col4row[i]
            col4row[i] = j
            j = k
            if i == cur:
                break
    return True


@njit(cache=True, nogil=True)
def _l_route(r0: int, c0: int, r1: int, c1: int, rows_first: bool, route: np.ndarray) -> int:
    """The L path from (r0, c0) to (r1, c1) into ``route``, both ends included: along the source's row first
    (``rows_first`` False: the columns change first) or along its column first. Returns its length."""
    n = 0
    route[n, 0] = r0
    route[n, 1] = c0
    n += 1
    r = r0
    c = c0
    for leg in range(2):
        vertical = (leg == 0) == rows_first
        d = (r1 - r) if vertical else (c1 - c)
        step = 1 if d > 0 else -1
        for _ in range(abs(d)):
            if vertical:
                r += step
            else:
                c += step
            route[n, 0] = r
            route[n, 1] = c
            n += 1
    return n


@njit(cache=True, nogil=True)
def route_pairs(
    occ: np.ndarray, free: np.ndarray, holes: np.ndarray, free_of_hole: np.ndarray, n_holes: int,
    order: np.ndarray, route: np.ndarray, route_alt: np.ndarray, hop_ptr: np.ndarray, cells: np.ndarray,
    group_ptr: np.ndarray,
) -> tuple[int, int]:
    """Each (free atom, hole) pair, shortest first (ties in hole order), on the L route that crosses fewer
    atoms (column change first on a tie), split at the atoms on it into hops, the one nearest the hole first;
    consecutive hops of a pair along one row (column) form a relay group. ``occ`` is updated as each pair
    lands. Returns (hops, groups); ``cells`` needs room for twice the total path length."""
    ny, nx = occ.shape
    n_len = nx + ny  # path lengths are below this: counting sort, stable like Python's sort
    counts = np.zeros(n_len + 1, dtype=np.int64)
    for h in range(n_holes):
        f = free_of_hole[h]
        counts[abs(free[f, 0] - holes[h, 0]) + abs(free[f, 1] - holes[h, 1]) + 1] += 1
    for d in range(n_len):
        counts[d + 1] += counts[d]
    for h in range(n_holes):
        f = free_of_hole[h]
        d = abs(free[f, 0] - holes[h, 0]) + abs(free[f, 1] - holes[h, 1])
        order[counts[d]] = h
        counts[d] += 1
    n_hops = 0
    n_groups = 0
    n_cells = 0
    hop_ptr[0] = 0
    group_ptr[0] = 0
    for k in range(n_holes):
        h = order[k]
        f = free_of_hole[h]
        r0, c0, r1, c1 = free[f, 0], free[f, 1], holes[h, 0], holes[h, 1]
        n = _l_route(r0, c0, r1, c1, False, route)
        atoms = 0
        for p in range(1, n - 1):
            atoms += occ[route[p, 0], route[p, 1]]
        _l_route(r0, c0, r1, c1, True, route_alt)
        atoms_alt = 0
        for p in range(1, n - 1):
            atoms_alt += occ[route_alt[p, 0], route_alt[p, 1]]
        path = route_alt if atoms_alt < atoms else route
        # hops from the last stop (nearest the hole) back to the source
        end = n - 1
        prev_axis = -1
        prev_line = -1
        for s in range(n - 2, -1, -1):
            if s > 0 and not occ[path[s, 0], path[s, 1]]:
                continue
            for p in range(s, end + 1):
                cells[n_cells, 0] = path[p, 0]
                cells[n_cells, 1] = path[p, 1]
                n_cells += 1
            hr0, hc0, hr1, hc1 = path[s, 0], path[s, 1], path[end, 0], path[end, 1]
            axis = 0 if hr0 == hr1 else (1 if hc0 == hc1 else -1)
            line = hr0 if axis == 0 else hc0
            if axis == -1 or axis != prev_axis or line != prev_line:
                n_groups += 1
            n_hops += 1
            hop_ptr[n_hops] = n_cells
            group_ptr[n_groups] = n_hops
            prev_axis = axis
            prev_line = line
            end = s
        occ[r0, c0] = False
        occ[r1, c1] = True
    return n_hops, n_groups


@njit(cache=True, nogil=True)
def _straight_key(hop_ptr: np.ndarray, cells: np.ndarray, k: int) -> tuple[int, int, int]:
    """(axis, start, end) of hop ``k`` along one row (axis 1: its columns) or one column (axis 0: its rows);
    axis -1 if it turns."""
    p0 = hop_ptr[k]
    p1 = hop_ptr[k + 1] - 1
    r0, c0, r1, c1 = cells[p0, 0], cells[p0, 1], cells[p1, 0], cells[p1, 1]
    if r0 == r1:
        return 1, c0, c1
    if c0 == c1:
        return 0, r0, r1
    return -1, 0, 0


@njit(cache=True, nogil=True)
def merge_aligned(
    hop_ptr: np.ndarray, cells: np.ndarray, group_ptr: np.ndarray, n_groups: int, last_touch: np.ndarray,
    merged_of: np.ndarray, keys: np.ndarray, created_by: np.ndarray, out_hop_ptr: np.ndarray,
    out_cells: np.ndarray, out_group_ptr: np.ndarray,
) -> int:
    """Straight single-hop groups with the same (axis, start, end) join the latest earlier group with that key
    if no group since it (its own creator excluded) touched their traps and no group in between blocks the
    search; written to ``out_*`` merged group by merged group. Returns the number of merged groups.
    ``last_touch`` (``occ``-shaped) is scratch."""
    last_touch[:, :] = -1
    n_merged = 0
    for g in range(n_groups):
        latest = -1  # the latest group (processing order) that touched one of this group's traps
        for p in range(hop_ptr[group_ptr[g]], hop_ptr[group_ptr[g + 1]]):
            latest = max(latest, last_touch[cells[p, 0], cells[p, 1]])
        axis, a, b = _straight_key(hop_ptr, cells, group_ptr[g])
        target = -1
        if group_ptr[g + 1] - group_ptr[g] == 1 and axis >= 0:
            for i in range(n_merged - 1, -1, -1):
                if keys[i, 0] == axis and keys[i, 1] == a and keys[i, 2] == b:
                    if i + 1 == n_merged or latest < created_by[i + 1]:
                        target = i
                    break
                if latest >= created_by[i]:
                    break
        if target < 0:
            target = n_merged
            keys[n_merged, 0] = axis if group_ptr[g + 1] - group_ptr[g] == 1 else -1
            keys[n_merged, 1] = a
            keys[n_merged, 2] = b
            created_by[n_merged] = g
            n_merged += 1
        merged_of[g] = target
        for p in range(hop_ptr[group_ptr[g]], hop_ptr[group_ptr[g + 1]]):
            last_touch[cells[p, 0], cells[p, 1]] = g
    # merged groups in order, each with its groups' hops in processing order (a counting sort on merged_of)
    start = np.zeros(n_merged + 1, dtype=np.int64)
    for g in range(n_groups):
        start[merged_of[g] + 1] += group_ptr[g + 1] - group_ptr[g]
    for i in range(n_merged):
        start[i + 1] += start[i]
    for i in range(n_merged + 1):
        out_group_ptr[i] = start[i]
    slot = start[:n_merged].copy()
    hop_at = np.empty(group_ptr[n_groups], dtype=np.int64)
    for g in range(n_groups):
        i = merged_of[g]
        for k in range(group_ptr[g], group_ptr[g + 1]):
            hop_at[slot[i]] = k
            slot[i] += 1
    n_cells = 0
    out_hop_ptr[0] = 0
    for q in range(group_ptr[n_groups]):
        k = hop_at[q]
        for p in range(hop_ptr[k], hop_ptr[k + 1]):
            out_cells[n_cells, 0] = cells[p, 0]
            out_cells[n_cells, 1] = cells[p, 1]
            n_cells += 1
        out_hop_ptr[q + 1] = n_cells
    return n_merged


@njit(cache=True, nogil=True)
def plan_repair(
    occupancy: np.ndarray, target: np.ndarray, objective: int, per_transfer: float, per_step: float,
    per_slot_atom: float, occ: np.ndarray, free: np.ndarray, holes: np.ndarray, row_cum: np.ndarray,
    col_cum: np.ndarray, cost: np.ndarray, lsa_f: np.ndarray, lsa_i: np.ndarray, in_sr: np.ndarray,
    in_sc: np.ndarray, route: np.ndarray, route_alt: np.ndarray, hop_ptr: np.ndarray, cells: np.ndarray,
    group_ptr: np.ndarray, last_touch: np.ndarray, merged_of: np.ndarray, keys: np.ndarray,
    created_by: np.ndarray, out_hop_ptr: np.ndarray, out_cells: np.ndarray, out_group_ptr: np.ndarray,
) -> tuple[int, int, int]:
    """The whole repair plan up to batching: (hops, merged groups, steps), or (-1, free atoms, holes) when
    there are fewer free atoms than holes. Every array is preallocated by ``RepairPlanner`` (``cost`` and the
    scratch arrays at least ``holes x free atoms``); ``occ`` ends as the occupancy after the plan."""
    occ[:, :] = occupancy
    n_free, n_holes = free_atoms_and_holes(occupancy, target, free, holes)
    if n_free < n_holes:
        return -1, n_free, n_holes
    if n_holes == 0:
        out_hop_ptr[0] = 0
        out_group_ptr[0] = 0
        return 0, 0, 0
    pair_costs(occ, free, n_free, holes, n_holes, objective, per_transfer, per_step, per_slot_atom, row_cum,
               col_cum, cost)  # fmt: skip
    u, v, shortest = lsa_f[0], lsa_f[1], lsa_f[2]
    path, row4col, col4row, remaining, order = lsa_i[0], lsa_i[1], lsa_i[2], lsa_i[3], lsa_i[4]
    assign(cost, n_holes, n_free, u, v, shortest, path, row4col, col4row, remaining, in_sr, in_sc)
    n_hops, n_groups = route_pairs(occ, free, holes, col4row, n_holes, order, route, route_alt, hop_ptr, cells,
                                   group_ptr)  # fmt: skip
    n_merged = merge_aligned(hop_ptr, cells, group_ptr, n_groups, last_touch, merged_of, keys, created_by,
                             out_hop_ptr, out_cells, out_group_ptr)  # fmt: skip
    return n_hops, n_merged, out_hop_ptr[n_hops] - n_hops
