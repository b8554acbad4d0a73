"""Per-stage timing of a cycle, named after the paper's Table 1.

The timer writes into preallocated rows, so timing a cycle allocates no array. Times come from the
device set's clock (see ``engine.devices``), so on the simulated lab device waits count with their
modelled durations.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

__all__ = ["STAGES", "PAPER_TABLE1_MS", "REPLAY_HOST_S", "StageTimer", "summarize_us"]

#: Stage names, in loop order. The paper's Table 1 rows they correspond to are in PAPER_TABLE1_MS.
STAGES: tuple[str, ...] = (
    "I.acquire",  # trigger -> frame in host memory (exposure + transfer + readout)
    "II.detect",  # PSF-weighted sums per trap
    "II.threshold",  # counts -> occupancy
    "III.solve",  # the rearrangement problem
    "III.batch",  # moves -> waveform slots
    "IV.lookup",  # slots of the first two segments -> table keys
    "IV.render",  # samples of the first two segments assembled into upload buffers
    "IV.upload",  # first two segments (and their failsafes) uploaded to the AWG
    "IV.sequence",  # step-memory writes that start playback
    "V.stream",  # playback start -> back at the idle step (remaining uploads overlap with it)
)

#: The paper's Table 1 (ms) for its three problems, for side-by-side reports.
PAPER_TABLE1_MS: dict[str, dict[str, float]] = {
    "1x64": {"I.acquire": 25.454, "II.detect": 0.259, "II.threshold": 0.001, "III.solve": 0.005,
             "III.batch": 0.003, "IV.lookup": 0.078, "IV.upload": 0.553, "IV.sequence": 0.000, "V.stream": 0.746},
    "16x32": {"I.acquire": 30.850, "II.detect": 0.279, "II.threshold": 0.002, "III.solve": 0.035,
              "III.batch": 0.024, "IV.lookup": 0.046, "IV.upload": 0.593, "IV.sequence": 0.025, "V.stream": 2.765},
    "32x64": {"I.acquire": 46.250, "II.detect": 0.269, "II.threshold": 0.007, "III.solve": 0.100,
              "III.batch": 0.077, "IV.lookup": 0.038, "IV.upload": 0.574, "IV.sequence": 0.023, "V.stream": 8.496},
}

#: Host time charged per lap of a stage when the simulated lab replays (``sim.time: replay``): the in-loop
#: per-cycle medians of the 16x32 problem in docs/benchmarks.md (``llrs bench runtime``, 2026-11-23), with
#: IV.lookup and IV.render halved because a plan of more than one segment laps them once per segment of the
#: first two. I.acquire, IV.upload and V.stream are device waits that the simulated devices charge
#: themselves, so they are not listed.
REPLAY_HOST_S: dict[str, float] = {
    "II.detect": 21.1e-6,
    "II.threshold": 6.2e-6,
    "III.solve": 29.8e-6,
    "III.batch": 17.2e-6,
    "IV.lookup": 10.0e-6,
    "IV.render": 106.2e-6,
    "IV.sequence": 39.4e-6,
}

_INDEX = {name: i for i, name in enumerate(STAGES)}
_NOT_RUN = math.nan


class StageTimer:
    """Stage durations (s) for up to ``max_cycles`` cycles of one shot, in preallocated rows.

    ``lap`` sits between the stages it times, so whatever it costs lands in the next stage: it is kept to a
    clock read, one subtraction and a list store (~0.3 us). Rows are Python lists rather than a numpy array
    because indexing a numpy array and ``np.isnan`` on its scalars cost microseconds with cold caches.
    """

    def __init__(
        self, now_s: Callable[[], float], max_cycles: int, *, charge: Callable[[str], None] | None = None
    ) -> None:
        """``charge(stage)``, when given, runs at the end of each lapped stage before the clock is read: a
        replaying simulated clock (``SimClock.charge``) adds the stage's modelled host time there."""
        self._now_s = now_s
        self._charge = charge
        self._rows = [[_NOT_RUN] * len(STAGES) for _ in range(max_cycles)]
        self.cycle = 0
        self._t0 = 0.0

    @property
    def durations_s(self) -> np.ndarray:
        """``float[max_cycles, n_stages]`` copy of the rows, NaN where a stage did not run."""
        return np.array(self._rows, dtype=float)

    def reset(self) -> None:
        for row in self._rows:
            row[:] = [_NOT_RUN] * len(STAGES)
        self.cycle = 0

    def start(self) -> float:
        self._t0 = self._now_s()
        return self._t0

    def lap(self, stage: str) -> float:
        """Add the time since the last ``start``/``lap`` to ``stage`` and restart the lap.

        A stage lapped several times in one cycle (e.g. the uploads of two segments) accumulates.
        """
        if self._charge is not None:
            self._charge(stage)
        t = self._now_s()
        self.record(stage, t - self._t0)
        self._t0 = t
        return t

    def record(self, stage: str, duration_s: float) -> None:
        row = self._rows[self.cycle]
        i = _INDEX[stage]
        previous = row[i]
        row[i] = duration_s if previous != previous else previous + duration_s  # NaN: not run yet

    def cycle_dict(self, cycle: int) -> dict[str, float]:
        """``{stage: seconds}`` of one cycle, stages that did not run left out."""
        row = self._rows[cycle]
        return {name: row[i] for i, name in enumerate(STAGES) if row[i] == row[i]}


def summarize_us(samples_s: dict[str, list[float]]) -> dict[str, dict[str, float]]:
    """``{stage: {"median_us", "p99_us", "mean_us", "max_us", "n"}}`` from lists of durations in seconds."""
    out: dict[str, dict[str, float]] = {}
    for stage in STAGES:
        values = samples_s.get(stage)
        if not values:
            continue
        us = np.asarray(values) * 1e6
        out[stage] = {
            "median_us": float(np.median(us)),
            "p99_us": float(np.percentile(us, 99)),
            "mean_us": float(us.mean()),
            "max_us": float(us.max()),
            "n": int(us.size),
        }
    return out
