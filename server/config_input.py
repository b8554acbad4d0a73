"""What a client sends as a configuration: validated strictly, and the tone files it names checked.

The lab service (``server.service``) runs every configuration from a request through these before the
engine sees it; ``ConfigRejected`` carries the errors in FastAPI's shape (422 over REST).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from pydantic import ValidationError

from engine.config import SystemConfig
from server.files import confine, open_regular

__all__ = ["MAX_TONE_FILE_BYTES", "ConfigRejected", "checked_tone_files", "validate_strict"]

#: A tone CSV holds one short ``alpha,nu,phi`` line per trap (at most 1024 per axis: about 50 kB).
MAX_TONE_FILE_BYTES = 256 * 2**10


class ConfigRejected(ValueError):
    """A configuration the service refused; ``errors`` say where and why (FastAPI's error shape)."""

    def __init__(self, errors: list[dict[str, Any]]) -> None:
        super().__init__("; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors))
        self.errors = errors


def validate_strict(data: Any) -> SystemConfig:
    """Validate JSON-shaped ``data`` strictly: ``"lossless": 0`` or ``"max_cycles": "5"`` are refused, not coerced
    (a lab config is typed by a person; a silent coercion would hide a typo)."""
    try:
        return SystemConfig.model_validate_json(json.dumps(data, allow_nan=False), strict=True)
    except ValueError as err:
        if not isinstance(err, ValidationError):  # NaN or infinity somewhere
            raise ConfigRejected([{"loc": ["body"], "msg": f"not valid JSON: {err}", "type": "json_invalid"}]) from None
        raise ConfigRejected(
            [{"loc": ["body", *e["loc"]], "msg": e["msg"], "type": e["type"]} for e in err.errors()]
        ) from None


def checked_tone_files(config: SystemConfig, running: SystemConfig | None, tone_dir: Path | None) -> SystemConfig:
    """``config`` with each tone CSV that differs from the running configuration's checked (inside
    ``tone_dir``, a regular file, at most ``MAX_TONE_FILE_BYTES``) and named by its resolved path, so the
    engine reads exactly the file checked here. A CSV already running was put there by the operator."""
    running_array = running.array if running is not None else None
    changes: dict[str, Any] = {}
    for axis in ("x_tones", "y_tones"):
        csv = getattr(config.array, axis).csv
        if csv is None or (running_array is not None and csv == getattr(running_array, axis).csv):
            continue
        try:
            path = confine(csv, tone_dir, what="tone file", option="--tone-dir")
            open_regular(path, what="tone file", max_bytes=MAX_TONE_FILE_BYTES).close()
        except (ValueError, FileNotFoundError) as err:
            msg = str(err) if not isinstance(err, FileNotFoundError) else f"tone file {csv!r}: no such file"
            raise ConfigRejected(
                [{"loc": ["body", "array", axis, "csv"], "msg": msg, "type": "file_refused"}]
            ) from None
        changes[axis] = getattr(config.array, axis).model_copy(update={"csv": str(path)})
    if not changes:
        return config
    return config.model_copy(update={"array": config.array.model_copy(update=changes)})
