"""Calibration of module II from fresh frames: fit a threshold or a PSF, list the fits, apply one."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body
from pydantic import Field

from server.models import (
    CalibrationApplyOut,
    CalibrationApplyRequest,
    CalibrationRequest,
    PsfCalibrationOut,
    ThresholdCalibrationOut,
)
from server.routes.common import BODY_ERRORS, CONFLICT, DEVICE, ERR, Service

__all__ = ["commands", "reads"]

reads = APIRouter()
commands = APIRouter()

_CALIBRATION = Annotated[ThresholdCalibrationOut | PsfCalibrationOut, Field(discriminator="kind")]


@commands.post(
    "/api/calibrate/threshold",
    response_model=ThresholdCalibrationOut,
    responses={**BODY_ERRORS, **CONFLICT, **DEVICE},
    summary="Acquire fresh frames and fit the occupancy threshold; returns the fit and its fidelity, "
    "applies nothing (see POST /api/calibrate/apply)",
)
def calibrate_threshold(
    service: Service, request: Annotated[CalibrationRequest | None, Body()] = None
) -> dict[str, Any]:
    return service.calibrate_threshold(images=(request or CalibrationRequest()).images)


@commands.post(
    "/api/calibrate/psf",
    response_model=PsfCalibrationOut,
    responses={**BODY_ERRORS, **CONFLICT, **DEVICE},
    summary="Acquire fresh frames and fit the PSF and trap lattice; returns the fit and the detection "
    "fidelity with it and with the PSF in use, applies nothing (see POST /api/calibrate/apply)",
)
def calibrate_psf(service: Service, request: Annotated[CalibrationRequest | None, Body()] = None) -> dict[str, Any]:
    return service.calibrate_psf(images=(request or CalibrationRequest()).images)


@reads.get(
    "/api/calibrate",
    response_model=list[_CALIBRATION],
    summary="Calibrations held by the server (newest last), applied or not",
)
def calibrations(service: Service) -> list[dict[str, Any]]:
    return service.calibrations()


@commands.post(
    "/api/calibrate/apply",
    response_model=CalibrationApplyOut,
    responses={
        **BODY_ERRORS,
        404: {**ERR, "description": "no calibration with that id"},
        409: {**ERR, "description": "the configuration changed since the calibration's frames were taken"},
    },
    summary="Put a calibration's values into the running configuration (an ordinary config change, "
    "applied between shots and recorded with every later shot)",
)
def apply_calibration(service: Service, request: CalibrationApplyRequest) -> CalibrationApplyOut:
    applied = service.apply_calibration(request.id)
    # validated from the service's plain dict: the discriminator ``kind`` picks the threshold or the PSF model
    return CalibrationApplyOut.model_validate({"applied": applied, "config_digest": service.config.digest()})
