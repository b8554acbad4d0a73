"""The simulated sequence-mode AWG: memory semantics, timing, underruns, errors, and atoms moved by playback."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.sim.awg import SimAWG
from drivers.sim.clock import SimClock
from drivers.sim.world import World
from engine.devices import DeviceError, SequenceAWG, StepInfo
from sim_signals import chain_config, chain_shift, static, synth_slots

N = 16
CFG = chain_config(N, awg={"upload_jitter_s": 0.0})
SLOT_S = CFG.waveforms.slot_duration_s


def make(cfg=CFG, atoms=None, time_mode="simulated"):
    clock = SimClock(time_mode)
    world = World(cfg, clock=clock, lossless=True)
    if atoms is not None:
        world.set_occupancy(np.asarray(atoms, bool).reshape(1, -1))
    return SimAWG(world, clock, cfg), world, clock


HOLD = synth_slots(CFG, [([static(k) for k in range(N)], None)])
# The host's own time runs at wall-clock rate (as on hardware), so a step the host must catch before it
# ends is made long enough (LONG_S) to outlast Python's overhead between two calls.
LONG = np.tile(HOLD, (1000, 1))
LONG_S = 1000 * SLOT_S


def padded(seg: np.ndarray) -> np.ndarray:
    return np.concatenate([seg, LONG])


def test_implements_the_protocol() -> None:
    awg, _, _ = make()
    assert isinstance(awg, SequenceAWG)
    assert awg.n_channels == 1 and awg.sample_rate_hz == CFG.waveforms.sample_rate_hz


def test_upload_time_model() -> None:
    """Replay time: the clock moves by the modelled device time only (no wall-clock host time to flake on)."""
    awg, _, clock = make(time_mode="replay")
    t0 = clock.now_s()
    awg.write_segment(1, np.tile(HOLD, (4, 1)))
    expect = 4 * HOLD.nbytes / CFG.awg.upload_bytes_per_s
    assert clock.now_s() - t0 == pytest.approx(expect, rel=1e-9)
    awg.upload_delay_s = 1e-3
    t0 = clock.now_s()
    awg.write_segment(2, HOLD)
    assert clock.now_s() - t0 == pytest.approx(HOLD.nbytes / CFG.awg.upload_bytes_per_s + 1e-3, rel=1e-9)
    t0 = clock.now_s()
    awg.write_step(0, StepInfo(segment=1, next_step=0))
    assert clock.now_s() - t0 == pytest.approx(CFG.awg.step_write_s, rel=1e-9)


def test_write_errors_name_the_problem() -> None:
    awg, _, _ = make(chain_config(N, awg={"max_memory_bytes": 3 * HOLD.nbytes}))
    with pytest.raises(DeviceError, match="segment index 99"):
        awg.write_segment(99, HOLD)
    with pytest.raises(DeviceError, match="int16"):
        awg.write_segment(0, HOLD.astype(np.int32))
    with pytest.raises(DeviceError, match="shape"):
        awg.write_segment(0, np.zeros((HOLD.shape[0], 2), np.int16))
    with pytest.raises(DeviceError, match="step index"):
        awg.write_step(10_000, StepInfo(segment=0, next_step=0))
    with pytest.raises(DeviceError, match="next_step"):
        awg.write_step(0, StepInfo(segment=0, next_step=10_000))
    with pytest.raises(DeviceError, match="never written"):
        awg.start(3)
    awg.write_segment(0, HOLD)
    awg.write_segment(1, HOLD)
    with pytest.raises(DeviceError, match="does not fit"):
        awg.write_segment(2, np.tile(HOLD, (2, 1)))
    awg.write_step(0, StepInfo(segment=0, next_step=0))
    awg.start(0)
    with pytest.raises(DeviceError, match="playing right now"):
        awg.write_segment(0, HOLD)
    awg.fail_next_upload = True
    with pytest.raises(DeviceError, match="injected"):
        awg.write_segment(1, HOLD)
    awg.write_segment(1, HOLD)  # the knob fires once


def test_loops_next_pointers_and_self_loop_fast_forward() -> None:
    awg, _, clock = make()
    awg.write_segment(0, HOLD)
    awg.write_segment(1, LONG)
    awg.write_segment(2, HOLD)
    awg.write_step(0, StepInfo(segment=0, next_step=0))  # idle
    awg.write_step(1, StepInfo(segment=1, next_step=2, loops=3))
    awg.write_step(2, StepInfo(segment=2, next_step=0))
    awg.start(0)
    clock.advance(5.0)  # five seconds of idle: fast-forwarded
    t0 = time.perf_counter()
    assert awg.current_step() == 0
    # fast-forwarded, not played: decoding five seconds of samples would take seconds; 0.5 s leaves room for a
    # loaded machine's scheduler without letting a played-out idle pass
    assert time.perf_counter() - t0 < 0.5
    assert awg.played_steps()[0].repeats == pytest.approx(5.0 / SLOT_S, rel=1e-3)
    awg.write_step(0, StepInfo(segment=0, next_step=1))
    awg.wait_for_step(1, timeout_s=1e-3)
    awg.write_step(0, StepInfo(segment=0, next_step=0))
    awg.wait_for_step(0, timeout_s=4 * LONG_S)
    log = awg.played_steps()
    assert [r.step for r in log] == [0, 1, 2, 0]
    assert log[1].repeats == 3 and log[1].segment == 1 and log[2].repeats == 1
    assert log[2].t_start_s - log[1].t_start_s == pytest.approx(3 * LONG_S)


def test_wait_for_step_timeout() -> None:
    awg, _, clock = make()
    awg.write_segment(0, HOLD)
    awg.write_step(0, StepInfo(segment=0, next_step=0))
    awg.write_step(1, StepInfo(segment=0, next_step=1))
    awg.start(0)
    t0 = clock.now_s()
    with pytest.raises(DeviceError, match="step 1 not reached"):
        awg.wait_for_step(1, timeout_s=0.25)
    assert clock.now_s() - t0 >= 0.25


def test_on_trigger_waits_for_a_trigger() -> None:
    awg, _, clock = make()
    awg.write_segment(0, HOLD)
    awg.write_step(0, StepInfo(segment=0, next_step=1, on_trigger=True))
    awg.write_step(1, StepInfo(segment=0, next_step=1))
    awg.start(0)
    clock.advance(1.0)
    assert awg.current_step() == 0
    awg.force_trigger()
    awg.wait_for_step(1, timeout_s=2 * SLOT_S)
    assert awg.current_step() == 1


def test_played_data_is_what_was_in_memory_at_play_time() -> None:
    awg, world, clock = make(atoms=[0, 1] + [0] * (N - 2))
    right = padded(synth_slots(CFG, [(chain_shift(N, [1], +1), None)]))
    left = padded(synth_slots(CFG, [(chain_shift(N, [2], -1), None)]))
    awg.write_segment(0, HOLD)
    awg.write_segment(1, right)
    awg.write_step(0, StepInfo(segment=0, next_step=0))
    awg.write_step(1, StepInfo(segment=1, next_step=0))
    awg.start(0)
    awg.write_step(0, StepInfo(segment=0, next_step=1))
    awg.wait_for_step(1, timeout_s=1e-3)
    awg.write_step(0, StepInfo(segment=0, next_step=0))
    awg.wait_for_step(0, timeout_s=2 * LONG_S)
    awg.write_segment(1, left)  # overwritten after it played: the atom stays where 'right' put it
    clock.advance(1e-3)
    assert np.flatnonzero(world.occupancy()[0]).tolist() == [2]
    assert awg.segment_samples(1) is not None and np.array_equal(awg.segment_samples(1), left)


def test_underrun_falls_into_failsafe_and_resumes() -> None:
    """Control steps with failsafes, as the streamer lays them out; the third segment arrives late."""
    atoms = np.zeros(N, bool)
    atoms[2] = True
    awg, world, clock = make(atoms=atoms)
    seg = [synth_slots(CFG, [(chain_shift(N, [k], +1), None)]) for k in (2, 3, 4)]
    awg.write_segment(0, HOLD)
    awg.write_step(0, StepInfo(segment=0, next_step=0))
    awg.start(0)
    # control k: step 1+2k (segment 1+k) -> failsafe step 2+2k (segment 4+k, a steady hold) loops on itself
    for k in range(2):
        awg.write_segment(1 + k, seg[k])
        awg.write_segment(4 + k, HOLD)
        awg.write_step(2 + 2 * k, StepInfo(segment=4 + k, next_step=2 + 2 * k))
        awg.write_step(1 + 2 * k, StepInfo(segment=1 + k, next_step=2 + 2 * k))
    awg.write_step(1, StepInfo(segment=1, next_step=3))  # link control 0 -> control 1
    awg.write_step(0, StepInfo(segment=0, next_step=1))
    awg.wait_for_step(1, timeout_s=1e-3)
    awg.write_step(0, StepInfo(segment=0, next_step=0))
    clock.advance(2e-3)  # the host is late: control 1 played, then its failsafe holds
    assert awg.current_step() == 4
    awg.sync()  # the streaming calls leave the world to whoever looks (the module docstring)
    assert np.flatnonzero(world.occupancy()[0]).tolist() == [4]
    awg.write_segment(3, seg[2])
    awg.write_step(5, StepInfo(segment=3, next_step=0))
    awg.write_step(4, StepInfo(segment=5, next_step=5))  # repoint the failsafe: playback resumes
    awg.wait_for_step(0, timeout_s=1e-2)
    assert np.flatnonzero(world.occupancy()[0]).tolist() == [5]
    assert awg.count_plays([2, 4, 6]) == 1
    assert [r.step for r in awg.played_steps()] == [0, 1, 3, 4, 5, 0]
    assert world.counters.lost == 0 and world.counters.steps == 3


def test_slm_silence_drops_held_atoms_and_steady_failsafe_keeps_them() -> None:
    from sim_signals import grid_config, ramp_up

    cfg = grid_config(8, 6, awg={"upload_jitter_s": 0.0})
    clock = SimClock()
    world = World(cfg, clock=clock, lossless=True)
    occ = np.zeros((6, 8), bool)
    occ[2, 3] = True
    world.set_occupancy(occ)
    awg = SimAWG(world, clock, cfg)
    silence = np.zeros((cfg.waveforms.slot_samples, 2), np.int16)
    extract = synth_slots(cfg, [([ramp_up(3)], [ramp_up(2)])])
    hold = synth_slots(cfg, [([static(3)], [static(2)])])
    awg.write_segment(0, silence)
    awg.write_segment(1, extract)
    awg.write_segment(2, hold)
    awg.write_step(0, StepInfo(segment=0, next_step=0))
    awg.write_step(1, StepInfo(segment=1, next_step=2))
    awg.write_step(2, StepInfo(segment=2, next_step=2))
    awg.start(1)
    clock.advance(0.5)
    awg.sync()
    assert world.held()[2, 3] and not world.occupancy().any()
    awg.write_step(2, StepInfo(segment=2, next_step=0))
    awg.wait_for_step(0, timeout_s=1e-3)
    clock.advance(2 * cfg.waveforms.slot_duration_s)  # the silent slot has played
    awg.sync()
    assert world.n_atoms == 0 and world.counters.lost_dropped == 1


def test_streaming_calls_leave_decoding_and_the_world_to_whoever_looks() -> None:
    """Uploads, step writes and step reads decode nothing and move no atom (a real card decodes nothing; the
    engine's core is the host's); ``sync`` then applies every slot played, where and when it played."""
    atoms = np.zeros(N, bool)
    atoms[2] = True
    awg, world, clock = make(atoms=atoms, time_mode="replay")
    decodes: list[int] = []
    decode = awg.decoder.decode
    awg.decoder.decode = lambda samples: decodes.append(len(samples)) or decode(samples)  # type: ignore[method-assign]
    shift = synth_slots(CFG, [(chain_shift(N, [2], +1), None)])
    awg.write_segment(0, HOLD)
    awg.write_segment(1, shift)
    awg.write_step(0, StepInfo(segment=0, next_step=0))
    awg.write_step(1, StepInfo(segment=1, next_step=0))
    awg.start(0)
    awg.write_step(0, StepInfo(segment=0, next_step=1))  # the hold, then the shift, then the hold again
    clock.advance(1.1 * SLOT_S)  # the shift is playing
    awg.write_step(0, StepInfo(segment=0, next_step=0))
    clock.advance(5 * SLOT_S)
    assert awg.current_step() == 0 and decodes == []
    assert np.flatnonzero(world.occupancy()[0]).tolist() == [2]  # not applied yet
    awg.write_segment(1, HOLD)  # the shift's samples are replaced after it played: the world still sees the shift
    awg.sync()
    assert np.flatnonzero(world.occupancy()[0]).tolist() == [3] and world.counters.steps == 1
    assert [r.step for r in awg.played_steps()] == [0, 1, 0]
