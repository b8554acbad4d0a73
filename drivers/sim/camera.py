"""The simulated EMCCD: renders the lab's atoms through the PSF with EMCCD statistics and the paper's readout
timing, behind the same ``Camera`` protocol as the hardware.

Image model, per shot (electrons unless a name says counts; parameters from ``sim.imaging``, the lab's hidden
truth, plus the camera's own settings):
- an atom yields ``scattering_rate_hz * exposure_s * collection_efficiency * quantum_efficiency`` mean
  photoelectrons, times its trap's brightness (``trap_brightness``: a Gaussian imaging-beam profile and a
  seeded trap-to-trap spread) and times the fraction of the exposure it was there (``World.expose``: an
  atom heated out mid-exposure is bright only until it leaves). They are Poisson and spread over the sensor
  by a pixel-integrated Gaussian PSF at the trap's sub-pixel position; split over pixels this is an
  independent Poisson draw per pixel with mean ``N * fraction`` (Poisson thinning), which is what we draw;
- every sensor pixel adds Poisson(``background_photons_per_px_per_s * exposure_s * quantum_efficiency``) of
  stray light and Poisson(clock-induced charge), which comes with every readout whatever the exposure and
  depends on how the rows are clocked (``clock_induced_charge``);
- binning is on-chip: charge of a ``bx x by`` bin is summed *before* the EM register, so a binned pixel is
  one Poisson draw of the summed mean, amplified once and read once (this is why binning helps an EMCCD);
- EM gain: ``Gamma(shape=n, scale=em_gain)`` for ``n > 0`` electrons, else 0;
- read noise Normal(0, the read noise at the horizontal readout rate, ``read_noise``), then
  ``counts = electrons / electrons_per_count + bias`` rounded and clipped to the 16-bit ADC
  range ``[0, 65535]`` (saturation).

The readout's timing and options, and the noise they set, are ``drivers/sim/readout.py``'s.

The expensive part runs in a numba kernel that draws from the caller's ``np.random.Generator``, so a seeded
lab is reproducible. Drawing it literally (``_emccd_counts``: a Poisson, a gain and a normal draw per pixel)
costs ~45 ns a pixel. ``_emccd_counts_split`` draws the same distribution faster by splitting each pixel's
electrons into background and atom light, two independent Poisson variables: ``n = n_bg + n_atom`` with
``n_bg ~ Poisson(background)`` and ``n_atom ~ Poisson(mean - background)``. Most pixels (all of them away
from atoms, and most of each PSF stamp's outer ring) draw ``n_atom = 0``, and then their count has one fixed
distribution, the background pixel's: tabulated at configure time from closed forms (the read-noise
Gaussian for ``n_bg = 0``, and that Gaussian convolved with the gain's Gamma(n_bg, em_gain) for
``n_bg = 1, 2``; binned to ADC counts with clipping) and drawn with one uniform through an alias table. The
remaining ~1 % of background probability (``n_bg >= 3``) and every pixel with atom electrons take the
literal path (gamma gain and read noise). The frames have the same statistics as the literal kernel's,
not the same pixels for a given seed; ``SimCamera(reference=True)`` renders with the literal kernel, and a
test compares the two. A background pixel costs ~10 ns instead of ~45; a 256x512 frame of the paper's grid
with ~300 atoms ~4 ms instead of ~6.5 (the atoms' own pixels, ~12k, still draw gamma gains).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np
from scipy.special import gammainc, log_ndtr, ndtr

from drivers.sim.clock import SimClock
from drivers.sim.readout import ReadoutTime, check_readout_options, clock_induced_charge, read_noise, readout_time
from engine.config import CameraConfig, SystemConfig
from engine.devices import DeviceError, FrameInfo
from engine.imaging_calibration import Population
from engine.psf import PsfModel, frame_shape, pixel_fractions, trap_positions_px

__all__ = [
    "BackgroundTable",
    "SimCamera",
    "background_table",
    "predicted_sum_statistics",
    "trap_brightness",
]

ADC_MAX_COUNTS = 65535
STAMP_RADIUS_SIGMAS = 5.0  # light beyond 5 sigma (< 1e-6 of it) is not rendered
EM_EXCESS_NOISE_FACTOR = 2.0  # variance of a high-gain EM register's output: 2 * n * gain**2
ADC_QUANTISATION_VAR = 1.0 / 12.0
_BRIGHTNESS_STREAM = int.from_bytes(b"brightness", "big")  # spawn key of the brightness pattern under sim.seed

FaultKind = Literal["timeout", "corrupt"]


def _stamps(config: SystemConfig) -> tuple[np.ndarray, np.ndarray]:
    """Where each trap's light lands: binned-frame pixel indices ``int64[n, s]`` and light fractions
    ``float64[n, s]`` over a sensor stamp of +-5 sigma (sensor pixels outside the read-out area get 0)."""
    cam = config.camera
    h, w = frame_shape(cam)
    bx, by = cam.binning
    xy = trap_positions_px(config)
    radius = int(math.ceil(STAMP_RADIUS_SIGMAS * cam.psf_sigma_px))
    offsets = np.arange(-radius, radius + 1)
    xs = np.floor(xy[:, :1] + 0.5).astype(np.int64) + offsets  # sensor pixels [n, side]
    ys = np.floor(xy[:, 1:] + 0.5).astype(np.int64) + offsets
    fx = pixel_fractions(xy[:, :1], cam.psf_sigma_px, xs) * ((xs >= 0) & (xs < w * bx))
    fy = pixel_fractions(xy[:, 1:], cam.psf_sigma_px, ys) * ((ys >= 0) & (ys < h * by))
    frac = fy[:, :, None] * fx[:, None, :]
    bin_idx = np.clip(ys // by, 0, h - 1)[:, :, None] * w + np.clip(xs // bx, 0, w - 1)[:, None, :]
    n = xy.shape[0]
    return bin_idx.reshape(n, -1).astype(np.int64), frac.reshape(n, -1)


def trap_brightness(config: SystemConfig) -> np.ndarray:
    """``float64[ny * nx]``: each trap's atom brightness relative to the array's centre.

    Two causes, as in a lab: the imaging beam's Gaussian profile, falling to ``beam_edge_brightness`` at the
    array's corners (``b = edge ** (r / r_corner) ** 2`` with ``r`` the distance from the centre in sites),
    and a trap-to-trap spread (trap depths differ, and with them the light shift and scattering rate):
    a factor ``1 + brightness_spread * N(0, 1)``, clipped at 0, drawn from a stream of ``sim.seed`` of its
    own, so the pattern is fixed for a seed (``seed: null``: a new pattern at every configuration).
    """
    arr, img = config.array, config.sim.imaging
    rows, cols = np.divmod(np.arange(arr.n_traps), arr.nx)
    cy, cx = (arr.ny - 1) / 2, (arr.nx - 1) / 2
    r2_corner = cx**2 + cy**2
    profile = img.beam_edge_brightness ** (((cols - cx) ** 2 + (rows - cy) ** 2) / r2_corner) if r2_corner else 1.0
    rng = np.random.default_rng(np.random.SeedSequence(config.sim.seed, spawn_key=(_BRIGHTNESS_STREAM,)))
    spread = np.clip(1.0 + img.brightness_spread * rng.standard_normal(arr.n_traps), 0.0, None)
    return profile * spread


def _electrons_per_exposure(config: SystemConfig) -> tuple[float, float]:
    """(photoelectrons from an atom of brightness 1 there for the whole exposure, mean electrons of a binned
    pixel with no atom: stray light and clock-induced charge of its ``bx * by`` sensor pixels)."""
    cam, img = config.camera, config.sim.imaging
    bx, by = cam.binning
    atom_e = img.scattering_rate_hz * cam.exposure_s * img.collection_efficiency * img.quantum_efficiency
    pixel_e = img.background_photons_per_px_per_s * cam.exposure_s * img.quantum_efficiency
    return atom_e, (pixel_e + clock_induced_charge(cam, img)) * bx * by


def predicted_sum_statistics(config: SystemConfig, psf: PsfModel) -> tuple[Population, Population]:
    """The simulator's prediction of each detector weighted sum when the trap is empty and when it holds an
    atom for the whole exposure (mean, std, skewness per trap, per-trap brightness included).

    For tests and for choosing settings; the engine never calls it (its detection is its own). A frame pixel
    with ``lam`` mean electrons is compound Poisson: ``n ~ Poisson(lam)`` electrons each multiplied into an
    exponential of mean ``gain``, so its cumulants are ``lam * r! * gain**r``; read noise and ADC
    quantisation add variance only. In counts divide by ``electrons_per_count**r``, add the bias to the
    mean. Pixels are independent, so the weighted sum's cumulants are ``sum(w**r * kappa_r)``.
    """
    cam, img = config.camera, config.sim.imaging
    atom_e, background_e = _electrons_per_exposure(config)
    lam_empty = np.full(psf.light_fraction.shape, background_e)
    lam_atom = lam_empty + atom_e * trap_brightness(config)[:, None] * psf.light_fraction
    w = psf.weights.astype(np.float64)
    g = cam.em_gain / img.electrons_per_count  # counts per electron entering the EM register
    noise_var = (read_noise(cam, img) / img.electrons_per_count) ** 2 + ADC_QUANTISATION_VAR
    populations = []
    for lam in (lam_empty, lam_atom):
        mean = (w * (img.bias_counts + lam * g)).sum(axis=1)
        var = (w**2 * (EM_EXCESS_NOISE_FACTOR * lam * g**2 + noise_var)).sum(axis=1)
        third = (w**3 * 6.0 * lam * g**3).sum(axis=1)
        std = np.sqrt(var)
        populations.append(Population(mean, std, third / std**3))
    return populations[0], populations[1]


@numba.njit(cache=True, nogil=True)
def _expected_electrons(
    atom_e: np.ndarray,
    stamp_idx: np.ndarray,
    stamp_frac: np.ndarray,
    background_e: float,
    out_mean_e: np.ndarray,
) -> None:
    """Mean electrons per binned pixel: uniform background plus the PSF stamp of every trap with light
    (``atom_e[t]``: trap ``t``'s photoelectrons this exposure, 0 when empty)."""
    flat = out_mean_e.reshape(out_mean_e.size)
    flat[:] = background_e
    for t in range(atom_e.size):
        if atom_e[t] > 0.0:
            for k in range(stamp_idx.shape[1]):
                flat[stamp_idx[t, k]] += atom_e[t] * stamp_frac[t, k]


@numba.njit(cache=True, nogil=True)
def _poisson(rng: np.random.Generator, lam: float) -> int:
    """A Poisson(``lam``) draw: below a mean of 10 the CDF inverted with one uniform (fast for dim pixels)."""
    if lam >= 10.0:
        return rng.poisson(lam)
    u = rng.random()
    p = math.exp(-lam)
    cdf = p
    n = 0
    while u > cdf and n < 100:
        n += 1
        p *= lam / n
        cdf += p
    return n


@numba.njit(cache=True, nogil=True)
def _read_out(
    rng: np.random.Generator, n: int, em_gain: float, read_noise_e: float, electrons_per_count: float,
    bias_counts: float,
) -> int:
    """ADC counts of a pixel holding ``n`` electrons: EM gain (Gamma(n, em_gain)), read noise, bias, and
    the 16-bit ADC's range."""
    if n == 0:
        e = 0.0
    elif n == 1:
        e = rng.standard_exponential() * em_gain
    else:
        e = rng.gamma(float(n), em_gain)
    counts = round((e + read_noise_e * rng.standard_normal()) / electrons_per_count + bias_counts)
    return 0 if counts < 0 else (ADC_MAX_COUNTS if counts > ADC_MAX_COUNTS else counts)


@numba.njit(cache=True, nogil=True)
def _emccd_counts(
    rng: np.random.Generator,
    mean_e: np.ndarray,
    em_gain: float,
    read_noise_e: float,
    electrons_per_count: float,
    bias_counts: float,
    out_counts: np.ndarray,
) -> None:
    """Shot noise, EM gain, read noise, ADC and saturation for every binned pixel."""
    lam_flat = mean_e.reshape(mean_e.size)
    out = out_counts.reshape(out_counts.size)
    for i in range(out.size):
        n = _poisson(rng, lam_flat[i])
        out[i] = _read_out(rng, n, em_gain, read_noise_e, electrons_per_count, bias_counts)


@dataclass(frozen=True)
class BackgroundTable:
    """The count distribution of a pixel that holds only background electrons, ready for ``_emccd_counts_split``.

    Entry ``j`` of the alias table is ADC count ``value[j]``, or ``-1`` for "more than ``TABLE_ELECTRONS``
    electrons": that case is drawn the literal way, its electron number ``n`` from ``slow_cdf``
    (``P(n <= j + TABLE_ELECTRONS + 1 | n > TABLE_ELECTRONS)``); ``bg_cdf``: ``P(n <= j)``.
    ``pmf``: the tabulated probabilities (for tests).
    """

    prob: np.ndarray
    alias: np.ndarray
    value: np.ndarray
    pmf: np.ndarray
    bg_cdf: np.ndarray
    slow_cdf: np.ndarray


#: Background pixels with up to this many electrons are drawn from the table.
TABLE_ELECTRONS = 2
#: Beyond this many read-noise sigmas or gain lengths the tabulated probability is below 1e-17 and is left out.
_TABLE_REACH = 45.0


def background_table(
    background_e: float, em_gain: float, read_noise_e: float, electrons_per_count: float, bias_counts: float
) -> BackgroundTable:
    """Tabulate the ADC count of a background-only pixel (see the module docstring for the model).

    Bin ``k`` holds the probability that ``(e + noise) / electrons_per_count + bias`` rounds to ``k`` (the
    first and last bins take everything beyond them, as the ADC clips), for ``e = 0`` (no electron) and ``e``
    ~ Gamma(n, em_gain) for ``n = 1, 2`` electrons, weighted by their Poisson probabilities. With
    ``a = x / s``, ``b = s / g`` (``s`` the read noise, ``x`` electrons), the CDFs of ``e + noise`` are
    ``Phi(a)``, ``Phi(a) - E`` and ``Phi(a) - (1 + x/g - b^2) E - b phi(a)`` with
    ``E = exp(-x/g + b^2/2) Phi(a - b)`` (the Gaussian integrals of the Gamma CDFs ``1 - exp(-y/g)`` and
    ``1 - exp(-y/g) (1 + y/g)``; checked against quadrature in the tests).
    """
    lam, g, sigma, epc, bias = background_e, em_gain, read_noise_e, electrons_per_count, bias_counts
    x_lo = -_TABLE_REACH * sigma - epc
    x_hi = _TABLE_REACH * (g + sigma) + epc
    k_lo = int(np.clip(math.floor(bias + x_lo / epc) - 1, 0, ADC_MAX_COUNTS))
    k_hi = int(np.clip(math.ceil(bias + x_hi / epc) + 1, 0, ADC_MAX_COUNTS))
    k = np.arange(k_lo, k_hi + 1, dtype=np.float64)
    x = (k[1:] - 0.5 - bias) * epc  # electrons at the lower edge of bins k_lo + 1 .. k_hi

    def binned(cdf: np.ndarray) -> np.ndarray:
        return np.diff(np.concatenate([[0.0], cdf, [1.0]]))

    if sigma > 0:
        a, b = x / sigma, sigma / g
        phi_a = ndtr(a)
        big_e = np.exp(-x / g + b * b / 2 + log_ndtr(a - b))  # computed in logs: no overflow for any x
        phi_density = np.exp(-a * a / 2) / math.sqrt(2 * math.pi)
        cdfs = [phi_a, phi_a - big_e, phi_a - (1 + x / g - b * b) * big_e - b * phi_density]
        pmfs = [binned(c) for c in cdfs]
    else:  # no read noise: the Gamma CDFs themselves, and a point at the bias for no electron
        y = np.maximum(x, 0.0) / g
        pmf0 = np.zeros(k.size)
        pmf0[min(max(round(bias), k_lo), k_hi) - k_lo] = 1.0
        one, two = np.where(x > 0, -np.expm1(-y), 0.0), np.where(x > 0, 1 - np.exp(-y) * (1 + y), 0.0)
        pmfs = [pmf0, binned(one), binned(two)]
    pois_table = [math.exp(-lam) * lam**n / math.factorial(n) for n in range(TABLE_ELECTRONS + 1)]
    p_slow = float(gammainc(TABLE_ELECTRONS + 1.0, lam)) if lam > 0 else 0.0  # P(n > TABLE_ELECTRONS)
    counts_pmf = sum(p * np.clip(m, 0.0, None) for p, m in zip(pois_table, pmfs, strict=True))
    pmf = np.concatenate([counts_pmf, [p_slow]])
    pmf /= pmf.sum()
    value = np.concatenate([k.astype(np.int64), [-1]])
    prob = np.empty(pmf.size)
    alias = np.empty(pmf.size, dtype=np.int64)
    _alias_table(pmf, prob, alias)

    # electron numbers by inversion, as ``_emccd_counts`` draws them (used while the mean is below 10)
    n = np.arange(101)
    pois = np.exp(-lam + n * math.log(lam) - np.cumsum(np.log(np.maximum(n, 1)))) if lam > 0 else (n == 0) * 1.0
    bg_cdf = np.minimum(np.cumsum(pois), 1.0)
    bg_cdf[-1] = 1.0
    slow = pois[TABLE_ELECTRONS + 1 :] / p_slow if p_slow > 0 else np.zeros(n.size - TABLE_ELECTRONS - 1)
    slow_cdf = np.minimum(np.cumsum(slow), 1.0)
    slow_cdf[-1] = 1.0
    return BackgroundTable(prob=prob, alias=alias, value=value, pmf=pmf, bg_cdf=bg_cdf, slow_cdf=slow_cdf)


@numba.njit(cache=True, nogil=True)
def _stack(
    j: int, scaled: np.ndarray, small: np.ndarray, ns: int, large: np.ndarray, nl: int
) -> tuple[int, int]:
    """Push entry ``j`` onto the alias method's small (``scaled[j] < 1``) or large stack; the new heights."""
    if scaled[j] < 1.0:
        small[ns] = j
        return ns + 1, nl
    large[nl] = j
    return ns, nl + 1


@numba.njit(cache=True, nogil=True)
def _alias_table(p: np.ndarray, prob: np.ndarray, alias: np.ndarray) -> None:
    """Vose's alias method: entry ``j`` keeps itself with probability ``prob[j]``, else becomes ``alias[j]``."""
    k = p.size
    scaled = p * (k / p.sum())
    small = np.empty(k, dtype=np.int64)
    large = np.empty(k, dtype=np.int64)
    ns = nl = 0
    for j in range(k):
        alias[j] = j
        ns, nl = _stack(j, scaled, small, ns, large, nl)
    while ns > 0 and nl > 0:
        ns -= 1
        s = small[ns]
        nl -= 1
        big = large[nl]
        prob[s] = scaled[s]
        alias[s] = big
        scaled[big] = (scaled[big] + scaled[s]) - 1.0
        ns, nl = _stack(big, scaled, small, ns, large, nl)
    for j in range(nl):
        prob[large[j]] = 1.0
    for j in range(ns):  # rounding leftovers: probability ~1
        prob[small[j]] = 1.0


@numba.njit(cache=True, nogil=True)
def _invert(rng: np.random.Generator, cdf: np.ndarray) -> int:
    """The first ``n`` with ``u <= cdf[n]`` (the last entry is 1)."""
    u = rng.random()
    n = 0
    while u > cdf[n] and n < cdf.size - 1:
        n += 1
    return n


@numba.njit(cache=True, nogil=True)
def _emccd_counts_split(
    rng: np.random.Generator,
    mean_e: np.ndarray,
    background_e: float,
    em_gain: float,
    read_noise_e: float,
    electrons_per_count: float,
    bias_counts: float,
    prob: np.ndarray,
    alias: np.ndarray,
    value: np.ndarray,
    bg_cdf: np.ndarray,
    slow_cdf: np.ndarray,
    out_counts: np.ndarray,
) -> None:
    """``_emccd_counts``'s distribution, drawn as background + atom electrons (see the module docstring)."""
    lam_flat = mean_e.reshape(mean_e.size)
    out = out_counts.reshape(out_counts.size)
    n_entries = prob.size
    small_bg = background_e < 10.0
    for i in range(out.size):
        d = lam_flat[i] - background_e  # atom light (>= 0: the atoms' stamps are added onto the background)
        n_atom = _poisson(rng, d) if d > 0.0 else 0
        if n_atom == 0:
            x = rng.random() * n_entries
            j = int(x)
            if j >= n_entries:
                j = n_entries - 1
            if x - j >= prob[j]:
                j = alias[j]
            k = value[j]
            if k >= 0:
                out[i] = k
                continue
            # more background electrons than the table holds
            if small_bg:
                n = TABLE_ELECTRONS + 1 + _invert(rng, slow_cdf)
            else:
                n = rng.poisson(background_e)
                while n <= TABLE_ELECTRONS:
                    n = rng.poisson(background_e)
        else:
            n = n_atom + (_invert(rng, bg_cdf) if small_bg else rng.poisson(background_e))
        out[i] = _read_out(rng, n, em_gain, read_noise_e, electrons_per_count, bias_counts)


class SimCamera:
    """A simulated EMCCD + frame grabber (implements ``engine.devices.Camera``).

    ``atoms(t0_s, exposure_s)`` is called at ``trigger()`` and returns, per static trap (``[ny, nx]``), the
    fraction of the exposure an atom was there (``World.expose``; a ``bool`` occupancy means "there
    throughout"); the frame is rendered then and handed out by ``read``. Set ``fail_next_read`` to
    ``"timeout"`` (no frame arrives) or ``"corrupt"`` (the grabber reports a torn transfer) to make the next
    ``read`` fail with ``DeviceError``; the knob clears itself once used. ``fault`` does the same for every
    read until it is set back to None. ``reference=True`` renders with the literal per-pixel kernel
    (``_emccd_counts``) instead of the background-table one (same statistics; see the module docstring).
    """

    def __init__(
        self,
        config: SystemConfig,
        *,
        atoms: Callable[[float, float], np.ndarray],
        clock: SimClock,
        rng: np.random.Generator,
        reference: bool = False,
    ) -> None:
        self.reference = reference
        self._system = config
        self._atoms = atoms
        self._clock = clock
        self._rng = rng
        self._fail_next_read: FaultKind | None = None
        self.fault: FaultKind | None = None
        self._frame_index = -1
        self._t_exposure_start_s: float | None = None
        self._presence = np.zeros((config.array.ny, config.array.nx), dtype=np.float64)
        self.configure(config.camera)
        self._warm_up()

    @property
    def frame_shape(self) -> tuple[int, int]:
        return self._frame_shape

    @property
    def readout(self) -> ReadoutTime:
        return self._readout

    @property
    def rng(self) -> np.random.Generator:
        """The generator of the camera's noise (photon counts, EM gain, read noise, torn frames)."""
        return self._rng

    @rng.setter
    def rng(self, rng: np.random.Generator) -> None:
        self._rng = rng

    @property
    def fail_next_read(self) -> FaultKind | None:
        return self._fail_next_read

    @fail_next_read.setter
    def fail_next_read(self, kind: FaultKind | None) -> None:
        if kind not in (None, "timeout", "corrupt"):
            raise ValueError(f"fail_next_read must be None, 'timeout' or 'corrupt' (got {kind!r})")
        self._fail_next_read = kind

    def set_system_config(self, config: SystemConfig) -> None:
        """Adopt a new system configuration (array size and geometry included); between shots only."""
        self._system = config
        self._presence = np.zeros((config.array.ny, config.array.nx), dtype=np.float64)
        self.configure(config.camera)

    def configure(self, config: CameraConfig) -> None:
        """Apply new camera settings; the trap geometry must still fit the ROI (validated like a config load)."""
        data = self._system.model_dump()
        data["camera"] = config.model_dump()
        self._system = SystemConfig.model_validate(data)
        cam = self._system.camera
        check_readout_options(cam)
        self._frame_shape = frame_shape(cam)
        self._frame = np.zeros(self._frame_shape, dtype=np.uint16)  # rendered at trigger(), handed out at read()
        self._readout = readout_time(cam)
        self._stamp_idx, self._stamp_frac = _stamps(self._system)
        self._mean_e = np.empty(self._frame_shape, dtype=np.float64)
        img = self._system.sim.imaging
        atom_e, self._background_e = _electrons_per_exposure(self._system)
        self._trap_atom_e = atom_e * trap_brightness(self._system)  # a whole exposure's light, per trap
        self._atom_e = np.empty_like(self._trap_atom_e)
        self._read_noise_e = read_noise(cam, img)
        self._table = background_table(
            self._background_e, cam.em_gain, self._read_noise_e, img.electrons_per_count, img.bias_counts
        )
        self._t_exposure_start_s = None

    def trigger(self) -> None:
        """Start an exposure now: ask the lab which atoms this exposure sees, and for how long each is there.
        A new trigger discards an unread frame."""
        t0_s = self._clock.now_s()
        # Render now, not at read(): on hardware the host is idle during the exposure and the frame arrives
        # by DMA, so the simulator's heavy work (the world's imaging, the rendering) must not run between the
        # frame and the engine's use of it, nor cost clock time.
        with self._clock.paused():
            presence = np.asarray(self._atoms(t0_s, self._readout.exposure_s), dtype=np.float64)
            if presence.shape != self._presence.shape:
                raise ValueError(f"atoms() returned shape {presence.shape}, expected {self._presence.shape}")
            self._presence[...] = presence
            self._render(self._frame)
        self._t_exposure_start_s = t0_s
        self._frame_index += 1

    def read(self, out: np.ndarray, *, timeout_s: float) -> FrameInfo:
        """Wait (in simulated time) for the triggered frame and render it into ``out`` (``uint16[h, w]``)."""
        if out.shape != self._frame_shape or out.dtype != np.uint16 or not out.flags.c_contiguous:
            raise ValueError(f"out must be a C-contiguous uint16 array of shape {self._frame_shape}")
        t0 = self._t_exposure_start_s
        if t0 is None:
            raise DeviceError(
                "camera: read() with no exposure pending; call trigger() first "
                "(on hardware: check that the AWG's camera trigger line reaches the EMCCD)"
            )
        self._t_exposure_start_s = None  # the frame is consumed whatever happens next
        fault, self._fail_next_read = self._fail_next_read or self.fault, None
        t_ready_s = t0 + self._readout.total_s
        if fault == "timeout" or t_ready_s - self._clock.now_s() > timeout_s:
            self._clock.advance(timeout_s)
            raise DeviceError(
                f"camera: no frame within {timeout_s * 1e3:.1f} ms of waiting (frame {self._frame_index} needs "
                f"{self._readout.total_s * 1e3:.2f} ms from trigger); check the trigger, exposure and timeout"
            )
        with self._clock.paused():  # the transfer is in the readout model; the copy is the simulator's work
            out[...] = self._frame
        self._clock.advance_to(t_ready_s)
        if fault == "corrupt":
            tear_row = int(self._rng.integers(0, self._frame_shape[0]))
            out[tear_row:] = 0
            raise DeviceError(
                f"camera: frame {self._frame_index} arrived corrupt (the frame grabber reported an incomplete "
                f"transfer from row {tear_row}); discard it and acquire again"
            )
        return FrameInfo(
            t_exposure_start_s=t0,
            exposure_s=self._readout.exposure_s,
            readout_s=self._readout.readout_s,
            frame_index=self._frame_index,
        )

    def close(self) -> None:
        self._t_exposure_start_s = None

    def _warm_up(self) -> None:
        """Compile (or load) the render kernels now, so the first read costs no compile time; a scratch
        generator keeps the lab's random stream untouched."""
        scratch = np.zeros((1, 1), dtype=np.float64)
        _expected_electrons(np.zeros(1), np.zeros((1, 1), dtype=np.int64), scratch, 0.0, scratch)
        _emccd_counts(np.random.default_rng(0), scratch, 1.0, 0.0, 1.0, 0.0, np.zeros((1, 1), dtype=np.uint16))
        t = self._table
        _emccd_counts_split(
            np.random.default_rng(0), scratch, 0.0, 1.0, 0.0, 1.0, 0.0, t.prob, t.alias, t.value, t.bg_cdf,
            t.slow_cdf, np.zeros((1, 1), dtype=np.uint16),
        )

    def _render(self, out: np.ndarray) -> None:
        cam, img = self._system.camera, self._system.sim.imaging
        np.multiply(self._trap_atom_e, self._presence.reshape(-1), out=self._atom_e)
        _expected_electrons(self._atom_e, self._stamp_idx, self._stamp_frac, self._background_e, self._mean_e)
        if self.reference:
            _emccd_counts(
                self._rng, self._mean_e, cam.em_gain, self._read_noise_e, img.electrons_per_count, img.bias_counts, out
            )
            return
        t = self._table
        _emccd_counts_split(
            self._rng, self._mean_e, self._background_e, cam.em_gain, self._read_noise_e, img.electrons_per_count,
            img.bias_counts, t.prob, t.alias, t.value, t.bg_cdf, t.slow_cdf, out,
        )  # fmt: skip
