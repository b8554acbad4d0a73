"""Planning under interstitial routing (``array.routing: interstitial``, ``engine/routing.py``).

Two planners, both writing ``Operations`` on the grid of positions (``half = 2``):

- ``InterstitialRepairPlanner`` (``repair`` under interstitial routing): each spare atom goes straight to the
  hole it is assigned, passing occupied traps in the channels, so no atom but the spare one is touched and
  nothing is relayed. Its route: extract at its trap; half a site along y into the row channel next to it
  (towards the hole's row); along that channel to the column channel beside the hole's column (on the side
  facing the spare atom); along the column channel to the hole's row; half a site along x onto the hole;
  implant. Every position between the two half steps is odd on one axis at least, so the loaded tweezer ends
  no slot over a trap. The assignment is the minimum total Manhattan distance (the repair planner's
  shortest-augmenting-path kernel, ``repair_kernels.assign``, scipy's algorithm and tie-breaking): with
  two transfers per moved atom whatever the pair, fewer sites travelled is also fewer expected losses, so
  every objective gives this plan. A route of ``d`` sites takes ``2 d`` half-site steps (2 more when the
  spare atom is in the hole's column or row). Spare atoms in one column going to holes in one column move
  together on one x tone and a y tone each (one row and one row likewise), so the product set is exactly
  their tweezers, all loaded: no empty tweezer anywhere. Groups run one after the other. It plans between two
  images, so the whole plan is numba kernels over preallocated arrays (``repair_kernels.free_atoms_and_holes``,
  ``interstitial_pairs``, ``group_pairs``, ``route_groups``); ``_groups`` and ``_route_group`` are their
  plain-Python references.
- ``LatticeOnPositions``: any lattice planner (a strategy's bulk planner) with its plan written on the grid of
  positions (``engine.routing.lattice_to_positions``: every one-site shift as two half-site shifts).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from engine.operations import EXTRACT, IMPLANT, SHIFT, Operations, Plan
from engine.routing import lattice_to_positions, n_positions
from engine.solvers.base import Planner, UnsolvableError
from engine.solvers.repair_kernels import assign, free_atoms_and_holes

__all__ = ["InterstitialRepairPlanner", "LatticeOnPositions"]


def _groups(pairs: np.ndarray, n_positions_yx: tuple[int, int]) -> list[tuple[int, np.ndarray]]:
    """Repairs that can move together: ``(shared axis, rows)`` with rows ``(r0, c0, r1, c1)``.

    Spare atoms in one column whose holes are in one column (most of them in a band: the nearest spare atom is
    straight above or below) share an x tone and move as a column group; the rest are grouped by source and hole
    row likewise, sharing a y tone. Within a group the holes are given to the spare atoms in order along the
    other axis (it keeps the total distance and the tones' order), and a group is cut where two tones would
    come within a site of each other beside their holes (``_sides``)."""
    out: list[tuple[int, np.ndarray]] = []
    rest = pairs
    for shared in (1, 0):  # column groups first, then row groups of what is left
        own = 1 - shared
        keys = rest[:, shared] * 1_000_000 + rest[:, 2 + shared]
        leftover = []
        for key in np.unique(keys):
            group = rest[keys == key]
            if group.shape[0] == 1 and shared == 1:
                leftover.append(group)
                continue
            group = group[np.argsort(group[:, own], kind="stable")]
            group[:, 2 + own] = np.sort(group[:, 2 + own])
            out.extend((shared, part) for part in _split_crowded(group, own, n_positions_yx[own]))
        rest = np.concatenate(leftover) if leftover else pairs[:0]
    return out


def _sides(a: np.ndarray, a1: np.ndarray, n: int) -> np.ndarray:
    """Which channel beside each hole (-1 below / +1 above its position ``a1``, on an axis of ``n`` positions)
    a tone from ``a`` travels to: the side facing where it comes from, the inner side at the edges."""
    side = np.where(a < a1, -1, 1)
    side = np.where((a == a1) & (a1 == n - 1), -1, side)
    return np.where((a1 + side < 0) | (a1 + side >= n), -side, side)


def _split_crowded(group: np.ndarray, own: int, n: int) -> list[np.ndarray]:
    """Cut a sorted group where neighbouring tones would end their channel travel less than a site apart
    (``n``: positions on the group's own axis)."""
    a, a1 = 2 * group[:, own], 2 * group[:, 2 + own]
    channel = a1 + _sides(a, a1, n)
    cuts = np.flatnonzero(np.diff(channel) < 2) + 1
    return np.split(group, cuts)


class InterstitialRepairPlanner:
    """Fills the holes of any target mask from the spare atoms, each moved once along the channels."""

    def __init__(self, nx: int, ny: int, *, reference: bool = False) -> None:
        """``reference``: group and write the routes in plain Python (``_groups``, ``_route_group``: for tests)
        instead of the ``group_pairs`` and ``route_groups`` kernels."""
        if min(nx, ny) < 2:
            raise ValueError(f"interstitial routing needs channels on both axes: at least 2 x 2 traps, got {ny} x {nx}")
        self.nx, self.ny = nx, ny
        self.px, self.py = n_positions(nx, 2), n_positions(ny, 2)
        self.operations = Operations(nx=self.px, ny=self.py, capacity=4 * (nx + ny) + 256, half=2)
        self._steps = np.zeros((4 * (nx + ny) + 256, 2), dtype=np.int32)
        self._n_steps = 0
        self._plan = Plan(steps=self._steps[:0], operations=self.operations, algorithm="repair")
        self.reference = reference
        self._spare = np.zeros((nx * ny, 2), dtype=np.int64)
        self._holes = np.zeros((nx * ny, 2), dtype=np.int64)
        self._pairs = np.zeros((nx * ny, 4), dtype=np.int64)
        self._grouped = np.zeros((nx * ny, 4), dtype=np.int64)
        self._group_ptr = np.zeros(nx * ny + 1, dtype=np.int64)
        self._group_shared = np.zeros(nx * ny, dtype=np.int64)
        self._alloc_assignment(holes=64, spare=128)

    def _alloc_assignment(self, *, holes: int, spare: int) -> None:
        """The assignment's cost matrix and scratch for up to ``holes`` x ``spare`` (grown on demand, doubled)."""
        self._cost = np.zeros((holes, spare), dtype=np.float64)
        self._lsa_f = np.zeros((3, spare), dtype=np.float64)
        self._lsa_i = np.zeros((4, spare), dtype=np.int64)
        self._col4row = np.zeros(holes, dtype=np.int64)
        self._in_sr = np.zeros(holes, dtype=np.bool_)
        self._in_sc = np.zeros(spare, dtype=np.bool_)

    def check_target(self, target: np.ndarray) -> None:
        if target.shape != (self.ny, self.nx):
            raise ValueError(f"target is {target.shape[0]}x{target.shape[1]}, the array {self.ny}x{self.nx}")

    def solve_moves(self, occupancy: np.ndarray, target: np.ndarray) -> int:
        """Assign spare atoms to holes (fewest sites travelled) and write each route; returns the half-site steps."""
        occ = np.asarray(occupancy, dtype=np.bool_)
        n_spare, n_holes = free_atoms_and_holes(occ, np.asarray(target, dtype=np.bool_), self._spare, self._holes)
        if n_spare < n_holes:
            raise UnsolvableError(f"{n_holes} holes in the target but only {n_spare} spare atoms")
        self.operations.clear()
        self._n_steps = 0
        if n_holes:
            if n_holes > self._cost.shape[0] or n_spare > self._cost.shape[1]:
                self._alloc_assignment(holes=max(n_holes, 2 * self._cost.shape[0]),
                                       spare=max(n_spare, 2 * self._cost.shape[1]))  # fmt: skip
            interstitial_pairs(
                self._spare, n_spare, self._holes, n_holes, self._cost, self._lsa_f, self._lsa_i, self._col4row,
                self._in_sr, self._in_sc, self._pairs,
            )  # fmt: skip
            if self.reference:
                for shared, group in _groups(self._pairs[:n_holes].copy(), (self.py, self.px)):
                    self._route_group(shared, group)
            else:
                self._route_kernels(n_holes)
        self._plan.steps = self._steps[: self._n_steps]
        return self._n_steps

    def batch(self) -> Plan:
        return self._plan

    def _route_kernels(self, n_holes: int) -> None:
        """``_groups`` and ``_route_group`` by the ``group_pairs`` and ``route_groups`` kernels, the buffers grown
        to the plan's size in between."""
        n_groups, n_slots, n_steps = group_pairs(
            self._pairs, n_holes, self.py, self.px, self._grouped, self._group_ptr, self._group_shared
        )
        ops = self.operations
        ops.reserve(n_slots)
        if n_steps > self._steps.shape[0]:
            self._steps = np.zeros((2 * n_steps, 2), dtype=np.int32)
        ops.n, self._n_steps = route_groups(
            self._grouped, self._group_ptr, self._group_shared, n_groups, self.py, self.px,
            ops.kind, ops.y_site, ops.y_delta, ops.x_site, ops.x_delta, self._steps,
        )  # fmt: skip

    def _route_group(self, shared: int, group: np.ndarray) -> None:
        """Move a group of spare atoms together (``_groups``): ``shared`` is the axis (0: y, 1: x) whose one tone
        they all use, ``group`` their ``(r0, c0, r1, c1)`` rows, sorted along the other axis.

        Phases (own = the other axis): extract; half a site along the shared axis into the channel towards the
        holes; along the channel, each own tone to the channel beside its hole (``_sides``), tones that arrive
        early waiting; along the shared axis to the holes' line; half a site along the own axis onto the holes;
        implant. Every tweezer of the 1 x k product set is loaded, so none is ever empty."""
        own = 1 - shared
        n_shared, n_own = (self.py, self.px) if shared == 0 else (self.px, self.py)
        b0, b1 = 2 * int(group[0, shared]), 2 * int(group[0, 2 + shared])
        a = 2 * group[:, own].astype(np.int64)
        a1 = 2 * group[:, 2 + own].astype(np.int64)
        sb = (1 if b1 > b0 else -1) if b1 != b0 else (1 if b0 < n_shared - 1 else -1)
        side = _sides(a, a1, n_own)
        moves: list[tuple[int, np.ndarray]] = [(sb, np.zeros_like(a))]
        channel = a1 + side
        pos = a.copy()
        while np.any(pos != channel):
            d = np.sign(channel - pos)
            moves.append((0, d))
            pos += d
        moves += [(int(np.sign(b1 - b0 - sb)), np.zeros_like(a))] * abs(b1 - b0 - sb)
        moves.append((0, -side))
        self._emit(shared, b0, a, moves)

    def _emit(self, shared: int, b: int, a: np.ndarray, moves: list[tuple[int, np.ndarray]]) -> None:
        """Write the group's slots and steps: one tone at ``b`` on the shared axis, tones ``a`` on the other;
        each move is (the shared tone's delta, the own tones' deltas)."""
        a = a.copy()

        def tones(db: int, da: np.ndarray) -> tuple[list[int], list[int], list[int], list[int]]:
            if shared == 0:
                return [b], a.tolist(), [db], da.tolist()
            return a.tolist(), [b], da.tolist(), [db]

        ys, xs, _, _ = tones(0, np.zeros_like(a))
        self.operations.append(EXTRACT, ys, xs)
        for db, da in moves:
            ys, xs, dys, dxs = tones(db, da)
            self.operations.append(SHIFT, ys, xs, dys, dxs)
            for k in np.flatnonzero(da != 0) if db == 0 else range(a.size):
                y0, x0 = (b, int(a[k])) if shared == 0 else (int(a[k]), b)
                y1, x1 = (b + db, int(a[k] + da[k])) if shared == 0 else (int(a[k] + da[k]), b + db)
                self._step(y0 * self.px + x0, y1 * self.px + x1)
            b += db
            a += da
        ys, xs, _, _ = tones(0, np.zeros_like(a))
        self.operations.append(IMPLANT, ys, xs)

    def _step(self, src: int, dst: int) -> None:
        if self._n_steps == self._steps.shape[0]:
            self._steps = np.concatenate([self._steps, np.zeros_like(self._steps)])
        self._steps[self._n_steps] = (src, dst)
        self._n_steps += 1


@njit(cache=True, nogil=True)
def interstitial_pairs(
    spare: np.ndarray, n_spare: int, holes: np.ndarray, n_holes: int, cost: np.ndarray, lsa_f: np.ndarray,
    lsa_i: np.ndarray, col4row: np.ndarray, in_sr: np.ndarray, in_sc: np.ndarray, pairs: np.ndarray,
) -> None:  # fmt: skip
    """The fewest sites travelled in all: ``pairs[h] = (r0, c0, r1, c1)``, the spare atom at ``(r0, c0)`` for
    hole ``h`` at ``(r1, c1)``, by ``repair_kernels.assign`` over the Manhattan distances (every objective's
    plan: two transfers per moved atom whatever the pair). ``n_spare >= n_holes``: with finite costs an
    assignment always exists, so ``assign``'s flag is always true."""
    for h in range(n_holes):
        for f in range(n_spare):
            cost[h, f] = abs(spare[f, 0] - holes[h, 0]) + abs(spare[f, 1] - holes[h, 1])
    assign(cost, n_holes, n_spare, lsa_f[0], lsa_f[1], lsa_f[2], lsa_i[0], lsa_i[1], col4row, lsa_i[2], in_sr, in_sc)
    for h in range(n_holes):
        f = col4row[h]
        pairs[h, 0] = spare[f, 0]
        pairs[h, 1] = spare[f, 1]
        pairs[h, 2] = holes[h, 0]
        pairs[h, 3] = holes[h, 1]


@njit(cache=True, nogil=True)
def _side(a: int, a1: int, n: int) -> int:
    """``_sides`` for one tone."""
    side = -1 if a < a1 else 1
    if a == a1 and a1 == n - 1:
        side = -1
    if a1 + side < 0 or a1 + side >= n:
        side = -side
    return side


@njit(cache=True, nogil=True)
def group_pairs(
    pairs: np.ndarray, n_pairs: int, py: int, px: int, grouped: np.ndarray, group_ptr: np.ndarray,
    group_shared: np.ndarray,
) -> tuple[int, int, int]:  # fmt: skip
    """``_groups`` as a kernel: group ``g`` is ``grouped[group_ptr[g]:group_ptr[g + 1]]`` moving along the
    shared axis ``group_shared[g]``, in ``_groups``' order. Returns (groups, slots, steps) of the routes.

    Column groups (same source and hole column, two atoms at least) by (source column, hole column), then row
    groups of the rest by (source row, hole row); within a group the atoms by their other coordinate, the holes'
    other coordinates sorted and handed out in order, cut where two tones' channels come within a site."""
    size = max(py, px) + 1  # every coordinate is below it: one integer key sorts by (line, line, other)
    keys = np.empty(n_pairs, dtype=np.int64)
    rest = pairs[:n_pairs].copy()
    n_rest = n_pairs
    leftover = np.empty_like(rest)
    n_groups = 0
    n_out = 0
    n_slots = 0
    n_steps = 0
    group_ptr[0] = 0
    for shared in (1, 0):
        own = 1 - shared
        n_own = py if shared == 1 else px
        for i in range(n_rest):
            keys[i] = (rest[i, shared] * size + rest[i, 2 + shared]) * size + rest[i, own]
        order = np.argsort(keys[:n_rest])
        n_left = 0
        start = 0
        while start < n_rest:
            first = order[start]
            end = start + 1
            while end < n_rest and keys[order[end]] // size == keys[first] // size:
                end += 1
            if end - start == 1 and shared == 1:
                leftover[n_left] = rest[first]
                n_left += 1
                start = end
                continue
            ends = np.empty(end - start, dtype=np.int64)
            for k in range(start, end):
                ends[k - start] = rest[order[k], 2 + own]
            ends.sort()
            b0 = 2 * rest[first, shared]
            b1 = 2 * rest[first, 2 + shared]
            shared_travel = abs(b1 - b0) + 2
            prev_channel = -(1 << 30)
            max_travel = 0
            for k in range(start, end):
                a = 2 * rest[order[k], own]
                a1 = 2 * ends[k - start]
                channel = a1 + _side(a, a1, n_own)
                if k > start and channel - prev_channel < 2:  # cut: a new group from here
                    n_slots += max_travel + shared_travel + 3
                    n_groups += 1
                    group_ptr[n_groups] = n_out
                    group_shared[n_groups - 1] = shared
                    max_travel = 0
                prev_channel = channel
                max_travel = max(max_travel, abs(channel - a))
                n_steps += abs(channel - a) + shared_travel + 1
                grouped[n_out] = rest[order[k]]
                grouped[n_out, 2 + own] = ends[k - start]
                n_out += 1
            n_slots += max_travel + shared_travel + 3
            n_groups += 1
            group_ptr[n_groups] = n_out
            group_shared[n_groups - 1] = shared
            start = end
        rest, leftover = leftover, rest
        n_rest = n_left
    return n_groups, n_slots, n_steps


@njit(cache=True, nogil=True)
def route_groups(
    grouped: np.ndarray, group_ptr: np.ndarray, group_shared: np.ndarray, n_groups: int, py: int, px: int,
    kind: np.ndarray, y_site: np.ndarray, y_delta: np.ndarray, x_site: np.ndarray, x_delta: np.ndarray,
    steps: np.ndarray,
) -> tuple[int, int]:  # fmt: skip
    """Every group of ``group_pairs`` by ``route_group``, one after the other from slot 0 (the buffers large
    enough, the rows cleared); returns (slots, steps)."""
    n = 0
    n_steps = 0
    for g in range(n_groups):
        shared = group_shared[g]
        own = 1 - shared
        n_own = py if shared == 1 else px
        k = group_ptr[g + 1] - group_ptr[g]
        a0 = np.empty(k, dtype=np.int64)
        side = np.empty(k, dtype=np.int64)
        channel = np.empty(k, dtype=np.int64)
        for t in range(k):
            row = group_ptr[g] + t
            a0[t] = 2 * grouped[row, own]
            side[t] = _side(a0[t], 2 * grouped[row, 2 + own], n_own)
            channel[t] = 2 * grouped[row, 2 + own] + side[t]
        first = group_ptr[g]
        n, n_steps = route_group(
            shared, 2 * grouped[first, shared], 2 * grouped[first, 2 + shared], a0, side, channel,
            py if shared == 0 else px, px, kind, y_site, y_delta, x_site, x_delta, n, steps, n_steps,
        )  # fmt: skip
    return n, n_steps


@njit(cache=True, nogil=True)
def _slot(
    shared: int, kind: int, b: int, db: int, a: np.ndarray, da: np.ndarray, i: int,
    out_kind: np.ndarray, y_site: np.ndarray, y_delta: np.ndarray, x_site: np.ndarray, x_delta: np.ndarray,
) -> None:  # fmt: skip
    """Slot ``i``: the shared tone at ``b`` (delta ``db``) and the own tones at ``a`` (deltas ``da``)."""
    out_kind[i] = kind
    s_site, s_delta = (y_site, y_delta) if shared == 0 else (x_site, x_delta)
    o_site, o_delta = (x_site, x_delta) if shared == 0 else (y_site, y_delta)
    s_site[i, 0] = b
    s_delta[i, 0] = db
    for t in range(a.size):
        o_site[i, t] = a[t]
        o_delta[i, t] = da[t]


@njit(cache=True, nogil=True)
def route_group(
    shared: int, b0: int, b1: int, a0: np.ndarray, side: np.ndarray, channel: np.ndarray, n_shared: int, px: int,
    kind: np.ndarray, y_site: np.ndarray, y_delta: np.ndarray, x_site: np.ndarray, x_delta: np.ndarray, n: int,
    steps: np.ndarray, n_steps: int,
) -> tuple[int, int]:  # fmt: skip
    """``InterstitialRepairPlanner._route_group`` as a kernel: the group's slots from slot ``n`` and its steps
    from ``n_steps`` (the buffers large enough, the rows cleared); returns the new ``(n, n_steps)``.

    ``b0``/``b1``: the shared tone's start and end positions; ``a0``: the own tones' start positions,
    ``channel``: where each travels along the channel, ``side``: which side of its hole that is."""
    k = a0.size
    a = a0.copy()
    da = np.zeros(k, dtype=np.int64)
    b = b0
    _slot(shared, EXTRACT, b, 0, a, da, n, kind, y_site, y_delta, x_site, x_delta)
    n += 1
    sb = (1 if b1 > b0 else -1) if b1 != b0 else (1 if b0 < n_shared - 1 else -1)
    phase = 0  # 0: shared half step, 1: own travel, 2: shared travel, 3: own half step
    while phase < 4:
        db = 0
        if phase == 0:
            db = sb
            phase = 1
        elif phase == 1:
            moving = False
            for t in range(k):
                da[t] = (channel[t] > a[t]) - (channel[t] < a[t])
                moving |= da[t] != 0
            if not moving:
                phase = 2
                continue
        elif phase == 2:
            if b == b1:
                phase = 3
                continue
            db = 1 if b1 > b else -1
        else:
            for t in range(k):
                da[t] = -side[t]
            phase = 4
        _slot(shared, SHIFT, b, db, a, da, n, kind, y_site, y_delta, x_site, x_delta)
        n += 1
        for t in range(k):
            if db == 0 and da[t] == 0:
                continue
            y0, x0, y1, x1 = b, a[t], b + db, a[t] + da[t]
            if shared == 1:
                y0, x0, y1, x1 = a[t], b, a[t] + da[t], b + db
            steps[n_steps, 0] = y0 * px + x0
            steps[n_steps, 1] = y1 * px + x1
            n_steps += 1
        b += db
        for t in range(k):
            a[t] += da[t]
            da[t] = 0
    _slot(shared, IMPLANT, b, 0, a, da, n, kind, y_site, y_delta, x_site, x_delta)
    return n + 1, n_steps


class LatticeOnPositions:
    """A lattice planner whose plans play under interstitial routing: each plan copied onto the grid of
    positions, every one-site shift as two half-site shifts (``engine.routing.lattice_to_positions``)."""

    def __init__(self, planner: Planner) -> None:
        self.planner = planner
        self.nx, self.ny = planner.nx, planner.ny
        self.operations = Operations(nx=n_positions(self.nx, 2), ny=n_positions(self.ny, 2), capacity=512, half=2)
        self._steps = np.zeros((512, 2), dtype=np.int32)
        self._plan = Plan(steps=self._steps[:0], operations=self.operations)
        self.check_target = planner.check_target
        self.solve_moves = planner.solve_moves

    def batch(self) -> Plan:
        plan = self.planner.batch()
        src, out = plan.operations, self.operations
        out.clear()
        out.reserve(2 * len(src))
        if self._steps.shape[0] < 2 * plan.n_steps:
            self._steps = np.zeros((2 * plan.n_steps, 2), dtype=np.int32)
        out.n = lattice_to_positions(
            src.kind, src.y_site, src.y_delta, src.x_site, src.x_delta, len(src), plan.steps, plan.n_steps, self.nx,
            out.kind, out.y_site, out.y_delta, out.x_site, out.x_delta, self._steps,
        )  # fmt: skip
        self._plan.steps = self._steps[: 2 * plan.n_steps]
        self._plan.algorithm = plan.algorithm
        self._plan.notes = plan.notes
        return self._plan
