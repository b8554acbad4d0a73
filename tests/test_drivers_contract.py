"""Contract suites: one per device protocol, run against every implementation at hand.

- the simulated devices, always;
- the real adapters over the fake vendor modules (``tests/fake_*.py``), always;
- the real hardware when ``LLRS_HARDWARE`` lists it (``LLRS_HARDWARE=spectrum,andor,activesilicon``), with the
  device settings from the YAML file ``LLRS_HARDWARE_CONFIG`` (default: the built-in defaults). On hardware,
  run the camera suite with ``devices.andor.trigger: software`` unless ``spectrum`` is listed too (then the
  AWG's camera line triggers the camera, as in a shot).

What any implementation must do is what the engine relies on (``engine/devices.py``): clear ``DeviceError``s
for bad arguments, a sequence that plays from an idle step to a plan and back by pointer updates only,
waits that time out, triggers that end ``on_trigger`` loops, frames that arrive after their trigger only.
"""

from __future__ import annotations

import os
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from engine.config import SystemConfig, config_from_dict, load_config
from engine.devices import Camera, DeviceError, SequenceAWG, StepInfo
from engine.psf import frame_shape

HARDWARE = {s.strip() for s in os.environ.get("LLRS_HARDWARE", "").split(",") if s.strip()}


def _config() -> SystemConfig:
    path = os.environ.get("LLRS_HARDWARE_CONFIG")
    base = load_config(path) if path else SystemConfig()
    data = base.model_dump(mode="json")
    data["awg"].update({"n_segments": 16, "n_steps": 64})
    data["camera"].update({"exposure_s": 0.005})
    return config_from_dict(data)


def _hw(name: str) -> Any:
    return pytest.param(name, marks=pytest.mark.skipif(name.split("-")[0] not in HARDWARE,
                                                         reason=f"set LLRS_HARDWARE={name.split('-')[0]} to run"))


# --- SequenceAWG ------------------------------------------------------------------------------------------

@dataclass
class AWGCase:
    awg: SequenceAWG
    config: SystemConfig
    n_channels: int
    close: Callable[[], None]


@pytest.fixture(params=["sim", "spectrum-fake", _hw("spectrum-hw")])
def awg_case(request: pytest.FixtureRequest) -> Iterator[AWGCase]:
    config = _config()
    n_ch = 1 if config.array.trap_source == "aod" else 2
    if request.param == "sim":
        from drivers.sim.lab import build_sim_lab

        devices, _ = build_sim_lab(config)
        case = AWGCase(devices.awg, config, n_ch, devices.awg.stop)
    else:
        from drivers.spectrum import SpectrumAWG

        if request.param == "spectrum-fake":
            from tests.fake_spcm import make_fake_spcm

            awg = SpectrumAWG(config.devices.spectrum, spcm_module=make_fake_spcm())
        else:
            awg = SpectrumAWG(config.devices.spectrum)
        case = AWGCase(awg, config, n_ch, awg.close)
    case.awg.configure(config.awg, n_channels=n_ch, sample_rate_hz=config.waveforms.sample_rate_hz)
    yield case
    case.close()


def _hold(case: AWGCase, slots: int = 1) -> np.ndarray:
    return np.zeros((slots * case.config.waveforms.slot_samples, case.n_channels), dtype=np.int16)


def test_awg_is_a_sequence_awg_with_the_configured_format(awg_case: AWGCase) -> None:
    awg = awg_case.awg
    assert isinstance(awg, SequenceAWG)
    assert awg.n_channels == awg_case.n_channels
    assert awg.sample_rate_hz == awg_case.config.waveforms.sample_rate_hz


def test_awg_rejects_bad_segments_and_steps_with_device_errors(awg_case: AWGCase) -> None:
    awg = awg_case.awg
    hold = _hold(awg_case)
    for index, data in [(awg_case.config.awg.n_segments, hold), (0, hold.astype(np.float64)),
                        (0, np.zeros((hold.shape[0], awg_case.n_channels + 1), np.int16))]:
        with pytest.raises(DeviceError):
            awg.write_segment(index, data)
    awg.write_segment(0, hold)
    for index, step in [(awg_case.config.awg.n_steps, StepInfo(0, 0)), (0, StepInfo(awg_case.config.awg.n_segments, 0)),
                        (0, StepInfo(0, awg_case.config.awg.n_steps)), (0, StepInfo(0, 0, loops=0))]:
        with pytest.raises(DeviceError):
            awg.write_step(index, step)


def test_awg_plays_idle_then_a_plan_then_rests(awg_case: AWGCase) -> None:
    awg = awg_case.awg
    awg.write_segment(0, _hold(awg_case))
    awg.write_step(0, StepInfo(segment=0, next_step=0))
    awg.write_step(2, StepInfo(segment=0, next_step=2))  # a second rest step
    awg.start(0)
    assert awg.current_step() == 0
    awg.wait_for_step(0, timeout_s=0.5)
    awg.write_segment(1, _hold(awg_case, 3))
    awg.write_step(1, StepInfo(segment=1, next_step=2))
    awg.write_step(0, StepInfo(segment=0, next_step=1))  # the pointer that starts the plan
    awg.wait_for_step(2, timeout_s=1.0)
    assert awg.current_step() == 2
    with pytest.raises(DeviceError):
        awg.wait_for_step(5, timeout_s=0.02)
    awg.stop()
    assert awg.current_step() == -1
    awg.stop()


def test_awg_on_trigger_step_waits_for_a_trigger(awg_case: AWGCase) -> None:
    awg = awg_case.awg
    awg.write_segment(0, _hold(awg_case))
    awg.write_step(0, StepInfo(segment=0, next_step=1, on_trigger=True))
    awg.write_step(1, StepInfo(segment=0, next_step=1))
    awg.start(0)
    with pytest.raises(DeviceError):
        awg.wait_for_step(1, timeout_s=0.02)
    awg.force_trigger()  # type: ignore[attr-defined] - the software trigger (POST /api/shots without a sequencer)
    awg.wait_for_step(1, timeout_s=1.0)


def test_awg_pulses_its_lines(awg_case: AWGCase) -> None:
    awg = awg_case.awg
    awg.pulse("camera")
    awg.pulse("resume")
    with pytest.raises(DeviceError):
        awg.pulse("laser")


# --- Camera -----------------------------------------------------------------------------------------------

@dataclass
class CameraCase:
    camera: Camera
    config: SystemConfig
    fire: Callable[[], None]  # what makes the triggered exposure happen (the AWG's camera line on hardware)
    can_miss: bool  # whether the implementation can be triggered without a frame following


@pytest.fixture(params=["sim", "andor-fake", "andor-activesilicon-fake", _hw("andor-hw")])
def camera_case(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[CameraCase]:
    config = _config()
    if request.param == "sim":
        from drivers.sim.lab import build_sim_lab

        devices, _ = build_sim_lab(config)
        case = CameraCase(devices.camera, config, lambda: None, False)
    elif request.param.endswith("-fake"):
        from drivers.andor import AndorCamera
        from tests.fake_andor import make_fake_andor

        mod = make_fake_andor()
        source = None
        if "activesilicon" in request.param:
            from drivers.activesilicon import ActiveSiliconFrameSource
            from tests.fake_activesilicon import FakePhxLibrary

            pcf = tmp_path / "ixon.pcf"
            pcf.write_text("")
            phx = FakePhxLibrary()
            mod.fake.sinks.append(phx.deliver)
            source = ActiveSiliconFrameSource(config.devices.activesilicon.model_copy(update={"config_file": str(pcf)}),
                                              library=phx)
        cam = AndorCamera(config.devices.andor, frame_source=source, sdk_module=mod)
        case = CameraCase(cam, config, mod.fake.external_trigger, True)
    else:
        from drivers.factory import open_devices

        hw = config.model_copy(update={"devices": config.devices.model_copy(
            update={"awg": "spectrum" if "spectrum" in HARDWARE else "sim", "camera": "andor"})})
        devices, _ = open_devices(hw)
        if "spectrum" in HARDWARE:
            devices.awg.configure(hw.awg, n_channels=1, sample_rate_hz=hw.waveforms.sample_rate_hz)
            fire = lambda: devices.awg.pulse("camera")  # noqa: E731 - one line per branch reads best
        else:
            fire = lambda: None  # noqa: E731 - run with devices.andor.trigger: software
        case = CameraCase(devices.camera, hw, fire, True)
    case.camera.configure(case.config.camera)
    yield case
    case.camera.close()


def test_camera_is_a_camera_with_the_configured_frame_shape(camera_case: CameraCase) -> None:
    assert isinstance(camera_case.camera, Camera)
    assert camera_case.camera.frame_shape == frame_shape(camera_case.config.camera)


def test_camera_delivers_one_frame_per_trigger(camera_case: CameraCase) -> None:
    cam = camera_case.camera
    out = np.zeros(cam.frame_shape, dtype=np.uint16)
    indices = []
    for _ in range(3):
        cam.trigger()
        camera_case.fire()
        info = cam.read(out, timeout_s=2.0)
        indices.append(info.frame_index)
        assert info.exposure_s > 0 and info.readout_s >= 0
        assert out.any()
    assert indices == sorted(indices) and len(set(indices)) == 3


def test_camera_read_without_a_trigger_or_a_frame_is_a_device_error(camera_case: CameraCase) -> None:
    cam = camera_case.camera
    out = np.zeros(cam.frame_shape, dtype=np.uint16)
    with pytest.raises(DeviceError):
        cam.read(out, timeout_s=0.05)
    if camera_case.can_miss:
        cam.trigger()  # no pulse follows
        t0 = time.monotonic()
        with pytest.raises(DeviceError):
            cam.read(out, timeout_s=0.05)
        assert time.monotonic() - t0 < 2.0
