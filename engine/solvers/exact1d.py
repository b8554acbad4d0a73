"""The exact 1D solver: minimum total displacement on a chain, streamed one waveform slot per parallel step.

On a line an optimal assignment of atoms to targets never lets two atoms cross, so the only decision is
which ``E = K - T`` surplus atoms stay out (see ``docs/algorithms.md`` of the design notes, section 2.1). We
solve it with a banded dynamic programme over (atoms seen, atoms skipped): ``K x (E + 1)`` cells, about 250
for the paper's 1x64 -> 32 problem, so it runs in a microsecond or two and is obviously exact, which is
what matters more than asymptotics at these sizes.

Two facts make the parallel schedule legal (``tests/test_solver_exact1d.py`` checks both on every plan):

- an optimal assignment never carries an atom over an atom that stays out (matching the skipped atom
  instead would be strictly cheaper), so no mover ever enters a trap holding a bystander;
- a right-mover and a left-mover never want the same trap or each other's (that would be a crossing).

So every slot moves *every* atom that has not arrived yet by one site towards its target, right- and
left-movers together, and a plan takes ``max |displacement|`` slots. For an AOD chain (``trap_source =
"aod"``) each slot is a conveyor ``SHIFT`` of the moving tones; for SLM traps the movers are extracted
once, shifted together (arrived tweezers wait with delta 0) and implanted.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from engine.operations import EXTRACT, IMPLANT, SHIFT, Operations, Plan

__all__ = ["Exact1DPlanner", "match_chain", "match_chain_reference"]

_INF = np.int64(1) << 40


@njit(cache=True, nogil=True)
def match_chain(
    occ: np.ndarray, target: np.ndarray, atoms: np.ndarray, sites: np.ndarray, cost: np.ndarray, take: np.ndarray,
    src: np.ndarray, dst: np.ndarray,
) -> int:
    """Minimum-displacement order-preserving assignment of the atoms in ``occ`` to the traps in ``target``.

    Writes the ``T`` pairs into ``src[:T]``, ``dst[:T]`` (ascending) and returns ``(T, total displacement)``,
    or ``(-1, 0)`` when there are fewer atoms than targets. ``cost`` (int64) and ``take`` (uint8) are ``(n + 1) * (n + 1)`` scratch.
    """
    n = occ.shape[0]
    k = 0
    t = 0
    for i in range(n):
        if occ[i]:
            atoms[k] = i
            k += 1
        if target[i]:
            sites[t] = i
            t += 1
    if k < t:
        return -1, 0
    e_max = k - t
    w = e_max + 1
    # cost[i * w + e]: best cost after the first i atoms with e of them skipped (so i - e targets filled)
    for e in range(w):
        cost[e] = _INF
    cost[0] = 0
    for i in range(k):
        row = i * w
        nxt = row + w
        for e in range(w):
            cost[nxt + e] = _INF
        for e in range(min(i, e_max) + 1):
            c = cost[row + e]
            if c >= _INF:
                continue
            j = i - e
            if j < t:  # atom i fills target j
                d = atoms[i] - sites[j]
                c_take = c + (d if d >= 0 else -d)
                if c_take < cost[nxt + e]:
                    cost[nxt + e] = c_take
                    take[nxt + e] = 1
            if e < e_max:  # atom i stays out
                if c < cost[nxt + e + 1]:
                    cost[nxt + e + 1] = c
                    take[nxt + e + 1] = 0
    e = e_max
    j = t
    for i in range(k, 0, -1):
        if take[i * w + e]:
            j -= 1
            src[j] = atoms[i - 1]
            dst[j] = sites[j]
        else:
            e -= 1
    return t, cost[k * w + e_max]


def match_chain_reference(occ: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    """Plain-numpy twin of ``match_chain`` (same recurrence, Python loops) for tests."""
    atoms = np.flatnonzero(occ)
    sites = np.flatnonzero(target)
    k, t = atoms.size, sites.size
    if k < t:
        return None
    e_max = k - t
    inf = float("inf")
    cost = np.full((k + 1, e_max + 1), inf)
    take = np.zeros((k + 1, e_max + 1), dtype=bool)
    cost[0, 0] = 0
    for i in range(k):
        for e in range(min(i, e_max) + 1):
            if cost[i, e] == inf:
                continue
            j = i - e
            if j < t and cost[i, e] + abs(atoms[i] - sites[j]) < cost[i + 1, e]:
                cost[i + 1, e] = cost[i, e] + abs(atoms[i] - sites[j])
                take[i + 1, e] = True
            if e < e_max and cost[i, e] < cost[i + 1, e + 1]:
                cost[i + 1, e + 1] = cost[i, e]
                take[i + 1, e + 1] = False
    src, e, j = np.zeros(t, dtype=np.int64), e_max, t
    for i in range(k, 0, -1):
        if take[i, e]:
            j -= 1
            src[j] = atoms[i - 1]
        else:
            e -= 1
    return src, sites.astype(np.int64)


@njit(cache=True, nogil=True)
def schedule_chain(
    src: np.ndarray, dst: np.ndarray, n_pairs: int, conveyor: bool, row: int, nx: int,
    n_old: int, kind: np.ndarray, y_site: np.ndarray, x_site: np.ndarray, x_delta: np.ndarray, steps: np.ndarray,
) -> tuple[int, int]:
    """Fill the operation table (from slot 0, clearing the ``n_old`` slots of the previous plan) and the
    one-site steps; returns ``(n_slots, n_steps)``.

    ``conveyor``: AOD-chain SHIFT slots of the moving tones only; otherwise EXTRACT, SHIFTs, IMPLANT of
    the movers (SLM traps). Returns ``(-1, 0)`` if the table has too few slots.
    """
    for i in range(n_old):
        kind[i] = 0
        y_site[i, 0] = -1
        for m in range(x_site.shape[1]):
            if x_site[i, m] < 0:
                break
            x_site[i, m] = -1
            x_delta[i, m] = 0
    n_mov = 0
    longest = 0
    for p in range(n_pairs):
        d = dst[p] - src[p]
        if d != 0:
            n_mov += 1
            if abs(d) > longest:
                longest = abs(d)
    if n_mov == 0:
        return 0, 0
    n_slots = longest if conveyor else longest + 2
    if n_slots > kind.shape[0]:
        return -1, 0
    slot = 0
    if not conveyor:
        kind[0] = EXTRACT
        y_site[0, 0] = row
        m = 0
        for p in range(n_pairs):
            if dst[p] != src[p]:
                x_site[0, m] = src[p]
                m += 1
        slot = 1
    n_steps = 0
    base = row * nx
    for s in range(longest):
        kind[slot] = SHIFT
        y_site[slot, 0] = row
        m = 0
        for p in range(n_pairs):
            d = dst[p] - src[p]
            if d == 0:
                continue
            dist = abs(d)
            sign = 1 if d > 0 else -1
            if s < dist:
                x_site[slot, m] = src[p] + sign * s
                x_delta[slot, m] = sign
                m += 1
            elif not conveyor:  # an arrived tweezer waits, still holding its atom
                x_site[slot, m] = dst[p]
                x_delta[slot, m] = 0
                m += 1
        # steps in an order that is legal one at a time: right-movers from the right, then left-movers
        for q in range(m - 1, -1, -1):
            if x_delta[slot, q] > 0:
                steps[n_steps, 0] = base + x_site[slot, q]
                steps[n_steps, 1] = base + x_site[slot, q] + 1
                n_steps += 1
        for q in range(m):
            if x_delta[slot, q] < 0:
                steps[n_steps, 0] = base + x_site[slot, q]
                steps[n_steps, 1] = base + x_site[slot, q] - 1
                n_steps += 1
        slot += 1
    if not conveyor:
        kind[slot] = IMPLANT
        y_site[slot, 0] = row
        m = 0
        for p in range(n_pairs):
            if dst[p] != src[p]:
                x_site[slot, m] = dst[p]
                m += 1
        slot += 1
    return slot, n_steps


class Exact1DPlanner:
    """Exact 1D planning for a one-row array; buffers sized once, kernels compiled in the constructor."""

    def __init__(self, nx: int, ny: int = 1, *, trap_source: str = "aod") -> None:
        if ny != 1:
            raise ValueError(
                f"exact-1d plans a single row (ny = 1) but the array has ny = {ny}; "
                "use red-rec, red-rec-wide or another 2D algorithm"
            )
        if trap_source not in ("aod", "slm"):
            raise ValueError(f"trap_source must be 'aod' or 'slm' (got {trap_source!r})")
        self.nx = nx
        self.ny = 1
        self.conveyor = trap_source == "aod"
        self._atoms = np.zeros(nx, dtype=np.int64)
        self._sites = np.zeros(nx, dtype=np.int64)
        self._cost = np.zeros((nx + 1) * (nx + 1), dtype=np.int64)
        self._take = np.zeros((nx + 1) * (nx + 1), dtype=np.uint8)
        self._src = np.zeros(nx, dtype=np.int64)
        self._dst = np.zeros(nx, dtype=np.int64)
        self._steps = np.zeros((nx * nx, 2), dtype=np.int32)
        self.operations = Operations(nx=nx, ny=1, capacity=nx + 2)
        self._plan = Plan(steps=self._steps[:0], operations=self.operations, algorithm="exact-1d")
        self._n_pairs = -1
        self._warm_up()

    def _warm_up(self) -> None:
        occ = np.zeros((1, self.nx), dtype=bool)
        occ[0, ::2] = True
        target = np.zeros_like(occ)
        target[0, : max(1, self.nx // 4)] = True
        self.solve_moves(occ, target)
        self.batch()
        self.operations.clear()
        self._n_pairs = -1

    def check_target(self, target: np.ndarray) -> None:
        """Any set of traps on the row is a valid target; only the shape is checked."""
        if target.shape != (1, self.nx):
            raise ValueError(f"target shape {target.shape} must be (1, {self.nx})")

    def solve_moves(self, occupancy: np.ndarray, target: np.ndarray) -> int:
        """Assign atoms to targets; returns the number of one-site steps. Raises ``UnsolvableError``."""
        if occupancy.shape != (1, self.nx) or target.shape != (1, self.nx):
            raise ValueError(f"occupancy {occupancy.shape} and target {target.shape} must both be (1, {self.nx})")
        self._n_pairs, n_steps = match_chain(
            occupancy[0], target[0], self._atoms, self._sites, self._cost, self._take, self._src, self._dst
        )
        if self._n_pairs < 0:
            from engine.solvers import UnsolvableError  # the package imports this module

            raise UnsolvableError(f"{int(occupancy.sum())} atoms cannot fill {int(target.sum())} target traps")
        return n_steps

    def batch(self) -> Plan:
        """The waveform slots of the last solve (a view of the planner's table, reused next time)."""
        if self._n_pairs < 0:
            raise RuntimeError("batch() needs a successful solve_moves() first")
        ops = self.operations
        n_slots, n_steps = schedule_chain(
            self._src, self._dst, self._n_pairs, self.conveyor, 0, self.nx,
            ops.n, ops.kind, ops.y_site, ops.x_site, ops.x_delta, self._steps,
        )  # fmt: skip
        if n_slots < 0:  # cannot happen: the table holds nx + 2 slots and a plan needs at most nx + 1
            raise RuntimeError("exact-1d: operation table too small")
        ops.n = n_slots
        plan = self._plan
        plan.steps = self._steps[:n_steps]
        return plan
