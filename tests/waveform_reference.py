"""``ReferenceSynth``: the bank's waveforms built tone by tone in plain numpy, the oracle of tests/test_waveforms.py."""

from __future__ import annotations

import numpy as np

from engine.config import SystemConfig
from engine.operations import EXTRACT, IDLE, IMPLANT, SHIFT, Operations
from engine.waveforms import axes_of, axis_tones, phase_track, shape_curve, shapes


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
        self.axes = axes_of(config)
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
        a = t.amplitude * shapes.FULL_SCALE
        if self.config.waveforms.compensate_dac_sinc:  # the DAC's zero-order hold delivers a * sinc(f / f_s)
            a = a / np.sinc(t.frequency_hz / self.config.waveforms.sample_rate_hz)
        static = a[k] * np.sin(self.phase(axis, k)[:-1])
        if kind >= shapes.INNER_UP:
            up = kind in (shapes.INNER_UP, shapes.HEAD_UP, shapes.TAIL_UP, shapes.ISO_UP)
            d = 1 if up else -1
            if not 0 <= k + d < a.size:
                return np.zeros(self.n)
            v = self.tone(axis, shapes.MOVE_UP if up else shapes.MOVE_DOWN, k) - static
            if kind in (shapes.HEAD_UP, shapes.HEAD_DOWN, shapes.ISO_UP, shapes.ISO_DOWN):
                v += self.tone(axis, shapes.FADE_OUT, k + d) - self.tone(axis, shapes.STATIC, k + d)
            if kind in (shapes.TAIL_UP, shapes.TAIL_DOWN, shapes.ISO_UP, shapes.ISO_DOWN):
                v += self.tone(axis, shapes.FADE_IN, k)
            return v
        if kind in (shapes.MOVE_UP, shapes.MOVE_DOWN):
            d = 1 if kind == shapes.MOVE_UP else -1
            if not 0 <= k + d < a.size:
                return np.zeros(self.n)
            amp = a[k] + (a[k + d] - a[k]) * self._s(self.u)
            return amp * np.sin(self.phase(axis, k, d)[:-1])
        if kind == shapes.STATIC:
            return static
        if kind == shapes.RAMP_UP:
            return self._s(self.u) * static
        if kind == shapes.RAMP_DOWN:
            return (1 - self._s(self.u)) * static
        if kind == shapes.FADE_OUT:
            return (1 - self._s(self.u / shapes.FADE_OUT_END)) * static
        if kind == shapes.FADE_IN:
            return self._s((self.u - shapes.FADE_IN_START) / (1 - shapes.FADE_IN_START)) * static
        raise ValueError(f"unknown kind {kind}")

    def hold(self) -> np.ndarray:
        out = np.zeros((self.n, 1 if self.chain else 2))
        if self.chain:
            for k in range(self.config.array.nx):
                out[:, 0] += self.tone("x", shapes.STATIC, k)
        return out

    def slot(self, ops: Operations, i: int) -> np.ndarray:
        """float64[N, n_channels] counts of slot ``i``."""
        ys, dys, xs, dxs = ops.tones(i)
        kind = int(ops.kind[i])
        if self.chain:
            out = np.zeros((self.n, 1))
            if kind == IDLE:
                return self.hold()
            deltas = {int(k): int(d) for k, d in zip(xs, dxs, strict=True) if d != 0}
            dst = {k + d for k, d in deltas.items()}
            for k, d in deltas.items():
                out[:, 0] += self.tone("x", shapes.MOVE_UP if d > 0 else shapes.MOVE_DOWN, k)
            for k in range(self.config.array.nx):
                if k in dst and k not in deltas:
                    out[:, 0] += self.tone("x", shapes.FADE_OUT, k)
                elif k in deltas and k not in dst:
                    out[:, 0] += self.tone("x", shapes.FADE_IN, k)
                elif k not in deltas:
                    out[:, 0] += self.tone("x", shapes.STATIC, k)
            return out
        out = np.zeros((self.n, 2))
        for ch, (sites, deltas, axis) in enumerate(((xs, dxs, "x"), (ys, dys, "y"))):
            for k, d in zip(sites.tolist(), deltas.tolist(), strict=True):
                if kind == EXTRACT:
                    out[:, ch] += self.tone(axis, shapes.RAMP_UP, k)
                elif kind == IMPLANT:
                    out[:, ch] += self.tone(axis, shapes.RAMP_DOWN, k)
                elif kind == SHIFT:
                    kind_d = shapes.STATIC if d == 0 else (shapes.MOVE_UP if d > 0 else shapes.MOVE_DOWN)
                    out[:, ch] += self.tone(axis, kind_d, k)
        return out

    def failsafe(self, ops: Operations, i: int) -> np.ndarray:
        if self.chain:
            return self.hold()
        ys, dys, xs, dxs = ops.tones(i)
        kind = int(ops.kind[i])
        out = np.zeros((self.n, 2))
        if kind in (EXTRACT, SHIFT):
            for ch, (sites, deltas, axis) in enumerate(((xs, dxs, "x"), (ys, dys, "y"))):
                for k, d in zip(sites.tolist(), deltas.tolist(), strict=True):
                    out[:, ch] += self.tone(axis, shapes.STATIC, k + (d if kind == SHIFT else 0))
        return out
