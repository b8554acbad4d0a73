"""A fake Active Silicon PHX library for testing ``drivers/activesilicon.py`` without a grabber.

It stands in for the ``ctypes.CDLL`` at the C boundary: every ``PHX_*`` function is a real C function
pointer (``ctypes.CFUNCTYPE``) with the prototype ``phx_api.h`` gives it (``PROTOTYPES``), so the adapter's
arguments go through ctypes' conversions as they would into the library, and the model reads and writes
memory through the pointers it receives (the ``ui32`` behind a ``void*`` parameter value, the ``char*``
behind ``PHX_CONFIG_FILE``, the ``stImageBuff`` of ``PHX_BUFFER_GET``). Its constants (``H``) are its own
table, copied from the header (Active Silicon's ``phx_api.h``; the same numbers as its C# port
``phx_api.cs``), never imported from the adapter: a wrong parameter number in the adapter is refused
(``PHX_ERROR_BAD_PARAM``) and recorded in ``violations``.

The model: parameters before ``PHX_Open`` are the pre-open ones (the camera file must exist), the rest
need an open board; the camera file sets a destination buffer wider than the iXon's ROI (``camera_file``:
a 1024-pixel line, 16-bit), so an adapter that does not set ``PHX_BUF_DST_XLENGTH`` / ``_YLENGTH`` /
``PHX_DST_FORMAT`` reads a sheared image, as it would on the lab PC; the board may round the line length up
(``dst_alignment``, read back with ``PHX_ParameterGet``); a frame is only captured while the stream is
started; ``PHX_CHECK_AND_WAIT`` blocks until a frame arrives or the stream is aborted (from another thread);
``PHX_BUFFER_GET`` hands out the address of the buffer holding the frame; buffers must be released. Frames
arrive through ``deliver(frame)`` (a fake camera's Camera Link output calls it). Every call is in ``log``.
"""

from __future__ import annotations

import ctypes
import os
import threading
import types
from collections.abc import Callable
from typing import Any

import numpy as np

# --- phx_api.h ---------------------------------------------------------------------------------------------
H = types.SimpleNamespace(
    # etStat
    PHX_OK=0, PHX_ERROR_BAD_HANDLE=1, PHX_ERROR_BAD_PARAM=2, PHX_ERROR_BAD_PARAM_VALUE=3,
    PHX_ERROR_OPEN_FAILED=5, PHX_ERROR_FILE_OPEN_FAILED=16, PHX_ERROR_INVALID_POINTER=23,
    PHX_WARNING_TIMEOUT=0x8000,
    # etParamValue
    PHX_ENABLE=1, PHX_DISABLE=2,
    PHX_BOARD1=0xC0010001, PHX_CHANNEL_A=0xC0010010, PHX_CHANNEL_B=0xC0010020, PHX_MODE_NORMAL=0xC0010000,
    PHX_DST_FORMAT_Y8=0xC0022601, PHX_DST_FORMAT_Y16=0xC0022602,  # PHX_BUS_FORMAT_MONO8 / _MONO16
    # etParam: PHX_SETANDGET | n << 8
    PHX_ACQ_CONTINUOUS=0xC0020100, PHX_ACQ_NUM_BUFFERS=0xC0020200,
    PHX_CAM_ACTIVE_XLENGTH=0xC0020A00, PHX_CAM_ACTIVE_YLENGTH=0xC0020B00,
    PHX_CAM_ACTIVE_XOFFSET=0xC0020C00, PHX_CAM_ACTIVE_YOFFSET=0xC0020D00,
    PHX_DST_FORMAT=0xC0022600,  # = PHX_BUS_FORMAT
    PHX_TIMEOUT_DMA=0xC0024C00,
    PHX_ROI_DST_XOFFSET=0xC0025700, PHX_ROI_DST_YOFFSET=0xC0025800,
    PHX_ROI_SRC_XOFFSET=0xC0025900, PHX_ROI_SRC_YOFFSET=0xC0025A00,
    PHX_ROI_XLENGTH=0xC0025B00, PHX_ROI_YLENGTH=0xC0025C00,
    PHX_BUF_DST_XLENGTH=0xC0025D00, PHX_BUF_DST_YLENGTH=0xC0025E00,
    PHX_ACQ_BLOCKING=0xC0029300,
    # etParam: PHX_PRE_OPEN | n << 8
    PHX_CONFIG_FILE=0xC0070100, PHX_BOARD_NUMBER=0xC0070300, PHX_CHANNEL_NUMBER=0xC0070400,
    PHX_CONFIG_MODE=0xC0070500,
    # etAcq: PHX_ACQUIRE | n << 8
    PHX_START=0xC0030100, PHX_CHECK_AND_WAIT=0xC0030200, PHX_STOP=0xC0030400, PHX_ABORT=0xC0030500,
    PHX_BUFFER_GET=0xC0030600, PHX_BUFFER_RELEASE=0xC0030700,
)
_PRE_OPEN = {H.PHX_CONFIG_FILE, H.PHX_BOARD_NUMBER, H.PHX_CHANNEL_NUMBER, H.PHX_CONFIG_MODE}
_PARAMS = {v: k for k, v in vars(H).items() if k.startswith("PHX_") and v >= 0xC0020000 and (v & 0xFF) == 0
           and (v & 0xFFFF0000) in (0xC0020000, 0xC0070000)}
_ACQ = {v: k[4:] for k, v in vars(H).items() if (v & 0xFFFF0000) == 0xC0030000}


class StImageBuff(ctypes.Structure):
    """``stImageBuff`` from the header."""

    _fields_ = [("pvAddress", ctypes.c_void_p), ("pvContext", ctypes.c_void_p)]


# tHandle is a 64-bit integer here; the C# port declares it uint: by value and through a zeroed 64-bit
# variable both work on x86-64, which is why the adapter may use c_uint64.
_HANDLE = ctypes.c_uint64
PROTOTYPES: dict[str, Any] = {
    "PHX_Create": ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(_HANDLE), ctypes.c_void_p),
    "PHX_Open": ctypes.CFUNCTYPE(ctypes.c_int, _HANDLE),
    "PHX_Close": ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(_HANDLE)),
    "PHX_Destroy": ctypes.CFUNCTYPE(ctypes.c_int, ctypes.POINTER(_HANDLE)),
    "PHX_ParameterSet": ctypes.CFUNCTYPE(ctypes.c_int, _HANDLE, ctypes.c_uint32, ctypes.c_void_p),
    "PHX_ParameterGet": ctypes.CFUNCTYPE(ctypes.c_int, _HANDLE, ctypes.c_uint32, ctypes.c_void_p),
    "PHX_StreamRead": ctypes.CFUNCTYPE(ctypes.c_int, _HANDLE, ctypes.c_uint32, ctypes.c_void_p),
}
_HANDLE_VALUE = 7


class FakePhxLibrary:
    """One fake grabber (board 1, channel A unless told otherwise)."""

    def __init__(self, *, boards: int = 1, fail_open: bool = False, camera_file: tuple[int, int] = (1024, 1024),
                 dst_alignment: int = 1) -> None:
        self.boards = boards
        self.fail_open = fail_open
        self.camera_file = camera_file  # (width, height) of the destination buffer the camera file sets
        self.dst_alignment = dst_alignment  # the board rounds PHX_BUF_DST_XLENGTH up to this many bytes
        self.log: list[tuple[Any, ...]] = []
        self.params: dict[int, Any] = {
            H.PHX_DST_FORMAT: H.PHX_DST_FORMAT_Y16,
            H.PHX_BUF_DST_XLENGTH: camera_file[0] * 2,
            H.PHX_BUF_DST_YLENGTH: camera_file[1],
        }
        self.created = False
        self.opened = False
        self.streaming = False
        self.violations: list[str] = []
        self._cv = threading.Condition()
        self._queue: list[np.ndarray] = []
        self._aborted = False
        self._held: np.ndarray | None = None  # the buffer handed out by BUFFER_GET, until released
        self.frames_captured = 0
        self.frames_dropped = 0
        for name, prototype in PROTOTYPES.items():
            setattr(self, name, prototype(self._guarded(name, getattr(self, "_" + name))))

    def _guarded(self, name: str, impl: Callable[..., int]) -> Callable[..., int]:
        """An exception inside a ctypes callback would be printed and read as 0 (PHX_OK): record it as a
        violation and return an error instead."""
        def call(*args: Any) -> int:
            try:
                return impl(*args)
            except Exception as err:  # noqa: BLE001 - every failure becomes a recorded violation
                self.violations.append(f"{name}: {type(err).__name__}: {err}")
                return H.PHX_ERROR_INVALID_POINTER

        return call

    # --- the C functions (arguments as ctypes hands them over: ints and pointer objects) ------------------
    # (noqa N802: named as in the vendor's C library)

    def _PHX_Create(self, handle_ptr: Any, handler: int | None) -> int:  # noqa: N802
        self.log.append(("PHX_Create",))
        handle_ptr[0] = _HANDLE_VALUE
        self.created = True
        return H.PHX_OK

    def _PHX_ParameterSet(self, handle: int, param: int, pv: int | None) -> int:  # noqa: N802
        name = _PARAMS.get(param)
        if name is None:
            self.violations.append(f"PHX_ParameterSet: {param:#x} is not a parameter of phx_api.h")
            return H.PHX_ERROR_BAD_PARAM
        if not pv:
            return H.PHX_ERROR_INVALID_POINTER
        if param == H.PHX_CONFIG_FILE:
            value: Any = ctypes.c_char_p.from_address(pv).value
        else:
            value = ctypes.c_uint32.from_address(pv).value
        self.log.append(("PHX_ParameterSet", name[4:], value))
        if not self.created or handle != _HANDLE_VALUE:
            return H.PHX_ERROR_BAD_HANDLE
        if (param in _PRE_OPEN) == self.opened:
            self.violations.append(f"{name} set {'after' if self.opened else 'before'} PHX_Open")
            return H.PHX_ERROR_BAD_PARAM
        if param == H.PHX_BUF_DST_XLENGTH:
            value = -(-value // self.dst_alignment) * self.dst_alignment
        if param == H.PHX_DST_FORMAT and value not in (H.PHX_DST_FORMAT_Y8, H.PHX_DST_FORMAT_Y16):
            return H.PHX_ERROR_BAD_PARAM_VALUE
        self.params[param] = value
        return H.PHX_OK

    def _PHX_ParameterGet(self, handle: int, param: int, pv: int | None) -> int:  # noqa: N802
        name = _PARAMS.get(param)
        self.log.append(("PHX_ParameterGet", name[4:] if name else hex(param)))
        if name is None or param == H.PHX_CONFIG_FILE or param not in self.params:
            return H.PHX_ERROR_BAD_PARAM
        if not pv:
            return H.PHX_ERROR_INVALID_POINTER
        ctypes.c_uint32.from_address(pv).value = self.params[param]
        return H.PHX_OK

    def _PHX_Open(self, handle: int) -> int:  # noqa: N802
        self.log.append(("PHX_Open",))
        path = self.params.get(H.PHX_CONFIG_FILE)
        if path is None or not os.path.isfile(os.fsdecode(path)):
            return H.PHX_ERROR_FILE_OPEN_FAILED
        board = self.params.get(H.PHX_BOARD_NUMBER, H.PHX_BOARD1) - (H.PHX_BOARD1 - 1)
        if self.fail_open or board > self.boards:
            return H.PHX_ERROR_OPEN_FAILED
        self.opened = True
        return H.PHX_OK

    def _PHX_Close(self, handle_ptr: Any) -> int:  # noqa: N802
        self.log.append(("PHX_Close",))
        if self._held is not None:
            self.violations.append("PHX_Close with a buffer not released")
        self.opened = False
        self.streaming = False
        return H.PHX_OK

    def _PHX_Destroy(self, handle_ptr: Any) -> int:  # noqa: N802
        self.log.append(("PHX_Destroy",))
        self.created = False
        handle_ptr[0] = 0
        return H.PHX_OK

    def _PHX_StreamRead(self, handle: int, op: int, pv: int | None) -> int:  # noqa: N802
        name = _ACQ.get(op, hex(op))
        self.log.append(("PHX_StreamRead", name))
        if not self.opened:
            return H.PHX_ERROR_BAD_HANDLE
        if op == H.PHX_START:
            with self._cv:
                self.streaming = True
                self._aborted = False
            return H.PHX_OK
        if op == H.PHX_CHECK_AND_WAIT:
            with self._cv:
                self._cv.wait_for(lambda: self._queue or self._aborted)
                if self._aborted and not self._queue:
                    return H.PHX_WARNING_TIMEOUT
                return H.PHX_OK
        if op == H.PHX_BUFFER_GET:
            if not pv:
                return H.PHX_ERROR_INVALID_POINTER
            buf = StImageBuff.from_address(pv)
            with self._cv:
                if not self._queue:
                    buf.pvAddress = None
                    return H.PHX_ERROR_BAD_PARAM_VALUE
                self._held = self._queue.pop(0)
                buf.pvAddress = self._held.ctypes.data
            return H.PHX_OK
        if op == H.PHX_BUFFER_RELEASE:
            if self._held is None:
                self.violations.append("BUFFER_RELEASE without BUFFER_GET")
            self._held = None
            return H.PHX_OK
        if op in (H.PHX_STOP, H.PHX_ABORT):
            with self._cv:
                self.streaming = False
                if op == H.PHX_ABORT:
                    self._aborted = True
                    self._queue.clear()
                self._cv.notify_all()
            return H.PHX_OK
        self.violations.append(f"PHX_StreamRead: {op:#x} is not an acquisition operation of phx_api.h")
        return H.PHX_ERROR_BAD_PARAM

    # --- the camera side -------------------------------------------------------------------------------

    def deliver(self, frame: np.ndarray) -> None:
        """A frame arrives over Camera Link: captured if the stream is started and the ROI matches, and laid
        out in the destination buffer as the grabber's parameters say (line length in bytes, format)."""
        with self._cv:
            if not self.streaming:
                self.frames_dropped += 1
                return
            roi = (self.params.get(H.PHX_ROI_YLENGTH), self.params.get(H.PHX_ROI_XLENGTH))
            active = (self.params.get(H.PHX_CAM_ACTIVE_YLENGTH), self.params.get(H.PHX_CAM_ACTIVE_XLENGTH))
            if frame.shape != roi or frame.shape != active:
                self.violations.append(f"frame {frame.shape} does not match the ROI {roi} / active region {active}")
                return
            self._queue.append(self._lay_out(np.ascontiguousarray(frame, dtype=np.uint16)))
            self.frames_captured += 1
            self._cv.notify_all()

    def _lay_out(self, frame: np.ndarray) -> np.ndarray:
        """The destination buffer holding ``frame``: ``BUF_DST_YLENGTH`` lines of ``BUF_DST_XLENGTH`` bytes."""
        stride = self.params[H.PHX_BUF_DST_XLENGTH]
        lines = self.params[H.PHX_BUF_DST_YLENGTH]
        pixels = frame if self.params[H.PHX_DST_FORMAT] == H.PHX_DST_FORMAT_Y16 else frame.astype(np.uint8)
        row_bytes = pixels.shape[1] * pixels.itemsize
        buffer = np.zeros((max(lines, frame.shape[0]), stride), dtype=np.uint8)
        buffer[: frame.shape[0], : min(row_bytes, stride)] = pixels.view(np.uint8)[:, :stride]
        return buffer


def make_fake_phx(**kwargs: Any) -> FakePhxLibrary:
    return FakePhxLibrary(**kwargs)


__all__ = ["H", "PROTOTYPES", "FakePhxLibrary", "StImageBuff", "make_fake_phx"]
