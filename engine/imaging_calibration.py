"""Module II calibration, run between shots: threshold from measured sums, PSF from calibration images, and
the camera-model statistics that give a threshold before any calibration exists.

The threshold is the point that minimises the probability of a wrong assignment (paper Sec. II, after
Cooper 2024): where ``P(filled) p_filled(s) = P(empty) p_empty(s)``. Each population is approximated by a
Gaussian; the weighted sum over ~50 pixels makes that a fair approximation of the EMCCD statistics near the
threshold, and the fidelity it reports is ``1 - P(error)`` under that approximation.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.special import ndtr

from engine.config import CameraConfig, SystemConfig
from engine.psf import PsfModel, box_pixels, frame_shape, pixel_fractions, psf_from_config

__all__ = [
    "ThresholdCalibration",
    "calibrate_threshold",
    "fit_psf",
    "min_error_threshold",
    "model_sum_statistics",
]

EM_EXCESS_NOISE_FACTOR = 2.0  # variance of a high-gain EM register's output: 2 * n * gain**2
ADC_QUANTISATION_VAR = 1.0 / 12.0


@dataclass(frozen=True)
class ThresholdCalibration:
    """A two-population fit of weighted sums and the minimum-error threshold it implies."""

    threshold: float
    fidelity: float
    mean_empty: float
    mean_atom: float
    std_empty: float
    std_atom: float
    fraction_filled: float


def _log_normal_pdf(x: np.ndarray, mean: np.ndarray, std: np.ndarray) -> np.ndarray:
    return -0.5 * ((x - mean) / std) ** 2 - np.log(std) - 0.5 * math.log(2 * math.pi)


def _normal_pdf(u: np.ndarray) -> np.ndarray:
    return np.exp(-0.5 * u**2) / math.sqrt(2 * math.pi)


def min_error_threshold(
    mean_empty: np.ndarray | float,
    std_empty: np.ndarray | float,
    mean_atom: np.ndarray | float,
    std_atom: np.ndarray | float,
    fraction_filled: float,
) -> np.ndarray:
    """Where the weighted Gaussian densities of the two populations cross, between the two means (bisection,
    vectorised over traps; at an end if one population dominates everywhere in between)."""
    m0, s0, m1, s1 = np.broadcast_arrays(*(np.asarray(v, dtype=np.float64) for v in (mean_empty, std_empty, mean_atom, std_atom)))
    log_ratio_prior = math.log(fraction_filled) - math.log1p(-fraction_filled)
    lo, hi = m0.copy(), m1.copy()
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        atom_wins = log_ratio_prior + _log_normal_pdf(mid, m1, s1) - _log_normal_pdf(mid, m0, s0) > 0
        hi = np.where(atom_wins, mid, hi)
        lo = np.where(atom_wins, lo, mid)
    return 0.5 * (lo + hi)


def _error_probability(t: float, m0: float, s0: float, m1: float, s1: float, p1: float) -> float:
    return float((1 - p1) * ndtr(-(t - m0) / s0) + p1 * ndtr((t - m1) / s1))


def calibrate_threshold(counts: np.ndarray, *, max_iterations: int = 500) -> ThresholdCalibration:
    """Fit two Gaussians to weighted sums (any shape, e.g. ``[n_images, n_traps]``) by expectation-maximisation
    and return the minimum-error threshold with its fidelity estimate.

    The fit starts from a split halfway between the 2nd and 98th percentiles, which lies between the
    populations for any filling fraction between a few percent and ~95 %.
    """
    x = np.asarray(counts, dtype=np.float64).ravel()
    x = x[np.isfinite(x)]
    if x.size < 20:
        raise ValueError(f"calibrate_threshold needs at least 20 finite counts (got {x.size})")
    lo, hi = np.percentile(x, [2.0, 98.0])
    split = x > 0.5 * (lo + hi)
    if hi <= lo or split.all() or not split.any():
        raise ValueError("counts look like a single population; image a partly loaded array to calibrate")
    floor = 1e-6 * (hi - lo)
    p1 = split.mean()
    m0, m1 = x[~split].mean(), x[split].mean()
    s0, s1 = max(x[~split].std(), floor), max(x[split].std(), floor)
    previous = -np.inf
    for _ in range(max_iterations):
        l0 = math.log1p(-p1) + _log_normal_pdf(x, m0, s0)
        l1 = math.log(p1) + _log_normal_pdf(x, m1, s1)
        top = np.maximum(l0, l1)
        norm = top + np.log(np.exp(l0 - top) + np.exp(l1 - top))
        r1 = np.exp(l1 - norm)
        n1 = r1.sum()
        n0 = x.size - n1
        if n1 < 1 or n0 < 1:
            raise ValueError("counts look like a single population; image a partly loaded array to calibrate")
        p1 = n1 / x.size
        m0, m1 = ((1 - r1) * x).sum() / n0, (r1 * x).sum() / n1
        s0 = max(math.sqrt(((1 - r1) * (x - m0) ** 2).sum() / n0), floor)
        s1 = max(math.sqrt((r1 * (x - m1) ** 2).sum() / n1), floor)
        log_likelihood = norm.sum()
        if log_likelihood - previous < 1e-10 * x.size:
            break
        previous = log_likelihood
    if m1 < m0:  # keep "atom" as the brighter population
        m0, m1, s0, s1, p1 = m1, m0, s1, s0, 1 - p1
    t = float(min_error_threshold(m0, s0, m1, s1, p1))
    return ThresholdCalibration(
        threshold=t,
        fidelity=1.0 - _error_probability(t, m0, s0, m1, s1, p1),
        mean_empty=float(m0),
        mean_atom=float(m1),
        std_empty=float(s0),
        std_atom=float(s1),
        fraction_filled=float(p1),
    )


def model_sum_statistics(
    camera: CameraConfig, psf: PsfModel
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Predicted mean and std of each trap's weighted sum when empty and when filled (``float64[n]`` each).

    Per frame pixel with ``lam`` mean photoelectrons: counts have mean ``bias + lam * gain / e_per_count``
    and variance ``(2 * lam * gain**2 + read_noise**2) / e_per_count**2 + 1/12`` (EM excess noise factor 2,
    ADC quantisation); pixels are independent, so the sum's variance is ``sum(w**2 * var)``.
    """
    bx, by = camera.binning
    background_e = camera.background_photons_per_px * camera.quantum_efficiency * bx * by
    lam_empty = np.full(psf.light_fraction.shape, background_e)
    lam_atom = lam_empty + camera.photons_per_atom * camera.quantum_efficiency * psf.light_fraction
    w = psf.weights.astype(np.float64)
    stats = []
    for lam in (lam_empty, lam_atom):
        mean = camera.bias_counts + lam * camera.em_gain / camera.electrons_per_count
        var = (EM_EXCESS_NOISE_FACTOR * lam * camera.em_gain**2 + camera.read_noise_e**2) / camera.electrons_per_count**2
        stats += [(w * mean).sum(axis=1), np.sqrt((w**2 * (var + ADC_QUANTISATION_VAR)).sum(axis=1))]
    m0, s0, m1, s1 = stats
    return m0, s0, m1, s1


def fit_psf(images: np.ndarray, config: SystemConfig, *, rounds: int = 3) -> PsfModel:
    """Fit the PSF from calibration frames (``uint16[k, h, w]``, a partly loaded array imaged ``k`` times).

    1. subtract each frame's median (the background: most pixels see no atom);
    2. cut a box around every nominal trap position, classify each (frame, trap) stamp as filled or empty
       from its total brightness (``calibrate_threshold``), and average the filled stamps per trap, weighted
       by brightness (bright shots carry more signal);
    3. alternate a per-trap Gauss-Newton fit of amplitude, sub-pixel centre and offset with a fit of the
       one shared sigma (per-trap amplitudes/offsets solved linearly for each trial sigma).

    Traps that held no atom in any frame keep their nominal centre. Returns weights in the detector layout
    built from the fitted sigma (sensor pixels) and centres (frame pixels).
    """
    cam = config.camera
    shape = frame_shape(cam)
    stack = np.asarray(images)
    if stack.ndim == 2:
        stack = stack[None]
    if stack.shape[1:] != shape:
        raise ValueError(f"calibration images must have the frame shape {shape} (got {stack.shape[1:]})")
    bx, by = cam.binning
    nominal = psf_from_config(config).centres_xy
    sigma_px = cam.psf_sigma_px
    box = max(config.imaging.psf_box_px, 2 * math.ceil(3 * sigma_px / min(bx, by)) + 1)
    xs, ys, inside, idx = box_pixels(nominal, box, shape)
    frames = stack.reshape(stack.shape[0], -1).astype(np.float64)
    frames -= np.median(frames, axis=1, keepdims=True)
    n = nominal.shape[0]
    stamps = frames[:, idx].reshape(stack.shape[0], n, box, box) * inside
    brightness = stamps.sum(axis=(2, 3))
    filled = brightness > calibrate_threshold(brightness).threshold
    weight = np.where(filled, brightness, 0.0)
    usable = filled.any(axis=0)
    if not usable.any():
        raise ValueError("no trap held an atom in the calibration images; cannot fit the PSF")
    mean_stamp = np.einsum("kn,knij->nij", weight[:, usable], stamps[:, usable]) / weight[:, usable].sum(axis=0)[:, None, None]
    fit = _StampFit(mean_stamp, xs[usable].astype(np.float64), ys[usable].astype(np.float64), inside[usable], (bx, by))
    centres = fit.centroids()
    for _ in range(rounds):
        centres = fit.refine_centres(centres, sigma_px)
        sigma_px = fit.fit_sigma(centres, sigma_px)
    fitted = nominal.copy()
    fitted[usable] = centres
    return PsfModel.build(fitted, sigma_px, cam, config.imaging.psf_box_px)


class _StampFit:
    """Least-squares model of mean stamps: ``A * fy(y) fx(x) + c`` with a pixel-integrated Gaussian."""

    def __init__(
        self, stamps: np.ndarray, xs: np.ndarray, ys: np.ndarray, inside: np.ndarray, binning: tuple[int, int]
    ) -> None:
        self.data = stamps * inside
        self.xs, self.ys, self.inside = xs, ys, inside.astype(np.float64)
        self.binning = binning

    def centroids(self) -> np.ndarray:
        positive = np.clip(self.data, 0, None)
        total = positive.sum(axis=(1, 2))
        x = (positive.sum(axis=1) * self.xs).sum(axis=1) / total
        y = (positive.sum(axis=2) * self.ys).sum(axis=1) / total
        return np.stack([x, y], axis=1)

    def _profiles(self, centres: np.ndarray, sigma_px: float) -> tuple[np.ndarray, ...]:
        sx, sy = sigma_px / self.binning[0], sigma_px / self.binning[1]
        fx = pixel_fractions(centres[:, :1], sx, self.xs)
        fy = pixel_fractions(centres[:, 1:], sy, self.ys)

        def slope(pixels: np.ndarray, c: np.ndarray, s: float) -> np.ndarray:
            """d/dc of the pixel fractions."""
            return -(_normal_pdf((pixels + 0.5 - c) / s) - _normal_pdf((pixels - 0.5 - c) / s)) / s

        return fx, fy, slope(self.xs, centres[:, :1], sx), slope(self.ys, centres[:, 1:], sy)

    def refine_centres(self, centres: np.ndarray, sigma_px: float, steps: int = 6) -> np.ndarray:
        """Gauss-Newton on (amplitude, x, y, offset) per trap, all traps at once."""
        centres = centres.copy()
        amp = np.clip(self.data, 0, None).sum(axis=(1, 2))
        offset = np.zeros(len(centres))
        for _ in range(steps):
            fx, fy, dfx, dfy = self._profiles(centres, sigma_px)
            shape_ = fy[:, :, None] * fx[:, None, :]
            model = amp[:, None, None] * shape_ + offset[:, None, None]
            resid = (self.data - model) * self.inside
            jac = np.stack(
                [shape_, amp[:, None, None] * fy[:, :, None] * dfx[:, None, :],
                 amp[:, None, None] * dfy[:, :, None] * fx[:, None, :], np.ones_like(shape_)],
                axis=-1,
            ) * self.inside[..., None]
            jac = jac.reshape(len(centres), -1, 4)
            jtj = np.einsum("npi,npj->nij", jac, jac) + 1e-9 * np.eye(4)
            jtr = np.einsum("npi,np->ni", jac, resid.reshape(len(centres), -1))
            step = np.linalg.solve(jtj, jtr[..., None])[..., 0]
            amp = amp + step[:, 0]
            centres += np.clip(step[:, 1:3], -0.5, 0.5)
            offset = offset + step[:, 3]
        return centres

    def fit_sigma(self, centres: np.ndarray, sigma_px: float) -> float:
        """The shared sigma (sensor px) minimising the residual, amplitudes and offsets solved per trap."""

        def cost(s: float) -> float:
            fx, fy, _, _ = self._profiles(centres, s)
            a = (fy[:, :, None] * fx[:, None, :] * self.inside).reshape(len(centres), -1)
            b = self.inside.reshape(len(centres), -1)
            d = self.data.reshape(len(centres), -1)
            # per-trap 2x2 normal equations for amplitude and offset
            aa, ab, bb = (a * a).sum(1), (a * b).sum(1), (b * b).sum(1)
            ad, bd = (a * d).sum(1), (b * d).sum(1)
            det = aa * bb - ab**2
            amp = (bb * ad - ab * bd) / det
            off = (aa * bd - ab * ad) / det
            return float(((d - amp[:, None] * a - off[:, None] * b) ** 2).sum())

        result = minimize_scalar(cost, bounds=(0.3 * sigma_px, 3.0 * sigma_px), method="bounded")
        return float(result.x)
