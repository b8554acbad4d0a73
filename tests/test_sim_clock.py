"""The simulated lab's clock: skipped device waits, and frozen while the simulator computes."""

import time

from drivers.sim.clock import SimClock


def test_advance_skips_in_simulated_mode() -> None:
    clock = SimClock("simulated")
    t0 = time.perf_counter()
    before = clock.now_s()
    clock.advance(5.0)
    assert clock.now_s() - before >= 5.0
    assert time.perf_counter() - t0 < 0.5


def test_paused_freezes_and_stays_monotonic() -> None:
    clock = SimClock("simulated")
    with clock.paused():
        frozen = clock.now_s()
        time.sleep(0.02)  # wall time passes on purpose: the paused clock must not follow it
        assert clock.now_s() == frozen
        clock.advance(1e-3)  # a device wait inside the pause still counts
        assert clock.now_s() == frozen + 1e-3
    after = clock.now_s()
    assert frozen + 1e-3 <= after < frozen + 1e-3 + 0.01


def test_realtime_advance_waits() -> None:
    clock = SimClock("realtime")
    t0 = clock.now_s()
    clock.advance(0.01)
    assert clock.now_s() - t0 >= 0.01


def test_replay_clock_moves_only_by_device_waits_and_charged_host_stages() -> None:
    clock = SimClock("replay", {"III.solve": 30e-6})
    t0 = clock.now_s()
    time.sleep(0.02)  # wall time passes on purpose: the replay clock must not follow it
    assert clock.now_s() == t0  # wall time does not pass in replay
    clock.advance(1e-3)
    assert clock.charge is not None
    clock.charge("III.solve")
    clock.charge("IV.upload")  # not listed: costs nothing
    assert clock.now_s() == t0 + 1e-3 + 30e-6
    with clock.paused():
        clock.advance(2e-3)
    assert clock.now_s() == t0 + 3e-3 + 30e-6


def test_only_the_replay_clock_charges_host_stages() -> None:
    assert SimClock("simulated").charge is None and SimClock("realtime").charge is None
