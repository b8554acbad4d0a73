"""One reading of the tone comb and one Nyquist rule for everyone who needs them: the configuration, the
waveform bank (``engine.waveforms.axis_tones``) and the simulated lab's decoder (``drivers.sim.decode``)
see the same tones from the same CSV, and refuse the same comb above Nyquist."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivers.sim.decode import DecodeConfigError, SampleDecoder, site_tones
from engine.config import ConfigError
from engine.tones import check_below_nyquist, schroeder_phases, tones_of
from engine.waveforms import axis_tones
from sim_signals import chain_config


def _csv(path: Path, header: str, rows: list[tuple[float, float, float]]) -> str:
    path.write_text(header + "\n" + "\n".join(",".join(f"{v!r}" for v in r) for r in rows) + "\n")
    return str(path)


ROWS = [(0.05 + 0.01 * (k % 3), 70e6 + 1e6 * k + (0.5e6 if k > 3 else 0), 0.1 * k) for k in range(8)]


@pytest.mark.parametrize("header", ["alpha,nu,phi", " alpha , nu , phi ", "alpha,\tnu,phi"])
def test_bank_and_decoder_read_the_same_tones_whatever_the_header_spacing(tmp_path: Path, header: str) -> None:
    config = chain_config(8, array={"x_tones": {"csv": _csv(tmp_path / "x.csv", header, ROWS)}})
    bank = axis_tones(config, "x")
    freq, amp = site_tones(config, "x")
    expected = np.asarray(ROWS)
    assert np.array_equal(bank.frequency_hz, expected[:, 1]) and np.array_equal(freq, expected[:, 1])
    assert np.array_equal(bank.amplitude, expected[:, 0]) and np.array_equal(amp, expected[:, 0])
    assert np.array_equal(bank.phase_rad, expected[:, 2])


def test_the_comb_is_read_the_same_way_too() -> None:
    config = chain_config(8, array={"x_tones": {"phases": "schroeder"}})
    tc = config.array.x_tones
    tones = tones_of(tc, 8, "x")
    assert np.allclose(tones.frequency_hz, tc.start_hz + tc.spacing_hz * np.arange(8))
    assert np.all(tones.amplitude == tc.amplitude) and np.array_equal(tones.phase_rad, schroeder_phases(8))
    freq, amp = site_tones(config, "x")
    assert np.array_equal(freq, tones.frequency_hz) and np.array_equal(amp, tones.amplitude)


def test_a_csv_the_decoder_cannot_use_fails_with_the_files_words(tmp_path: Path) -> None:
    short = chain_config(8, array={"x_tones": {"csv": _csv(tmp_path / "x.csv", "alpha,nu,phi", ROWS[:5])}})
    for read in (lambda: axis_tones(short, "x"), lambda: site_tones(short, "x")):
        with pytest.raises(ConfigError, match="has 5 tone rows but the x axis has 8 sites"):
            read()


def test_one_nyquist_rule_with_each_users_error() -> None:
    check_below_nyquist(1e6, 311e6, 624e6, where="x")  # below 312 MHz: fine
    with pytest.raises(ConfigError, match=r"x: tones span 1e\+06..3.12e\+08 Hz, outside \(0, Nyquist = 3.12e\+08 Hz\)"):
        check_below_nyquist(1e6, 312e6, 624e6, where="x")
    with pytest.raises(ConfigError, match="outside"):
        check_below_nyquist(0.0, 10e6, 624e6, where="x")
    with pytest.raises(DecodeConfigError, match="; lower it"):
        check_below_nyquist(1e6, 400e6, 624e6, where="x", fix="lower it", error=DecodeConfigError)


def test_config_bank_and_decoder_all_refuse_tones_above_nyquist(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="Nyquist"):  # a comb: refused when the configuration is made
        chain_config(8, array={"x_tones": {"start_hz": 308e6}})
    high = [(0.05, 308e6 + 1e6 * k, 0.0) for k in range(8)]
    config = chain_config(8, array={"x_tones": {"csv": _csv(tmp_path / "x.csv", "alpha,nu,phi", high)}})
    with pytest.raises(ConfigError, match="Nyquist"):  # a CSV: refused when its tones are read
        axis_tones(config, "x")
    with pytest.raises(DecodeConfigError, match="Nyquist"):
        SampleDecoder(config)
