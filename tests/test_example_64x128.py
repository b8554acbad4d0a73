"""``examples/grid-64x128.yaml``, the 8192-trap array of issue 14: a configuration a real AOD and card allow
(checked here from its own numbers, not assumed), and one shot of it filling its target in a lossless world."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivers.sim.lab import build_sim_lab
from engine.aod_limits import sample_amplitudes
from engine.card_rules import slot_length_problem
from engine.config import load_config
from engine.engine import Engine
from engine.records import Outcome
from engine.targets import build_target
from engine.tones import tones_of

EXAMPLE = Path(__file__).resolve().parents[1] / "examples" / "grid-64x128.yaml"


def test_the_8192_trap_example_is_a_comb_a_card_and_an_aod_allow() -> None:
    config = load_config(EXAMPLE)
    arr, wf = config.array, config.waveforms
    assert (arr.nx, arr.ny) == (64, 128)
    assert int(build_target(config.target, nx=arr.nx, ny=arr.ny).sum()) == 64 * 64
    assert slot_length_problem(wf.sample_rate_hz, wf.slot_duration_s, 2) is None  # a multiple of 32 samples
    for axis, n in (("x", arr.nx), ("y", arr.ny)):
        tones = tones_of(getattr(arr, f"{axis}_tones"), n, axis)
        freqs = tones.frequency_hz
        assert freqs.max() - freqs.min() < 80e6  # within a wide-band AOD's passband
        images = wf.sample_rate_hz - freqs  # the DAC's images stay out of the band the tones use
        assert images.min() > freqs.max()
        amps = sample_amplitudes(freqs, tones.amplitude, wf.sample_rate_hz, wf.compensate_dac_sinc)
        assert wf.compensate_dac_sinc and float(np.sum(amps)) <= 1.0  # the summed, DAC-compensated tones cannot clip
        assert float(np.min(np.diff(freqs))) * wf.slot_duration_s >= 5  # tones a slot apart are resolved


@pytest.mark.bench
def test_a_lossless_8192_trap_shot_fills_its_target_in_two_cycles() -> None:
    loaded = load_config(EXAMPLE)
    config = loaded.model_copy(update={"sim": loaded.sim.model_copy(update={"lossless": True, "seed": 5})})
    devices, lab = build_sim_lab(config)
    try:
        record = Engine(config, devices, lab=lab).run_shot()
    finally:
        devices.close()
    assert record.outcome is Outcome.SUCCESS, record.fault
    assert record.lab_report["target_filled"]
    assert len(record.cycles) <= 2
    truth = np.array([[c == "1" for c in row] for row in record.lab_report["occupancy_rows"]])
    assert np.array_equal(record.cycles[-1].occupancy, truth)  # detection agrees with the world, every trap
