"""The engine host contract (``engine.host.EngineHost``): both hosts answer ``has_trigger_input`` from the
devices, so a card without a trigger input is never armed on a hardware trigger, on a thread or in a process."""

from __future__ import annotations

from dataclasses import replace
from functools import partial
from typing import Any

import pytest

from drivers.sim.lab import build_sim_lab
from engine.config import SystemConfig
from engine.engine import Engine, EngineThread
from engine.host import EngineHost
from engine.process import EngineProcess
from server.service import LabService, NotArmed
from sim_signals import chain_config


class AWGWithoutTrigger:
    """The simulated AWG with its trigger input taken away (as a card whose trigger line is not wired)."""

    def __init__(self, awg: Any) -> None:
        self._awg = awg

    def __getattr__(self, name: str) -> Any:
        if name == "wait_trigger":
            raise AttributeError(name)
        return getattr(self._awg, name)


def config(trigger: str = "software") -> SystemConfig:
    return chain_config(16, loop={"trigger": trigger}, sim={"lossless": True})


def build(with_trigger: bool, trigger: str = "software") -> Engine:
    cfg = config(trigger)
    devices, lab = build_sim_lab(cfg)
    if not with_trigger:
        devices = replace(devices, awg=AWGWithoutTrigger(devices.awg))
    return Engine(cfg, devices, lab=lab)


@pytest.mark.parametrize("with_trigger", [True, False])
def test_thread_host_asks_the_devices(with_trigger: bool) -> None:
    with EngineThread(partial(build, with_trigger)) as host:
        assert host.has_trigger_input is with_trigger
        record, frame = host.run_shot(7).result()
        assert record.shot_id == 7 and frame is not None


def test_process_host_asks_the_devices() -> None:
    with EngineProcess(partial(build, False)) as host:
        assert host.has_trigger_input is False
        assert not host.shares_interpreter


def test_service_refuses_a_hardware_arm_without_a_trigger_input() -> None:
    host: EngineHost = EngineThread(partial(build, False, "hardware"))
    service = LabService(engine_thread=host, pause_s=0.0).start()
    try:
        with pytest.raises(NotArmed, match="no trigger input"):
            service.arm()
        assert not service.armed
    finally:
        service.close()
    with_input = LabService(engine_thread=EngineThread(partial(build, True, "hardware")), pause_s=0.0).start()
    try:
        with_input.arm(shots=1)
        assert with_input.armed
    finally:
        with_input.close()
