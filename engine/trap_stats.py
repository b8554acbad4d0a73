"""Per-trap statistics accumulated over shots: what a physicist looks at to find a bad trap.

Every number is a count in a fixed-size array per trap, so memory stays flat however many shots run; the
imaging histogram keeps the weighted sums of the last ``window_shots`` loaded images in a ring. Statistics are
kept per configuration (``StatsBook``, keyed by the configuration digest): a new array, target or threshold
starts fresh numbers, and going back to an earlier configuration finds its numbers again.

Definitions (each map is ``float[ny, nx]``, NaN where a trap has no samples yet):

- loading probability: the fraction of shots whose first image shows an atom in the trap;
- survival per rearrangement cycle: for every atom a cycle's plan had (moved or left in place), was an atom
  seen where the plan left it in the next image? Counted at that destination trap, so a trap that loses what
  it holds, or what is brought into it, stands out;
- defect rate: the fraction of shots that ended with this target trap empty (target traps only);
- detection disagreements: the fraction of shots whose final detected occupancy differs from the simulated
  lab's ground truth in this trap (only where the lab reports ground truth).
"""

from __future__ import annotations

import threading
from collections import OrderedDict
from typing import Any

import numpy as np

from engine.records import ShotRecord

__all__ = ["StatsBook", "TrapStatistics"]


def _ratio(numerator: np.ndarray, denominator: np.ndarray) -> np.ndarray:
    out = np.full(numerator.shape, np.nan)
    np.divide(numerator, denominator, out=out, where=denominator > 0)
    return out


def _rows_to_bool(rows: list[str]) -> np.ndarray:
    return np.array([[c == "1" for c in row] for row in rows], dtype=bool)


class TrapStatistics:
    """Counts per trap for one configuration (``ny`` x ``nx`` traps), updated by ``add(record)``."""

    def __init__(self, ny: int, nx: int, *, window_shots: int = 50) -> None:
        if ny < 1 or nx < 1 or window_shots < 1:
            raise ValueError(f"TrapStatistics needs ny, nx, window_shots >= 1 (got {ny}, {nx}, {window_shots})")
        self.shape = (ny, nx)
        n = ny * nx
        self.shots = 0
        self.loaded = np.zeros(n, dtype=np.int64)
        self.survival_trials = np.zeros(n, dtype=np.int64)
        self.survival_kept = np.zeros(n, dtype=np.int64)
        self.target = np.zeros(n, dtype=bool)
        self.defects = np.zeros(n, dtype=np.int64)
        self.truth_shots = 0
        self.disagreements = np.zeros(n, dtype=np.int64)
        self.window_shots = window_shots
        self._counts = np.full((window_shots, n), np.nan, dtype=np.float32)  # ring of first-image counts
        self._next = 0
        self.latest_counts = np.zeros((0, n), dtype=np.float32)  # every cycle of the latest shot

    def add(self, record: ShotRecord) -> None:
        """Count one finished shot (a shot with no image, e.g. a fault before the first frame, counts nothing)."""
        cycles = record.cycles
        n = self.loaded.size
        if not cycles or cycles[0].occupancy.size != n:
            return
        self.shots += 1
        occ = [c.occupancy.reshape(-1) for c in cycles]
        self.loaded += occ[0]
        for k in range(len(cycles) - 1):
            moves = cycles[k].moves
            if moves is None:  # no plan played in this cycle
                continue
            where = np.arange(n)  # where the plan leaves the atom of each trap
            where[moves[:, 0]] = moves[:, 1]
            destination = where[np.flatnonzero(occ[k])]
            np.add.at(self.survival_trials, destination, 1)
            np.add.at(self.survival_kept, destination, occ[k + 1][destination])
        self.target = np.asarray(record.target, dtype=bool).reshape(-1)
        self.defects += self.target & ~occ[-1]
        truth_rows = record.lab_report.get("occupancy_rows")
        if truth_rows:
            truth = _rows_to_bool(truth_rows).reshape(-1)
            if truth.size == n:
                self.truth_shots += 1
                self.disagreements += truth != occ[-1]
        counts = [c.counts for c in cycles if c.counts is not None and c.counts.size == n]
        if counts:
            self.latest_counts = np.stack(counts).astype(np.float32)
            self._counts[self._next] = counts[0]
            self._next = (self._next + 1) % self.window_shots

    def recent_counts(self) -> np.ndarray:
        """``float32[m]``: the weighted sums of the first image of the last ``window_shots`` shots (up to)."""
        values = self._counts.ravel()
        return values[np.isfinite(values)]

    def maps(self) -> dict[str, np.ndarray]:
        """Each statistic as ``float[ny, nx]`` (NaN where undefined: no samples, or not a target trap)."""
        shots = np.full(self.loaded.shape, self.shots)
        defect = np.where(self.target, _ratio(self.defects, shots), np.nan)
        maps = {
            "loading_probability": _ratio(self.loaded, shots),
            "survival": _ratio(self.survival_kept, self.survival_trials),
            "defect_rate": defect,
            "disagreement_rate": _ratio(self.disagreements, np.full(self.loaded.shape, self.truth_shots)),
        }
        return {name: values.reshape(self.shape) for name, values in maps.items()}

    def samples(self) -> dict[str, Any]:
        """How many samples each map rests on: shots, shots with ground truth, survival trials per trap."""
        return {
            "shots": self.shots,
            "truth_shots": self.truth_shots,
            "survival_trials": self.survival_trials.reshape(self.shape),
        }


class StatsBook:
    """``TrapStatistics`` per configuration digest (the latest ``configs_kept``), safe to use from threads:
    the service's listener adds shots on the runner thread while routes and the dashboard read."""

    def __init__(self, *, window_shots: int = 50, configs_kept: int = 8) -> None:
        self.window_shots = window_shots
        self.configs_kept = configs_kept
        self._by_digest: OrderedDict[str, TrapStatistics] = OrderedDict()
        self._lock = threading.Lock()

    def add(self, record: ShotRecord) -> None:
        """Count a finished shot under its configuration (a listener of ``LabService``)."""
        ny, nx = np.asarray(record.target).shape
        with self._lock:
            stats = self._by_digest.get(record.config_digest)
            if stats is None or stats.shape != (ny, nx):
                stats = TrapStatistics(ny, nx, window_shots=self.window_shots)
                self._by_digest[record.config_digest] = stats
            self._by_digest.move_to_end(record.config_digest)
            while len(self._by_digest) > self.configs_kept:
                self._by_digest.popitem(last=False)
            stats.add(record)

    def get(self, digest: str) -> TrapStatistics | None:
        with self._lock:
            return self._by_digest.get(digest)

    def reset(self, digest: str | None = None) -> None:
        """Forget the statistics of one configuration (``None``: of every configuration)."""
        with self._lock:
            if digest is None:
                self._by_digest.clear()
            else:
                self._by_digest.pop(digest, None)
