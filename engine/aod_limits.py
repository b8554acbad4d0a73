"""What the AODs and the RF chain in front of them allow: tone resolution, the AOD's band, the DAC's images,
and the RF limits of each channel (peak amplitude, summed tone amplitude, RF power, tone count).

Physics, in the order a signal meets it:

- **Resolution.** A tone moved one site in one slot must be told from its neighbour within that slot, which
  takes at least one period of their beat: ``slot_duration_s * spacing_hz >= PHYSICAL_MIN_SLOT_SPACING``
  (= 1). This is the physical limit; the simulated lab's decoder needs more (``drivers.sim.decode``,
  ``SIMULATOR_MIN_SLOT_SPACING`` = 5) and says so when it refuses.
- **The DAC.** A card sampling at ``f_s`` plays every tone ``f`` also as an image at ``f_s - f`` (and its
  zero-order hold scales a tone's amplitude by ``sinc(f / f_s)``; ``dac_sinc_gain``). An image that falls
  inside the AOD's band is diffracted like a tone: a spurious tweezer. So the comb must lie inside the band
  and every image outside it. With ``waveforms.compensate_dac_sinc`` (the default) every tone is rendered at
  ``sample_amplitudes``: its configured amplitude divided by the hold's gain at its frequency, so what reaches
  the amplifier is the configured comb, flat across the band; the limits below are checked on those larger
  sample amplitudes (they are what the DAC must produce).
- **The AOD's band.** An AOD diffracts efficiently only within its bandwidth around its centre frequency
  (tens of MHz); a comb outside it makes no traps there.
- **The amplifier.** The card's full scale is ``devices.spectrum.amplitude_mv`` peak volts at the load
  (``load_ohm``). A tone of amplitude ``a`` (fraction of full scale) delivers ``(a V)^2 / (2 R)``; a comb the
  sum over its tones. Each channel may cap that power (dBm or mW), the largest sample, the sum of its tone
  amplitudes (which bounds the peak of any phase choice) and the number of tones.

The configuration is checked once (``comb_problems``, called by ``SystemConfig``); every rendered segment is
checked again before upload (``SegmentGuard``, called by the streamer and by the simulated AWG), because the
samples, not the configuration, are what reach the amplifier.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

__all__ = [
    "PHYSICAL_MIN_SLOT_SPACING",
    "ChannelLimits",
    "RFLimitError",
    "SegmentGuard",
    "band_problem",
    "comb_power_w",
    "dac_sinc_gain",
    "dbm_to_w",
    "resolution_problem",
    "segment_levels",
    "sample_amplitudes",
    "segment_levels_reference",
    "w_to_dbm",
]

#: ``slot_duration_s * spacing_hz`` at least this: one beat period of neighbouring tones per slot.
PHYSICAL_MIN_SLOT_SPACING = 1.0
#: Relative tolerance of every comparison of configured numbers (10 us x 0.5 MHz is 5, not 4.999999999).
_REL_TOL = 1e-9


class RFLimitError(ValueError):
    """A segment or a comb would exceed a channel's RF limit or leave the AOD's band."""


def dbm_to_w(dbm: float) -> float:
    return 1e-3 * 10 ** (dbm / 10)


def w_to_dbm(watts: float) -> float:
    return 10 * math.log10(watts / 1e-3) if watts > 0 else -math.inf


def dac_sinc_gain(frequency_hz: np.ndarray | float, sample_rate_hz: float) -> np.ndarray:
    """Amplitude of a tone after the DAC's zero-order hold, relative to its sample amplitude: ``sinc(f / f_s)``
    (0.67 at 295 MHz and 624 MS/s)."""
    return np.sinc(np.asarray(frequency_hz, dtype=np.float64) / sample_rate_hz)


def sample_amplitudes(
    frequency_hz: np.ndarray, amplitude: np.ndarray, sample_rate_hz: float, compensate: bool
) -> np.ndarray:
    """The sample amplitude of every static tone (fraction of full scale) that delivers ``amplitude`` after
    the DAC's zero-order hold: ``amplitude / sinc(f / f_s)`` when ``compensate``, else ``amplitude`` as it is.

    A moving tone ramps its sample amplitude linearly in the transition shape between the compensated
    amplitudes of its two sites, while its frequency ramps in the same shape; since the hold's gain is smooth
    in frequency the product stays flat to second order: at most 7e-5 off over a 5 MHz step at 290 MHz and
    624 MS/s (1e-5 over 1 MHz at 140 MHz and 313.6 MS/s), against 1e-3 for the int16 rounding of a 0.015 tone
    (half a count of 491). Compensating at the slot's midpoint frequency instead would be off by up to 7e-3.
    So the compensation is folded into the per-tone amplitudes the waveform bank precomputes, and the hot
    path does no extra work."""
    amp = np.asarray(amplitude, dtype=np.float64)
    if not compensate:
        return amp.copy()
    return amp / dac_sinc_gain(frequency_hz, sample_rate_hz)


def comb_power_w(amplitudes: np.ndarray, full_scale_v: float, load_ohm: float) -> float:
    """Mean RF power of tones of these amplitudes (fractions of full scale) into ``load_ohm``: sum of a^2 V^2 / 2R."""
    return float(np.sum(np.square(amplitudes)) * full_scale_v**2 / (2 * load_ohm))


def resolution_problem(slot_duration_s: float, spacing_hz: float, *, where: str) -> str | None:
    """Why an AOD cannot resolve neighbouring tones ``spacing_hz`` apart within one slot, or None."""
    product = slot_duration_s * spacing_hz
    if product >= PHYSICAL_MIN_SLOT_SPACING * (1 - _REL_TOL):
        return None
    return (
        f"{where}: tones {spacing_hz / 1e6:g} MHz apart cannot be resolved within a {slot_duration_s * 1e6:g} us slot "
        f"(physical limit: slot_duration_s * spacing_hz >= {PHYSICAL_MIN_SLOT_SPACING:g}, one beat period of "
        f"neighbouring tones; got {product:.6g}); widen the spacing or lengthen waveforms.slot_duration_s"
    )


def band_problem(
    low_hz: float, high_hz: float, centre_hz: float, bandwidth_hz: float, sample_rate_hz: float, *, where: str
) -> str | None:
    """Why a comb spanning ``low_hz..high_hz`` does not suit an AOD passing ``centre_hz +- bandwidth_hz / 2``
    at this sample rate (outside the band, or its images ``f_s - f`` inside it), or None."""
    band_lo, band_hi = centre_hz - bandwidth_hz / 2, centre_hz + bandwidth_hz / 2
    slack = _REL_TOL * centre_hz
    if low_hz < band_lo - slack or high_hz > band_hi + slack:
        return (
            f"{where}: tones span {low_hz / 1e6:g}..{high_hz / 1e6:g} MHz, outside the AOD's band "
            f"{band_lo / 1e6:g}..{band_hi / 1e6:g} MHz (aod_centre_hz +- aod_bandwidth_hz / 2): the AOD would not "
            "diffract them; move start_hz/spacing_hz into the band or configure the AOD's real band"
        )
    image_lo, image_hi = sample_rate_hz - high_hz, sample_rate_hz - low_hz
    if image_lo < band_hi - slack and image_hi > band_lo + slack:
        return (
            f"{where}: the DAC's images of the tones (sample rate - tone) span {image_lo / 1e6:g}..{image_hi / 1e6:g} "
            f"MHz and fall inside the AOD's band {band_lo / 1e6:g}..{band_hi / 1e6:g} MHz, where they would make "
            f"spurious tweezers; raise waveforms.sample_rate_hz above {(high_hz + band_hi) / 1e6:g} MHz"
        )
    return None


@dataclass(frozen=True)
class ChannelLimits:
    """One channel's limits as the segment check needs them (built from the configuration)."""

    channel: int
    name: str  # the configuration section, e.g. "array.x_tones.rf", for the messages
    full_scale_counts: float  # int16 counts of amplitude 1.0
    full_scale_v: float  # peak volts of amplitude 1.0 at the load
    load_ohm: float
    max_peak_amplitude: float  # fraction of full scale
    max_power_w: float | None


def segment_levels_reference(samples: np.ndarray, slot_samples: int) -> tuple[np.ndarray, np.ndarray]:
    """Plain numpy ``(peak |count| per channel, largest per-slot mean square count per channel)`` of
    ``int16[n, ch]`` samples (a segment shorter than a slot counts as one slot): the reference for
    ``segment_levels``."""
    x = samples.astype(np.float64)
    length = min(slot_samples, x.shape[0])
    n_slots = x.shape[0] // length
    per_slot = np.square(x[: n_slots * length]).reshape(n_slots, length, x.shape[1]).mean(axis=1)
    return np.max(np.abs(x), axis=0), per_slot.max(axis=0)


@njit(cache=True, nogil=True)
def _segment_levels(samples: np.ndarray, slot_samples: int, peak: np.ndarray, mean_square: np.ndarray) -> None:
    """The largest |count| per channel (every sample) and the largest mean square of a whole slot (a segment
    shorter than a slot counts as one slot) of ``int16[n, ch]`` samples; scalar accumulators, one channel at a
    time, in int64 (|-32768| does not fit an int16)."""
    n, n_ch = samples.shape
    length = min(slot_samples, n)
    n_whole = n // length * length if length > 0 else 0
    for c in range(n_ch):
        col = samples[:, c]
        top = np.int64(0)
        best = np.int64(0)
        for start in range(0, n_whole, max(length, 1)):
            acc = np.int64(0)
            for i in range(start, start + length):
                v = np.int64(col[i])
                acc += v * v
                a = -v if v < 0 else v
                if a > top:
                    top = a
            if acc > best:
                best = acc
        for i in range(n_whole, n):
            v = np.int64(col[i])
            a = -v if v < 0 else v
            if a > top:
                top = a
        peak[c] = float(top)
        mean_square[c] = best / length if length > 0 else 0.0


@njit(cache=True, nogil=True)
def _flat_peak(flat: np.ndarray) -> int:
    """The largest |count| of a contiguous ``int16`` buffer, every channel at once: one pass LLVM vectorises
    (~4 us for a 32-slot two-channel segment, against ~100 us for the per-channel, per-slot levels)."""
    hi = np.int16(0)
    lo = np.int16(0)
    for i in range(flat.size):
        v = flat[i]
        if v > hi:
            hi = v
        if v < lo:
            lo = v
    return int(max(np.int32(hi), -np.int32(lo)))


def segment_levels(samples: np.ndarray, slot_samples: int) -> tuple[np.ndarray, np.ndarray]:
    """``(peak |count|, largest per-slot mean square count)`` per channel of ``int16[n, ch]`` samples."""
    peak = np.empty(samples.shape[1], dtype=np.float64)
    mean_square = np.empty(samples.shape[1], dtype=np.float64)
    _segment_levels(samples, slot_samples, peak, mean_square)
    return peak, mean_square


class SegmentGuard:
    """Checks every segment before it is uploaded against each channel's peak and RF power limits.

    The power of a slot is its samples' mean square, in volts at the load, over ``load_ohm``: the power the
    amplifier receives while that slot plays (whatever the phases, moves or fades did to the comb).
    """

    def __init__(self, limits: list[ChannelLimits], slot_samples: int) -> None:
        self.limits = limits
        self.slot_samples = slot_samples
        self._peak = np.empty(len(limits), dtype=np.float64)
        self._mean_square = np.empty(len(limits), dtype=np.float64)
        _segment_levels(np.zeros((slot_samples, len(limits)), np.int16), slot_samples, self._peak, self._mean_square)
        _flat_peak(np.zeros(1, np.int16))

    def _within_by_peak(self, samples: np.ndarray) -> bool:
        """True when the segment's largest |count| over all channels already proves every limit: no sample
        above any channel's peak limit, and no slot's mean square above that peak squared, so no slot's power
        above any channel's power limit. Exact in what it accepts; whatever it cannot prove goes to the
        per-channel, per-slot measurement (which also names the channel and the limit)."""
        if not samples.flags.c_contiguous:
            return False
        peak = float(_flat_peak(samples.reshape(-1)))
        for lim in self.limits:
            if peak / lim.full_scale_counts > lim.max_peak_amplitude * (1 + _REL_TOL):
                return False
            if lim.max_power_w is not None:
                volts = peak * lim.full_scale_v / lim.full_scale_counts
                if volts * volts / lim.load_ohm > lim.max_power_w * (1 + _REL_TOL):
                    return False
        return True

    def problem(self, samples: np.ndarray) -> str | None:
        """Why ``samples`` (``int16[n, ch]``) must not be played, or None."""
        if samples.shape[1] < len(self.limits):
            return f"a segment of {samples.shape[1]} channel(s) for a card configured with {len(self.limits)}"
        if self._within_by_peak(samples):
            return None
        _segment_levels(samples[:, : len(self.limits)], self.slot_samples, self._peak, self._mean_square)
        for lim in self.limits:
            peak = self._peak[lim.channel] / lim.full_scale_counts
            if peak > lim.max_peak_amplitude * (1 + _REL_TOL):
                return (
                    f"channel {lim.channel}: a sample reaches {peak:.4g} of full scale, above {lim.name}."
                    f"max_peak_amplitude = {lim.max_peak_amplitude:g}; the segment is not played"
                )
            if lim.max_power_w is not None:
                volts_sq = self._mean_square[lim.channel] * (lim.full_scale_v / lim.full_scale_counts) ** 2
                power_w = volts_sq / lim.load_ohm
                if power_w > lim.max_power_w * (1 + _REL_TOL):
                    return (
                        f"channel {lim.channel}: a slot delivers {w_to_dbm(power_w):.2f} dBm ({power_w * 1e3:.4g} mW) "
                        f"into {lim.load_ohm:g} ohm, above {lim.name}'s limit of {w_to_dbm(lim.max_power_w):.2f} dBm; "
                        "the segment is not played"
                    )
        return None

    def check(self, samples: np.ndarray) -> None:
        """Raise ``RFLimitError`` naming the limit when ``samples`` must not be played."""
        problem = self.problem(samples)
        if problem is not None:
            raise RFLimitError(problem)
