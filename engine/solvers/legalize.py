"""Make a crossed-AOD plan legal under the complete move model by splitting the batches that are not.

Crossed AODs make a tweezer at every intersection of the active tones, loaded or not. A planner that picks
atoms on a product set of rows x columns also makes empty tweezers at the intersections without an atom;
when one of those arrives over an occupied trap it captures that atom (``engine/move_model.py``), which
the plan did not mean to move. This pass replays each batch (extract, shifts, implant) through the move
model from the occupancy the plan has reached; a batch that captures or collides is replaced by smaller
batches in which every tweezer is loaded (no empty tweezer exists, so none can capture):

- the batch's rows are grouped by the set of columns they hold atoms in (rows with the same set form a
  product set with no empty intersection), or its columns by their set of rows, whichever makes fewer groups;
- the groups run one after another, each with the batch's own tone moves (slots where none of its tones
  moves are left out), in an order where no group's tweezers meet an atom: a group goes when its path is
  clear now and its destinations lie on no waiting group's path; if none can, the groups split into single
  atoms, which are ordered the same way.

Every atom keeps its path, so the plan's one-site steps are rewritten in the new execution order. Plans
whose batches are all legal (red-rec's, most of the time) come back unchanged after one compiled replay.
"""

from __future__ import annotations

import numpy as np

from engine import move_model as mm
from engine.operations import EXTRACT, IMPLANT, SHIFT, Operations, Plan

__all__ = ["PlanLegalizer"]


class PlanLegalizer:
    """Checks and repairs plans for one ``ny x nx`` array; owns the buffers of the plans it rewrites."""

    def __init__(self, ny: int, nx: int) -> None:
        self.ny = ny
        self.nx = nx
        self._state = mm.MoveState(ny, nx)
        self._events = mm.new_events()
        self.operations = Operations(nx=nx, ny=ny, capacity=64)
        self.batches_split = 0

    def _play(self, ops: Operations, first: int, stop: int, static: np.ndarray) -> bool:
        """Replay slots ``first..stop-1`` from ``static`` (losses off); True when nothing is captured or hit."""
        st = self._state
        st.static[:] = static
        st.held[:] = False
        ev = self._events
        ev[:] = 0
        ev[mm.EV_FIRST_COLLISION :] = -1
        mm.replay_operations(
            ops.kind, ops.y_site, ops.y_delta, ops.x_site, ops.x_delta, first, stop, False,
            st.static, st.held, st.held_mark, st.static_id, st.held_id, st.atom_stats, False,
            st.arrivals, st.tweezer_flags, st.tweezer_id, st.tweezer_mark, st.chain_scratch,
            st.y_tracks, st.x_tracks, ev, False, False,
        )  # fmt: skip
        return bool(
            ev[mm.EV_CAPTURED] == 0 and ev[mm.EV_LOST_COLLISION] == 0 and ev[mm.EV_LOST_DROPPED] == 0
            and not st.held.any()
        )  # fmt: skip

    def legalize(self, plan: Plan, occupancy: np.ndarray) -> Plan:
        """``plan`` itself when every batch is legal from ``occupancy``, else a rewritten plan (a view of this
        legalizer's buffers, valid until its next rewrite)."""
        ops = plan.operations
        n = len(ops)
        occupancy = np.asarray(occupancy, dtype=bool)
        if self._play(ops, 0, n, occupancy):
            return plan
        out = self.operations
        out.clear()
        out.reserve(n)
        static = occupancy.copy()
        steps: list[np.ndarray] = []
        cursor = 0  # into plan.steps, which lists each batch's steps in execution order
        split = 0
        i = 0
        while i < n:
            if int(ops.kind[i]) != EXTRACT:
                _copy_slots(out, ops, i, i + 1)
                i += 1
                continue
            end = i
            while int(ops.kind[end]) != IMPLANT:
                end += 1
            if self._play(ops, i, end + 1, static):
                _copy_slots(out, ops, i, end + 1)
                n_steps = int(self._events[mm.EV_STEPS])
                steps.append(plan.steps[cursor : cursor + n_steps])
                static[:] = self._state.static
            else:
                split += 1
                batch = _Batch(ops, i, end)
                n_steps = batch.planned_steps(static)
                self._split(batch, static, steps)
            cursor += n_steps
            i = end + 1
        self.batches_split = split
        notes = dict(plan.notes)
        notes["batches_split"] = float(split)
        all_steps = np.concatenate(steps).astype(np.int32) if steps else np.zeros((0, 2), dtype=np.int32)
        return Plan(steps=all_steps.reshape(-1, 2), operations=out, algorithm=plan.algorithm, notes=notes)

    def _split(self, batch: _Batch, static: np.ndarray, steps: list[np.ndarray]) -> None:
        flat = static.reshape(-1)
        pending = [_Unit(batch, rows, cols, self.nx) for rows, cols in _groups(flat[batch.sites(0, *_all(batch))])]
        on_path = np.zeros(flat.size, dtype=np.int64)  # how many waiting units pass over each site
        for unit in pending:
            on_path[unit.path] += 1
        while pending:
            k = _next_unit(pending, flat, on_path)
            if k < 0:  # the groups block each other: go atom by atom
                atoms = [_Unit(batch, r[None], c[None], self.nx) for u in pending for r in u.rows for c in u.cols]
                pending = [a for a in atoms if flat[a.starts[0]]]
                on_path[:] = 0
                for unit in pending:
                    on_path[unit.path] += 1
                k = _next_unit(pending, flat, on_path)
                if k < 0:
                    k = 0  # no order works; the validator will name the collision
            unit = pending.pop(k)
            on_path[unit.path] -= 1
            rows, cols = self._grow(batch, unit, pending, flat, on_path)
            self._emit(self.operations, batch, rows, cols)
            _batch_steps(batch, rows, cols, static, self.nx, steps)

    def _grow(
        self, batch: _Batch, unit: _Unit, pending: list[_Unit], flat: np.ndarray, on_path: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray]:
        """Add waiting units to the batch about to run while the union stays legal: it picks up no atom but
        theirs, none of its tweezers (the new empty intersections included) arrives over an atom, and the
        added unit's destinations lie on no other waiting unit's path."""
        rows, cols = unit.rows, unit.cols
        n_atoms = int(flat[unit.starts].sum())
        j = 0
        while j < len(pending):
            other = pending[j]
            r2 = np.union1d(rows, other.rows)
            c2 = np.union1d(cols, other.cols)
            starts = batch.sites(0, r2, c2).ravel()
            n2 = n_atoms + int(flat[other.starts].sum())
            if int(flat[starts].sum()) == n2 and not other.blocks(on_path, waiting=True) and _path_clear(batch, r2, c2, starts, flat):
                rows, cols, n_atoms = r2, c2, n2
                on_path[other.path] -= 1
                pending.pop(j)
                continue
            j += 1
        return rows, cols

    @staticmethod
    def _emit(out: Operations, batch: _Batch, rows: np.ndarray, cols: np.ndarray) -> None:
        out.append(EXTRACT, batch.y[0][rows], batch.x[0][cols])
        for s in range(batch.n_shifts):
            dy, dx = batch.dy[s][rows], batch.dx[s][cols]
            if dy.any() or dx.any():
                out.append(SHIFT, batch.y[s][rows], batch.x[s][cols], dy, dx)
        out.append(IMPLANT, batch.y[-1][rows], batch.x[-1][cols])


class _Batch:
    """One batch of a plan: tone sites after each shift (``y[t]``, ``x[t]``, t = 0..n_shifts) and the deltas."""

    def __init__(self, ops: Operations, first: int, implant: int) -> None:
        ys, _, xs, _ = ops.tones(first)
        self.y = [ys.astype(np.int64)]
        self.x = [xs.astype(np.int64)]
        self.dy: list[np.ndarray] = []
        self.dx: list[np.ndarray] = []
        for k in range(first + 1, implant):
            _, dys, _, dxs = ops.tones(k)
            self.dy.append(dys.astype(np.int64))
            self.dx.append(dxs.astype(np.int64))
            self.y.append(self.y[-1] + self.dy[-1])
            self.x.append(self.x[-1] + self.dx[-1])
        self.n_shifts = len(self.dy)
        self.nx = ops.nx

    def planned_steps(self, static: np.ndarray) -> int:
        """One-site steps the batch means to make from ``static``: its loaded tweezers' moves."""
        loaded = static.reshape(-1)[self.sites(0, *_all(self))]
        return sum(int((loaded & ((dy[:, None] != 0) | (dx[None, :] != 0))).sum()) for dy, dx in zip(self.dy, self.dx))

    def sites(self, t: int, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
        """Flat trap index under tweezer (row tone, col tone) after ``t`` shifts, ``[len(rows), len(cols)]``."""
        return self.y[t][rows][:, None] * self.nx + self.x[t][cols][None, :]


def _all(batch: _Batch) -> tuple[np.ndarray, np.ndarray]:
    return np.arange(batch.y[0].size), np.arange(batch.x[0].size)


class _Unit:
    """A product set of the batch's row and column tones that runs as a batch of its own: its start sites,
    the sites its tweezers are over after each shift (``path``, unique) and its destinations."""

    def __init__(self, batch: _Batch, rows: np.ndarray, cols: np.ndarray, nx: int) -> None:
        self.rows = rows
        self.cols = cols
        self.starts = batch.sites(0, rows, cols).ravel()
        self.path = np.unique(np.concatenate([batch.sites(t, rows, cols).ravel() for t in range(1, batch.n_shifts + 1)]
                                             or [np.zeros(0, dtype=np.int64)]))  # fmt: skip
        self.dest = batch.sites(batch.n_shifts, rows, cols).ravel()

    def blocks(self, on_path: np.ndarray, *, waiting: bool) -> bool:
        """Whether another waiting unit passes over one of this unit's destinations (``on_path`` counts this
        unit's own path too while it is ``waiting``; its destinations are on it when it moves)."""
        own = 1 if waiting and self.path.size else 0
        return bool(np.any(on_path[self.dest] > own))


def _path_clear(batch: _Batch, rows: np.ndarray, cols: np.ndarray, starts: np.ndarray, flat: np.ndarray) -> bool:
    """The move model's rule for one batch at full depth: after every shift, no tweezer of the product set
    (loaded or empty) is over an atom other than the ones it lifted (an empty one would capture it, a loaded
    one collide). The legalized plan is replayed by the model itself; this is the planner's cheap form."""
    free = flat.copy()
    free[starts] = False
    return not any(free[batch.sites(t, rows, cols)].any() for t in range(1, batch.n_shifts + 1))


def _copy_slots(out: Operations, ops: Operations, first: int, stop: int) -> None:
    """Append slots ``first..stop-1`` of ``ops`` to ``out`` unchanged."""
    k = stop - first
    if out.n + k > out.capacity:
        out.reserve(max(2 * out.capacity, out.n + k))
    for name in ("kind", "y_site", "y_delta", "x_site", "x_delta"):
        getattr(out, name)[out.n : out.n + k] = getattr(ops, name)[first:stop]
    out.n += k


def _groups(loaded: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Product sets with no empty intersection covering every loaded tweezer: rows grouped by their set of
    loaded columns, or columns by their set of loaded rows, whichever gives fewer groups."""
    by_rows: dict[bytes, list[int]] = {}
    for r in range(loaded.shape[0]):
        if loaded[r].any():
            by_rows.setdefault(loaded[r].tobytes(), []).append(r)
    by_cols: dict[bytes, list[int]] = {}
    for c in range(loaded.shape[1]):
        if loaded[:, c].any():
            by_cols.setdefault(loaded[:, c].tobytes(), []).append(c)
    if len(by_rows) <= len(by_cols):
        return [(np.array(rs), np.flatnonzero(loaded[rs[0]])) for rs in by_rows.values()]
    return [(np.flatnonzero(loaded[:, cs[0]]), np.array(cs)) for cs in by_cols.values()]


def _next_unit(pending: list[_Unit], flat: np.ndarray, on_path: np.ndarray) -> int:
    """Index of a unit that can run now: its tweezers meet no atom, and (if any unit allows it) its
    destinations lie on no other waiting unit's path. -1 if none can run now."""
    clear = []
    for k, unit in enumerate(pending):
        free = flat.copy()
        free[unit.starts] = False
        if not free[unit.path].any():
            clear.append(k)
    for k in clear:
        if not pending[k].blocks(on_path, waiting=True):
            return k
    return clear[0] if clear else -1


def _batch_steps(
    batch: _Batch, rows: np.ndarray, cols: np.ndarray, static: np.ndarray, nx: int, out: list[np.ndarray]
) -> None:
    """Append the unit's one-site steps, slot by slot (within a slot, an atom moves once the site ahead is
    free, as ``replay_steps`` checks), and move its atoms in ``static``."""
    r0 = batch.y[0][rows][:, None]
    c0 = batch.x[0][cols][None, :]
    loaded = static[r0, c0]
    where = static.copy()  # every atom, static or held, for the order of the steps
    steps: list[tuple[int, int]] = []
    for t in range(batch.n_shifts):
        src = (batch.y[t][rows][:, None] * nx + batch.x[t][cols][None, :])[loaded]
        dst = (batch.y[t + 1][rows][:, None] * nx + batch.x[t + 1][cols][None, :])[loaded]
        pending = [(int(s), int(d)) for s, d in zip(src.tolist(), dst.tolist()) if s != d]
        flat = where.ravel()
        while pending:
            waiting = []
            for s, d in pending:
                if flat[d]:
                    waiting.append((s, d))
                else:
                    steps.append((s, d))
                    flat[s] = False
                    flat[d] = True
            if len(waiting) == len(pending):  # a closed loop cannot happen with tones that never cross
                steps.extend(waiting)
                break
            pending = waiting
    start = (r0 * nx + c0)[loaded]
    final = (batch.y[-1][rows][:, None] * nx + batch.x[-1][cols][None, :])[loaded]
    flat = static.reshape(-1)
    flat[start] = False
    flat[final] = True
    out.append(np.array(steps, dtype=np.int32).reshape(-1, 2))
