"""The FastAPI app: REST commands and queries for a lab sequencer, live cycles over a websocket.

``create_app`` assembles the parts: the routers of ``server.routes`` (reads open, commands behind the token
dependency), the exception-to-status table of ``server.errors``, and the request guard of
``server.security`` (hosts, origins, token before the body, JSON bodies of bounded size).
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import Depends, FastAPI, Request
from fastapi.exception_handlers import http_exception_handler
from fastapi.middleware.cors import CORSMiddleware
from fastapi.responses import JSONResponse, Response
from fastapi.routing import APIRoute
from starlette.exceptions import HTTPException as StarletteHTTPException

from server.errors import register_error_handlers
from server.hub import LiveHub
from server.routes import calibration, config, control, live, pages, runs, shots, stats
from server.routes.common import ERR
from server.security import RequestGuard, require_token
from server.service import LabService

__all__ = ["MAX_BODY_BYTES", "MAX_LIVE_SUBSCRIBERS", "create_app"]

#: The largest request body: a whole configuration with a 1024 x 1024 target mask is about 1.1 MB.
MAX_BODY_BYTES = 2 * 2**20

#: Live websocket subscribers at once (each is a browser tab or a script watching cycles).
MAX_LIVE_SUBSCRIBERS = 64

_COMMAND_ERRORS: dict[int | str, dict[str, Any]] = {
    403: {**ERR, "description": "a request from a browser page of another origin (see --cors-origin)"},
    413: {**ERR, "description": "request body too large"},
    415: {**ERR, "description": "a request body that is not JSON (Content-Type: application/json)"},
}
_AUTH_ERRORS: dict[int | str, dict[str, Any]] = {
    401: {**ERR, "description": "missing or wrong bearer token (only when LLRS_TOKEN is set)"}
}


def create_app(
    *,
    service: LabService,
    token: str | None = None,
    cors_origins: tuple[str, ...] = (),
    trusted_hosts: tuple[str, ...] | None = None,
    dashboard_port: int | None = None,
    live_queue: int = 64,
    max_live: int = MAX_LIVE_SUBSCRIBERS,
    max_body_bytes: int = MAX_BODY_BYTES,
) -> FastAPI:
    """Build the app around a started ``service``.

    ``token``: when set, mutating routes need ``Authorization: Bearer <token>``. ``cors_origins``: browsers on
    these origins may call the API (none by default: CORS stays closed, and mutating requests from other
    origins are refused). ``trusted_hosts``: the ``Host`` names the server answers to (``None``: any; a
    loopback-only server without a token should name its loopback names, see ``server.security``).
    ``dashboard_port``: where ``GET /`` links the viser dashboard. ``max_live``: live websocket subscribers
    at once. ``max_body_bytes``: the largest request body.
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
        # a path is answered as sent or not at all: with slash redirects a run named "/" (``/api/runs/%2F``)
        # was redirected to the run listing instead of being refused
        redirect_slashes=False,
    )
    app.state.service = service
    app.state.hub = hub
    app.state.token = token
    app.state.dashboard_port = dashboard_port
    app.state.max_live = max_live
    if cors_origins:
        app.add_middleware(
            CORSMiddleware, allow_origins=list(cors_origins), allow_methods=["*"], allow_headers=["*"]
        )
    # Added last, so it runs first: nothing reads a body before the guard has looked at the headers.
    app.add_middleware(
        RequestGuard,
        token=token,
        trusted_hosts=trusted_hosts,
        cors_origins=cors_origins,
        max_body_bytes=max_body_bytes,
    )
    register_error_handlers(app)

    @app.exception_handler(StarletteHTTPException)
    async def http_error(request: Request, exc: StarletteHTTPException) -> Response:
        """A 405 names every method of the path (Starlette names only the first route's, e.g. GET for /api/config)."""
        if exc.status_code == 405:
            allowed = sorted(
                {
                    method
                    for route in app.router.routes
                    if isinstance(route, APIRoute) and route.path_regex.match(request.url.path)
                    for method in route.methods or ()  # Starlette types it Optional; an APIRoute always has a set
                }
            )
            return JSONResponse({"detail": exc.detail}, status_code=405, headers={"Allow": ", ".join(allowed)})
        return await http_exception_handler(request, exc)

    # Without a token the commands carry no security requirement at all, so /openapi.json stays true either way.
    auth = [Depends(require_token)] if token is not None else []
    command_errors = {**_COMMAND_ERRORS, **(_AUTH_ERRORS if token is not None else {})}
    for reads in (pages.reads, control.reads, config.reads, shots.reads, calibration.reads, live.reads, stats.reads,
                  runs.reads):
        app.include_router(reads)
    for commands in (control.commands, config.commands, shots.commands, calibration.commands, stats.commands):
        app.include_router(commands, dependencies=auth, responses=command_errors)
    return app
