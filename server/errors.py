"""One table from exception type to HTTP status, registered once on the app.

Routes never pick a status themselves from what went wrong: the service (and the modules it uses) raise
typed exceptions, and this table says what each means to a client. Lookup follows the class hierarchy
(Starlette walks the exception's MRO), so a subclass listed here wins over its base. The detail is the
exception's message, which the raising code writes for a person (never file contents, never an object's repr).
"""

from __future__ import annotations

from fastapi import FastAPI, Request
from fastapi.responses import JSONResponse, Response

from engine.devices import DeviceError
from server.files import FileRefused
from server.labscript import ShotFileError, ShotFileHasResults, ShotFileMissing
from server.service import (
    CalibrationConflict,
    CalibrationFailed,
    ConfigRejected,
    DevicesUnavailable,
    EngineBusy,
    NotArmed,
    UnknownCalibration,
)

__all__ = ["STATUS_OF", "register_error_handlers"]

#: exception type -> (status, what it means; the second column documents the table, the message is the detail)
STATUS_OF: dict[type[Exception], tuple[int, str]] = {
    ConfigRejected: (422, "a configuration the engine or the validation refused; the running one is unchanged"),
    RecursionError: (400, "a request body nested too deeply to read"),
    NotArmed: (409, "a trigger while not armed, or an arm the devices cannot honour"),
    CalibrationConflict: (409, "the configuration changed since the calibration's frames were taken"),
    CalibrationFailed: (409, "the frames could not be fitted (e.g. no atoms loaded)"),
    UnknownCalibration: (404, "no calibration with that id"),
    ShotFileMissing: (404, "no such shot file"),
    ShotFileHasResults: (409, "the shot file already holds results"),
    ShotFileError: (422, "a shot file that cannot be used (not labscript, bad llrs_ globals)"),
    FileRefused: (422, "a file path outside the configured directories, not a regular file, or too big"),
    DevicesUnavailable: (503, "the configured devices could not be opened"),
    EngineBusy: (503, "the engine stayed busy longer than a command may wait; nothing was done"),
    DeviceError: (503, "a device failed"),
}


def _handler(status: int):  # noqa: ANN202 - a Starlette exception handler
    async def handle(request: Request, exc: Exception) -> Response:
        detail = exc.errors if isinstance(exc, ConfigRejected) else str(exc)
        if isinstance(exc, RecursionError):
            detail = "request body is nested too deeply"
        return JSONResponse({"detail": detail}, status_code=status)

    return handle


def register_error_handlers(app: FastAPI) -> None:
    """Map every exception type of ``STATUS_OF`` to its status on ``app``."""
    for exc_type, (status, _meaning) in STATUS_OF.items():
        app.add_exception_handler(exc_type, _handler(status))
