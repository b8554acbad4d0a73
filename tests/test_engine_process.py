"""The engine in its own process (``engine.process.EngineProcess``): real shots on the simulated lab, errors
and results across the boundary, a build that fails, a child that dies, and the service on top of it."""

from __future__ import annotations

import os
import signal
from collections.abc import Callable
from functools import partial
from operator import methodcaller

import numpy as np
import pytest

from engine.config import SystemConfig
from engine.devices import DeviceError
from engine.process import EngineProcess, EngineProcessDied, default_engine_cpu, shot_with_frame
from engine.psf import frame_shape
from engine.records import Outcome
from server.serve import build_engine


@pytest.fixture(scope="module")
def engine_process(lossless_chain: SystemConfig):
    with EngineProcess(partial(build_engine, lossless_chain)) as host:
        yield host


def test_shots_run_in_the_child_and_come_back_with_their_frame(engine_process: EngineProcess) -> None:
    assert engine_process.config is not None and engine_process.config.name == "chain-1x64"
    assert engine_process.has_trigger_input
    assert engine_process.alive
    records = [engine_process.submit(shot_with_frame).result(timeout=60) for _ in range(5)]
    ids = [record.shot_id for record, _ in records]
    assert ids == sorted(ids) and len(set(ids)) == 5  # commands run one after another
    for record, frame in records:
        assert record.outcome in (Outcome.SUCCESS, Outcome.UNSOLVABLE)
        assert record.lab_report["target_filled"] == (record.outcome is Outcome.SUCCESS)  # the child's world judged it
        assert isinstance(frame, np.ndarray) and frame.dtype == np.uint16
        assert frame.shape == frame_shape(engine_process.config.camera)  # the example's ROI and binning


def test_errors_cross_the_boundary_with_their_type(engine_process: EngineProcess) -> None:
    with pytest.raises(ValueError, match="n >= 1"):
        engine_process.submit(methodcaller("acquire_images", 0)).result(timeout=30)
    with pytest.raises(Exception, match="pickle"):  # a lambda cannot be sent to another process
        engine_process.submit(lambda engine: engine.config).result(timeout=30)
    frames = engine_process.submit(methodcaller("acquire_images", 2)).result(timeout=30)
    assert engine_process.config is not None
    assert frames.shape == (2, *frame_shape(engine_process.config.camera))  # the engine survived both errors


def test_a_build_that_fails_raises_its_own_error_in_start(lossless_chain: SystemConfig) -> None:
    data = lossless_chain.model_dump()
    data["devices"]["awg"] = "spectrum"  # no Spectrum driver here
    host = EngineProcess(partial(build_engine, SystemConfig.model_validate(data)))
    with pytest.raises(DeviceError):
        host.start(timeout_s=120)
    assert not host.alive


@pytest.mark.skipif(default_engine_cpu() is None, reason="needs two cores to pin the engine")
def test_pinning_keeps_the_server_off_the_engine_core(lossless_chain: SystemConfig) -> None:
    cpu = default_engine_cpu()
    before = os.sched_getaffinity(0)
    host = EngineProcess(partial(build_engine, lossless_chain), cpu=cpu).start(timeout_s=120)
    try:
        assert os.sched_getaffinity(host.pid) == {cpu}
        assert cpu not in os.sched_getaffinity(0)
    finally:
        host.close()
    assert os.sched_getaffinity(0) == before


def test_a_dead_child_fails_pending_and_later_commands_and_the_service_recovers(
    lossless_chain: SystemConfig, lab_server: Callable, wait_until: Callable
) -> None:
    with lab_server(lossless_chain) as (service, client):
        assert client.post("/api/shots").status_code == 200
        old = service._et
        os.kill(old.pid, signal.SIGKILL)
        wait_until(lambda: not old.alive, what="the killed engine process to be seen dead")
        with pytest.raises(EngineProcessDied, match="signal 9"):
            old.submit(shot_with_frame).result(timeout=10)
        r = client.post("/api/shots")
        assert r.status_code == 503 and "signal 9" in r.json()["detail"]
        status = client.get("/api/status").json()
        assert status["state"] == "fault" and "PUT /api/config" in status["reason"]
        assert client.get("/api/shots").json()["total"] >= 1  # the history survived
        # applying a configuration starts a new engine process
        assert client.put("/api/config", json=lossless_chain.model_dump(mode="json")).status_code == 200
        assert client.get("/api/status").json()["state"] != "fault"
        assert client.post("/api/shots").status_code == 200
        assert service._et is not old and service._et.alive


def test_a_command_sent_into_a_dead_childs_pipe_names_how_the_child_ended(
    lossless_chain: SystemConfig, wait_until: Callable
) -> None:
    """The race the service can lose: the child is gone but the results thread has not yet said so. The
    command then breaks the pipe, and the error must still say the child was killed, not "Broken pipe"."""
    host = EngineProcess(partial(build_engine, lossless_chain)).start(timeout_s=120)
    try:
        os.kill(host.pid, signal.SIGKILL)
        wait_until(lambda: host.exit_reason is not None and host._dead is not None, what="the child's death")
        host._dead = None  # as if the results thread had not noticed yet
        with pytest.raises(EngineProcessDied, match="signal 9"):
            host.submit(shot_with_frame).result(timeout=10)
    finally:
        host.close()


def test_an_injected_fault_crosses_the_boundary_and_clears(
    engine_process: EngineProcess, lossless_chain: SystemConfig
) -> None:
    config = lossless_chain
    data = config.model_dump()
    data["sim"]["faults"]["camera"] = "timeout"
    broken = SystemConfig.model_validate(data)
    engine_process.submit(methodcaller("apply", broken)).result(timeout=60)
    record, _ = engine_process.submit(shot_with_frame).result(timeout=60)
    assert record.outcome is Outcome.FAULT and "no frame within" in (record.fault or "")
    engine_process.submit(methodcaller("apply", config)).result(timeout=60)
    record, _ = engine_process.submit(shot_with_frame).result(timeout=60)
    assert record.outcome in (Outcome.SUCCESS, Outcome.UNSOLVABLE) and record.fault is None
