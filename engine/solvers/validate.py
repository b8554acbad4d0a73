"""The plan validator: replay every waveform slot under the move model and prove the plan legal.

The physics is ``engine/move_model.py``, the same code the simulated lab runs on the tracks it decodes from
the AWG's samples (here with losses off): crossed AODs make a tweezer at every intersection of active tones,
loaded or not; an empty one at full depth that arrives over an atom captures it and drags it along; a loaded
one that meets an atom collides. This module adds the grammar of planned operations and the accounting.
Plain Python around one compiled replay: it is the independent check of the planners, used by tests and
benchmarks, never in the hot loop. Atoms carry identities through the replay, so the report can say how
often one atom was picked up and how far it travelled (each pick-up and each step risks losing it).

Grammar (``docs/ARCHITECTURE.md``; the crossed-AOD model is worked through in ``aod-parallel.md``):

``trap_source = "slm"`` (static traps, crossed AODs make mobile tweezers at rows x columns):
- tones are listed strictly ascending, on the grid, with deltas in {-1, 0, +1};
- ``EXTRACT`` (no tweezers on; deltas 0) ramps tweezers up over the product set;
- ``SHIFT``: the listed tones must be where the tweezers are; after the move they are still strictly
  ascending and on the grid (no crossing, no merging);
- ``IMPLANT``: the listed tones are the tweezers, and they ramp down;
- nothing may be held at the end.

Interstitial routing (``ops.half = 2``, ``engine/routing.py``): the tones list positions, half a site apart, of
which the even ones are sites; a delta moves a tone half a site; the tones of a slot stay at least a whole site
apart (two tones closer than that would make one tweezer); a tweezer may ramp down only over a trap (in a
channel its atom is lost); the plan's steps are half-site steps between neighbouring positions.

Physics (the move model): a loaded tweezer may not meet an atom (moving onto one, or implanting onto one);
an ``IDLE`` slot while atoms are held drops them (the AWG plays silence). An atom that an empty tweezer
captures on its way, or that an extract picks up, must be one the plan's steps move (it is **accounted**);
otherwise the plan disturbs an atom it did not mean to move, and is rejected. Every atom's steps and final trap
in the replay must match the plan's one-site steps.

``trap_source = "aod"`` (a chain whose traps are the x tones; every slot is a conveyor ``SHIFT``):
- the listed tones move by their deltas; an atom under a listed tone moves with it; a moving tone may only
  enter a site that is empty or left by another tone in the same slot (else that site's tone fades out
  under its atom); tones never cross or merge.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from engine import move_model as mm
from engine.operations import EXTRACT, IDLE, IMPLANT, SHIFT, Operations, OpKind, Plan
from engine.routing import n_positions, position_name, positions_of, trap_index, traps_of

__all__ = ["InvalidPlan", "PlanReport", "replay", "replay_steps", "validate"]


class InvalidPlan(ValueError):
    """A plan that breaks the AOD model or misses its target; the message names the slot and the rule."""


@dataclass
class PlanReport:
    """What a replay measured. ``occupancy`` is the static-trap occupancy after the last slot.

    ``captures``: atoms taken by an empty full-depth tweezer arriving over them (not by an extract);
    ``dragged``: captured atoms that then moved. Per atom (numbered in row-major order of the starting
    occupancy): ``atom_steps``, ``atom_pickups`` (extracts and captures), ``atom_captures``, ``atom_site``
    (its final trap, flat index).
    """

    occupancy: np.ndarray
    slots: int = 0
    batches: int = 0
    steps: int = 0
    atoms_moved: int = 0
    max_steps_per_atom: int = 0
    max_pickups_per_atom: int = 0
    captures: int = 0
    dragged: int = 0
    target_reached: bool = False
    atom_steps: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64), repr=False)
    atom_pickups: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64), repr=False)
    atom_captures: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64), repr=False)
    atom_site: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64), repr=False)

    def as_dict(self) -> dict[str, int | bool]:
        return {
            "slots": self.slots,
            "batches": self.batches,
            "steps": self.steps,
            "atoms_moved": self.atoms_moved,
            "max_steps_per_atom": self.max_steps_per_atom,
            "max_pickups_per_atom": self.max_pickups_per_atom,
            "captures": self.captures,
            "dragged": self.dragged,
            "target_reached": self.target_reached,
        }


def _fail(ops: Operations, i: int, why: str) -> InvalidPlan:
    return InvalidPlan(f"{ops.describe(i)}: {why}")


def _check_tones(ops: Operations, i: int, sites: np.ndarray, deltas: np.ndarray, n: int, axis: str) -> None:
    if sites.size and (sites.min() < 0 or sites.max() >= n):
        raise _fail(ops, i, f"{axis} tone off the array (0..{n - 1})")
    if np.any(np.diff(sites) <= 0):
        raise _fail(ops, i, f"{axis} tones are not strictly ascending")
    if np.any(np.diff(sites) < ops.half):
        raise _fail(ops, i, f"{axis} tones less than a site apart (one tweezer, not two)")
    if np.any(np.abs(deltas) > 1):
        raise _fail(ops, i, f"{axis} tone moves more than one site")


def _check_chain_grammar(ops: Operations, nx: int) -> None:
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
        move_to = dict(zip(src.tolist(), dst.tolist(), strict=True))
        for s, d in move_to.items():
            if move_to.get(d) == s:
                raise _fail(ops, i, f"tones at sites {s} and {d} cross")


def _check_tweezer_grammar(ops: Operations, ny: int, nx: int) -> int:
    """The slot sequence is extract, shifts, implant with consistent tones; returns the number of batches."""
    on = False
    ty = tx = np.zeros(0, dtype=np.int64)
    batches = 0
    for i in range(len(ops)):
        kind = int(ops.kind[i])
        ys, dys, xs, dxs = (a.astype(np.int64) for a in ops.tones(i))
        _check_tones(ops, i, ys, dys, ny, "y")
        _check_tones(ops, i, xs, dxs, nx, "x")
        if kind == IDLE:
            on = False
            continue
        if kind == EXTRACT:
            if on:
                raise _fail(ops, i, "extract while tweezers are still on")
            if np.any(dys) or np.any(dxs):
                raise _fail(ops, i, "extract tones must not move")
            if ys.size == 0 or xs.size == 0:
                raise _fail(ops, i, "extract with no tones on one axis")
            on, ty, tx = True, ys, xs
            batches += 1
            continue
        if not on:
            raise _fail(ops, i, f"{OpKind(kind).name} with no tweezers on (extract first)")
        if not (np.array_equal(ys, ty) and np.array_equal(xs, tx)):
            raise _fail(ops, i, f"tones listed at rows {ty.tolist()} x cols {tx.tolist()} are where the tweezers are")
        if kind == SHIFT:
            ny1, nx1 = ty + dys, tx + dxs
            if ny1.size and (ny1.min() < 0 or ny1.max() >= ny) or nx1.size and (nx1.min() < 0 or nx1.max() >= nx):
                raise _fail(ops, i, "a tweezer leaves the array")
            if np.any(np.diff(ny1) < ops.half) or np.any(np.diff(nx1) < ops.half):
                why = "tones cross or merge" if ops.half == 1 else "tones cross, merge or come within a site"
                raise _fail(ops, i, why)
            ty, tx = ny1, nx1
        elif kind == IMPLANT:
            on = False
        else:
            raise _fail(ops, i, f"unknown operation kind {kind}")
    return batches


def _play(
    ops: Operations, state: mm.MoveState, chain: bool, *, stop_on_capture: bool = False
) -> tuple[int, np.ndarray]:
    """Run the move model over all slots (identities on); returns (slot of the first fault or ``len(ops)``, events)."""
    events = mm.new_events()
    n = len(ops)
    at = mm.replay_operations(
        ops.kind, ops.y_site, ops.y_delta, ops.x_site, ops.x_delta, 0, n, chain, ops.half,
        state.static, state.held, state.held_mark, state.ids, state.atom_stats, True, state.arrivals,
        state.tweezers, state.chain_scratch, state.y_tracks, state.x_tracks, events, True, stop_on_capture,
    )  # fmt: skip
    return at, events


def _site(flat: int, nx: int, half: int = 1) -> str:
    """A flat index on a grid of ``nx`` columns of positions (``half`` per site) in sites."""
    return position_name(flat, nx, half)


def replay(ops: Operations, occupancy: np.ndarray, *, trap_source: str) -> PlanReport:
    """Replay ``ops`` from ``occupancy`` (``bool[ny, nx]``); raises ``InvalidPlan`` at the first broken rule.

    Captures are counted in the report, not rejected here: only ``validate`` knows whether the plan's steps
    account for them.
    """
    half = ops.half
    ny, nx = n_positions(occupancy.shape[0], half), n_positions(occupancy.shape[1], half)
    if (ops.ny, ops.nx) != (ny, nx):
        raise InvalidPlan(f"operations are for a {ops.ny}x{ops.nx} array, occupancy is {ny}x{nx}"
                          + (" (in positions: interstitial routing)" if half > 1 else ""))
    if trap_source == "aod":
        _check_chain_grammar(ops, nx)
        batches = len(ops)
    elif trap_source == "slm":
        batches = _check_tweezer_grammar(ops, ny, nx)
    else:
        raise ValueError(f"trap_source must be 'aod' or 'slm' (got {trap_source!r})")
    chain = trap_source == "aod"
    state = mm.MoveState(ny, nx)
    state.load(positions_of(occupancy, half))
    at, ev = _play(ops, state, chain)
    if at < len(ops):
        if ev[mm.EV_LOST_COLLISION]:
            where = _site(int(ev[mm.EV_FIRST_COLLISION]), nx, half)
            why = f"two atoms meet at {where}" if chain else f"a loaded tweezer lands on the atom at {where}"
            raise _fail(ops, at, why)
        where = _site(int(ev[mm.EV_FIRST_DROP]), nx, half)
        if ev[mm.EV_LOST_RELEASED] and not chain:
            raise _fail(ops, at, f"a loaded tweezer ramps down at {where}, between traps (its atom is lost)")
        if chain:
            raise _fail(ops, at, f"a moving tone enters {where}, which holds an atom (its own tone fades out under it)")
        if int(ops.kind[at]) == IDLE:
            raise _fail(ops, at, "an idle slot (silence) while tweezers hold atoms drops them")
        raise _fail(ops, at, f"the atom held at {where} is dropped (no tweezer holds it any more)")
    if state.held.any():
        raise InvalidPlan("the plan ends with atoms still in the tweezers")
    stats = state.atom_stats
    site = np.full(stats.shape[0], -1, dtype=np.int64)
    flat_id = state.ids[0].ravel()
    occupied = np.flatnonzero(flat_id >= 0)
    site[flat_id[occupied]] = occupied
    return PlanReport(
        occupancy=traps_of(state.static, half).copy(),
        slots=len(ops),
        batches=batches,
        steps=int(ev[mm.EV_STEPS]),
        atoms_moved=int(np.count_nonzero(stats[:, mm.STAT_STEPS])),
        max_steps_per_atom=int(stats[:, mm.STAT_STEPS].max(initial=0)),
        max_pickups_per_atom=int(stats[:, mm.STAT_PICKUPS].max(initial=0)),
        captures=int(ev[mm.EV_CAPTURED]),
        dragged=int(ev[mm.EV_DRAGGED]),
        atom_steps=stats[:, mm.STAT_STEPS].copy(),
        atom_pickups=stats[:, mm.STAT_PICKUPS].copy(),
        atom_captures=stats[:, mm.STAT_CAPTURES].copy(),
        atom_site=trap_index(site, occupancy.shape[1], half),
    )


def _replay_chain(ops: Operations, ident: np.ndarray, steps: np.ndarray) -> None:
    """Per-atom replay for callers that number atoms themselves (``server/bench_solvers.py``): moves
    ``ident`` (atom id per trap, -1 empty) to the final traps and adds each atom's steps to ``steps``."""
    _replay_ident(ops, ident, steps, np.zeros_like(steps), "aod")


def _replay_tweezers(ops: Operations, ident: np.ndarray, steps: np.ndarray, pickups: np.ndarray) -> int:
    """As ``_replay_chain`` for crossed AODs, also counting pick-ups per atom; returns the number of batches."""
    return _replay_ident(ops, ident, steps, pickups, "slm")


def _replay_ident(ops: Operations, ident: np.ndarray, steps: np.ndarray, pickups: np.ndarray, source: str) -> int:
    occ = ident >= 0
    order = ident[occ]  # caller's id of the atom numbered k in row-major order
    report = replay(ops, occ, trap_source=source)
    steps[order] += report.atom_steps
    pickups[order] += report.atom_pickups
    ident[:] = -1
    ident.ravel()[report.atom_site] = order
    return report.batches


def _replay_steps_ident(
    steps: np.ndarray, traps: np.ndarray, half: int = 1
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``replay_steps`` following each atom: (final occupancy, steps per atom, final trap per atom). With
    ``half = 2`` the steps are between positions (half-site steps, ``engine.routing``)."""
    occupancy = positions_of(traps, half)
    nx = occupancy.shape[1]
    ident = np.full(occupancy.size, -1, dtype=np.int64)
    n_atoms = int(occupancy.sum())
    ident[np.flatnonzero(occupancy.ravel())] = np.arange(n_atoms)
    per_atom = np.zeros(n_atoms, dtype=np.int64)
    for k, (src, dst) in enumerate(np.asarray(steps).tolist()):
        if ident[src] < 0 or ident[dst] >= 0:
            raise InvalidPlan(f"step {k} ({src} -> {dst}): source empty or destination occupied")
        if abs(src // nx - dst // nx) + abs(src % nx - dst % nx) != 1:
            raise InvalidPlan(f"step {k} ({src} -> {dst}) is not between neighbouring "
                              + ("traps" if half == 1 else "positions (half a site apart)"))
        per_atom[ident[src]] += 1
        ident[dst] = ident[src]
        ident[src] = -1
    site = np.full(n_atoms, -1, dtype=np.int64)
    occupied = np.flatnonzero(ident >= 0)
    site[ident[occupied]] = occupied
    final = (ident >= 0).reshape(occupancy.shape)
    if np.any(final & ~positions_of(traps_of(final, half), half)):
        raise InvalidPlan("the plan's steps leave an atom between traps")
    return traps_of(final, half).copy(), per_atom, trap_index(site, traps.shape[1], half)


def replay_steps(steps: np.ndarray, occupancy: np.ndarray) -> np.ndarray:
    """Replay one-site steps in order (source occupied, destination an empty neighbour); final occupancy."""
    return _replay_steps_ident(steps, occupancy)[0]


def validate(plan: Plan, occupancy: np.ndarray, target: np.ndarray, *, trap_source: str) -> PlanReport:
    """Replay ``plan`` from ``occupancy``; check it fills ``target``, that its ``steps`` move every atom as
    its slots do, and that every atom a tweezer takes (by an extract or a capture on its way) is one the
    steps move.

    Raises ``InvalidPlan`` with the first broken rule; returns the replay's figures.
    """
    report = replay(plan.operations, occupancy, trap_source=trap_source)
    nx = occupancy.shape[1]
    after_steps, plan_atom_steps, plan_atom_site = _replay_steps_ident(plan.steps, occupancy, plan.operations.half)
    start = np.flatnonzero(np.asarray(occupancy).ravel())
    unaccounted = np.flatnonzero((report.atom_captures > 0) & (plan_atom_steps == 0))
    if unaccounted.size:
        ops = plan.operations
        state = mm.MoveState(ops.ny, ops.nx)
        state.load(positions_of(occupancy, ops.half))
        at, ev = _play(ops, state, trap_source == "aod", stop_on_capture=True)
        raise _fail(
            ops, at,
            f"an empty tweezer at full depth arrives over the atom at "
            f"{_site(int(ev[mm.EV_FIRST_CAPTURE]), ops.nx, ops.half)} "
            f"and captures it; {unaccounted.size} atom(s) are disturbed that the plan's steps do not move "
            f"(first from {_site(int(start[unaccounted[0]]), nx)})",
        )  # fmt: skip
    idle = np.flatnonzero((report.atom_pickups > 0) & (plan_atom_steps == 0))
    if idle.size:
        raise InvalidPlan(
            f"the slots pick up {idle.size} atom(s) that the plan's steps never move (each pick-up and implant "
            f"risks the atom), first the one at {_site(int(start[idle[0]]), nx)}"
        )
    if not np.array_equal(after_steps, report.occupancy):
        raise InvalidPlan("the plan's one-site steps and its waveform slots leave the atoms in different traps")
    if report.steps != plan.n_steps:
        raise InvalidPlan(f"the slots displace atoms {report.steps} times but the plan lists {plan.n_steps} steps")
    differ = np.flatnonzero((plan_atom_steps != report.atom_steps) | (plan_atom_site != report.atom_site))
    if differ.size:
        a = int(differ[0])
        raise InvalidPlan(
            f"the atom from {_site(int(start[a]), nx)}: the slots move it {report.atom_steps[a]} sites to "
            f"{_site(int(report.atom_site[a]), nx)}, the plan's steps {plan_atom_steps[a]} sites to "
            f"{_site(int(plan_atom_site[a]), nx)}"
        )
    report.target_reached = bool(np.all(report.occupancy[target]))
    if not report.target_reached:
        missing = np.argwhere(target & ~report.occupancy)[:5].tolist()
        raise InvalidPlan(f"the plan leaves target traps empty, e.g. (row, col) {missing}")
    return report
