"""The device protocols the engine drives. Implementations live in ``drivers/`` (the simulated lab in
``drivers/sim``); the engine never imports a vendor SDK.

Time: every device set provides a ``Clock``. On hardware it is the host's monotonic clock. In the simulated
lab it may run *simulated*: device waits (exposure, readout, uploads, playback) advance the clock instantly
by their modelled duration, while the host's own computation still counts at wall-clock rate. The engine
times its stages with this clock, so stage times mean the same thing on both.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from engine.config import AWGConfig, CameraConfig

__all__ = ["Camera", "Clock", "DeviceError", "DeviceSet", "FrameInfo", "SequenceAWG", "StepInfo"]


class DeviceError(RuntimeError):
    """A device failed or timed out; the message says which device and what to check."""


@runtime_checkable
class Clock(Protocol):
    def now_s(self) -> float:
        """Seconds on a monotonic clock shared by the host and the devices."""
        ...


@dataclass(frozen=True)
class FrameInfo:
    """What came with a frame: when exposure started and how long readout + transfer took (the paper's model)."""

    t_exposure_start_s: float
    exposure_s: float
    readout_s: float
    frame_index: int


@runtime_checkable
class Camera(Protocol):
    """An EMCCD behind a frame grabber (or a simulated one)."""

    @property
    def frame_shape(self) -> tuple[int, int]:
        """``(height, width)`` of frames after ROI and binning."""
        ...

    def configure(self, config: CameraConfig) -> None: ...

    def trigger(self) -> None:
        """Start an exposure now (on hardware the AWG's async output does this; the adapter may no-op)."""
        ...

    def read(self, out: np.ndarray, *, timeout_s: float) -> FrameInfo:
        """Block until the triggered frame has arrived and write it into ``out`` (``uint16[h, w]``).

        Raises ``DeviceError`` on timeout.
        """
        ...

    def close(self) -> None: ...


@dataclass(frozen=True)
class StepInfo:
    """One entry of the AWG's sequence memory."""

    segment: int
    next_step: int
    loops: int = 1
    on_trigger: bool = False


@runtime_checkable
class SequenceAWG(Protocol):
    """An AWG in sequence mode (Spectrum M4i style): segments of samples, and steps that play a segment
    ``loops`` times and then go to ``next_step`` (waiting for a trigger first when ``on_trigger``).

    Samples are ``int16[n_samples, n_channels]`` (channels interleaved in memory, as the card stores them).
    Steps and segments may be rewritten while the card plays; a segment that is playing must not be written.
    """

    @property
    def n_channels(self) -> int: ...

    @property
    def sample_rate_hz(self) -> float: ...

    def configure(self, config: AWGConfig, *, n_channels: int, sample_rate_hz: float) -> None: ...

    def write_segment(self, index: int, samples: np.ndarray) -> None:
        """Upload ``samples`` into data-memory segment ``index`` (blocking until the transfer is done)."""
        ...

    def start_upload(self, index: int, samples: np.ndarray) -> None:
        """Start a DMA of ``samples`` into segment ``index`` and return at once, so the host can render the
        next segment meanwhile. ``samples`` must stay untouched until ``wait_upload`` returns."""
        ...

    def wait_upload(self, *, timeout_s: float) -> None:
        """Block until the upload started last is in card memory; raises ``DeviceError`` after ``timeout_s``."""
        ...

    def write_step(self, index: int, step: StepInfo) -> None: ...

    def start(self, entry_step: int) -> None:
        """Start playback at ``entry_step`` (the idle step)."""
        ...

    def current_step(self) -> int:
        """The step playing now."""
        ...

    def wait_for_step(self, step: int, *, timeout_s: float) -> None:
        """Block until the card plays ``step``; raises ``DeviceError`` after ``timeout_s``."""
        ...

    def pulse(self, line: str) -> None:
        """Pulse an async digital output: ``"camera"`` (exposure trigger) or ``"resume"`` (the sequencer's clock)."""
        ...

    def stop(self) -> None: ...


@dataclass
class DeviceSet:
    """The devices one engine owns."""

    camera: Camera
    awg: SequenceAWG
    clock: Clock

    def close(self) -> None:
        self.awg.stop()
        self.camera.close()
