"""The Andor iXon EMCCD behind ``engine.devices.Camera``, through Andor's Python SDK2 wrapper ``pyAndorSDK2``.

``pyAndorSDK2`` ships with Andor's SDK2 (it is not on PyPI) and loads the SDK's C library (``libandor`` on
Linux). Both are imported only when the camera opens; if either is missing, opening raises ``DeviceError``
saying what to install. Every SDK call returns its status (``DRV_SUCCESS = 20002``) or a tuple
``(status, values...)``; the adapter checks each one and names the call that failed.

What the camera is set to (values are the SDK2 manual's): image read mode (4), acquisition mode "run till
abort" (5) so that every trigger yields a frame without re-arming, the EMCCD output amplifier (0), the EM
gain mode and gain, horizontal/vertical shift speeds (the camera config's ``horizontal_rate_hz`` and
``vertical_shift_s``: the vertical index is looked up from the speed unless ``devices.andor.vs_speed_index``
names it, and either index must give the configured speed), the vertical clock voltage amplitude
(``camera.vertical_clock_voltage``), pre-amp gain, frame transfer,
baseline clamp, the ROI and binning (``SetImage``: 1-based inclusive sensor coordinates; or isolated crop
mode), exposure, trigger mode (external 1, software 10, internal 0), shutter, cooler and set point, and
Camera Link output when frames go through a grabber.

Frames reach the engine one of two ways:
- through a ``FrameSource`` (the Active Silicon grabber, ``drivers/activesilicon.py``): the camera streams
  over Camera Link and the grabber is armed before each exposure (this is the paper's fast path);
- straight from the SDK: after a trigger, wait until the SDK's count of acquired images goes up
  (``GetTotalNumberImagesAcquired`` / ``WaitForAcquisitionTimeOut``), then copy ``GetMostRecentImage16``.

Capabilities: EM advanced mode (gains above x300), Camera Link output and isolated crop mode are optional
features; the adapter reads ``GetCapabilities`` at open and uses a feature only where the camera has it (a
camera without one answers ``DRV_NOT_AVAILABLE`` / ``DRV_NOT_SUPPORTED``). The EM gain range depends on the
gain mode *and* on ``SetEMAdvanced``, so both are set before the range is read. Crop mode, once on, stays on
in the camera until switched off, so it is switched off explicitly when not wanted.

``Initialize`` is given the directory holding the SDK's detector files: ``devices.andor.sdk_path``, or, when
that is empty, ``/usr/local/etc/andor`` on Linux (where Andor's installer puts them) and the SDK's own
default elsewhere.

Triggering: the engine pulses the AWG's camera line and then calls ``trigger()``. In external mode that
pulse starts the exposure and ``trigger()`` only notes the time and the image count; in software mode
``trigger()`` sends ``SendSoftwareTrigger``. Note (SDK2 manual): with frame transfer *and* external trigger
the iXon ends one exposure and starts the next at each trigger; set ``devices.andor.frame_transfer: false``
if each image must hold only the light after its own trigger.
"""

from __future__ import annotations

import importlib
import sys
import time
from collections.abc import Callable
from types import ModuleType
from typing import Any, Protocol, runtime_checkable

import numpy as np

from engine.config import CameraConfig, DevicesConfig
from engine.devices import Clock, DeviceError, FrameInfo
from engine.psf import frame_shape

__all__ = ["AndorCamera", "FrameSource", "import_andor"]

AndorSettings = DevicesConfig.AndorSettings

DRV_SUCCESS = 20002
DRV_NO_NEW_DATA = 20024
DRV_TEMP_OFF = 20034
DRV_TEMP_NOT_STABILIZED = 20035
DRV_TEMP_STABILIZED = 20036
DRV_TEMP_NOT_REACHED = 20037
DRV_TEMP_DRIFT = 20040
DRV_ACQUIRING = 20072
DRV_IDLE = 20073
_NAMES = {
    20002: "DRV_SUCCESS", 20024: "DRV_NO_NEW_DATA", 20034: "DRV_TEMP_OFF", 20035: "DRV_TEMP_NOT_STABILIZED",
    20036: "DRV_TEMP_STABILIZED", 20037: "DRV_TEMP_NOT_REACHED", 20040: "DRV_TEMP_DRIFT", 20066: "DRV_P1INVALID",
    20067: "DRV_P2INVALID", 20068: "DRV_P3INVALID", 20069: "DRV_P4INVALID", 20072: "DRV_ACQUIRING",
    20073: "DRV_IDLE", 20075: "DRV_NOT_INITIALIZED", 20076: "DRV_P5INVALID", 20077: "DRV_P6INVALID",
    20078: "DRV_INVALID_MODE", 20083: "DRV_P7INVALID", 20013: "DRV_ERROR_ACK", 20990: "DRV_ERROR_NOCAMERA",
    20991: "DRV_NOT_SUPPORTED", 20992: "DRV_NOT_AVAILABLE",
}
# GetCapabilities bits (atmcd.h): the optional features the adapter uses
AC_SETFUNCTION_CROPMODE = 0x0400
AC_SETFUNCTION_EMADVANCED = 0x8000
AC_FEATURES_CAMERALINK = 0x8000000
EM_GAIN_CAPABILITY = {"dac255": 1, "dac4095": 2, "linear": 4, "real": 8}  # ulEMGainCapability bit per mode
LINUX_SDK_DIR = "/usr/local/etc/andor"  # where Andor's Linux installer puts the detector files
READ_MODE_IMAGE = 4
ACQ_RUN_TILL_ABORT = 5
AMP_EMCCD = 0
TRIGGER_MODES = {"internal": 0, "external": 1, "software": 10}
EM_GAIN_MODES = {"dac255": 0, "dac4095": 1, "linear": 2, "real": 3}
SHUTTER_MODES = {"auto": 0, "open": 1, "closed": 2}
SHUTTER_TTL_HIGH = 1

INSTALL_SDK = (
    "install Andor SDK2 for your platform (it provides libandor and the pyAndorSDK2 Python wrapper; "
    "pip install the wrapper from the SDK's python folder), then check with 'llrs devices'"
)


def _same_speed(a: float, b: float) -> bool:
    """The SDK answers speeds as 32-bit floats (4.33 us reads 4.3299999): equal to 1 part in 1e4."""
    return abs(a - b) <= 1e-4 * max(abs(a), abs(b))


def status_name(code: int) -> str:
    return _NAMES.get(int(code), str(code))


def initialize_dir(sdk_path: str) -> str:
    """The directory ``Initialize`` gets: the configured one, else the platform's install location."""
    if sdk_path:
        return sdk_path
    return LINUX_SDK_DIR if sys.platform.startswith("linux") else ""


@runtime_checkable
class FrameSource(Protocol):
    """Where frames come from when the camera streams them elsewhere (a Camera Link grabber)."""

    @property
    def frame_shape(self) -> tuple[int, int]: ...

    def open(self) -> None: ...

    def configure(self, width: int, height: int) -> None:
        """Expect frames of ``height x width`` uint16 pixels."""
        ...

    def start(self) -> None:
        """Arm for the next frame (called before the exposure is triggered)."""
        ...

    def read(self, out: np.ndarray, *, timeout_s: float) -> int:
        """Block until the next frame is in ``out``; return a running frame count; ``DeviceError`` on timeout."""
        ...

    def stop(self) -> None: ...

    def close(self) -> None: ...


def import_andor() -> ModuleType:
    """Import ``pyAndorSDK2``, turning a missing package or library into a ``DeviceError``."""
    try:
        return importlib.import_module("pyAndorSDK2")
    except ModuleNotFoundError as err:
        if err.name == "pyAndorSDK2":
            raise DeviceError(f"Andor camera: the pyAndorSDK2 package is not installed; {INSTALL_SDK}") from None
        raise DeviceError(f"Andor camera: pyAndorSDK2 is installed but needs {err.name!r}; {INSTALL_SDK}") from None
    except Exception as err:  # noqa: BLE001 - the wrapper may load the library at import time
        raise DeviceError(
            f"Andor camera: pyAndorSDK2 is installed but the Andor SDK library could not be loaded ({err}); "
            f"{INSTALL_SDK}"
        ) from None


class _HostClock:
    def now_s(self) -> float:
        return time.monotonic()


class AndorCamera:
    """``Camera`` on an Andor iXon (see the module docstring).

    ``sdk_module`` replaces ``import pyAndorSDK2`` (tests pass a fake that records every call);
    ``frame_source`` is the grabber, or ``None`` to read frames from the SDK.
    """

    def __init__(
        self,
        settings: AndorSettings | None = None,
        *,
        frame_source: FrameSource | None = None,
        sdk_module: ModuleType | None = None,
        clock: Clock | None = None,
    ) -> None:
        self.settings = settings if settings is not None else AndorSettings()
        self.frame_source = frame_source
        self._mod = sdk_module
        self._sdk: Any = None
        self._clock: Callable[[], float] = (clock or _HostClock()).now_s
        self._shape: tuple[int, int] = (0, 0)
        self._n_pixels = 0
        self._detector = (0, 0)
        self._exposure_s = 0.0
        self._readout_model_s = 0.0
        self._t_trigger: float | None = None
        self._count_at_trigger = 0
        self._frames = 0
        self._out: np.ndarray | None = None
        self._out_flat: np.ndarray | None = None
        self._trigger_mode = TRIGGER_MODES[self.settings.trigger]
        self._set_functions = 0
        self._features = 0
        self._em_gain_capability = 0
        self.info: dict[str, Any] = {}

    # --- life cycle ------------------------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        return self._sdk is not None

    def open(self) -> None:
        """Load the SDK, pick the camera, initialize it, start cooling; open the frame source."""
        if self._sdk is not None:
            return
        mod = self._mod if self._mod is not None else import_andor()
        self._mod = mod
        try:
            sdk = mod.atmcd()
        except Exception as err:  # noqa: BLE001 - loading libandor fails with OSError and friends
            raise DeviceError(
                f"Andor camera: the Andor SDK library could not be loaded ({err}); {INSTALL_SDK}"
            ) from None
        s = self.settings
        ret, n = sdk.GetAvailableCameras()
        self._ok(ret, "GetAvailableCameras")
        if s.index >= n:
            raise DeviceError(
                f"Andor camera: devices.andor.index is {s.index} but the SDK sees {n} camera(s); check the USB/PCIe "
                "connection and that no other program (Solis) holds the camera"
            )
        ret, handle = sdk.GetCameraHandle(s.index)
        self._ok(ret, "GetCameraHandle")
        self._ok(sdk.SetCurrentCamera(handle), "SetCurrentCamera")
        directory = initialize_dir(s.sdk_path)
        self._ok(sdk.Initialize(directory), "Initialize", hint=(
            f"the SDK's files were looked for in {directory!r}: check devices.andor.sdk_path and the camera's power"))
        self._sdk = sdk
        try:
            ret, xpix, ypix = sdk.GetDetector()
            self._ok(ret, "GetDetector")
            self._detector = (int(xpix), int(ypix))
            ret, serial = sdk.GetCameraSerialNumber()
            self._ok(ret, "GetCameraSerialNumber")
            ret, caps = sdk.GetCapabilities()
            self._ok(ret, "GetCapabilities")
            self._set_functions = int(caps.ulSetFunctions)
            self._features = int(caps.ulFeatures)
            self._em_gain_capability = int(caps.ulEMGainCapability)
            self.info = {"serial": int(serial), "detector": self._detector}
            if self.frame_source is not None and not self._features & AC_FEATURES_CAMERALINK:
                raise DeviceError(
                    "Andor camera: this camera has no Camera Link output (GetCapabilities), so frames cannot come "
                    "through the grabber; set devices.frame_source: andor"
                )
            if s.cooler:
                self._ok(sdk.SetTemperature(s.temperature_c), "SetTemperature",
                         hint="devices.andor.temperature_c is outside the camera's range")
                self._ok(sdk.CoolerON(), "CoolerON")
                if s.keep_cooling_on_close:
                    self._ok(sdk.SetCoolerMode(1), "SetCoolerMode")  # keep cooling after ShutDown
                if s.wait_for_temperature_s > 0:
                    self._wait_for_temperature(s.wait_for_temperature_s)
            if self.frame_source is not None:
                self.frame_source.open()
        except Exception:
            self.close()
            raise

    def _wait_for_temperature(self, timeout_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            ret, temp = self._sdk.GetTemperature()
            if ret == DRV_TEMP_STABILIZED:
                return
            if time.monotonic() > deadline:
                raise DeviceError(
                    f"Andor camera: the temperature did not stabilize at {self.settings.temperature_c} C within "
                    f"{timeout_s:g} s (now {temp} C, {status_name(ret)}); raise devices.andor.wait_for_temperature_s "
                    "or the set point"
                )
            time.sleep(0.5)

    def close(self) -> None:
        """Stop acquiring and shut the SDK down (the cooler keeps running if ``keep_cooling_on_close``)."""
        sdk, self._sdk = self._sdk, None
        try:
            if self.frame_source is not None:
                self.frame_source.close()
        finally:
            if sdk is not None:
                sdk.AbortAcquisition()
                if not self.settings.keep_cooling_on_close:
                    sdk.CoolerOFF()
                sdk.ShutDown()

    def status(self) -> dict[str, Any]:
        """Temperature and its status, and the EM gain the camera reports (for ``llrs devices check`` and
        the dashboard)."""
        if self._sdk is None:
            return {"open": False}
        ret, temp = self._sdk.GetTemperature()
        gain_ret, gain = self._sdk.GetEMCCDGain()
        return {"open": True, "temperature_c": temp, "temperature_status": status_name(ret),
                "em_gain": gain if gain_ret == DRV_SUCCESS else None, **self.info}

    # --- Camera protocol -------------------------------------------------------------------------------

    @property
    def frame_shape(self) -> tuple[int, int]:
        return self._shape

    def configure(self, config: CameraConfig) -> None:
        """Stop acquiring, apply ``config`` and the device settings, arm the frame source, start acquiring."""
        self.open()
        sdk, s = self._sdk, self.settings
        ret = sdk.AbortAcquisition()
        if ret not in (DRV_SUCCESS, DRV_IDLE):
            self._ok(ret, "AbortAcquisition")
        bx, by = config.binning
        try:
            h, w = frame_shape(config)
        except ValueError as err:
            raise DeviceError(f"Andor camera: {err}") from None
        x0, y0 = s.roi_offset_px
        xpix, ypix = self._detector
        if x0 + w * bx > xpix or y0 + h * by > ypix:
            raise DeviceError(
                f"Andor camera: the ROI ({w * bx}x{h * by} px at offset ({x0}, {y0})) does not fit the "
                f"{xpix}x{ypix} sensor; check camera.roi_width_px/roi_height_px/binning and devices.andor.roi_offset_px"
            )
        ok = self._ok
        ok(sdk.SetReadMode(READ_MODE_IMAGE), "SetReadMode")
        ok(sdk.SetAcquisitionMode(ACQ_RUN_TILL_ABORT), "SetAcquisitionMode")
        ok(sdk.SetFrameTransferMode(1 if s.frame_transfer else 0), "SetFrameTransferMode")
        ok(sdk.SetOutputAmplifier(AMP_EMCCD), "SetOutputAmplifier")
        ok(sdk.SetHSSpeed(AMP_EMCCD, s.hs_speed_index), "SetHSSpeed", hint="devices.andor.hs_speed_index")
        self._check_horizontal_rate(config.horizontal_rate_hz, s.hs_speed_index)
        vs_index = self._vertical_shift_index(config.vertical_shift_s) if s.vs_speed_index is None else s.vs_speed_index
        ok(sdk.SetVSSpeed(vs_index), "SetVSSpeed", hint="devices.andor.vs_speed_index")
        ret, vs_us = sdk.GetVSSpeed(vs_index)
        ok(ret, "GetVSSpeed")
        if not _same_speed(vs_us * 1e-6, config.vertical_shift_s):
            raise DeviceError(
                f"Andor camera: devices.andor.vs_speed_index {vs_index} shifts rows in {vs_us:g} us but "
                f"camera.vertical_shift_s is {config.vertical_shift_s * 1e6:g} us (the readout model and the "
                "simulated camera use it); make them agree, or leave vs_speed_index null to pick it from the camera"
            )
        ok(sdk.SetVSAmplitude(config.vertical_clock_voltage), "SetVSAmplitude", hint="camera.vertical_clock_voltage")
        ok(sdk.SetPreAmpGain(s.preamp_gain_index), "SetPreAmpGain", hint="devices.andor.preamp_gain_index")
        if not self._em_gain_capability & EM_GAIN_CAPABILITY[s.em_gain_mode]:
            modes = [m for m, bit in EM_GAIN_CAPABILITY.items() if self._em_gain_capability & bit]
            raise DeviceError(
                f"Andor camera: devices.andor.em_gain_mode '{s.em_gain_mode}' is not one this camera has "
                f"(GetCapabilities); use one of {modes}"
            )
        ok(sdk.SetEMGainMode(EM_GAIN_MODES[s.em_gain_mode]), "SetEMGainMode")
        gain = int(round(config.em_gain))
        advanced = bool(self._set_functions & AC_SETFUNCTION_EMADVANCED)
        if advanced:  # before the range is read: the range depends on it
            ok(sdk.SetEMAdvanced(1 if gain > 300 else 0), "SetEMAdvanced")
        ret, lo, hi = sdk.GetEMGainRange()
        ok(ret, "GetEMGainRange")
        if not lo <= gain <= hi:
            why = "" if advanced or gain <= 300 else " (gains above 300 need EM advanced mode, which this camera lacks)"
            raise DeviceError(
                f"Andor camera: camera.em_gain = {config.em_gain:g} is outside the camera's range {lo}..{hi} "
                f"in EM gain mode '{s.em_gain_mode}'{why}"
            )
        ok(sdk.SetEMCCDGain(gain), "SetEMCCDGain")
        ok(sdk.SetBaselineClamp(1 if s.baseline_clamp else 0), "SetBaselineClamp")
        if self._features & AC_FEATURES_CAMERALINK:
            ok(sdk.SetCameraLinkMode(1 if self.frame_source is not None else 0), "SetCameraLinkMode")
        crop_capable = bool(self._set_functions & AC_SETFUNCTION_CROPMODE)
        if s.crop_mode and not crop_capable:
            raise DeviceError("Andor camera: this camera has no isolated crop mode (GetCapabilities); set "
                              "devices.andor.crop_mode: false")
        if crop_capable:  # on, or explicitly off: a crop mode left on by an earlier run would persist
            ok(sdk.SetIsolatedCropModeEx(1 if s.crop_mode else 0, h * by, w * bx, by, bx, x0 + 1, y0 + 1),
               "SetIsolatedCropModeEx", hint="crop mode needs frame transfer and a ROI the camera supports")
        if s.crop_mode:
            ok(sdk.SetImage(bx, by, 1, w * bx, 1, h * by), "SetImage")
        else:
            ok(sdk.SetImage(bx, by, x0 + 1, x0 + w * bx, y0 + 1, y0 + h * by), "SetImage")
        ok(sdk.SetExposureTime(config.exposure_s), "SetExposureTime")
        ok(sdk.SetTriggerMode(self._trigger_mode), "SetTriggerMode")
        ok(sdk.SetShutter(SHUTTER_TTL_HIGH, SHUTTER_MODES[s.shutter], 0, 0), "SetShutter")
        ok(sdk.SetKineticCycleTime(0.0), "SetKineticCycleTime")
        ret, exposure, _accumulate, _kinetic = sdk.GetAcquisitionTimings()
        ok(ret, "GetAcquisitionTimings")
        ret, readout = sdk.GetReadOutTime()
        ok(ret, "GetReadOutTime")
        self._exposure_s = float(exposure)
        self._readout_model_s = float(readout)
        self._shape = (h, w)
        self._n_pixels = h * w
        self._out = None
        if self.frame_source is not None:
            self.frame_source.configure(w, h)
            self.frame_source.start()  # armed before the camera can produce a frame
        ok(sdk.PrepareAcquisition(), "PrepareAcquisition")
        ok(sdk.StartAcquisition(), "StartAcquisition")
        self._t_trigger = None

    def trigger(self) -> None:
        """Note the exposure start (and the image count); in software trigger mode, trigger the camera."""
        sdk = self._sdk
        if sdk is None or not self._n_pixels:
            raise DeviceError("Andor camera: trigger() before configure()")
        if self.frame_source is None:
            ret, count = sdk.GetTotalNumberImagesAcquired()
            if ret != DRV_SUCCESS:
                self._ok(ret, "GetTotalNumberImagesAcquired")
            self._count_at_trigger = count
        self._t_trigger = self._clock()
        if self._trigger_mode == 10:
            ret = sdk.SendSoftwareTrigger()
            if ret != DRV_SUCCESS:
                self._ok(ret, "SendSoftwareTrigger")

    def read(self, out: np.ndarray, *, timeout_s: float) -> FrameInfo:
        """Block until the triggered frame is in ``out`` (``uint16[h, w]``); ``DeviceError`` on timeout."""
        t0 = self._t_trigger
        if t0 is None:
            raise DeviceError(
                "Andor camera: read() with no exposure pending; call trigger() first "
                "(on hardware: check that the AWG's camera trigger line reaches the EMCCD)"
            )
        if out is not self._out:
            if out.shape != self._shape or out.dtype != np.uint16 or not out.flags.c_contiguous:
                raise DeviceError(
                    f"Andor camera: out must be a C-contiguous uint16{self._shape} array, got {out.dtype}{out.shape}"
                )
            self._out, self._out_flat = out, out.reshape(-1)
        self._t_trigger = None
        if self.frame_source is not None:
            self.frame_source.read(out, timeout_s=timeout_s)
        else:
            self._read_from_sdk(timeout_s)
        t_done = self._clock()
        self._frames += 1
        return FrameInfo(
            t_exposure_start_s=t0,
            exposure_s=self._exposure_s,
            readout_s=max(t_done - t0 - self._exposure_s, 0.0),
            frame_index=self._frames,
        )

    def _read_from_sdk(self, timeout_s: float) -> None:
        sdk = self._sdk
        deadline = time.monotonic() + timeout_s
        while True:
            ret, count = sdk.GetTotalNumberImagesAcquired()
            if ret != DRV_SUCCESS:
                self._ok(ret, "GetTotalNumberImagesAcquired")
            if count > self._count_at_trigger:
                break
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise DeviceError(
                    f"Andor camera: no frame within {timeout_s:g} s of the trigger; check that the AWG's camera line "
                    "reaches the camera's external trigger input, the trigger mode, and camera.timeout_s"
                )
            ret = sdk.WaitForAcquisitionTimeOut(max(1, int(remaining * 1000)))
            if ret not in (DRV_SUCCESS, DRV_NO_NEW_DATA):
                self._ok(ret, "WaitForAcquisitionTimeOut")
        ret, image = sdk.GetMostRecentImage16(self._n_pixels)
        if ret != DRV_SUCCESS:
            self._ok(ret, "GetMostRecentImage16")
        # the wrapper returns int16 (it allocates c_short); the camera's counts are unsigned 16-bit: same bits
        if self._out_flat is None:
            raise DeviceError("Andor camera: read() before configure(): no frame buffer to fill")
        np.copyto(self._out_flat, image.view(np.uint16))

    def _vertical_shift_index(self, shift_s: float) -> int:
        """The SDK's index of the vertical shift speed ``shift_s`` (``GetVSSpeed`` answers in microseconds)."""
        sdk = self._sdk
        ret, n = sdk.GetNumberVSSpeeds()
        self._ok(ret, "GetNumberVSSpeeds")
        speeds_us = []
        for index in range(n):
            ret, speed_us = sdk.GetVSSpeed(index)
            self._ok(ret, "GetVSSpeed")
            if _same_speed(speed_us * 1e-6, shift_s):
                return index
            speeds_us.append(f"{speed_us:g}")
        raise DeviceError(
            f"Andor camera: camera.vertical_shift_s = {shift_s * 1e6:g} us is not a vertical shift speed of this "
            f"camera; it has {', '.join(speeds_us)} us"
        )

    def _check_horizontal_rate(self, rate_hz: float, index: int) -> None:
        """The readout rate at ``index`` of the EM amplifier must be ``camera.horizontal_rate_hz``."""
        ret, rate_mhz = self._sdk.GetHSSpeed(0, AMP_EMCCD, index)
        self._ok(ret, "GetHSSpeed", hint="devices.andor.hs_speed_index")
        if not _same_speed(rate_mhz * 1e6, rate_hz):
            raise DeviceError(
                f"Andor camera: devices.andor.hs_speed_index {index} reads {rate_mhz:g} MHz but "
                f"camera.horizontal_rate_hz is {rate_hz / 1e6:g} MHz (the readout model and the simulated camera "
                "use it); set the index of that rate or change the rate"
            )

    @staticmethod
    def _ok(ret: int, call: str, *, hint: str = "") -> None:
        if ret != DRV_SUCCESS:
            raise DeviceError(f"Andor camera: {call} failed with {status_name(ret)}" + (f"; {hint}" if hint else ""))
