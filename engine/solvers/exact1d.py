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

The hot path is one numba call (``plan_chain``, from ``Exact1DPlanner.solve_moves``) that matches and
schedules into the planner's own buffers; ``batch`` only hands out the filled table. At ~5 us per plan, the
dispatch of a numba call (~0.1 us per argument) and any Python-side view or check are a visible share, so
the buffers are packed into few arrays and everything else is fixed in the constructor.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from engine.operations import EXTRACT, IMPLANT, SHIFT, Operations, Plan
from engine.solvers.base import UnsolvableError

__all__ = ["Exact1DPlanner", "match_chain", "match_chain_reference", "plan_chain"]

_INF = np.int64(1) << 40


@njit(cache=True, nogil=True)
def match_chain(
    occ: np.ndarray, target: np.ndarray, atoms: np.ndarray, sites: np.ndarray, cost: np.ndarray, take: np.ndarray,
    src: np.ndarray, dst: np.ndarray,
) -> tuple[int, int]:
    """Minimum-displacement order-preserving assignment of the atoms in ``occ`` to the traps in ``target``.

    Writes the ``T`` pairs into ``src[:T]``, ``dst[:T]`` (ascending) and returns ``(T, total displacement)``,
    or ``(-1, 0)`` when there are fewer atoms than targets. ``cost`` and ``take`` (int64) are
    ``(n + 1) * (n + 2)`` scratch.

    Written without data-dependent branches in the loops (random occupancies defeat the branch predictor,
    which cost more than the arithmetic): the site lists are built by conditional increments, and every
    cell of the band is a ``min`` of its two moves.
    """
    n = occ.shape[0]
    k = 0
    t = 0
    for i in range(n):  # atoms[k] and sites[t] are overwritten until occupied / targeted
        atoms[k] = i
        k += occ[i] != 0
        sites[t] = i
        t += target[i] != 0
    if k < t:
        return -1, 0
    e_max = k - t
    # cost[i * w + 1 + e]: best cost after the first i atoms with e of them skipped (so i - e targets
    # filled); column 0 of each row is an unreachable sentinel, the "e = -1" that a skip into e = 0 reads
    w = e_max + 2
    cost[0] = _INF
    cost[1] = 0
    for i in range(k):
        row = i * w + 1
        nxt = row + w
        cost[nxt - 1] = _INF
        a = atoms[i]
        # reachable cells of row i + 1 with i - e < t, where atom i may fill target i - e
        for e in range(max(0, i + 1 - t), min(i, e_max) + 1):
            c_take = cost[row + e] + abs(a - sites[i - e])
            c_skip = cost[row + e - 1]  # atom i stays out
            take[nxt + e] = c_take < c_skip  # ties: stay out
            cost[nxt + e] = min(c_take, c_skip)
        if i + 1 <= e_max:  # all of the first i + 1 atoms stay out
            cost[nxt + i + 1] = cost[row + i]
            take[nxt + i + 1] = 0
    e = e_max
    j = t
    for i in range(k, 0, -1):
        if take[i * w + 1 + e]:
            j -= 1
            src[j] = atoms[i - 1]
            dst[j] = sites[j]
        else:
            e -= 1
    return t, cost[k * w + 1 + e_max]


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
    src: np.ndarray, dst: np.ndarray, n_pairs: int, conveyor: bool, n_old: int, kind: np.ndarray,
    y_site: np.ndarray, x_site: np.ndarray, x_delta: np.ndarray, steps: np.ndarray, site: np.ndarray,
    sign: np.ndarray, left: np.ndarray,
) -> tuple[int, int]:
    """Fill the operation table of row 0 (from slot 0, clearing the ``n_old`` slots of the previous plan) and
    the one-site steps (flat trap index = site); returns ``(n_slots, n_steps)``.

    ``conveyor``: AOD-chain SHIFT slots of the moving tones only; otherwise EXTRACT, SHIFTs, IMPLANT of
    the movers (SLM traps). Returns ``(-1, 0)`` if the table has too few slots. ``site``, ``sign`` and
    ``left`` (int64[n]) are scratch: the movers' current sites, directions and sites still to go. A
    conveyor drops a mover from the list when it arrives, so the work is the number of steps, not
    slots x pairs.
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
    for p in range(n_pairs):  # the movers, ascending (a pair that stays put is overwritten by the next)
        d = dst[p] - src[p]
        site[n_mov] = src[p]
        sign[n_mov] = 1 if d > 0 else -1
        left[n_mov] = abs(d)
        n_mov += d != 0
        longest = max(longest, abs(d))
    if n_mov == 0:
        return 0, 0
    n_slots = longest if conveyor else longest + 2
    if n_slots > kind.shape[0]:
        return -1, 0
    slot = 0
    if not conveyor:
        kind[0] = EXTRACT
        y_site[0, 0] = 0
        for q in range(n_mov):
            x_site[0, q] = site[q]
        slot = 1
    n_steps = 0
    n_act = n_mov
    for _ in range(longest):
        kind[slot] = SHIFT
        y_site[slot, 0] = 0
        for q in range(n_act):  # an arrived tweezer (slm) waits with delta 0, still holding its atom
            x_site[slot, q] = site[q]
            x_delta[slot, q] = sign[q] if left[q] > 0 else 0
        # steps in an order that is legal one at a time: right-movers from the right, then left-movers;
        # every tone writes a row, kept (n_steps advances) only for a step of that direction
        for q in range(n_act - 1, -1, -1):
            steps[n_steps, 0] = site[q]
            steps[n_steps, 1] = site[q] + 1
            n_steps += x_delta[slot, q] > 0
        for q in range(n_act):
            steps[n_steps, 0] = site[q]
            steps[n_steps, 1] = site[q] - 1
            n_steps += x_delta[slot, q] < 0
        kept = 0
        for q in range(n_act):  # advance every mover by its delta; a conveyor forgets the arrived ones
            delta = x_delta[slot, q]
            to_go = left[q] - abs(delta)
            site[kept] = site[q] + delta
            sign[kept] = sign[q]
            left[kept] = to_go
            kept += to_go > 0 or not conveyor
        n_act = kept
        slot += 1
    if not conveyor:
        kind[slot] = IMPLANT
        y_site[slot, 0] = 0
        for q in range(n_mov):
            x_site[slot, q] = site[q]
        slot += 1
    return slot, n_steps


@njit(cache=True, nogil=True)
def plan_chain(
    occ: np.ndarray, target: np.ndarray, conveyor: bool, work: np.ndarray, dp: np.ndarray, n_old: int,
    kind: np.ndarray, y_site: np.ndarray, x_site: np.ndarray, x_delta: np.ndarray, steps: np.ndarray,
) -> tuple[int, int, int]:
    """``match_chain`` then ``schedule_chain`` for ``occ``, ``target`` (``bool[1, n]``) in one call; returns
    ``(n_pairs, n_slots, n_steps)``, or ``(-1, 0, 0)`` with the table untouched when there are too few atoms.

    ``work`` (int64[7, n]) holds the atoms, sites, sources, destinations and the movers' sites, signs and
    sites to go; ``dp`` (int64[2, (n + 1) * (n + 2)]) the programme's costs and choices: two arrays instead
    of nine keep the call's dispatch short.
    """
    src, dst = work[2], work[3]
    n_pairs, _ = match_chain(occ[0], target[0], work[0], work[1], dp[0], dp[1], src, dst)
    if n_pairs < 0:
        return -1, 0, 0
    n_slots, n_steps = schedule_chain(
        src, dst, n_pairs, conveyor, n_old, kind, y_site, x_site, x_delta, steps, work[4], work[5], work[6]
    )
    return n_pairs, n_slots, n_steps


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
        self._shape = (1, nx)
        self._work = np.zeros((7, nx), dtype=np.int64)
        self._dp = np.zeros((2, (nx + 1) * (nx + 2)), dtype=np.int64)
        self._steps = np.zeros((nx * nx, 2), dtype=np.int32)
        self.operations = Operations(nx=nx, ny=1, capacity=nx + 2)
        self._plan = Plan(steps=self._steps[:0], operations=self.operations, algorithm="exact-1d")
        self._n_steps = -1
        self._warm_up()

    def _warm_up(self) -> None:
        occ = np.zeros(self._shape, dtype=bool)
        occ[0, ::2] = True
        target = np.zeros_like(occ)
        target[0, : max(1, self.nx // 4)] = True
        self.solve_moves(occ, target)
        self.batch()
        self.operations.clear()
        self._n_steps = -1

    def check_target(self, target: np.ndarray) -> None:
        """Any set of traps on the row is a valid target; only the shape is checked."""
        if target.shape != self._shape:
            raise ValueError(f"target shape {target.shape} must be (1, {self.nx})")

    def solve_moves(self, occupancy: np.ndarray, target: np.ndarray) -> int:
        """Assign atoms to targets and schedule their slots; returns the number of one-site steps.

        Raises ``UnsolvableError`` (the previous plan is then gone: ``batch`` refuses until a solve succeeds).
        """
        if occupancy.shape != self._shape or target.shape != self._shape:  # the kernel does not bound-check
            raise ValueError(f"occupancy {occupancy.shape} and target {target.shape} must both be (1, {self.nx})")
        ops = self.operations
        n_pairs, n_slots, n_steps = plan_chain(
            occupancy, target, self.conveyor, self._work, self._dp, ops.n, ops.kind, ops.y_site, ops.x_site,
            ops.x_delta, self._steps,
        )  # fmt: skip
        if n_pairs < 0:
            self._n_steps = -1

            raise UnsolvableError(f"{int(occupancy.sum())} atoms cannot fill {int(target.sum())} target traps")
        if n_slots < 0:  # cannot happen: the table holds nx + 2 slots and a plan needs at most nx + 1
            raise RuntimeError("exact-1d: operation table too small")
        ops.n = n_slots
        self._n_steps = n_steps
        return n_steps

    def batch(self) -> Plan:
        """The waveform slots of the last solve (a view of the planner's table, reused next time)."""
        if self._n_steps < 0:
            raise RuntimeError("batch() needs a successful solve_moves() first")
        plan = self._plan
        plan.steps = self._steps[: self._n_steps]
        return plan
