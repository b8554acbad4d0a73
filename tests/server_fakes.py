"""A stand-in engine for the server tests: the real ``EngineThread`` around an engine that fakes shots in microseconds.

The server's contract with the engine is small (``config``, ``apply``, ``run_shot``, ``acquire_images``,
``last_frame``, ``devices.close``); faking it keeps the API tests fast and lets them provoke what the simulated
lab rarely does (a refused config, a fault, kept images, a slow shot, optics that differ from the config).
Calibration frames are real simulated EMCCD frames (``drivers.sim.camera.SimCamera``).
"""

from __future__ import annotations

import struct
import threading
import time
import zlib
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from engine.config import SystemConfig, load_config
from engine.engine import EngineThread
from engine.psf import frame_shape
from engine.records import CycleRecord, Outcome, ShotRecord
from engine.targets import build_target
from server.runstore import FrameKeeping, RunStore
from server.service import LabService

EXAMPLE = Path(__file__).resolve().parent.parent / "examples" / "chain-1x64.yaml"


def example_config() -> SystemConfig:
    return load_config(EXAMPLE)


def fake_engine_host(config: SystemConfig, **engine_kw: Any) -> EngineThread:
    """An engine thread whose engine is a ``FakeEngine`` under ``config`` (``engine_kw``: the fake's options)."""
    return EngineThread(lambda: FakeEngine(config, **engine_kw))  # type: ignore[arg-type, return-value]  # a FakeEngine stands in for Engine


@contextmanager
def fake_lab_service(
    runs: Path | None,
    *,
    engine_kw: dict[str, Any] | None = None,
    frames: FrameKeeping | None = None,
    **options: Any,
) -> Iterator[LabService]:
    """A started ``LabService`` over a ``FakeEngine`` on ``example_config()``, recording to ``runs`` (``None``:
    not recorded; camera frames kept as ``frames`` says); ``options`` go to the service (``pause_s`` is 10 ms
    unless given). Closed on exit."""
    config = example_config()
    service = LabService(
        engine_thread=fake_engine_host(config, **(engine_kw or {})),
        store=RunStore(runs, frames=frames) if runs is not None else None,
        config=config,
        **{"pause_s": 0.01, **options},
    ).start()
    try:
        yield service
    finally:
        service.close()


class _Devices:
    def __init__(self) -> None:
        self.closed = False

    def close(self) -> None:
        self.closed = True


class FakeEngine:
    """Loads atoms at ``sim.loading_probability`` and fills the target in one rearrangement when it can.

    ``shot_s``: how long a shot takes (to provoke overlap). ``keep_images``: attach a frame per cycle.
    ``fault``: the next shot faults with this message. An algorithm named ``refuse`` makes ``apply`` raise,
    as the real engine does for a solver it does not know.
    """

    def __init__(
        self,
        config: SystemConfig,
        *,
        shot_s: float = 0.0,
        keep_images: bool = False,
        optics: dict | None = None,
    ) -> None:
        self.devices = _Devices()
        self.optics = optics or {}  # camera fields where the (simulated) truth differs from the config
        self._camera = None
        self._last_frame: np.ndarray | None = None
        self.shots_done = 0
        self.shot_s = shot_s
        self.keep_images = keep_images
        self.fault: str | None = None
        self.applied: list[SystemConfig] = []
        self.in_shot = 0
        self.max_in_shot = 0
        self._guard = threading.Lock()
        self.apply(config)

    has_trigger_input = False  # like an AWG without a trigger line
    watchdog_s = 60.0  # what ``shot_watchdog_s`` answers

    def shot_watchdog_s(self) -> float:
        return self.watchdog_s

    def apply(self, config: SystemConfig) -> None:
        if config.solver.algorithm == "refuse":
            raise ValueError("unknown solver algorithm 'refuse'")
        self.config = config
        self.target = build_target(config.target, nx=config.array.nx, ny=config.array.ny)
        self.rng = np.random.default_rng(config.sim.seed)
        self.applied.append(config)

    def run_shot(self, shot_id: int | None = None) -> ShotRecord:
        with self._guard:
            self.in_shot += 1
            self.max_in_shot = max(self.max_in_shot, self.in_shot)
        try:
            time.sleep(self.shot_s)
            return self._shot(self.shots_done if shot_id is None else shot_id)
        finally:
            with self._guard:
                self.in_shot -= 1

    def _shot(self, shot_id: int) -> ShotRecord:
        cfg = self.config
        record = ShotRecord(
            shot_id=shot_id, config_digest=cfg.digest(), algorithm=cfg.solver.algorithm, target=self.target
        )
        loaded = self.rng.random(self.target.shape) < cfg.sim.loading_probability
        states = [loaded]
        if self.fault is not None:
            record.outcome, record.fault, self.fault = Outcome.FAULT, self.fault, None
        elif loaded.sum() < self.target.sum():
            record.outcome = Outcome.UNSOLVABLE
        elif not np.all(loaded[self.target]):
            states.append(self.target.copy())
            record.outcome = Outcome.SUCCESS
        else:
            record.outcome = Outcome.SUCCESS
        for i, occ in enumerate(states):
            rearranges = i < len(states) - 1
            record.cycles.append(
                CycleRecord(
                    index=i,
                    occupancy=occ,
                    atoms=int(occ.sum()),
                    defects=int((self.target & ~occ).sum()),
                    stage_s={"I.acquire": 30e-3, "II.detect": 20e-6, "III.solve": 5e-6 if rearranges else 0.0},
                    n_slots=3 if rearranges else 0,
                    n_steps=1 if rearranges else 0,
                    pickups=1 if rearranges else 0,
                    # the atoms that do not fit the target are let go (the fake's only loss)
                    lab_report={"lost_by_cause": {"released": int(occ.sum() - states[i + 1].sum())}}
                    if rearranges
                    else {},
                )
            )
        if self.keep_images:
            shape = frame_shape(cfg.camera)  # as a camera configured by it reads them
            record.images = [np.full(shape, 500 + 100 * i, dtype=np.uint16) for i in range(len(states))]
            self._last_frame = record.images[-1]
        record.lab_report = {"target_filled": record.outcome is Outcome.SUCCESS}
        record.duration_s = 0.05
        self.shots_done += 1
        return record

    def last_frame(self) -> np.ndarray | None:
        return self._last_frame

    def acquire_images(self, n: int) -> np.ndarray:
        """``n`` simulated EMCCD frames, each of a freshly loaded array, through optics ``self.optics``."""
        from drivers.sim.camera import SimCamera
        from drivers.sim.clock import SimClock

        cfg = self.config
        truth = cfg.model_copy(update={"camera": cfg.camera.model_copy(update=self.optics)})
        key = truth.camera.model_dump_json()
        if self._camera is None or self._camera[0] != key:
            self._atoms = np.zeros((cfg.array.ny, cfg.array.nx), dtype=bool)
            camera = SimCamera(
                truth, atoms=lambda *_: self._atoms, clock=SimClock("simulated"), rng=np.random.default_rng(7)
            )
            self._camera = (key, camera)
        camera = self._camera[1]
        frames = np.zeros((n, *camera.frame_shape), dtype=np.uint16)
        for i in range(n):
            self._atoms[...] = self.rng.random(self._atoms.shape) < cfg.sim.loading_probability
            camera.trigger()
            camera.read(frames[i], timeout_s=1.0)
        return frames


def png_pixels(data: bytes) -> np.ndarray:
    """The pixels of a 16-bit grayscale PNG as the server encodes it (``server.png``: one IDAT, no filters)."""
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    w, h, depth = struct.unpack(">IIB", data[16:25])
    idat = data[data.index(b"IDAT") + 4 :]
    raw = np.frombuffer(zlib.decompress(idat[: idat.index(b"IEND") - 8]), dtype=np.uint8).reshape(h, -1)
    assert depth == 16 and (raw[:, 0] == 0).all()
    return raw[:, 1:].copy().view(">u2").reshape(h, w)
