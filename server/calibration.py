"""Module II calibration for the lab server: fit a threshold or a PSF to fresh frames, say how good it is, and
express the result as a configuration change, so that applying it is an ordinary (validated, recorded) config
update and every later shot's run file holds the calibration it used.

The fits themselves are the engine's (``engine.imaging_calibration``); this module only prepares their input
from frames and compares the result with what is in use now, on the same frames. ``CalibrationBook`` holds
the fitted results under ids until a person applies one (the lab service composes it).
"""

from __future__ import annotations

import itertools
import threading
from collections import OrderedDict
from collections.abc import Callable
from typing import Any

import numpy as np

from engine.config import SystemConfig
from engine.imaging import weighted_sums_reference
from engine.imaging_calibration import Population, calibrate_threshold, error_probability, fit_psf
from engine.psf import PsfModel, psf_from_config

__all__ = [
    "MAX_CALIBRATION_BYTES",
    "CalibrationBook",
    "CalibrationConflict",
    "CalibrationFailed",
    "UnknownCalibration",
    "fitted",
    "frame_budget_problem",
    "psf_calibration",
    "threshold_calibration",
    "weighted_sums",
]

#: Frames one calibration may acquire, in bytes of uint16 pixels (each process holds them, and the fits
#: make float copies): 40 frames of a 1024 x 1024 ROI fit, 500 frames of 4096 x 4096 do not.
MAX_CALIBRATION_BYTES = 128 * 2**20


class CalibrationConflict(RuntimeError):
    """A calibration cannot be applied: the configuration changed since its frames were taken."""


class CalibrationFailed(RuntimeError):
    """The calibration frames could not be fitted (e.g. no atoms were loaded in them)."""


class UnknownCalibration(LookupError):
    """No calibration with that id is held."""

    def __str__(self) -> str:
        return f"no calibration {self.args[0]!r}"


def weighted_sums(images: np.ndarray, psf: PsfModel) -> np.ndarray:
    """``float64[n_images, n_traps]``: the detector's PSF-weighted sums of every frame."""
    return np.stack([weighted_sums_reference(np.ascontiguousarray(img), psf.pixel_idx, psf.weights) for img in images])


def _fidelity(counts: np.ndarray) -> float:
    return calibrate_threshold(counts).fidelity


def threshold_calibration(images: np.ndarray, config: SystemConfig) -> dict:
    """Fit the occupancy threshold to the weighted sums of ``images`` (``uint16[k, h, w]``) under ``config``'s PSF.

    Returns the fields of ``server.models.ThresholdCalibrationOut`` that describe the fit (no id, no digest).
    ``current_fidelity`` evaluates the configured threshold under the same fitted populations, so the two
    fidelities (1 - predicted detection error) are directly comparable. With ``imaging.threshold: null``
    there is no fixed threshold to compare (the engine fitted one to frames when the configuration was
    applied): both current fields are None, and applying the result fixes the threshold in the config.
    """
    psf = psf_from_config(config)
    counts = weighted_sums(images, psf)
    cal = calibrate_threshold(counts).require_two_populations()
    current_threshold = current_fidelity = None
    if config.imaging.threshold is not None:
        empty = Population(np.float64(cal.mean_empty), np.float64(cal.std_empty), np.float64(cal.skew_empty))
        atom = Population(np.float64(cal.mean_atom), np.float64(cal.std_atom), np.float64(cal.skew_atom))
        current_threshold = float(config.imaging.threshold)
        current_error = error_probability(np.float64(current_threshold), empty, atom, cal.fraction_filled)
        current_fidelity = 1.0 - float(current_error)
    return {
        "kind": "threshold",
        "images": int(len(images)),
        "threshold": cal.threshold,
        "fidelity": cal.fidelity,
        "current_threshold": current_threshold,
        "current_fidelity": current_fidelity,
        "fraction_filled": cal.fraction_filled,
        "mean_empty": cal.mean_empty,
        "mean_atom": cal.mean_atom,
        "std_empty": cal.std_empty,
        "std_atom": cal.std_atom,
        "apply_patch": {"imaging": {"threshold": round(cal.threshold, 3)}},
    }


def _fit_lattice(xy: np.ndarray, rows: np.ndarray, cols: np.ndarray, config: SystemConfig) -> tuple[np.ndarray, ...]:
    """Least-squares ``xy = origin + col * col_step + row * row_step`` (a step the array cannot show, e.g. the
    row step of a chain, keeps its configured value). Returns origin, col_step, row_step (each ``(x, y)``)."""
    cam = config.camera
    col_step = np.asarray(cam.col_step_px, dtype=np.float64)
    row_step = np.asarray(cam.row_step_px, dtype=np.float64)
    fit_cols = np.unique(cols).size > 1
    fit_rows = np.unique(rows).size > 1
    known = xy - (0 if fit_cols else cols[:, None] * col_step) - (0 if fit_rows else rows[:, None] * row_step)
    design = [np.ones_like(rows, dtype=np.float64)]
    if fit_cols:
        design.append(cols.astype(np.float64))
    if fit_rows:
        design.append(rows.astype(np.float64))
    solution, *_ = np.linalg.lstsq(np.stack(design, axis=1), known, rcond=None)
    origin = solution[0]
    k = 1
    if fit_cols:
        col_step = solution[k]
        k += 1
    if fit_rows:
        row_step = solution[k]
    return origin, col_step, row_step


def psf_calibration(images: np.ndarray, config: SystemConfig) -> dict:
    """Fit the PSF (shared sigma and trap centres) to ``images``, then the trap lattice to the centres.

    The config change it proposes sets ``camera.psf_sigma_px`` and the lattice (``origin_px``, ``col_step_px``,
    ``row_step_px``); both fidelities are measured on the same frames, with the detection weights of the
    proposed configuration and of the current one. Returns the fields of ``server.models.PsfCalibrationOut``
    that describe the fit.
    """
    cam = config.camera
    nominal = psf_from_config(config)
    calibrate_threshold(weighted_sums(images, nominal)).require_two_populations()  # a PSF is fitted to atoms
    fitted = fit_psf(images, config)
    binning = np.asarray(cam.binning, dtype=np.float64)
    to_sensor = lambda frame_xy: (frame_xy + 0.5) * binning - 0.5  # noqa: E731 - inverse of sensor_to_frame_px
    moved = np.any(fitted.centres_xy != nominal.centres_xy, axis=1)
    if not moved.any():
        raise ValueError("no trap held an atom in the calibration frames; cannot fit the PSF")
    centres = to_sensor(fitted.centres_xy)
    rows, cols = np.divmod(np.arange(config.array.n_traps), config.array.nx)
    origin, col_step, row_step = _fit_lattice(centres[moved], rows[moved], cols[moved], config)
    lattice = origin + cols[:, None] * col_step + rows[:, None] * row_step
    residual = np.linalg.norm(centres[moved] - lattice[moved], axis=1)
    shift = np.linalg.norm(centres[moved] - to_sensor(nominal.centres_xy)[moved], axis=1)
    patch = {
        "camera": {
            "psf_sigma_px": round(fitted.sigma_px, 4),
            "origin_px": [round(float(v), 3) for v in origin],
            "col_step_px": [round(float(v), 4) for v in col_step],
            "row_step_px": [round(float(v), 4) for v in row_step],
        }
    }
    data = config.model_dump(mode="json")
    data["camera"].update(patch["camera"])
    proposed = SystemConfig.model_validate(data)  # raises if the fitted lattice leaves the ROI
    return {
        "kind": "psf",
        "images": int(len(images)),
        "sigma_px": fitted.sigma_px,
        "current_sigma_px": cam.psf_sigma_px,
        "origin_px": [float(v) for v in origin],
        "col_step_px": [float(v) for v in col_step],
        "row_step_px": [float(v) for v in row_step],
        "lattice_rms_px": float(np.sqrt(np.mean(residual**2))),
        "max_shift_px": float(shift.max()),
        "traps_fitted": int(moved.sum()),
        "fidelity": _fidelity(weighted_sums(images, psf_from_config(proposed))),
        "current_fidelity": _fidelity(weighted_sums(images, nominal)),
        "apply_patch": patch,
    }


def frame_budget_problem(images: int, config: SystemConfig) -> str | None:
    """Why ``images`` frames of ``config``'s ROI are too many for one calibration (``None``: they are not)."""
    frame_bytes = 2 * config.camera.roi_width_px * config.camera.roi_height_px
    if images * frame_bytes <= MAX_CALIBRATION_BYTES:
        return None
    return (
        f"{images} frames of {frame_bytes} bytes exceed {MAX_CALIBRATION_BYTES} bytes; "
        f"ask for at most {MAX_CALIBRATION_BYTES // frame_bytes} frames with this ROI"
    )


def fitted(
    kind: str, fit: Callable[[np.ndarray, SystemConfig], dict[str, Any]], frames: np.ndarray, config: SystemConfig
) -> dict[str, Any]:
    """``fit(frames, config)``; frames that cannot be fitted raise ``CalibrationFailed`` naming the ``kind``."""
    try:
        return fit(frames, config)
    except ValueError as err:
        raise CalibrationFailed(f"{kind} calibration failed: {err}") from None


class CalibrationBook:
    """The newest ``kept`` calibration results, each under an id with the digest of the configuration its
    frames were taken under, and whether it has been applied. Callers get copies, never the held dicts."""

    def __init__(self, kept: int = 32) -> None:
        self._kept = kept
        self._lock = threading.Lock()
        self._held: OrderedDict[str, dict[str, Any]] = OrderedDict()
        self._ids = itertools.count(1)

    def keep(self, result: dict[str, Any], config: SystemConfig) -> dict[str, Any]:
        """Hold a fit's ``result`` (taken under ``config``), not applied, under a new id ``<kind>-<n>``."""
        result = {
            "id": f"{result['kind']}-{next(self._ids)}",
            "config_digest": config.digest(),
            "applied": False,
            **result,
        }
        with self._lock:
            self._held[result["id"]] = result
            while len(self._held) > self._kept:
                self._held.popitem(last=False)
            return dict(result)

    def all(self) -> list[dict[str, Any]]:
        """Calibrations held (newest last)."""
        with self._lock:
            return [dict(c) for c in self._held.values()]

    def to_apply(self, calibration_id: str, running_digest: str) -> dict[str, Any]:
        """The held calibration ``calibration_id``, checked for applying under the configuration whose digest
        is ``running_digest`` (one already applied is returned as it is).

        ``UnknownCalibration``: no such id. ``CalibrationConflict``: its frames were taken under another
        configuration."""
        with self._lock:
            cal = self._held.get(calibration_id)
            if cal is None:
                raise UnknownCalibration(calibration_id)
            cal = dict(cal)
        if not cal["applied"] and cal["config_digest"] != running_digest:
            raise CalibrationConflict(
                f"calibration {calibration_id} was fitted under configuration {cal['config_digest']}, "
                f"but {running_digest} is running now; calibrate again"
            )
        return cal

    def mark_applied(self, calibration: dict[str, Any]) -> dict[str, Any]:
        """Note that ``calibration`` (from ``to_apply``) is applied; returns it as now held."""
        with self._lock:
            held = self._held.get(calibration["id"], calibration)
            held["applied"] = True
            return dict(held)
