"""Lab-sequencer integration through labscript shot files (HDF5).

A labscript shot file carries the shot's globals as attributes of the group ``/globals`` (labscript stores
each global's evaluated value there; the per-group subgroups hold the expressions). Globals whose name
starts with ``llrs_`` parameterize our shot (``GLOBALS`` lists them and where each lands in the
configuration); ``llrs_config`` may hold a JSON object merged over the configuration for anything else.
An unknown ``llrs_`` global is an error, so a typo cannot silently run the wrong shot.

The shot's results are written *into the same file*, under ``/results/llrs`` (labscript's analysis tools keep
per-analysis results under ``/results``): outcome, per-cycle occupancy, atoms, defects, per-stage times,
latencies, the target, the configuration and its digest, and the globals used. A file that already holds
``/results/llrs`` is refused before the shot runs: a shot file describes one shot, and its results are never
overwritten. The group is written under a temporary name and renamed at the end, so a crash never leaves a
half-written ``/results/llrs``.

Everything here is a plain function over ``engine.records.ShotRecord`` and a ``run_shot`` callable, so it
works (and is tested) without the engine; the server passes a callable that runs one shot on its engine.
"""

from __future__ import annotations

import json
import math
import uuid
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import h5py
import numpy as np

from engine.config import ConfigError, SystemConfig, config_from_dict, deep_merge
from engine.records import ShotRecord
from engine.timing import STAGES
from server.files import open_regular

__all__ = [
    "GLOBALS",
    "RESULTS_GROUP",
    "MAX_SHOT_FILE_BYTES",
    "ShotFileError",
    "ShotFileHasResults",
    "ShotFileMissing",
    "read_shot_globals",
    "read_shot_results",
    "run_shot_file",
    "shot_config",
    "shot_overrides",
    "write_shot_fault",
    "write_shot_results",
]

RESULTS_GROUP = "results/llrs"

# global name -> configuration path it sets
GLOBALS: dict[str, tuple[str, ...]] = {
    "llrs_algorithm": ("solver", "algorithm"),
    "llrs_target": ("target", "kind"),
    "llrs_target_count": ("target", "count"),
    "llrs_target_rows": ("target", "rows"),
    "llrs_target_cols": ("target", "cols"),
    "llrs_target_row0": ("target", "row0"),
    "llrs_target_col0": ("target", "col0"),
    "llrs_target_mask": ("target", "mask"),
    "llrs_max_cycles": ("loop", "max_cycles"),
    "llrs_loading_probability": ("sim", "loading_probability"),
    "llrs_seed": ("sim", "seed"),
    "llrs_exposure_s": ("camera", "exposure_s"),
    "llrs_em_gain": ("camera", "em_gain"),
}
SPECIAL_GLOBALS = ("llrs_config", "llrs_enabled")

#: Shot files hold a shot's instructions and, here, its results: far below this (images are not in them).
MAX_SHOT_FILE_BYTES = 256 * 2**20


class ShotFileError(RuntimeError):
    """A shot file that cannot be used: missing, not a labscript file, bad ``llrs_`` globals, or it already
    holds results. The message names the file and what is wrong."""


class ShotFileMissing(ShotFileError):
    """There is no shot file at that path."""


class ShotFileHasResults(ShotFileError):
    """The shot file already holds LLRS results (a shot file records one shot)."""


@contextmanager
def _open_h5(path: Path, mode: str) -> Iterator[h5py.File]:
    """The shot file through a descriptor checked to be a regular file of bounded size (``server.files``),
    so that a FIFO or a device named as a shot file is refused instead of hanging the server."""
    try:
        fh = open_regular(path, what="shot file", max_bytes=MAX_SHOT_FILE_BYTES, write=mode == "r+")
    except FileNotFoundError:
        raise ShotFileMissing(
            f"{path}: no such shot file (results are written into the shot file, never beside it)"
        ) from None
    with fh:
        try:
            f = h5py.File(fh, mode)
        except OSError:
            raise ShotFileError(f"{path}: not an HDF5 file (a labscript shot file is one)") from None
        with f:
            yield f


def _plain(value: Any) -> Any:
    """An HDF5 attribute value as plain Python (bytes -> str, numpy scalars and arrays -> numbers and lists)."""
    if isinstance(value, bytes):
        return value.decode()
    if isinstance(value, np.ndarray):
        return [_plain(v) for v in value.tolist()] if value.ndim else _plain(value.item())
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, list):
        return [_plain(v) for v in value]
    return value


def read_shot_globals(path: str | Path) -> dict[str, Any]:
    """Every global of a labscript shot file (the attributes of ``/globals``), as plain Python values."""
    path = Path(path)
    with _open_h5(path, "r") as f:
        if "globals" not in f:
            raise ShotFileError(f"{path}: no /globals group; is this a labscript shot file?")
        return {name: _plain(value) for name, value in f["globals"].attrs.items()}


def shot_overrides(globals_: Mapping[str, Any]) -> dict[str, Any]:
    """The configuration patch the ``llrs_`` globals ask for (nested like the YAML; empty if none)."""
    unknown = sorted(n for n in globals_ if n.startswith("llrs_") and n not in GLOBALS and n not in SPECIAL_GLOBALS)
    if unknown:
        raise ShotFileError(
            f"unknown llrs_ global(s) {', '.join(unknown)}; recognised: {', '.join([*GLOBALS, *SPECIAL_GLOBALS])}"
        )
    patch: dict[str, Any] = {}
    blob = globals_.get("llrs_config")
    if blob is not None:
        try:
            extra = json.loads(blob) if isinstance(blob, str) else blob
        except json.JSONDecodeError as err:
            raise ShotFileError(f"global llrs_config is not valid JSON: {err}") from None
        if not isinstance(extra, dict):
            raise ShotFileError(f"global llrs_config must be a JSON object, not {type(extra).__name__}")
        patch = deep_merge(patch, extra)
    for name, where in GLOBALS.items():
        if name in globals_:
            node = patch
            for key in where[:-1]:
                node = node.setdefault(key, {})
            node[where[-1]] = globals_[name]
    return patch


def shot_config(
    base: SystemConfig | None, globals_: Mapping[str, Any], *, source: str = "shot file"
) -> SystemConfig | None:
    """The configuration for this shot: ``base`` with the globals' overrides, or ``None`` when there are none
    (the engine then keeps its current configuration)."""
    patch = shot_overrides(globals_)
    if not patch:
        return None
    base = base if base is not None else SystemConfig()
    try:
        return config_from_dict(deep_merge(base.model_dump(mode="json"), patch), source=f"{source} (llrs_ globals)")
    except ConfigError as err:
        msg = str(err)
        for name, where in GLOBALS.items():  # point each bad field back at the global that set it
            if name in globals_:
                dotted = ".".join(where)
                msg = msg.replace(f"  {dotted}:", f"  {dotted} (global {name} = {globals_[name]!r}):")
        used = ", ".join(n for n in globals_ if n.startswith("llrs_"))
        raise ShotFileError(f"the globals {used} make an invalid configuration: {msg}") from None


def _results_exist(f: h5py.File) -> bool:
    return RESULTS_GROUP in f


def _refuse_existing(f: h5py.File, path: Path) -> None:
    if _results_exist(f):
        g = f[RESULTS_GROUP]
        raise ShotFileHasResults(
            f"{path} already holds LLRS results (shot {g.attrs.get('shot_id', '?')}, outcome "
            f"{_plain(g.attrs.get('outcome', '?'))}, written {_plain(g.attrs.get('written_at', '?'))}); a shot file "
            "records one shot and its results are never overwritten: compile a new shot file"
        )


def _write_group(path: Path, fill: Callable[[h5py.Group], None]) -> None:
    """Create ``/results/llrs`` atomically: fill a temporary group, then rename it."""
    with _open_h5(path, "r+") as f:  # r+: the file must exist; results never go beside it
        _refuse_existing(f, path)
        results = f.require_group("results")
        tmp = f"llrs.partial-{uuid.uuid4().hex[:8]}"
        group = results.create_group(tmp)
        try:
            group.attrs["written_at"] = datetime.now(UTC).isoformat(timespec="seconds")
            group.attrs["writer"] = "llrs"
            fill(group)
            results.move(tmp, "llrs")
        except BaseException:
            if tmp in results:
                del results[tmp]
            raise


def write_shot_results(
    path: str | Path,
    record: ShotRecord,
    *,
    config: SystemConfig | None = None,
    globals_used: Mapping[str, Any] | None = None,
) -> None:
    """Write ``record`` into the shot file under ``/results/llrs``; ``ShotFileError`` if results are there."""
    path = Path(path)
    cycles = record.cycles
    n = len(cycles)
    target = np.asarray(record.target, dtype=bool)

    def fill(g: h5py.Group) -> None:
        g.attrs["shot_id"] = record.shot_id
        g.attrs["outcome"] = record.outcome.value
        g.attrs["success"] = record.success
        g.attrs["fault"] = record.fault or ""
        g.attrs["config_digest"] = record.config_digest
        g.attrs["algorithm"] = record.algorithm
        g.attrs["n_cycles"] = n
        g.attrs["duration_s"] = record.duration_s
        if config is not None:
            g.attrs["config"] = config.model_dump_json()
        if globals_used:
            g.attrs["globals"] = json.dumps(dict(globals_used), sort_keys=True, default=str)
        if record.lab_report:
            g.attrs["truth"] = json.dumps(record.lab_report, sort_keys=True, default=str)
        g.create_dataset("target", data=target)
        occ = np.zeros((n, *target.shape), dtype=bool)
        for i, c in enumerate(cycles):
            occ[i] = c.occupancy
        g.create_dataset("occupancy", data=occ, compression="gzip")
        for name in ("atoms", "defects", "n_slots", "n_steps", "underruns"):
            g.create_dataset(name, data=np.array([getattr(c, name) for c in cycles], dtype=np.int64))
        g.create_dataset("latency_s", data=np.array([c.latency_s for c in cycles], dtype=np.float64))
        stages = g.create_group("stage_s")
        names = [s for s in STAGES if any(s in c.stage_s for c in cycles)]
        names += sorted({s for c in cycles for s in c.stage_s} - set(names))
        for stage in names:
            per_cycle = np.array([c.stage_s.get(stage, math.nan) for c in cycles], dtype=np.float64)
            stages.create_dataset(stage, data=per_cycle)
        if record.images:
            g.create_dataset("images", data=np.stack(record.images), compression="gzip")

    _write_group(path, fill)


def write_shot_fault(path: str | Path, message: str, *, config: SystemConfig | None = None,
                     outcome: str = "fault") -> None:
    """Record a shot that produced no ``ShotRecord`` (it failed, or was skipped) in the shot file."""

    def fill(g: h5py.Group) -> None:
        g.attrs["outcome"] = outcome
        g.attrs["success"] = False
        g.attrs["fault"] = message
        g.attrs["n_cycles"] = 0
        if config is not None:
            g.attrs["config"] = config.model_dump_json()
            g.attrs["config_digest"] = config.digest()

    _write_group(Path(path), fill)


def read_shot_results(path: str | Path) -> dict[str, Any]:
    """``/results/llrs`` as plain Python (attributes, datasets as arrays, ``stage_s`` as a dict)."""
    path = Path(path)
    with _open_h5(path, "r") as f:
        if RESULTS_GROUP not in f:
            raise ShotFileError(f"{path}: no LLRS results")
        g = f[RESULTS_GROUP]
        out: dict[str, Any] = {k: _plain(v) for k, v in g.attrs.items()}
        for name, item in g.items():
            if isinstance(item, h5py.Group):
                out[name] = {k: v[()] for k, v in item.items()}
            else:
                out[name] = item[()]
        return out


def run_shot_file(
    path: str | Path,
    run_shot: Callable[[SystemConfig | None], ShotRecord],
    base_config: SystemConfig | None = None,
) -> ShotRecord | None:
    """Run the shot a labscript file describes and write its results into that file.

    Reads ``/globals``, refuses a file that already holds results (before running anything), builds the
    shot's configuration from ``base_config`` (the engine's current one) and the ``llrs_`` globals, calls
    ``run_shot(config_or_None)``, and writes the record. ``llrs_enabled = False`` skips the shot (recorded as
    outcome ``skipped``; returns ``None``). If ``run_shot`` raises, the fault is written into the file and
    the exception propagates.
    """
    path = Path(path)
    globals_ = read_shot_globals(path)
    with _open_h5(path, "r+") as f:
        _refuse_existing(f, path)
    used = {k: v for k, v in globals_.items() if k.startswith("llrs_")}
    config = shot_config(base_config, globals_, source=str(path))
    applied = config if config is not None else base_config
    if not bool(globals_.get("llrs_enabled", True)):
        write_shot_fault(
            path, "llrs_enabled is false: no rearrangement in this shot", config=applied, outcome="skipped"
        )
        return None
    try:
        record = run_shot(config)
    except Exception as err:
        write_shot_fault(path, f"{type(err).__name__}: {err}", config=applied)
        raise
    write_shot_results(path, record, config=applied, globals_used=used)
    return record
