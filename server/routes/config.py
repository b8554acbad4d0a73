"""The running configuration: read it, replace it, change part of it (applied between shots)."""

from __future__ import annotations

from typing import Annotated, Any

from fastapi import APIRouter, Body, HTTPException

from engine.config import SystemConfig
from server.routes.common import BODY_ERRORS, JsonBody, Service

__all__ = ["commands", "reads"]

reads = APIRouter()
commands = APIRouter(responses=BODY_ERRORS)


@reads.get("/api/config", response_model=SystemConfig, summary="The running configuration")
def get_config(service: Service) -> SystemConfig:
    return service.config


@commands.put(
    "/api/config",
    response_model=SystemConfig,
    summary="Replace the whole configuration (validated strictly: no type coercion; applied between shots)",
    openapi_extra={
        "requestBody": {
            "required": True,
            "content": {"application/json": {"schema": {"$ref": "#/components/schemas/SystemConfig"}}},
        }
    },
)
def put_config(service: Service, config: JsonBody) -> SystemConfig:
    if not isinstance(config, dict):
        raise HTTPException(
            422,
            detail=[{"loc": ["body"], "msg": "expected a JSON object (the whole configuration)", "type": "dict_type"}],
        )
    return service.replace_config(config)


@commands.patch(
    "/api/config",
    response_model=SystemConfig,
    summary="Change part of the configuration (deep-merged, then validated; applied between shots)",
)
def patch_config(
    service: Service,
    patch: Annotated[dict[str, Any], Body(examples=[{"sim": {"loading_probability": 0.5}, "loop": {"max_cycles": 4}}])],
) -> SystemConfig:
    return service.patch_config(patch)
