"""Per-trap statistics, the imaging histogram and the assembly figures (what the dashboard's physicist's view
shows), and resetting them."""

from __future__ import annotations

from typing import Any

from fastapi import APIRouter
from pydantic import BaseModel, Field

from frontend import views
from server.routes.common import Service

__all__ = ["commands", "reads"]

reads = APIRouter()
commands = APIRouter()

#: Shots (newest) the assembly figures are computed from.
ASSEMBLY_SHOTS = 200


class HistogramOut(BaseModel):
    centres: list[float] = Field(description="bin centres, PSF-weighted counts")
    counts: list[float] = Field(description="sums per bin")


class PopulationsOut(BaseModel):
    mean_empty: float
    std_empty: float
    skew_empty: float
    mean_atom: float
    std_atom: float
    skew_atom: float
    fraction_filled: float
    separation: float = Field(description="distance between the means in combined standard deviations")


class ThresholdOut(BaseModel):
    threshold: float | None
    error: float | None = Field(description="detection error the fitted populations imply at this threshold")


class ImagingOut(BaseModel):
    samples: int = Field(description="weighted sums in the histogram: the first image of each recent shot")
    histogram: HistogramOut
    fit: PopulationsOut | None = Field(description="the two fitted populations (null: no two populations)")
    best: ThresholdOut | None = Field(description="the fit's own minimum-error threshold")
    current: ThresholdOut | None = Field(description="the configured threshold (null when the engine fits one)")
    candidate: ThresholdOut | None = Field(description="the newest threshold calibration not applied yet")


class AssemblyOut(BaseModel):
    shots: int
    success_rate: float | None
    time_to_defect_free_ms_median: float | None = Field(
        description="median over defect-free shots of when the image showing the defect-free array was in memory"
    )
    cycles_histogram: list[int] = Field(description="shots with 0, 1, 2, ... rearrangement cycles")
    lost_per_cycle_mean: float | None = Field(description="atoms the next image misses, per rearrangement cycle")
    slots_per_cycle_mean: float | None
    atoms_moved_per_cycle_mean: float | None
    pickups_per_cycle_mean: float | None = Field(
        default=None, description="atoms taken into a tweezer (extracts and captures) per rearrangement cycle"
    )
    lost_by_cause_per_cycle_mean: dict[str, float] = Field(
        default_factory=dict,
        description="atoms the lab saw lost per rearrangement cycle, by cause (from image to next image; the "
        "simulated world knows the cause, hardware does not: empty there)",
    )


class StatsOut(BaseModel):
    config_digest: str = Field(description="the configuration these statistics belong to (the running one)")
    shape: list[int] = Field(description="[ny, nx]: every map is ny rows of nx traps")
    shots: int = Field(description="shots counted since the last reset")
    truth_shots: int = Field(description="of which with the simulated lab's ground truth")
    maps: dict[str, list[list[float | None]]] = Field(
        description="loading_probability, survival (per rearrangement cycle, where the plan left the atom), "
        "defect_rate (target traps), disagreement_rate (detected vs ground truth); null: no samples"
    )
    survival_trials: list[list[int]] = Field(description="atoms each survival value rests on")
    imaging: ImagingOut
    assembly: AssemblyOut


class StatsResetOut(BaseModel):
    config_digest: str = Field(description="the configuration whose statistics were forgotten")


@reads.get(
    "/api/stats",
    response_model=StatsOut,
    summary="Per-trap statistics of the running configuration (loading, survival, defects, detection "
    "disagreements), the imaging histogram with its fitted populations and thresholds, and assembly figures",
)
def get_stats(service: Service) -> dict[str, Any]:
    return views.lab_stats(service, assembly_shots=ASSEMBLY_SHOTS)


@commands.post(
    "/api/stats/reset",
    response_model=StatsResetOut,
    summary="Forget the per-trap statistics of the running configuration (they start again from the next shot)",
)
def reset_stats(service: Service) -> StatsResetOut:
    digest = service.config.digest()
    service.trap_stats.reset(digest)
    return StatsResetOut(config_digest=digest)
