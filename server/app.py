"""The FastAPI app: REST commands and queries for a lab sequencer, live cycles over a websocket.

Every route is a thin adapter over ``LabService``; blocking engine calls are plain ``def`` routes, which FastAPI
runs in its thread pool, so the event loop (and the live websockets) never waits for a shot.
"""

from __future__ import annotations

import asyncio
import hmac
import html
import json
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Annotated, Any

import numpy as np

from fastapi import Body, Depends, FastAPI, HTTPException, Path, Query, Request, WebSocket
from fastapi.exception_handlers import http_exception_handler
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import HTMLResponse, JSONResponse, Response
from fastapi.routing import APIRoute
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from pydantic import Field
from starlette.exceptions import HTTPException as StarletteHTTPException

from engine.config import SystemConfig
from engine.devices import DeviceError
from server.hub import LiveHub, cycle_messages
from server.models import (
    ArmOut,
    ArmRequest,
    CalibrationApplyOut,
    CalibrationApplyRequest,
    CalibrationRequest,
    ErrorOut,
    PsfCalibrationOut,
    RunStateOut,
    ShotFileRequest,
    ShotList,
    ShotOut,
    ShotRequest,
    StatusOut,
    ThresholdCalibrationOut,
    shot_out,
    shot_summary,
)
from server.labscript import ShotFileError
from server.png import encode_png
from server.service import CalibrationConflict, ConfigRejected, DevicesUnavailable, LabService, NotArmed

__all__ = ["create_app"]

_bearer = HTTPBearer(auto_error=False, description="LLRS_TOKEN: required on every mutating route")

_ERR = {"model": ErrorOut}
_BODY_ERRORS: dict[int | str, dict[str, Any]] = {
    400: {**_ERR, "description": "malformed request body"},
    401: {**_ERR, "description": "missing or wrong bearer token (only when LLRS_TOKEN is set)"},
    422: {**_ERR, "description": "invalid input: `detail` names each field and why; nothing was changed"},
}
_AUTH_ERRORS: dict[int | str, dict[str, Any]] = {401: _BODY_ERRORS[401]}
_CONFLICT: dict[int | str, dict[str, Any]] = {409: {**_ERR, "description": "not possible in the present state; `detail` says why"}}
_DEVICE = {503: {**_ERR, "description": "a device failed while acquiring frames; `detail` says which"}}
_NO_DEVICES: dict[int | str, dict[str, Any]] = {
    503: {**_ERR, "description": "the configured devices could not be opened; `detail` says why and how to fix it"}
}
_CALIBRATION = Annotated[ThresholdCalibrationOut | PsfCalibrationOut, Field(discriminator="kind")]


async def _json_body(request: Request) -> Any:
    """The request body as JSON (400 if it is not JSON), for routes that validate it themselves."""
    try:
        return json.loads(await request.body())
    except ValueError as err:
        raise HTTPException(400, detail=f"request body is not valid JSON: {err}") from None

_NOT_FOUND: dict[int | str, dict[str, Any]] = {
    404: {**_ERR, "description": "no such shot held by the server"},
    422: {**_ERR, "description": "invalid path or query parameter"},
}


def create_app(
    *,
    service: LabService,
    token: str | None = None,
    cors_origins: tuple[str, ...] = (),
    dashboard_port: int | None = None,
    live_queue: int = 64,
) -> FastAPI:
    """Build the app around a started ``service``.

    ``token``: when set, mutating routes need ``Authorization: Bearer <token>``. ``cors_origins``: browsers on
    these origins may call the API (none by default: CORS stays closed). ``dashboard_port``: where ``GET /``
    links the viser dashboard.
    """
    hub = LiveHub(maxsize=live_queue)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        hub.bind(asyncio.get_running_loop())
        service.add_listener(hub.publish_record)
        try:
            yield
        finally:
            service.remove_listener(hub.publish_record)
            hub.bind(None)

    app = FastAPI(
        title="LLRS lab server",
        version="0.1.0",
        summary="Low-latency reconfiguration of optical-tweezer arrays: run shots, change the configuration, "
        "read the history, watch live cycles (websocket /api/live).",
        lifespan=lifespan,
    )
    app.state.service = service
    app.state.hub = hub
    if cors_origins:
        app.add_middleware(
            CORSMiddleware, allow_origins=list(cors_origins), allow_methods=["*"], allow_headers=["*"]
        )

    @app.exception_handler(DevicesUnavailable)
    async def no_devices(request: Request, exc: DevicesUnavailable) -> Response:
        return JSONResponse({"detail": str(exc)}, status_code=503)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        """A 405 names every method of the path (Starlette names only the first route's, e.g. GET for /api/config)."""
        if exc.status_code == 405:
            allowed = sorted(
                {
                    method
                    for route in app.router.routes
                    if isinstance(route, APIRoute) and route.path_regex.match(request.url.path)
                    for method in route.methods
                }
            )
            return JSONResponse({"detail": exc.detail}, status_code=405, headers={"Allow": ", ".join(allowed)})
        return await http_exception_handler(request, exc)

    def require_token(
        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
    ) -> None:
        if credentials is None or not hmac.compare_digest(credentials.credentials.encode(), token.encode()):
            raise HTTPException(401, detail="missing or wrong bearer token", headers={"WWW-Authenticate": "Bearer"})

    # Without a token the routes carry no security requirement at all, so /openapi.json stays true either way.
    auth = [Depends(require_token)] if token is not None else []
    body_errors = _BODY_ERRORS if token is not None else {k: v for k, v in _BODY_ERRORS.items() if k != 401}
    auth_errors = _AUTH_ERRORS if token is not None else {}

    def rejected(err: ConfigRejected) -> HTTPException:
        return HTTPException(422, detail=err.errors)

    @app.get("/", response_class=HTMLResponse, summary="Links to the dashboard, the API docs and the status")
    def index(request: Request) -> str:
        host = request.url.hostname or "127.0.0.1"
        dash = (
            f'<li><a id="dashboard" href="http://{html.escape(host)}:{dashboard_port}/">dashboard</a> '
            "(live atom map, timings, controls)</li>"
            if dashboard_port
            else "<li>dashboard: not running</li>"
        )
        return (
            "<!doctype html><html><head><meta charset='utf-8'><title>LLRS lab server</title></head><body>"
            f"<h1>LLRS lab server</h1><ul>{dash}<li><a href='/docs'>API docs</a> "
            "(<a href='/openapi.json'>openapi.json</a>)</li><li><a href='/api/status'>status</a></li>"
            "<li>live cycles: websocket <code>/api/live</code></li></ul></body></html>"
        )

    @app.get("/api/status", response_model=StatusOut, summary="Engine state, devices, shots done, last shot")
    def status() -> StatusOut:
        return service.status()

    @app.get("/api/config", response_model=SystemConfig, summary="The running configuration")
    def get_config() -> SystemConfig:
        return service.config

    @app.put(
        "/api/config",
        response_model=SystemConfig,
        dependencies=auth,
        responses=body_errors,
        summary="Replace the whole configuration (validated strictly: no type coercion; applied between shots)",
        openapi_extra={
            "requestBody": {
                "required": True,
                "content": {"application/json": {"schema": {"$ref": "#/components/schemas/SystemConfig"}}},
            }
        },
    )
    def put_config(config: Annotated[Any, Depends(_json_body)]) -> SystemConfig:
        if not isinstance(config, dict):
            raise HTTPException(
                422, detail=[{"loc": ["body"], "msg": "expected a JSON object (the whole configuration)", "type": "dict_type"}]
            )
        try:
            return service.replace_config(config)
        except ConfigRejected as err:
            raise rejected(err) from None

    @app.patch(
        "/api/config",
        response_model=SystemConfig,
        dependencies=auth,
        responses=body_errors,
        summary="Change part of the configuration (deep-merged, then validated; applied between shots)",
    )
    def patch_config(
        patch: Annotated[
            dict[str, Any],
            Body(examples=[{"sim": {"loading_probability": 0.5}, "loop": {"max_cycles": 4}}]),
        ],
    ) -> SystemConfig:
        try:
            return service.patch_config(patch)
        except ConfigRejected as err:
            raise rejected(err) from None

    @app.post(
        "/api/run",
        response_model=RunStateOut,
        dependencies=auth,
        responses={**auth_errors, **_NO_DEVICES},
        summary="Run shots continuously (with a pause between them)",
    )
    def run() -> RunStateOut:
        service.run()
        return RunStateOut(running=service.running, pause_s=service.pause_s)

    @app.post(
        "/api/stop",
        response_model=RunStateOut,
        dependencies=auth,
        responses=auth_errors,
        summary="Stop continuous shots after the one in progress",
    )
    def stop() -> RunStateOut:
        service.stop()
        return RunStateOut(running=service.running, pause_s=service.pause_s)

    @app.post(
        "/api/arm",
        response_model=ArmOut,
        dependencies=auth,
        responses={**body_errors, **_CONFLICT, **_NO_DEVICES},
        summary="Stop continuous shots and wait for the sequencer's trigger (POST /api/trigger, or the hardware line)",
    )
    def arm(request: Annotated[ArmRequest | None, Body()] = None) -> ArmOut:
        try:
            service.arm(shots=request.shots if request is not None else None)
        except NotArmed as err:
            raise HTTPException(409, detail=str(err)) from None
        return ArmOut(armed=service.armed, trigger=service.trigger_source, shots_left=service.armed_shots_left)  # type: ignore[arg-type]

    @app.post(
        "/api/trigger",
        response_model=ShotOut,
        dependencies=auth,
        responses={**auth_errors, **_CONFLICT, **_NO_DEVICES},
        summary="The sequencer's software trigger: run one shot now (only while armed) and return its record",
    )
    def trigger() -> ShotOut:
        try:
            return shot_out(service.trigger())
        except NotArmed as err:
            raise HTTPException(409, detail=str(err)) from None

    def calibration(kind: str, run: Any, request: CalibrationRequest | None) -> dict[str, Any]:
        try:
            return run(images=(request or CalibrationRequest()).images)
        except ValueError as err:  # the frames could not be fitted (e.g. no atoms loaded)
            raise HTTPException(409, detail=f"{kind} calibration failed: {err}") from None
        except DeviceError as err:  # the camera failed while acquiring
            raise HTTPException(503, detail=f"{kind} calibration failed: {err}") from None

    @app.post(
        "/api/calibrate/threshold",
        response_model=ThresholdCalibrationOut,
        dependencies=auth,
        responses={**body_errors, **_CONFLICT, **_DEVICE},
        summary="Acquire fresh frames and fit the occupancy threshold; returns the fit and its fidelity, "
        "applies nothing (see POST /api/calibrate/apply)",
    )
    def calibrate_threshold(request: Annotated[CalibrationRequest | None, Body()] = None) -> dict[str, Any]:
        return calibration("threshold", service.calibrate_threshold, request)

    @app.post(
        "/api/calibrate/psf",
        response_model=PsfCalibrationOut,
        dependencies=auth,
        responses={**body_errors, **_CONFLICT, **_DEVICE},
        summary="Acquire fresh frames and fit the PSF and trap lattice; returns the fit and the detection "
        "fidelity with it and with the PSF in use, applies nothing (see POST /api/calibrate/apply)",
    )
    def calibrate_psf(request: Annotated[CalibrationRequest | None, Body()] = None) -> dict[str, Any]:
        return calibration("psf", service.calibrate_psf, request)

    @app.get(
        "/api/calibrate",
        response_model=list[_CALIBRATION],
        summary="Calibrations held by the server (newest last), applied or not",
    )
    def calibrations() -> list[dict[str, Any]]:
        return service.calibrations()

    @app.post(
        "/api/calibrate/apply",
        response_model=CalibrationApplyOut,
        dependencies=auth,
        responses={
            **body_errors,
            404: {**_ERR, "description": "no calibration with that id"},
            409: {**_ERR, "description": "the configuration changed since the calibration's frames were taken"},
        },
        summary="Put a calibration's values into the running configuration (an ordinary config change, "
        "applied between shots and recorded with every later shot)",
    )
    def apply_calibration(request: CalibrationApplyRequest) -> CalibrationApplyOut:
        try:
            applied = service.apply_calibration(request.id)
        except KeyError:
            raise HTTPException(404, detail=f"no calibration {request.id!r}") from None
        except CalibrationConflict as err:
            raise HTTPException(409, detail=str(err)) from None
        except ConfigRejected as err:
            raise rejected(err) from None
        return CalibrationApplyOut(applied=applied, config_digest=service.config.digest())  # type: ignore[arg-type]

    @app.post(
        "/api/shots",
        response_model=ShotOut,
        dependencies=auth,
        responses={**body_errors, **_NO_DEVICES},
        summary="Run one shot now and return its record (optionally with a config override for this shot only)",
    )
    def post_shot(request: Annotated[ShotRequest | None, Body()] = None) -> ShotOut:
        try:
            record = service.shot(override=request.config if request is not None else None)
        except ConfigRejected as err:
            raise rejected(err) from None
        return shot_out(record)

    @app.post(
        "/api/labscript",
        response_model=ShotOut | None,
        dependencies=auth,
        responses={
            **body_errors,
            404: {"model": ErrorOut, "description": "no such shot file"},
            409: {"model": ErrorOut, "description": "the shot file already holds results"},
            **_NO_DEVICES,
        },
        summary="Run the shot a labscript shot file describes and write its results into that file",
    )
    def post_shot_file(request: ShotFileRequest) -> ShotOut | None:
        try:
            record = service.shot_file(request.path)
        except ShotFileError as err:
            status = 409 if "already holds" in str(err) else 404 if "no such shot file" in str(err) else 422
            raise HTTPException(status, detail=str(err)) from None
        except ConfigRejected as err:
            raise rejected(err) from None
        return shot_out(record) if record is not None else None

    @app.get("/api/shots", response_model=ShotList, responses=_NOT_FOUND, summary="Past shots, newest first")
    def list_shots(
        limit: Annotated[int, Query(ge=1, le=1000)] = 50,
        offset: Annotated[int, Query(ge=0)] = 0,
    ) -> ShotList:
        total, records = service.shots(limit=limit, offset=offset)
        return ShotList(total=total, offset=offset, limit=limit, shots=[shot_summary(r) for r in records])

    @app.get("/api/shots/{shot_id}", response_model=ShotOut, responses=_NOT_FOUND, summary="One shot's record")
    def get_shot(shot_id: int) -> ShotOut:
        record = service.get_shot(shot_id)
        if record is None:
            raise HTTPException(404, detail=f"shot {shot_id} is not held by the server")
        return shot_out(record)

    @app.get(
        "/api/shots/{shot_id}/image/{cycle}",
        response_class=Response,
        responses={
            200: {"content": {"image/png": {}}, "description": "the camera frame (16-bit grayscale PNG, raw counts)"},
            404: {**_ERR, "description": "no such shot, or no image kept for that cycle"},
            422: _NOT_FOUND[422],
        },
        summary="A cycle's camera frame as PNG: the final frame of recent shots, every cycle's if images are kept",
    )
    def get_image(shot_id: int, cycle: Annotated[int, Path(ge=0)]) -> Response:
        record = service.get_shot(shot_id)
        if record is None:
            raise HTTPException(404, detail=f"shot {shot_id} is not held by the server")
        image = service.frame(shot_id, cycle)
        if image is None:
            raise HTTPException(
                404,
                detail=f"no frame kept for shot {shot_id} cycle {cycle}: the server keeps the final frame "
                f"(cycle {len(record.cycles) - 1}) of its {service.final_frames_kept} most recent shots",
            )
        return Response(content=encode_png(image), media_type="image/png")

    @app.websocket("/api/live")
    async def live(ws: WebSocket) -> None:
        """Per-cycle JSON messages (``server.models.LiveCycle``): the last shot at once, then every new one.

        Send ``{"images": true}`` to also get camera frames: after a cycle's JSON message, when the server holds
        that cycle's frame (the final frame of every shot; every cycle's if images are kept), a JSON header
        ``{"type": "image", "shot_id", "cycle", "shape": [h, w], "dtype": "<u2"}`` and then one binary message
        with the raw little-endian uint16 pixels, row by row. ``{"images": false}`` stops them.
        """
        await ws.accept()
        queue = hub.subscribe()
        want_images = False
        last = service.last_record()
        if last is not None:
            for message in cycle_messages(last)[-queue.maxsize :]:
                queue.put_nowait(message)

        async def pump() -> None:
            while True:
                message = await queue.get()
                await ws.send_json(message)
                if want_images:
                    frame = service.frame(message["shot_id"], message["cycle"])
                    if frame is not None:
                        pixels = np.ascontiguousarray(frame, dtype="<u2")
                        await ws.send_json(
                            {"type": "image", "shot_id": message["shot_id"], "cycle": message["cycle"],
                             "shape": list(pixels.shape), "dtype": "<u2"}
                        )
                        await ws.send_bytes(pixels.tobytes())

        sender = asyncio.create_task(pump())
        try:
            while (event := await ws.receive())["type"] != "websocket.disconnect":
                try:
                    request = json.loads(event.get("text") or "null")
                except ValueError:
                    request = None
                if isinstance(request, dict) and isinstance(request.get("images"), bool):
                    want_images = request["images"]
        finally:
            sender.cancel()
            hub.unsubscribe(queue)

    return app
