"""Shots: run one (optionally with a one-shot configuration, or from a labscript shot file), read the history
and the camera frames kept with it."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Body, HTTPException, Path, Query
from fastapi.responses import Response

from server.models import ShotFileRequest, ShotList, ShotOut, ShotRequest, shot_out, shot_summary
from server.png import encode_png
from server.routes.common import BODY_ERRORS, ERR, NO_DEVICES, NOT_FOUND, Service

__all__ = ["commands", "reads"]

reads = APIRouter()
commands = APIRouter()


@commands.post(
    "/api/shots",
    response_model=ShotOut,
    responses={**BODY_ERRORS, **NO_DEVICES},
    summary="Run one shot now and return its record (optionally with a config override for this shot only)",
)
def post_shot(service: Service, request: Annotated[ShotRequest | None, Body()] = None) -> ShotOut:
    return shot_out(service.shot(override=request.config if request is not None else None))


@commands.post(
    "/api/labscript",
    response_model=ShotOut | None,
    responses={
        **BODY_ERRORS,
        404: {**ERR, "description": "no such shot file"},
        409: {**ERR, "description": "the shot file already holds results"},
        **NO_DEVICES,
    },
    summary="Run the shot a labscript shot file (in the server's --shot-dir) describes and write its results "
    "into that file",
)
def post_shot_file(service: Service, request: ShotFileRequest) -> ShotOut | None:
    record = service.shot_file(request.path)
    return shot_out(record) if record is not None else None


@reads.get("/api/shots", response_model=ShotList, responses=NOT_FOUND, summary="Past shots, newest first")
def list_shots(
    service: Service,
    limit: Annotated[int, Query(ge=1, le=1000)] = 50,
    offset: Annotated[int, Query(ge=0)] = 0,
) -> ShotList:
    total, records = service.shots(limit=limit, offset=offset)
    return ShotList(total=total, offset=offset, limit=limit, shots=[shot_summary(r) for r in records])


@reads.get("/api/shots/{shot_id}", response_model=ShotOut, responses=NOT_FOUND, summary="One shot's record")
def get_shot(service: Service, shot_id: int) -> ShotOut:
    record = service.get_shot(shot_id)
    if record is None:
        raise HTTPException(404, detail=f"shot {shot_id} is not held by the server")
    return shot_out(record)


@reads.get(
    "/api/shots/{shot_id}/image/{cycle}",
    response_class=Response,
    responses={
        200: {"content": {"image/png": {}}, "description": "the camera frame (16-bit grayscale PNG, raw counts)"},
        404: {**ERR, "description": "no such shot, or no image kept for that cycle"},
        422: NOT_FOUND[422],
    },
    summary="A cycle's camera frame as PNG: the final frame of recent shots, every cycle's if images are kept",
)
def get_image(service: Service, shot_id: int, cycle: Annotated[int, Path(ge=0)]) -> Response:
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
