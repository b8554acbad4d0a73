"""Assignment-based planning for ANY target mask (checkerboard, ring, sub-lattice, a picture): ``"assignment"``.

Three stages, in the spirit of aro (assignment, rerouting, ordering; see ``docs/algorithms.md`` of the
design notes, section 2.3):

1. **Assignment.** Atoms already in target traps stay. The other atoms are matched to the empty target
   traps by a minimum total Manhattan distance assignment (``scipy.optimize.linear_sum_assignment`` on the
   small free-atoms x empty-targets problem).
2. **Rerouting.** Each pair travels an L-shaped path (the corner chosen to cross fewer atoms). If atoms sit on
   the path, the pair is realized as a chain: the atom nearest the target moves into it, the next one into
   the place just vacated, and so on back to the source. Every hop then runs over empty traps only, the
   total displacement equals the path length, and the set of occupied traps changes exactly by
   source -> target, so atoms already in place stay in place.
3. **Ordering and batching.** Pairs run in order of path length. The hops of a chain along one row (or
   column) run together as a relay (one row tone, each atom to the next one's trap); relays and single
   hops whose atoms sit in distinct rows and columns share one product set of tweezers, each atom on its
   own path (``assignment_batching``: tone order, bystanders, free traps and overtaking are checked), so a
   batch moves many atoms. Any mask is legal this way; band and rectangle targets still take fewer slots
   with ``aod-parallel`` or ``red-rec-wide``, whose batches move whole columns.

Planning is Python + scipy over small arrays: a few milliseconds for a 32 x 32 array (tested under 50 ms).
"""

from __future__ import annotations

import numpy as np
from scipy.optimize import linear_sum_assignment

from engine.operations import Operations, Plan
from engine.solvers.assignment_batching import batch_hops, emit_hop_batches
from engine.solvers.base import UnsolvableError

__all__ = ["AssignmentPlanner"]


class AssignmentPlanner:
    """Fills an arbitrary target mask on an ``ny x nx`` grid of SLM traps (crossed AODs)."""

    def __init__(self, nx: int, ny: int, *, trap_source: str = "slm") -> None:
        if trap_source != "slm":
            raise ValueError(
                "assignment moves single atoms between static SLM traps with crossed AODs; an AOD chain "
                "(trap_source 'aod') uses exact-1d"
            )
        self.nx = nx
        self.ny = ny
        self.operations = Operations(nx=nx, ny=ny, capacity=4 * (nx + ny) + 256)
        self.window = 256  # hops a batch looks ahead
        self.extend = 1  # slots a hop may add to a batch's length
        m = max(nx, ny)
        self._occ0 = np.zeros((ny, nx), dtype=np.bool_)
        self._occ = np.zeros((ny, nx), dtype=np.bool_)
        self._blocked = np.zeros((ny, nx), dtype=np.int64)
        self._src_mark = np.zeros((ny, nx), dtype=np.bool_)
        self._dst_mark = np.zeros((ny, nx), dtype=np.bool_)
        self._done = np.zeros(nx * ny, dtype=np.bool_)
        self._members = np.zeros(m, dtype=np.int64)
        self._order_r = np.zeros(m, dtype=np.int64)
        self._order_c = np.zeros(m, dtype=np.int64)
        self._batch_ptr = np.zeros(nx * ny + 1, dtype=np.int64)
        self._batch_hop = np.zeros(nx * ny, dtype=np.int64)
        self._y_used = np.zeros(self.operations.capacity, dtype=np.int64)
        self._x_used = np.zeros(self.operations.capacity, dtype=np.int64)
        self._hops: list[list[tuple[int, int]]] = []
        self._plan = Plan(steps=np.zeros((0, 2), dtype=np.int32), operations=self.operations, algorithm="assignment")
        self._solved = False
        self._warm_up()

    def _warm_up(self) -> None:
        """Compile (or load) the batching kernels now, not in the first cycle."""
        occ = np.zeros((self.ny, self.nx), dtype=bool)
        target = np.zeros_like(occ)
        occ.flat[0] = True
        target.flat[-1] = True
        self.solve_moves(occ, target)
        self.batch()
        self.operations.clear()
        self._solved = False

    def check_target(self, target: np.ndarray) -> None:
        if target.shape != (self.ny, self.nx):
            raise ValueError(f"target shape {target.shape} must be (ny, nx) = {(self.ny, self.nx)}")
        if not target.any():
            raise ValueError("the target selects no trap")

    def solve_moves(self, occupancy: np.ndarray, target: np.ndarray) -> int:
        """Assign and reroute; returns the number of one-site steps. Raises ``UnsolvableError``."""
        if occupancy.shape != (self.ny, self.nx) or target.shape != (self.ny, self.nx):
            raise ValueError(f"occupancy {occupancy.shape} and target {target.shape} must both be {(self.ny, self.nx)}")
        self._solved = False
        occ = occupancy.astype(bool, copy=True)
        self._occ0[:] = occ
        free = np.argwhere(occ & ~target)
        holes = np.argwhere(target & ~occ)
        if len(free) < len(holes):
            raise UnsolvableError(f"{int(occupancy.sum())} atoms cannot fill {int(target.sum())} target traps")
        self._hops = []
        self._groups = [0]
        if len(holes):
            cost = self._pair_costs(occ, free, holes)
            rows, cols = linear_sum_assignment(cost.T)  # holes x free atoms: every hole gets an atom
            pairs = [(tuple(free[c]), tuple(holes[r])) for r, c in zip(rows, cols, strict=True)]
            pairs.sort(key=lambda st: abs(st[0][0] - st[1][0]) + abs(st[0][1] - st[1][1]))
            for source, dest in pairs:
                path = self._route(occ, source, dest)
                for group in _relay_groups(_chain_hops(occ, path)):
                    self._hops.extend(group)
                    self._groups.append(len(self._hops))
                occ[source] = False
                occ[dest] = True
        self._solved = True
        return sum(len(h) - 1 for h in self._hops)

    def _pair_costs(self, occ: np.ndarray, free: np.ndarray, holes: np.ndarray) -> np.ndarray:
        """``[free atoms, holes]`` cost the assignment minimises: the Manhattan distance (one-site steps)."""
        return np.abs(free[:, None, 0] - holes[None, :, 0]) + np.abs(free[:, None, 1] - holes[None, :, 1])

    def _route(self, occ: np.ndarray, source: tuple[int, int], dest: tuple[int, int]) -> list[tuple[int, int]]:
        """The L-shaped path (both corners tried) that crosses fewer atoms; inclusive of both ends."""
        (r0, c0), (r1, c1) = source, dest
        best: list[tuple[int, int]] | None = None
        best_atoms = -1
        for rows_first in (False, True):
            path = [(r0, c0)]
            r, c = r0, c0
            legs = ((1, r1 - r0), (0, c1 - c0)) if rows_first else ((0, c1 - c0), (1, r1 - r0))
            for axis, d in legs:
                step = 1 if d > 0 else -1
                for _ in range(abs(d)):
                    if axis == 1:
                        r += step
                    else:
                        c += step
                    path.append((r, c))
            atoms = sum(1 for site in path[1:-1] if occ[site])
            if best is None or atoms < best_atoms:
                best, best_atoms = path, atoms
        assert best is not None
        return best

    def batch(self) -> Plan:
        """Hops in parallel batches (``assignment_batching``): atoms in distinct rows and columns move
        together on one product set of tweezers, each along its own path."""
        if not self._solved:
            raise RuntimeError("batch() needs a successful solve_moves() first")
        hops = self._hops
        hop_ptr = np.zeros(len(hops) + 1, dtype=np.int64)
        hop_ptr[1:] = np.cumsum([len(h) for h in hops])
        cells = np.array([site for h in hops for site in h], dtype=np.int64).reshape(-1, 2)
        group_ptr = np.asarray(self._groups, dtype=np.int64)
        return self._batch_hops(hop_ptr, len(hops), cells, group_ptr, group_ptr.size - 1)

    def _batch_hops(
        self, hop_ptr: np.ndarray, n_hops: int, cells: np.ndarray, group_ptr: np.ndarray, n_groups: int
    ) -> Plan:
        """Batch and emit hop ``k``'s path ``cells[hop_ptr[k]:hop_ptr[k + 1]]`` for ``k < n_hops``, in groups
        ``group_ptr[:n_groups + 1]`` (the arrays may be longer: preallocated)."""
        n_cells = int(hop_ptr[n_hops])
        if self._done.size < n_groups:
            self._done = np.zeros(2 * n_groups, dtype=np.bool_)
        if self._members.size < n_hops:
            self._members = np.zeros(n_hops, dtype=np.int64)
            self._order_r = np.zeros(n_hops, dtype=np.int64)
            self._order_c = np.zeros(n_hops, dtype=np.int64)
        n_batches = batch_hops(
            self._occ0, hop_ptr, n_hops, cells, group_ptr, n_groups, self.window, self.extend, self._occ,
            self._done, self._blocked, self._src_mark, self._dst_mark, self._members, self._batch_ptr_for(n_hops),
            self._batch_hop_for(n_hops),
        )  # fmt: skip
        if n_batches < 0:
            raise RuntimeError("assignment: hops out of sequential order (a planner bug)")
        ops = self.operations
        steps = np.zeros((n_cells - n_hops, 2), dtype=np.int32)
        while True:
            n, n_steps = emit_hop_batches(
                hop_ptr, cells, self._batch_ptr, n_batches, self._batch_hop, self.nx, self._order_r,
                self._order_c, ops.n, ops.kind, ops.y_site, ops.y_delta, ops.x_site, ops.x_delta,
                self._y_used, self._x_used, steps,
            )  # fmt: skip
            if n >= 0:
                break
            ops.clear()
            ops.reserve(2 * (-n))
            self._y_used = np.zeros(ops.capacity, dtype=np.int64)
            self._x_used = np.zeros(ops.capacity, dtype=np.int64)
        ops.n = n
        self._plan.steps = steps[:n_steps]
        return self._plan

    def _batch_ptr_for(self, n_hops: int) -> np.ndarray:
        if self._batch_ptr.size < n_hops + 1:
            self._batch_ptr = np.zeros(2 * n_hops + 1, dtype=np.int64)
        return self._batch_ptr

    def _batch_hop_for(self, n_hops: int) -> np.ndarray:
        if self._batch_hop.size < n_hops:
            self._batch_hop = np.zeros(2 * n_hops, dtype=np.int64)
        return self._batch_hop


def _relay_groups(hops: list[list[tuple[int, int]]]) -> list[list[list[tuple[int, int]]]]:
    """Consecutive straight hops of a chain along one row (or one column) run together as a relay: every
    atom moves to where the next one (nearer the target, earlier in the list) starts. A hop that turns the
    corner runs alone."""
    groups: list[list[list[tuple[int, int]]]] = []
    prev_line: tuple[int, int] | None = None
    for hop in hops:
        (r0, c0), (r1, c1) = hop[0], hop[-1]
        straight = len(hop) == abs(r1 - r0) + abs(c1 - c0) + 1 and (r0 == r1 or c0 == c1)
        line = (0, r0) if straight and r0 == r1 else (1, c0) if straight else None
        if line is not None and line == prev_line:
            groups[-1].append(hop)
        else:
            groups.append([hop])
        prev_line = line
    return groups


def _chain_hops(occ: np.ndarray, path: list[tuple[int, int]]) -> list[list[tuple[int, int]]]:
    """Split ``path`` at the atoms on it: hops that each run over empty traps, nearest the target first."""
    stops = [0] + [i for i in range(1, len(path) - 1) if occ[path[i]]] + [len(path) - 1]
    return [path[stops[j] : stops[j + 1] + 1] for j in range(len(stops) - 2, -1, -1)]
