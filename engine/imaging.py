"""Module II: from a camera frame to trap occupancy.

Per trap, a PSF-weighted sum of the pixels in a small box (the matched filter of ``engine.psf``), then a
per-trap threshold. Both steps are numba kernels over buffers the ``Detector`` allocates once at configure
time, so a cycle allocates nothing and never waits on the GIL; numpy references of both are kept for tests.

The sums read a ``BoxLayout`` the ``Detector`` derives from the PSF model's per-pixel index table: per trap
the flat index of its box's top-left pixel and dense weights, the boxes sorted in frame memory order. With
2048 traps the index table alone (800 KB) overflowed the 1 MB L2 cache beside the frame; the box rows are
read as runs of adjacent pixels, ``SIMD_LANES`` at a time.

Thresholds come from, in order: an explicit array/scalar, ``imaging.threshold`` in the config, or, when
both are absent, ``Detector.calibrate`` on frames (the engine takes ``calibration_frames`` of them when it
applies such a configuration): the two-population fit of ``engine.imaging_calibration``. Never from a model
of the camera: the engine's detection parameters are its own, measured, not read from a simulator.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from engine.config import SystemConfig
from engine.imaging_calibration import ThresholdCalibration, calibrate_threshold, fit_psf
from engine.psf import PsfModel, psf_from_config

__all__ = [
    "BoxLayout",
    "Detector",
    "PsfModel",
    "SIMD_LANES",
    "ThresholdCalibration",
    "box_sums",
    "calibrate_threshold",
    "calibration_frames",
    "fit_psf",
    "psf_from_config",
    "threshold",
    "threshold_reference",
    "weighted_sums_reference",
]


SIMD_LANES = 8
"""Pixels the detection kernel converts, weighs and adds with one vector instruction each (8 float32 = AVX2)."""


@intrinsic
def _box_dot(  # noqa: ANN202 - a numba typing hook: arguments are numba types
    typingctx, pixels_u16, first_px, row_stride_px, weights_f32, first_weight, box_rows, row_px  # noqa: ANN001
):
    """One trap's weighted sum: ``sum_{r < box_rows, c < row_px} weights[first_weight + r * row_px + c] *
    pixels[first_px + r * row_stride_px + c]`` over 1D C-contiguous ``uint16``/``float32`` arrays.

    Why an intrinsic: numba turns LLVM's SLP vectoriser off and its loop vectoriser only takes loops much
    longer than a box row, so a plain loop compiles to a serial chain of scalar converts and multiply-adds.
    Here each ``SIMD_LANES`` pixels are one vector load, convert and multiply-add into a vector accumulator,
    summed across lanes once per trap. ``row_px`` must be a multiple of ``SIMD_LANES`` and every index in
    range; ``BoxLayout`` guarantees both, nothing here checks.
    """
    vector_u16 = ir.VectorType(ir.IntType(16), SIMD_LANES)
    vector_f32 = ir.VectorType(ir.FloatType(), SIMD_LANES)

    def codegen(context, builder, signature, args):  # noqa: ANN001, ANN202 - llvmlite objects
        pixels_arg, first_px, row_stride_px, weights_arg, first_weight, box_rows, row_px = args
        pixels = context.make_array(signature.args[0])(context, builder, pixels_arg)
        weights = context.make_array(signature.args[3])(context, builder, weights_arg)
        acc = cgutils.alloca_once_value(builder, ir.Constant(vector_f32, None))
        lanes = ir.Constant(row_px.type, SIMD_LANES)
        with cgutils.for_range(builder, box_rows) as row:
            row_first_px = builder.add(first_px, builder.mul(row.index, row_stride_px))
            row_first_weight = builder.add(first_weight, builder.mul(row.index, row_px))
            with cgutils.for_range(builder, builder.udiv(row_px, lanes)) as chunk:
                column = builder.mul(chunk.index, lanes)
                pixel_at = builder.gep(pixels.data, [builder.add(row_first_px, column)], inbounds=True)
                weight_at = builder.gep(weights.data, [builder.add(row_first_weight, column)], inbounds=True)
                pixel_vector = builder.load(builder.bitcast(pixel_at, vector_u16.as_pointer()), align=2)
                weight_vector = builder.load(builder.bitcast(weight_at, vector_f32.as_pointer()), align=4)
                products = builder.fmul(builder.uitofp(pixel_vector, vector_f32), weight_vector, flags=("fast",))
                builder.store(builder.fadd(builder.load(acc), products, flags=("fast",)), acc)
        reduce_add = cgutils.get_or_insert_function(
            builder.module,
            ir.FunctionType(ir.FloatType(), [ir.FloatType(), vector_f32]),
            f"llvm.vector.reduce.fadd.v{SIMD_LANES}f32",
        )
        return builder.call(reduce_add, [ir.Constant(ir.FloatType(), 0.0), builder.load(acc)], fastmath=("fast",))

    index = types.intp
    return types.float32(pixels_u16, index, index, weights_f32, index, index, index), codegen


@dataclass(frozen=True)
class BoxLayout:
    """The per-trap weights as boxes of contiguous pixel rows, in the order the frame lies in memory.

    Box ``i`` belongs to trap ``trap[i]``; its row ``r`` is the ``row_px`` adjacent pixels that start at flat
    index ``origin_px[i] + r * width``, weighted by ``weights[i, r]`` (``float32[n, box_rows, row_px]``).
    ``row_px`` is the box width rounded up to whole ``SIMD_LANES``; the extra pixels weigh 0. Every read stays
    inside the frame: a box that would cross an edge is shifted inside with its weights moved along, so the
    kernel needs no index table and no bounds check. Boxes are sorted by ``origin_px``, so the frame is swept
    once from top to bottom, each cache line fetched once and in an order the hardware prefetcher follows.
    """

    origin_px: np.ndarray
    trap: np.ndarray
    weights: np.ndarray

    @classmethod
    def from_pixels(
        cls, pixel_idx: np.ndarray, weights: np.ndarray, frame_shape: tuple[int, int], box_px: int
    ) -> BoxLayout:
        """Boxes of ``box_px`` rows and columns (at most the frame's) holding the weighted pixels of each trap.

        ``pixel_idx``/``weights`` are the general ``PsfModel`` description (any flat indices); pixels of weight
        0 are dropped, so the off-frame pixels that ``box_pixels`` clips carry over as nothing, and repeated
        indices add up, as in ``weighted_sums_reference``. Raises if a trap's weighted pixels do not fit in
        such a box, or if the frame holds fewer pixels than one padded box.
        """
        height, width = frame_shape
        box_rows, box_cols = min(box_px, height), min(box_px, width)
        row_px = -(-box_cols // SIMD_LANES) * SIMD_LANES
        last_origin_px = height * width - (box_rows - 1) * width - row_px
        if last_origin_px < 0:
            raise ValueError(f"a {height}x{width} px frame is too small for {box_rows} box rows of {row_px} px")
        n_traps = pixel_idx.shape[0]
        weighted = weights != 0
        ys, xs = np.divmod(pixel_idx, width)
        # top-left corner: the first weighted row and column, moved back inside the frame where the box would
        # cross its far edge (a trap with no weight at all gets a box of zeros at the frame's end); then moved
        # back up to row_px - box_cols pixels where the padding of the last row would run past the frame
        y0 = np.minimum(np.where(weighted, ys, height).min(axis=1), height - box_rows)
        x0 = np.minimum(np.where(weighted, xs, width).min(axis=1), width - box_cols)
        origin_px = np.minimum(y0 * width + x0, last_origin_px)
        rows = ys - y0[:, None]
        cols = pixel_idx - origin_px[:, None] - rows * width
        outside = weighted & ((rows >= box_rows) | (cols < 0) | (cols >= row_px))
        if outside.any():
            trap = int(np.flatnonzero(outside.any(axis=1))[0])
            raise ValueError(f"trap {trap}: its weighted pixels do not fit in a {box_rows}x{box_cols} px box")
        box_weights = np.zeros((n_traps, box_rows * row_px), dtype=np.float32)
        trap_of_pixel = np.broadcast_to(np.arange(n_traps)[:, None], pixel_idx.shape)
        np.add.at(box_weights, (trap_of_pixel[weighted], (rows * row_px + cols)[weighted]), weights[weighted])
        order = np.argsort(origin_px, kind="stable")
        return cls(
            origin_px=origin_px[order].astype(np.int64),
            trap=order.astype(np.int64),
            weights=box_weights[order].reshape(n_traps, box_rows, row_px),
        )


@numba.njit(cache=True, nogil=True)
def box_sums(
    image_u16: np.ndarray, origin_px: np.ndarray, trap: np.ndarray, weights: np.ndarray, out_f32: np.ndarray
) -> None:
    """``out[trap[i]] = sum_{r, c} weights[i, r, c] * image.flat[origin_px[i] + r * width + c]``: the weighted
    sums over a ``BoxLayout`` (image C-contiguous)."""
    flat = image_u16.reshape(image_u16.size)
    flat_weights = weights.reshape(weights.size)
    width = image_u16.shape[1]
    box_rows, row_px = weights.shape[1], weights.shape[2]
    for i in range(origin_px.shape[0]):
        # numba's stubs give the @intrinsic's call the typing hook's signature (typingctx first): wrong at call sites
        out_f32[trap[i]] = _box_dot(  # type: ignore[call-arg]
            flat, origin_px[i], width, flat_weights, i * box_rows * row_px, box_rows, row_px
        )


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


#: Weighted sums a threshold calibration at configure time collects: about 1,000 per population at 50 %
#: filling, so each fitted width carries ~2 % relative error (1 / sqrt(2n)) and the threshold, which sits in
#: a flat valley of the error rate, moves by a small fraction of a population's width.
CALIBRATION_READINGS = 2000


def calibration_frames(n_traps: int) -> int:
    """Frames to take for a threshold calibration of ``n_traps`` traps (at least 4, whatever the array)."""
    return max(4, -(-CALIBRATION_READINGS // n_traps))


class Detector:
    """Frame -> occupancy for one configuration; owns every buffer and compiles its kernels on construction.

    ``detect(image, out)`` = ``sum(image)`` (stage II.detect) + ``classify(out)`` (stage II.threshold).
    ``counts`` holds the last weighted sums (``float32[n_traps]``); calibration collects them. Without a
    threshold (none given, ``imaging.threshold: null``) it classifies nothing until ``calibrate(frames)``.
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
        self.boxes = BoxLayout.from_pixels(self.psf.pixel_idx, self.psf.weights, self.frame_shape, self.psf.box_px)
        self.counts = np.zeros(self.n_traps, dtype=np.float32)
        self.thresholds = np.full(self.n_traps, np.nan, dtype=np.float32)
        self.calibration: ThresholdCalibration | None = None  # the fit the thresholds came from, if any
        self.has_thresholds = False
        if thresholds is None:
            thresholds = config.imaging.threshold
        if thresholds is not None:
            self.set_thresholds(thresholds)
        # The last image and occupancy buffers that passed the checks: the engine passes the same two buffers
        # every cycle, so their checks (microseconds with cold caches) run once, not in every cycle.
        self._checked_image: np.ndarray | None = None
        self._checked_out: np.ndarray | None = None
        self._warm_up()

    def set_thresholds(self, thresholds: float | np.ndarray) -> None:
        """Replace the thresholds (a scalar is broadcast to every trap); between shots only."""
        values = np.broadcast_to(np.asarray(thresholds, dtype=np.float32), (self.n_traps,))
        if not np.all(np.isfinite(values)):
            raise ValueError("thresholds must be finite")
        self.thresholds[:] = values
        self.has_thresholds = True

    def calibrate(self, frames: np.ndarray) -> ThresholdCalibration:
        """Fit one threshold to the weighted sums of ``frames`` (``uint16[k, h, w]`` of a partly loaded array)
        and use it for every trap; returns the fit. Raises ``ValueError`` if the sums do not show an empty and
        a filled population (an empty or a full array, no light)."""
        counts = np.empty((len(frames), self.n_traps), dtype=np.float64)
        for i, frame in enumerate(frames):
            self.sum(np.ascontiguousarray(frame))
            counts[i] = self.counts
        self._checked_image = None
        calibration = calibrate_threshold(counts).require_two_populations()
        self.set_thresholds(calibration.threshold)
        self.calibration = calibration
        return calibration

    def keep_calibration(self, running: Detector | None) -> bool:
        """Take over ``running``'s calibrated threshold if it detects with the same camera settings, imaging
        settings and array as this one (a change elsewhere, e.g. of the solver, needs no new calibration);
        returns whether it did. What the engine cannot see (the atoms growing dimmer) is caught by
        calibrating again through the API, as in a lab."""
        if running is None or running.calibration is None:
            return False
        if any(getattr(running.config, key) != getattr(self.config, key) for key in ("camera", "imaging", "array")):
            return False
        self.set_thresholds(running.thresholds)
        self.calibration = running.calibration
        return True

    def sum(self, image: np.ndarray) -> None:
        """Weighted sums of ``image`` (``uint16[h, w]``, C-contiguous) into ``self.counts``."""
        if image is not self._checked_image:
            if image.shape != self.frame_shape or image.dtype != np.uint16 or not image.flags.c_contiguous:
                raise ValueError(f"image must be a C-contiguous uint16 array of shape {self.frame_shape}")
            self._checked_image = image
        boxes = self.boxes
        box_sums(image, boxes.origin_px, boxes.trap, boxes.weights, self.counts)

    def classify(self, out_occupancy: np.ndarray) -> None:
        """Threshold ``self.counts`` into ``out_occupancy`` (``bool[ny, nx]`` or ``bool[n_traps]``)."""
        if out_occupancy is not self._checked_out:
            if not self.has_thresholds:
                raise ValueError(
                    "the detector has no threshold: set imaging.threshold or calibrate it from frames "
                    "(Detector.calibrate; the engine does this when it applies imaging.threshold: null)"
                )
            if (
                out_occupancy.size != self.n_traps
                or out_occupancy.dtype != np.bool_
                or not out_occupancy.flags.c_contiguous
            ):
                raise ValueError(f"out_occupancy must be a C-contiguous bool array with {self.n_traps} elements")
            self._checked_out = out_occupancy
        threshold(self.counts, self.thresholds, out_occupancy)

    def detect(self, image: np.ndarray, out_occupancy: np.ndarray) -> None:
        """Occupancy of every trap in ``image``, written into ``out_occupancy``."""
        self.sum(image)
        self.classify(out_occupancy)

    def _warm_up(self) -> None:
        """Compile (or load from cache) both kernels for the exact argument types used in a cycle."""
        self.sum(np.zeros(self.frame_shape, dtype=np.uint16))
        threshold(self.counts, self.thresholds, np.zeros((self.config.array.ny, self.config.array.nx), dtype=bool))
        threshold(self.counts, self.thresholds, np.zeros(self.n_traps, dtype=bool))
        self.counts[:] = 0
        self._checked_image = self._checked_out = None
