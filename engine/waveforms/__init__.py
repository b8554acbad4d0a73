"""Module IV: turn waveform slots (``engine.operations.Operations``) into int16 AWG samples.

Tones
-----
``alpha_k`` below is the sample amplitude: the configured amplitude divided by the DAC's hold gain
``sinc(nu_k / f_s)`` when ``waveforms.compensate_dac_sinc`` (``tone_sample_amplitudes``), so that the AOD
receives the configured comb.

Every site k of an axis has a static tone ``alpha_k * sin(theta_k[n])`` (``axis_tones``): frequency ``nu_k``
is a whole number ``M_k`` of cycles per slot of ``N = slot_samples`` samples, so the static phase is computed
exactly with integers, ``theta_k[n] = phi_k + 2 pi ((M_k n) mod N) / N``, and is ``phi_k`` at every slot
boundary. A tone moving k -> k+d (d = +-1) follows the configured transition shape ``s(u)``, ``u = n / N``
(min-jerk, tanh or erf, symmetric about mid-slot): frequency ``nu_k + (nu_{k+d} - nu_k) s(u)``, amplitude
``alpha_k + (alpha_{k+d} - alpha_k) s(u)``, phase = the discrete running sum of the frequency plus an
end-pinned correction ``c g(u)`` (``g`` = min-jerk: ``g(0) = 0``, ``g(1) = 1``, ``g' = g'' = 0`` at both ends;
``c = wrap(phi_{k+d} - theta_raw[N])``), so the phase is exactly ``phi_k`` at the start and ``phi_{k+d}``
(mod 2 pi) at the end and the instantaneous frequency at both ends is the site frequency. With the default
``continuous`` site phases (``continuous_phases``: ``phi_k = pi (M_k - M_0) (N - 1) / N``) the raw phase
already ends on ``phi_{k+d}``, so ``c`` is zero to rounding (~1e-12 rad) and the tone's frequency, hence the
tweezer's position, is exactly the shape: a true minimum-jerk move, monotonic, with zero velocity and
acceleration at both slot edges. With Schroeder, zero or CSV phases ``c`` is up to pi and shifts the tone by
up to ``pi * 15/8 / (2 pi T)`` (94 kHz at T = 10 us) mid-move, which can make it back up; those phases buy a
low crest factor (Schroeder) at that price. Amplitude ramps (extract/implant) use ``s`` over the whole
slot; chain fades use it over ``[0, 0.4]`` (fade-out of a site entered by a mover) and ``[0.6, 1]`` (fade-in
of a vacated site).

Trap sources
------------
- ``aod`` (1D chain, one channel): every slot is the hold waveform (every site's static tone) plus one table
  row per mover, a *difference* against the hold: ``move_{k,d} - static_k``, plus the fade-out of the site
  ahead (``fade_out_{k+d} - static_{k+d}``) when that site is not itself a source (the mover heads a block),
  plus the fade-in of site k (``fade_in_k``) when no mover enters k (it tails a block). The four variants
  (inner, head, tail, isolated) x two directions are separate kinds, so a slot costs one base row and exactly
  one row per mover, never one per site. ``IDLE`` and the failsafe are the hold waveform.
- ``slm`` (two channels: ch0 = x AOD, ch1 = y AOD): ``EXTRACT`` ramps the listed tones up, ``SHIFT`` moves
  them by their deltas at full amplitude (delta 0: steady), ``IMPLANT`` ramps them down, ``IDLE`` is silence.
  The failsafe after an extract/shift holds steady full tones at the tones' end sites; after an
  implant/idle it is silence.

Lookup table
------------
``int16`` rows of ``N`` samples keyed by ``(axis, kind, site)``; a row stores ``rint(value / q[axis])`` where
``q`` (counts per unit: 0.045 for chain-1x64, 0.015 for grid-32x64) comes from a bound on every row of the axis
(chain rows: 3x the largest amplitude; slm rows: 1x), so rows never overflow and the quantization error is
at most ``q / 2`` per row. Kinds: chain ``isolated/head/tail/inner x (+1, -1)`` (x axis); slm ``move+1``,
``move-1``, ``static``, ``ramp-up``, ``ramp-down`` (x and y axes). Its size is::

    table_bytes = 2 * slot_samples * sum over axes (n_sites(axis) * n_kinds)     (n_kinds: aod 8, slm 5)

e.g. chain-1x64 (6240 samples): 2 * 6240 * 64 * 8 = 6,389,760 B; grid-32x64 (3136 samples):
2 * 3136 * (32 + 64) * 5 = 3,010,560 B. If ``waveforms.table_max_bytes`` is smaller, whole (axis, kind)
blocks are tabulated in order of use (moves first, y axis before x) while they fit, and the rest is
synthesized at render time by the same numba tone function and quantization that fill the table, so both
paths give bit-identical samples.

Prefix rows (slm): for every tabulated (axis, kind) block there is an int32 prefix block
``P[k] = sum_{j<k} row_j`` (k = 0..n_sites), so a run of consecutive sites ``[a, b)`` of one (axis, kind)
(a block of rows moving together, a whole extracted line) costs two row reads, ``P[b] - P[a]``, instead of
``b - a``; the sum is exact in int32 (|P| <= 64 * 32767), so the samples are bit-identical to the single rows.
``lookup`` emits one run key for every run of two or more tones, so a slot never has more keys than tones.
Their size is::

    prefix_bytes = 4 * slot_samples * sum over axes ((n_sites(axis) + 1) * 5)     (slm; aod: none)

e.g. grid-32x64 (3136 samples): 4 * 3136 * (33 + 65) * 5 = 6,146,560 B. They take what is left of
``table_max_bytes`` after the int16 rows, whole blocks in the same order while they fit; runs of a kind
without a prefix block fall back to single rows. Chain slots use single rows only.

Rendering: a slot's rows are summed exactly in int32 (four rows per pass, a run per pass), then each sample is
``rint(base + q * sum)`` with base the float32 hold row (chain) or zero (slm). int16 rows halve the memory
traffic of float32 rows, and a slot is bound by reading its rows.

Scaling: amplitude 1.0 is 32767 counts (the decoder's full scale). At most one tone per site is lit at a
time, so an axis peaks at the sum of its sample amplitudes; a configuration whose sum exceeds 1 is rejected, which
makes clipping impossible (samples are also clamped to +-32767 against float rounding).

Hot paths (``lookup``, ``render``, ``render_failsafe``) are numba ``nogil`` kernels over buffers the bank
allocates; every kernel is compiled in ``WaveformBank.__init__``. ``tests/waveform_reference.py`` builds the
same waveforms tone by tone in plain numpy, the oracle the kernels are tested against.

Layout
------
- ``shapes``: full scale, the tone kinds, the transition shape and the phase track (plain numpy: the
  specification).
- ``axes``: the static tones of each axis (whole cycles per slot, continuous phases) and the headroom check.
- ``kernels``: the numba tone, lookup and render kernels.
- ``bank``: the lookup table (its size formulas) and ``WaveformBank``, what the streamer calls.
Reading a comb or a tone CSV is ``engine.tones``, shared with the simulated decoder.
"""

from engine.tones import Tones, schroeder_phases
from engine.waveforms.axes import axes_of, axis_tones, check_headroom, continuous_phases, tone_sample_amplitudes
from engine.waveforms.bank import WaveformBank, prefix_formula_bytes, table_formula_bytes
from engine.waveforms.shapes import (
    CHAIN_KINDS,
    FADE_IN,
    FADE_IN_START,
    FADE_OUT,
    FADE_OUT_END,
    FULL_SCALE,
    INNER_UP,
    KIND_NAMES,
    MOVE_DOWN,
    MOVE_UP,
    RAMP_DOWN,
    RAMP_UP,
    SLM_KINDS,
    STATIC,
    phase_track,
    shape_curve,
)

__all__ = [
    "CHAIN_KINDS",
    "FADE_IN",
    "FADE_IN_START",
    "FADE_OUT",
    "FADE_OUT_END",
    "FULL_SCALE",
    "INNER_UP",
    "KIND_NAMES",
    "MOVE_DOWN",
    "MOVE_UP",
    "RAMP_DOWN",
    "RAMP_UP",
    "SLM_KINDS",
    "STATIC",
    "Tones",
    "WaveformBank",
    "axes_of",
    "axis_tones",
    "check_headroom",
    "continuous_phases",
    "phase_track",
    "prefix_formula_bytes",
    "schroeder_phases",
    "shape_curve",
    "table_formula_bytes",
    "tone_sample_amplitudes",
]
