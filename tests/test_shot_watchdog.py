"""The shot watchdog: a shot that keeps being slow (here every segment upload late by 0.3 s) is ended as a
fault once it runs past ``loop.watchdog_factor`` times the longest healthy shot, with the atoms held; a
healthy shot never comes near it. An engine stuck in one call that never returns is stopped by the service."""

from __future__ import annotations

from functools import partial

import pytest

from drivers.sim.lab import build_sim_lab
from engine.config import SystemConfig
from engine.engine import Engine
from engine.process import EngineProcess
from engine.records import Outcome
from server.service import DevicesUnavailable, LabService
from server_fakes import FakeEngine, example_config
from sim_signals import chain_config


def chain(**over: object) -> SystemConfig:
    """A 24-trap lossless chain with 2-slot segments, so a plan needs several uploads."""
    data = chain_config(24).model_dump()
    data["sim"].update(lossless=True, seed=5)
    data["awg"].update(waveforms_per_segment=2)
    for section, values in over.items():
        data[section].update(values)  # type: ignore[arg-type]  # every section is a dict
    return SystemConfig.model_validate(data)


def test_slow_shot_ends_as_a_watchdog_fault_with_atoms_held() -> None:
    # a frame may take up to 50 ms: the longest healthy shot is about 6 x 70 ms
    config = chain(loop={"watchdog_factor": 1.0, "max_cycles": 5}, camera={"timeout_s": 0.05})
    devices, lab = build_sim_lab(config)
    engine = Engine(config, devices, lab=lab)
    healthy = engine.run_shot()
    assert healthy.outcome is not Outcome.FAULT, healthy.fault
    assert healthy.duration_s < engine.shot_watchdog_s()

    slow = chain(
        loop={"watchdog_factor": 1.0, "max_cycles": 5},
        camera={"timeout_s": 0.05},
        sim={"faults": {**config.sim.faults.model_dump(), "upload_delay_s": 0.3}},
    )
    engine.apply(slow)
    for _ in range(5):
        record = engine.run_shot()
        if record.outcome is not Outcome.UNSOLVABLE:
            break
    assert record.outcome is Outcome.FAULT and "watchdog" in (record.fault or ""), record.fault
    assert record.duration_s > engine.shot_watchdog_s()
    step = lab.awg.current_step()
    layout = engine._p.streamer.layout  # noqa: SLF001 - the test checks the card's real state
    assert layout.is_idle_step(step) or layout.is_failsafe_step(step)
    atoms = lab.world.n_atoms
    lab.awg.clock.advance(0.01)
    assert lab.world.n_atoms == atoms  # held, not dropped

    engine.apply(config)  # the fault cleared: shots run again
    assert engine.run_shot().outcome is not Outcome.FAULT


def hanging_engine(watchdog_s: float) -> object:
    """A stand-in engine whose shots never end (a device call that never returns), for an engine process."""
    engine = FakeEngine(example_config(), shot_s=3600.0)
    engine.watchdog_s = watchdog_s
    return engine


def test_service_stops_an_engine_process_stuck_in_a_shot() -> None:
    host = EngineProcess(partial(hanging_engine, 0.2))
    service = LabService(engine_thread=host, pause_s=0.0).start()
    try:
        with pytest.raises(DevicesUnavailable, match="watchdog"):
            service.shot()  # given up after 2 x 0.2 s + 1 s
        assert not host.alive  # the stuck process was killed
        status = service.status()
        assert status.state == "fault" and "watchdog" in (status.reason or "")
    finally:
        service.close()
