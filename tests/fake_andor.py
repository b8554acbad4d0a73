"""A fake ``pyAndorSDK2`` for testing ``drivers/andor.py`` without a camera or Andor's SDK.

Calls return what the real wrapper returns (a status, or ``(status, values...)``; ``DRV_SUCCESS = 20002``)
and are all recorded in ``fake.log``. The model keeps the rules the adapter must respect:
- nothing works before ``Initialize``; settings are refused with ``DRV_ACQUIRING`` while acquiring;
- ``SetImage`` takes 1-based inclusive sensor coordinates whose spans divide by the binning and fit the
  detector;
- in run-till-abort mode each trigger makes one frame (software trigger in mode 10, ``external_trigger()``
  in mode 1); frames go to Camera Link sinks (a fake grabber) when Camera Link mode is on, and are counted
  and kept for ``GetMostRecentImage16`` either way;
- EM gain within ``GetEMGainRange`` of the current gain mode; temperatures within the cooler's range.
"""

from __future__ import annotations

import threading
import types
from collections.abc import Callable
from typing import Any

import numpy as np

DRV_SUCCESS = 20002
DRV_NO_NEW_DATA = 20024
DRV_TEMP_OFF = 20034
DRV_TEMP_NOT_REACHED = 20037
DRV_TEMP_STABILIZED = 20036
DRV_P1INVALID = 20066
DRV_P2INVALID = 20067
DRV_ACQUIRING = 20072
DRV_IDLE = 20073
DRV_NOT_INITIALIZED = 20075


def pattern(frame_index: int, shape: tuple[int, int]) -> np.ndarray:
    """The default frame: pixel (y, x) = 1000 * frame_index + 10 * y + x (mod 2**16)."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w]
    return ((1000 * frame_index + 10 * y + x) % 65536).astype(np.uint16)


class FakeAndor:
    """State shared by a fake module: cameras, the call log, frame production."""

    def __init__(self, n_cameras: int = 1, detector: tuple[int, int] = (1024, 1024), *,
                 library_missing: bool = False) -> None:
        self.n_cameras = n_cameras
        self.detector = detector
        self.library_missing = library_missing
        self.log: list[tuple[Any, ...]] = []
        self.initialized = False
        self.acquiring = False
        self.settings: dict[str, Any] = {}
        self.temperature = 20
        self.frames: list[np.ndarray] = []
        self.sinks: list[Callable[[np.ndarray], None]] = []
        self.frame_factory: Callable[[int, tuple[int, int]], np.ndarray] = pattern
        self.shut_down = False
        self.on_start: list[Callable[[], None]] = []  # called when acquisition starts (e.g. to check a grabber)
        self._cv = threading.Condition()
        self._waited = 0

    @property
    def shape(self) -> tuple[int, int]:
        hbin, vbin, hs, he, vs, ve = self.settings["SetImage"]
        return (ve - vs + 1) // vbin, (he - hs + 1) // hbin

    def produce(self) -> np.ndarray:
        """One exposure ends: make a frame, count it, and send it over Camera Link if that is on."""
        frame = self.frame_factory(len(self.frames) + 1, self.shape)
        with self._cv:
            self.frames.append(frame)
            self._cv.notify_all()
        if self.settings.get("SetCameraLinkMode") == 1:
            for sink in self.sinks:
                sink(frame)
        return frame

    def external_trigger(self) -> bool:
        """An edge on the camera's external trigger input (the AWG's camera line)."""
        if self.acquiring and self.settings.get("SetTriggerMode") == 1:
            self.produce()
            return True
        return False


def make_fake_andor(n_cameras: int = 1, detector: tuple[int, int] = (1024, 1024), *,
                    library_missing: bool = False) -> types.ModuleType:
    """A module that can stand in for ``pyAndorSDK2``; its ``fake`` attribute is the shared ``FakeAndor``."""
    fake = FakeAndor(n_cameras, detector, library_missing=library_missing)
    mod = types.ModuleType("pyAndorSDK2")
    mod.fake = fake  # type: ignore[attr-defined]

    class atmcd:  # noqa: N801 - the vendor's name
        """The subset of ``pyAndorSDK2.atmcd`` the adapter uses."""

        def __init__(self, userPath: str | None = None) -> None:  # noqa: N803
            fake.log.append(("atmcd",))
            if fake.library_missing:
                raise OSError("libandor.so: cannot open shared object file: No such file or directory")

        def __getattr__(self, name: str) -> Callable[..., Any]:
            impl = _IMPL.get(name)
            if impl is None:
                raise AttributeError(name)

            def call(*args: Any) -> Any:
                fake.log.append((name, *args))
                if name not in ("GetAvailableCameras", "GetCameraHandle", "SetCurrentCamera", "Initialize") \
                        and not fake.initialized:
                    return DRV_NOT_INITIALIZED if not name.startswith("Get") else (DRV_NOT_INITIALIZED, 0)
                return impl(fake, *args)

            return call

    mod.atmcd = atmcd  # type: ignore[attr-defined]
    return mod


_SETTINGS_REFUSED_WHILE_ACQUIRING = {
    "SetReadMode", "SetAcquisitionMode", "SetFrameTransferMode", "SetOutputAmplifier", "SetHSSpeed", "SetVSSpeed",
    "SetVSAmplitude", "SetPreAmpGain", "SetEMGainMode", "SetEMAdvanced", "SetBaselineClamp", "SetCameraLinkMode",
    "SetIsolatedCropModeEx", "SetImage", "SetExposureTime", "SetTriggerMode", "SetKineticCycleTime",
    "PrepareAcquisition",
}


def _setter(name: str, check: Callable[[FakeAndor, tuple[Any, ...]], int] | None = None) -> Callable[..., int]:
    def impl(fake: FakeAndor, *args: Any) -> int:
        if name in _SETTINGS_REFUSED_WHILE_ACQUIRING and fake.acquiring:
            return DRV_ACQUIRING
        if check is not None:
            ret = check(fake, args)
            if ret != DRV_SUCCESS:
                return ret
        fake.settings[name] = args if len(args) != 1 else args[0]
        return DRV_SUCCESS

    return impl


def _check_image(fake: FakeAndor, args: tuple[Any, ...]) -> int:
    hbin, vbin, hs, he, vs, ve = args
    xpix, ypix = fake.detector
    if not (1 <= hs <= he <= xpix) or not (1 <= vs <= ve <= ypix):
        return DRV_P1INVALID + 2
    if (he - hs + 1) % hbin or (ve - vs + 1) % vbin:
        return DRV_P1INVALID
    return DRV_SUCCESS


def _em_range(fake: FakeAndor) -> tuple[int, int]:
    mode = fake.settings.get("SetEMGainMode", 0)
    return {0: (0, 255), 1: (0, 4095), 2: (0, 4095), 3: (0, 1000)}[mode]


def _check_gain(fake: FakeAndor, args: tuple[Any, ...]) -> int:
    lo, hi = _em_range(fake)
    if not lo <= args[0] <= hi or (args[0] > 300 and not fake.settings.get("SetEMAdvanced")):
        return DRV_P1INVALID
    return DRV_SUCCESS


def _initialize(fake: FakeAndor, path: str) -> int:
    fake.initialized = True
    return DRV_SUCCESS


def _start(fake: FakeAndor) -> int:
    if fake.acquiring:
        return DRV_ACQUIRING
    if "SetImage" not in fake.settings:
        return DRV_P1INVALID
    fake.acquiring = True
    for hook in fake.on_start:
        hook()
    return DRV_SUCCESS


def _abort(fake: FakeAndor) -> int:
    if not fake.acquiring:
        return DRV_IDLE
    fake.acquiring = False
    return DRV_SUCCESS


def _software_trigger(fake: FakeAndor) -> int:
    if not fake.acquiring or fake.settings.get("SetTriggerMode") != 10:
        return DRV_P1INVALID
    fake.produce()
    return DRV_SUCCESS


def _wait(fake: FakeAndor, timeout_ms: int) -> int:
    with fake._cv:
        if len(fake.frames) > fake._waited or fake._cv.wait_for(lambda: len(fake.frames) > fake._waited,
                                                              timeout_ms / 1000):
            fake._waited = len(fake.frames)
            return DRV_SUCCESS
    return DRV_NO_NEW_DATA


def _most_recent(fake: FakeAndor, size: int) -> tuple[int, np.ndarray]:
    if not fake.frames:
        return DRV_NO_NEW_DATA, np.zeros(0, np.uint16)
    frame = fake.frames[-1]
    if size != frame.size:
        return DRV_P2INVALID, np.zeros(0, np.uint16)
    return DRV_SUCCESS, frame.reshape(-1).copy()


def _set_temperature(fake: FakeAndor, t: int) -> int:
    if not -120 <= t <= 30:
        return DRV_P1INVALID
    fake.settings["SetTemperature"] = t
    fake.temperature = t  # the fake cools instantly
    return DRV_SUCCESS


def _get_temperature(fake: FakeAndor) -> tuple[int, int]:
    if not fake.settings.get("CoolerON"):
        return DRV_TEMP_OFF, fake.temperature
    return DRV_TEMP_STABILIZED, fake.temperature


def _shut_down(fake: FakeAndor) -> int:
    fake.shut_down = True
    fake.initialized = False
    fake.acquiring = False
    return DRV_SUCCESS


_IMPL: dict[str, Callable[..., Any]] = {
    "GetAvailableCameras": lambda f: (DRV_SUCCESS, f.n_cameras),
    "GetCameraHandle": lambda f, i: (DRV_SUCCESS, 100 + i) if i < f.n_cameras else (DRV_P1INVALID, 0),
    "SetCurrentCamera": lambda f, h: DRV_SUCCESS,
    "Initialize": _initialize,
    "GetDetector": lambda f: (DRV_SUCCESS, *f.detector),
    "GetCameraSerialNumber": lambda f: (DRV_SUCCESS, 4242),
    "SetTemperature": _set_temperature,
    "CoolerON": lambda f: f.settings.__setitem__("CoolerON", True) or DRV_SUCCESS,
    "CoolerOFF": lambda f: f.settings.__setitem__("CoolerON", False) or DRV_SUCCESS,
    "SetCoolerMode": _setter("SetCoolerMode"),
    "GetTemperature": _get_temperature,
    "AbortAcquisition": _abort,
    "SetReadMode": _setter("SetReadMode"),
    "SetAcquisitionMode": _setter("SetAcquisitionMode"),
    "SetFrameTransferMode": _setter("SetFrameTransferMode"),
    "SetOutputAmplifier": _setter("SetOutputAmplifier"),
    "SetHSSpeed": _setter("SetHSSpeed"),
    "GetFastestRecommendedVSSpeed": lambda f: (DRV_SUCCESS, 3, 4.33),
    "SetVSSpeed": _setter("SetVSSpeed", lambda f, a: DRV_SUCCESS if 0 <= a[0] < 4 else DRV_P1INVALID),
    "SetVSAmplitude": _setter("SetVSAmplitude"),
    "SetPreAmpGain": _setter("SetPreAmpGain"),
    "SetEMGainMode": _setter("SetEMGainMode"),
    "GetEMGainRange": lambda f: (DRV_SUCCESS, *_em_range(f)),
    "SetEMAdvanced": _setter("SetEMAdvanced"),
    "SetEMCCDGain": _setter("SetEMCCDGain", _check_gain),
    "SetBaselineClamp": _setter("SetBaselineClamp"),
    "SetCameraLinkMode": _setter("SetCameraLinkMode"),
    "SetIsolatedCropModeEx": _setter("SetIsolatedCropModeEx"),
    "SetImage": _setter("SetImage", _check_image),
    "SetExposureTime": _setter("SetExposureTime"),
    "SetTriggerMode": _setter("SetTriggerMode", lambda f, a: DRV_SUCCESS if a[0] in (0, 1, 10) else DRV_P1INVALID),
    "SetShutter": _setter("SetShutter"),
    "SetKineticCycleTime": _setter("SetKineticCycleTime"),
    "GetAcquisitionTimings": lambda f: (DRV_SUCCESS, f.settings.get("SetExposureTime", 0.0) + 1e-5, 0.0, 0.0),
    "GetReadOutTime": lambda f: (DRV_SUCCESS, 0.0045),
    "PrepareAcquisition": _setter("PrepareAcquisition"),
    "StartAcquisition": _start,
    "SendSoftwareTrigger": _software_trigger,
    "GetTotalNumberImagesAcquired": lambda f: (DRV_SUCCESS, len(f.frames)),
    "WaitForAcquisitionTimeOut": _wait,
    "GetMostRecentImage16": _most_recent,
    "ShutDown": _shut_down,
}
