"""The lookup table and ``WaveformBank``: int16 rows per (axis, kind, site) within ``waveforms.table_max_bytes``,
int32 prefix rows for runs, and the calls the streamer makes per cycle (``lookup``, ``render``,
``render_failsafe``). The table layout and its size formulas are in the package docstring.
"""

from __future__ import annotations

import numpy as np

from engine.config import SystemConfig
from engine.operations import EXTRACT, IDLE, IMPLANT, SHIFT, Operations
from engine.routing import n_positions, positions_per_site
from engine.waveforms.axes import axes_of, axis_tones, check_headroom, tone_sample_amplitudes
from engine.waveforms.kernels import (
    _E_ARRAY,
    _E_KEYS,
    _ERRORS,
    _failsafe_keys,
    _lookup_chain,
    _lookup_slm,
    _render,
    _tone,
)
from engine.waveforms.shapes import CHAIN_KINDS, FULL_SCALE, KIND_NAMES, N_KINDS, SLM_KINDS, STATIC, _shape_table


def table_formula_bytes(config: SystemConfig) -> int:
    """Bytes of the full lookup table: ``2 * slot_samples * sum over axes (n_sites * n_kinds)``."""
    kinds = len(CHAIN_KINDS) if config.array.trap_source == "aod" else len(SLM_KINDS)
    sites = config.array.nx if config.array.trap_source == "aod" else sum(_positions(config))
    return 2 * config.waveforms.slot_samples * sites * kinds


def prefix_formula_bytes(config: SystemConfig) -> int:
    """Bytes of the full prefix tables (slm only): ``4 * slot_samples * sum over axes ((n_sites + 1) * 5)``."""
    if config.array.trap_source == "aod":
        return 0
    return 4 * config.waveforms.slot_samples * (sum(_positions(config)) + 2) * len(SLM_KINDS)


def _positions(config: SystemConfig) -> tuple[int, int]:
    """Tones per axis, (x, y): a site each, and under interstitial routing the midpoints too (``engine.routing``)."""
    half = positions_per_site(config.array.routing)
    return n_positions(config.array.nx, half), n_positions(config.array.ny, half)


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
        self.axes = axes_of(config)
        self.tones = {ax: axis_tones(config, ax) for ax in self.axes}
        check_headroom(config, self.tones)
        self.half = positions_per_site(arr.routing)
        self.nx, self.ny = _positions(config)  # the tones (positions) per axis, what a plan's slots list
        self.n_max = max(self.nx, self.ny)
        self._n_sites = np.array([self.nx, self.ny], dtype=np.int64)
        self._cyc = np.zeros((2, self.n_max), dtype=np.int64)
        self._amp = np.zeros((2, self.n_max), dtype=np.float64)
        self._phi = np.zeros((2, self.n_max), dtype=np.float64)
        # the amplitude each tone is rendered at: compensated for the DAC's sinc roll-off here, once, so the
        # table and direct synthesis (and a move's linear amplitude ramp between two sites) carry it for free
        self.sample_amplitude = {ax: tone_sample_amplitudes(config, self.tones[ax]) for ax in self.axes}
        for a, ax in enumerate(self.axes):
            t = self.tones[ax]
            self._cyc[a, : t.frequency_hz.size] = np.round(t.frequency_hz * wf.slot_duration_s).astype(np.int64)
            self._amp[a, : t.amplitude.size] = self.sample_amplitude[ax]
            self._phi[a, : t.phase_rad.size] = t.phase_rad
        self._shp = _shape_table(wf.shape, wf.shape_sharpness, n)
        self.scale = FULL_SCALE

        # int16 table units: q counts per unit, from a bound on every row of the axis (chain mover rows hold
        # a moving tone, minus a static tone, plus a fading one: at most 3x the largest amplitude)
        self.q = np.ones(2, dtype=np.float32)
        self._inv_q = np.ones(2, dtype=np.float64)
        for a, ax in enumerate(self.axes):
            bound = (3.0 if self.chain else 1.0) * float(np.max(self.sample_amplitude[ax])) * self.scale
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
                hold += self._amp[0, k] * self.scale * np.sin(t.phase_rad[k] + 2 * np.pi / n * ((m0 * idx) % n))
            self._base[0] = hold.astype(np.float32)
        self._hold = np.ascontiguousarray(np.clip(np.rint(self._base.T), -32767, 32767).astype(np.int16))

        self.stride = 2 + (arr.nx if self.chain else self.nx + self.ny)
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

    def render(self, first: int, count: int, out: np.ndarray) -> None:
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
        self.render(first, count, out)
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
        ops = Operations(nx=self.nx, ny=self.ny, capacity=4, half=self.half)
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
        self.render(0, n, out)
        fs = np.zeros((self.slot_samples, self.n_channels), dtype=np.int16)
        self.render_failsafe(ops, 0, fs)
        self.synthesize(self.axes[0], STATIC, 0)  # the standalone tone kernel (int16 and float64 rows)
        self.synthesize(self.axes[0], STATIC, 0, exact=True)
        self._last_keys = None
