"""Decode played AWG samples into what the AODs physically did, slot by slot, with no side channel.

The simulated lab must move atoms only because of the samples the engine streamed, exactly as real AODs
would. This module listens to each channel (ch0 = x AOD, ch1 = y AOD) and reports, per waveform slot and
axis, a list of **tone tracks**: ``(start site, end site, start amplitude fraction, end amplitude
fraction)``. The world (``drivers/sim/world.py``) turns tracks into atom motion.

Method
------
For every slot, five short windows (at the start, a quarter, the middle, three quarters and the end of the
slot) are fitted by least squares onto sine/cosine pairs at the **half-site frequency grid**: every site
frequency ``nu_k`` and every midpoint ``(nu_k + nu_{k+1}) / 2`` (plus one half-step beyond each end of the
comb to soak up edge energy). The amplitude at each grid point, divided by the site's static amplitude, is a
fraction that is ~1 for a full tone sitting there and ~0 for none. Then:

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

``SampleDecoder`` raises ``DecodeConfigError`` at construction when a configuration violates it. Transitions
must also linger near the half-site point for a good part of a window: min-jerk, and tanh/erf up to a
sharpness of about 8 (at 1 MHz / 10 us) decode; much sharper jumps look like a hand-off at mid-slot.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numba import njit

from engine.config import SystemConfig

__all__ = [
    "FULL_FRACTION",
    "DecodeConfigError",
    "DecodedSegment",
    "SampleDecoder",
    "site_tones",
]

#: Amplitude (or tweezer depth) fraction at or above which a tone counts as "on" (holds an atom).
FULL_FRACTION = 0.5
#: Window centres as fractions of the slot: start, quarter, mid, three-quarter, end (clipped into the slot).
WINDOW_CENTRES = (0.0, 0.25, 0.5, 0.75, 1.0)
#: A mid-window half-site amplitude at least this large (and a local maximum) marks a moving tone.
MOVER_FRACTION = 0.4
#: Non-moving tracks are reported when their start or end amplitude reaches this fraction.
REPORT_FRACTION = 0.3
#: Longest window as a fraction of the slot (see the resolution condition above).
MAX_WINDOW_FRACTION = 0.4


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

    The one place the simulated lab learns the comb: the evenly spaced ``start_hz + k * spacing_hz`` or the
    ``alpha,nu,phi`` CSV, exactly as configured (amplitudes are fractions of full scale).
    """
    tones = config.array.x_tones if axis == "x" else config.array.y_tones
    n = config.array.nx if axis == "x" else config.array.ny
    if tones.csv is None:
        freqs = tones.start_hz + tones.spacing_hz * np.arange(n, dtype=np.float64)
        return freqs, np.full(n, tones.amplitude, dtype=np.float64)
    rows: list[tuple[float, float]] = []
    with Path(tones.csv).open(newline="") as fh:
        for rec in csv.DictReader(fh):
            rows.append((float(rec["nu"]), float(rec["alpha"])))
    if len(rows) < n:
        raise DecodeConfigError(f"array.{axis}_tones.csv {tones.csv} has {len(rows)} rows but the axis needs {n}")
    arr = np.asarray(rows[:n], dtype=np.float64)
    return arr[:, 0].copy(), arr[:, 1].copy()


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
        if half[0] <= 0 or half[-1] >= sample_rate_hz / 2:
            raise DecodeConfigError(
                f"{axis} tones span {half[0]:g}..{half[-1]:g} Hz (with half-site margins), outside (0, "
                f"Nyquist = {sample_rate_hz / 2:g}) Hz"
            )
        self.grid_hz = half
        ref = np.empty_like(half)
        ref[1::2] = amps
        ref[2:-1:2] = 0.5 * (amps[:-1] + amps[1:])
        ref[0], ref[-1] = amps[0], amps[-1]
        self.ref_amp = ref
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
        self.window_samples = int(np.ceil(self.sample_rate_hz / min_gap - 1e-9))
        if self.window_samples > MAX_WINDOW_FRACTION * self.slot_samples:
            spacing = 2 * min_gap
            raise DecodeConfigError(
                f"the simulated AWG cannot resolve tones {spacing / 1e6:g} MHz apart in "
                f"{config.waveforms.slot_duration_s * 1e6:g} us slots: it needs slot_duration_s * spacing_hz >= "
                f"{2 / MAX_WINDOW_FRACTION:g} (got {config.waveforms.slot_duration_s * spacing:g}); widen the tone "
                "spacing or lengthen waveforms.slot_duration_s"
            )
        width = transition_width_fraction(config.waveforms.shape, config.waveforms.shape_sharpness)
        if width < MIN_TRANSITION_PER_WINDOW * self.window_samples / self.slot_samples:
            raise DecodeConfigError(
                f"waveforms.shape '{config.waveforms.shape}' with shape_sharpness {config.waveforms.shape_sharpness:g} "
                f"moves a tone in {width:.2f} of a slot (10-90 %), faster than the simulated AWG's decoding window "
                f"({self.window_samples / self.slot_samples:.2f} of a slot) can follow; lower shape_sharpness to at most "
                f"{_max_sharpness(config.waveforms.shape, self.window_samples / self.slot_samples):.1f}, use min-jerk, or "
                "widen the tone spacing"
            )
        n, w = self.slot_samples, self.window_samples
        self.window_offsets = np.array(
            [min(max(int(round(c * n - w / 2)), 0), n - w) for c in WINDOW_CENTRES], dtype=np.int64
        )
        self._proj = [a.projector(self.sample_rate_hz, w) for a in axes]
        self._gather = self.window_offsets[:, None] + np.arange(w, dtype=np.int64)[None, :]  # [W, L]
        # compile (or load from cache) the classifier now, not during the first playback
        q = self._axes[0].grid_hz.size
        _classify(
            np.zeros((1, len(WINDOW_CENTRES), q), np.float32), self._axes[0].n_sites, MOVER_FRACTION,
            REPORT_FRACTION, np.zeros((1, 2 * self._axes[0].n_sites, 4), np.float32), np.zeros(1, np.int32),
        )

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
        amp /= (model.ref_amp * self.full_scale).astype(np.float32)
        return amp.reshape(n_slots, len(WINDOW_CENTRES), q)

    def decode(self, samples: np.ndarray) -> DecodedSegment:
        """Tracks of every whole slot in ``samples`` (``int16[n, n_channels]``; a tail shorter than a slot is ignored)."""
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
        stationary = all(_is_stationary(t, c, FULL_FRACTION) for t, c in zip(tracks, counts))
        return DecodedSegment(
            n_slots=n_slots,
            x=tracks[0],
            x_count=counts[0],
            y=tracks[1] if len(tracks) > 1 else None,
            y_count=counts[1] if len(counts) > 1 else None,
            stationary=stationary,
        )


@njit(cache=True, nogil=True)
def _classify(
    amp: np.ndarray, n_sites: int, mover_frac: float, report_frac: float, out: np.ndarray, count: np.ndarray
) -> None:
    """Fill ``out[s, :count[s]]`` with tracks from the amplitudes ``amp[s, window, q]`` (see module docstring)."""
    mover = np.zeros(max(n_sites - 1, 1), dtype=np.bool_)
    origin = np.zeros(n_sites, dtype=np.bool_)
    dest = np.zeros(n_sites, dtype=np.bool_)
    for s in range(amp.shape[0]):
        a = amp[s]
        m = 0
        for k in range(n_sites - 1):
            q = 2 * k + 2
            v = a[2, q]
            mover[k] = v >= mover_frac and v >= a[2, q - 1] and v >= a[2, q + 1]
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
                out[s, m, 0] = src
                out[s, m, 1] = dst
                out[s, m, 2] = a[0, 2 * src + 1]
                out[s, m, 3] = a[4, 2 * dst + 1]
                m += 1
            k += 1
        for k in range(n_sites):
            a0 = 0.0 if origin[k] else a[0, 2 * k + 1]
            a1 = 0.0 if dest[k] else a[4, 2 * k + 1]
            if a0 >= report_frac or a1 >= report_frac:
                out[s, m, 0] = k
                out[s, m, 1] = k
                out[s, m, 2] = a0
                out[s, m, 3] = a1
                m += 1
        count[s] = m


def _is_stationary(tracks: np.ndarray, count: np.ndarray, full: float) -> bool:
    for s in range(tracks.shape[0]):
        t = tracks[s, : count[s]]
        if np.any(t[:, 0] != t[:, 1]) or np.any((t[:, 2] >= full) != (t[:, 3] >= full)):
            return False
    return True
