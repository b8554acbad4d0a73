"""Module II calibration for the lab server: fit a threshold or a PSF to fresh frames, say how good it is, and
express the result as a configuration change, so that applying it is an ordinary (validated, recorded) config
update and every later shot's run file holds the calibration it used.

The fits themselves are the engine's (``engine.imaging_calibration``); this module only prepares their input
from frames and compares the result with what is in use now, on the same frames.
"""

from __future__ import annotations

import numpy as np

from engine.config import SystemConfig
from engine.imaging import model_threshold, weighted_sums_reference
from engine.imaging_calibration import Population, ThresholdCalibration, calibrate_threshold, error_probability, fit_psf
from engine.psf import PsfModel, psf_from_config

__all__ = ["MIN_SEPARATION", "psf_calibration", "threshold_calibration", "weighted_sums"]

#: The fitted populations must be this many (combined) standard deviations apart to be called empty and filled
#: traps: frames of an empty (or a full) array still split into two noise "populations" about one apart.
MIN_SEPARATION = 4.0


def weighted_sums(images: np.ndarray, psf: PsfModel) -> np.ndarray:
    """``float64[n_images, n_traps]``: the detector's PSF-weighted sums of every frame."""
    return np.stack([weighted_sums_reference(np.ascontiguousarray(img), psf.pixel_idx, psf.weights) for img in images])


def _fidelity(counts: np.ndarray) -> float:
    return calibrate_threshold(counts).fidelity


def _two_populations(counts: np.ndarray) -> ThresholdCalibration:
    """The threshold fit of ``counts``, if they split into empty and filled traps (``MIN_SEPARATION``);
    ``ValueError`` if not: frames without atoms (or with every trap full) calibrate nothing."""
    cal = calibrate_threshold(counts)
    separation = (cal.mean_atom - cal.mean_empty) / float(np.hypot(cal.std_empty, cal.std_atom))
    if separation < MIN_SEPARATION:
        raise ValueError(
            f"the weighted sums look like a single population (the two fitted ones are only {separation:.1f} "
            f"standard deviations apart, {MIN_SEPARATION:g} needed); image a partly loaded array to calibrate"
        )
    return cal


def threshold_calibration(images: np.ndarray, config: SystemConfig) -> dict:
    """Fit the occupancy threshold to the weighted sums of ``images`` (``uint16[k, h, w]``) under ``config``'s PSF.

    Returns the fields of ``server.models.ThresholdCalibrationOut`` that describe the fit (no id, no digest).
    ``current_fidelity`` evaluates the threshold in use now (the config's, or the camera model's per trap)
    under the same fitted populations, so the two fidelities are directly comparable.
    """
    psf = psf_from_config(config)
    cal = _two_populations(weighted_sums(images, psf))
    empty = Population(np.float64(cal.mean_empty), np.float64(cal.std_empty), np.float64(cal.skew_empty))
    atom = Population(np.float64(cal.mean_atom), np.float64(cal.std_atom), np.float64(cal.skew_atom))
    if config.imaging.threshold is not None:
        current = np.full(config.array.n_traps, float(config.imaging.threshold))
    else:
        current = np.asarray(model_threshold(config, psf), dtype=np.float64)
    current_error = float(np.mean(error_probability(current, empty, atom, cal.fraction_filled)))
    return {
        "kind": "threshold",
        "images": int(len(images)),
        "threshold": cal.threshold,
        "fidelity": cal.fidelity,
        "current_threshold": float(current.mean()),
        "current_fidelity": 1.0 - current_error,
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
    _two_populations(weighted_sums(images, nominal))  # a PSF is fitted to atoms: refuse frames without any
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
