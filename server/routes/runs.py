"""Run files: list them, download one (HDF5), read one recorded shot of one, and a camera frame kept with it.

Names are checked strictly (``server.runstore.RUN_NAME``: what the run store writes, never a path), and
files come only from the server's runs directory (``llrs serve --runs-dir``, through ``server.files.confine``).
All are reads: open to anyone the server answers, as the shot history is."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Path, Query
from fastapi.responses import FileResponse, Response
from pydantic import BaseModel, Field

from server.models import CycleDiagnostics
from server.png import encode_png
from server.routes.common import ERR, Service
from server.runstore import RUN_NAME, RunStore

__all__ = ["reads"]

reads = APIRouter()

RunName = Annotated[
    str, Path(pattern=RUN_NAME, max_length=40, description="a run file's name, e.g. 20260101-120000-0.h5")
]
_MISSING: dict[int | str, dict[str, Any]] = {
    404: {**ERR, "description": "no such run file (or the server records no runs)"}
}


class RunOut(BaseModel):
    name: str
    size_bytes: int
    created: str
    config_name: str
    config_digest: str
    shape: list[int] = Field(description="[ny, nx]")
    shots: int


class AtomPathOut(BaseModel):
    source: int = Field(description="the trap index the atom started the cycle in")
    points: list[list[float]] = Field(
        description="[row, column] in sites of each corner of its route, start to end; a half (3.5) is the "
        "channel between two rows or columns of traps (interstitial routing)"
    )


class RunCycleOut(CycleDiagnostics):
    atoms_moved: int
    pickups: int | None = Field(default=None, description="atoms the plan took into a tweezer (null: not recorded)")
    moves: list[list[int]] = Field(description="[source, destination] trap index of every atom the plan moved")
    paths: list[AtomPathOut] = Field(
        default_factory=list,
        description="the route of each moved atom as its corner points, start to end ([] in older run files; "
        "atoms past a bound per cycle keep only their move)",
    )
    counts: list[float] | None = Field(description="the image's PSF-weighted sums per trap (null: not recorded)")
    frame: bool = Field(
        default=False, description="its camera frame is kept (GET /api/runs/{name}/shots/{index}/frames/{cycle})"
    )


class RunShotOut(BaseModel):
    shot_id: int
    index: int = Field(description="the shot's position in its run file")
    config_digest: str
    algorithm: str
    target: list[str]
    outcome: str
    fault: str | None
    cycles: list[RunCycleOut]
    duration_s: float
    truth: dict[str, Any]


def _store(service: Any) -> RunStore:
    store = service.run_store
    if store is None:
        raise HTTPException(404, detail="this server records no run files")
    return store


@reads.get("/api/runs", response_model=list[RunOut], responses=_MISSING, summary="Run files, newest first")
def list_runs(service: Service, limit: Annotated[int, Query(ge=1, le=1000)] = 100) -> list[dict[str, Any]]:
    return _store(service).runs(limit=limit)


@reads.get(
    "/api/runs/{name}",
    response_class=FileResponse,
    responses={
        200: {"content": {"application/x-hdf5": {}}, "description": "the run file (HDF5; see the README)"},
        **_MISSING,
    },
    summary="Download a run file (the one being written is a snapshot: open it with h5py's swmr=True)",
)
def download_run(service: Service, name: RunName) -> FileResponse:
    path = _store(service).path_of(name)
    if path is None:
        raise HTTPException(404, detail=f"no run file {name!r} in the runs directory")
    return FileResponse(path, media_type="application/x-hdf5", filename=name)


@reads.get(
    "/api/runs/{name}/shots/{index}",
    response_model=RunShotOut,
    responses={404: {**ERR, "description": "no such run file, or no such shot in it"}},
    summary="One recorded shot of a run file, with every cycle's occupancy, plan (moved atoms) and counts",
)
def run_shot(service: Service, name: RunName, index: Annotated[int, Path(ge=0)]) -> dict[str, Any]:
    try:
        return _store(service).read_shot(name, index)
    except (FileNotFoundError, IndexError) as err:
        raise HTTPException(404, detail=str(err)) from None


@reads.get(
    "/api/runs/{name}/shots/{index}/frames/{cycle}",
    response_class=Response,
    responses={
        200: {"content": {"image/png": {}}, "description": "the camera frame (16-bit grayscale PNG, raw counts)"},
        404: {**ERR, "description": "no such run file or shot, or no frame kept for that cycle (llrs serve "
              "--keep-frames)"},
    },
    summary="A recorded cycle's camera frame as PNG, where the run file kept it",
)
def run_frame(
    service: Service, name: RunName, index: Annotated[int, Path(ge=0)], cycle: Annotated[int, Path(ge=0)]
) -> Response:
    try:
        frame = _store(service).read_frame(name, index, cycle)
    except (FileNotFoundError, LookupError) as err:  # IndexError is a LookupError: no such shot
        raise HTTPException(404, detail=str(err)) from None
    return Response(content=encode_png(frame), media_type="image/png")
