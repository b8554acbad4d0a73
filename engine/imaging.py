"""Module II: from a camera frame to trap occupancy.

Per trap, a PSF-weighted sum of the pixels in a small box (the matched filter of ``engine.psf``), then a
per-trap threshold. Both steps are numba kernels over buffers the ``Detector`` allocates once at configure
time, so a cycle allocates nothing and never waits on the GIL; numpy references of both are kept for tests.

Thresholds come from, in order: an explicit array/scalar, ``imaging.threshold`` in the config, or the
camera model (``model_threshold``). ``calibrate_threshold`` fits measured sums instead (see
``engine.imaging_calibration``).
"""

from __future__ import annotations

import numba
import numpy as np

from engine.config import SystemConfig
from engine.imaging_calibration import (
    ThresholdCalibration,
    calibrate_threshold,
    fit_psf,
    min_error_threshold,
    model_sum_statistics,
)
from engine.psf import PsfModel, psf_from_config

__all__ = [
    "Detector",
    "PsfModel",
    "ThresholdCalibration",
    "calibrate_threshold",
    "fit_psf",
    "model_threshold",
    "psf_from_config",
    "threshold",
    "threshold_reference",
    "weighted_sums",
    "weighted_sums_reference",
]


@numba.njit(cache=True, nogil=True, fastmath=True)
def weighted_sums(image_u16: np.ndarray, pixel_idx: np.ndarray, weights: np.ndarray, out_f32: np.ndarray) -> None:
    """``out[t] = sum_k weights[t, k] * image.flat[pixel_idx[t, k]]`` (image C-contiguous)."""
    flat = image_u16.reshape(image_u16.size)
    for t in range(pixel_idx.shape[0]):
        acc = np.float32(0.0)
        for k in range(pixel_idx.shape[1]):
            acc += weights[t, k] * np.float32(flat[pixel_idx[t, k]])
        out_f32[t] = acc


@numba.njit(cache=True, nogil=True)
def threshold(counts: np.ndarray, thresholds: np.ndarray, out_bool: np.ndarray) -> None:
    """``out.flat[t] = counts[t] > thresholds[t]`` (strictly above, as the reference); ``out`` any C shape."""
    out = out_bool.reshape(out_bool.size)
    for t in range(counts.shape[0]):
        out[t] = counts[t] > thresholds[t]


def weighted_sums_reference(image: np.ndarray, pixel_idx: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Plain-numpy ``weighted_sums`` (float64 accumulation)."""
    return (image.reshape(-1)[pixel_idx].astype(np.float64) * weights).sum(axis=1)


def threshold_reference(counts: np.ndarray, thresholds: np.ndarray) -> np.ndarray:
    """Plain-numpy ``threshold``."""
    return counts > thresholds


def model_threshold(config: SystemConfig, psf: PsfModel, *, fraction_filled: float = 0.5) -> np.ndarray:
    """Per-trap thresholds from the camera model: the minimum-error point between the predicted empty and
    filled weighted-sum distributions (moment-matched shifted gammas, EMCCD statistics included)."""
    empty, atom = model_sum_statistics(config.camera, psf)
    return min_error_threshold(empty, atom, fraction_filled)


class Detector:
    """Frame -> occupancy for one configuration; owns every buffer and compiles its kernels on construction.

    ``detect(image, out)`` = ``sum(image)`` (stage II.detect) + ``classify(out)`` (stage II.threshold).
    ``counts`` holds the last weighted sums (``float32[n_traps]``); calibration collects them.
    """

    def __init__(
        self,
        config: SystemConfig,
        *,
        psf: PsfModel | None = None,
        thresholds: float | np.ndarray | None = None,
    ) -> None:
        self.config = config
        self.psf = psf if psf is not None else psf_from_config(config)
        self.frame_shape = self.psf.frame_shape
        self.n_traps = config.array.n_traps
        if self.psf.pixel_idx.shape[0] != self.n_traps:
            raise ValueError(f"psf has {self.psf.pixel_idx.shape[0]} traps, config has {self.n_traps}")
        self._pixel_idx = np.ascontiguousarray(self.psf.pixel_idx, dtype=np.int64)
        self._weights = np.ascontiguousarray(self.psf.weights, dtype=np.float32)
        self.counts = np.zeros(self.n_traps, dtype=np.float32)
        self.thresholds = np.empty(self.n_traps, dtype=np.float32)
        if thresholds is None:
            thresholds = config.imaging.threshold
        if thresholds is None:
            thresholds = model_threshold(config, self.psf)
        self.set_thresholds(thresholds)
        self._warm_up()

    def set_thresholds(self, thresholds: float | np.ndarray) -> None:
        """Replace the thresholds (a scalar is broadcast to every trap); between shots only."""
        values = np.broadcast_to(np.asarray(thresholds, dtype=np.float32), (self.n_traps,))
        if not np.all(np.isfinite(values)):
            raise ValueError("thresholds must be finite")
        self.thresholds[:] = values

    def sum(self, image: np.ndarray) -> None:
        """Weighted sums of ``image`` (``uint16[h, w]``, C-contiguous) into ``self.counts``."""
        if image.shape != self.frame_shape or image.dtype != np.uint16 or not image.flags.c_contiguous:
            raise ValueError(f"image must be a C-contiguous uint16 array of shape {self.frame_shape}")
        weighted_sums(image, self._pixel_idx, self._weights, self.counts)

    def classify(self, out_occupancy: np.ndarray) -> None:
        """Threshold ``self.counts`` into ``out_occupancy`` (``bool[ny, nx]`` or ``bool[n_traps]``)."""
        if out_occupancy.size != self.n_traps or out_occupancy.dtype != np.bool_ or not out_occupancy.flags.c_contiguous:
            raise ValueError(f"out_occupancy must be a C-contiguous bool array with {self.n_traps} elements")
        threshold(self.counts, self.thresholds, out_occupancy)

    def detect(self, image: np.ndarray, out_occupancy: np.ndarray) -> None:
        """Occupancy of every trap in ``image``, written into ``out_occupancy``."""
        self.sum(image)
        self.classify(out_occupancy)

    def _warm_up(self) -> None:
        """Compile (or load from cache) both kernels for the exact argument types used in a cycle."""
        self.sum(np.zeros(self.frame_shape, dtype=np.uint16))
        self.classify(np.zeros((self.config.array.ny, self.config.array.nx), dtype=bool))
        self.classify(np.zeros(self.n_traps, dtype=bool))
        self.counts[:] = 0
