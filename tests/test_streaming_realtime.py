"""Module V under a busy host: plans stream at real-time priority from the first render to the last link and
at normal priority otherwise, and every plan reports the slack the host left the card (replayed time, so the
figures are the model's, not this machine's)."""

from __future__ import annotations

import os

import numpy as np
import pytest

from drivers.sim.lab import build_sim_lab
from engine.config import SystemConfig
from engine.operations import Operations
from engine.solvers import solve
from engine.streaming import RealtimeScheduling, Streamer
from engine.targets import build_target
from engine.waveforms import WaveformBank
from sim_signals import grid_config

pytestmark = pytest.mark.skipif(not hasattr(os, "sched_getscheduler"), reason="Linux scheduling calls")


def config(*, priority: int = 10) -> SystemConfig:
    """16 x 12, red-rec into the centre band: plans of four 32-slot segments; replayed time."""
    return grid_config(
        16, 12,
        solver={"algorithm": "red-rec"},
        target={"kind": "centre", "count": 16 * 6, "rows": None, "cols": None},
        awg={"waveforms_per_segment": 32, "n_segments": 16, "n_steps": 64, "stream_priority": priority},
        sim={"lossless": True, "seed": 3, "time": "replay"},
    )


def a_long_plan(cfg: SystemConfig) -> Operations:
    target = build_target(cfg.target, nx=cfg.array.nx, ny=cfg.array.ny)
    occupancy = np.random.default_rng(0).random((cfg.array.ny, cfg.array.nx)) < 0.6
    ops = solve(occupancy, target, algorithm="red-rec", trap_source="slm").operations
    assert len(ops) > 2 * cfg.awg.waveforms_per_segment  # streams through failsafe-guarded segments
    return ops


class PolicyRecordingAWG:
    """The simulated AWG, noting the calling thread's scheduling policy at every step write."""

    def __init__(self, awg) -> None:  # noqa: ANN001 - any SequenceAWG
        self._awg = awg
        self.policies: list[int] = []

    def write_step(self, *args, **kw) -> None:  # noqa: ANN002, ANN003 - passed through
        self.policies.append(os.sched_getscheduler(0))
        self._awg.write_step(*args, **kw)

    def set_upload_delay(self, delay_s: float) -> None:
        self._awg.upload_delay_s = delay_s

    def __getattr__(self, name: str):  # noqa: ANN204 - everything else is the simulated AWG's
        return getattr(self._awg, name)


def streamer_for(cfg: SystemConfig) -> tuple[Streamer, PolicyRecordingAWG]:
    devices, _ = build_sim_lab(cfg)
    awg = PolicyRecordingAWG(devices.awg)
    streamer = Streamer(cfg, WaveformBank(cfg), awg, devices.clock)
    streamer.program_idle()
    awg.start(streamer.layout.idle_step)
    return streamer, awg


def test_a_plan_streams_at_real_time_priority_and_the_thread_returns_to_normal() -> None:
    cfg = config()
    streamer, awg = streamer_for(cfg)
    if streamer.realtime_refused is not None:
        pytest.skip(f"this OS refuses real-time scheduling: {streamer.realtime_refused}")
    awg.policies.clear()
    report = streamer.stream(a_long_plan(cfg))
    assert report.n_segments >= 3 and report.underruns == 0
    # every link, from the first pointer to the plan's last one, was written at real-time priority
    assert awg.policies and set(awg.policies) == {os.SCHED_FIFO}
    assert os.sched_getscheduler(0) == os.SCHED_OTHER  # and the engine waits for the camera at normal priority


def test_priority_zero_streams_at_normal_priority_and_says_so() -> None:
    cfg = config(priority=0)
    streamer, awg = streamer_for(cfg)
    assert streamer.realtime_refused is not None and "stream_priority is 0" in streamer.realtime_refused
    streamer.stream(a_long_plan(cfg))
    assert set(awg.policies) == {os.SCHED_OTHER}


def test_realtime_scheduling_that_the_os_refuses_is_reported_not_raised(monkeypatch: pytest.MonkeyPatch) -> None:
    def refuse(*_args: object) -> None:
        raise PermissionError(1, "Operation not permitted")

    monkeypatch.setattr(os, "sched_setscheduler", refuse)
    realtime = RealtimeScheduling(10)
    assert realtime.refused is not None and "CAP_SYS_NICE" in realtime.refused
    realtime.enter()  # a no-op, not an error
    realtime.leave()


def test_slack_is_positive_on_time_and_negative_exactly_when_an_upload_is_late() -> None:
    """In replayed time the host costs nothing: the slack is the model's (two segments ahead, DMA faster
    than playback); an upload later than a segment's playback leaves negative slack and an underrun."""
    cfg = config()
    streamer, _ = streamer_for(cfg)
    ops = a_long_plan(cfg)
    report = streamer.stream(ops)
    segment_s = cfg.awg.waveforms_per_segment * cfg.waveforms.slot_duration_s
    assert report.underruns == 0
    assert 0 < report.min_slack_s <= 2 * segment_s
    assert 0 < report.max_upload_s < segment_s

    streamer, awg = streamer_for(cfg)
    awg.set_upload_delay(3 * segment_s)  # the sim AWG's knob behind sim.faults.upload_delay_s
    report = streamer.stream(ops)
    assert report.underruns > 0
    assert report.min_slack_s < 0
