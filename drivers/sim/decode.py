"""Decode played AWG samples into what the AODs physically did, slot by slot, with no side channel.

The simulated lab must move atoms only because of the samples the engine streamed, exactly as real AODs
would. This module listens to each channel (ch0 = x AOD, ch1 = y AOD) and reports, per waveform slot and
axis, a list of **tone tracks**: ``(start site, end site, start amplitude fraction, end amplitude
fraction)``. The world (``drivers/sim/world.py``) turns tracks into atom motion.

It is one module over 600 lines on purpose: the window fit, the grid, the run detection and the checks of
the resolution condition are one decoder whose parts share its constants and only make sense together.

Method
------
For every slot, five short windows (at the start, a quarter, the middle, three quarters and the end of the
slot) are fitted by least squares onto sine/cosine pairs at the **half-site frequency grid**: every site
frequency ``nu_k`` and every midpoint ``(nu_k + nu_{k+1}) / 2`` (plus one half-step beyond each end of the
comb to soak up edge energy). The amplitude at each grid point, times the DAC's zero-order-hold gain at its
frequency (``sinc(f / f_s)``: what the card's output, hence the AOD, receives; ``engine.aod_limits.dac_sinc_gain``)
and divided by the site's configured amplitude, is a fraction that is ~1 for a full tone sitting there and ~0
for none. The waveform bank renders tones at ``amplitude / sinc(f / f_s)`` by default
(``waveforms.compensate_dac_sinc``), which reads ~1 everywhere; uncompensated tones read ``sinc(f / f_s)``
(0.67 at 295 MHz and 624 MS/s), and the world sees the shallower tweezers (``FULL_FRACTION``). Then:

- a tone **moving** between k and k+1 is at the half-site point at mid-slot (transitions are symmetric about
  mid-slot), so a local maximum at ``k + 1/2`` in the mid window marks a mover. Adjacent movers form a run
  (tones never cross or merge, so a run moves one way). The run's direction comes from its two end sites:
  the origin end is full early (start, quarter windows) and the destination end is full late (three-quarter,
  end windows). This also decides AOD-chain block shifts, where fades make the start and end spectra identical
  and only the timing tells forward from backward.
- every other site with a tone at start or end is a **static / ramp / fade** track ``(k, k, a_start, a_end)``;
  a site that a mover leaves or enters has that mover's share removed first, so a vacated site that fades in
  reads ``(k, k, 0, 1)`` and an entered site that fades out reads ``(k, k, 1, 0)``.

Resolution condition
--------------------
Least squares separates grid frequencies ``Delta = spacing / 2`` apart once a window spans at least one
period of their beat: ``window_s * spacing_hz / 2 >= 1``. The windows are exactly that long, and they must
fit the slot with room for five of them to mean different times: ``window_s <= 0.4 * slot_duration_s``, i.e.

    slot_duration_s * min_spacing_hz >= 5      (10 us slots: spacing >= 0.5 MHz)

``SampleDecoder`` raises ``DecodeConfigError`` at construction when a configuration violates it (compared on
the configuration's numbers with a relative tolerance; the window is then capped at 0.4 of the slot, so a
product of exactly 5 whose window would round up by a sample is accepted). This is the simulator's limit; the
physical one, which ``SystemConfig`` checks for every configuration, is ``engine.aod_limits.PHYSICAL_MIN_SLOT_SPACING``
(a tone moved one site in one slot must be resolvable from its neighbour within the slot: one beat period). Transitions
must also linger near the half-site point for a good part of a window: min-jerk, and tanh/erf up to a
sharpness of about 8 (at 1 MHz / 10 us) decode; much sharper jumps look like a hand-off at mid-slot.

Speed
-----
``decode`` runs one numba kernel per axis (``_decode_axis``) that projects each window straight from the
interleaved samples and classifies the slot in the same pass. It computes only the coefficients the
classifier reads: every grid point of the mid window, the site points of the start and end windows, and the
site points of the quarter windows only in slots that have a mover. A slot's tracks depend on nothing but
its own samples on that axis, so a slot equal to the previous one (holds, repeated steps) copies its tracks,
a silent slot has none, and every other slot is looked up first in a per-axis cache of recently decoded
slots keyed by two 64-bit universal hashes of its samples (a grid shot's slots recur across cycles and
shots). The cache is a fixed 4-way set-associative table with least-recently-used replacement, allocated
(and touched) when the decoder is built, so memory does not grow while the lab runs. The plain-numpy
path (``amplitudes`` + ``_classify``, i.e. ``decode_reference``) stays as the reference; both run the same
per-slot classifier, and the only difference is float32 rounding in the projection (sequential sums here,
BLAS blocking there), far below every threshold's margin.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

from engine.aod_limits import PHYSICAL_MIN_SLOT_SPACING, dac_sinc_gain
from engine.config import SystemConfig
from engine.routing import position_tones, positions_per_site
from engine.tones import check_below_nyquist, tones_of

__all__ = [
    "FULL_FRACTION",
    "SIMULATOR_MIN_SLOT_SPACING",
    "DecodeConfigError",
    "DecodedSegment",
    "SampleDecoder",
    "site_tones",
]

#: Delivered amplitude fraction (of the configured amplitude; for crossed AODs the product ``amp_x * amp_y``)
#: at or above which a tweezer holds an atom. An AOD in its linear regime diffracts a power proportional to the
#: RF power, so a tweezer's depth goes as the square of this product: the threshold is a quarter of the design
#: depth. A modelling choice (docs/physics-figures.md gives no figure; docs/simulation.md explains it): deep
#: enough that a full tweezer is far above it (a 5 % amplitude error or the hold's 0.92 at 143 MHz and 624 MS/s
#: changes nothing), shallow enough that only a real fault crosses it, such as an uncompensated comb near
#: Nyquist (0.67 x 0.67 = 0.45 at 295 MHz on both axes), where a tweezer spills the atom it carries there.
FULL_FRACTION = 0.5
#: Window centres as fractions of the slot: start, quarter, mid, three-quarter, end (clipped into the slot).
WINDOW_CENTRES = (0.0, 0.25, 0.5, 0.75, 1.0)
#: A mid-window half-site amplitude at least this large (and a local maximum) marks a moving tone.
MOVER_FRACTION = 0.4
#: Non-moving tracks are reported when their start or end amplitude reaches this fraction.
REPORT_FRACTION = 0.3
#: Longest window as a fraction of the slot (see the resolution condition above).
MAX_WINDOW_FRACTION = 0.4
#: The decoder's resolution condition, ``slot_duration_s * spacing_hz >= 2 / MAX_WINDOW_FRACTION``: a limit
#: of this simulator (it follows a move through five windows of a slot), not of the AOD.
SIMULATOR_MIN_SLOT_SPACING = 2 / MAX_WINDOW_FRACTION


#: Memory of each axis's cache of decoded slots (entries: a power of two, at most 8192), and its ways per set.
SLOT_CACHE_BYTES = 8 << 20
CACHE_WAYS = 4

#: A transition's 10-90 % time must be at least this many window lengths for the mid window to see it.
MIN_TRANSITION_PER_WINDOW = 0.8


def transition_width_fraction(shape: str, sharpness: float) -> float:
    """10-90 % duration of a transition, as a fraction of the slot (min-jerk 0.51, tanh ~1.1/v, erf ~1.0/v)."""
    if shape == "min-jerk":
        return 0.507
    if shape == "tanh":
        return float(np.arctanh(0.8 * np.tanh(sharpness)) / sharpness)
    from scipy.special import erf, erfinv

    return float(2 * erfinv(0.8 * erf(np.sqrt(np.pi) * sharpness / 2)) / (np.sqrt(np.pi) * sharpness))


def _max_sharpness(shape: str, window_fraction: float) -> float:
    lo, hi = 0.1, 50.0
    for _ in range(60):
        mid = 0.5 * (lo + hi)
        if transition_width_fraction(shape, mid) >= MIN_TRANSITION_PER_WINDOW * window_fraction:
            lo = mid
        else:
            hi = mid
    return lo


class DecodeConfigError(ValueError):
    """The configuration's tone comb cannot be resolved by the simulated lab's decoder."""


def site_tones(config: SystemConfig, axis: str) -> tuple[np.ndarray, np.ndarray]:
    """``(frequency_hz[n], amplitude[n])`` of the static tone of every site on ``axis`` ('x' or 'y').

    The one place the simulated lab learns the comb, read by ``engine.tones.tones_of`` exactly as the
    waveform bank reads it: the evenly spaced ``start_hz + k * spacing_hz`` or the ``alpha,nu,phi`` CSV
    (amplitudes are fractions of full scale). Under interstitial routing (``engine.routing``) the comb has a
    position every half site, so the decoder's "sites" are positions and its tracks say where each tone is in
    half sites (position ``2 k + 1`` is the channel between sites ``k`` and ``k + 1``).
    """
    tones = config.array.x_tones if axis == "x" else config.array.y_tones
    n = config.array.nx if axis == "x" else config.array.ny
    site = position_tones(tones_of(tones, n, axis), positions_per_site(config.array.routing))
    return site.frequency_hz, site.amplitude


@dataclass
class DecodedSegment:
    """Tone tracks of every whole slot of one segment.

    ``x`` / ``y``: ``float32[n_slots, max_tracks, 4]`` rows ``(site0, site1, amp0, amp1)``; ``x_count`` /
    ``y_count``: how many rows of each slot are valid. ``y`` is None for a one-axis (chain) decoder.
    ``stationary``: no track moves or switches on/off, so playing the segment again changes nothing.
    """

    n_slots: int
    x: np.ndarray
    x_count: np.ndarray
    y: np.ndarray | None
    y_count: np.ndarray | None
    stationary: bool

    def slot(self, i: int) -> tuple[np.ndarray, np.ndarray | None]:
        """``(x_tracks, y_tracks)`` of slot ``i``, each ``float32[m, 4]`` (views)."""
        xt = self.x[i, : self.x_count[i]]
        yt = None if self.y is None or self.y_count is None else self.y[i, : self.y_count[i]]
        return xt, yt

    def describe(self, i: int) -> str:
        xt, yt = self.slot(i)
        return f"slot {i}: x={_fmt_tracks(xt)} y={_fmt_tracks(yt)}"


def _fmt_tracks(t: np.ndarray | None) -> str:
    if t is None:
        return "-"
    return "[" + ", ".join(f"{int(r[0])}->{int(r[1])} {r[2]:.2f}->{r[3]:.2f}" for r in t) + "]"


class _AxisModel:
    """The half-site grid of one axis and the least-squares projector for one window length."""

    def __init__(self, freqs_hz: np.ndarray, amps: np.ndarray, sample_rate_hz: float, axis: str) -> None:
        if freqs_hz.size == 0:
            raise DecodeConfigError(f"{axis} axis has no tones")
        if np.any(np.diff(freqs_hz) <= 0):
            raise DecodeConfigError(f"{axis} tone frequencies must be strictly ascending")
        if np.any(amps <= 0):
            raise DecodeConfigError(f"{axis} tone amplitudes must be positive to normalise by them")
        self.n_sites = int(freqs_hz.size)
        gaps = np.diff(freqs_hz)
        first_gap = gaps[0] if gaps.size else 1e6
        last_gap = gaps[-1] if gaps.size else 1e6
        half = np.empty(2 * self.n_sites + 1)
        half[1::2] = freqs_hz
        half[2:-1:2] = 0.5 * (freqs_hz[:-1] + freqs_hz[1:])
        half[0] = freqs_hz[0] - 0.5 * first_gap
        half[-1] = freqs_hz[-1] + 0.5 * last_gap
        check_below_nyquist(half[0], half[-1], sample_rate_hz, where=f"{axis} axis (half-site margins included)",
                            error=DecodeConfigError)
        self.grid_hz = half
        ref = np.empty_like(half)
        ref[1::2] = amps
        ref[2:-1:2] = 0.5 * (amps[:-1] + amps[1:])
        ref[0], ref[-1] = amps[0], amps[-1]
        # the sample amplitude at each grid point that the DAC's zero-order hold delivers as the configured one:
        # dividing a measured sample amplitude by it gives the delivered fraction
        self.full_sample_amp = ref / dac_sinc_gain(half, sample_rate_hz)
        self.min_gap_hz = float(np.min(np.diff(half)))

    def projector(self, sample_rate_hz: float, n_window: int) -> np.ndarray:
        """``float32[2Q, L]``: least-squares cos/sin coefficients of a window of ``L`` samples."""
        t = np.arange(n_window, dtype=np.float64) / sample_rate_hz
        arg = 2 * np.pi * np.outer(t, self.grid_hz)
        basis = np.concatenate([np.cos(arg), np.sin(arg)], axis=1)
        return np.linalg.pinv(basis).astype(np.float32)


class SampleDecoder:
    """Turns ``int16[n, n_channels]`` samples into per-slot tone tracks (see the module docstring).

    ``full_scale``: int16 counts of a tone of amplitude 1.0 (a tone of config amplitude ``alpha`` has
    ``alpha * full_scale`` counts of amplitude).
    """

    def __init__(
        self,
        config: SystemConfig,
        *,
        sample_rate_hz: float | None = None,
        n_channels: int | None = None,
        full_scale: float = 32767.0,
    ) -> None:
        self.sample_rate_hz = float(sample_rate_hz if sample_rate_hz is not None else config.waveforms.sample_rate_hz)
        self.slot_samples = int(round(self.sample_rate_hz * config.waveforms.slot_duration_s))
        self.slot_s = self.slot_samples / self.sample_rate_hz
        self.trap_source = config.array.trap_source
        needed = 1 if self.trap_source == "aod" else 2
        self.n_channels = needed if n_channels is None else int(n_channels)
        if self.n_channels < needed:
            raise DecodeConfigError(
                f"trap_source '{self.trap_source}' needs {needed} AWG channel(s) (x{', y' if needed == 2 else ''}) "
                f"but the card has {self.n_channels}"
            )
        self.full_scale = float(full_scale)
        axes = [_AxisModel(*site_tones(config, "x"), self.sample_rate_hz, "x")]
        if needed == 2:
            axes.append(_AxisModel(*site_tones(config, "y"), self.sample_rate_hz, "y"))
        self._axes = axes
        min_gap = min(a.min_gap_hz for a in axes)
        spacing = 2 * min_gap
        # the condition is stated on the configuration's own numbers, with a relative tolerance: 10 us x 0.5 MHz
        # is 5 even where the product rounds to 4.999999999 or the window rounds up to a whole sample
        if config.waveforms.slot_duration_s * spacing < SIMULATOR_MIN_SLOT_SPACING * (1 - 1e-9):
            raise DecodeConfigError(
                f"the simulated AWG's decoder cannot resolve tones {spacing / 1e6:g} MHz apart in "
                f"{config.waveforms.slot_duration_s * 1e6:g} us slots: it needs slot_duration_s * spacing_hz >= "
                f"{SIMULATOR_MIN_SLOT_SPACING:g} (got {config.waveforms.slot_duration_s * spacing:.6g}). This is a "
                "limit of the simulated lab (five decoding windows per slot), not of an AOD, which needs >= "
                f"{PHYSICAL_MIN_SLOT_SPACING:g}; widen the tone spacing or lengthen waveforms.slot_duration_s"
            )
        # one beat period of the half-site grid, but never more than the slot leaves to each window (at the limit
        # the two differ by the rounding of a sample, and least squares still separates the grid)
        self.window_samples = min(
            int(np.ceil(self.sample_rate_hz / min_gap - 1e-9)),
            int(np.floor(MAX_WINDOW_FRACTION * self.slot_samples + 1e-9)),
        )
        width = transition_width_fraction(config.waveforms.shape, config.waveforms.shape_sharpness)
        window_fraction = self.window_samples / self.slot_samples
        if width < MIN_TRANSITION_PER_WINDOW * window_fraction:
            raise DecodeConfigError(
                f"waveforms.shape '{config.waveforms.shape}' with shape_sharpness "
                f"{config.waveforms.shape_sharpness:g} moves a tone in {width:.2f} of a slot (10-90 %), faster than "
                f"the simulated AWG's decoding window ({window_fraction:.2f} of a slot) can follow; lower "
                f"shape_sharpness to at most {_max_sharpness(config.waveforms.shape, window_fraction):.1f}, use "
                "min-jerk, or widen the tone spacing"
            )
        n, w = self.slot_samples, self.window_samples
        self.window_offsets = np.array(
            [min(max(int(round(c * n - w / 2)), 0), n - w) for c in WINDOW_CENTRES], dtype=np.int64
        )
        self._proj = [a.projector(self.sample_rate_hz, w) for a in axes]
        self._gather = self.window_offsets[:, None] + np.arange(w, dtype=np.int64)[None, :]  # [W, L]
        self._kernel_args = [
            _KernelArgs.build(p, (a.full_sample_amp * self.full_scale).astype(np.float32), a.n_sites)
            for p, a in zip(self._proj, axes, strict=True)
        ]
        # the cache's hash weights (``_hash_slots``): fixed random 32-bit numbers, one pair per sample of a slot
        self._hash_weights = np.random.default_rng(0x51075).integers(0, 1 << 32, (2, n), dtype=np.uint64)
        # compile (or load from cache) the kernels now, not during the first playback
        q = self._axes[0].grid_hz.size
        _classify(
            np.zeros((1, len(WINDOW_CENTRES), q), np.float32), self._axes[0].n_sites, MOVER_FRACTION,
            REPORT_FRACTION, np.zeros((1, 2 * self._axes[0].n_sites, 4), np.float32), np.zeros(1, np.int32),
        )
        self.decode(np.zeros((2 * self.slot_samples, self.n_channels), dtype=np.int16))

    @property
    def n_axes(self) -> int:
        return len(self._axes)

    def amplitudes(self, samples: np.ndarray, axis: int = 0) -> np.ndarray:
        """``float32[n_slots, 5, 2 n_sites + 1]`` normalised amplitudes on the half-site grid of ``axis``.

        Grid index ``q``: ``q = 2k + 1`` is site k, ``q = 2k + 2`` is site ``k + 1/2``, ``q = 0`` is ``-1/2``.
        """
        n_slots = samples.shape[0] // self.slot_samples
        model = self._axes[axis]
        if n_slots == 0:
            return np.zeros((0, len(WINDOW_CENTRES), model.grid_hz.size), dtype=np.float32)
        idx = (np.arange(n_slots, dtype=np.int64) * self.slot_samples)[:, None, None] + self._gather[None]
        x = samples[:, axis][idx].astype(np.float32)  # [S, W, L]
        coef = x.reshape(-1, x.shape[-1]) @ self._proj[axis].T  # [S*W, 2Q]
        q = model.grid_hz.size
        amp = np.hypot(coef[:, :q], coef[:, q:])
        amp /= (model.full_sample_amp * self.full_scale).astype(np.float32)
        return amp.reshape(n_slots, len(WINDOW_CENTRES), q)

    def decode(self, samples: np.ndarray) -> DecodedSegment:
        """Tracks of every whole slot in ``samples`` (``int16[n, n_channels]``; a shorter tail is ignored)."""
        if samples.ndim != 2 or samples.shape[1] < self.n_axes:
            raise ValueError(f"expected int16[n, >= {self.n_axes}] samples, got shape {samples.shape}")
        if samples.dtype != np.int16:
            return self.decode_reference(samples)
        samples = np.ascontiguousarray(samples)
        n_slots = samples.shape[0] // self.slot_samples
        hashes = np.empty((self.n_axes, n_slots, 2), dtype=np.uint64)
        silent = np.empty((self.n_axes, n_slots), dtype=np.bool_)
        _hash_slots(samples.reshape(-1), samples.shape[1], self.slot_samples, self._hash_weights, hashes, silent)
        tracks: list[np.ndarray] = []
        counts: list[np.ndarray] = []
        for axis, model in enumerate(self._axes):
            out = np.zeros((n_slots, 2 * model.n_sites, 4), dtype=np.float32)
            cnt = np.zeros(n_slots, dtype=np.int32)
            k = self._kernel_args[axis]
            _decode_axis(
                samples, axis, self.slot_samples, self.window_offsets, k.pt_mid, k.den_mid, k.pt_site, k.den_site,
                model.n_sites, MOVER_FRACTION, REPORT_FRACTION, k.amp, k.acc, out, cnt,
                hashes[axis], silent[axis], k.cache_meta, k.cache_clock, k.cache_tracks, k.cache_count,
            )  # fmt: skip
            tracks.append(out)
            counts.append(cnt)
        stationary = all(_stationary(t, c, FULL_FRACTION) for t, c in zip(tracks, counts, strict=True))
        return _segment(n_slots, tracks, counts, stationary)

    def decode_reference(self, samples: np.ndarray) -> DecodedSegment:
        """``decode`` the plain way: every amplitude of every window by one matrix product, then classify."""
        if samples.ndim != 2 or samples.shape[1] < self.n_axes:
            raise ValueError(f"expected int16[n, >= {self.n_axes}] samples, got shape {samples.shape}")
        n_slots = samples.shape[0] // self.slot_samples
        tracks: list[np.ndarray] = []
        counts: list[np.ndarray] = []
        silent = not np.any(samples[: n_slots * self.slot_samples, : self.n_axes])
        for axis, model in enumerate(self._axes):
            out = np.zeros((n_slots, 2 * model.n_sites, 4), dtype=np.float32)
            cnt = np.zeros(n_slots, dtype=np.int32)
            if not silent and n_slots:
                _classify(self.amplitudes(samples, axis), model.n_sites, MOVER_FRACTION, REPORT_FRACTION, out, cnt)
            tracks.append(out)
            counts.append(cnt)
        stationary = all(_is_stationary(t, c, FULL_FRACTION) for t, c in zip(tracks, counts, strict=True))
        return _segment(n_slots, tracks, counts, stationary)


def _segment(n_slots: int, tracks: list[np.ndarray], counts: list[np.ndarray], stationary: bool) -> DecodedSegment:
    return DecodedSegment(
        n_slots=n_slots,
        x=tracks[0],
        x_count=counts[0],
        y=tracks[1] if len(tracks) > 1 else None,
        y_count=counts[1] if len(counts) > 1 else None,
        stationary=stationary,
    )


@dataclass
class _KernelArgs:
    """One axis's projector rows in the layout ``_decode_axis`` reads, plus its scratch.

    ``pt_mid``: ``float32[L, 2(2n - 1)]``, the cos then sin rows of grid points ``q = 1 .. 2n - 1`` (all the
    mid window's points the classifier reads), transposed so a window is summed sample by sample;
    ``pt_site``: ``float32[L, 2n]``, the same for the site points ``q = 2k + 1``. The rows are rows of the
    same least-squares projector (``_AxisModel.projector``): a subset of its outputs, not a different fit.
    """

    pt_mid: np.ndarray
    den_mid: np.ndarray
    pt_site: np.ndarray
    den_site: np.ndarray
    amp: np.ndarray
    acc: np.ndarray
    cache_meta: np.ndarray  # uint64[entries, 3]: the slot's two hashes, and when it was last used (0: empty)
    cache_clock: np.ndarray  # uint64[1]: lookups so far (the "last used" clock)
    cache_tracks: np.ndarray  # float32[entries, 2 n_sites, 4]
    cache_count: np.ndarray  # int32[entries]

    @classmethod
    def build(cls, proj: np.ndarray, den: np.ndarray, n_sites: int) -> _KernelArgs:
        q = den.size
        mid = np.arange(1, 2 * n_sites)
        site = np.arange(1, 2 * n_sites, 2)
        entries = 1 << int(np.clip(np.log2(SLOT_CACHE_BYTES / (2 * n_sites * 16)), 4, 13))
        # np.full writes every page now: the cache's memory is resident from the start, never grows later
        return cls(
            pt_mid=np.ascontiguousarray(np.concatenate([proj[mid], proj[q + mid]]).T),
            den_mid=np.ascontiguousarray(den[mid]),
            pt_site=np.ascontiguousarray(np.concatenate([proj[site], proj[q + site]]).T),
            den_site=np.ascontiguousarray(den[site]),
            amp=np.zeros((len(WINDOW_CENTRES), q), dtype=np.float32),
            acc=np.zeros(2 * mid.size, dtype=np.float32),
            cache_meta=np.full((entries, 3), 0, dtype=np.uint64),
            cache_clock=np.zeros(1, dtype=np.uint64),
            cache_tracks=np.full((entries, 2 * n_sites, 4), 0.0, dtype=np.float32),
            cache_count=np.full(entries, 0, dtype=np.int32),
        )


@njit(cache=True, nogil=True)
def _project(samples: np.ndarray, axis: int, start: int, pt: np.ndarray, acc: np.ndarray) -> None:
    """``acc[r] = sum_l pt[l, r] * samples[start + l, axis]`` in float32, summed in sample order.

    Sample-major with the rows innermost: the inner loop is independent per row, so it vectorises without
    reassociating any sum (deterministic, no fastmath), and four samples per pass cut the ``acc`` traffic
    (the parenthesised chain is the same sequential sum; eight per pass, FMA contraction and blocking four
    windows per pass over ``pt`` measured no faster).
    """
    n_rows = pt.shape[1]
    n = pt.shape[0]
    acc[:n_rows] = 0.0
    n4 = n - n % 4
    for i in range(0, n4, 4):
        x0 = np.float32(samples[start + i, axis])
        x1 = np.float32(samples[start + i + 1, axis])
        x2 = np.float32(samples[start + i + 2, axis])
        x3 = np.float32(samples[start + i + 3, axis])
        p0 = pt[i]
        p1 = pt[i + 1]
        p2 = pt[i + 2]
        p3 = pt[i + 3]
        for r in range(n_rows):
            acc[r] = (((acc[r] + p0[r] * x0) + p1[r] * x1) + p2[r] * x2) + p3[r] * x3
    for i in range(n4, n):
        x = np.float32(samples[start + i, axis])
        p = pt[i]
        for r in range(n_rows):
            acc[r] += p[r] * x


@njit(cache=True, nogil=True)
def _window_amplitudes(
    samples: np.ndarray, axis: int, start: int, pt: np.ndarray, den: np.ndarray, acc: np.ndarray,
    amp_w: np.ndarray, q0: int, q_step: int,
) -> None:  # fmt: skip
    """``amp_w[q0 + i * q_step] = |(cos, sin) coefficient i| / den[i]`` for the rows of ``pt``."""
    _project(samples, axis, start, pt, acc)
    m = den.size
    for i in range(m):
        amp_w[q0 + i * q_step] = np.float32(np.hypot(acc[i], acc[m + i])) / den[i]


@njit(cache=True, nogil=True)
def _decode_axis(
    samples: np.ndarray,
    axis: int,
    slot_samples: int,
    offsets: np.ndarray,
    pt_mid: np.ndarray,
    den_mid: np.ndarray,
    pt_site: np.ndarray,
    den_site: np.ndarray,
    n_sites: int,
    mover_frac: float,
    report_frac: float,
    amp: np.ndarray,
    acc: np.ndarray,
    out: np.ndarray,
    count: np.ndarray,
    hashes: np.ndarray,
    silent: np.ndarray,
    cache_meta: np.ndarray,
    cache_clock: np.ndarray,
    cache_tracks: np.ndarray,
    cache_count: np.ndarray,
) -> None:
    """Project and classify every slot of one axis (see "Speed" in the module docstring); ``hashes[s]`` and
    ``silent[s]`` come from ``_hash_slots``."""
    mover = np.zeros(max(n_sites - 1, 1), dtype=np.bool_)
    origin = np.zeros(n_sites, dtype=np.bool_)
    dest = np.zeros(n_sites, dtype=np.bool_)
    set_mask = np.uint64(cache_meta.shape[0] // CACHE_WAYS - 1)
    for s in range(out.shape[0]):
        base = s * slot_samples
        if silent[s]:  # every amplitude is 0: no tracks
            count[s] = 0
            continue
        h1 = hashes[s, 0]
        h2 = hashes[s, 1]
        if s > 0 and h1 == hashes[s - 1, 0] and h2 == hashes[s - 1, 1]:
            same = True  # very likely the previous slot again: check it sample by sample
            for i in range(slot_samples):
                if samples[base + i, axis] != samples[base - slot_samples + i, axis]:
                    same = False
                    break
            if same:  # the same samples decode to the same tracks
                m = count[s - 1]
                out[s, :m] = out[s - 1, :m]
                count[s] = m
                continue
        c = _cache_way(cache_meta, cache_clock, int(h1 & set_mask) * CACHE_WAYS, h1, h2)
        if cache_meta[c, 0] == h1 and cache_meta[c, 1] == h2:
            m = cache_count[c]
            out[s, :m] = cache_tracks[c, :m]
            count[s] = m
            continue
        amp[:, :] = 0.0
        _window_amplitudes(samples, axis, base + offsets[2], pt_mid, den_mid, acc, amp[2], 1, 1)
        _window_amplitudes(samples, axis, base + offsets[0], pt_site, den_site, acc, amp[0], 1, 2)
        _window_amplitudes(samples, axis, base + offsets[4], pt_site, den_site, acc, amp[4], 1, 2)
        if _find_movers(amp, n_sites, mover_frac, mover):  # runs need the quarter windows for their direction
            _window_amplitudes(samples, axis, base + offsets[1], pt_site, den_site, acc, amp[1], 1, 2)
            _window_amplitudes(samples, axis, base + offsets[3], pt_site, den_site, acc, amp[3], 1, 2)
        m = _classify_slot(amp, n_sites, mover_frac, report_frac, out[s], mover, origin, dest)
        count[s] = m
        cache_meta[c, 0] = h1
        cache_meta[c, 1] = h2
        cache_tracks[c, :m] = out[s, :m]
        cache_count[c] = m


@njit(cache=True, nogil=True)
def _cache_way(meta: np.ndarray, clock: np.ndarray, first: int, h1: np.uint64, h2: np.uint64) -> int:
    """The entry of the set starting at ``first`` that holds ``(h1, h2)``, else the least recently used one
    (an empty entry first), to be filled; either way it is marked used now."""
    clock[0] += np.uint64(1)
    pick = first
    for c in range(first, first + CACHE_WAYS):
        if meta[c, 2] != 0 and meta[c, 0] == h1 and meta[c, 1] == h2:
            pick = c
            break
        if meta[c, 2] < meta[pick, 2]:
            pick = c
    else:
        meta[pick, 0] = ~h1  # claimed for a new slot: cannot match (h1, h2) until it is filled
    meta[pick, 2] = clock[0]
    return pick


@njit(cache=True, nogil=True)
def _hash_slots(
    flat: np.ndarray, n_channels: int, slot_samples: int, weights: np.ndarray, hashes: np.ndarray, silent: np.ndarray
) -> None:
    """``hashes[axis, s]``: two independent multilinear hashes ``sum_i w[i] * u[i]`` of slot ``s``'s samples on
    ``axis`` (``u`` the samples as uint16, ``w`` two rows of fixed random 32-bit weights); ``silent[axis, s]``:
    all its samples are 0. ``flat`` is the C-ordered ``int16[n, n_channels]`` samples, flattened.

    Why these: each term is below 2^48, so for slots of fewer than 2^16 samples (10 us at up to 6.5 GS/s) the
    sums never wrap, and two different slots (some ``u_j`` differs) collide in one hash only if ``w_j`` hits
    one value out of 2^32: in both, about 2^-64 per comparison whatever the samples are (a universal hash
    family, so no assumption about the waveforms is needed). It is also a multiply-add loop, unlike byte-serial
    hashes (~3x slower here); one loop serves every channel count: a copy with the stride fixed at 2 was no
    faster (0.78 ns a sample either way on the dev machine, 2 and 4 channels alike).
    """
    for axis in range(hashes.shape[0]):
        for s in range(hashes.shape[1]):
            start = n_channels * s * slot_samples + axis
            h1, h2, nz = _hash_stride(flat, start, n_channels, slot_samples, weights)
            hashes[axis, s, 0] = h1
            hashes[axis, s, 1] = h2
            silent[axis, s] = nz == 0


@njit(cache=True, nogil=True)
def _hash_stride(
    flat: np.ndarray, start: int, stride: int, n: int, weights: np.ndarray
) -> tuple[np.uint64, np.uint64, int]:
    """The two hashes of ``flat[start + stride * i]``, ``i < n``, and the OR of those samples."""
    h1 = np.uint64(0)
    h2 = np.uint64(0)
    nz = 0
    for i in range(n):
        v = flat[start + stride * i]
        nz |= v
        u = np.uint64(np.uint16(v))
        h1 += weights[0, i] * u
        h2 += weights[1, i] * u
    return h1, h2, nz


@njit(cache=True, nogil=True)
def _stationary(tracks: np.ndarray, count: np.ndarray, full: float) -> bool:
    """``_is_stationary`` as a loop: no track moves or crosses ``full`` in any slot."""
    for s in range(tracks.shape[0]):
        for m in range(count[s]):
            t = tracks[s, m]
            if t[0] != t[1] or (t[2] >= full) != (t[3] >= full):
                return False
    return True


@njit(cache=True, nogil=True)
def _classify(
    amp: np.ndarray, n_sites: int, mover_frac: float, report_frac: float, out: np.ndarray, count: np.ndarray
) -> None:
    """Fill ``out[s, :count[s]]`` with tracks from the amplitudes ``amp[s, window, q]`` (see module docstring)."""
    mover = np.zeros(max(n_sites - 1, 1), dtype=np.bool_)
    origin = np.zeros(n_sites, dtype=np.bool_)
    dest = np.zeros(n_sites, dtype=np.bool_)
    for s in range(amp.shape[0]):
        _find_movers(amp[s], n_sites, mover_frac, mover)
        count[s] = _classify_slot(amp[s], n_sites, mover_frac, report_frac, out[s], mover, origin, dest)


@njit(cache=True, nogil=True)
def _find_movers(a: np.ndarray, n_sites: int, mover_frac: float, mover: np.ndarray) -> bool:
    """``mover[k]``: a local maximum of at least ``mover_frac`` at ``k + 1/2`` in the mid window; any?"""
    found = False
    for k in range(n_sites - 1):
        q = 2 * k + 2
        v = a[2, q]
        mover[k] = v >= mover_frac and v >= a[2, q - 1] and v >= a[2, q + 1]
        found = found or mover[k]
    return found


@njit(cache=True, nogil=True)
def _classify_slot(
    a: np.ndarray, n_sites: int, mover_frac: float, report_frac: float, out: np.ndarray, mover: np.ndarray,
    origin: np.ndarray, dest: np.ndarray,
) -> int:
    """Tracks of one slot from its amplitudes ``a[window, q]`` and ``mover`` (from ``_find_movers``) into
    ``out``; returns how many. Reads ``a[2, 1 .. 2n - 1]``, the site points of windows 0 and 4, and the
    site points of windows 1 and 3 at the ends of mover runs only."""
    m = 0
    origin[:] = False
    dest[:] = False
    k = 0
    while k < n_sites - 1:
        if not mover[k]:
            k += 1
            continue
        ka = k
        while k + 1 < n_sites - 1 and mover[k + 1]:
            k += 1
        kb = k
        lo = 2 * ka + 1
        hi = 2 * (kb + 1) + 1
        early = a[0, lo] + a[1, lo] - a[0, hi] - a[1, hi]
        late = a[3, hi] + a[4, hi] - a[3, lo] - a[4, lo]
        forward = early + late >= 0.0
        for j in range(ka, kb + 1):
            src = j if forward else j + 1
            dst = j + 1 if forward else j
            origin[src] = True
            dest[dst] = True
            out[m, 0] = src
            out[m, 1] = dst
            out[m, 2] = a[0, 2 * src + 1]
            out[m, 3] = a[4, 2 * dst + 1]
            m += 1
        k += 1
    for k in range(n_sites):
        a0 = 0.0 if origin[k] else a[0, 2 * k + 1]
        a1 = 0.0 if dest[k] else a[4, 2 * k + 1]
        if a0 >= report_frac or a1 >= report_frac:
            out[m, 0] = k
            out[m, 1] = k
            out[m, 2] = a0
            out[m, 3] = a1
            m += 1
    return m


def _is_stationary(tracks: np.ndarray, count: np.ndarray, full: float) -> bool:
    for s in range(tracks.shape[0]):
        t = tracks[s, : count[s]]
        if np.any(t[:, 0] != t[:, 1]) or np.any((t[:, 2] >= full) != (t[:, 3] >= full)):
            return False
    return True
