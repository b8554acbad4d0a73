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
        self._trial = Operations(nx=nx, ny=ny, capacity=64)  # a candidate batch, checked before it is kept
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
        static = occupancy.copy()
        steps: list[tuple[int, int]] = []
        split = 0
        i = 0
        while i < n:
            if int(ops.kind[i]) != EXTRACT:
                out.append(int(ops.kind[i]), *_tones(ops, i))
                i += 1
                continue
            end = i
            while int(ops.kind[end]) != IMPLANT:
                end += 1
            if self._play(ops, i, end + 1, static):
                for k in range(i, end + 1):
                    out.append(int(ops.kind[k]), *_tones(ops, k))
                _batch_steps(_Batch(ops, i, end), np.arange(len(ops.tones(i)[0])), np.arange(len(ops.tones(i)[2])),
                             static, self.nx, steps)  # fmt: skip
            else:
                split += 1
                self._split(_Batch(ops, i, end), static, steps)
            i = end + 1
        self.batches_split = split
        notes = dict(plan.notes)
        notes["batches_split"] = float(split)
        return Plan(steps=np.array(steps, dtype=np.int32).reshape(-1, 2), operations=out, algorithm=plan.algorithm,
                    notes=notes)  # fmt: skip

    def _split(self, batch: _Batch, static: np.ndarray, steps: list[tuple[int, int]]) -> None:
        loaded = static[np.ix_(batch.y[0], batch.x[0])]
        pending = _groups(loaded)
        while pending:
            k = _next_unit(batch, pending, static)
            if k < 0:  # the groups block each other: go atom by atom
                pending = [(np.array([r]), np.array([c])) for rows, cols in pending for r in rows for c in cols]
                k = _next_unit(batch, pending, static)
                if k < 0:
                    k = 0  # no order works; the validator will name the collision
            rows, cols = pending.pop(k)
            rows, cols = self._grow(batch, rows, cols, pending, static)
            self._emit(self.operations, batch, rows, cols)
            _batch_steps(batch, rows, cols, static, self.nx, steps)

    def _grow(
        self, batch: _Batch, rows: np.ndarray, cols: np.ndarray, pending: list[tuple[np.ndarray, np.ndarray]],
        static: np.ndarray,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Add waiting groups to the batch about to run while the model finds the union legal: it picks up
        no atom but theirs, none of its tweezers (the new empty intersections included) captures or meets an
        atom, and its destinations lie on no other waiting group's path."""
        trial = self._trial
        j = 0
        while j < len(pending):
            r2 = np.union1d(rows, pending[j][0])
            c2 = np.union1d(cols, pending[j][1])
            n_atoms = int(static[np.ix_(batch.y[0][rows], batch.x[0][cols])].sum())
            n_atoms += int(static[np.ix_(batch.y[0][pending[j][0]], batch.x[0][pending[j][1]])].sum())
            others = [p for q, p in enumerate(pending) if q != j]
            if int(static[np.ix_(batch.y[0][r2], batch.x[0][c2])].sum()) == n_atoms and not _blocks(
                batch, pending[j], others, self.nx
            ):
                trial.clear()
                self._emit(trial, batch, r2, c2)
                if self._play(trial, 0, len(trial), static):
                    rows, cols = r2, c2
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


def _tones(ops: Operations, i: int) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    ys, dys, xs, dxs = ops.tones(i)
    return ys, xs, dys, dxs


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


def _path_sites(batch: _Batch, rows: np.ndarray, cols: np.ndarray, nx: int) -> np.ndarray:
    """Flat sites the unit's tweezers are over after each shift (t >= 1), one row per time."""
    out = np.empty((batch.n_shifts, rows.size * cols.size), dtype=np.int64)
    for t in range(1, batch.n_shifts + 1):
        out[t - 1] = (batch.y[t][rows][:, None] * nx + batch.x[t][cols][None, :]).ravel()
    return out


def _next_unit(batch: _Batch, pending: list[tuple[np.ndarray, np.ndarray]], static: np.ndarray) -> int:
    """Index of a unit that can run now: its loaded tweezers meet no atom, and (if any unit allows it) its
    destinations lie on no other waiting unit's path. -1 if none can run now."""
    nx = static.shape[1]
    flat = static.ravel()
    paths = [_path_sites(batch, rows, cols, nx) for rows, cols in pending]
    starts = [(batch.y[0][rows][:, None] * nx + batch.x[0][cols][None, :]).ravel() for rows, cols in pending]
    clear = []
    for k, path in enumerate(paths):
        own = set(starts[k].tolist())
        hits = [s for s in path.ravel().tolist() if flat[s] and s not in own]
        if not hits:
            clear.append(k)
    for k in clear:
        if not _blocks(batch, pending[k], [p for q, p in enumerate(pending) if q != k], nx):
            return k
    return clear[0] if clear else -1


def _blocks(
    batch: _Batch, unit: tuple[np.ndarray, np.ndarray], others: list[tuple[np.ndarray, np.ndarray]], nx: int
) -> bool:
    """Whether ``unit``'s destinations lie on the path of one of the ``others`` (which would then meet its atoms)."""
    rows, cols = unit
    dest = (batch.y[-1][rows][:, None] * nx + batch.x[-1][cols][None, :]).ravel()
    return any(np.isin(dest, _path_sites(batch, r, c, nx)).any() for r, c in others)


def _batch_steps(
    batch: _Batch, rows: np.ndarray, cols: np.ndarray, static: np.ndarray, nx: int, steps: list[tuple[int, int]]
) -> None:
    """Append the unit's one-site steps, slot by slot (within a slot, an atom moves once the site ahead is
    free, as ``replay_steps`` checks), and move its atoms in ``static``."""
    r0 = batch.y[0][rows][:, None]
    c0 = batch.x[0][cols][None, :]
    loaded = static[r0, c0]
    where = static.copy()  # every atom, static or held, for the order of the steps
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
    flat = static.ravel()
    flat[start] = False
    flat[final] = True
