"""The static tones of each AOD axis, as the bank uses them: whole cycles per slot, below Nyquist, amplitudes
in (0, 1], and (by default) continuous site phases; plus the headroom check that makes clipping impossible.

Reading a comb or CSV (``engine.tones``) is shared with the simulated decoder; the slot-specific rules live here.
"""

from __future__ import annotations

import numpy as np

from engine.aod_limits import sample_amplitudes
from engine.config import ConfigError, SystemConfig, ToneAxisConfig
from engine.routing import position_tones, positions_per_site
from engine.tones import Tones, check_below_nyquist, tones_of


def continuous_phases(cycles: np.ndarray, n_samples: int) -> np.ndarray:
    """Site phases that make every one-site move end exactly on the next site's phase with no correction.

    A tone moving k -> k + d with a symmetric shape (``s(u) + s(1 - u) = 1``) advances by
    ``2 pi M_k + (2 pi / N) (M_{k+d} - M_k) sum_{j<N} s(j / N)`` and that sum is exactly ``(N - 1) / 2``, so the
    move lands on ``phi_{k+d}`` iff ``phi_{k+d} - phi_k = pi (M_{k+d} - M_k) (N - 1) / N`` (mod 2 pi): phases
    linear in the cycle count, ``phi_k = pi (M_k - M_0) (N - 1) / N``, reduced with integers so that no
    rounding grows with ``M``. (It is a time shift of the zero-phase comb, so the comb peaks at the sum of its
    amplitudes once per slot, which ``check_headroom`` keeps at or below full scale.)
    """
    m = np.asarray(cycles, dtype=np.int64)
    half_turns = ((m - m[0]) * (n_samples - 1)) % (2 * n_samples)  # in units of pi / N
    return np.pi * half_turns.astype(np.float64) / n_samples


def _axis_config(config: SystemConfig, axis: str) -> tuple[ToneAxisConfig, int]:
    if axis not in ("x", "y"):
        raise ValueError(f"axis must be 'x' or 'y', not {axis!r}")
    tc = config.array.x_tones if axis == "x" else config.array.y_tones
    n = config.array.nx if axis == "x" else config.array.ny
    return tc, n


def axis_tones(config: SystemConfig, axis: str) -> Tones:
    """Static tones of ``axis`` ('x' or 'y'): the configured comb, or the ``alpha,nu,phi`` CSV.

    Comb: ``start_hz + k * spacing_hz`` at the configured amplitude, with continuous (``continuous_phases``),
    Schroeder or zero phases; a CSV brings its own phases. Raises
    ``ConfigError`` (a ``ValueError``) naming the field when the tones cannot be used: an unreadable file,
    missing columns, too few rows, a frequency that is not a whole number of cycles per slot, frequencies not
    strictly ascending or at/above Nyquist, an amplitude outside (0, 1].
    """
    tc, n = _axis_config(config, axis)
    wf = config.waveforms
    where = f"array.{axis}_tones" + (".csv" if tc.csv is not None else "")
    half = positions_per_site(config.array.routing)
    freq, amp, phase = position_tones(tones_of(tc, n, axis), half)
    cycles = freq * wf.slot_duration_s
    bad = np.flatnonzero(np.abs(cycles - np.round(cycles)) > 1e-6)
    if bad.size:
        k = int(bad[0])
        raise ConfigError(
            f"{where}: tone {k} at {freq[k]:.9g} Hz is not a whole number of cycles per slot "
            f"({cycles[k]:.6g}); frequencies must be multiples of 1/slot_duration_s = {1 / wf.slot_duration_s:g} Hz"
        )
    if np.any(np.diff(freq) <= 0):
        k = int(np.flatnonzero(np.diff(freq) <= 0)[0])
        raise ConfigError(
            f"{where}: frequencies must be strictly ascending (tone {k + 1} at {freq[k + 1]:g} Hz "
            f"follows {freq[k]:g} Hz)"
        )
    check_below_nyquist(freq[0], freq[-1], wf.sample_rate_hz, where=where)
    if np.any(amp <= 0) or np.any(amp > 1):
        k = int(np.flatnonzero((amp <= 0) | (amp > 1))[0])
        raise ConfigError(f"{where}: tone {k} amplitude {amp[k]:g} must be in (0, 1] (a fraction of full scale)")
    m = np.round(cycles).astype(np.int64)
    if tc.csv is None and tc.phases == "continuous":
        phase = continuous_phases(m, wf.slot_samples)
    elif half == 2:  # a midpoint: the phase a tone from the site below reaches with no correction
        phase = np.asarray(phase, dtype=np.float64).copy()
        n_samples = wf.slot_samples
        turns = ((m[1::2] - m[:-1:2]) * (n_samples - 1)) % (2 * n_samples)
        phase[1::2] = np.mod(phase[:-1:2] + np.pi * turns / n_samples, 2 * np.pi)
    return Tones(freq, amp, np.asarray(phase, dtype=np.float64))


def tone_sample_amplitudes(config: SystemConfig, tones: Tones) -> np.ndarray:
    """The amplitude every static tone of ``tones`` is rendered at (fraction of full scale): its configured
    amplitude, divided by the DAC's sinc gain at its frequency when ``waveforms.compensate_dac_sinc``
    (``engine.aod_limits.sample_amplitudes``), so that the AOD receives the configured comb."""
    wf = config.waveforms
    return sample_amplitudes(tones.frequency_hz, tones.amplitude, wf.sample_rate_hz, wf.compensate_dac_sinc)


def axes_of(config: SystemConfig) -> tuple[str, ...]:
    """The AOD axes a configuration drives: x only for a chain (trap_source ``aod``), x and y for ``slm``."""
    return ("x",) if config.array.trap_source == "aod" else ("x", "y")


def check_headroom(config: SystemConfig, tones: dict[str, Tones] | None = None) -> None:
    """Raise ``ValueError`` if an axis could clip: its worst case (the sum of its n largest sample amplitudes,
    one tone per site, compensated for the DAC's sinc roll-off when so configured; under interstitial routing
    the comb also holds the midpoints, but tones stay a site apart, so at most n of them play) must be at most
    1.0 of full scale."""
    for axis in axes_of(config):
        t = tones[axis] if tones is not None else axis_tones(config, axis)
        n = _axis_config(config, axis)[1]
        amps = tone_sample_amplitudes(config, t)
        loudest = np.argsort(amps)[::-1][:n]
        worst = float(np.sum(amps[loudest]))
        if worst > 1.0 + 1e-12:
            gain = float(np.sum(t.amplitude[loudest]) / worst)
            why = " (compensated for the DAC's sinc roll-off: waveforms.compensate_dac_sinc)" if gain < 1 else ""
            raise ValueError(
                f"array.{axis}_tones: the {n} tones can sum to {worst:.4g} of full scale{why}, so int16 samples "
                f"would clip; lower array.{axis}_tones.amplitude (at most {gain / n:.4g} for {n} equal tones)"
            )

