"""The AOD's and the RF chain's limits: tone resolution (physical against the simulator's), the AOD band and
the DAC's images, and each channel's RF limits, checked when a configuration is applied and on every segment
before it is played (the streamer's guard and the simulated AWG)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim.awg import SimAWG
from drivers.sim.clock import SimClock
from drivers.sim.decode import DecodeConfigError, SampleDecoder
from drivers.sim.world import World
from drivers.spectrum import SpectrumAWG
from engine.aod_limits import (
    RFLimitError,
    SegmentGuard,
    comb_power_w,
    dac_sinc_gain,
    dbm_to_w,
    segment_levels,
    segment_levels_reference,
    w_to_dbm,
)
from engine.config import AWGConfig, DevicesConfig
from engine.devices import DeviceError
from engine.errors import ConfigError
from engine.operations import EXTRACT, IMPLANT, SHIFT, Operations
from engine.streaming import Streamer
from engine.waveforms import WaveformBank
from sim_signals import chain_config, grid_config, static, synth_slots
from tests.fake_spcm import C, make_fake_spcm

BAND = {"aod_centre_hz": 100e6, "aod_bandwidth_hz": 70e6}  # 65..135 MHz


def _refused(**over) -> str:
    with pytest.raises(ConfigError) as info:
        chain_config(32, **over)
    return str(info.value)


def test_a_spacing_finer_than_one_beat_per_slot_is_refused_as_the_physical_limit() -> None:
    message = _refused(array={"x_tones": {"spacing_hz": 0.05e6}})
    assert "physical limit" in message and "array.x_tones.spacing_hz" in message and "got 0.5" in message


def test_half_a_megahertz_at_ten_microseconds_is_exactly_the_decoders_limit_and_accepted() -> None:
    # 313.6 MS/s: the half-site window would round up to 1255 samples, past 0.4 of the 3136-sample slot
    cfg = grid_config(8, 6, array={"x_tones": {"spacing_hz": 0.5e6}, "y_tones": {"spacing_hz": 0.5e6}})
    decoder = SampleDecoder(cfg)
    assert decoder.window_samples <= 0.4 * decoder.slot_samples


def test_a_spacing_the_physics_allows_but_the_simulator_cannot_decode_says_it_is_the_simulators_limit() -> None:
    cfg = chain_config(16, array={"x_tones": {"spacing_hz": 0.3e6}})  # accepted: 10 us x 0.3 MHz = 3 >= 1
    with pytest.raises(DecodeConfigError, match="limit of the simulated lab") as info:
        SampleDecoder(cfg)
    assert "needs >= 1" in str(info.value) and "(got 3)" in str(info.value)


def test_a_comb_outside_the_aod_band_is_refused() -> None:
    # the issue's 64-tone comb from 5 to 295 MHz at 624 MS/s
    message = _refused(array={"nx": 64, "x_tones": {"start_hz": 5e6, "spacing_hz": 4.6e6, **BAND}},
                       camera={"roi_width_px": 1024}, target={"count": 32})
    assert "outside the AOD's band 65..135 MHz" in message and "array.x_tones" in message


def test_a_comb_whose_dac_images_fall_in_the_band_is_refused() -> None:
    # 70..101 MHz sampled at 224 MS/s: images at 123..154 MHz, inside 65..135 MHz (below Nyquist, so only the
    # band check can see it)
    message = _refused(array={"x_tones": BAND}, waveforms={"sample_rate_hz": 224e6})
    assert "images" in message and "123..154 MHz" in message and "raise waveforms.sample_rate_hz" in message
    chain_config(32, array={"x_tones": BAND}, waveforms={"sample_rate_hz": 313.6e6})  # images 212..244: fine


def test_the_band_needs_centre_and_width() -> None:
    assert "both aod_centre_hz and aod_bandwidth_hz" in _refused(array={"x_tones": {"aod_centre_hz": 100e6}})


@pytest.mark.parametrize(
    ("rf", "hint"),
    [
        ({"max_tones": 31}, "32 tones, above array.x_tones.rf.max_tones = 31"),
        ({"max_summed_amplitude": 0.4}, "above array.x_tones.rf.max_summed_amplitude = 0.4"),
        # 32 tones of 0.014 at 140 mV into 50 ohm: 32 (1.96 mV)^2 / 100 ohm = 1.23e-6 W = -29.10 dBm, and
        # -28.83 dBm with each tone at 0.014 / sinc(f / 624 MS/s) (70..101 MHz) as the samples carry it
        ({"max_rf_power_dbm": -29.0}, "deliver -28.83 dBm"),
        ({"max_rf_power_mw": 1e-3}, "deliver -28.83 dBm"),
    ],
)
def test_each_rf_limit_is_refused_when_a_configuration_exceeds_it(rf: dict, hint: str) -> None:
    message = _refused(array={"x_tones": {"rf": rf}})
    assert hint in message
    looser = {k: (v + 1 if k == "max_tones" else v * 2 if k != "max_rf_power_dbm" else v + 1) for k, v in rf.items()}
    chain_config(32, array={"x_tones": {"rf": looser}})  # just inside: accepted


def test_power_is_given_once() -> None:
    assert "not both" in _refused(array={"x_tones": {"rf": {"max_rf_power_dbm": 0.0, "max_rf_power_mw": 1.0}}})


def test_power_units_and_the_dac_roll_off() -> None:
    assert dbm_to_w(0.0) == pytest.approx(1e-3) and w_to_dbm(1e-3) == pytest.approx(0.0)
    assert w_to_dbm(dbm_to_w(13.0)) == pytest.approx(13.0)
    # one full-scale tone of 1 V peak into 50 ohm: 10 mW = 10 dBm
    assert comb_power_w(np.array([1.0]), 1.0, 50.0) == pytest.approx(0.01)
    assert float(dac_sinc_gain(295e6, 624e6)) == pytest.approx(0.67, abs=0.005)  # the issue's figure


def test_the_segment_kernel_matches_the_plain_reference() -> None:
    rng = np.random.default_rng(3)
    x = rng.integers(-32768, 32768, (5 * 96 + 40, 2)).astype(np.int16)
    x[7, 1] = -32768  # |-32768| must not overflow
    for slot in (96, 1000):
        peak, ms = segment_levels(x, slot)
        ref_peak, ref_ms = segment_levels_reference(x, slot)
        np.testing.assert_allclose(peak, ref_peak)
        np.testing.assert_allclose(ms, ref_ms, rtol=1e-12)
    assert segment_levels(x, 96)[0][1] == 32768


def _sample_amplitudes(cfg) -> np.ndarray:
    """The chain's tones as the samples carry them: amplitude / sinc(f / f_s), the DAC's hold compensated."""
    tones = cfg.array.x_tones
    freq = tones.start_hz + tones.spacing_hz * np.arange(cfg.array.nx)
    return tones.amplitude / np.sinc(freq / cfg.waveforms.sample_rate_hz)


def _full_comb_samples(cfg) -> np.ndarray:
    n = cfg.array.nx
    return synth_slots(cfg, [([static(k) for k in range(n)], None)] * 2)


def test_the_guard_measures_the_segment_the_amplifier_would_get() -> None:
    cfg = chain_config(32)
    samples = _full_comb_samples(cfg)
    # the measured slot power equals the comb's power (the tones are orthogonal over a slot)
    expected_w = comb_power_w(_sample_amplitudes(cfg), cfg.full_scale_v(0), 50.0)
    _, ms = segment_levels(samples, cfg.waveforms.slot_samples)
    measured_w = ms[0] * (cfg.full_scale_v(0) / 32767.0) ** 2 / 50.0
    assert measured_w == pytest.approx(expected_w, rel=2e-3)
    peak = np.abs(samples.astype(np.int64)).max() / 32767.0
    assert peak <= float(np.sum(_sample_amplitudes(cfg))) + 1e-3

    tight_peak = chain_config(32, array={"x_tones": {"rf": {"max_peak_amplitude": 0.5 * peak}}})
    guard = SegmentGuard(tight_peak.channel_limits(), cfg.waveforms.slot_samples)
    with pytest.raises(RFLimitError, match="max_peak_amplitude"):
        guard.check(samples)
    # a limit the configuration allows (the comb's own power) but a louder segment breaks: the samples decide
    at_limit = chain_config(32, array={"x_tones": {"rf": {"max_rf_power_dbm": w_to_dbm(expected_w) + 0.1}}})
    guard = SegmentGuard(at_limit.channel_limits(), cfg.waveforms.slot_samples)
    assert guard.problem(samples) is None
    with pytest.raises(RFLimitError, match=r"dBm .* into 50 ohm"):
        guard.check((samples.astype(np.float64) * 1.1).astype(np.int16))


def test_the_simulated_awg_refuses_a_segment_over_the_limits_and_plays_one_within() -> None:
    cfg = chain_config(32, awg={"upload_jitter_s": 0.0})
    samples = _full_comb_samples(cfg)
    peak = np.abs(samples.astype(np.int64)).max() / 32767.0
    tight = chain_config(32, awg={"upload_jitter_s": 0.0},
                         array={"x_tones": {"rf": {"max_peak_amplitude": math.floor(100 * peak) / 100}}})
    for config, refused in ((cfg, False), (tight, True)):
        clock = SimClock("simulated")
        awg = SimAWG(World(config, clock=clock, lossless=True), clock, config)
        if refused:
            with pytest.raises(DeviceError, match="refused by the RF limits.*max_peak_amplitude"):
                awg.write_segment(0, samples)
        else:
            awg.write_segment(0, samples)


# --- the Spectrum adapter over the fake card -----------------------------------------------------------------

def _spectrum(settings: dict, rf_guard: SegmentGuard | None = None, **card):
    mod = make_fake_spcm(**card)
    dev = SpectrumAWG(DevicesConfig.SpectrumSettings(**settings), spcm_module=mod, rf_guard=rf_guard)
    dev.configure(AWGConfig(n_segments=16, n_steps=64), n_channels=1, sample_rate_hz=624e6)
    return dev, mod.fake.cards["/dev/spcm0"]


def test_the_spectrum_adapter_sets_the_configured_output_range_and_never_a_larger_one() -> None:
    _, card = _spectrum({"amplitude_mv": 300})
    assert card.registers[C.SPC_AMP0] == 300
    # a card whose range steps are 50 mV would make 300 mV out of 280 mV: refused, output off
    with pytest.raises(DeviceError, match="came out at 300 mV, above the configured 280 mV"):
        _spectrum({"amplitude_mv": 280}, amp_quantum_mv=50)


def test_the_spectrum_adapter_refuses_a_segment_over_the_rf_limits() -> None:
    cfg = chain_config(32)
    segment = _full_comb_samples(cfg)
    assert segment.shape[0] % 32 == 0
    peak = np.abs(segment.astype(np.int64)).max() / 32767.0
    power_w = comb_power_w(_sample_amplitudes(cfg), cfg.full_scale_v(0), 50.0)
    louder = (segment.astype(np.float64) * 1.1).astype(np.int16)  # a render that went wrong: 0.8 dB too loud
    for rf, sent, match in (
        ({"max_peak_amplitude": math.floor(100 * peak) / 100}, segment, "max_peak_amplitude"),
        ({"max_rf_power_dbm": w_to_dbm(power_w) + 0.1}, louder, "dBm"),
    ):
        limits = chain_config(32, array={"x_tones": {"rf": rf}}).channel_limits()
        dev, card = _spectrum({}, SegmentGuard(limits, cfg.waveforms.slot_samples))
        with pytest.raises(DeviceError, match=f"refused by the RF limits.*{match}"):
            dev.write_segment(0, np.ascontiguousarray(sent))
    dev, _ = _spectrum({}, SegmentGuard(cfg.channel_limits(), cfg.waveforms.slot_samples))
    dev.write_segment(0, np.ascontiguousarray(segment))  # within the limits: uploaded


def test_the_streamer_refuses_a_rendered_segment_over_the_limits_before_uploading_it() -> None:
    cfg = grid_config(8, 6)
    ops = Operations(nx=8, ny=6)
    ops.append(EXTRACT, [0, 1, 2], [0, 1, 2, 3])
    ops.append(SHIFT, [0, 1, 2], [0, 1, 2, 3], [1, 1, 1], [1, 1, 1, 1])
    ops.append(IMPLANT, [1, 2, 3], [1, 2, 3, 4])
    bank = WaveformBank(cfg)
    peak = np.abs(bank.render_slots(ops).astype(np.int64)).max(axis=0) / 32767.0  # per channel
    strict = grid_config(8, 6, array={"y_tones": {"rf": {"max_peak_amplitude": float(peak[1]) * 0.9}}})
    clock = SimClock("simulated")
    awg = SimAWG(World(cfg, clock=clock, lossless=True), clock, cfg)  # a card that would play it
    with pytest.raises(RFLimitError, match="channel 1: a sample reaches .* above array.y_tones.rf.max_peak_amplitude"):
        Streamer(strict, bank, awg, clock).stream(ops)
    assert awg.uploads == 0
    guard = SegmentGuard(cfg.channel_limits(), cfg.waveforms.slot_samples)
    assert guard.problem(bank.render_slots(ops)) is None  # within the configured limits the same render passes


def test_the_guards_peak_shortcut_decides_as_the_full_measurement() -> None:
    """A segment the all-channel peak proves safe is accepted without the per-slot sums; any other goes to the
    full measurement, so the guard's verdict (and its message) is the full measurement's, segment by segment."""
    from engine.aod_limits import ChannelLimits

    rng = np.random.default_rng(4)
    slot = 64
    for trial in range(60):
        amplitude = int(rng.integers(1, 32767))
        samples = rng.integers(-amplitude, amplitude + 1, (slot * 8, 2)).astype(np.int16)
        limits = [
            ChannelLimits(channel=c, name=f"ch{c}", max_peak_amplitude=float(rng.uniform(0.2, 1.0)),
                          max_power_w=float(rng.choice([1e-4, 1e-3, 1e-2])) if trial % 3 else None,
                          load_ohm=50.0, full_scale_counts=32767.0, full_scale_v=0.5)
            for c in range(2)
        ]  # fmt: skip
        guard = SegmentGuard(limits, slot)
        full = SegmentGuard(limits, slot)
        full._within_by_peak = lambda _samples: False  # type: ignore[method-assign]  # the full measurement only
        assert guard.problem(samples) == full.problem(samples)
