"""The state of the lab and what starts shots: status, continuous running, arm and trigger."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Body

from server.models import ArmOut, ArmRequest, RunStateOut, ShotOut, StatusOut, shot_out
from server.routes.common import BODY_ERRORS, CONFLICT, NO_DEVICES, Service

__all__ = ["commands", "reads"]

reads = APIRouter()
commands = APIRouter()


@reads.get("/api/status", response_model=StatusOut, summary="Engine state, devices, shots done, last shot")
def status(service: Service) -> StatusOut:
    return service.status()


@commands.post("/api/run", response_model=RunStateOut, responses=NO_DEVICES,
               summary="Run shots continuously (with a pause between them)")
def run(service: Service) -> RunStateOut:
    service.run()
    return RunStateOut(running=service.running, pause_s=service.pause_s)


@commands.post("/api/stop", response_model=RunStateOut, summary="Stop continuous shots after the one in progress")
def stop(service: Service) -> RunStateOut:
    service.stop()
    return RunStateOut(running=service.running, pause_s=service.pause_s)


@commands.post(
    "/api/arm",
    response_model=ArmOut,
    responses={**BODY_ERRORS, **CONFLICT, **NO_DEVICES},
    summary="Stop continuous shots and wait for the sequencer's trigger (POST /api/trigger, or the hardware line)",
)
def arm(service: Service, request: Annotated[ArmRequest | None, Body()] = None) -> ArmOut:
    service.arm(shots=request.shots if request is not None else None)
    return ArmOut(
        armed=service.armed,
        trigger=service.trigger_source,
        shots_left=service.armed_shots_left,
    )


@commands.post(
    "/api/trigger",
    response_model=ShotOut,
    responses={**CONFLICT, **NO_DEVICES},
    summary="The sequencer's software trigger: run one shot now (only while armed) and return its record",
)
def trigger(service: Service) -> ShotOut:
    return shot_out(service.trigger())
