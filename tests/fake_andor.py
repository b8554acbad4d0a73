"""A fake ``pyAndorSDK2`` for testing ``drivers/andor.py`` without a camera or Andor's SDK.

Every call is checked against the real wrapper's signature (``SIGNATURES``: the parameters of
``pyAndorSDK2.atmcd``'s methods and the ctypes type each one is converted to), so a wrong argument count or
type raises ``TypeError`` as the wrapper's ``c_int(...)`` / ``c_float(...)`` / ``str.encode`` would. Calls
return what the real wrapper returns (a status, or ``(status, values...)``; ``DRV_SUCCESS = 20002``;
``GetMostRecentImage16`` an int16 array, since the wrapper allocates ``c_short * size``;
``GetCapabilities`` an ``AndorCapabilities`` structure) and are all recorded in ``fake.log``. The model keeps
the rules the adapter must respect:
- a setting the camera lacks (``GetCapabilities``) is refused: ``SetEMAdvanced`` with
  ``DRV_NOT_AVAILABLE``, ``SetCameraLinkMode`` and isolated crop mode with ``DRV_NOT_SUPPORTED``;
- the EM gain range depends on the gain mode and on ``SetEMAdvanced`` (above x300 needs it);
- nothing works before ``Initialize``; settings are refused with ``DRV_ACQUIRING`` while acquiring;
- ``SetImage`` takes 1-based inclusive sensor coordinates whose spans divide by the binning and fit the
  detector;
- in run-till-abort mode each trigger makes one frame (software trigger in mode 10, ``external_trigger()``
  in mode 1); frames go to Camera Link sinks (a fake grabber) when Camera Link mode is on, and are counted
  and kept for ``GetMostRecentImage16`` either way;
- temperatures within the cooler's range.
"""

from __future__ import annotations

import ctypes
import inspect
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
DRV_NOT_SUPPORTED = 20991
DRV_NOT_AVAILABLE = 20992

# Capability bits (atmcd.h / pyAndorSDK2's capability codes).
AC_SETFUNCTION_EMCCDGAIN = 0x10
AC_SETFUNCTION_CROPMODE = 0x0400
AC_SETFUNCTION_EMADVANCED = 0x8000
AC_FEATURES_CAMERALINK = 0x8000000
AC_EMGAIN_8BIT, AC_EMGAIN_12BIT, AC_EMGAIN_LINEAR12, AC_EMGAIN_REAL12 = 1, 2, 4, 8
IXON_SET_FUNCTIONS = AC_SETFUNCTION_EMCCDGAIN | AC_SETFUNCTION_CROPMODE | AC_SETFUNCTION_EMADVANCED
IXON_FEATURES = AC_FEATURES_CAMERALINK
IXON_EM_GAIN = AC_EMGAIN_8BIT | AC_EMGAIN_12BIT | AC_EMGAIN_LINEAR12 | AC_EMGAIN_REAL12


class AndorCapabilities(ctypes.Structure):
    """``AndorCapabilities`` as the wrapper declares it (every field a C unsigned long)."""

    _fields_ = [(name, ctypes.c_ulong) for name in (
        "ulSize", "ulAcqModes", "ulReadModes", "ulTriggerModes", "ulCameraType", "ulPixelMode", "ulSetFunctions",
        "ulGetFunctions", "ulFeatures", "ulPCICard", "ulEMGainCapability", "ulFTReadModes", "ulFeatures2")]


# The wrapper's methods: parameter names and the conversion each argument goes through ("int": c_int,
# "float": c_float, "str": str.encode). Methods without parameters take none.
SIGNATURES: dict[str, tuple[tuple[str, str], ...]] = {
    "GetAvailableCameras": (), "GetCameraHandle": (("cameraIndex", "int"),),
    "SetCurrentCamera": (("cameraHandle", "int"),), "Initialize": (("dir", "str"),), "GetDetector": (),
    "GetCameraSerialNumber": (), "GetCapabilities": (), "SetTemperature": (("temperature", "int"),),
    "GetTemperatureRange": (), "CoolerON": (), "CoolerOFF": (), "SetCoolerMode": (("mode", "int"),),
    "GetTemperature": (), "AbortAcquisition": (), "SetReadMode": (("mode", "int"),),
    "SetAcquisitionMode": (("mode", "int"),), "SetFrameTransferMode": (("mode", "int"),),
    "SetOutputAmplifier": (("typ", "int"),), "SetHSSpeed": (("typ", "int"), ("index", "int")),
    "GetFastestRecommendedVSSpeed": (), "SetVSSpeed": (("index", "int"),), "SetVSAmplitude": (("index", "int"),),
    "GetNumberVSSpeeds": (), "GetVSSpeed": (("index", "int"),),
    "GetHSSpeed": (("channel", "int"), ("typ", "int"), ("index", "int")),
    "SetPreAmpGain": (("index", "int"),), "SetEMGainMode": (("mode", "int"),), "GetEMGainRange": (),
    "SetEMAdvanced": (("state", "int"),), "SetEMCCDGain": (("gain", "int"),), "GetEMCCDGain": (),
    "SetBaselineClamp": (("state", "int"),), "SetCameraLinkMode": (("mode", "int"),),
    "SetIsolatedCropModeEx": (("active", "int"), ("cropheight", "int"), ("cropwidth", "int"), ("vbin", "int"),
                              ("hbin", "int"), ("cropleft", "int"), ("cropbottom", "int")),
    "SetImage": (("hbin", "int"), ("vbin", "int"), ("hstart", "int"), ("hend", "int"), ("vstart", "int"),
                 ("vend", "int")),
    "SetExposureTime": (("time", "float"),), "SetTriggerMode": (("mode", "int"),),
    "SetShutter": (("typ", "int"), ("mode", "int"), ("closingtime", "int"), ("openingtime", "int")),
    "SetKineticCycleTime": (("time", "float"),), "GetAcquisitionTimings": (), "GetReadOutTime": (),
    "PrepareAcquisition": (), "StartAcquisition": (), "SendSoftwareTrigger": (), "GetStatus": (),
    "GetTotalNumberImagesAcquired": (), "WaitForAcquisitionTimeOut": (("iTimeOutMs", "int"),),
    "GetMostRecentImage16": (("size", "int"),), "ShutDown": (),
}
#: The iXon Ultra 888's vertical shift speeds (us, as 32-bit floats come back) and EM-amplifier readout rates
VS_SPEEDS_US = (0.6, 1.13, 2.2, 4.3299999)
HS_SPEEDS_MHZ = (30.0, 20.0, 10.0, 1.0)
_CONVERT: dict[str, Callable[[Any], Any]] = {"int": ctypes.c_int, "float": ctypes.c_float, "str": str.encode}


def check_signature(name: str, args: tuple[Any, ...], kwargs: dict[str, Any]) -> tuple[Any, ...]:
    """Bind the call as the wrapper's method would and convert each argument as it does; ``TypeError`` if
    the wrapper would raise it (wrong count, unknown keyword, a float where it builds a ``c_int``...)."""
    params = SIGNATURES[name]
    signature = inspect.Signature(
        [inspect.Parameter(p, inspect.Parameter.POSITIONAL_OR_KEYWORD) for p, _ in params])
    bound = signature.bind(*args, **kwargs)
    for pname, kind in params:
        value = bound.arguments[pname]
        if kind == "int" and isinstance(value, float):
            raise TypeError(f"{name}: {pname} = {value!r}: the wrapper builds c_int({pname}), which takes no float")
        _CONVERT[kind](value)
    return tuple(bound.args)


def pattern(frame_index: int, shape: tuple[int, int]) -> np.ndarray:
    """The default frame: pixel (y, x) = 1000 * frame_index + 10 * y + x (mod 2**16)."""
    h, w = shape
    y, x = np.mgrid[0:h, 0:w]
    return ((1000 * frame_index + 10 * y + x) % 65536).astype(np.uint16)


class FakeAndor:
    """State shared by a fake module: cameras, the call log, frame production."""

    def __init__(self, n_cameras: int = 1, detector: tuple[int, int] = (1024, 1024), *,
                 library_missing: bool = False, set_functions: int = IXON_SET_FUNCTIONS,
                 features: int = IXON_FEATURES, em_gain_capability: int = IXON_EM_GAIN) -> None:
        self.set_functions = set_functions
        self.features = features
        self.em_gain_capability = em_gain_capability
        self.initialize_dir: str | None = None
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


def make_fake_andor(n_cameras: int = 1, detector: tuple[int, int] = (1024, 1024), **kwargs: Any) -> types.ModuleType:
    """A module that can stand in for ``pyAndorSDK2``; its ``fake`` attribute is the shared ``FakeAndor``
    (``kwargs``: ``library_missing`` and the camera's capabilities, see ``FakeAndor``)."""
    fake = FakeAndor(n_cameras, detector, **kwargs)
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

            def call(*args: Any, **kwargs: Any) -> Any:
                args = check_signature(name, args, kwargs)
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
    """The range for the current gain mode; gains above x300 (real) or DAC 300 exist only in advanced mode."""
    mode = fake.settings.get("SetEMGainMode", 0)
    advanced = bool(fake.settings.get("SetEMAdvanced"))
    if mode == 0:
        return 0, 255
    if mode == 3:
        return 1, 1000 if advanced else 300
    return 0, 4095 if advanced else 300


def _check_gain(fake: FakeAndor, args: tuple[Any, ...]) -> int:
    lo, hi = _em_range(fake)
    return DRV_SUCCESS if lo <= args[0] <= hi else DRV_P1INVALID


def _check_gain_mode(fake: FakeAndor, args: tuple[Any, ...]) -> int:
    bit = {0: AC_EMGAIN_8BIT, 1: AC_EMGAIN_12BIT, 2: AC_EMGAIN_LINEAR12, 3: AC_EMGAIN_REAL12}.get(args[0], 0)
    return DRV_SUCCESS if fake.em_gain_capability & bit else DRV_P1INVALID


def _needs(flag: str, bit: int, refusal: int) -> Callable[[FakeAndor, tuple[Any, ...]], int]:
    """A check that refuses the call on a camera without the capability bit ``bit`` of ``flag``."""
    def check(fake: FakeAndor, args: tuple[Any, ...]) -> int:
        return DRV_SUCCESS if getattr(fake, flag) & bit else refusal

    return check


def _capabilities(fake: FakeAndor) -> tuple[int, AndorCapabilities]:
    caps = AndorCapabilities()
    caps.ulSize = ctypes.sizeof(caps)
    caps.ulSetFunctions = fake.set_functions
    caps.ulFeatures = fake.features
    caps.ulEMGainCapability = fake.em_gain_capability
    return DRV_SUCCESS, caps


def _initialize(fake: FakeAndor, path: str) -> int:
    fake.initialize_dir = path
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
    return DRV_SUCCESS, frame.reshape(-1).view(np.int16).copy()  # the wrapper's c_short buffer: int16


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
    "GetNumberVSSpeeds": lambda f: (DRV_SUCCESS, len(VS_SPEEDS_US)),
    "GetVSSpeed": lambda f, i: (DRV_SUCCESS, VS_SPEEDS_US[i]) if 0 <= i < len(VS_SPEEDS_US) else (DRV_P1INVALID, 0.0),
    "GetHSSpeed": lambda f, ch, typ, i: (DRV_SUCCESS, HS_SPEEDS_MHZ[i]) if 0 <= i < len(HS_SPEEDS_MHZ)
    else (DRV_P1INVALID, 0.0),
    "SetPreAmpGain": _setter("SetPreAmpGain"),
    "GetCapabilities": _capabilities,
    "GetTemperatureRange": lambda f: (DRV_SUCCESS, -120, 30),
    "GetStatus": lambda f: (DRV_SUCCESS, DRV_ACQUIRING if f.acquiring else DRV_IDLE),
    "GetEMCCDGain": lambda f: (DRV_SUCCESS, f.settings.get("SetEMCCDGain", 0)),
    "SetEMGainMode": _setter("SetEMGainMode", _check_gain_mode),
    "GetEMGainRange": lambda f: (DRV_SUCCESS, *_em_range(f)),
    "SetEMAdvanced": _setter("SetEMAdvanced", _needs("set_functions", AC_SETFUNCTION_EMADVANCED, DRV_NOT_AVAILABLE)),
    "SetEMCCDGain": _setter("SetEMCCDGain", _check_gain),
    "SetBaselineClamp": _setter("SetBaselineClamp"),
    "SetCameraLinkMode": _setter("SetCameraLinkMode", _needs("features", AC_FEATURES_CAMERALINK, DRV_NOT_SUPPORTED)),
    "SetIsolatedCropModeEx": _setter("SetIsolatedCropModeEx",
                                     _needs("set_functions", AC_SETFUNCTION_CROPMODE, DRV_NOT_SUPPORTED)),
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
