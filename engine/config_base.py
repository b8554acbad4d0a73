"""What every configuration section shares: the strict pydantic base model and the common field types.

Its own module so that ``engine.config`` and the sections it composes from ``engine.config_sim`` and
``engine.config_devices`` use one base without importing each other.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

__all__ = ["Fraction", "_Model"]


class _Model(BaseModel):
    """Unknown fields are errors (a misspelt key never passes silently) and assignments are validated too."""

    model_config = ConfigDict(extra="forbid", validate_assignment=True)


Fraction = Annotated[float, Field(ge=0, le=1)]
