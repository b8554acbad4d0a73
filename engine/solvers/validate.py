"""The plan validator: replay every waveform slot under the AOD model and prove the plan legal.

Plain numpy on purpose: it is the independent check of the numba planners, used by tests and benchmarks,
never in the hot loop. Atoms carry identities through the replay, so the report can say how often one atom
was picked up and how far it travelled (each pick-up and each step risks losing it).

Rules (``docs/ARCHITECTURE.md``; the crossed-AOD model is worked through in ``aod-parallel.md``):

``trap_source = "slm"`` (static traps, crossed AODs make mobile tweezers at rows x columns):
- tones are listed strictly ascending, on the grid, with deltas in {-1, 0, +1};
- ``EXTRACT`` (nothing held yet; deltas 0): every atom at the product set goes into the tweezer above it;
- ``SHIFT``: the listed tones must be where the tweezers are; after the move they are still strictly
  ascending and on the grid (no crossing, no merging); a loaded tweezer that moves must land on an empty trap;
- ``IMPLANT``: the listed tones are the tweezers; each loaded one leaves its atom in the (empty) trap below;
- ``IDLE`` while atoms are held drops them (the AWG plays silence): invalid. Nothing may be held at the end.

``trap_source = "aod"`` (a chain whose traps are the x tones; every slot is a conveyor ``SHIFT``):
- the listed tones move by their deltas; an atom under a listed tone moves with it; a moving tone may only
  enter a site that is empty or left by another tone in the same slot; tones never cross or merge.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from engine.operations import EXTRACT, IDLE, IMPLANT, SHIFT, Operations, OpKind, Plan

__all__ = ["InvalidPlan", "PlanReport", "replay", "replay_steps", "validate"]


class InvalidPlan(ValueError):
    """A plan that breaks the AOD model or misses its target; the message names the slot and the rule."""


@dataclass
class PlanReport:
    """What a replay measured. ``occupancy`` is the static-trap occupancy after the last slot."""

    occupancy: np.ndarray
    slots: int = 0
    batches: int = 0
    steps: int = 0
    atoms_moved: int = 0
    max_steps_per_atom: int = 0
    max_pickups_per_atom: int = 0
    target_reached: bool = False

    def as_dict(self) -> dict[str, int | bool]:
        return {
            "slots": self.slots,
            "batches": self.batches,
            "steps": self.steps,
            "atoms_moved": self.atoms_moved,
            "max_steps_per_atom": self.max_steps_per_atom,
            "max_pickups_per_atom": self.max_pickups_per_atom,
            "target_reached": self.target_reached,
        }


def _fail(ops: Operations, i: int, why: str) -> InvalidPlan:
    return InvalidPlan(f"{ops.describe(i)}: {why}")


def _check_tones(ops: Operations, i: int, sites: np.ndarray, deltas: np.ndarray, n: int, axis: str) -> None:
    if sites.size and (sites.min() < 0 or sites.max() >= n):
        raise _fail(ops, i, f"{axis} tone off the array (0..{n - 1})")
    if np.any(np.diff(sites) <= 0):
        raise _fail(ops, i, f"{axis} tones are not strictly ascending")
    if np.any(np.abs(deltas) > 1):
        raise _fail(ops, i, f"{axis} tone moves more than one site")


def replay(ops: Operations, occupancy: np.ndarray, *, trap_source: str) -> PlanReport:
    """Replay ``ops`` from ``occupancy`` (``bool[ny, nx]``); raises ``InvalidPlan`` at the first broken rule."""
    ny, nx = occupancy.shape
    if (ops.ny, ops.nx) != (ny, nx):
        raise InvalidPlan(f"operations are for a {ops.ny}x{ops.nx} array, occupancy is {ny}x{nx}")
    ident = np.full((ny, nx), -1, dtype=np.int64)  # atom id in each static trap
    ident[occupancy] = np.arange(int(occupancy.sum()))
    n_atoms = int(occupancy.sum())
    steps = np.zeros(n_atoms, dtype=np.int64)
    pickups = np.zeros(n_atoms, dtype=np.int64)
    report = PlanReport(occupancy=occupancy)
    if trap_source == "aod":
        _replay_chain(ops, ident, steps)
        report.batches = len(ops)
    elif trap_source == "slm":
        report.batches = _replay_tweezers(ops, ident, steps, pickups)
    else:
        raise ValueError(f"trap_source must be 'aod' or 'slm' (got {trap_source!r})")
    report.occupancy = ident >= 0
    report.slots = len(ops)
    report.steps = int(steps.sum())
    report.atoms_moved = int(np.count_nonzero(steps))
    report.max_steps_per_atom = int(steps.max(initial=0))
    report.max_pickups_per_atom = int(pickups.max(initial=0))
    return report


def _replay_chain(ops: Operations, ident: np.ndarray, steps: np.ndarray) -> None:
    row = ident[0]
    nx = row.size
    for i in range(len(ops)):
        kind = int(ops.kind[i])
        if kind == IDLE:
            continue
        if kind != SHIFT:
            raise _fail(ops, i, f"an AOD chain only shifts tones, not {OpKind(kind).name}")
        _, _, xs, dxs = (a.astype(np.int64) for a in ops.tones(i))
        _check_tones(ops, i, xs, dxs, nx, "x")
        ends = xs + dxs
        if ends.size and (ends.min() < 0 or ends.max() >= nx):
            raise _fail(ops, i, "a tone leaves the chain")
        movers = dxs != 0
        src, dst = xs[movers], ends[movers]
        if np.unique(dst).size != dst.size:
            raise _fail(ops, i, "two tones merge")
        move_to = dict(zip(src.tolist(), dst.tolist()))
        for s, d in move_to.items():
            if move_to.get(d) == s:
                raise _fail(ops, i, f"tones at sites {s} and {d} cross")
            if d not in move_to and row[d] >= 0:
                raise _fail(ops, i, f"the tone from site {s} enters site {d}, which holds an atom")
        moving_ids = row[src].copy()
        row[src] = -1
        row[dst] = moving_ids
        carried = moving_ids[moving_ids >= 0]
        steps[carried] += 1


def _replay_tweezers(ops: Operations, ident: np.ndarray, steps: np.ndarray, pickups: np.ndarray) -> int:
    ny, nx = ident.shape
    held: np.ndarray | None = None  # atom id per tweezer [len(ty), len(tx)], -1 = empty
    ty = tx = np.zeros(0, dtype=np.int64)
    batches = 0
    for i in range(len(ops)):
        kind = int(ops.kind[i])
        ys, dys, xs, dxs = (a.astype(np.int64) for a in ops.tones(i))
        _check_tones(ops, i, ys, dys, ny, "y")
        _check_tones(ops, i, xs, dxs, nx, "x")
        if kind == IDLE:
            if held is not None and np.any(held >= 0):
                raise _fail(ops, i, "an idle slot (silence) while tweezers hold atoms drops them")
            held = None
            continue
        if kind == EXTRACT:
            if held is not None:
                raise _fail(ops, i, "extract while tweezers are still on")
            if np.any(dys) or np.any(dxs):
                raise _fail(ops, i, "extract tones must not move")
            if ys.size == 0 or xs.size == 0:
                raise _fail(ops, i, "extract with no tones on one axis")
            ty, tx = ys, xs
            held = ident[np.ix_(ty, tx)].copy()
            ident[np.ix_(ty, tx)] = -1
            pickups[held[held >= 0]] += 1
            batches += 1
            continue
        if held is None:
            raise _fail(ops, i, f"{OpKind(kind).name} with no tweezers on (extract first)")
        if not (np.array_equal(ys, ty) and np.array_equal(xs, tx)):
            raise _fail(ops, i, f"tones listed at rows {ty.tolist()} x cols {tx.tolist()} are where the tweezers are")
        if kind == SHIFT:
            ny1, nx1 = ty + dys, tx + dxs
            if ny1.size and (ny1.min() < 0 or ny1.max() >= ny) or nx1.size and (nx1.min() < 0 or nx1.max() >= nx):
                raise _fail(ops, i, "a tweezer leaves the array")
            if np.any(np.diff(ny1) <= 0) or np.any(np.diff(nx1) <= 0):
                raise _fail(ops, i, "tones cross or merge")
            moved = (dys[:, None] != 0) | (dxs[None, :] != 0)
            loaded = held >= 0
            clash = loaded & moved & (ident[np.ix_(ny1, nx1)] >= 0)
            if np.any(clash):
                r, c = np.argwhere(clash)[0]
                raise _fail(ops, i, f"a loaded tweezer lands on the atom at row {ny1[r]}, col {nx1[c]}")
            steps[held[loaded & moved]] += 1
            ty, tx = ny1, nx1
        elif kind == IMPLANT:
            loaded = held >= 0
            below = ident[np.ix_(ty, tx)]
            if np.any(loaded & (below >= 0)):
                raise _fail(ops, i, "implant onto an occupied trap")
            ident[np.ix_(ty, tx)] = np.where(loaded, held, below)
            held = None
        else:
            raise _fail(ops, i, f"unknown operation kind {kind}")
    if held is not None and np.any(held >= 0):
        raise InvalidPlan("the plan ends with atoms still in the tweezers")
    return batches


def replay_steps(steps: np.ndarray, occupancy: np.ndarray) -> np.ndarray:
    """Replay one-site steps in order (source occupied, destination an empty neighbour); final occupancy."""
    grid = occupancy.copy().ravel()
    nx = occupancy.shape[1]
    for k, (src, dst) in enumerate(np.asarray(steps).tolist()):
        if not grid[src] or grid[dst]:
            raise InvalidPlan(f"step {k} ({src} -> {dst}): source empty or destination occupied")
        if abs(src // nx - dst // nx) + abs(src % nx - dst % nx) != 1:
            raise InvalidPlan(f"step {k} ({src} -> {dst}) is not between neighbouring traps")
        grid[src] = False
        grid[dst] = True
    return grid.reshape(occupancy.shape)


def validate(plan: Plan, occupancy: np.ndarray, target: np.ndarray, *, trap_source: str) -> PlanReport:
    """Replay ``plan`` from ``occupancy``; check it fills ``target`` and that its ``steps`` say the same.

    Raises ``InvalidPlan`` with the first broken rule; returns the replay's figures.
    """
    report = replay(plan.operations, occupancy, trap_source=trap_source)
    after_steps = replay_steps(plan.steps, occupancy)
    if not np.array_equal(after_steps, report.occupancy):
        raise InvalidPlan("the plan's one-site steps and its waveform slots leave the atoms in different traps")
    if report.steps != plan.n_steps:
        raise InvalidPlan(f"the slots displace atoms {report.steps} times but the plan lists {plan.n_steps} steps")
    report.target_reached = bool(np.all(report.occupancy[target]))
    if not report.target_reached:
        missing = np.argwhere(target & ~report.occupancy)[:5].tolist()
        raise InvalidPlan(f"the plan leaves target traps empty, e.g. (row, col) {missing}")
    return report
