"""Trap geometry on the camera and the per-trap PSF weights that module II sums over.

Pixel convention (shared with the simulated camera): pixel ``i`` of a frame covers ``[i - 0.5, i + 0.5)``,
so a pixel's centre sits at an integer coordinate. ``CameraConfig.trap_pixel_xy`` is in *sensor* pixels of
the ROI (before binning); a frame binned by ``(bx, by)`` has its own pixels, and a sensor coordinate ``x``
maps to frame coordinate ``(x + 0.5) / bx - 0.5``. In frame pixels the PSF is a Gaussian of
``sigma / bx`` by ``sigma / by`` integrated over a unit pixel, exactly as on the sensor.

Weights layout: ``pixel_idx int64[n_traps, box*box]`` holds row-major flat indices into the frame,
``weights float32[n_traps, box*box]`` the matching weights. Box pixels that fall outside the frame keep a valid
index (clipped) and weight 0. This is the general description that calibration and the numpy reference read;
the detection kernel reads boxes of contiguous pixel rows that ``engine.imaging.BoxLayout`` derives from it
once per configuration (edge boxes shifted inside the frame, off-frame weights dropped).

Why the weights are the PSF normalised to sum 1: for an empty trap the noise is the same in every pixel
(background and read noise), and the linear estimator of an atom's brightness with the best signal-to-noise
ratio under uniform noise is the matched filter, weights proportional to the PSF. Normalising the sum to 1
keeps the weighted sum in "counts per pixel": an empty trap reads ``bias + background`` whatever the box size,
which makes thresholds readable and comparable across configurations.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import ndtr

from engine.config import CameraConfig, SystemConfig

__all__ = [
    "PsfModel",
    "box_pixels",
    "box_psf",
    "frame_shape",
    "pixel_fractions",
    "psf_from_config",
    "sensor_to_frame_px",
    "trap_positions_px",
]


def frame_shape(camera: CameraConfig) -> tuple[int, int]:
    """``(height, width)`` of a frame after ROI and binning; ``binning`` is ``(x, y)`` like every other pair
    in the camera config. Sensor rows/columns that do not fill a whole bin are not read out."""
    bx, by = camera.binning
    h, w = camera.roi_height_px // by, camera.roi_width_px // bx
    if h == 0 or w == 0:
        raise ValueError(
            f"camera: binning {camera.binning} is larger than the {camera.roi_width_px}x{camera.roi_height_px} ROI"
        )
    return h, w


def trap_positions_px(config: SystemConfig) -> np.ndarray:
    """Sensor-pixel ``(x, y)`` of every trap, ``float64[n_traps, 2]`` in flat trap order (``row * nx + col``)."""
    nx, ny = config.array.nx, config.array.ny
    rows, cols = np.divmod(np.arange(nx * ny), nx)
    cam = config.camera
    x = cam.origin_px[0] + cols * cam.col_step_px[0] + rows * cam.row_step_px[0]
    y = cam.origin_px[1] + cols * cam.col_step_px[1] + rows * cam.row_step_px[1]
    return np.stack([x, y], axis=1).astype(np.float64)


def sensor_to_frame_px(xy_sensor: np.ndarray, binning: tuple[int, int]) -> np.ndarray:
    """Map sensor-pixel coordinates to coordinates in the binned frame (see the module docstring)."""
    b = np.asarray(binning, dtype=np.float64)
    return (np.asarray(xy_sensor, dtype=np.float64) + 0.5) / b - 0.5


def pixel_fractions(centre: np.ndarray, sigma: float | np.ndarray, pixels: np.ndarray) -> np.ndarray:
    """Fraction of a 1D Gaussian (``centre``, ``sigma``) that falls on each pixel ``[p - 0.5, p + 0.5)``.

    Broadcasts ``centre``/``sigma`` against ``pixels``; integrating over the pixel (rather than sampling the
    Gaussian at its centre) keeps the model right for the ~1 px PSFs of a tweezer array.
    """
    return ndtr((pixels + 0.5 - centre) / sigma) - ndtr((pixels - 0.5 - centre) / sigma)


def box_pixels(
    centres_xy: np.ndarray, box_px: int, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The ``box_px`` square box of frame pixels centred on the pixel nearest to each centre.

    Returns pixel columns ``xs int64[n, box]``, rows ``ys int64[n, box]``, in-frame mask ``bool[n, box, box]``
    and row-major flat indices ``int64[n, box*box]`` (off-frame pixels clipped to a valid index).
    """
    h, w = shape
    offsets = np.arange(box_px) - box_px // 2
    xs = np.floor(centres_xy[:, :1] + 0.5).astype(np.int64) + offsets
    ys = np.floor(centres_xy[:, 1:2] + 0.5).astype(np.int64) + offsets
    inside = ((ys >= 0) & (ys < h))[:, :, None] & ((xs >= 0) & (xs < w))[:, None, :]
    idx = np.clip(ys, 0, h - 1)[:, :, None] * w + np.clip(xs, 0, w - 1)[:, None, :]
    return xs, ys, inside, idx.reshape(centres_xy.shape[0], box_px * box_px)


def box_psf(
    centres_xy: np.ndarray, sigma_xy: tuple[float, float], box_px: int, shape: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray]:
    """Pixel indices and PSF light fractions of a ``box_px`` square box around each centre.

    Returns ``pixel_idx int64[n, box*box]`` and the *unnormalised* fraction of the atom's light on each box
    pixel, ``float64[n, box*box]`` (0 off-frame).
    """
    xs, ys, inside, idx = box_pixels(centres_xy, box_px, shape)
    fx = pixel_fractions(centres_xy[:, :1], sigma_xy[0], xs)
    fy = pixel_fractions(centres_xy[:, 1:2], sigma_xy[1], ys)
    frac = fy[:, :, None] * fx[:, None, :] * inside
    return idx, frac.reshape(idx.shape)


@dataclass(frozen=True)
class PsfModel:
    """Per-trap detection weights plus the PSF parameters they were built from.

    ``sigma_px`` is the isotropic Gaussian sigma in *sensor* pixels (comparable with
    ``CameraConfig.psf_sigma_px``); ``centres_xy`` are trap centres in *frame* pixels, ``float64[n, 2]``.
    """

    pixel_idx: np.ndarray
    weights: np.ndarray
    light_fraction: np.ndarray
    sigma_px: float
    centres_xy: np.ndarray
    box_px: int
    frame_shape: tuple[int, int]

    @classmethod
    def build(
        cls, centres_xy: np.ndarray, sigma_px: float, camera: CameraConfig, box_px: int
    ) -> PsfModel:
        """Matched-filter weights (PSF normalised to sum 1 over the in-frame box pixels)."""
        shape = frame_shape(camera)
        bx, by = camera.binning
        idx, frac = box_psf(centres_xy, (sigma_px / bx, sigma_px / by), box_px, shape)
        total = frac.sum(axis=1, keepdims=True)
        if np.any(total <= 0):
            raise ValueError("a trap's PSF box lies entirely outside the frame; check the trap geometry and ROI")
        weights = (frac / total).astype(np.float32)
        return cls(idx, weights, frac, float(sigma_px), np.array(centres_xy, dtype=np.float64), box_px, shape)


def psf_from_config(config: SystemConfig) -> PsfModel:
    """The nominal PSF model: Gaussian of ``camera.psf_sigma_px`` at the configured trap positions."""
    centres = sensor_to_frame_px(trap_positions_px(config), config.camera.binning)
    return PsfModel.build(centres, config.camera.psf_sigma_px, config.camera, config.imaging.psf_box_px)
