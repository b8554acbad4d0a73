"""The DAC's sinc roll-off: a card's zero-order hold delivers a tone of sample amplitude ``a`` at frequency ``f``
as ``a * sinc(f / f_s)`` (0.67 at 295 MHz and 624 MS/s). With ``waveforms.compensate_dac_sinc`` (the default)
the bank renders every tone at ``amplitude / sinc(f / f_s)``, so the AODs receive a flat comb; the RF limits are
checked on those compensated amplitudes; and the simulated lab's decoder applies the hold's gain, so an
uncompensated comb near Nyquist makes shallow tweezers there that fail to move atoms and lose some.
"""

from __future__ import annotations

import numpy as np
import pytest

from drivers.sim.lab import build_sim_lab
from engine.config import ConfigError, SystemConfig
from engine.engine import Engine
from engine.operations import IDLE, Operations
from engine.waveforms import MOVE_UP, WaveformBank, axis_tones, phase_track
from sim_signals import chain_config, grid_config

FS = 624e6
#: 64 tones from 5 to 294.8 MHz: the whole band of a 624 MS/s card, where the hold's gain falls from 1 to 0.67
WIDE = {"start_hz": 5e6, "spacing_hz": 4.6e6, "amplitude": 0.012}


def _wide_chain(compensate: bool) -> SystemConfig:
    return chain_config(64, array={"x_tones": WIDE}, waveforms={"compensate_dac_sinc": compensate})


def _delivered_comb(config: SystemConfig) -> tuple[np.ndarray, np.ndarray]:
    """``(frequency_hz, delivered amplitude)`` of every tone of the chain's hold waveform: the FFT of one slot's
    samples (every tone a whole number of cycles per slot: exact bins) times the hold's response sinc(f / f_s)."""
    bank = WaveformBank(config)
    ops = Operations(nx=64, ny=1, capacity=1)
    ops.append(IDLE, [], [])
    samples = bank.render_slots(ops)[:, 0].astype(np.float64) / 32767.0
    n = samples.size
    spectrum = np.abs(np.fft.rfft(samples)) * 2 / n
    freq = axis_tones(config, "x").frequency_hz
    bins = np.round(freq * n / FS).astype(int)
    return freq, spectrum[bins] * np.sinc(freq / FS)


def test_the_compensated_comb_reaches_the_aod_flat_across_the_band() -> None:
    freq, delivered = _delivered_comb(_wide_chain(True))
    # flat to the int16 rounding (half a count of 32767 against 0.012 of full scale is 1.3e-4)
    np.testing.assert_allclose(delivered, 0.012, rtol=2e-3)
    _, rolled_off = _delivered_comb(_wide_chain(False))
    np.testing.assert_allclose(rolled_off, 0.012 * np.sinc(freq / FS), rtol=2e-3)
    assert rolled_off[-1] / 0.012 == pytest.approx(0.672, abs=0.003)  # the issue's 0.67 at 295 MHz


def test_a_moving_tone_stays_compensated_along_its_frequency_ramp() -> None:
    """A tone moving between the two top sites (290.2 -> 294.8 MHz) ramps its sample amplitude between the
    two sites' compensated amplitudes; after the hold it delivers the configured amplitude all the way."""
    config = _wide_chain(True)
    bank = WaveformBank(config)
    row = bank.synthesize("x", MOVE_UP, 62, exact=True) / 32767.0
    wf = config.waveforms
    theta = phase_track(bank.cycles("x"), axis_tones(config, "x").phase_rad, 62, 1, wf.slot_samples, wf.shape,
                        wf.shape_sharpness)
    f_inst = np.mod(np.diff(theta), 2 * np.pi) / (2 * np.pi) * FS  # between samples n and n + 1
    f_inst = np.concatenate([[f_inst[0]], 0.5 * (f_inst[1:] + f_inst[:-1])])  # at sample n
    assert f_inst[0] == pytest.approx(290.2e6, abs=1e3) and f_inst[-1] == pytest.approx(294.8e6, abs=5e3)
    s = np.sin(theta[:-1])
    ok = np.abs(s) > 0.5
    sample_amp = row[ok] / s[ok]
    delivered = sample_amp * np.sinc(f_inst[ok] / FS)
    np.testing.assert_allclose(delivered, 0.012, rtol=2e-4)  # 7e-5 is the interpolation's worst case here
    assert sample_amp.max() / sample_amp.min() > 1.01  # the sample amplitude really follows the ramp


def test_a_comb_whose_compensated_amplitudes_break_a_limit_is_refused_with_the_reason() -> None:
    loud = {**WIDE, "amplitude": 0.015}  # 64 x 0.015 = 0.96 of full scale, 1.10 once compensated
    with pytest.raises(ConfigError, match=r"= 1.103 of full scale \(compensated for the DAC's sinc roll-off.*"
                                          r"1.49x at 294.8 MHz.*max_summed_amplitude.*use at most 0.0136"):
        chain_config(64, array={"x_tones": loud})
    chain_config(64, array={"x_tones": loud}, waveforms={"compensate_dac_sinc": False})  # 0.96: fits
    # the RF power, too: 64 tones of 0.012 at 140 mV into 50 ohm are -27.43 dBm, -26.16 dBm compensated
    with pytest.raises(ConfigError, match=r"compensated for the DAC.*deliver -26.16 dBm"):
        chain_config(64, array={"x_tones": {**WIDE, "rf": {"max_rf_power_dbm": -27.0}}})
    chain_config(64, array={"x_tones": {**WIDE, "rf": {"max_rf_power_dbm": -27.0}}},
                 waveforms={"compensate_dac_sinc": False})


def _near_nyquist_grid(compensate: bool, algorithm: str) -> SystemConfig:
    """12 x 10 traps with tones from 115 MHz up to 148 MHz at 313.6 MS/s (Nyquist 156.8 MHz): the hold's gain
    falls from 0.79 to 0.67 per axis, so uncompensated tweezers over the upper corner are below half depth."""
    band = {"start_hz": 115e6, "spacing_hz": 3e6}
    return grid_config(12, 10, target={"kind": "centre", "count": 48},
                       awg={"n_segments": 64, "n_steps": 256, "waveforms_per_segment": 8},
                       array={"x_tones": band, "y_tones": band}, solver={"algorithm": algorithm},
                       waveforms={"compensate_dac_sinc": compensate}, sim={"lossless": True, "seed": 3})


def _run(config: SystemConfig, shots: int) -> tuple[int, int, int]:
    """``(atoms lost, solvable shots, solvable shots filled)`` of lossless shots in the simulated lab."""
    devices, lab = build_sim_lab(config)
    engine = Engine(config, devices, lab=lab)
    records = [engine.run_shot() for _ in range(shots)]
    solvable = [r for r in records if r.cycles and r.cycles[0].atoms >= config.target.count]
    filled = sum(bool(r.lab_report.get("target_filled")) for r in solvable)
    assert all(r.fault is None for r in records), [r.fault for r in records]
    return engine.lab.world.counters.lost, len(solvable), filled


@pytest.mark.parametrize("algorithm", ["aod-parallel", "red-rec"])
def test_a_band_near_nyquist_loses_no_atom_when_compensated(algorithm: str) -> None:
    lost, solvable, filled = _run(_near_nyquist_grid(True, algorithm), shots=4)
    assert lost == 0
    assert solvable >= 3 and filled == solvable


def test_without_compensation_the_simulated_lab_sees_the_shallower_traps() -> None:
    """The same shots with the roll-off left in: tweezers over the upper corner stay below the hold threshold
    (``drivers.sim.decode.FULL_FRACTION``), so atoms are not picked there and loaded tweezers meet them."""
    lost, solvable, filled = _run(_near_nyquist_grid(False, "aod-parallel"), shots=4)
    assert filled < solvable
    assert lost > 0
