"""The simulator's fast paths against their plain references: numba world kernels, the fused decoder and the
background-table EMCCD sampler must behave exactly (world, decoder) or statistically (camera) like the code
they replace."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy import integrate, stats
from scipy.special import ndtr

from drivers.sim.camera import (
    TABLE_ELECTRONS,
    SimCamera,
    _emccd_counts,
    _emccd_counts_split,
    background_table,
)
from drivers.sim.clock import SimClock
from drivers.sim.decode import SampleDecoder
from drivers.sim.world import World, _Uniforms
from sim_signals import Tone, chain_config, grid_config, synth_slots

# --- world ------------------------------------------------------------------------------------------------


def random_tracks(rng: np.random.Generator, n_sites: int, m: int) -> np.ndarray:
    """Decoder-shaped tracks with every corner: repeated start sites, moves, amplitudes at the 0.5 edge."""
    s0 = rng.integers(0, n_sites, m)
    s1 = np.clip(s0 + rng.integers(-1, 2, m) * (rng.random(m) < 0.5), 0, n_sites - 1)
    amps = rng.choice(np.array([0.0, 0.2, 0.49, 0.5, 0.51, 0.7, 0.71, 1.0], np.float32), (m, 2))
    return np.column_stack([s0, s1, amps]).astype(np.float32)


@pytest.mark.parametrize(
    ("cfg", "lossless"),
    [
        (grid_config(8, 6, sim={"survival_transfer": 0.8, "survival_step": 0.7, "vacuum_lifetime_s": 10.0}), False),
        (grid_config(16, 32, sim={"survival_transfer": 0.8, "survival_step": 0.7, "vacuum_lifetime_s": 10.0}), False),
        (grid_config(8, 6), True),
        (chain_config(16, sim={"survival_step": 0.7, "vacuum_lifetime_s": 10.0}), False),
        (chain_config(16), True),
    ],
    ids=["grid-8x6", "grid-16x32", "grid-lossless", "chain", "chain-lossless"],
)
def test_world_kernels_equal_numpy_reference_on_random_slots(cfg, lossless: bool) -> None:
    ny, nx = cfg.array.ny, cfg.array.nx
    slm = cfg.array.trap_source == "slm"
    for seed in range(25):
        rng = np.random.default_rng(seed)
        fast = World(cfg, rng=np.random.default_rng(100 + seed), lossless=lossless)
        ref = World(cfg, rng=np.random.default_rng(100 + seed), lossless=lossless, reference=True)
        fast.load()
        ref.load()
        for k in range(30):
            if rng.random() < 0.3:
                dt = float(rng.random() * 5)
                fast.elapse_to(fast._t_s + dt)
                ref.elapse_to(ref._t_s + dt)
            xt = random_tracks(rng, nx, int(rng.integers(0, 2 * nx)))
            yt = random_tracks(rng, ny, int(rng.integers(0, 2 * ny))) if slm else None
            fast.apply_slot(xt, yt)
            ref.apply_slot(xt, yt)
            assert np.array_equal(fast.occupancy(), ref.occupancy()), (seed, k)
            assert np.array_equal(fast.held(), ref.held()), (seed, k)
            assert fast.counters == ref.counters, (seed, k)
        # the same draws
        assert (fast._move_draws.pos, fast._vacuum_draws.pos) == (ref._move_draws.pos, ref._vacuum_draws.pos)


def test_world_kernels_equal_reference_on_decoded_segments() -> None:
    """Random extract / shift / implant tone sets, decoded from samples, applied to both worlds."""
    cfg = grid_config(8, 6, sim={"survival_transfer": 0.9, "survival_step": 0.9})
    dec = SampleDecoder(cfg)
    rng = np.random.default_rng(7)
    for trial in range(4):
        slots = [(random_tones(rng, 8), random_tones(rng, 6)) for _ in range(6)]
        d = dec.decode(synth_slots(cfg, slots))
        fast = World(cfg, rng=np.random.default_rng(trial))
        ref = World(cfg, rng=np.random.default_rng(trial), reference=True)
        fast.load()
        ref.load()
        fast.apply_segment(d, t0_s=0.0, slot_s=1.0)
        ref.apply_segment(d, t0_s=0.0, slot_s=1.0)
        assert np.array_equal(fast.occupancy(), ref.occupancy())
        assert np.array_equal(fast.held(), ref.held())
        assert fast.counters == ref.counters


def test_predrawn_uniforms_are_the_generators_own_sequence() -> None:
    """The buffer hands out exactly what successive ``rng.random(n)`` calls return, across refills."""
    u = _Uniforms(np.random.default_rng(3))
    direct = np.random.default_rng(3)
    sizes = [5, 0, 1, 16000, 3, 40000, 7, 1]
    for n in sizes:
        np.testing.assert_array_equal(u.take(n), direct.random(n))


def test_world_loading_draws_the_same_as_before() -> None:
    cfg = grid_config(16, 32, sim={"loading_probability": 0.6})
    w = World(cfg, rng=np.random.default_rng(11))
    direct = np.random.default_rng(11)
    for _ in range(3):
        np.testing.assert_array_equal(w.load(), direct.random((32, 16)) < 0.6)


# --- decoder ----------------------------------------------------------------------------------------------


def random_tones(rng: np.random.Generator, n_sites: int) -> list[Tone]:
    """A random, decodable slot: tones a site or more apart, each static, moving, ramping or partial."""
    tones: list[Tone] = []
    k = int(rng.integers(0, 2))
    while k < n_sites:
        kind = rng.integers(0, 6)
        if kind == 0 and k + 1 < n_sites:
            tones.append(Tone(k, k + 1))
            k += 3
            continue
        if kind == 1 and k > 0 and (not tones or tones[-1].site1 < k - 1):
            tones.append(Tone(k, k - 1))
        elif kind == 2:
            tones.append(Tone(k, k, 0.0, 1.0))
        elif kind == 3:
            tones.append(Tone(k, k, 1.0, 0.0))
        elif kind == 4:
            tones.append(Tone(k, k, float(rng.uniform(0.1, 1.0)), float(rng.uniform(0.1, 1.0))))
        else:
            tones.append(Tone(k, k))
        k += int(rng.integers(2, 4))
    return tones


def assert_same_decode(a, b) -> None:
    assert a.n_slots == b.n_slots and a.stationary == b.stationary
    for axis in ("x", "y"):
        ta, tb = getattr(a, axis), getattr(b, axis)
        if ta is None:
            assert tb is None
            continue
        np.testing.assert_array_equal(getattr(a, axis + "_count"), getattr(b, axis + "_count"))
        np.testing.assert_array_equal(ta[..., :2], tb[..., :2])  # sites
        np.testing.assert_allclose(ta[..., 2:], tb[..., 2:], atol=1e-4)  # amplitudes: float32 rounding only


@pytest.mark.parametrize(
    "cfg",
    [grid_config(8, 6), grid_config(16, 32), chain_config(32)],
    ids=["grid-8x6", "grid-16x32", "chain-32"],
)
def test_fast_decoder_equals_reference_on_random_samples(cfg) -> None:
    dec = SampleDecoder(cfg)
    rng = np.random.default_rng(5)
    nx, ny = cfg.array.nx, cfg.array.ny
    slot = cfg.waveforms.slot_samples
    for _ in range(3):
        slots = [(random_tones(rng, nx), random_tones(rng, ny)) for _ in range(5)]
        slots.insert(2, slots[1])  # a repeated slot (decoded once by the fast path)
        slots.append(([], []))  # silence
        samples = synth_slots(cfg, slots)
        noisy = np.clip(samples + rng.normal(0, 30, samples.shape), -32768, 32767).astype(np.int16)
        noise_only = rng.integers(-2000, 2000, (3 * slot, samples.shape[1])).astype(np.int16)
        for s in (samples, noisy, noise_only, samples[: 2 * slot + 100]):
            assert_same_decode(dec.decode(s), dec.decode_reference(s))


# --- camera -----------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("g", "sigma", "epc"),
    [(300.0, 60.0, 20.0), (50.0, 10.0, 5.0), (300.0, 0.0, 20.0)],
    ids=["paper", "low", "no-read-noise"],
)
def test_background_table_matches_quadrature(g: float, sigma: float, epc: float) -> None:
    """The tabulated count probabilities against direct numerical integration of the model."""
    lam, bias = 0.45, 500.0
    t = background_table(lam, g, sigma, epc, bias)
    k0 = int(t.value[0])

    def cdf_n(n: int, x: float) -> float:  # P(Gamma(n, g) + N(0, sigma) <= x)
        if sigma == 0:
            return float(stats.gamma.cdf(x, n, scale=g)) if x > 0 else 0.0
        return integrate.quad(lambda e: stats.gamma.pdf(e, n, scale=g) * ndtr((x - e) / sigma), 0, np.inf, limit=400)[0]

    for k in (k0 + 5, int(bias) - 1, int(bias), int(bias) + 3, int(bias) + 20, int(bias) + 150):
        lo, hi = (k - 0.5 - bias) * epc, (k + 0.5 - bias) * epc
        no_electron = float(round(bias) == k) if sigma == 0 else ndtr(hi / sigma) - ndtr(lo / sigma)
        want = math.exp(-lam) * no_electron
        for n in range(1, TABLE_ELECTRONS + 1):
            want += math.exp(-lam) * lam**n / math.factorial(n) * (cdf_n(n, hi) - cdf_n(n, lo))
        assert t.pmf[k - k0] == pytest.approx(want, rel=1e-6, abs=1e-12), k
    assert t.pmf[-1] == pytest.approx(stats.poisson.sf(TABLE_ELECTRONS, lam), rel=1e-9)  # the literal-path share


@pytest.mark.parametrize(
    ("bg", "g", "sigma", "epc", "bias"),
    [
        (0.45, 300.0, 60.0, 20.0, 500.0),
        (1.8, 300.0, 60.0, 20.0, 500.0),
        (0.45, 300.0, 60.0, 20.0, 0.0),
        (12.0, 50.0, 10.0, 5.0, 100.0),
    ],
    ids=["paper", "bright-background", "clipped-at-zero", "background-above-10"],
)
def test_split_sampler_matches_literal_sampler(bg: float, g: float, sigma: float, epc: float, bias: float) -> None:
    """Two-sample chi-square on the count histograms of a frame with background and atom light."""
    t = background_table(bg, g, sigma, epc, bias)
    shape = (400, 1000)
    mean = bg + np.where(np.arange(shape[1]) % 4 == 0, 30.0 * np.random.default_rng(0).random(shape) ** 4, 0.0)
    a = np.empty(shape, np.uint16)
    b = np.empty(shape, np.uint16)
    _emccd_counts(np.random.default_rng(1), mean, g, sigma, epc, bias, a)
    _emccd_counts_split(
        np.random.default_rng(2), mean, bg, g, sigma, epc, bias, t.prob, t.alias, t.value, t.bg_cdf, t.slow_cdf, b
    )
    for cols in (slice(1, None, 4), slice(0, None, 4)):  # background-only columns, then columns with atom light
        ha = np.bincount(a[:, cols].ravel(), minlength=65536).astype(float)
        hb = np.bincount(b[:, cols].ravel(), minlength=65536).astype(float)
        big = (ha + hb) >= 40
        table = np.vstack([np.r_[ha[big], ha[~big].sum()], np.r_[hb[big], hb[~big].sum()]])
        table = table[:, table.sum(axis=0) > 0]
        assert stats.chi2_contingency(table)[1] > 1e-4
        assert a[:, cols].mean() == pytest.approx(b[:, cols].mean(), rel=2e-3)


def test_camera_reference_mode_renders_with_the_literal_kernel() -> None:
    cfg = grid_config(8, 6)
    occ = np.zeros((6, 8), bool)
    occ[2, 3] = True
    frames = {}
    for ref in (False, True):
        cam = SimCamera(cfg, atoms=lambda *_: occ, clock=SimClock(), rng=np.random.default_rng(4), reference=ref)
        out = np.empty(cam.frame_shape, np.uint16)
        stack = []
        for _ in range(40):
            cam.trigger()
            cam.read(out, timeout_s=1.0)
            stack.append(out.astype(np.float64))
        frames[ref] = np.stack(stack)
    # same seed, different samplers: different pixels, the same picture
    assert not np.array_equal(frames[False][0], frames[True][0])
    mean_f, mean_r = frames[False].mean(axis=0), frames[True].mean(axis=0)
    assert mean_f.sum() == pytest.approx(mean_r.sum(), rel=2e-3)
    empty = np.median(mean_r)
    atom = (slice(2 * 16, 3 * 16), slice(3 * 16, 4 * 16))  # the atom's cell
    assert (mean_f[atom] - empty).sum() == pytest.approx((mean_r[atom] - empty).sum(), rel=0.05)


def test_decoder_cache_returns_what_decoding_returns(monkeypatch: pytest.MonkeyPatch) -> None:
    """Slots found in the cache (a full one, and a 16-entry one that keeps evicting) decode as from scratch."""
    import drivers.sim.decode as decode

    cfg = grid_config(8, 6)
    rng = np.random.default_rng(9)
    segments = []
    for _ in range(6):
        slots = [(random_tones(rng, 8), random_tones(rng, 6)) for _ in range(4)]
        segments.append(synth_slots(cfg, slots))
    segments += segments[::-1]  # every slot again, from the cache
    # a slot that differs from a cached one in a single sample decodes afresh
    edited = segments[0].copy()
    edited[cfg.waveforms.slot_samples // 2, 0] += 1
    segments.append(edited)
    for entries_bytes in (decode.SLOT_CACHE_BYTES, 1):
        monkeypatch.setattr(decode, "SLOT_CACHE_BYTES", entries_bytes)
        dec = SampleDecoder(cfg)
        for s in segments:
            assert_same_decode(dec.decode(s), dec.decode_reference(s))


def test_slot_hashes_tell_slots_apart() -> None:
    """Any one changed sample changes both hashes; equal slots hash equal, on either channel."""
    from drivers.sim.decode import _hash_slots

    rng = np.random.default_rng(2)
    n = 3136
    s = rng.integers(-3000, 3000, (3 * n, 2)).astype(np.int16)
    s[n : 2 * n] = s[:n]  # slot 1 repeats slot 0 on both channels
    w = rng.integers(0, 1 << 32, (2, n), dtype=np.uint64)
    h = np.empty((2, 3, 2), np.uint64)
    silent = np.empty((2, 3), np.bool_)
    _hash_slots(s.reshape(-1), 2, n, w, h, silent)
    assert np.array_equal(h[:, 0], h[:, 1]) and not silent.any()
    for _ in range(200):
        t = s.copy()
        i, axis = int(rng.integers(0, n)), int(rng.integers(0, 2))
        t[i, axis] = np.int16(int(t[i, axis]) + int(rng.choice([-1, 1, 257, -4096])))
        h2 = np.empty_like(h)
        _hash_slots(t.reshape(-1), 2, n, w, h2, silent)
        assert h2[axis, 0, 0] != h[axis, 0, 0] and h2[axis, 0, 1] != h[axis, 0, 1]
        assert np.array_equal(h2[1 - axis], h[1 - axis])
    _hash_slots(np.zeros(3 * n * 2, np.int16), 2, n, w, h, silent)
    assert silent.all()
