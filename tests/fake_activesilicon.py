"""A fake Active Silicon PHX library for testing ``drivers/activesilicon.py`` without a grabber.

It stands in for the ``ctypes.CDLL``: its ``PHX_*`` functions take the same ctypes arguments (values by
reference through ``byref``) and return the same status codes, and every call is recorded in ``log``.
The model enforces what the adapter must respect: parameters before ``PHX_Open`` are the pre-open ones (the
camera file must exist), the rest need an open board; a frame is only captured while the stream is started;
``PHX_CHECK_AND_WAIT`` blocks until a frame arrives or the stream is aborted (from another thread);
``PHX_BUFFER_GET`` hands out the address of a buffer holding the frame; buffers must be released.
Frames arrive through ``deliver(frame)`` (a fake camera's Camera Link output calls it).
"""

from __future__ import annotations

import os
import threading
from typing import Any

import numpy as np

from drivers.activesilicon import PHX

PHX_ERROR_BAD_HANDLE = 1
PHX_ERROR_BAD_PARAM = 2
PHX_ERROR_BAD_PARAM_VALUE = 3
PHX_ERROR_OPEN_FAILED = 5
PHX_ERROR_FILE_OPEN_FAILED = 16
_PRE_OPEN = {PHX.CONFIG_FILE, PHX.BOARD_NUMBER, PHX.CHANNEL_NUMBER, PHX.CONFIG_MODE}
_NAMES = {v: k for k, v in vars(PHX).items() if isinstance(v, int)}


def _value(arg: Any) -> Any:
    """What a ``byref(x)`` / ctypes scalar / plain int argument holds."""
    obj = getattr(arg, "_obj", arg)
    return getattr(obj, "value", obj)


class FakePhxLibrary:
    """One fake grabber (board 1, channel A unless told otherwise)."""

    def __init__(self, *, boards: int = 1, fail_open: bool = False) -> None:
        self.boards = boards
        self.fail_open = fail_open
        self.log: list[tuple[Any, ...]] = []
        self.params: dict[int, Any] = {}
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

    # --- the C functions -------------------------------------------------------------------------------

    def PHX_Create(self, handle_ref: Any, handler: Any) -> int:  # noqa: N802
        self.log.append(("PHX_Create",))
        handle_ref._obj.value = 7
        self.created = True
        return PHX.OK

    def PHX_ParameterSet(self, handle: Any, param: Any, value_ref: Any) -> int:  # noqa: N802
        p = _value(param)
        v = _value(value_ref)
        self.log.append(("PHX_ParameterSet", _NAMES.get(p, hex(p)), v))
        if not self.created or _value(handle) != 7:
            return PHX_ERROR_BAD_HANDLE
        if (p in _PRE_OPEN) == self.opened:
            self.violations.append(f"{_NAMES.get(p, hex(p))} set {'after' if self.opened else 'before'} PHX_Open")
            return PHX_ERROR_BAD_PARAM
        self.params[p] = v
        return PHX.OK

    def PHX_Open(self, handle: Any) -> int:  # noqa: N802
        self.log.append(("PHX_Open",))
        path = self.params.get(PHX.CONFIG_FILE)
        if path is None or not os.path.isfile(os.fsdecode(path)):
            return PHX_ERROR_FILE_OPEN_FAILED
        board = self.params.get(PHX.BOARD_NUMBER, PHX.board(1)) - PHX.board(0)
        if self.fail_open or board > self.boards:
            return PHX_ERROR_OPEN_FAILED
        self.opened = True
        return PHX.OK

    def PHX_Close(self, handle_ref: Any) -> int:  # noqa: N802
        self.log.append(("PHX_Close",))
        if self._held is not None:
            self.violations.append("PHX_Close with a buffer not released")
        self.opened = False
        self.streaming = False
        return PHX.OK

    def PHX_Destroy(self, handle_ref: Any) -> int:  # noqa: N802
        self.log.append(("PHX_Destroy",))
        self.created = False
        return PHX.OK

    def PHX_StreamRead(self, handle: Any, op: Any, arg: Any) -> int:  # noqa: N802
        o = _value(op)
        name = _NAMES.get(o, hex(o))
        self.log.append(("PHX_StreamRead", name))
        if not self.opened:
            return PHX_ERROR_BAD_HANDLE
        if o == PHX.START:
            with self._cv:
                self.streaming = True
                self._aborted = False
            return PHX.OK
        if o == PHX.CHECK_AND_WAIT:
            with self._cv:
                self._cv.wait_for(lambda: self._queue or self._aborted)
                if self._aborted and not self._queue:
                    return PHX.WARNING_TIMEOUT
                return PHX.OK
        if o == PHX.BUFFER_GET:
            with self._cv:
                if not self._queue:
                    arg._obj.pvAddress = None
                    return PHX_ERROR_BAD_PARAM_VALUE
                self._held = self._queue.pop(0)
                arg._obj.pvAddress = self._held.ctypes.data
            return PHX.OK
        if o == PHX.BUFFER_RELEASE:
            if self._held is None:
                self.violations.append("BUFFER_RELEASE without BUFFER_GET")
            self._held = None
            return PHX.OK
        if o in (PHX.STOP, PHX.ABORT):
            with self._cv:
                self.streaming = False
                if o == PHX.ABORT:
                    self._aborted = True
                    self._queue.clear()
                self._cv.notify_all()
            return PHX.OK
        return PHX_ERROR_BAD_PARAM

    # --- the camera side -------------------------------------------------------------------------------

    def deliver(self, frame: np.ndarray) -> None:
        """A frame arrives over Camera Link: captured if the stream is started and the ROI matches."""
        with self._cv:
            if not self.streaming:
                self.frames_dropped += 1
                return
            roi = (self.params.get(PHX.ROI_YLENGTH), self.params.get(PHX.ROI_XLENGTH))
            active = (self.params.get(PHX.CAM_ACTIVE_YLENGTH), self.params.get(PHX.CAM_ACTIVE_XLENGTH))
            if frame.shape != roi or frame.shape != active:
                self.violations.append(f"frame {frame.shape} does not match the ROI {roi} / active region {active}")
                return
            self._queue.append(np.ascontiguousarray(frame, dtype=np.uint16).copy())
            self.frames_captured += 1
            self._cv.notify_all()


def make_fake_phx(**kwargs: Any) -> FakePhxLibrary:
    return FakePhxLibrary(**kwargs)


__all__ = ["FakePhxLibrary", "make_fake_phx"]
