"""What the engine keeps of every shot: occupancy per cycle, plan summaries, stage times and the outcome."""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import StrEnum
from itertools import chain
from typing import Any

import numpy as np

from engine.move_model import MoveState, new_events, replay_operations
from engine.operations import Operations
from engine.routing import n_positions, positions_of, trap_index

__all__ = [
    "PATH_POINTS_MAX", "CycleRecord", "Outcome", "ShotRecord", "atom_moves", "atom_paths", "atoms_in_flight",
    "occupancy_to_rows",
]  # fmt: skip


class Outcome(StrEnum):
    SUCCESS = "success"  # every target trap occupied (judged from the image)
    UNSOLVABLE = "unsolvable"  # fewer atoms than target traps
    MAX_CYCLES = "max_cycles"  # still defects after max_cycles cycles
    FAULT = "fault"  # a device or the solver failed; see ShotRecord.fault


def occupancy_to_rows(occupancy: np.ndarray) -> list[str]:
    """``bool[ny, nx]`` as one string of '0'/'1' per row: compact, readable JSON."""
    return ["".join("1" if v else "0" for v in row) for row in np.asarray(occupancy, dtype=bool)]


def _routes(steps: np.ndarray) -> list[list[int]]:
    """Every atom a plan's steps (``int[m, 2]``: source, destination site, in execution order) touch, followed
    through them: its sites in order, the one it started on first. A step from a site where an earlier step
    left an atom continues that atom's route (a relay moves several atoms, each its own route)."""
    at: dict[int, list[int]] = {}  # site an atom is at now -> its route so far
    for src, dst in np.asarray(steps, dtype=np.int64).reshape(-1, 2):
        route = at.pop(int(src), None) or [int(src)]
        route.append(int(dst))
        at[int(dst)] = route
    return list(at.values())


def atom_moves(steps: np.ndarray, *, nx: int = 0, half: int = 1) -> np.ndarray:
    """A plan's one-site steps (``int[m, 2]``: source, destination, in execution order) as one row per moved
    atom: ``int32[k, 2]`` (the trap it started in, the trap it ended in), sorted by source.

    An atom is followed through its steps (``_routes``). Atoms whose steps bring them back to their start do
    not count as moved. Steps of an interstitial plan (``half = 2``, an array of ``nx`` traps) are between
    positions; the rows are traps.
    """
    moves = sorted((route[0], route[-1]) for route in _routes(steps) if route[0] != route[-1])
    rows = np.array(moves, dtype=np.int64).reshape(-1, 2)
    return (trap_index(rows, nx, half) if half > 1 else rows).astype(np.int32)


PATH_POINTS_MAX = 1 << 15  # corner points a cycle keeps of its plan's routes (at most 640 KiB of i4 rows)


def atom_paths(steps: np.ndarray, *, nx: int, half: int = 1, max_points: int = PATH_POINTS_MAX) -> np.ndarray:
    """The route of every atom ``atom_moves`` lists, as its corner points, so that a plan can be drawn as the
    atoms really travelled (through the channels between traps under interstitial routing, trap to trap for a
    lattice relay) and not as straight arrows: ``int32[n, 3]`` rows (the trap it started in, y, x), with y and x
    on the **half-site grid** (2 per site whatever the routing: odd is a channel), grouped by atom in the
    order of ``atom_moves``, each route from its start to its end with a point where its direction changes.

    ``steps`` as for ``atom_moves`` (positions of ``half`` per site on an array of ``nx`` traps). The size is
    bounded: routes are kept whole, atom after atom, up to ``max_points`` rows; the atoms after that keep only
    their straight move. Run after the plan has played (a Python walk over its steps, as ``atom_moves``)."""
    routes = sorted((r for r in _routes(steps) if r[0] != r[-1]), key=lambda r: r[0])
    if not routes:
        return np.zeros((0, 3), dtype=np.int32)
    # all routes end to end, corners found at once (a loop per atom costs ~40 ms for a 32x64 bulk plan)
    lengths = np.fromiter(map(len, routes), dtype=np.int64, count=len(routes))
    flat = np.fromiter(chain.from_iterable(routes), dtype=np.int64, count=int(lengths.sum()))
    first = np.r_[0, np.cumsum(lengths)[:-1]]
    y, x = np.divmod(flat, n_positions(nx, half))
    yx = np.stack([y, x], axis=1) * (2 // half)
    d = np.diff(yx, axis=0)
    turn = np.zeros(len(flat), dtype=bool)
    turn[1:-1] = np.any(d[1:] != d[:-1], axis=1)
    turn[first] = turn[first + lengths - 1] = True  # every route's own start and end
    route_of = np.repeat(np.arange(len(routes)), lengths)[turn]
    kept = np.cumsum(np.bincount(route_of, minlength=len(routes))) <= max_points  # whole routes, a prefix
    rows = np.empty((int(turn.sum()), 3), dtype=np.int32)
    rows[:, 0] = trap_index(flat[first], nx, half)[route_of]
    rows[:, 1:] = yx[turn]
    return rows[kept[route_of]]


def atoms_in_flight(ops: Operations, occupancy: np.ndarray, n_played: int, *, chain: bool) -> np.ndarray:
    """The atoms away from their traps after the first ``n_played`` slots of a plan that started from
    ``occupancy``: ``int32[k, 2]`` rows (the trap it started the cycle in, the site it is at now), sorted by
    source. This is what a failsafe holds when the card underruns there, so a shot record can say which
    atoms paused mid-move (the slots are replayed through the move model, losses off, after the cycle).

    Sites are flat indices on the plan's grid of positions (``engine.routing``: the traps themselves under
    lattice routing). Crossed AODs: the atoms held in tweezers. A chain (``chain``, its traps are the tones
    themselves): the atoms whose tone has carried them off their starting site.
    """
    occ = np.asarray(occupancy, dtype=bool)
    if not 0 <= n_played <= len(ops):
        raise ValueError(f"n_played = {n_played} is outside the plan's 0..{len(ops)} slots")
    state = MoveState(ops.ny, ops.nx)
    state.load(positions_of(occ, ops.half))
    replay_operations(
        ops.kind, ops.y_site, ops.y_delta, ops.x_site, ops.x_delta, 0, n_played, chain, ops.half,
        state.static, state.held, state.held_mark, state.ids, state.atom_stats, True, state.arrivals,
        state.tweezers, state.chain_scratch, state.y_tracks, state.x_tracks, new_events(), False, False,
    )  # fmt: skip
    source_of = np.flatnonzero(positions_of(occ, ops.half))  # atom ids: row-major ranks (MoveState.load)
    # where atoms are now (the chain's traps, or the tweezers), and their ids (stale where no atom is)
    present, ids_now = (state.static, state.ids[0]) if chain else (state.held, state.ids[1])
    sites = np.flatnonzero(present)
    rows = np.stack([source_of[ids_now.reshape(-1)[sites]], sites], axis=1)
    if chain:
        rows = rows[rows[:, 0] != rows[:, 1]]
    return rows[np.argsort(rows[:, 0], kind="stable")].astype(np.int32).reshape(-1, 2)


@dataclass
class CycleRecord:
    index: int
    occupancy: np.ndarray  # bool[ny, nx], as detected at the start of the cycle
    atoms: int
    defects: int  # target traps without an atom
    stage_s: dict[str, float] = field(default_factory=dict)
    n_slots: int = 0
    n_steps: int = 0
    underruns: int = 0
    latency_s: float = 0.0  # image in memory -> playback started
    t_start_s: float = 0.0  # the cycle began (camera triggered), seconds after the shot began
    t_image_s: float = 0.0  # its image was in host memory, seconds after the shot began
    # For diagnostics (per-trap statistics, imaging histograms, plans drawn as arrows); not in ``to_dict``,
    # so the live messages stay small: routes that need them read them from the record or the run file.
    counts: np.ndarray | None = None  # float32[n_traps]: the PSF-weighted counts of this cycle's image
    moves: np.ndarray | None = None  # int32[k, 2]: the plan's moved atoms, (source, destination) trap index
    # int32[n, 3]: their routes' corner points, (source trap, y, x) on the half-site grid (``atom_paths``)
    paths: np.ndarray | None = None
    # per underrun of this cycle's plan, the atoms its failsafe held mid-move: [source trap, site] pairs
    # (``atoms_in_flight``; empty when the plan streamed without an underrun)
    in_flight: list[list[list[int]]] = field(default_factory=list)

    @property
    def atoms_moved(self) -> int:
        """Atoms the cycle's plan moved (0 for a cycle without a plan)."""
        return 0 if self.moves is None else int(self.moves.shape[0])
    planner: str = ""  # the planner that made this cycle's plan ("" when the cycle planned nothing)
    pickups: int = 0  # atoms the plan took into a tweezer (extracts and captures; an atom taken twice, twice)
    # what the lab reported about this cycle (``engine.engine.Lab.cycle_reports``), carried unread; empty on
    # hardware. The simulated lab reports the atoms its world lost, by cause (``SimLab.cycle_reports``).
    lab_report: dict[str, Any] = field(default_factory=dict)

    def to_dict(self) -> dict[str, Any]:
        return {
            "index": self.index,
            "occupancy": occupancy_to_rows(self.occupancy),
            "atoms": self.atoms,
            "defects": self.defects,
            "stage_us": {k: v * 1e6 for k, v in self.stage_s.items()},
            "n_slots": self.n_slots,
            "n_steps": self.n_steps,
            "underruns": self.underruns,
            "latency_us": self.latency_s * 1e6,
            "t_start_ms": self.t_start_s * 1e3,
            "t_image_ms": self.t_image_s * 1e3,
            "atoms_moved": self.atoms_moved,
            "planner": self.planner,
            "in_flight": self.in_flight,
            "pickups": self.pickups,
            "truth": self.lab_report,  # the key the shot's lab report has always used
        }


@dataclass
class ShotRecord:
    shot_id: int
    config_digest: str
    algorithm: str
    target: np.ndarray
    outcome: Outcome = Outcome.MAX_CYCLES
    fault: str | None = None
    cycles: list[CycleRecord] = field(default_factory=list)
    t_start_s: float = 0.0
    duration_s: float = 0.0
    images: list[np.ndarray] | None = None
    # what the lab reported after the shot (``engine.engine.Lab.shot_report``), carried unread; empty on
    # hardware. The simulated lab reports its world's atoms (``drivers.sim.lab.SimLab.shot_report``).
    lab_report: dict[str, Any] = field(default_factory=dict)

    @property
    def success(self) -> bool:
        return self.outcome is Outcome.SUCCESS

    def to_dict(self) -> dict[str, Any]:
        return {
            "shot_id": self.shot_id,
            "config_digest": self.config_digest,
            "algorithm": self.algorithm,
            "target": occupancy_to_rows(self.target),
            "outcome": self.outcome.value,
            "fault": self.fault,
            "cycles": [c.to_dict() for c in self.cycles],
            "duration_s": self.duration_s,
            "truth": self.lab_report,  # the key stored runs and the dashboard have always used
        }
