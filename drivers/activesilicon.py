"""Frames from the Andor iXon over Camera Link, through an Active Silicon FireBird grabber and its C library.

There is no Python package for Active Silicon's "PHX" API, so this is a thin ``ctypes`` adapter, loaded only
when the frame source opens. It implements ``drivers.andor.FrameSource``; the camera's settings (exposure,
gain, ROI, trigger) are made through the Andor SDK by ``drivers/andor.py``, which hands frame delivery here.

The calls and their order (Active Silicon's ``phx_api.h``; the reference system uses the same sequence):
``PHX_Create`` (with the library's default error handler), ``PHX_ParameterSet`` of ``PHX_CONFIG_FILE`` (the
camera's .pcf file), ``PHX_BOARD_NUMBER``, ``PHX_CHANNEL_NUMBER``, ``PHX_CONFIG_MODE``, then ``PHX_Open``;
per configuration the camera's active region and the ROI (``PHX_CAM_ACTIVE_X/YLENGTH``,
``PHX_ROI_SRC_X/YOFFSET``, ``PHX_ROI_X/YLENGTH``) and the destination buffer's layout: 16-bit pixels
(``PHX_DST_FORMAT_Y16``), one ROI line per buffer line (``PHX_BUF_DST_XLENGTH`` in bytes,
``PHX_BUF_DST_YLENGTH`` in lines, read back because the board may round the line length up) and the DMA
timeout (``PHX_TIMEOUT_DMA``). Without them the buffer keeps the camera file's layout, typically the full
sensor width, and a ROI copied as contiguous lines comes out sheared. Per frame ``PHX_StreamRead(PHX_START)`` (armed
before the exposure is triggered), ``PHX_CHECK_AND_WAIT`` (blocks until the frame event), ``PHX_BUFFER_GET``, a copy
out of the grabber's buffer, ``PHX_STOP`` and ``PHX_BUFFER_RELEASE``, then ``PHX_START`` again to arm for the next
frame. ``PHX_CHECK_AND_WAIT`` has no timeout of its own: a watchdog thread aborts the stream (``PHX_ABORT``) at the
deadline, which makes the wait return; the next read re-arms the stream.

Parameter identifiers are computed from the header's scheme (function group in the top bits, parameter number
``<< 8``), so no header is needed at run time; the functions get the header's prototypes (``PROTOTYPES``).
This adapter has been exercised only against the fake in ``tests/fake_activesilicon.py``; check it on the lab
PC with ``llrs devices`` and a test shot.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import os
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from engine.config import DevicesConfig
from engine.devices import DeviceError

__all__ = ["ActiveSiliconFrameSource", "PHX", "PROTOTYPES", "StImageBuff", "library_candidates", "load_library"]

ActiveSiliconSettings = DevicesConfig.ActiveSiliconSettings

_FNTYPE_PHX_API = 0xC0000000
_CAMERACONFIG_LOAD = _FNTYPE_PHX_API | 0x00010000
_SETANDGET = _FNTYPE_PHX_API | 0x00020000
_ACQUIRE = _FNTYPE_PHX_API | 0x00030000
_PRE_OPEN = _FNTYPE_PHX_API | 0x00070000


class PHX:
    """The ``phx_api.h`` values this adapter uses (as unsigned 32-bit numbers)."""

    OK = 0
    WARNING_TIMEOUT = 0x8000
    ENABLE = 1
    DISABLE = 2
    # parameters (PHX_ParameterSet / PHX_ParameterGet)
    ACQ_CONTINUOUS = _SETANDGET | (1 << 8)
    ACQ_NUM_IMAGES = _SETANDGET | (2 << 8)
    CAM_ACTIVE_XLENGTH = _SETANDGET | (10 << 8)
    CAM_ACTIVE_YLENGTH = _SETANDGET | (11 << 8)
    CAM_ACTIVE_XOFFSET = _SETANDGET | (12 << 8)
    CAM_ACTIVE_YOFFSET = _SETANDGET | (13 << 8)
    DST_FORMAT = _SETANDGET | (38 << 8)  # PHX_BUS_FORMAT
    TIMEOUT_DMA = _SETANDGET | (76 << 8)  # milliseconds
    ROI_DST_XOFFSET = _SETANDGET | (87 << 8)
    ROI_DST_YOFFSET = _SETANDGET | (88 << 8)
    ROI_SRC_XOFFSET = _SETANDGET | (89 << 8)
    ROI_SRC_YOFFSET = _SETANDGET | (90 << 8)
    ROI_XLENGTH = _SETANDGET | (91 << 8)
    ROI_YLENGTH = _SETANDGET | (92 << 8)
    BUF_DST_XLENGTH = _SETANDGET | (93 << 8)  # bytes per destination line
    BUF_DST_YLENGTH = _SETANDGET | (94 << 8)  # destination lines
    ACQ_BLOCKING = _SETANDGET | (147 << 8)
    CONFIG_FILE = _PRE_OPEN | (1 << 8)
    BOARD_NUMBER = _PRE_OPEN | (3 << 8)
    CHANNEL_NUMBER = _PRE_OPEN | (4 << 8)
    CONFIG_MODE = _PRE_OPEN | (5 << 8)
    # parameter values
    CONFIG_NORMAL = _CAMERACONFIG_LOAD | 0x0000
    DST_FORMAT_Y16 = DST_FORMAT + 2  # PHX_BUS_FORMAT_MONO16: 16-bit monochrome pixels

    @staticmethod
    def board(n: int) -> int:
        """``PHX_BOARD_NUMBER_n`` (1 = the first board in scan order)."""
        return _CAMERACONFIG_LOAD | n

    @staticmethod
    def channel(n: int) -> int:
        """``PHX_CHANNEL_NUMBER_n`` (1 = channel A)."""
        return _CAMERACONFIG_LOAD | (0x10 * n)

    # PHX_StreamRead operations
    START = _ACQUIRE | (1 << 8)
    CHECK_AND_WAIT = _ACQUIRE | (2 << 8)
    STOP = _ACQUIRE | (4 << 8)
    ABORT = _ACQUIRE | (5 << 8)
    BUFFER_GET = _ACQUIRE | (6 << 8)
    BUFFER_RELEASE = _ACQUIRE | (7 << 8)


class StImageBuff(ctypes.Structure):
    """``stImageBuff``: where the grabber put a frame."""

    _fields_ = [("pvAddress", ctypes.c_void_p), ("pvContext", ctypes.c_void_p)]


# phx_api.h's prototypes: (argument types), every function returns etStat. tHandle is passed as a 64-bit
# integer: the library's handle fits it by value and through a zeroed 64-bit variable on x86-64.
PROTOTYPES: dict[str, list[Any]] = {
    "PHX_Create": [ctypes.POINTER(ctypes.c_uint64), ctypes.c_void_p],
    "PHX_Open": [ctypes.c_uint64],
    "PHX_Close": [ctypes.POINTER(ctypes.c_uint64)],
    "PHX_Destroy": [ctypes.POINTER(ctypes.c_uint64)],
    "PHX_ParameterSet": [ctypes.c_uint64, ctypes.c_uint32, ctypes.c_void_p],
    "PHX_ParameterGet": [ctypes.c_uint64, ctypes.c_uint32, ctypes.c_void_p],
    "PHX_StreamRead": [ctypes.c_uint64, ctypes.c_uint32, ctypes.c_void_p],
}
#: PHX_TIMEOUT_DMA: a frame of at most 1024 x 1024 x 2 B crosses PCIe in milliseconds, so a second only
#: catches a transfer that is stuck (the frame timeout itself is camera.timeout_s, see read()).
DMA_TIMEOUT_MS = 1000


INSTALL_SDK = (
    "install Active Silicon's ActiveSDK for the FireBird (default location /usr/local/activesilicon) or set "
    "devices.activesilicon.library to the PHX library's path, then check with 'llrs devices'"
)


def library_candidates(path: str | None = None) -> list[str]:
    """Where to look for the PHX library: the configured path, ``LLRS_PHX_LIBRARY``, then the usual places."""
    if path:
        return [path]
    out: list[str] = []
    env = os.environ.get("LLRS_PHX_LIBRARY")
    if env:
        out.append(env)
    out += [
        "/usr/local/activesilicon/lib64/libphxapi-x86_64.so",
        "/usr/local/activesilicon/lib/libphxapi-x86_64.so",
        "libphxapi-x86_64.so",
        "libphxapi.so",
    ]
    found = ctypes.util.find_library("phxapi")
    if found:
        out.append(found)
    return out


def load_library(path: str | None = None) -> Any:
    """Load the PHX library (``ctypes.CDLL``); ``DeviceError`` naming every place tried when it is not there."""
    tried = library_candidates(path)
    errors = []
    for name in tried:
        try:
            lib = ctypes.CDLL(name)
        except OSError as err:
            errors.append(f"{name}: {err}")
            continue
        for fn, argtypes in PROTOTYPES.items():
            getattr(lib, fn).restype = ctypes.c_int
            getattr(lib, fn).argtypes = argtypes
        return lib
    raise DeviceError(
        f"Active Silicon: the PHX library was not found (tried {', '.join(tried)}); {INSTALL_SDK}"
        + (f" [{errors[0]}]" if path and errors else "")
    )


class _Watchdog:
    """One thread that calls ``on_expire`` when an armed deadline passes (it is reused for every frame, so a
    read allocates nothing for its timeout)."""

    def __init__(self, on_expire: Callable[[], None]) -> None:
        self._cv = threading.Condition()
        self._deadline: float | None = None
        self._fired = False
        self._closed = False
        self._on_expire = on_expire
        self._thread = threading.Thread(target=self._run, name="llrs-phx-watchdog", daemon=True)
        self._thread.start()

    def arm(self, timeout_s: float) -> None:
        with self._cv:
            self._deadline = time.monotonic() + timeout_s
            self._fired = False
            self._cv.notify()

    def disarm(self) -> bool:
        """Cancel the deadline; True if it had already fired."""
        with self._cv:
            self._deadline = None
            fired, self._fired = self._fired, False
            self._cv.notify()
            return fired

    def close(self) -> None:
        with self._cv:
            self._closed = True
            self._cv.notify()
        self._thread.join(timeout=5)

    def _run(self) -> None:
        with self._cv:
            while not self._closed:
                if self._deadline is None:
                    self._cv.wait()
                    continue
                remaining = self._deadline - time.monotonic()
                if remaining > 0:
                    self._cv.wait(remaining)
                    continue
                self._deadline = None
                self._fired = True
                try:
                    self._on_expire()
                except Exception:  # noqa: BLE001 - the reader reports the timeout; nothing to add here
                    pass


class ActiveSiliconFrameSource:
    """``FrameSource`` on a FireBird Camera Link grabber (see the module docstring for the call sequence).

    ``library`` replaces loading the C library (tests pass a fake that records every call).
    """

    def __init__(self, settings: ActiveSiliconSettings | None = None, *, library: Any = None) -> None:
        self.settings = settings if settings is not None else ActiveSiliconSettings()
        self._lib = library
        self._handle = ctypes.c_uint64(0)
        self._open = False
        self._streaming = False
        self._shape = (0, 0)
        self._nbytes = 0
        self._line_bytes = 0  # bytes of one ROI line
        self._stride = 0  # bytes of one destination buffer line (the board may round it up)
        self._buf = StImageBuff()
        self._buf_ref = ctypes.byref(self._buf)
        self._event = ctypes.c_uint32(0)
        self._event_ref = ctypes.byref(self._event)
        self._out: np.ndarray | None = None
        self._out_ptr = 0
        self._frames = 0
        self._watchdog: _Watchdog | None = None
        self._acq = {name: ctypes.c_uint32(getattr(PHX, name)) for name in
                     ("START", "CHECK_AND_WAIT", "STOP", "ABORT", "BUFFER_GET", "BUFFER_RELEASE")}

    # --- life cycle ------------------------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        return self._open

    def open(self) -> None:
        """Create the handle, hand it the camera file, board and channel, and open the board."""
        if self._open:
            return
        s = self.settings
        if not s.config_file:
            raise DeviceError(
                "Active Silicon: devices.activesilicon.config_file (the iXon's .pcf camera file) is not set"
            )
        if not Path(s.config_file).is_file():
            raise DeviceError(
                f"Active Silicon: camera configuration file {s.config_file!r} does not exist "
                "(devices.activesilicon.config_file)"
            )
        lib = self._lib if self._lib is not None else load_library(s.library)
        self._lib = lib
        handler = getattr(lib, "PHX_ErrHandlerDefault", None)
        self._check(lib.PHX_Create(ctypes.byref(self._handle), handler), "PHX_Create")
        try:
            path = ctypes.c_char_p(os.fsencode(s.config_file))
            self._set(PHX.CONFIG_FILE, ctypes.byref(path), "PHX_CONFIG_FILE")
            self._set_u32(PHX.BOARD_NUMBER, PHX.board(s.board))
            self._set_u32(PHX.CHANNEL_NUMBER, PHX.channel(s.channel))
            self._set_u32(PHX.CONFIG_MODE, PHX.CONFIG_NORMAL)
            self._check(lib.PHX_Open(self._handle), "PHX_Open", hint=(
                f"check board {s.board} / channel {s.channel} (devices.activesilicon.board, .channel), the cable "
                "and the camera file"))
        except DeviceError:
            lib.PHX_Destroy(ctypes.byref(self._handle))
            raise
        self._open = True
        self._watchdog = _Watchdog(self._abort_from_watchdog)

    def close(self) -> None:
        """Stop streaming and release the board."""
        if not self._open:
            return
        lib = self._lib
        try:
            self.stop()
        finally:
            self._open = False
            if self._watchdog is not None:
                self._watchdog.close()
                self._watchdog = None
            lib.PHX_Close(ctypes.byref(self._handle))
            lib.PHX_Destroy(ctypes.byref(self._handle))

    # --- FrameSource -----------------------------------------------------------------------------------

    @property
    def frame_shape(self) -> tuple[int, int]:
        return self._shape

    def configure(self, width: int, height: int) -> None:
        """Frames of ``height x width`` 16-bit pixels (the camera sends exactly its ROI, binned)."""
        self.open()
        self.stop()
        self._set_u32(PHX.CAM_ACTIVE_XOFFSET, 0)
        self._set_u32(PHX.CAM_ACTIVE_YOFFSET, 0)
        self._set_u32(PHX.CAM_ACTIVE_XLENGTH, width)
        self._set_u32(PHX.CAM_ACTIVE_YLENGTH, height)
        self._set_u32(PHX.ROI_SRC_XOFFSET, 0)
        self._set_u32(PHX.ROI_SRC_YOFFSET, 0)
        self._set_u32(PHX.ROI_XLENGTH, width)
        self._set_u32(PHX.ROI_YLENGTH, height)
        self._set_u32(PHX.ROI_DST_XOFFSET, 0)
        self._set_u32(PHX.ROI_DST_YOFFSET, 0)
        self._set_u32(PHX.DST_FORMAT, PHX.DST_FORMAT_Y16)
        self._set_u32(PHX.BUF_DST_XLENGTH, width * 2)
        self._set_u32(PHX.BUF_DST_YLENGTH, height)
        self._set_u32(PHX.TIMEOUT_DMA, DMA_TIMEOUT_MS)
        self._set_u32(PHX.ACQ_BLOCKING, PHX.ENABLE)
        self._set_u32(PHX.ACQ_CONTINUOUS, PHX.ENABLE)
        stride = self._get_u32(PHX.BUF_DST_XLENGTH, "PHX_BUF_DST_XLENGTH")
        if stride < width * 2:
            raise DeviceError(
                f"Active Silicon: the grabber's buffer line is {stride} B, shorter than a {width}-pixel ROI line "
                f"({width * 2} B); check the camera file (devices.activesilicon.config_file)"
            )
        self._shape = (height, width)
        self._line_bytes = width * 2
        self._stride = stride
        self._nbytes = height * width * 2
        self._out = None

    def start(self) -> None:
        """Arm the grabber for the next frame (must happen before the exposure is triggered)."""
        if not self._open:
            raise DeviceError("Active Silicon: start() before open()/configure()")
        if not self._streaming:
            self._stream("START")
            self._streaming = True

    def read(self, out: np.ndarray, *, timeout_s: float) -> int:
        """Wait for the next frame, copy it into ``out`` (``uint16[h, w]``), re-arm; return the frame count."""
        if out is not self._out:
            if out.shape != self._shape or out.dtype != np.uint16 or not out.flags.c_contiguous:
                raise DeviceError(
                    f"Active Silicon: out must be a C-contiguous uint16{self._shape} array, got {out.dtype}{out.shape}"
                )
            self._out, self._out_ptr = out, out.ctypes.data
        self.start()
        wd = self._watchdog
        assert wd is not None
        wd.arm(timeout_s)
        ret = self._lib.PHX_StreamRead(self._handle, self._acq["CHECK_AND_WAIT"], self._event_ref)
        if wd.disarm() or ret == PHX.WARNING_TIMEOUT:
            self._streaming = False  # aborted; the next read starts it again
            raise DeviceError(
                f"Active Silicon: no frame within {timeout_s:g} s; check that the camera is triggered (the AWG's "
                "camera line), that it is in Camera Link mode, and the Camera Link cable"
            )
        self._check(ret, "PHX_StreamRead(CHECK_AND_WAIT)")
        self._stream("BUFFER_GET", self._buf_ref)
        if not self._buf.pvAddress:
            raise DeviceError("Active Silicon: the grabber returned an empty buffer")
        self._copy_out(self._buf.pvAddress)
        self._stream("STOP")
        self._stream("BUFFER_RELEASE", self._buf_ref)
        self._streaming = False
        self.start()
        self._frames += 1
        return self._frames

    def stop(self) -> None:
        """Abort any acquisition in progress."""
        if self._open and self._streaming:
            self._streaming = False
            self._stream("ABORT")

    # --- internals -------------------------------------------------------------------------------------

    def _copy_out(self, address: int) -> None:
        """The ROI from the grabber's buffer into ``out``: one copy when the lines are packed, else line by
        line, skipping the padding the board adds at the end of each line."""
        if self._stride == self._line_bytes:
            ctypes.memmove(self._out_ptr, address, self._nbytes)
            return
        for row in range(self._shape[0]):
            ctypes.memmove(self._out_ptr + row * self._line_bytes, address + row * self._stride, self._line_bytes)

    def _abort_from_watchdog(self) -> None:
        self._lib.PHX_StreamRead(self._handle, self._acq["ABORT"], None)

    def _stream(self, op: str, arg: Any = None) -> None:
        ret = self._lib.PHX_StreamRead(self._handle, self._acq[op], arg)
        if ret != PHX.OK:  # the message is built only on failure: nothing allocated per frame
            self._check(ret, f"PHX_StreamRead({op})")

    def _set(self, param: int, ref: Any, name: str) -> None:
        self._check(self._lib.PHX_ParameterSet(self._handle, ctypes.c_uint32(param), ref), f"PHX_ParameterSet({name})")

    def _set_u32(self, param: int, value: int) -> None:
        v = ctypes.c_uint32(value)
        self._check(self._lib.PHX_ParameterSet(self._handle, ctypes.c_uint32(param), ctypes.byref(v)),
                    f"PHX_ParameterSet({param:#x} = {value:#x})")

    def _get_u32(self, param: int, name: str) -> int:
        v = ctypes.c_uint32(0)
        self._check(self._lib.PHX_ParameterGet(self._handle, ctypes.c_uint32(param), ctypes.byref(v)),
                    f"PHX_ParameterGet({name})")
        return int(v.value)

    @staticmethod
    def _check(ret: int, what: str, *, hint: str = "") -> None:
        if ret != PHX.OK:
            raise DeviceError(f"Active Silicon: {what} failed with status {ret:#x}" + (f"; {hint}" if hint else ""))
