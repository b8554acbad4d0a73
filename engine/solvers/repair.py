"""A repair planner for a few defects: ``"repair"``. Only the atoms needed move, on short paths.

When a bulk planner has done its work, a handful of target traps are empty (atoms lost in the cycle, or
never loaded) and the spare atoms sit outside the target. Re-planning the whole array (red-rec, aod-parallel)
moves tens of atoms per hole; every pick-up, implant and one-site step can lose one. The repair planner moves
a spare atom into each hole and leaves every other atom alone unless the spare atom's path needs it:

- **Which spare atom fills which hole.** A minimum-cost assignment of spare atoms to holes, where the cost of a
  pair is what its move risks (``objective``):

  - ``slots``: one-site steps (the Manhattan distance), as the assignment planner;
  - ``transfers``: atoms picked up (the spare atom plus every atom on its path), steps as the tie-break;
  - ``survival``: expected atoms lost, ``transfers x -ln p_transfer + steps x -ln p_step + time x atoms /
    lifetime`` (a pick-up and an implant per atom moved, a step per site, ``slot_duration_s`` per site of
    path), from the configured loss model.

  Atoms on a path are counted on both L-shaped routes (row first or column first) with prefix sums over the
  occupancy, so the cost of every (spare atom, hole) pair costs O(1).
- **Paths in the lattice model.** A loaded tweezer may not end a slot over an occupied trap, so an atom cannot
  pass one. We chose to **move blocking atoms as part of the plan**, not to detour around them: the route is
  the L with fewer atoms on it, and the atoms on it relay (the one nearest the hole moves into it, the next
  into the trap just vacated, back to the spare atom), each one hop over empty traps, each picked up once.
  Atoms off the route are never touched, and the set of occupied traps changes only by spare trap -> hole.
  An atom is picked up once per repair whose route crosses it: two holes in one column, filled from the same
  side, relay the atoms nearer the edge twice (a column compression, as red-rec's, would take them once).
  A detour through empty traps would be longer (each extra site a step and a slot of everyone's vacuum
  time) and in a filled band there is rarely one; the survival cost charges the relayed atoms, so a spare
  atom with a clear path wins when it is close.
- **Batching.** The hops share product sets of AOD tweezers wherever their rows and columns line up
  (``assignment_batching``: bystanders, captures and overtaking are checked), so several holes are repaired
  in the same slots.

Not a bulk planner: on a freshly loaded 32 x 64 array (about 410 holes in a 32 x 32 band) it relays ~3,500
atoms in 3,500-4,200 slots, beyond the examples' AWG layout (4,064 slots) in about 1 shot in 10, where red-rec
takes ~950 pick-ups in ~800 slots. Use it behind a bulk planner (``solver.strategy``).

Planning runs in numba kernels over preallocated arrays (``repair_kernels``: pair costs, a
shortest-augmenting-path assignment, routes, relays, merging), then the assignment planner's batching; the
plain-Python path (``reference_hops``: scipy's ``linear_sum_assignment`` and the assignment planner's list
routing) is kept as the kernels' reference in the tests and gives the same plans.
"""

from __future__ import annotations

import numpy as np

from engine.operations import Plan
from engine.solvers.assignment import AssignmentPlanner
from engine.solvers.base import LossWeights, UnsolvableError
from engine.solvers.repair_kernels import OBJECTIVE_CODES, plan_repair

__all__ = ["RepairPlanner", "route_atoms"]


def route_atoms(occ: np.ndarray, free: np.ndarray, holes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Atoms strictly between each spare atom and each hole on the two L routes, ``int[free, holes]`` each:
    row first (along the spare atom's row, then the hole's column) and column first."""
    occ_i = occ.astype(np.int64)
    ny, nx = occ.shape
    row_cum = np.zeros((ny, nx + 1), dtype=np.int64)
    row_cum[:, 1:] = np.cumsum(occ_i, axis=1)
    col_cum = np.zeros((ny + 1, nx), dtype=np.int64)
    col_cum[1:, :] = np.cumsum(occ_i, axis=0)
    r0, c0 = free[:, 0:1], free[:, 1:2]  # [free, 1]
    r1, c1 = holes[None, :, 0], holes[None, :, 1]  # [1, holes]

    def along_row(r: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return row_cum[r, np.maximum(a, b) + 1] - row_cum[r, np.minimum(a, b)]

    def along_col(c: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return col_cum[np.maximum(a, b) + 1, c] - col_cum[np.minimum(a, b), c]

    # each segment counts its ends; take out the spare atom, the corner (counted twice) and the hole
    row_first = along_row(r0, c0, c1) + along_col(c1, r0, r1) - occ_i[r0, c0] - occ_i[r0, c1] - occ_i[r1, c1]
    col_first = along_col(c0, r0, r1) + along_row(r1, c0, c1) - occ_i[r0, c0] - occ_i[r1, c0] - occ_i[r1, c1]
    return row_first, col_first


class RepairPlanner(AssignmentPlanner):
    """Fills the holes of any target mask from the spare atoms, moving as few atoms as the paths allow."""

    def __init__(
        self,
        nx: int,
        ny: int,
        *,
        trap_source: str = "slm",
        objective: str = "survival",
        loss: LossWeights | None = None,
    ) -> None:
        if objective not in ("slots", "transfers", "survival"):
            raise ValueError(f"objective must be slots, transfers or survival (got {objective!r})")
        self.objective = objective
        self.loss = loss or LossWeights()
        self._alloc(nx, ny, holes=64, free=256)
        super().__init__(nx, ny, trap_source=trap_source)
        self._plan.algorithm = "repair"
        # Look 32 groups ahead, not 256: in a filled band the relays' tone crossings are occupied traps, so a
        # group almost never joins a batch far ahead, and the scan of every batch over every group left was
        # the batching's cost (64 holes on 32 x 64: ~90 groups, ~90 batches). The same batches as 256 on 300
        # instances of up to 64 holes; 16 changed one.
        self.window = 32

    def _alloc(self, nx: int, ny: int, *, holes: int, free: int) -> None:
        """The kernels' arrays for up to ``holes`` holes and ``free`` free atoms (grown on demand, doubled)."""
        self._cap = (holes, free)
        per_path = 2 * (nx + ny)  # cells of one pair's hops: its path plus one repeated cell per hop, at most
        self._k_occ = np.zeros((ny, nx), dtype=np.bool_)
        self._k_free = np.zeros((free, 2), dtype=np.int64)
        self._k_holes = np.zeros((holes, 2), dtype=np.int64)
        self._k_row_cum = np.zeros((ny, nx + 1), dtype=np.int64)
        self._k_col_cum = np.zeros((ny + 1, nx), dtype=np.int64)
        self._k_cost = np.zeros((holes, free), dtype=np.float64)
        self._k_lsa_f = np.zeros((3, free), dtype=np.float64)
        self._k_lsa_i = np.zeros((5, max(holes, free)), dtype=np.int64)
        self._k_in_sr = np.zeros(holes, dtype=np.bool_)
        self._k_in_sc = np.zeros(free, dtype=np.bool_)
        self._k_route = np.zeros((nx + ny, 2), dtype=np.int64)
        self._k_route_alt = np.zeros((nx + ny, 2), dtype=np.int64)
        self._k_hop_ptr = np.zeros(holes * per_path + 1, dtype=np.int64)
        self._k_cells = np.zeros((holes * per_path, 2), dtype=np.int64)
        self._k_group_ptr = np.zeros(holes * per_path + 1, dtype=np.int64)
        self._k_last_touch = np.zeros((ny, nx), dtype=np.int64)
        self._k_merged_of = np.zeros(holes * per_path, dtype=np.int64)
        self._k_keys = np.zeros((holes * per_path, 3), dtype=np.int64)
        self._k_created_by = np.zeros(holes * per_path, dtype=np.int64)
        self._out_hop_ptr = np.zeros(holes * per_path + 1, dtype=np.int64)
        self._out_cells = np.zeros((holes * per_path, 2), dtype=np.int64)
        self._out_group_ptr = np.zeros(holes * per_path + 1, dtype=np.int64)
        self._n_hops = 0
        self._n_groups = 0

    def solve_moves(self, occupancy: np.ndarray, target: np.ndarray) -> int:
        """Assign, reroute, then put repairs whose paths line up into shared groups (``repair_kernels``);
        returns the steps."""
        if occupancy.shape != (self.ny, self.nx) or target.shape != (self.ny, self.nx):
            raise ValueError(f"occupancy {occupancy.shape} and target {target.shape} must both be {(self.ny, self.nx)}")
        self._solved = False
        occ = occupancy if occupancy.dtype == np.bool_ else occupancy.astype(bool)
        tgt = target if target.dtype == np.bool_ else target.astype(bool)
        n_atoms = int(np.count_nonzero(occ))
        n_holes = int(np.count_nonzero(tgt)) - int(np.count_nonzero(occ & tgt))
        n_free = n_atoms - (int(np.count_nonzero(tgt)) - n_holes)
        if n_free < n_holes:
            raise UnsolvableError(f"{n_atoms} atoms cannot fill {int(tgt.sum())} target traps")
        if n_holes > self._cap[0] or n_free > self._cap[1]:
            self._alloc(self.nx, self.ny, holes=max(n_holes, 2 * self._cap[0]), free=max(n_free, 2 * self._cap[1]))
        self._occ0[:] = occ
        w = self.loss
        n_hops, n_groups, n_steps = plan_repair(
            occ, tgt, OBJECTIVE_CODES[self.objective], w.per_transfer, w.per_step, w.per_slot_atom, self._k_occ,
            self._k_free, self._k_holes, self._k_row_cum, self._k_col_cum, self._k_cost, self._k_lsa_f,
            self._k_lsa_i, self._k_in_sr, self._k_in_sc, self._k_route, self._k_route_alt, self._k_hop_ptr,
            self._k_cells, self._k_group_ptr, self._k_last_touch, self._k_merged_of, self._k_keys,
            self._k_created_by, self._out_hop_ptr, self._out_cells, self._out_group_ptr,
        )  # fmt: skip
        self._n_hops, self._n_groups = n_hops, n_groups
        self._solved = True
        return n_steps

    def batch(self) -> Plan:
        if not self._solved:
            raise RuntimeError("batch() needs a successful solve_moves() first")
        return self._batch_hops(self._out_hop_ptr, self._n_hops, self._out_cells, self._out_group_ptr, self._n_groups)

    def hop_groups(self) -> list[list[list[tuple[int, int]]]]:
        """The last plan's hop groups before batching, as ``reference_hops`` returns them (for the tests)."""
        hp, cells, gp = self._out_hop_ptr, self._out_cells, self._out_group_ptr
        return [
            [[(int(r), int(c)) for r, c in cells[hp[k] : hp[k + 1]]] for k in range(gp[g], gp[g + 1])]
            for g in range(self._n_groups)
        ]

    def reference_hops(self, occupancy: np.ndarray, target: np.ndarray) -> list[list[list[tuple[int, int]]]]:
        """The kernels' reference, in plain Python over lists with scipy's assignment: the hop groups of the
        plan (the planner must be solved again before ``batch``)."""
        AssignmentPlanner.solve_moves(self, occupancy, target)
        self._merge_aligned()
        self._solved = False
        return [self._hops[a:b] for a, b in zip(self._groups[:-1], self._groups[1:], strict=True)]

    def _merge_aligned(self) -> None:
        """Straight single-hop repairs that start in one column and cover the same columns (or start in one
        row and cover the same rows) become one group: one column (row) tone and a row (column) tone per atom,
        so their product set is exactly their atoms, and they move together. A repair joins an earlier one
        only if no group in between touches its traps, so running it earlier changes nothing else."""
        hops, bounds = self._hops, self._groups
        groups = [hops[bounds[g] : bounds[g + 1]] for g in range(len(bounds) - 1)]
        merged: list[list[list[tuple[int, int]]]] = []
        key_of: list[tuple[int, int, int] | None] = []  # (axis, start, end) of a mergeable group
        touched: list[set[tuple[int, int]]] = []  # traps of every group from each merged group on
        for group in groups:
            cells = {site for hop in group for site in hop}
            key = _straight_key(group[0]) if len(group) == 1 else None
            joined = False
            if key is not None:
                for i in range(len(merged) - 1, -1, -1):
                    if key_of[i] == key:
                        later = touched[i + 1] if i + 1 < len(touched) else set()
                        if not later & cells:
                            merged[i].append(group[0])
                            joined = True
                        break
                    if touched[i] & cells:
                        break
            if not joined:
                merged.append(list(group))
                key_of.append(key)
                touched.append(set())
            for t in touched:
                t |= cells
        self._hops = [hop for group in merged for hop in group]
        self._groups = [0, *np.cumsum([len(g) for g in merged]).tolist()]

    def _pair_costs(self, occ: np.ndarray, free: np.ndarray, holes: np.ndarray) -> np.ndarray:
        steps = super()._pair_costs(occ, free, holes).astype(np.float64)
        if self.objective == "slots":
            return steps
        blockers = np.minimum(*route_atoms(occ, free, holes))
        moved = 1 + blockers  # the spare atom and the atoms it relays, each picked up and implanted once
        if self.objective == "transfers":
            return moved + steps / (steps.max() + 1.0)  # fewest atoms moved, then the shortest
        atoms = float(np.count_nonzero(occ))
        slots = steps + 2.0  # a pick-up, a slot per site, an implant (batching shares them: an upper bound)
        return self.loss.expected_loss(transfers=2.0 * moved, steps=steps, slots=slots, atoms=atoms)


def _straight_key(hop: list[tuple[int, int]]) -> tuple[int, int, int] | None:
    """(axis, start, end) of a hop along one row (axis 1: its columns) or one column (axis 0: its rows)."""
    (r0, c0), (r1, c1) = hop[0], hop[-1]
    if r0 == r1 and len(hop) == abs(c1 - c0) + 1:
        return (1, c0, c1)
    if c0 == c1 and len(hop) == abs(r1 - r0) + 1:
        return (0, r0, r1)
    return None
