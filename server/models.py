"""What crosses the HTTP boundary: pydantic models for every request and response body.

The engine's own types (``ShotRecord``, numpy arrays) never leave the process directly; these models are the
contract a lab sequencer or a browser relies on, and FastAPI turns them into ``/openapi.json``.
"""

from __future__ import annotations

from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

from engine.records import ShotRecord

__all__ = [
    "ArmOut",
    "ArmRequest",
    "CalibrationApplyOut",
    "CalibrationApplyRequest",
    "CalibrationRequest",
    "CycleDiagnostics",
    "CycleOut",
    "PsfCalibrationOut",
    "ThresholdCalibrationOut",
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


def _not_bool(value: Any) -> Any:
    """A count in a request: 8 and 8.0 (JSON has one number type), never ``true`` or ``"8"``."""
    if isinstance(value, (bool, str)):
        raise ValueError(f"expected a number, got {value!r}")
    return value


class _Request(BaseModel):
    """A request body: unknown fields are refused (a misspelt option must not be silently ignored)."""

    model_config = ConfigDict(extra="forbid")


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


class CycleDiagnostics(BaseModel):
    """What every rearrangement cycle reports, live (``CycleOut``) or read back from a run file
    (``server.routes.runs.RunCycleOut``): one definition, so the two bodies cannot drift apart."""

    index: int
    occupancy: list[str] = Field(description="one string of '0'/'1' per trap row, as detected")
    atoms: int
    defects: int
    stage_us: dict[str, float] = Field(description="per-stage time in microseconds, names as in the paper's Table 1")
    n_slots: int
    n_steps: int
    underruns: int
    latency_us: float
    truth: dict[str, Any] = Field(
        default_factory=dict,
        description="the simulated lab's report on this cycle: lost_by_cause, atoms its world lost from this "
        "cycle's image to the next, per cause; empty on hardware",
    )


class CycleOut(CycleDiagnostics):
    atoms_moved: int = Field(0, description="atoms the cycle's plan moved")
    planner: str = Field(default="", description="the planner that made this cycle's plan; empty: none planned")
    pickups: int = Field(default=0, description="atoms the cycle's plan took into a tweezer (extracts and captures)")


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


class ShotRequest(_Request):
    """``POST /api/shots`` body (optional): a partial configuration used for this one shot only."""

    config: dict[str, Any] | None = Field(
        default=None,
        description="deep-merged into the running configuration for this shot; the running one is restored after",
    )


class ShotFileRequest(_Request):
    """``POST /api/labscript`` body: a labscript shot file on this machine."""

    path: str = Field(
        min_length=1,
        description="the shot file (HDF5); its llrs_ globals in /globals set the shot, results go to /results/llrs",
    )


class RunStateOut(BaseModel):
    running: bool = Field(description="true while shots run continuously")
    pause_s: float = Field(description="pause between continuous shots")


class ArmRequest(_Request):
    """``POST /api/arm`` body (optional)."""

    shots: int | None = Field(
        default=None, ge=1, le=1_000_000,
        description="disarm after this many triggered shots; null: stay armed until stop",
    )

    _shots_is_a_number = field_validator("shots", mode="before")(_not_bool)


class ArmOut(BaseModel):
    armed: bool
    trigger: Literal["rest", "hardware"] = Field(
        description="what starts a shot while armed: 'rest' = POST /api/trigger, 'hardware' = the sequencer's "
        "trigger line (loop.trigger: hardware, on devices that have one)"
    )
    shots_left: int | None = Field(description="triggered shots before the server disarms; null: until stop")


class StatusOut(BaseModel):
    state: Literal["idle", "armed", "running", "fault"] = Field(
        description="idle: waiting for a command; armed: waiting for a trigger; running: a shot or a calibration "
        "is in progress or continuous shots are on; fault: a device failed (see reason), shots stopped"
    )
    reason: str | None = Field(default=None, description="why the state is 'fault'")
    activity: str | None = Field(default=None, description="what the engine is doing now, in words")
    running: bool = Field(description="continuous shots requested")
    armed: bool = Field(default=False, description="waiting for the sequencer's trigger (POST /api/arm)")
    trigger: Literal["rest", "hardware"] = "rest"
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
    unrecorded_shots: int = Field(default=0, description="shots that could not be written to the run file")
    recording_error: str | None = Field(default=None, description="why the last shot could not be written")


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
        target_filled=record.lab_report.get("target_filled"),
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


class CalibrationRequest(_Request):
    """Body of ``POST /api/calibrate/threshold`` and ``/psf`` (optional)."""

    images: int = Field(
        default=40,
        ge=5,
        le=500,
        description="fresh frames to acquire (in the simulated lab each one is a newly loaded array)",
    )

    _images_is_a_number = field_validator("images", mode="before")(_not_bool)


class _CalibrationBase(BaseModel):
    id: str = Field(description="pass to POST /api/calibrate/apply to put these values into the running config")
    images: int = Field(description="frames the fit used")
    config_digest: str = Field(description="configuration the frames were taken under; apply refuses another")
    applied: bool = False
    apply_patch: dict[str, Any] = Field(description="the config change POST /api/calibrate/apply would make")


class ThresholdCalibrationOut(_CalibrationBase):
    """A two-population fit of per-trap weighted sums and its minimum-error threshold (not yet applied)."""

    kind: Literal["threshold"] = "threshold"

    threshold: float = Field(description="fitted threshold (counts, weighted sum per trap)")
    fidelity: float = Field(description="1 - P(wrong assignment) at the fitted threshold, under the fit")
    current_threshold: float | None = Field(
        description="the configured threshold; null when imaging.threshold is null (the engine calibrates at apply)"
    )
    current_fidelity: float | None = Field(description="the same fidelity estimate for the configured threshold")
    fraction_filled: float
    mean_empty: float
    mean_atom: float
    std_empty: float
    std_atom: float


class PsfCalibrationOut(_CalibrationBase):
    """A PSF fitted from frames: shared sigma, trap centres, and the trap lattice they imply (not yet applied)."""

    kind: Literal["psf"] = "psf"

    sigma_px: float = Field(description="fitted Gaussian sigma (sensor pixels)")
    current_sigma_px: float
    origin_px: list[float] = Field(
        min_length=2, max_length=2, description="fitted (x, y) of trap (row 0, col 0), sensor pixels"
    )
    col_step_px: list[float] = Field(min_length=2, max_length=2, description="(x, y) step from column c to c+1")
    row_step_px: list[float] = Field(min_length=2, max_length=2, description="(x, y) step from row r to r+1")
    lattice_rms_px: float = Field(description="rms distance of the fitted centres from the fitted lattice")
    max_shift_px: float = Field(description="largest move of a trap centre from its configured position")
    traps_fitted: int = Field(description="traps that held an atom in at least one frame")
    fidelity: float = Field(description="detection fidelity of these frames with the fitted PSF's weights")
    current_fidelity: float = Field(description="the same with the PSF in use now")


class CalibrationApplyRequest(_Request):
    id: str = Field(description="a calibration id returned by POST /api/calibrate/threshold or /psf")


class CalibrationApplyOut(BaseModel):
    applied: ThresholdCalibrationOut | PsfCalibrationOut = Field(discriminator="kind")
    config_digest: str = Field(description="digest of the configuration now running")
