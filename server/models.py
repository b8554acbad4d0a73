"""What crosses the HTTP boundary: pydantic models for every request and response body.

The engine's own types (``ShotRecord``, numpy arrays) never leave the process directly; these models are the
contract a lab sequencer or a browser relies on, and FastAPI turns them into ``/openapi.json``.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, Field

from engine.records import ShotRecord

__all__ = [
    "CycleOut",
    "DevicesOut",
    "ErrorItem",
    "ErrorOut",
    "LiveCycle",
    "RunStateOut",
    "ShotList",
    "ShotOut",
    "ShotRequest",
    "ShotSummary",
    "StatusOut",
    "shot_out",
    "shot_summary",
]


class ErrorItem(BaseModel):
    """One reason a request was refused, shaped like FastAPI's own validation errors."""

    loc: list[str | int] = Field(description="where the problem is, e.g. ['body', 'sim', 'loading_probability']")
    msg: str
    type: str


class ErrorOut(BaseModel):
    detail: str | list[ErrorItem]


class DevicesOut(BaseModel):
    camera: str = Field(description="camera implementation, e.g. 'sim'")
    awg: str = Field(description="AWG implementation, e.g. 'sim'")
    time: str = Field(description="'simulated' or 'realtime' for the simulated lab; 'hardware' otherwise")


class ShotSummary(BaseModel):
    """One line of the run history: enough to list shots without their per-cycle data."""

    shot_id: int
    outcome: Literal["success", "unsolvable", "max_cycles", "fault"]
    fault: str | None = None
    n_cycles: int = Field(description="images taken in this shot (the last one shows the final state)")
    rearrangements: int = Field(description="cycles that streamed a plan")
    atoms_loaded: int
    atoms_final: int
    defects_final: int = Field(description="target traps still empty at the last image")
    duration_s: float
    target_filled: bool | None = Field(description="simulated lab's ground truth; null on hardware")
    config_digest: str
    images: int = Field(description="camera frames kept with this shot (0 unless images were kept)")


class CycleOut(BaseModel):
    index: int
    occupancy: list[str] = Field(description="one string of '0'/'1' per trap row, as detected")
    atoms: int
    defects: int
    stage_us: dict[str, float] = Field(description="per-stage time in microseconds, names as in the paper's Table 1")
    n_slots: int
    n_steps: int
    underruns: int
    latency_us: float


class ShotOut(ShotSummary):
    algorithm: str
    target: list[str]
    cycles: list[CycleOut]
    truth: dict[str, Any] = Field(default_factory=dict)


class ShotList(BaseModel):
    total: int = Field(description="shots held by the server (the most recent ones; older shots are in runs/*.h5)")
    offset: int
    limit: int
    shots: list[ShotSummary] = Field(description="newest first")


class ShotRequest(BaseModel):
    """``POST /api/shots`` body (optional): a partial configuration used for this one shot only."""

    config: dict[str, Any] | None = Field(
        default=None,
        description="deep-merged into the running configuration for this shot; the running one is restored after",
    )


class RunStateOut(BaseModel):
    running: bool = Field(description="true while shots run continuously")
    pause_s: float = Field(description="pause between continuous shots")


class StatusOut(BaseModel):
    state: Literal["idle", "running", "fault"]
    reason: str | None = Field(default=None, description="why the state is 'fault'")
    running: bool = Field(description="continuous shots requested")
    pause_s: float
    devices: DevicesOut
    config_name: str
    config_digest: str
    shots_done: int
    successes: int = Field(description="shots the engine judged successful from its own images")
    success_rate: float | None = None
    truth_successes: int | None = Field(default=None, description="simulated lab: shots whose world filled the target")
    last_shot: ShotSummary | None = None
    run_file: str | None = Field(default=None, description="HDF5 file the current shots go to")


class LiveCycle(BaseModel):
    """One websocket message on ``/api/live``: a cycle of a finished shot, small enough to send per cycle."""

    type: Literal["cycle"] = "cycle"
    shot_id: int
    cycle: int
    n_cycles: int
    last: bool = Field(description="true on the shot's final cycle")
    occupancy: list[str]
    target: list[str]
    atoms: int
    defects: int
    stage_us: dict[str, float]
    n_slots: int
    outcome: str = Field(description="the shot's outcome (known once the shot is over)")
    target_filled: bool | None = None


def shot_summary(record: ShotRecord) -> ShotSummary:
    cycles = record.cycles
    return ShotSummary(
        shot_id=record.shot_id,
        outcome=record.outcome.value,
        fault=record.fault,
        n_cycles=len(cycles),
        rearrangements=sum(1 for c in cycles if c.n_slots > 0),
        atoms_loaded=cycles[0].atoms if cycles else 0,
        atoms_final=cycles[-1].atoms if cycles else 0,
        defects_final=cycles[-1].defects if cycles else int(record.target.sum()),
        duration_s=record.duration_s,
        target_filled=record.truth.get("target_filled"),
        config_digest=record.config_digest,
        images=len(record.images or ()),
    )


def shot_out(record: ShotRecord) -> ShotOut:
    data = record.to_dict()
    return ShotOut(
        **shot_summary(record).model_dump(),
        algorithm=record.algorithm,
        target=data["target"],
        cycles=[CycleOut(**c) for c in data["cycles"]],
        truth=data["truth"],
    )
