"""Module IV: turn waveform slots (``engine.operations.Operations``) into int16 AWG samples.

Tones
-----
Every site k of an axis has a static tone ``alpha_k * sin(theta_k[n])`` (``axis_tones``): frequency ``nu_k``
is a whole number ``M_k`` of cycles per slot of ``N = slot_samples`` samples, so the static phase is computed
exactly with integers, ``theta_k[n] = phi_k + 2 pi ((M_k n) mod N) / N``, and is ``phi_k`` at every slot
boundary. A tone moving k -> k+d (d = +-1) follows the configured transition shape ``s(u)``, ``u = n / N``
(min-jerk, tanh or erf, symmetric about mid-slot): frequency ``nu_k + (nu_{k+d} - nu_k) s(u)``, amplitude
``alpha_k + (alpha_{k+d} - alpha_k) s(u)``, phase = the discrete running sum of the frequency plus an
end-pinned correction ``c g(u)`` (``g`` = min-jerk: ``g(0) = 0``, ``g(1) = 1``, ``g' = g'' = 0`` at both ends;
``c = wrap(phi_{k+d} - theta_raw[N])``), so the phase is exactly ``phi_k`` at the start and ``phi_{k+d}``
(mod 2 pi) at the end and the instantaneous frequency at both ends is the site frequency. Amplitude ramps
(extract/implant) use ``s`` over the whole slot; chain fades use it over ``[0, 0.4]`` (fade-out of a site
entered by a mover) and ``[0.6, 1]`` (fade-in of a vacated site).

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

e.g. chain-1x64 (6240 samples): 2 * 6240 * 64 * 8 = 6,389,760 B; grid-32x64 (3120 samples):
2 * 3120 * (32 + 64) * 5 = 2,995,200 B. If ``waveforms.table_max_bytes`` is smaller, whole (axis, kind)
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
time, so an axis peaks at the sum of its amplitudes; a configuration whose sum exceeds 1 is rejected, which
makes clipping impossible (samples are also clamped to +-32767 against float rounding).

Hot paths (``lookup``, ``render``, ``render_failsafe``) are numba ``nogil`` kernels over buffers allocated
here; every kernel is compiled in ``WaveformBank.__init__``. ``ReferenceSynth`` is a plain-numpy
synthesizer of the same waveforms for tests.
"""

from __future__ import annotations

import csv
import math
from pathlib import Path
from typing import NamedTuple

import numpy as np
from numba import njit

from engine.config import ConfigError, SystemConfig
from engine.operations import EXTRACT, IDLE, IMPLANT, SHIFT, Operations

__all__ = [
    "FULL_SCALE",
    "KIND_NAMES",
    "ReferenceSynth",
    "Tones",
    "WaveformBank",
    "axis_tones",
    "check_headroom",
    "schroeder_phases",
    "phase_track",
    "shape_curve",
    "prefix_formula_bytes",
    "table_formula_bytes",
]

#: int16 counts of a tone of amplitude 1.0 (what the simulated decoder divides by).
FULL_SCALE = 32767.0
#: Chain fades: a site entered by a mover fades out over [0, FADE_OUT_END]; a vacated site fades in over
#: [FADE_IN_START, 1] (fractions of the slot), so at mid-slot all tones are at least a site apart.
FADE_OUT_END = 0.4
FADE_IN_START = 0.6

# tone kinds (the "kind" of a table key). Plain tones:
STATIC, MOVE_UP, MOVE_DOWN, RAMP_UP, RAMP_DOWN, FADE_OUT, FADE_IN = range(7)
# chain mover rows, differences against the hold waveform, one per mover k -> k + d (see ``_tone``):
# INNER = move - static_k; HEAD = INNER + fade-out of the entered site k + d (minus its static tone);
# TAIL = INNER + fade-in of the vacated site k; ISO = INNER + both.
INNER_UP, INNER_DOWN, HEAD_UP, HEAD_DOWN, TAIL_UP, TAIL_DOWN, ISO_UP, ISO_DOWN = range(7, 15)
N_KINDS = 15
KIND_NAMES = (
    "static", "move+1", "move-1", "ramp-up", "ramp-down", "fade-out", "fade-in",
    "chain inner+1", "chain inner-1", "chain head+1", "chain head-1", "chain tail+1", "chain tail-1",
    "chain isolated+1", "chain isolated-1",
)
#: Kinds tabulated per trap source, most used first (the order blocks are given table space).
CHAIN_KINDS = (ISO_UP, ISO_DOWN, HEAD_UP, HEAD_DOWN, TAIL_UP, TAIL_DOWN, INNER_UP, INNER_DOWN)
SLM_KINDS = (MOVE_UP, MOVE_DOWN, STATIC, RAMP_UP, RAMP_DOWN)

# run keys (prefix rows): _RUN0 + (row of P[b] << _RUN_SHIFT) + row of P[a]; below _RUN0 are single rows
_RUN_SHIFT = 20
_RUN_MASK = (1 << _RUN_SHIFT) - 1
_RUN0 = 1 << 44

# rows of the shape table passed to the kernels
_S, _G, _CUM, _ENV_OUT, _ENV_IN = range(5)

# lookup error codes (returned as code + 16 * slot); the last two are about the call, not a slot
_E_CHAIN_KIND, _E_SITE, _E_ORDER, _E_DELTA, _E_EDGE, _E_CROSS, _E_KIND, _E_ARRAY, _E_KEYS = range(1, 10)
_ERRORS = {
    _E_CHAIN_KIND: "a chain (trap_source 'aod') slot must be SHIFT or IDLE",
    _E_SITE: "a tone site is outside the axis",
    _E_ORDER: "tone sites must be listed in strictly ascending order",
    _E_DELTA: "a delta must be -1, 0 or +1",
    _E_EDGE: "a tone would move off the end of the axis",
    _E_CROSS: "tones would cross or merge (their end sites are not strictly ascending)",
    _E_KIND: "unknown operation kind",
}


# --------------------------------------------------------------------------------------------------------
# static tones


class Tones(NamedTuple):
    """The static tone of every site of one axis (float64 arrays, one entry per site)."""

    frequency_hz: np.ndarray
    amplitude: np.ndarray  # fraction of full scale
    phase_rad: np.ndarray


def schroeder_phases(n: int) -> np.ndarray:
    """Low-crest-factor phases for ``n`` equal tones: ``phi_k = -pi k (k - 1) / n`` (mod 2 pi)."""
    k = np.arange(n, dtype=np.float64)
    return np.mod(-np.pi * k * (k - 1) / n, 2 * np.pi)


def _axis_config(config: SystemConfig, axis: str):
    if axis not in ("x", "y"):
        raise ValueError(f"axis must be 'x' or 'y', not {axis!r}")
    tc = config.array.x_tones if axis == "x" else config.array.y_tones
    n = config.array.nx if axis == "x" else config.array.ny
    return tc, n


def _read_tone_csv(path: str, axis: str, n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    where = f"array.{axis}_tones.csv"
    try:
        with Path(path).open(newline="") as fh:
            reader = csv.DictReader(fh)
            cols = [c.strip() for c in (reader.fieldnames or [])]
            missing = [c for c in ("alpha", "nu", "phi") if c not in cols]
            if missing:
                raise ConfigError(
                    f"{where} {path}: needs columns alpha,nu,phi (amplitude fraction, Hz, rad); "
                    f"missing {','.join(missing)} in its first line"
                )
            reader.fieldnames = cols
            rows = []
            for line, rec in enumerate(reader, start=2):
                try:
                    rows.append((float(rec["alpha"]), float(rec["nu"]), float(rec["phi"])))
                except (TypeError, ValueError):
                    raise ConfigError(  # the file's text is not quoted: it could be any file's
                        f"{where} {path} line {line}: alpha, nu and phi must be numbers"
                    ) from None
    except OSError as err:
        raise ConfigError(f"{where}: cannot read tone file {path}: {err.strerror or err}") from None
    if len(rows) < n:
        raise ConfigError(f"{where} {path} has {len(rows)} tone rows but the {axis} axis has {n} sites")
    arr = np.asarray(rows[:n], dtype=np.float64)
    return arr[:, 1].copy(), arr[:, 0].copy(), arr[:, 2].copy()


def axis_tones(config: SystemConfig, axis: str) -> Tones:
    """Static tones of ``axis`` ('x' or 'y'): the configured comb, or the ``alpha,nu,phi`` CSV.

    Comb: ``start_hz + k * spacing_hz`` at the configured amplitude, with Schroeder or zero phases. Raises
    ``ConfigError`` (a ``ValueError``) naming the field when the tones cannot be used: an unreadable file,
    missing columns, too few rows, a frequency that is not a whole number of cycles per slot, frequencies not
    strictly ascending or at/above Nyquist, an amplitude outside (0, 1].
    """
    tc, n = _axis_config(config, axis)
    wf = config.waveforms
    where = f"array.{axis}_tones" + (".csv" if tc.csv is not None else "")
    if tc.csv is None:
        freq = tc.start_hz + tc.spacing_hz * np.arange(n, dtype=np.float64)
        amp = np.full(n, tc.amplitude, dtype=np.float64)
        phase = schroeder_phases(n) if tc.phases == "schroeder" else np.zeros(n)
    else:
        freq, amp, phase = _read_tone_csv(tc.csv, axis, n)
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
    if freq[0] <= 0 or freq[-1] >= wf.sample_rate_hz / 2:
        raise ConfigError(
            f"{where}: tones span {freq[0]:g}..{freq[-1]:g} Hz, outside (0, Nyquist = {wf.sample_rate_hz / 2:g} Hz)"
        )
    if np.any(amp <= 0) or np.any(amp > 1):
        k = int(np.flatnonzero((amp <= 0) | (amp > 1))[0])
        raise ConfigError(f"{where}: tone {k} amplitude {amp[k]:g} must be in (0, 1] (a fraction of full scale)")
    return Tones(freq, amp, np.asarray(phase, dtype=np.float64))


def _axes_of(config: SystemConfig) -> tuple[str, ...]:
    return ("x",) if config.array.trap_source == "aod" else ("x", "y")


def check_headroom(config: SystemConfig, tones: dict[str, Tones] | None = None) -> None:
    """Raise ``ValueError`` if an axis could clip: its worst case (the sum of its n largest amplitudes, one
    tone per site) must be at most 1.0 of full scale."""
    for axis in _axes_of(config):
        t = tones[axis] if tones is not None else axis_tones(config, axis)
        worst = float(np.sum(t.amplitude))
        if worst > 1.0 + 1e-12:
            n = t.amplitude.size
            raise ValueError(
                f"array.{axis}_tones: the {n} tones can sum to {worst:.4g} of full scale, so int16 samples would "
                f"clip; lower array.{axis}_tones.amplitude (at most {1.0 / n:.4g} for {n} equal tones)"
            )


# --------------------------------------------------------------------------------------------------------
# shapes and the phase track (plain numpy: the specification)


def shape_curve(shape: str, sharpness: float, u: np.ndarray) -> np.ndarray:
    """Transition shape ``s(u)``, 0 at u <= 0 and 1 at u >= 1, symmetric about 1/2."""
    u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
    if shape == "min-jerk":
        return u**3 * (10.0 - 15.0 * u + 6.0 * u * u)
    v = float(sharpness)
    if shape == "tanh":
        return 0.5 + 0.5 * np.tanh(2.0 * v * (u - 0.5)) / np.tanh(v)
    if shape == "erf":
        from scipy.special import erf

        r = np.sqrt(np.pi) * v
        return 0.5 + 0.5 * erf(r * (u - 0.5)) / erf(r / 2.0)
    raise ValueError(f"unknown transition shape {shape!r} (min-jerk, tanh, erf)")


def _wrap(x: float) -> float:
    """Wrap into (-pi, pi]."""
    return np.pi - np.mod(np.pi - x, 2 * np.pi)


def _shape_table(shape: str, sharpness: float, n: int) -> np.ndarray:
    """float64[5, N + 1]: s(u), g(u) (min-jerk), running sum S[n] = sum_{j<n} s(j/N), fade-out and fade-in envelopes."""
    u = np.arange(n + 1, dtype=np.float64) / n
    out = np.empty((5, n + 1))
    out[_S] = shape_curve(shape, sharpness, u)
    out[_G] = shape_curve("min-jerk", 0.0, u)
    out[_CUM, 0] = 0.0
    np.cumsum(out[_S, :-1], out=out[_CUM, 1:])
    out[_ENV_OUT] = 1.0 - shape_curve(shape, sharpness, u / FADE_OUT_END)
    out[_ENV_IN] = shape_curve(shape, sharpness, (u - FADE_IN_START) / (1.0 - FADE_IN_START))
    return out


def phase_track(
    cycles: np.ndarray, phases: np.ndarray, k: int, d: int, n_samples: int, shape: str, sharpness: float
) -> np.ndarray:
    """float64[N + 1]: phase (rad) at samples 0..N of a tone moving from site k to k + d.

    The static part ``2 pi ((M_k n) mod N) / N`` is reduced exactly with integers, so differences between
    samples are meaningful modulo 2 pi.

    ``cycles``: whole cycles per slot of every site; ``phases``: site phases. ``d = 0`` is a static tone.
    The phase is ``phases[k]`` at n = 0 and ``phases[k + d]`` (mod 2 pi) at n = N; the per-sample increment
    is ``2 pi (M_k + (M_{k+d} - M_k) s(n / N)) / N`` plus the end-pinned correction ``c g(n / N)``.
    """
    n = np.arange(n_samples + 1, dtype=np.int64)
    u = n / n_samples
    s = shape_curve(shape, sharpness, u)
    cum = np.concatenate([[0.0], np.cumsum(s[:-1])])
    m0 = int(cycles[k]) % n_samples
    dm = float(int(cycles[k + d]) - int(cycles[k]))
    raw = phases[k] + 2 * np.pi / n_samples * (((m0 * n) % n_samples) + dm * cum)
    c = _wrap(phases[k + d] - raw[-1])
    return raw + c * shape_curve("min-jerk", 0.0, u)


def table_formula_bytes(config: SystemConfig) -> int:
    """Bytes of the full lookup table: ``2 * slot_samples * sum over axes (n_sites * n_kinds)``."""
    kinds = len(CHAIN_KINDS) if config.array.trap_source == "aod" else len(SLM_KINDS)
    sites = config.array.nx if config.array.trap_source == "aod" else config.array.nx + config.array.ny
    return 2 * config.waveforms.slot_samples * sites * kinds


def prefix_formula_bytes(config: SystemConfig) -> int:
    """Bytes of the full prefix tables (slm only): ``4 * slot_samples * sum over axes ((n_sites + 1) * 5)``."""
    if config.array.trap_source == "aod":
        return 0
    return 4 * config.waveforms.slot_samples * (config.array.nx + config.array.ny + 2) * len(SLM_KINDS)


# --------------------------------------------------------------------------------------------------------
# numba kernels


@njit(cache=True, nogil=True)
def _tone(kind, k, n_sites, cyc, amp, phi, shp, scale, inv_q, out):
    """One tone of ``kind`` at site ``k`` into ``out[N]``: table units ``rint(value * inv_q)`` when
    ``inv_q > 0`` (int16 table rows and direct synthesis alike, so both paths give identical rows), else the
    exact value in counts (float64 ``out``, for tests)."""
    n_samp = out.shape[0]
    quantize = inv_q > 0.0
    w = 2.0 * np.pi / n_samp
    m0 = cyc[k] % n_samp
    p0 = phi[k]
    a0 = amp[k] * scale
    if kind == MOVE_UP or kind == MOVE_DOWN or kind >= INNER_UP:
        up = kind == MOVE_UP or kind == INNER_UP or kind == HEAD_UP or kind == TAIL_UP or kind == ISO_UP
        d = 1 if up else -1
        k2 = k + d
        if k2 < 0 or k2 >= n_sites:
            out[:] = 0
            return
        chain = kind >= INNER_UP
        head = kind == HEAD_UP or kind == HEAD_DOWN or kind == ISO_UP or kind == ISO_DOWN
        tail = kind == TAIL_UP or kind == TAIL_DOWN or kind == ISO_UP or kind == ISO_DOWN
        m2 = cyc[k2] % n_samp
        p2 = phi[k2]
        dm = float(cyc[k2] - cyc[k])
        a1 = amp[k2] * scale
        raw_end = p0 + w * dm * shp[2, n_samp]
        x = p2 - raw_end
        c = np.pi - ((np.pi - x) % (2.0 * np.pi))  # wrap into (-pi, pi]
        for n in range(n_samp):
            st = w * ((m0 * n) % n_samp)
            th = p0 + st + w * dm * shp[2, n] + c * shp[1, n]
            v = (a0 + (a1 - a0) * shp[0, n]) * math.sin(th)
            if chain:
                # minus the static tone of the source, plus its fade-in if vacated
                e = shp[4, n] - 1.0 if tail else -1.0
                v += a0 * e * math.sin(p0 + st)
                if head:  # the entered site's static tone fades out
                    v += a1 * (shp[3, n] - 1.0) * math.sin(p2 + w * ((m2 * n) % n_samp))
            if quantize:
                out[n] = np.rint(v * inv_q)
            else:
                out[n] = v
        return
    # stationary tones: static phase times an envelope e0 + e1 * env[n]
    e0 = 1.0
    e1 = 0.0
    env = 0
    if kind == RAMP_UP:
        e0, e1, env = 0.0, 1.0, 0
    elif kind == RAMP_DOWN:
        e0, e1, env = 1.0, -1.0, 0
    elif kind == FADE_OUT:
        e0, e1, env = 0.0, 1.0, 3
    elif kind == FADE_IN:
        e0, e1, env = 0.0, 1.0, 4
    for n in range(n_samp):
        v = a0 * (e0 + e1 * shp[env, n]) * math.sin(p0 + w * ((m0 * n) % n_samp))
        if quantize:
            out[n] = np.rint(v * inv_q)
        else:
            out[n] = v


@njit(cache=True, nogil=True)
def _lookup_chain(kind, x_site, x_delta, first, count, keys, key_of):
    """Chain (``trap_source = "aod"``) slots ``first..first+count-1`` to keys; returns 0, or ``code + 16 * slot``
    on an invalid slot or ``_E_ARRAY`` / ``_E_KEYS`` when the plan's row or ``keys`` does not fit the bank.

    Slot j's keys start at ``j * (2 + nx)``: ``[n_movers, 0, one key per mover...]`` (see ``_lookup_slm``
    for the key encoding). A mover's kind (inner, head, tail, isolated; up or down) depends on the tones
    before and after it in the slot's list, which the loop carries along (each tone is read once) and
    combines with arithmetic and selects rather than branches: which variant a mover is follows the atoms,
    not a pattern the branch predictor could learn.
    """
    nx = x_site.shape[1]
    stride = 2 + nx
    if nx != key_of.shape[1]:
        return _E_ARRAY
    if keys.shape[0] < count * stride:
        return _E_KEYS
    for j in range(count):
        i = first + j
        kb = j * stride
        kd = kind[i]
        keys[kb] = 0
        keys[kb + 1] = 0
        if kd == IDLE:
            continue
        if kd != SHIFT:
            return _E_CHAIN_KIND + 16 * i
        m = 0
        kp, dp = -2, 0  # the tone before (none yet: a site no tone can start from or reach)
        k, d = x_site[i, 0], x_delta[i, 0]
        for t in range(nx):
            if k < 0:
                break
            kn, dn = (x_site[i, t + 1], x_delta[i, t + 1]) if t + 1 < nx else (-1, 0)  # the tone after
            if k >= nx:
                return _E_SITE + 16 * i
            if d < -1 or d > 1:
                return _E_DELTA + 16 * i
            if k + d < 0 or k + d >= nx:
                return _E_EDGE + 16 * i
            if k <= kp:
                return _E_ORDER + 16 * i
            if k + d <= kp + dp:
                return _E_CROSS + 16 * i
            if d != 0:
                up = d > 0
                # head: the site ahead is not a source, so it is entered and fades out
                head = (kn if up else kp) != k + d
                # tail: no tone behind moves in the same way, so the vacated site fades in
                tail = ((kp if up else kn) != k - d) | ((dp if up else dn) != d)
                # INNER_UP, INNER_DOWN, HEAD_UP, ..., ISO_DOWN in that order: + 2 head + 4 tail + 1 down
                keys[kb + 2 + m] = key_of[INNER_UP + 2 * head + 4 * tail + (1 - up), k]
                m += 1
            kp, dp = k, d
            k, d = kn, dn
        keys[kb] = m
    return 0


@njit(cache=True, nogil=True)
def _lookup_slm(kind, x_site, x_delta, y_site, y_delta, first, count, keys, key_of, prow_of, nx, ny):
    """slm slots ``first..first+count-1`` to keys; returns 0, or ``code + 16 * slot`` on an invalid slot
    or ``_E_ARRAY`` / ``_E_KEYS`` when the plan's array or ``keys`` does not fit the bank.

    Slot j's keys start at ``j * (2 + nx + ny)``: ``[n_ch0, n_ch1, ch0 keys..., ch1 keys...]``. A key in
    ``[0, _RUN0)`` is a table row; a negative key ``-(code + 1)`` is synthesized directly,
    ``code = (axis * N_KINDS + kind) * n_max + site`` (``key_of`` holds both, by ``[axis * N_KINDS + kind,
    site]``); a key ``>= _RUN0`` is a run of consecutive sites ``[a, b)`` of one (axis, kind) with a prefix
    block: ``_RUN0 + (p_b << _RUN_SHIFT) + p_a``, with ``p_a``, ``p_b`` rows of the prefix table. A run
    replaces two or more single keys, so a slot never has more keys than tones and the stride stays a bound.
    """
    stride = 2 + nx + ny
    if x_site.shape[1] != nx or y_site.shape[1] != ny:
        return _E_ARRAY
    if keys.shape[0] < count * stride:
        return _E_KEYS
    for j in range(count):
        i = first + j
        kb = j * stride
        kd = kind[i]
        keys[kb] = 0
        keys[kb + 1] = 0
        m = 0
        if kd == IDLE:
            continue
        if kd != EXTRACT and kd != SHIFT and kd != IMPLANT:
            return _E_KIND + 16 * i
        for axis in range(2):
            sites = x_site if axis == 0 else y_site
            deltas = x_delta if axis == 0 else y_delta
            n_ax = nx if axis == 0 else ny
            m_axis = m
            run_m = 0  # key position, first site, length and kind of the run being built
            run_a = 0
            run_len = 0
            run_kind = -1
            for t in range(n_ax):
                k = sites[i, t]
                if k < 0:
                    break
                if k >= n_ax:
                    return _E_SITE + 16 * i
                if t > 0 and k <= sites[i, t - 1]:
                    return _E_ORDER + 16 * i
                if kd == EXTRACT:
                    tk = RAMP_UP
                elif kd == IMPLANT:
                    tk = RAMP_DOWN
                else:
                    d = deltas[i, t]
                    if d < -1 or d > 1:
                        return _E_DELTA + 16 * i
                    if k + d < 0 or k + d >= n_ax:
                        return _E_EDGE + 16 * i
                    if t > 0 and k + d <= sites[i, t - 1] + deltas[i, t - 1]:
                        return _E_CROSS + 16 * i
                    tk = STATIC if d == 0 else (MOVE_UP if d > 0 else MOVE_DOWN)
                p0 = prow_of[axis * N_KINDS + tk]
                if p0 >= 0 and run_len > 0 and tk == run_kind and k == run_a + run_len:
                    run_len += 1
                    keys[kb + 2 + run_m] = _RUN0 + ((p0 + run_a + run_len) << _RUN_SHIFT) + (p0 + run_a)
                    m = run_m + 1
                else:
                    run_m = m
                    run_a = k
                    run_len = 1
                    run_kind = tk
                    keys[kb + 2 + m] = key_of[axis * N_KINDS + tk, k]
                    m += 1
            keys[kb + axis] = m - m_axis
    return 0


@njit(cache=True, nogil=True)
def _failsafe_keys(kind, x_site, x_delta, y_site, y_delta, i, keys, key_of, prow_of, nx, ny):
    """Keys (one slot, as ``_lookup_slm``) of steady full tones where slm slot ``i`` leaves them."""
    keys[0] = 0
    keys[1] = 0
    kd = kind[i]
    if kd != EXTRACT and kd != SHIFT:
        return
    m = 0
    for axis in range(2):
        sites = x_site if axis == 0 else y_site
        deltas = x_delta if axis == 0 else y_delta
        n_ax = nx if axis == 0 else ny
        m_axis = m
        p0 = prow_of[axis * N_KINDS + STATIC]
        run_m = 0
        run_a = 0
        run_len = 0
        for t in range(n_ax):
            k = sites[i, t]
            if k < 0:
                break
            end = k + deltas[i, t] if kd == SHIFT else k
            if end < 0 or end >= n_ax:
                continue
            if p0 >= 0 and run_len > 0 and end == run_a + run_len:
                run_len += 1
                keys[2 + run_m] = _RUN0 + ((p0 + run_a + run_len) << _RUN_SHIFT) + (p0 + run_a)
                m = run_m + 1
            else:
                run_m = m
                run_a = end
                run_len = 1
                keys[2 + m] = key_of[axis * N_KINDS + STATIC, end]
                m += 1
        keys[axis] = m - m_axis


@njit(cache=True, nogil=True)
def _row(key, table, scratch, n_sites, cyc, amp, phi, shp, n_max, scale, inv_q):
    """int16 row of ``key``: the table row, or ``scratch`` filled by direct synthesis."""
    if key >= 0:
        return table[key]
    code = -key - 1
    site = code % n_max
    ak = code // n_max
    ax = ak // N_KINDS
    _tone(ak % N_KINDS, site, n_sites[ax], cyc[ax], amp[ax], phi[ax], shp, scale, inv_q[ax], scratch)
    return scratch


@njit(cache=True, nogil=True)
def _add_rows(acc, first, r0, r1, r2, r3, g):
    """``acc (=|+=) r0 + ... + r_{g-1}`` in int32 (exact; the order does not matter)."""
    n_samp = acc.shape[0]
    if g == 4:
        if first:
            for n in range(n_samp):
                acc[n] = (np.int32(r0[n]) + np.int32(r1[n])) + (np.int32(r2[n]) + np.int32(r3[n]))
        else:
            for n in range(n_samp):
                acc[n] += (np.int32(r0[n]) + np.int32(r1[n])) + (np.int32(r2[n]) + np.int32(r3[n]))
    elif g == 3:
        if first:
            for n in range(n_samp):
                acc[n] = (np.int32(r0[n]) + np.int32(r1[n])) + np.int32(r2[n])
        else:
            for n in range(n_samp):
                acc[n] += (np.int32(r0[n]) + np.int32(r1[n])) + np.int32(r2[n])
    elif g == 2:
        if first:
            for n in range(n_samp):
                acc[n] = np.int32(r0[n]) + np.int32(r1[n])
        else:
            for n in range(n_samp):
                acc[n] += np.int32(r0[n]) + np.int32(r1[n])
    else:
        if first:
            for n in range(n_samp):
                acc[n] = np.int32(r0[n])
        else:
            for n in range(n_samp):
                acc[n] += np.int32(r0[n])


@njit(cache=True, nogil=True)
def _add_run(acc, first, pb, pa):
    """``acc (=|+=) pb - pa``: a run's rows from two int32 prefix rows (exact)."""
    n_samp = acc.shape[0]
    if first:
        for n in range(n_samp):
            acc[n] = pb[n] - pa[n]
    else:
        for n in range(n_samp):
            acc[n] += pb[n] - pa[n]


@njit(cache=True, nogil=True)
def _render(keys, count, stride, n_ch, base, q, table, prefix, n_sites, cyc, amp, phi, shp, n_max, scale, inv_q,
            acc, scratch, out):
    """Write ``count`` slots to ``out`` (int16[>= count*N, n_ch], C-contiguous): per channel,
    ``rint(base[ch] + q[ch] * sum of the slot's int16 rows)``, clipped to +-32767. A run key adds
    ``P[b] - P[a]`` (two int32 prefix rows), the same int32 sum as its rows one by one."""
    n_samp = acc.shape[1]
    flat = out.reshape(-1)
    for j in range(count):
        kb = j * stride
        off = kb + 2
        for ch in range(n_ch):
            nk = keys[kb + ch]
            a = acc[ch]
            if nk == 0:
                a[:] = 0
            t = 0
            while t < nk:
                key = keys[off + t]
                if key >= _RUN0:
                    v = key - _RUN0
                    _add_run(a, t == 0, prefix[v >> _RUN_SHIFT], prefix[v & _RUN_MASK])
                    t += 1
                    continue
                g = 1  # up to four single rows, up to the next run
                while g < 4 and t + g < nk and keys[off + t + g] < _RUN0:
                    g += 1
                r0 = _row(keys[off + t], table, scratch[0], n_sites, cyc, amp, phi, shp, n_max, scale, inv_q)
                r1 = r0
                r2 = r0
                r3 = r0
                if g >= 2:
                    r1 = _row(keys[off + t + 1], table, scratch[1], n_sites, cyc, amp, phi, shp, n_max, scale, inv_q)
                if g >= 3:
                    r2 = _row(keys[off + t + 2], table, scratch[2], n_sites, cyc, amp, phi, shp, n_max, scale, inv_q)
                if g >= 4:
                    r3 = _row(keys[off + t + 3], table, scratch[3], n_sites, cyc, amp, phi, shp, n_max, scale, inv_q)
                _add_rows(a, t == 0, r0, r1, r2, r3, g)
                t += g
            off += nk
        o = j * n_samp * n_ch
        if n_ch == 1:
            _convert1(flat[o : o + n_samp], base[0], acc[0], q[0])
        else:
            _convert2(flat[o : o + 2 * n_samp], base[0], acc[0], q[0], base[1], acc[1], q[1])


@njit(cache=True, nogil=True)
def _convert1(out, b0, a0, q0):
    """``out[n] = rint(b0[n] + q0 * a0[n])``, clipped to +-32767."""
    lo = np.float32(-32767.0)
    hi = np.float32(32767.0)
    for n in range(a0.shape[0]):
        v = b0[n] + q0 * np.float32(a0[n])
        out[n] = np.int16(np.rint(min(max(v, lo), hi)))


@njit(cache=True, nogil=True)
def _convert2(out, b0, a0, q0, b1, a1, q1):
    """Two channels, interleaved: ``out[2n + ch]``."""
    lo = np.float32(-32767.0)
    hi = np.float32(32767.0)
    for n in range(a0.shape[0]):
        v0 = b0[n] + q0 * np.float32(a0[n])
        v1 = b1[n] + q1 * np.float32(a1[n])
        out[2 * n] = np.int16(np.rint(min(max(v0, lo), hi)))
        out[2 * n + 1] = np.int16(np.rint(min(max(v1, lo), hi)))


# --------------------------------------------------------------------------------------------------------
# the bank


class WaveformBank:
    """Tone tables, the lookup table and the render kernels for one configuration (see the module docstring)."""

    def __init__(self, config: SystemConfig, *, prefix: bool = True) -> None:
        """``prefix=False`` renders every tone from its own row (no prefix tables; for tests)."""
        wf = config.waveforms
        arr = config.array
        self.config = config
        self.trap_source = arr.trap_source
        self.chain = arr.trap_source == "aod"
        self.n_channels = 1 if self.chain else 2
        self.slot_samples = n = wf.slot_samples
        self.axes = _axes_of(config)
        self.tones = {ax: axis_tones(config, ax) for ax in self.axes}
        check_headroom(config, self.tones)
        self.nx, self.ny = arr.nx, arr.ny
        self.n_max = max(arr.nx, arr.ny)
        self._n_sites = np.array([arr.nx, arr.ny], dtype=np.int64)
        self._cyc = np.zeros((2, self.n_max), dtype=np.int64)
        self._amp = np.zeros((2, self.n_max), dtype=np.float64)
        self._phi = np.zeros((2, self.n_max), dtype=np.float64)
        for a, ax in enumerate(self.axes):
            t = self.tones[ax]
            self._cyc[a, : t.frequency_hz.size] = np.round(t.frequency_hz * wf.slot_duration_s).astype(np.int64)
            self._amp[a, : t.amplitude.size] = t.amplitude
            self._phi[a, : t.phase_rad.size] = t.phase_rad
        self._shp = _shape_table(wf.shape, wf.shape_sharpness, n)
        self.scale = FULL_SCALE

        # int16 table units: q counts per unit, from a bound on every row of the axis (chain mover rows hold
        # a moving tone, minus a static tone, plus a fading one: at most 3x the largest amplitude)
        self.q = np.ones(2, dtype=np.float32)
        self._inv_q = np.ones(2, dtype=np.float64)
        for a, ax in enumerate(self.axes):
            bound = (3.0 if self.chain else 1.0) * float(np.max(self.tones[ax].amplitude)) * self.scale
            self._inv_q[a] = 32767.0 / bound
            self.q[a] = np.float32(1.0 / self._inv_q[a])

        # the lookup table: whole (axis, kind) blocks, most used first, while they fit the budget
        kinds = CHAIN_KINDS if self.chain else SLM_KINDS
        axes_order = (0,) if self.chain else (1, 0)  # y moves dominate 2D plans
        budget = wf.table_max_bytes
        chosen = []
        rows = 0
        for k in kinds:
            for a in axes_order:
                size = 2 * n * int(self._n_sites[a])
                if size <= budget:
                    chosen.append((a, k, rows))
                    rows += int(self._n_sites[a])
                    budget -= size
        self.table = np.zeros((rows, n), dtype=np.int16)
        # the key of every (axis, kind, site), by [axis * N_KINDS + kind, site]: its table row, or -(code + 1)
        # to synthesize it at render time (code = (axis * N_KINDS + kind) * n_max + site); int32, so a lookup
        # after a render (which evicts the caches) reads half the cache lines
        self._key_of = -1 - np.arange(2 * N_KINDS * self.n_max, dtype=np.int32).reshape(2 * N_KINDS, self.n_max)
        self.tabulated = [(self.axes[a], KIND_NAMES[k]) for a, k, _ in chosen]
        for a, k, r0 in chosen:
            ns = int(self._n_sites[a])
            for site in range(ns):
                _tone(k, site, ns, self._cyc[a], self._amp[a], self._phi[a], self._shp, self.scale,
                      self._inv_q[a], self.table[r0 + site])
                self._key_of[a * N_KINDS + k, site] = r0 + site
        self.table_bytes = int(self.table.nbytes)

        # prefix tables (slm): for every tabulated (axis, kind) block, in the same order, while the rest of the
        # budget holds them: int32 P[k] = sum_{j<k} row_j, k = 0..n_sites, so a run [a, b) is P[b] - P[a]
        pchosen = []
        prows = 0
        if prefix and not self.chain:
            for a, k, r0 in chosen:
                size = 4 * n * (int(self._n_sites[a]) + 1)
                if size <= budget:
                    pchosen.append((a, k, r0, prows))
                    prows += int(self._n_sites[a]) + 1
                    budget -= size
        self.prefix = np.zeros((prows, n), dtype=np.int32)
        self._prow_of = np.full(2 * N_KINDS, -1, dtype=np.int64)
        for a, k, r0, p0 in pchosen:
            ns = int(self._n_sites[a])
            np.cumsum(self.table[r0 : r0 + ns], axis=0, dtype=np.int32, out=self.prefix[p0 + 1 : p0 + ns + 1])
            self._prow_of[a * N_KINDS + k] = p0
        self.prefixed = [(self.axes[a], KIND_NAMES[k]) for a, k, _, _ in pchosen]
        self.prefix_bytes = int(self.prefix.nbytes)

        # the base row of every slot: the hold waveform (chain) or silence (slm), and its int16 rendering
        self._base = np.zeros((self.n_channels, n), dtype=np.float32)
        if self.chain:
            t = self.tones["x"]
            idx = np.arange(n, dtype=np.int64)
            hold = np.zeros(n)
            for k in range(arr.nx):
                m0 = int(self._cyc[0, k]) % n
                hold += t.amplitude[k] * self.scale * np.sin(t.phase_rad[k] + 2 * np.pi / n * ((m0 * idx) % n))
            self._base[0] = hold.astype(np.float32)
        self._hold = np.ascontiguousarray(np.clip(np.rint(self._base.T), -32767, 32767).astype(np.int16))

        self.stride = 2 + (arr.nx if self.chain else arr.nx + arr.ny)
        self._acc = np.zeros((self.n_channels, n), dtype=np.int32)
        self._scratch = np.zeros((4, n), dtype=np.int16)
        self._fs_keys = np.zeros(self.stride, dtype=np.int64)
        self._last_keys: np.ndarray | None = None
        self._last_first = -1
        self._last_count = -1
        self._warm_up()

    # --- interface used by the streamer --------------------------------------------------------------

    def max_keys(self, n_slots: int) -> int:
        """Length of an int64 keys buffer that can hold ``lookup`` output for ``n_slots`` slots."""
        return int(n_slots) * self.stride

    def lookup(self, ops: Operations, first: int, count: int, keys: np.ndarray) -> None:
        """Stage IV.lookup: resolve slots ``first..first+count-1`` to table keys in ``keys`` (no allocation).

        A chain plan is ~10 slots that resolve in ~1 us, so the call itself must stay small: one kernel with
        few arguments (the constant tables fixed at construction), which also checks the plan's array and the
        size of ``keys``; only the slot range needs ``ops.n`` and is checked here.
        """
        if first < 0 or count < 0 or first + count > ops.n:
            raise ValueError(f"slots {first}..{first + count - 1} are outside the {ops.n} slots of the plan")
        if self.chain:
            err = _lookup_chain(ops.kind, ops.x_site, ops.x_delta, first, count, keys, self._key_of)
        else:
            err = _lookup_slm(ops.kind, ops.x_site, ops.x_delta, ops.y_site, ops.y_delta, first, count, keys,
                              self._key_of, self._prow_of, self.nx, self.ny)
        if err:
            self._last_keys = None
            self._lookup_failed(err, ops, count, keys)
        self._last_keys = keys
        self._last_first = first
        self._last_count = count

    def _lookup_failed(self, err: int, ops: Operations, count: int, keys: np.ndarray) -> None:
        """Raise the ``ValueError`` that the lookup kernel's error code ``err`` stands for."""
        code, i = err % 16, err // 16
        if code == _E_ARRAY:
            raise ValueError(f"the plan is for a {ops.ny} x {ops.nx} array; this bank is for {self.ny} x {self.nx}")
        if code == _E_KEYS:
            raise ValueError(
                f"keys buffer holds {keys.shape[0]} keys; {count} slots need max_keys({count}) = {count * self.stride}"
            )
        try:
            where = ops.describe(i)
        except ValueError:
            where = f"slot {i}: kind {int(ops.kind[i])}"
        raise ValueError(f"invalid waveform slot: {_ERRORS.get(code, 'error')} ({where})")

    def _check_out(self, out: np.ndarray, n_samples: int) -> None:
        if (out.dtype != np.int16 or out.ndim != 2 or out.shape[0] < n_samples or out.shape[1] != self.n_channels
                or not out.flags.c_contiguous):
            raise ValueError(
                f"out must be a C-contiguous int16[>= {n_samples}, {self.n_channels}] array, "
                f"got {out.dtype}{list(out.shape)}"
            )

    def render(self, ops: Operations, first: int, count: int, out: np.ndarray) -> None:
        """Stage IV.render: int16 samples of slots ``first..first+count-1`` into ``out[:count*N]``, from the keys
        of the last ``lookup`` of the same slots (no allocation)."""
        if self._last_keys is None or first != self._last_first or count > self._last_count:
            raise ValueError(f"render({first}, {count}) needs a lookup() of the same slots first")
        self._check_out(out, count * self.slot_samples)
        _render(self._last_keys, count, self.stride, self.n_channels, self._base, self.q, self.table, self.prefix,
                self._n_sites, self._cyc, self._amp, self._phi, self._shp, self.n_max, self.scale, self._inv_q,
                self._acc, self._scratch, out)

    def render_failsafe(self, ops: Operations, i: int, out: np.ndarray) -> None:
        """``out`` (int16[N, n_channels]): the tones where slot ``i`` leaves them, steady (loops seamlessly)."""
        self._check_out(out, self.slot_samples)
        if self.chain:
            out[: self.slot_samples] = self._hold
            return
        if not 0 <= i < ops.n:
            raise ValueError(f"slot {i} is outside the {ops.n} slots of the plan")
        _failsafe_keys(ops.kind, ops.x_site, ops.x_delta, ops.y_site, ops.y_delta, i, self._fs_keys,
                       self._key_of, self._prow_of, self.nx, self.ny)
        _render(self._fs_keys, 1, self.stride, self.n_channels, self._base, self.q, self.table, self.prefix,
                self._n_sites, self._cyc, self._amp, self._phi, self._shp, self.n_max, self.scale, self._inv_q,
                self._acc, self._scratch, out)

    def hold(self) -> np.ndarray:
        """int16[N, n_channels]: the idle waveform (chain: every site's static tone; slm: silence)."""
        return self._hold.copy()

    # --- conveniences (allocate; for tests and tools) --------------------------------------------------

    def render_slots(self, ops: Operations, first: int = 0, count: int | None = None) -> np.ndarray:
        """Look up and render ``count`` slots into a new ``int16[count * N, n_channels]`` array."""
        count = ops.n - first if count is None else count
        keys = np.zeros(self.max_keys(count), dtype=np.int64)
        out = np.zeros((count * self.slot_samples, self.n_channels), dtype=np.int16)
        self.lookup(ops, first, count, keys)
        self.render(ops, first, count, out)
        return out

    def failsafe(self, ops: Operations, i: int) -> np.ndarray:
        """``render_failsafe`` into a new array."""
        out = np.zeros((self.slot_samples, self.n_channels), dtype=np.int16)
        self.render_failsafe(ops, i, out)
        return out

    def table_row(self, axis: str, kind: int, site: int) -> np.ndarray | None:
        """The int16 table row of ``(axis, kind, site)`` (units of ``q[axis]`` counts), or None when that
        row is synthesized at render time."""
        a = self.axes.index(axis)
        key = self._key_of[a * N_KINDS + kind, site]
        return None if key < 0 else self.table[key]

    def synthesize(self, axis: str, kind: int, site: int, *, exact: bool = False) -> np.ndarray:
        """One tone from the numba tone kernel: int16 table units (as direct synthesis at render time), or
        with ``exact`` the float64 value in counts."""
        a = self.axes.index(axis)
        row = np.zeros(self.slot_samples, dtype=np.float64 if exact else np.int16)
        _tone(kind, site, int(self._n_sites[a]), self._cyc[a], self._amp[a], self._phi[a], self._shp, self.scale,
              0.0 if exact else self._inv_q[a], row)
        return row

    def cycles(self, axis: str) -> np.ndarray:
        """Whole cycles per slot of every site of ``axis``."""
        a = self.axes.index(axis)
        return self._cyc[a, : self._n_sites[a]].copy()

    # --- warm-up ---------------------------------------------------------------------------------------

    def _warm_up(self) -> None:
        """Compile (or load from numba's cache) every kernel now, not during the first cycle."""
        ops = Operations(nx=self.nx, ny=self.ny, capacity=4)
        if self.chain:
            if self.nx >= 2:
                ops.append(SHIFT, [0], [0], [0], [1])
            ops.append(IDLE, [], [])
        else:
            ops.append(EXTRACT, [0], [0])
            ops.append(SHIFT, [0], [0], [0], [0])
            ops.append(IMPLANT, [0], [0])
        n = ops.n
        keys = np.zeros(self.max_keys(n), dtype=np.int64)
        out = np.zeros((n * self.slot_samples, self.n_channels), dtype=np.int16)
        self.lookup(ops, 0, n, keys)
        self.render(ops, 0, n, out)
        fs = np.zeros((self.slot_samples, self.n_channels), dtype=np.int16)
        self.render_failsafe(ops, 0, fs)
        self.synthesize(self.axes[0], STATIC, 0)  # the standalone tone kernel (int16 and float64 rows)
        self.synthesize(self.axes[0], STATIC, 0, exact=True)
        self._last_keys = None


# --------------------------------------------------------------------------------------------------------
# plain-numpy reference synthesizer (tests)


class ReferenceSynth:
    """The same waveforms built tone by tone in plain numpy (float64 counts), from the rules in the docstring.

    Chain slots are assembled from the full tone list (movers, fades, statics), not differentially, so the
    tests compare two independent constructions.
    """

    def __init__(self, config: SystemConfig) -> None:
        wf = config.waveforms
        self.config = config
        self.chain = config.array.trap_source == "aod"
        self.n = wf.slot_samples
        self.shape = wf.shape
        self.sharpness = wf.shape_sharpness
        self.axes = _axes_of(config)
        self.tones = {ax: axis_tones(config, ax) for ax in self.axes}
        self.cyc = {ax: np.round(t.frequency_hz * wf.slot_duration_s).astype(np.int64) for ax, t in self.tones.items()}
        self.u = np.arange(self.n) / self.n

    def phase(self, axis: str, k: int, d: int = 0) -> np.ndarray:
        return phase_track(self.cyc[axis], self.tones[axis].phase_rad, k, d, self.n, self.shape, self.sharpness)

    def _s(self, u: np.ndarray) -> np.ndarray:
        return shape_curve(self.shape, self.sharpness, u)

    def tone(self, axis: str, kind: int, k: int) -> np.ndarray:
        """float64[N] counts of one tone (any kind, the chain's composite mover rows included)."""
        t = self.tones[axis]
        a = t.amplitude * FULL_SCALE
        static = a[k] * np.sin(self.phase(axis, k)[:-1])
        if kind >= INNER_UP:
            up = kind in (INNER_UP, HEAD_UP, TAIL_UP, ISO_UP)
            d = 1 if up else -1
            if not 0 <= k + d < a.size:
                return np.zeros(self.n)
            v = self.tone(axis, MOVE_UP if up else MOVE_DOWN, k) - static
            if kind in (HEAD_UP, HEAD_DOWN, ISO_UP, ISO_DOWN):
                v += self.tone(axis, FADE_OUT, k + d) - self.tone(axis, STATIC, k + d)
            if kind in (TAIL_UP, TAIL_DOWN, ISO_UP, ISO_DOWN):
                v += self.tone(axis, FADE_IN, k)
            return v
        if kind in (MOVE_UP, MOVE_DOWN):
            d = 1 if kind == MOVE_UP else -1
            if not 0 <= k + d < a.size:
                return np.zeros(self.n)
            amp = a[k] + (a[k + d] - a[k]) * self._s(self.u)
            return amp * np.sin(self.phase(axis, k, d)[:-1])
        if kind == STATIC:
            return static
        if kind == RAMP_UP:
            return self._s(self.u) * static
        if kind == RAMP_DOWN:
            return (1 - self._s(self.u)) * static
        if kind == FADE_OUT:
            return (1 - self._s(self.u / FADE_OUT_END)) * static
        if kind == FADE_IN:
            return self._s((self.u - FADE_IN_START) / (1 - FADE_IN_START)) * static
        raise ValueError(f"unknown kind {kind}")

    def hold(self) -> np.ndarray:
        out = np.zeros((self.n, 1 if self.chain else 2))
        if self.chain:
            for k in range(self.config.array.nx):
                out[:, 0] += self.tone("x", STATIC, k)
        return out

    def slot(self, ops: Operations, i: int) -> np.ndarray:
        """float64[N, n_channels] counts of slot ``i``."""
        ys, dys, xs, dxs = ops.tones(i)
        kind = int(ops.kind[i])
        if self.chain:
            out = np.zeros((self.n, 1))
            if kind == IDLE:
                return self.hold()
            deltas = {int(k): int(d) for k, d in zip(xs, dxs) if d != 0}
            dst = {k + d for k, d in deltas.items()}
            for k, d in deltas.items():
                out[:, 0] += self.tone("x", MOVE_UP if d > 0 else MOVE_DOWN, k)
            for k in range(self.config.array.nx):
                if k in dst and k not in deltas:
                    out[:, 0] += self.tone("x", FADE_OUT, k)
                elif k in deltas and k not in dst:
                    out[:, 0] += self.tone("x", FADE_IN, k)
                elif k not in deltas:
                    out[:, 0] += self.tone("x", STATIC, k)
            return out
        out = np.zeros((self.n, 2))
        for ch, (sites, deltas, axis) in enumerate(((xs, dxs, "x"), (ys, dys, "y"))):
            for k, d in zip(sites.tolist(), deltas.tolist()):
                if kind == EXTRACT:
                    out[:, ch] += self.tone(axis, RAMP_UP, k)
                elif kind == IMPLANT:
                    out[:, ch] += self.tone(axis, RAMP_DOWN, k)
                elif kind == SHIFT:
                    out[:, ch] += self.tone(axis, STATIC if d == 0 else (MOVE_UP if d > 0 else MOVE_DOWN), k)
        return out

    def failsafe(self, ops: Operations, i: int) -> np.ndarray:
        if self.chain:
            return self.hold()
        ys, dys, xs, dxs = ops.tones(i)
        kind = int(ops.kind[i])
        out = np.zeros((self.n, 2))
        if kind in (EXTRACT, SHIFT):
            for ch, (sites, deltas, axis) in enumerate(((xs, dxs, "x"), (ys, dys, "y"))):
                for k, d in zip(sites.tolist(), deltas.tolist()):
                    out[:, ch] += self.tone(axis, STATIC, k + (d if kind == SHIFT else 0))
        return out
