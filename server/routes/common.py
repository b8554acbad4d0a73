"""What every route module shares: the service dependency, the JSON body reader and the documented errors."""

from __future__ import annotations

import json
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request

from server.models import ErrorOut
from server.service import LabService

__all__ = ["BODY_ERRORS", "CONFLICT", "DEVICE", "ERR", "JsonBody", "NOT_FOUND", "NO_DEVICES", "Service"]


def _service(request: Request) -> LabService:
    return request.app.state.service


#: The lab service the app was built around (a route parameter: ``service: Service``).
Service = Annotated[LabService, Depends(_service)]


async def _json_body(request: Request) -> Any:
    """The request body as JSON (400 if it is not JSON, or nested too deeply to read), for routes that
    validate it themselves."""
    try:
        return json.loads(await request.body())
    except ValueError as err:
        raise HTTPException(400, detail=f"request body is not valid JSON: {err}") from None
    except RecursionError:
        raise HTTPException(400, detail="request body is nested too deeply") from None


JsonBody = Annotated[Any, Depends(_json_body)]

ERR = {"model": ErrorOut}
BODY_ERRORS: dict[int | str, dict[str, Any]] = {
    400: {**ERR, "description": "malformed request body"},
    422: {**ERR, "description": "invalid input: `detail` names each field and why; nothing was changed"},
}
CONFLICT: dict[int | str, dict[str, Any]] = {
    409: {**ERR, "description": "not possible in the present state; `detail` says why"}
}
DEVICE: dict[int | str, dict[str, Any]] = {
    503: {**ERR, "description": "a device failed while acquiring frames; `detail` says which"}
}
NO_DEVICES: dict[int | str, dict[str, Any]] = {
    503: {**ERR, "description": "the configured devices could not be opened; `detail` says why and how to fix it"}
}
NOT_FOUND: dict[int | str, dict[str, Any]] = {
    404: {**ERR, "description": "no such shot held by the server"},
    422: {**ERR, "description": "invalid path or query parameter"},
}
