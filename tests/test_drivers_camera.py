"""The Andor camera adapter over a fake ``pyAndorSDK2``, alone (frames from the SDK) and with the Active Silicon
frame source over a fake PHX library (frames over Camera Link); what opening says when vendor software is
missing."""

from __future__ import annotations

import ctypes
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.activesilicon import DMA_TIMEOUT_MS, PHX, ActiveSiliconFrameSource, load_library
from drivers.andor import LINUX_SDK_DIR, AndorCamera, FrameSource, status_name
from engine.config import CameraConfig, DevicesConfig
from engine.devices import Camera, DeviceError
from tests.fake_activesilicon import FakePhxLibrary, H
from tests.fake_andor import AC_SETFUNCTION_EMCCDGAIN, DRV_SUCCESS, make_fake_andor, pattern


def camera_config(**kw: Any) -> CameraConfig:
    base = {"roi_width_px": 64, "roi_height_px": 16, "binning": (1, 1), "exposure_s": 0.001, "em_gain": 200.0,
            "timeout_s": 0.5}
    base.update(kw)
    return CameraConfig(**base)


def andor(settings: dict[str, Any] | None = None, *, grabber: FakePhxLibrary | None = None, pcf: Path | None = None,
          **fake_kw: Any) -> tuple[AndorCamera, Any]:
    mod = make_fake_andor(**fake_kw)
    source = None
    if grabber is not None:
        source = ActiveSiliconFrameSource(DevicesConfig.ActiveSiliconSettings(config_file=str(pcf)), library=grabber)
        mod.fake.sinks.append(grabber.deliver)
    cam = AndorCamera(DevicesConfig.AndorSettings(**(settings or {})), frame_source=source, sdk_module=mod)
    return cam, mod.fake


@pytest.fixture
def pcf(tmp_path: Path) -> Path:
    path = tmp_path / "andor_ixonultra888.pcf"
    path.write_text("; camera file\n")
    return path


def calls(fake: Any) -> list[str]:
    return [c[0] for c in fake.log]


# --- opening ----------------------------------------------------------------------------------------------

def test_without_the_wrapper_opening_says_to_install_the_sdk(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "pyAndorSDK2", None)
    with pytest.raises(DeviceError, match="pyAndorSDK2 package is not installed; install Andor SDK2"):
        AndorCamera().open()


def test_without_the_library_opening_says_so() -> None:
    cam, _ = andor(library_missing=True)
    with pytest.raises(DeviceError, match="Andor SDK library could not be loaded.*libandor"):
        cam.open()


def test_a_camera_index_beyond_what_the_sdk_sees_names_the_setting() -> None:
    cam, _ = andor({"index": 1})
    with pytest.raises(DeviceError, match=r"devices\.andor\.index is 1 but the SDK sees 1 camera"):
        cam.open()


def test_open_initializes_and_starts_cooling_that_outlives_shutdown() -> None:
    cam, fake = andor({"temperature_c": -70, "wait_for_temperature_s": 1.0})
    cam.open()
    assert calls(fake)[:4] == ["atmcd", "GetAvailableCameras", "GetCameraHandle", "SetCurrentCamera"]
    assert fake.settings["SetTemperature"] == -70 and fake.settings["CoolerON"] and fake.settings["SetCoolerMode"] == 1
    assert cam.status()["temperature_status"] == "DRV_TEMP_STABILIZED"
    cam.close()
    assert fake.shut_down and "CoolerOFF" not in calls(fake)


# --- configuration ----------------------------------------------------------------------------------------

def test_configure_programs_roi_binning_gain_and_trigger_then_starts_acquiring() -> None:
    cam, fake = andor({"roi_offset_px": (10, 20), "hs_speed_index": 1, "preamp_gain_index": 2, "em_gain_mode": "real"})
    cam.configure(camera_config(roi_width_px=64, roi_height_px=16, binning=(2, 2), em_gain=500, exposure_s=0.02,
                                horizontal_rate_hz=20e6, vertical_shift_s=0.6e-6, vertical_clock_voltage=4))
    s = fake.settings
    assert s["SetImage"] == (2, 2, 11, 74, 21, 36)  # 1-based inclusive sensor coordinates, whole bins
    assert cam.frame_shape == (8, 32)
    assert (s["SetReadMode"], s["SetAcquisitionMode"], s["SetTriggerMode"]) == (4, 5, 1)
    assert s["SetFrameTransferMode"] == 1 and s["SetOutputAmplifier"] == 0 and s["SetHSSpeed"] == (0, 1)
    assert s["SetVSSpeed"] == 0 and s["SetVSAmplitude"] == 4  # the camera config's speed when no index is set
    assert (s["SetEMGainMode"], s["SetEMAdvanced"], s["SetEMCCDGain"]) == (3, 1, 500)
    assert s["SetCameraLinkMode"] == 0 and s["SetExposureTime"] == 0.02 and s["SetPreAmpGain"] == 2
    order = calls(fake)
    assert order.index("AbortAcquisition") < order.index("SetImage") < order.index("PrepareAcquisition") \
        < order.index("StartAcquisition") == len(order) - 1
    assert fake.acquiring
    cam.configure(camera_config(exposure_s=0.05, horizontal_rate_hz=20e6))  # again while acquiring: it stops first
    assert fake.settings["SetExposureTime"] == 0.05 and fake.acquiring


@pytest.mark.parametrize(
    ("settings", "config", "match"),
    [
        ({"roi_offset_px": (1000, 0)}, {}, r"does not fit the 1024x1024 sensor.*roi_offset_px"),
        ({"em_gain_mode": "dac255"}, {"em_gain": 300}, r"camera\.em_gain = 300 is outside .* 0\.\.255"),
        ({"vs_speed_index": 9}, {}, r"SetVSSpeed failed with DRV_P1INVALID; devices\.andor\.vs_speed_index"),
        ({"vs_speed_index": 1}, {}, r"shifts rows in 1\.13 us but camera\.vertical_shift_s is 4\.33 us"),
        ({}, {"vertical_shift_s": 1e-6}, r"not a vertical shift speed of this camera; it has 0\.6, 1\.13"),
        ({"hs_speed_index": 2}, {}, r"hs_speed_index 2 reads 10 MHz but camera\.horizontal_rate_hz is 30 MHz"),
    ],
)
def test_bad_settings_fail_naming_the_field(settings: dict[str, Any], config: dict[str, Any], match: str) -> None:
    cam, _ = andor(settings)
    with pytest.raises(DeviceError, match=match):
        cam.configure(camera_config(**config))


def test_em_gain_above_300_is_reached_by_setting_advanced_mode_before_reading_the_range() -> None:
    cam, fake = andor({"em_gain_mode": "real"})
    cam.configure(camera_config(em_gain=1000))
    order = calls(fake)
    assert order.index("SetEMGainMode") < order.index("SetEMAdvanced") < order.index("GetEMGainRange")
    assert fake.settings["SetEMAdvanced"] == 1 and fake.settings["SetEMCCDGain"] == 1000
    cam.configure(camera_config(em_gain=200))
    assert fake.settings["SetEMAdvanced"] == 0  # back to the normal range when it is not needed


def test_a_camera_without_the_optional_features_is_not_asked_for_them(pcf: Path) -> None:
    """No EM advanced mode, no crop mode, no Camera Link: the adapter reads GetCapabilities and leaves them be."""
    cam, fake = andor(set_functions=AC_SETFUNCTION_EMCCDGAIN, features=0)
    cam.configure(camera_config(em_gain=200))
    assert not {"SetEMAdvanced", "SetIsolatedCropModeEx", "SetCameraLinkMode"} & set(calls(fake))
    assert fake.acquiring
    with pytest.raises(DeviceError, match=r"outside the camera's range 1\.\.300 .*need EM advanced mode"):
        cam.configure(camera_config(em_gain=500))
    cropping, _ = andor({"crop_mode": True}, set_functions=AC_SETFUNCTION_EMCCDGAIN)
    with pytest.raises(DeviceError, match=r"no isolated crop mode.*devices\.andor\.crop_mode: false"):
        cropping.configure(camera_config())
    grabbing, _ = andor(grabber=FakePhxLibrary(), pcf=pcf, features=0)
    with pytest.raises(DeviceError, match=r"no Camera Link output.*frame_source: andor"):
        grabbing.open()
    unreal, _ = andor({"em_gain_mode": "real"}, em_gain_capability=1)
    with pytest.raises(DeviceError, match=r"em_gain_mode 'real' is not one this camera has.*\['dac255'\]"):
        unreal.configure(camera_config())


def test_crop_mode_left_on_by_an_earlier_run_is_switched_off() -> None:
    cam, fake = andor()
    fake.settings["SetIsolatedCropModeEx"] = (1, 16, 64, 1, 1, 1, 1)  # what the last program left
    cam.configure(camera_config())
    assert fake.settings["SetIsolatedCropModeEx"][0] == 0
    assert fake.settings["SetCameraLinkMode"] == 0  # frames from the SDK: Camera Link off


def test_initialize_looks_for_the_sdk_where_the_installer_puts_it(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(sys, "platform", "linux")
    cam, fake = andor()
    cam.open()
    assert fake.initialize_dir == LINUX_SDK_DIR == "/usr/local/etc/andor"
    cam, fake = andor({"sdk_path": "/opt/andor/etc"})
    cam.open()
    assert fake.initialize_dir == "/opt/andor/etc"


def test_every_status_the_configuration_calls_can_return_has_a_name() -> None:
    names = {code: status_name(code) for code in (20066, 20067, 20068, 20069, 20076, 20077, 20078, 20083, 20991, 20992)}
    assert names[20076] == "DRV_P5INVALID" and names[20077] == "DRV_P6INVALID" and names[20083] == "DRV_P7INVALID"
    assert names[20078] == "DRV_INVALID_MODE" and names[20991] == "DRV_NOT_SUPPORTED"
    assert all(name.startswith("DRV_") for name in names.values())


def test_the_fake_wrapper_rejects_what_the_real_wrapper_rejects() -> None:
    sdk = make_fake_andor().atmcd()
    assert sdk.Initialize("") == DRV_SUCCESS
    with pytest.raises(TypeError, match="c_int"):
        sdk.SetEMCCDGain(300.0)  # c_int(300.0) raises in the wrapper
    with pytest.raises(TypeError):
        sdk.SetImage(1, 1, 1, 64, 1)  # one argument short
    with pytest.raises(TypeError):
        sdk.Initialize(None)  # the wrapper calls dir.encode()
    with pytest.raises(TypeError):
        sdk.SetShutter(1, 1, 0, 0, closing=0)  # no such keyword
    assert sdk.SetHSSpeed(typ=0, index=1) == DRV_SUCCESS  # the wrapper's own parameter names work


# --- frames straight from the SDK --------------------------------------------------------------------------

def test_software_trigger_frames_come_from_the_sdk() -> None:
    cam, fake = andor({"trigger": "software"})
    cam.configure(camera_config())
    out = np.zeros(cam.frame_shape, dtype=np.uint16)
    for k in (1, 2):
        cam.trigger()
        info = cam.read(out, timeout_s=0.5)
        np.testing.assert_array_equal(out, pattern(k, cam.frame_shape))
        assert info.frame_index == k and info.exposure_s == pytest.approx(0.001 + 1e-5) and info.readout_s >= 0


def test_counts_above_32767_survive_the_wrappers_int16_array() -> None:
    """``GetMostRecentImage16`` fills a ``c_short`` buffer: the wrapper hands back int16; an EMCCD count of
    40000 must still arrive as 40000."""
    cam, fake = andor({"trigger": "software"})
    fake.frame_factory = lambda k, shape: np.full(shape, 40000 + k, np.uint16)
    cam.configure(camera_config())
    out = np.zeros(cam.frame_shape, dtype=np.uint16)
    cam.trigger()
    cam.read(out, timeout_s=0.5)
    assert (out == 40001).all()


def test_external_trigger_waits_for_the_frame_after_the_trigger() -> None:
    cam, fake = andor()
    cam.configure(camera_config())
    out = np.zeros(cam.frame_shape, dtype=np.uint16)
    fake.external_trigger()  # a stray frame before our trigger must not be taken for ours
    cam.trigger()
    t0 = time.monotonic()
    with pytest.raises(DeviceError, match="no frame within 0.05 s.*camera line"):
        cam.read(out, timeout_s=0.05)
    assert time.monotonic() - t0 < 1.0
    cam.trigger()
    timer = threading.Timer(0.02, fake.external_trigger)  # the AWG's pulse, a little later
    timer.start()
    cam.read(out, timeout_s=1.0)
    timer.join()
    np.testing.assert_array_equal(out, pattern(2, cam.frame_shape))
    with pytest.raises(DeviceError, match="no exposure pending"):
        cam.read(out, timeout_s=0.01)
    with pytest.raises(DeviceError, match="C-contiguous uint16"):
        cam.trigger()
        cam.read(np.zeros((3, 3), np.uint16), timeout_s=0.01)


# --- frames over Camera Link through the grabber -----------------------------------------------------------

def test_grabber_frames_roi_and_arming_before_the_exposure(pcf: Path) -> None:
    phx = FakePhxLibrary()
    cam, fake = andor(grabber=phx, pcf=pcf)
    armed_at_start: list[bool] = []
    fake.on_start.append(lambda: armed_at_start.append(phx.streaming))
    cam.configure(camera_config(roi_width_px=128, roi_height_px=32, binning=(1, 2)))
    assert fake.settings["SetCameraLinkMode"] == 1
    assert armed_at_start == [True]  # the grabber listens before the camera can send a frame
    assert phx.params[PHX.ROI_XLENGTH] == 128 and phx.params[PHX.ROI_YLENGTH] == 16
    assert phx.params[PHX.CAM_ACTIVE_XLENGTH] == 128 and phx.params[PHX.CAM_ACTIVE_YLENGTH] == 16
    assert phx.params[PHX.CONFIG_FILE] == str(pcf).encode()
    assert phx.params[PHX.BOARD_NUMBER] == PHX.board(1) and phx.params[PHX.CHANNEL_NUMBER] == PHX.channel(1)
    out = np.zeros(cam.frame_shape, dtype=np.uint16)
    for k in (1, 2, 3):
        cam.trigger()
        fake.external_trigger()
        info = cam.read(out, timeout_s=1.0)
        np.testing.assert_array_equal(out, pattern(k, (16, 128)))
        assert info.frame_index == k
        assert phx.streaming  # re-armed for the next exposure
    ops = [c[1] for c in phx.log if c[0] == "PHX_StreamRead"]
    assert ops[-6:] == ["START", "CHECK_AND_WAIT", "BUFFER_GET", "STOP", "BUFFER_RELEASE", "START"]
    cam.close()
    assert not phx.opened and not phx.created and phx.violations == [] and fake.shut_down


@pytest.mark.parametrize("dst_alignment", [1, 256])
def test_grabber_buffer_layout_is_set_so_a_roi_narrower_than_the_camera_file_is_not_sheared(
        pcf: Path, dst_alignment: int) -> None:
    """The camera file's destination buffer is 1024 pixels wide; the iXon sends a 100 x 12 ROI. The adapter
    sets the buffer's format and line length (which the board may round up to its alignment) and copies
    line by line when the lines are padded."""
    phx = FakePhxLibrary(dst_alignment=dst_alignment)
    cam, fake = andor(grabber=phx, pcf=pcf)
    cam.configure(camera_config(roi_width_px=100, roi_height_px=12))
    p = phx.params
    assert p[H.PHX_DST_FORMAT] == H.PHX_DST_FORMAT_Y16 and p[H.PHX_BUF_DST_YLENGTH] == 12
    assert p[H.PHX_BUF_DST_XLENGTH] == (200 if dst_alignment == 1 else 256)
    assert p[H.PHX_TIMEOUT_DMA] == DMA_TIMEOUT_MS and p[H.PHX_ROI_DST_XOFFSET] == p[H.PHX_ROI_DST_YOFFSET] == 0
    out = np.zeros(cam.frame_shape, dtype=np.uint16)
    cam.trigger()
    fake.external_trigger()
    cam.read(out, timeout_s=1.0)
    np.testing.assert_array_equal(out, pattern(1, (12, 100)))
    cam.close()
    assert phx.violations == []


def test_the_fake_grabber_refuses_a_constant_or_an_argument_the_header_does_not_have(pcf: Path) -> None:
    phx = FakePhxLibrary()
    handle = ctypes.c_uint64(0)
    assert phx.PHX_Create(ctypes.byref(handle), None) == H.PHX_OK and handle.value != 0
    value = ctypes.c_uint32(1)
    assert phx.PHX_ParameterSet(handle, ctypes.c_uint32(0xC0021234), ctypes.byref(value)) == H.PHX_ERROR_BAD_PARAM
    assert "0xc0021234 is not a parameter of phx_api.h" in phx.violations[0]
    with pytest.raises(ctypes.ArgumentError):  # etParam is an integer, never a double
        phx.PHX_ParameterSet(handle, ctypes.c_double(1.0), ctypes.byref(value))
    with pytest.raises(ctypes.ArgumentError):  # the value goes by pointer, not by value
        phx.PHX_ParameterSet(handle, ctypes.c_uint32(H.PHX_ROI_XLENGTH), 3.5)
    assert phx.PHX_StreamRead(handle, ctypes.c_uint32(H.PHX_START), None) == H.PHX_ERROR_BAD_HANDLE  # not open
    assert PHX.BUF_DST_XLENGTH == H.PHX_BUF_DST_XLENGTH and PHX.DST_FORMAT_Y16 == H.PHX_DST_FORMAT_Y16
    assert PHX.TIMEOUT_DMA == H.PHX_TIMEOUT_DMA


def test_grabber_timeout_aborts_then_the_next_frame_arrives(pcf: Path) -> None:
    phx = FakePhxLibrary()
    cam, fake = andor(grabber=phx, pcf=pcf)
    cam.configure(camera_config())
    out = np.zeros(cam.frame_shape, dtype=np.uint16)
    cam.trigger()
    t0 = time.monotonic()
    with pytest.raises(DeviceError, match="no frame within 0.05 s"):
        cam.read(out, timeout_s=0.05)
    assert time.monotonic() - t0 < 1.0
    assert not phx.streaming  # the watchdog aborted the wait
    cam.trigger()
    threading.Timer(0.02, fake.external_trigger).start()  # the next read re-arms first
    cam.read(out, timeout_s=1.0)
    np.testing.assert_array_equal(out, pattern(1, cam.frame_shape))
    cam.close()
    assert phx.violations == []


def test_grabber_open_errors_are_clear(tmp_path: Path, pcf: Path) -> None:
    missing = ActiveSiliconFrameSource(
        DevicesConfig.ActiveSiliconSettings(config_file=str(tmp_path / "nope.pcf")), library=FakePhxLibrary())
    with pytest.raises(DeviceError, match=r"nope\.pcf' does not exist \(devices\.activesilicon\.config_file\)"):
        missing.open()
    failing = ActiveSiliconFrameSource(
        DevicesConfig.ActiveSiliconSettings(config_file=str(pcf), board=2), library=FakePhxLibrary())
    with pytest.raises(DeviceError, match=r"PHX_Open failed .*devices\.activesilicon\.board"):
        failing.open()
    with pytest.raises(DeviceError, match=r"PHX library was not found \(tried /nonexistent/libphx\.so\).*ActiveSDK"):
        load_library("/nonexistent/libphx.so")


def test_the_adapters_satisfy_the_protocols(pcf: Path) -> None:
    cam, _ = andor()
    assert isinstance(cam, Camera)
    settings = DevicesConfig.ActiveSiliconSettings(config_file=str(pcf))
    source = ActiveSiliconFrameSource(settings, library=FakePhxLibrary())
    assert isinstance(source, FrameSource)
