"""A tiny analytic tone synthesizer for the simulated lab's tests (independent of engine/waveforms).

Each tone is ``a(t) * alpha * sin(phase(t))`` where the position along the site comb follows a smooth
transition symmetric about mid-slot (min-jerk, or tanh with a sharpness) and the amplitude follows the same
shape over its own window (the whole slot for ramps; the first/last 40 % for chain fades).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.sim.decode import site_tones
from engine.config import SystemConfig, config_from_dict


@dataclass(frozen=True)
class Tone:
    site0: float
    site1: float
    amp0: float = 1.0
    amp1: float = 1.0
    ramp: tuple[float, float] = (0.0, 1.0)  # amplitude transition window, fractions of the slot


def static(k: int) -> Tone:
    return Tone(k, k)


def move(k: int, d: int) -> Tone:
    return Tone(k, k + d)


def ramp_up(k: int) -> Tone:
    return Tone(k, k, 0.0, 1.0)


def ramp_down(k: int) -> Tone:
    return Tone(k, k, 1.0, 0.0)


def fade_out(k: int) -> Tone:
    return Tone(k, k, 1.0, 0.0, (0.0, 0.4))


def fade_in(k: int) -> Tone:
    return Tone(k, k, 0.0, 1.0, (0.6, 1.0))


def chain_shift(n: int, movers: list[int], d: int) -> list[Tone]:
    """A chain slot: tones at ``movers`` shift by ``d``; entered sites fade out, vacated sites fade in."""
    return chain_moves(n, {k: d for k in movers})


def chain_moves(n: int, deltas: dict[int, int]) -> list[Tone]:
    """A chain slot where the tone at site k moves by ``deltas[k]`` (blocks may move different ways)."""
    src = set(deltas)
    dst = {k + d for k, d in deltas.items()}
    tones = [move(k, d) for k, d in deltas.items()]
    for k in range(n):
        if k in dst and k not in src:
            tones.append(fade_out(k))
        elif k in src and k not in dst:
            tones.append(fade_in(k))
        elif k not in src:
            tones.append(static(k))
    return tones


def min_jerk(u: np.ndarray) -> np.ndarray:
    u = np.clip(u, 0.0, 1.0)
    return u**3 * (10 - 15 * u + 6 * u * u)


def tanh_shape(sharpness: float):
    def shape(u: np.ndarray) -> np.ndarray:
        u = np.clip(u, 0.0, 1.0)
        return 0.5 + 0.5 * np.tanh(2 * sharpness * (u - 0.5)) / np.tanh(sharpness)

    return shape


def synth_axis(
    config: SystemConfig, axis: str, tones: list[Tone], *, shape=min_jerk, full_scale: float = 32767.0, seed: int = 0
) -> np.ndarray:
    """float64 samples of one slot on one axis."""
    fs = config.waveforms.sample_rate_hz
    n = config.waveforms.slot_samples
    freqs, alphas = site_tones(config, axis)
    sites = np.arange(freqs.size, dtype=np.float64)
    u = np.arange(n) / n
    phases = np.random.default_rng(seed).uniform(0, 2 * np.pi, len(tones))
    out = np.zeros(n)
    for tone, phi in zip(tones, phases, strict=True):
        pos = tone.site0 + (tone.site1 - tone.site0) * shape(u)
        f = np.interp(pos, sites, freqs)
        alpha = np.interp(pos, sites, alphas)
        if config.waveforms.compensate_dac_sinc:  # as the bank renders: delivered after the DAC's hold at f
            alpha = alpha / np.sinc(f / fs)
        lo, hi = tone.ramp
        a = tone.amp0 + (tone.amp1 - tone.amp0) * shape((u - lo) / (hi - lo))
        out += a * alpha * np.sin(phi + 2 * np.pi * np.cumsum(f) / fs)
    return out * full_scale


def synth_slots(
    config: SystemConfig,
    slots: list[tuple[list[Tone], list[Tone] | None]],
    *,
    shape=min_jerk,
    full_scale: float = 32767.0,
) -> np.ndarray:
    """``int16[n_slots * slot_samples, n_channels]`` for a list of ``(x_tones, y_tones)`` slots."""
    n_ch = 1 if config.array.trap_source == "aod" else 2
    n = config.waveforms.slot_samples
    out = np.zeros((len(slots) * n, n_ch))
    for i, (xt, yt) in enumerate(slots):
        out[i * n : (i + 1) * n, 0] = synth_axis(config, "x", xt, shape=shape, full_scale=full_scale, seed=i)
        if n_ch == 2 and yt:
            out[i * n : (i + 1) * n, 1] = synth_axis(config, "y", yt, shape=shape, full_scale=full_scale, seed=i + 7)
    return np.clip(np.round(out), -32768, 32767).astype(np.int16)


def chain_config(nx: int = 16, **over) -> SystemConfig:
    data = {
        "array": {
            "nx": nx,
            "ny": 1,
            "trap_source": "aod",
            "x_tones": {"start_hz": 70e6, "spacing_hz": 1e6, "amplitude": 0.014},
        },
        "target": {"kind": "centre", "count": max(1, nx // 2)},
        "camera": {"roi_width_px": 16 * nx, "roi_height_px": 16},
        "awg": {"n_segments": 16, "n_steps": 64, "waveforms_per_segment": 4},
    }
    return config_from_dict(_merge(data, over))


def grid_config(nx: int = 8, ny: int = 6, **over) -> SystemConfig:
    data = {
        "array": {
            "nx": nx,
            "ny": ny,
            "trap_source": "slm",
            "x_tones": {"start_hz": 70e6, "spacing_hz": 1e6, "amplitude": 0.015},
            "y_tones": {"start_hz": 80e6, "spacing_hz": 1e6, "amplitude": 0.015},
        },
        "target": {"kind": "rectangle", "row0": 0, "col0": 0, "rows": 1, "cols": 1},
        "camera": {"roi_width_px": 16 * nx, "roi_height_px": 16 * ny},
        "waveforms": {"sample_rate_hz": 313.6e6},  # 3136 samples per 10 us slot: a multiple of 32, as the card needs
        "awg": {"n_segments": 16, "n_steps": 64, "waveforms_per_segment": 4},
    }
    return config_from_dict(_merge(data, over))


def _merge(base: dict, over: dict) -> dict:
    out = dict(base)
    for k, v in over.items():
        out[k] = _merge(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else v
    return out
