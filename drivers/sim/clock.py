"""The simulated lab's clock: wall-clock time plus the device waits it skipped, or no wall clock at all.

In ``simulated`` mode a device that would block (an exposure, an upload, playback) calls ``advance(dt)``
and returns at once; the clock jumps ahead by ``dt``. The host's own computation still passes at
wall-clock rate, so latency, underruns and vacuum loss see the engine's real speed. In ``realtime`` mode
``advance`` really waits.

The simulator's own work (rendering a camera frame, decoding played samples) is not the lab's time: it
runs inside ``paused()``, which freezes the simulated clock, so a slow simulation never shows up as a slow
upload or an underrun the hardware would not have.

In ``replay`` mode the clock never reads the wall clock: it moves only by device waits (``advance``) and by
the modelled host time of each stage of the loop (``charge``, called by the engine's stage timer at the end of
each stage; seconds per stage from ``sim.replay_host_s``). Host speed, and so the machine's load, then cannot
change what happens: the same seed gives the same shots, atom for atom. What it cannot show is a host that is
really slow (a slow solve only shows if its charged time says so).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import Literal

__all__ = ["SimClock"]


class SimClock:
    def __init__(
        self,
        mode: Literal["simulated", "realtime", "replay"] = "simulated",
        host_stage_s: Mapping[str, float] | None = None,
    ) -> None:
        """``host_stage_s``: replay mode's charge per stage (seconds; stages not listed cost nothing)."""
        self.mode = mode
        self._skipped_s = 0.0
        self._frozen_s: float | None = None
        self._pause_depth = 0
        self._lock = threading.RLock()
        self._host_stage_s = dict(host_stage_s or {})
        #: ``charge(stage)`` for the engine's stage timer: set in replay mode only, ``None`` otherwise, so the
        #: timer of a wall-clock run does not even make the call.
        self.charge: Callable[[str], None] | None = self._charge if mode == "replay" else None
        if mode == "replay":
            self._frozen_s = 0.0  # replay time starts at zero and only moves when told to

    def now_s(self) -> float:
        frozen = self._frozen_s
        return frozen if frozen is not None else time.perf_counter() + self._skipped_s

    @contextmanager
    def paused(self) -> Iterator[None]:
        """Freeze the clock (simulated mode only; replay time is always frozen) while the simulator computes."""
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
        """Let ``dt_s`` seconds of device time pass (instantly unless realtime)."""
        if dt_s <= 0:
            return
        if self.mode == "realtime":
            deadline = time.perf_counter() + dt_s
            while (remaining := deadline - time.perf_counter()) > 0:
                time.sleep(min(remaining, 1e-3)) if remaining > 2e-3 else None
            return
        with self._lock:
            self._skipped_s += dt_s
            if self._frozen_s is not None:
                self._frozen_s += dt_s

    def advance_to(self, t_s: float) -> None:
        """Let time pass until the clock reads ``t_s`` (no-op if it already does)."""
        self.advance(t_s - self.now_s())

    def _charge(self, stage: str) -> None:
        """Replay mode: the host has just finished ``stage``; its modelled duration passes."""
        self.advance(self._host_stage_s.get(stage, 0.0))
