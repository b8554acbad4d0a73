"""Run history on disk: every shot appended to an HDF5 file, so that a crash never loses or corrupts earlier shots.

Layout of ``runs/<YYYYmmdd-HHMMSS>-<n>.h5`` (one *run* = consecutive shots under one configuration; any change of
configuration, a one-shot override included, starts a new file, so each file's shapes and config are fixed):

- attrs: ``config_json`` (the whole ``SystemConfig``), ``config_digest``, ``stages`` (JSON list of stage names),
  ``created``; dataset ``target`` ``bool[ny, nx]``;
- per shot (axis 0 grows by one per shot): ``shot_id`` i8, ``outcome`` S16, ``fault`` S256, ``n_cycles`` i2,
  ``duration_s`` f8, ``target_filled`` i1 (1/0, -1 unknown), ``occupancy`` ``bool[shot, cycle, ny, nx]``,
  ``stage_us`` ``f4[shot, cycle, stage]`` (NaN where a stage did not run), ``plan`` ``i4[shot, cycle, 3]``
  (slots, steps, underruns), ``latency_us`` ``f4[shot, cycle]``. Cycles past ``n_cycles`` are zero.

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
import threading
import time
from collections import OrderedDict
from pathlib import Path

import h5py
import numpy as np

from engine.config import SystemConfig
from engine.records import ShotRecord
from engine.targets import build_target
from engine.timing import STAGES

#: Configurations the store remembers for the shots still queued (see ``RunStore.note_config``).
CONFIGS_KEPT = 16

__all__ = ["RunStore"]

_PER_SHOT_1D = {
    "shot_id": "i8",
    "outcome": "S16",
    "fault": "S256",
    "n_cycles": "i2",
    "duration_s": "f8",
    "target_filled": "i1",
}


class _RunFile:
    """One open run file: fixed shapes from its configuration, appended one shot at a time."""

    def __init__(self, path: Path, config: SystemConfig) -> None:
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
        ):
            rows = max(1, min(chunk, (1 << 20) // max(1, int(np.prod(tail)))))
            self.ds[name] = f.create_dataset(
                name, shape=(0, *tail), maxshape=(None, *tail), dtype=dtype, chunks=(rows, *tail)
            )
        f.swmr_mode = True

    def append(self, record: ShotRecord) -> None:
        c = self.max_cycles
        occupancy = np.zeros((c, *self.shape), dtype=bool)
        stage_us = np.full((c, len(STAGES)), np.nan, dtype=np.float32)
        plan = np.zeros((c, 3), dtype=np.int32)
        latency = np.zeros(c, dtype=np.float32)
        for cyc in record.cycles[:c]:
            occupancy[cyc.index] = cyc.occupancy
            for stage, seconds in cyc.stage_s.items():
                if stage in STAGES:
                    stage_us[cyc.index, STAGES.index(stage)] = seconds * 1e6
            plan[cyc.index] = (cyc.n_slots, cyc.n_steps, cyc.underruns)
            latency[cyc.index] = cyc.latency_s * 1e6
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
        }
        i = self.n
        for name, value in values.items():
            ds = self.ds[name]
            ds.resize(i + 1, axis=0)
            ds[i] = value
        for ds in self.ds.values():
            ds.flush()
        self.n = i + 1

    def close(self) -> None:
        self.file.close()


class RunStore:
    """Appends every shot to the run file of its configuration; a writer thread does the disk work.

    ``note_config`` must be called with every configuration before shots under it arrive (the service does it
    when it applies one), so the store can write the config into the file the shot belongs to.
    """

    def __init__(self, directory: str | Path) -> None:
        self.directory = Path(directory)
        self.directory.mkdir(parents=True, exist_ok=True)
        self._configs: OrderedDict[str, SystemConfig] = OrderedDict()  # the latest, for the shots queued
        self._queue: queue.Queue[ShotRecord | None] = queue.Queue()
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

    def put(self, record: ShotRecord) -> None:
        """Queue a finished shot for writing; returns at once (called on the engine thread)."""
        self._queue.put(record)

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
                    self._current = _RunFile(self._new_path(), config)
                    break
                except FileExistsError:  # another process took the name between exists() and create
                    continue
            return self._current

    def _write_loop(self) -> None:
        while True:
            record = self._queue.get()
            try:
                if record is None:
                    return
                try:
                    with self._lock:
                        config = self._configs.get(record.config_digest)
                    if config is not None and config.sim.faults.disk_full:
                        raise OSError(errno.ENOSPC, "No space left on device (injected: sim.faults.disk_full)")
                    self._file_for(record.config_digest).append(record)
                    with self._lock:
                        self.errors.clear()
                except (OSError, KeyError, ValueError) as err:
                    with self._lock:
                        self.errors.append(f"shot {record.shot_id} not recorded: {type(err).__name__}: {err}")
                        del self.errors[:-100]  # keep the latest; the count is in failed_writes
                        self.failed_writes += 1
            finally:
                self._queue.task_done()
