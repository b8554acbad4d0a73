"""The shots a lab service holds in memory: the newest records by id, their tallies and their final frames.

Its own lock guards it, so queries (the REST API's, the dashboard's) never wait for the engine lock; the
service (``server.service.LabService``) adds every shot here and answers its history queries from it.
"""

from __future__ import annotations

import threading
from collections import OrderedDict, deque

import numpy as np

from engine.records import ShotRecord

__all__ = ["ShotHistory"]


class ShotHistory:
    """The newest ``history`` shot records, the success tallies of every shot, and the final camera frame
    of the newest ``final_frames_kept`` shots (one frame per shot, not one per cycle)."""

    def __init__(self, history: int, *, final_frames_kept: int = 32) -> None:
        self.final_frames_kept = final_frames_kept
        self._lock = threading.Lock()
        self._records: deque[ShotRecord] = deque(maxlen=history)
        self._by_id: dict[int, ShotRecord] = {}
        self._latest_with_counts: ShotRecord | None = None
        self._shots = 0
        self._successes = 0
        self._truth_successes: int | None = None
        self._last_frame: tuple[int, np.ndarray] | None = None
        self._final_frames: OrderedDict[int, np.ndarray] = OrderedDict()  # shot_id -> its last cycle's frame

    def add(self, record: ShotRecord, frame: np.ndarray | None) -> None:
        """Hold ``record`` (dropping the oldest beyond ``history``) and its final ``frame``, and count it; a
        lab report's ``target_filled`` (the simulated lab's truth) is tallied beside the engine's success."""
        with self._lock:
            if len(self._records) == self._records.maxlen:
                self._by_id.pop(self._records[0].shot_id, None)
            self._records.append(record)
            self._by_id[record.shot_id] = record
            self._shots += 1
            self._successes += record.success
            filled = record.lab_report.get("target_filled")
            if filled is not None:
                self._truth_successes = (self._truth_successes or 0) + bool(filled)
            if frame is not None:
                self._last_frame = (record.shot_id, frame)
                self._final_frames[record.shot_id] = frame
                while len(self._final_frames) > self.final_frames_kept:
                    self._final_frames.popitem(last=False)

    def drop_counts_of_older_shots(self, latest: ShotRecord) -> None:
        """Held records keep their per-trap counts only while they are the latest shot: the run file and the
        trap statistics have them by then, and 2000 held shots of 8192 traps would otherwise hold ~200 MB."""
        previous, self._latest_with_counts = self._latest_with_counts, latest
        if previous is not None and previous is not latest:
            for cycle in previous.cycles:
                cycle.counts = None

    def tallies(self) -> tuple[ShotRecord | None, int, int, int | None]:
        """``(latest record, shots, successes, truth successes)``, read together."""
        with self._lock:
            last = self._records[-1] if self._records else None
            return last, self._shots, self._successes, self._truth_successes

    def page(self, *, limit: int, offset: int) -> tuple[int, list[ShotRecord]]:
        """``(total held, records)`` newest first."""
        with self._lock:
            newest_first = list(reversed(self._records))
        return len(newest_first), newest_first[offset : offset + limit]

    def get(self, shot_id: int) -> ShotRecord | None:
        with self._lock:
            return self._by_id.get(shot_id)

    def last(self) -> ShotRecord | None:
        with self._lock:
            return self._records[-1] if self._records else None

    def frame(self, shot_id: int, cycle: int) -> np.ndarray | None:
        """A camera frame of a held shot: any cycle's if the engine kept images with the record, else the last
        cycle's (the final image) for the most recent shots. ``None`` if not kept."""
        with self._lock:
            record = self._by_id.get(shot_id)
            if record is None:
                return None
            if record.images is not None and cycle < len(record.images):
                return record.images[cycle]
            if cycle == len(record.cycles) - 1:
                return self._final_frames.get(shot_id)
            return None

    def last_frame(self) -> tuple[int, np.ndarray] | None:
        """``(shot_id, uint16[h, w])``: the last camera frame of the latest shot (the final state)."""
        with self._lock:
            return self._last_frame
