"""Run history on disk: every shot appended to an HDF5 file, so that a crash never loses or corrupts earlier shots.

Layout of ``runs/<YYYYmmdd-HHMMSS>-<n>.h5`` (one *run* = consecutive shots under one configuration; any change of
configuration, a one-shot override included, starts a new file, so each file's shapes and config are fixed):

- attrs: ``config_json`` (the whole ``SystemConfig``), ``config_digest``, ``stages`` (JSON list of stage names),
  ``created``; dataset ``target`` ``bool[ny, nx]``;
- per shot (axis 0 grows by one per shot): ``shot_id`` i8, ``outcome`` S16, ``fault`` S256, ``n_cycles`` i2,
  ``duration_s`` f8, ``target_filled`` i1 (1/0, -1 unknown), ``occupancy`` ``bool[shot, cycle, ny, nx]``,
  ``stage_us`` ``f4[shot, cycle, stage]`` (NaN where a stage did not run), ``plan`` ``i4[shot, cycle, 3]``
  (slots, steps, underruns), ``latency_us`` ``f4[shot, cycle]``, ``counts`` ``f4[shot, cycle, trap]`` (each
  image's PSF-weighted sums, trap order row-major), ``atoms_moved`` ``i4[shot, cycle]``, ``planner``
  ``S32[shot, cycle]`` (the planner each cycle used; empty: it planned nothing), ``pickups`` ``i4[shot, cycle]``
  (atoms each plan took into a tweezer), ``lost_by_cause`` ``i4[shot, cycle, cause]`` (the atoms the lab's world
  lost from the cycle's image to the next, per cause; the causes are listed in the attr ``loss_causes``, JSON;
  -1: the lab reported nothing for that cycle, as on hardware). Cycles past ``n_cycles`` are zero.
- ``moves`` ``i4[row, 4]``: one row per atom a plan moved, ``(shot index in this file, cycle, source trap,
  destination trap)``, appended shot after shot.
- ``paths`` ``i4[row, 5]``: the routes of those atoms as their corner points, ``(shot index in this file, cycle,
  source trap, y, x)`` with y and x on the half-site grid (2 per site; odd: the channel between two rows or
  columns of traps, where interstitial routing carries atoms), each route in order from its start to its end,
  at most ``engine.records.PATH_POINTS_MAX`` rows per cycle (``engine.records.atom_paths``).
- camera frames, only when the store keeps them (``FrameKeeping``; attr ``frames_every_nth_shot``, 0: none):
  ``frames`` ``u2[k, h, w]`` (gzip-compressed, one chunk per frame) and ``frame_index`` ``i4[k, 2]`` (shot index
  in this file, cycle) for each kept frame, in order. At most ``frames_max`` frames go into one file.

Files written before ``counts``, ``atoms_moved``, ``moves``, ``paths``, ``planner``, ``pickups``,
``lost_by_cause`` and ``frames`` existed lack them; the readers below cope.

Why it survives crashes: the file is written in HDF5's single-writer/multiple-reader (SWMR) mode. After the
datasets are created no new object is ever added; a shot only extends chunked datasets, and each dataset is
flushed after every shot. SWMR orders metadata writes so the file on disk is always a consistent snapshot.
After a clean stop the file opens normally; after a crash open it with ``h5py.File(path, "r", swmr=True)``
(or clear the flag once with ``h5clear -s``) and every flushed shot is there. Files are created with mode
``"x"`` (fail if present), so no run ever overwrites another.

Writing happens on a thread of its own: the engine only puts a record on a queue.
"""

from __future__ import annotations

import errno
import json
import queue
import re
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from drivers.sim.lab import LOSS_CAUSES
from engine.config import SystemConfig
from engine.psf import frame_shape
from engine.records import ShotRecord
from engine.targets import build_target
from engine.timing import STAGES
from server.files import FileRefused, confine

#: Configurations the store remembers for the shots still queued (see ``RunStore.note_config``).
CONFIGS_KEPT = 16

__all__ = ["RUN_NAME", "FrameKeeping", "RunStore", "read_run_frame", "read_run_shot"]

#: What a run file's name looks like (``_new_path``); a client may name no other file.
RUN_NAME = r"^[0-9]{8}-[0-9]{6}-[0-9]{1,6}\.h5$"

_PER_SHOT_1D = {
    "shot_id": "i8",
    "outcome": "S16",
    "fault": "S256",
    "n_cycles": "i2",
    "duration_s": "f8",
    "target_filled": "i1",
}


@dataclass(frozen=True)
class FrameKeeping:
    """Which camera frames the run files keep (``llrs serve --keep-frames N --keep-frames-mib M``).

    Frames are what the run file would otherwise lose for good (a historic shot's camera image cannot be
    remade), but a 32x64 frame is 1 MiB raw, 1000 times a cycle's other data, so they are kept only when asked:
    those of every ``every_nth_shot``-th shot of a run file (0: none; 1: every shot), every cycle's where the
    engine attached them to the record (``ShotRecord.images``), else the shot's final frame (its last cycle's
    image, which the engine always returns). Stored gzip-compressed; at most ``max_mib`` MiB of raw frames
    per run file, so a long run cannot fill the disk with images (later shots keep their other data).
    """

    every_nth_shot: int = 0
    max_mib: float = 256.0

    def __post_init__(self) -> None:
        if self.every_nth_shot < 0:
            raise ValueError(f"keep frames of every Nth shot: N must be >= 0 (0: none), got {self.every_nth_shot}")
        if not self.max_mib > 0:
            raise ValueError(f"the frames' size limit per run file must be > 0 MiB, got {self.max_mib}")

    def max_frames(self, shape: tuple[int, int]) -> int:
        """How many ``uint16`` frames of ``shape`` fit the limit (at least one, so a huge frame is still kept)."""
        return max(1, int(self.max_mib * (1 << 20)) // (2 * shape[0] * shape[1]))


class _RunFile:
    """One open run file: fixed shapes from its configuration, appended one shot at a time."""

    def __init__(self, path: Path, config: SystemConfig, frames: FrameKeeping | None = None) -> None:
        frames = frames if frames is not None else FrameKeeping()  # none kept
        self.path = path
        self.digest = config.digest()
        arr = config.array
        self.max_cycles = config.loop.max_cycles + 1
        self.shape = (arr.ny, arr.nx)
        self.n = 0
        # appends only: a small chunk cache per dataset keeps a long run's memory flat (HDF5's default is 1 MiB each)
        f = h5py.File(path, "x", libver="latest", rdcc_nbytes=64 * 1024)
        self.file = f
        f.attrs["config_json"] = config.model_dump_json()
        f.attrs["config_digest"] = self.digest
        f.attrs["stages"] = json.dumps(list(STAGES))
        f.attrs["created"] = time.strftime("%Y-%m-%dT%H:%M:%S%z")
        f.attrs["loss_causes"] = json.dumps(list(LOSS_CAUSES))
        f.attrs["frames_every_nth_shot"] = frames.every_nth_shot
        f.create_dataset("target", data=build_target(config.target, nx=arr.nx, ny=arr.ny))
        chunk = 64
        self.ds: dict[str, h5py.Dataset] = {}
        for name, dtype in _PER_SHOT_1D.items():
            self.ds[name] = f.create_dataset(name, shape=(0,), maxshape=(None,), dtype=dtype, chunks=(chunk,))
        c = self.max_cycles
        for name, tail, dtype in (
            ("occupancy", (c, *self.shape), "bool"),
            ("stage_us", (c, len(STAGES)), "f4"),
            ("plan", (c, 3), "i4"),
            ("latency_us", (c,), "f4"),
            ("counts", (c, arr.n_traps), "f4"),
            ("atoms_moved", (c,), "i4"),
            ("planner", (c,), "S32"),  # the planner each cycle used (a strategy switches; empty: none)
            ("pickups", (c,), "i4"),
            ("lost_by_cause", (c, len(LOSS_CAUSES)), "i4"),
        ):
            rows = max(1, min(chunk, (1 << 20) // max(1, int(np.prod(tail)))))
            self.ds[name] = f.create_dataset(
                name, shape=(0, *tail), maxshape=(None, *tail), dtype=dtype, chunks=(rows, *tail)
            )
        self.ds["moves"] = f.create_dataset("moves", shape=(0, 4), maxshape=(None, 4), dtype="i4", chunks=(1024, 4))
        self.ds["paths"] = f.create_dataset(  # gzip: shot, cycle and source repeat down the rows
            "paths", shape=(0, 5), maxshape=(None, 5), dtype="i4", chunks=(4096, 5), compression="gzip",
            compression_opts=1, shuffle=True,
        )
        self.frames_every = frames.every_nth_shot
        self.frame_shape = frame_shape(config.camera)
        self.frames_max = frames.max_frames(self.frame_shape) if self.frames_every else 0
        if self.frames_every:  # created now or never: no object may be added once the file is in SWMR mode
            f.attrs["frames_max"] = self.frames_max
            self.ds["frames"] = f.create_dataset(
                "frames", shape=(0, *self.frame_shape), maxshape=(self.frames_max, *self.frame_shape), dtype="u2",
                chunks=(1, *self.frame_shape), compression="gzip", compression_opts=1, shuffle=True,
            )
            self.ds["frame_index"] = f.create_dataset(
                "frame_index", shape=(0, 2), maxshape=(self.frames_max, 2), dtype="i4",
                chunks=(min(256, self.frames_max), 2),
            )
        f.swmr_mode = True

    def _frames_of(self, record: ShotRecord, final_frame: np.ndarray | None) -> list[tuple[int, np.ndarray]]:
        """``(cycle, frame)`` to keep for this shot under the store's ``FrameKeeping`` (see there)."""
        if not self.frames_every or self.n % self.frames_every or not record.cycles:
            return []
        if record.images is not None:
            kept = list(enumerate(record.images[: len(record.cycles)]))
        elif final_frame is not None:
            kept = [(len(record.cycles) - 1, final_frame)]
        else:
            return []
        room = self.frames_max - self.ds["frames"].shape[0]
        return [(c, img) for c, img in kept if img.shape == self.frame_shape][:room]

    def append(self, record: ShotRecord, final_frame: np.ndarray | None = None) -> None:
        """Add one shot; ``final_frame``: its last cycle's camera image, kept if ``FrameKeeping`` asks for it."""
        c = self.max_cycles
        occupancy = np.zeros((c, *self.shape), dtype=bool)
        stage_us = np.full((c, len(STAGES)), np.nan, dtype=np.float32)
        plan = np.zeros((c, 3), dtype=np.int32)
        latency = np.zeros(c, dtype=np.float32)
        counts = np.zeros((c, self.shape[0] * self.shape[1]), dtype=np.float32)
        atoms_moved = np.zeros(c, dtype=np.int32)
        moves, paths = [], []
        planner = np.zeros(c, dtype="S32")
        pickups = np.zeros(c, dtype=np.int32)
        lost_by_cause = np.zeros((c, len(LOSS_CAUSES)), dtype=np.int32)
        for cyc in record.cycles[:c]:
            occupancy[cyc.index] = cyc.occupancy
            for stage, seconds in cyc.stage_s.items():
                if stage in STAGES:
                    stage_us[cyc.index, STAGES.index(stage)] = seconds * 1e6
            plan[cyc.index] = (cyc.n_slots, cyc.n_steps, cyc.underruns)
            latency[cyc.index] = cyc.latency_s * 1e6
            if cyc.counts is not None and cyc.counts.size == counts.shape[1]:
                counts[cyc.index] = cyc.counts
            if cyc.moves is not None and len(cyc.moves):
                atoms_moved[cyc.index] = len(cyc.moves)
                rows = np.empty((len(cyc.moves), 4), dtype=np.int32)
                rows[:, 0], rows[:, 1], rows[:, 2:] = self.n, cyc.index, cyc.moves
                moves.append(rows)
            if cyc.paths is not None and len(cyc.paths):
                rows = np.empty((len(cyc.paths), 5), dtype=np.int32)
                rows[:, 0], rows[:, 1], rows[:, 2:] = self.n, cyc.index, cyc.paths
                paths.append(rows)
            planner[cyc.index] = cyc.planner.encode()[:32]
            pickups[cyc.index] = cyc.pickups
            lost = cyc.lab_report.get("lost_by_cause")
            # causes a lab reports that the file does not list are not kept (the simulated lab's are all listed)
            lost_by_cause[cyc.index] = -1 if lost is None else [lost.get(cause, 0) for cause in LOSS_CAUSES]
        filled = record.lab_report.get("target_filled")
        values = {
            "shot_id": record.shot_id,
            "outcome": record.outcome.value.encode(),
            "fault": (record.fault or "").encode()[:256],
            "n_cycles": len(record.cycles),
            "duration_s": record.duration_s,
            "target_filled": -1 if filled is None else int(bool(filled)),
            "occupancy": occupancy,
            "stage_us": stage_us,
            "plan": plan,
            "latency_us": latency,
            "counts": counts,
            "atoms_moved": atoms_moved,
            "planner": planner,
            "pickups": pickups,
            "lost_by_cause": lost_by_cause,
        }
        i = self.n
        frames = self._frames_of(record, final_frame)
        for name, value in values.items():
            ds = self.ds[name]
            ds.resize(i + 1, axis=0)
            ds[i] = value
        for name, parts in (("moves", moves), ("paths", paths)):
            if parts:
                new = np.concatenate(parts)
                ds = self.ds[name]
                start = ds.shape[0]
                ds.resize(start + len(new), axis=0)
                ds[start:] = new
        if frames:
            start = self.ds["frames"].shape[0]
            for name in ("frames", "frame_index"):
                self.ds[name].resize(start + len(frames), axis=0)
            for k, (cycle, image) in enumerate(frames):
                self.ds["frames"][start + k] = image
                self.ds["frame_index"][start + k] = (i, cycle)
        for ds in self.ds.values():
            ds.flush()
        self.file.flush()  # the superblock's end of file too, so a copy taken now (a download) reads whole
        self.n = i + 1

    def close(self) -> None:
        self.file.close()


def _decode(value: Any) -> str:
    return value.decode() if isinstance(value, bytes) else str(value)


def _summary(f: h5py.File, path: Path) -> dict[str, Any]:
    config = json.loads(_decode(f.attrs["config_json"]))
    return {
        "name": path.name,
        "size_bytes": path.stat().st_size,
        "created": _decode(f.attrs.get("created", "")),
        "config_name": config.get("name", ""),
        "config_digest": _decode(f.attrs["config_digest"]),
        "shape": list(f["target"].shape),
        "shots": int(f["shot_id"].shape[0]),
    }


def _check_shot(f: h5py.File, index: int) -> None:
    n_shots = int(f["shot_id"].shape[0])
    if not 0 <= index < n_shots:
        raise IndexError(f"the run file holds {n_shots} shots (0..{n_shots - 1}); there is no shot {index}")


def _frame_rows(f: h5py.File, index: int) -> dict[int, int]:
    """cycle -> row of ``frames`` for the frames kept of shot ``index`` (empty: none kept)."""
    if "frame_index" not in f or not f["frame_index"].shape[0]:
        return {}
    rows = f["frame_index"][:]
    return {int(cycle): int(row) for row, (shot, cycle) in enumerate(rows) if shot == index}


def read_run_frame(f: h5py.File, index: int, cycle: int) -> np.ndarray:
    """The camera frame kept for cycle ``cycle`` of shot ``index`` of an open run file, ``uint16[h, w]``.
    ``IndexError``: no such shot; ``LookupError``: no frame kept for that cycle (see ``FrameKeeping``)."""
    _check_shot(f, index)
    row = _frame_rows(f, index).get(cycle)
    if row is None:
        every = int(f.attrs.get("frames_every_nth_shot", 0))
        kept = "keeps no frames" if not every else f"keeps the frames of one shot in {every} (within its size limit)"
        raise LookupError(f"no camera frame kept for shot {index} cycle {cycle}: this run file {kept}")
    return np.asarray(f["frames"][row])


def _paths_of(f: h5py.File, index: int) -> dict[int, list[dict[str, Any]]]:
    """Cycle -> the routes of shot ``index``'s moved atoms: ``[{"source": trap, "points": [[y, x], ...]}]``, the
    corner points in sites (``3.5``: the channel between rows 3 and 4), start to end (none in older files)."""
    out: dict[int, list[dict[str, Any]]] = {}
    if "paths" not in f or not f["paths"].shape[0]:
        return out
    rows = f["paths"][:]
    rows = rows[rows[:, 0] == index]
    for cycle in np.unique(rows[:, 1]):
        of_cycle = rows[rows[:, 1] == cycle]
        # a route ends where the next atom's begins: the source changes (routes are stored atom after atom)
        starts = np.flatnonzero(np.r_[True, of_cycle[1:, 2] != of_cycle[:-1, 2]])
        out[int(cycle)] = [
            {"source": int(part[0, 2]), "points": (part[:, 3:] / 2).tolist()}
            for part in np.split(of_cycle, starts[1:])
        ]
    return out


def read_run_shot(f: h5py.File, index: int) -> dict[str, Any]:
    """Shot ``index`` (0-based, in file order) of an open run file, shaped as ``ShotRecord.to_dict()`` plus,
    per cycle, ``moves`` (``[[source, destination], ...]``), ``paths`` (the moved atoms' routes: ``_paths_of``),
    ``counts`` (the weighted sums, where recorded) and ``frame`` (whether its camera frame is kept:
    ``read_run_frame``); a cycle's ``truth`` holds the lab's ``lost_by_cause`` where it reported one.
    ``IndexError`` if the file holds fewer shots."""
    _check_shot(f, index)
    stages = json.loads(_decode(f.attrs["stages"]))
    n_cycles = int(f["n_cycles"][index])
    occupancy = f["occupancy"][index]
    stage_us = f["stage_us"][index]
    plan = f["plan"][index]
    latency = f["latency_us"][index]
    counts = f["counts"][index] if "counts" in f else None
    pickups = f["pickups"][index] if "pickups" in f else None
    lost = f["lost_by_cause"][index] if "lost_by_cause" in f else None
    causes = json.loads(_decode(f.attrs["loss_causes"])) if lost is not None else []
    frames = _frame_rows(f, index)
    moves_of: dict[int, list[list[int]]] = {}
    if "moves" in f and f["moves"].shape[0]:
        rows = f["moves"][:]
        for _, cycle, src, dst in rows[rows[:, 0] == index]:
            moves_of.setdefault(int(cycle), []).append([int(src), int(dst)])
    paths_of = _paths_of(f, index)
    target = np.asarray(f["target"][:], dtype=bool)
    cycles = []
    for c in range(n_cycles):
        occ = np.asarray(occupancy[c], dtype=bool)
        cycles.append({
            "index": c,
            "occupancy": ["".join("1" if v else "0" for v in row) for row in occ],
            "atoms": int(occ.sum()),
            "defects": int((target & ~occ).sum()),
            "stage_us": {s: float(v) for s, v in zip(stages, stage_us[c], strict=True) if np.isfinite(v)},
            "n_slots": int(plan[c, 0]),
            "n_steps": int(plan[c, 1]),
            "underruns": int(plan[c, 2]),
            "latency_us": float(latency[c]),
            "atoms_moved": len(moves_of.get(c, [])),
            "pickups": None if pickups is None else int(pickups[c]),
            "moves": moves_of.get(c, []),
            "paths": paths_of.get(c, []),
            "counts": None if counts is None else [float(v) for v in counts[c]],
            "frame": c in frames,
            "truth": {} if lost is None or lost[c, 0] < 0 else {
                "lost_by_cause": {cause: int(v) for cause, v in zip(causes, lost[c], strict=True)}
            },
        })
    filled = int(f["target_filled"][index])
    return {
        "shot_id": int(f["shot_id"][index]),
        "index": index,
        "config_digest": _decode(f.attrs["config_digest"]),
        "algorithm": json.loads(_decode(f.attrs["config_json"]))["solver"]["algorithm"],
        "target": ["".join("1" if v else "0" for v in row) for row in target],
        "outcome": _decode(f["outcome"][index]),
        "fault": _decode(f["fault"][index]) or None,
        "cycles": cycles,
        "duration_s": float(f["duration_s"][index]),
        "truth": {} if filled < 0 else {"target_filled": bool(filled)},
    }


class RunStore:
    """Appends every shot to the run file of its configuration; a writer thread does the disk work.

    ``note_config`` must be called with every configuration before shots under it arrive (the service does it
    when it applies one), so the store can write the config into the file the shot belongs to.
    """

    def __init__(self, directory: str | Path, *, frames: FrameKeeping | None = None) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self.frames = frames if frames is not None else FrameKeeping()
        self._configs: OrderedDict[str, SystemConfig] = OrderedDict()  # the latest, for the shots queued
        self._queue: queue.Queue[tuple[ShotRecord, np.ndarray | None] | None] = queue.Queue()
        self._current: _RunFile | None = None
        self._lock = threading.Lock()
        self.errors: list[str] = []  # the latest write failures, newest last
        self.failed_writes = 0
        self._thread = threading.Thread(target=self._write_loop, name="llrs-runstore", daemon=True)
        self._thread.start()

    @property
    def current_path(self) -> Path | None:
        with self._lock:
            return self._current.path if self._current is not None else None

    def write_errors(self) -> tuple[int, str | None]:
        """How many shots could not be written, and why the last one failed (``None`` once a later shot was
        written: the fault is over, the count stays)."""
        with self._lock:
            return self.failed_writes, (self.errors[-1] if self.errors else None)

    def note_config(self, config: SystemConfig) -> None:
        """A configuration shots will run under (the latest ``CONFIGS_KEPT``: shots are written within
        moments, so older ones are no longer needed; keeping all would grow without bound)."""
        with self._lock:
            self._configs[config.digest()] = config
            self._configs.move_to_end(config.digest())
            while len(self._configs) > CONFIGS_KEPT:
                self._configs.popitem(last=False)

    def put(self, record: ShotRecord, final_frame: np.ndarray | None = None) -> None:
        """Queue a finished shot (and its final camera frame, kept if ``FrameKeeping`` asks) for writing;
        returns at once (called on the engine thread). The frame must not be modified afterwards."""
        self._queue.put((record, final_frame))

    def flush(self, *, timeout_s: float = 10.0) -> None:
        """Wait until every queued shot is on disk (tests, shutdown)."""
        deadline = time.monotonic() + timeout_s
        while self._queue.unfinished_tasks and time.monotonic() < deadline:
            time.sleep(0.005)

    def close(self) -> None:
        self._queue.put(None)
        self._thread.join(timeout=10)
        with self._lock:
            if self._current is not None:
                self._current.close()
                self._current = None

    # -- reading run files back (the API's /api/runs) -----------------------------------------------------------

    def path_of(self, name: str) -> Path | None:
        """The run file called ``name`` in this store's directory, or ``None`` (no such file, or a name that is
        not a run file's: only names like ``20260101-120000-0.h5`` are looked up, never a path)."""
        if not re.fullmatch(RUN_NAME, name):
            return None
        try:
            path = confine(name, self.directory, what="run file", option="--runs-dir")
        except FileRefused:
            return None
        unresolved = self.directory / name
        return path if path.is_file() and not unresolved.is_symlink() else None

    def runs(self, *, limit: int = 100) -> list[dict[str, Any]]:
        """The newest ``limit`` run files, newest first: name, size, creation time, configuration, shots."""
        names = sorted((p.name for p in self.directory.glob("*.h5") if re.fullmatch(RUN_NAME, p.name)), reverse=True)
        out = []
        for name in names[:limit]:
            try:
                out.append(self._with_file(name, lambda f, path: _summary(f, path)))
            except (OSError, KeyError, ValueError):
                continue  # not a readable run file (being created, or damaged): not listed
        return out

    def read_shot(self, name: str, index: int) -> dict[str, Any]:
        """Shot ``index`` of run file ``name`` (see ``read_run_shot``). ``FileNotFoundError``: no such run file;
        ``IndexError``: no such shot in it."""
        return self._with_file(name, lambda f, path: read_run_shot(f, index))

    def read_frame(self, name: str, index: int, cycle: int) -> np.ndarray:
        """The camera frame kept for cycle ``cycle`` of shot ``index`` of run file ``name`` (see
        ``read_run_frame``). ``FileNotFoundError``, ``IndexError`` or ``LookupError`` when there is none."""
        return self._with_file(name, lambda f, path: read_run_frame(f, index, cycle))

    def _with_file(self, name: str, read: Any) -> Any:
        path = self.path_of(name)
        if path is None:
            raise FileNotFoundError(f"no run file {name!r} in the runs directory")
        with self._lock:  # the file being written is read through the writer's own handle, between shots
            if self._current is not None and self._current.path.name == name:
                return read(self._current.file, path)
        with h5py.File(path, "r", swmr=True) as f:
            return read(f, path)

    def _new_path(self) -> Path:
        stamp = time.strftime("%Y%m%d-%H%M%S")
        n = 0
        while (self.directory / f"{stamp}-{n}.h5").exists():
            n += 1
        return self.directory / f"{stamp}-{n}.h5"

    def _file_for(self, digest: str) -> _RunFile:
        with self._lock:
            if self._current is not None and self._current.digest == digest:
                return self._current
            if self._current is not None:
                self._current.close()
                self._current = None
            config = self._configs[digest]
            while True:
                try:
                    self._current = _RunFile(self._new_path(), config, self.frames)
                    break
                except FileExistsError:  # another process took the name between exists() and create
                    continue
            return self._current

    def _write_loop(self) -> None:
        while True:
            item = self._queue.get()
            try:
                if item is None:
                    return
                record, final_frame = item
                try:
                    with self._lock:
                        config = self._configs.get(record.config_digest)
                    if config is not None and config.sim.faults.disk_full:
                        raise OSError(errno.ENOSPC, "No space left on device (injected: sim.faults.disk_full)")
                    run = self._file_for(record.config_digest)
                    with self._lock:  # readers of the current file (read_run_shot) see whole shots only
                        run.append(record, final_frame)
                        self.errors.clear()
                except (OSError, KeyError, ValueError) as err:
                    with self._lock:
                        self.errors.append(f"shot {record.shot_id} not recorded: {type(err).__name__}: {err}")
                        del self.errors[:-100]  # keep the latest; the count is in failed_writes
                        self.failed_writes += 1
            finally:
                self._queue.task_done()
