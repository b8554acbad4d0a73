"""The waveform vocabulary and its specification in plain numpy: full scale, the tone kinds (the ``kind`` of a
lookup-table key), the transition shape ``s(u)`` and the phase track of a moving tone.

The numba kernels (``engine.waveforms.kernels``) evaluate the same formulas sample by sample; the functions
here are what they are tested against (see the package docstring for the physics).
"""

from __future__ import annotations

import numpy as np
from scipy.special import erf

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

# rows of the shape table passed to the kernels
_S, _G, _CUM, _ENV_OUT, _ENV_IN = range(5)


def shape_curve(shape: str, sharpness: float, u: np.ndarray) -> np.ndarray:
    """Transition shape ``s(u)``, 0 at u <= 0 and 1 at u >= 1, symmetric about 1/2."""
    u = np.clip(np.asarray(u, dtype=np.float64), 0.0, 1.0)
    if shape == "min-jerk":
        return u**3 * (10.0 - 15.0 * u + 6.0 * u * u)
    v = float(sharpness)
    if shape == "tanh":
        return 0.5 + 0.5 * np.tanh(2.0 * v * (u - 0.5)) / np.tanh(v)
    if shape == "erf":
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

