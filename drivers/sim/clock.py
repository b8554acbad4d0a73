"""The simulated lab's clock: wall-clock time plus the device waits it skipped.

In ``simulated`` mode a device that would block (an exposure, an upload, playback) calls ``advance(dt)``
and returns at once; the clock jumps ahead by ``dt``. The host's own computation still passes at
wall-clock rate, so latency, underruns and vacuum loss see the engine's real speed. In ``realtime`` mode
``advance`` really waits.

The simulator's own work (rendering a camera frame, decoding played samples) is not the lab's time: it
runs inside ``paused()``, which freezes the simulated clock, so a slow simulation never shows up as a slow
upload or an underrun the hardware would not have.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Literal

__all__ = ["SimClock"]


class SimClock:
    def __init__(self, mode: Literal["simulated", "realtime"] = "simulated") -> None:
        self.mode = mode
        self._skipped_s = 0.0
        self._frozen_s: float | None = None
        self._pause_depth = 0
        self._lock = threading.RLock()

    def now_s(self) -> float:
        frozen = self._frozen_s
        return frozen if frozen is not None else time.perf_counter() + self._skipped_s

    @contextmanager
    def paused(self) -> Iterator[None]:
        """Freeze the clock (simulated mode only) while the simulator itself computes."""
        if self.mode != "simulated":
            yield
            return
        with self._lock:
            if self._pause_depth == 0:
                self._frozen_s = time.perf_counter() + self._skipped_s
            self._pause_depth += 1
        try:
            yield
        finally:
            with self._lock:
                self._pause_depth -= 1
                if self._pause_depth == 0:
                    assert self._frozen_s is not None
                    self._skipped_s = self._frozen_s - time.perf_counter()
                    self._frozen_s = None

    def advance(self, dt_s: float) -> None:
        """Let ``dt_s`` seconds of device time pass (instantly when simulated)."""
        if dt_s <= 0:
            return
        if self.mode == "simulated":
            with self._lock:
                self._skipped_s += dt_s
                if self._frozen_s is not None:
                    self._frozen_s += dt_s
        else:
            deadline = time.perf_counter() + dt_s
            while (remaining := deadline - time.perf_counter()) > 0:
                time.sleep(min(remaining, 1e-3)) if remaining > 2e-3 else None

    def advance_to(self, t_s: float) -> None:
        """Let time pass until the clock reads ``t_s`` (no-op if it already does)."""
        self.advance(t_s - self.now_s())
