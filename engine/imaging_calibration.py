"""Module II calibration, run between shots: threshold from measured sums, PSF from calibration images.

Detection is calibrated from frames only, never from a model of the camera: on hardware the sensor's noise,
gain and the atoms' brightness are not known to the engine, and in the simulated lab they are the world's
hidden truth (``sim.imaging``), which the engine must not read.

The threshold is the point that minimises the probability of a wrong assignment (paper Sec. II, after
Cooper 2024): where ``P(filled) p_filled(s) = P(empty) p_empty(s)``. Each population of weighted sums is
modelled as a *shifted gamma* matched to its mean, standard deviation and skewness. Why not Gaussians: EM
gain makes every pixel a compound Poisson-exponential variable, so both populations are right-skewed and
the empty one has an exponential, not Gaussian, tail toward the threshold; a Gaussian fit puts the threshold
too low and under-reports errors whenever the populations come close (measured: 5x the optimal error rate
at 60 photons/atom). The gamma's exponential tail matches that shape, and it tends to the Gaussian as the
skewness goes to zero. The reported fidelity is ``1 - P(error)`` under the fitted model.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import minimize_scalar
from scipy.special import gammainc, gammaincc, gammaln

from engine.config import SystemConfig
from engine.psf import PsfModel, box_pixels, frame_shape, pixel_fractions, psf_from_config

__all__ = [
    "Population",
    "ThresholdCalibration",
    "calibrate_threshold",
    "fit_psf",
    "min_error_threshold",
    "MIN_SEPARATION",
]

#: The fitted populations must be this many (combined) standard deviations apart to be called empty and filled
#: traps: frames of an empty (or a full) array still split into two noise "populations" about one apart (3 apart
#: leaves ~0.5 % detection error, a usable if poor calibration).
MIN_SEPARATION = 3.0
MIN_SKEW = 1e-2  # below this a population is treated as (a gamma indistinguishable from) a Gaussian
MAX_SKEW = 10.0


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
    skew_empty: float
    skew_atom: float

    @property
    def separation(self) -> float:
        """Distance between the population means in (combined) standard deviations."""
        return (self.mean_atom - self.mean_empty) / math.hypot(self.std_empty, self.std_atom)

    def require_two_populations(self) -> ThresholdCalibration:
        """This fit, or a ``ValueError`` if its populations are too close to be empty and filled traps."""
        if self.separation < MIN_SEPARATION:
            raise ValueError(
                f"the weighted sums look like a single population (the two fitted ones are only "
                f"{self.separation:.1f} standard deviations apart, {MIN_SEPARATION:g} needed); image a partly "
                "loaded array to calibrate"
            )
        return self


@dataclass(frozen=True)
class Population:
    """A shifted gamma, ``loc + Gamma(shape, scale)``, given by mean, std and skewness (arrays broadcast)."""

    mean: np.ndarray | float  # per trap, or one value for all
    std: np.ndarray | float
    skew: np.ndarray | float

    @property
    def _params(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        skew = np.clip(self.skew, MIN_SKEW, MAX_SKEW)
        shape = 4.0 / skew**2
        scale = self.std * skew / 2.0
        return shape, scale, self.mean - shape * scale

    def logpdf(self, x: np.ndarray) -> np.ndarray:
        shape, scale, loc = self._params
        z = np.maximum((x - loc) / scale, 1e-300)
        value = (shape - 1) * np.log(z) - z - gammaln(shape) - np.log(scale)
        return np.where(x > loc, value, -np.inf)

    def cdf(self, x: np.ndarray | float) -> np.ndarray:
        shape, scale, loc = self._params
        return gammainc(shape, np.maximum((x - loc) / scale, 0.0))

    def sf(self, x: np.ndarray | float) -> np.ndarray:
        shape, scale, loc = self._params
        return gammaincc(shape, np.maximum((x - loc) / scale, 0.0))


def min_error_threshold(empty: Population, atom: Population, fraction_filled: float) -> np.ndarray:
    """Where the prior-weighted densities of the two populations cross, between the two means (bisection,
    vectorised over traps; at an end if one population dominates everywhere in between)."""
    log_ratio_prior = math.log(fraction_filled) - math.log1p(-fraction_filled)
    lo, hi = np.broadcast_arrays(np.array(empty.mean, dtype=np.float64), np.array(atom.mean, dtype=np.float64))
    lo, hi = lo.copy(), hi.copy()
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        atom_wins = log_ratio_prior + atom.logpdf(mid) - empty.logpdf(mid) > 0
        hi = np.where(atom_wins, mid, hi)
        lo = np.where(atom_wins, lo, mid)
    return 0.5 * (lo + hi)


def error_probability(
    threshold: np.ndarray | float, empty: Population, atom: Population, fraction_filled: float
) -> np.ndarray:
    """P(wrong assignment) at ``threshold``: empty read above it or atom read at/below it."""
    return (1 - fraction_filled) * empty.sf(threshold) + fraction_filled * atom.cdf(threshold)


def _weighted_moments(x: np.ndarray, r: np.ndarray, floor: float) -> tuple[float, float, float]:
    n = r.sum()
    mean = (r * x).sum() / n
    d = x - mean
    std = max(math.sqrt((r * d**2).sum() / n), floor)
    return mean, std, (r * d**3).sum() / n / std**3


def calibrate_threshold(counts: np.ndarray, *, max_iterations: int = 300) -> ThresholdCalibration:
    """Split weighted sums (any shape, e.g. ``[n_images, n_traps]``) into two populations and return the
    minimum-error threshold and its fidelity.

    Membership comes from a Gaussian-mixture expectation-maximisation (stable even when the populations
    overlap; a gamma E-step is not, its hard lower edge throws points out of a population); each population is
    then described by its mean, std and skewness as a shifted gamma for the threshold and the fidelity.

    The fit starts from a split halfway between the 2nd and 98th percentiles, which lies between the
    populations for any filling fraction between a few percent and ~95 %.
    """
    x = np.asarray(counts, dtype=np.float64).ravel()
    x = x[np.isfinite(x)]
    if x.size < 20:
        raise ValueError(f"calibrate_threshold needs at least 20 finite counts (got {x.size})")
    lo, hi = np.percentile(x, [2.0, 98.0])
    r1 = (x > 0.5 * (lo + hi)).astype(np.float64)
    if hi <= lo or r1.all() or not r1.any():
        raise ValueError("counts look like a single population; image a partly loaded array to calibrate")
    floor = 1e-6 * (hi - lo)
    for _ in range(max_iterations):
        p1 = r1.mean()
        if p1 * x.size < 1 or (1 - p1) * x.size < 1:
            raise ValueError("counts look like a single population; image a partly loaded array to calibrate")
        m0, s0, _ = _weighted_moments(x, 1 - r1, floor)
        m1, s1, _ = _weighted_moments(x, r1, floor)
        z0, z1 = (x - m0) / s0, (x - m1) / s1
        log_odds = math.log(p1 / (1 - p1)) - math.log(s1 / s0) - 0.5 * (z1**2 - z0**2)
        new_r1 = 1.0 / (1.0 + np.exp(-np.clip(log_odds, -700, 700)))
        converged = np.abs(new_r1 - r1).max() < 1e-9
        r1 = new_r1
        if converged:
            break
    p1 = float(r1.mean())
    empty = Population(*_weighted_moments(x, 1 - r1, floor))
    atom = Population(*_weighted_moments(x, r1, floor))
    if atom.mean < empty.mean:  # keep "atom" as the brighter population
        empty, atom, p1 = atom, empty, 1 - p1
    t = float(min_error_threshold(empty, atom, p1))
    return ThresholdCalibration(
        threshold=t,
        fidelity=float(1.0 - error_probability(np.float64(t), empty, atom, p1)),
        mean_empty=float(empty.mean),
        mean_atom=float(atom.mean),
        std_empty=float(empty.std),
        std_atom=float(atom.std),
        fraction_filled=p1,
        skew_empty=float(empty.skew),
        skew_atom=float(atom.skew),
    )


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
    weighted_sum = np.einsum("kn,knij->nij", weight[:, usable], stamps[:, usable])
    mean_stamp = weighted_sum / weight[:, usable].sum(axis=0)[:, None, None]
    fit = _StampFit(mean_stamp, xs[usable].astype(np.float64), ys[usable].astype(np.float64), inside[usable], (bx, by))
    centres = fit.centroids()
    for _ in range(rounds):
        centres = fit.refine_centres(centres, sigma_px)
        sigma_px = fit.fit_sigma(centres, sigma_px)
    fitted = nominal.copy()
    fitted[usable] = centres
    return PsfModel.build(fitted, sigma_px, cam, config.imaging.psf_box_px)


def _normal_pdf(u: np.ndarray) -> np.ndarray:
    return np.exp(-0.5 * u**2) / math.sqrt(2 * math.pi)


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
