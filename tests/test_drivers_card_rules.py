"""One statement of the card's rules (``engine/card_rules.py``): the simulated AWG and the fake card below the
real ``spcm`` package accept and refuse the same segments and steps, configurations the card cannot play are
refused when applied, and the shipped configurations obey the rules."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from drivers.sim.lab import build_sim_lab
from engine import card_rules
from engine.config import SystemConfig, config_from_dict, load_config
from engine.devices import DeviceError, StepInfo
from tests.fake_spcm import C, make_fake_spcm

EXAMPLES = sorted((Path(__file__).resolve().parent.parent / "examples").glob("*.yaml"))


def fake_card_accepts(n_samples: int, n_channels: int) -> bool:
    """Whether the fake card (through the real ``spcm``) takes ``SEGMENTSIZE = n_samples``."""
    mod = make_fake_spcm()
    card = mod.Card("/dev/spcm0").open()
    try:
        card.set_i(C.SPC_CHENABLE, (1 << n_channels) - 1)
        card.set_i(C.SPC_SEQMODE_MAXSEGMENTS, 16)
        card.set_i(C.SPC_SEQMODE_WRITESEGMENT, 0)
        try:
            card.set_i(C.SPC_SEQMODE_SEGMENTSIZE, n_samples)
        except mod.SpcmException:
            return False
        return True
    finally:
        card.close()


def sim_awg_accepts(n_samples: int, config: SystemConfig) -> bool:
    devices, _ = build_sim_lab(config)
    awg = devices.awg
    try:
        awg.write_segment(0, np.zeros((n_samples, awg.n_channels), np.int16))
    except DeviceError as err:
        assert "the Spectrum card would refuse it" in str(err)
        return False
    return True


@pytest.mark.parametrize("n_samples", [6240, 6250, 6256, 6272, 3136, 3120, 352, 384, 96])
def test_the_simulated_awg_refuses_exactly_what_the_card_refuses(n_samples: int) -> None:
    chain = SystemConfig()  # one channel (a chain of AOD traps)
    assert sim_awg_accepts(n_samples, chain) == fake_card_accepts(n_samples, 1) == (
        n_samples % 32 == 0 and n_samples >= 384)


def test_two_channel_minimum_is_half_the_one_channel_minimum() -> None:
    assert card_rules.min_segment_samples(2) == 192 and card_rules.min_segment_samples(4) == 96
    assert fake_card_accepts(192, 2) and not fake_card_accepts(160, 2)


def test_the_simulated_awg_refuses_a_loop_count_the_step_word_cannot_hold() -> None:
    devices, _ = build_sim_lab(SystemConfig())
    awg = devices.awg
    awg.write_segment(0, np.zeros((6240, 1), np.int16))
    awg.write_step(0, StepInfo(0, 0, loops=card_rules.SPCSEQ_LOOPMASK))
    with pytest.raises(DeviceError, match="loops must be 1..1048575"):
        awg.write_step(0, StepInfo(0, 0, loops=card_rules.SPCSEQ_LOOPMASK + 1))


def test_step_words_round_trip_through_the_manuals_fields() -> None:
    word = card_rules.encode_step(0xABCD, 0x1234, 0xFFFFF, on_trigger=True)
    assert word == ((0x40000000 | 0xFFFFF) << 32) | (0x1234 << 16) | 0xABCD
    assert card_rules.decode_step(word) == {"segment": 0xABCD, "next_step": 0x1234, "loops": 0xFFFFF,
                                            "on_trigger": True, "end": False}


@pytest.mark.parametrize(
    ("rate_hz", "slot_s", "trap_source", "match"),
    [
        (625e6, 10e-6, "aod", r"6250 samples.*use sample_rate_hz 624 MS/s or 627\.2 MS/s.*9\.984 us or 10\.0352 us"),
        (312e6, 10e-6, "aod", r"3120 samples.*310\.4 MS/s or 313\.6 MS/s"),
        (624e6, 0.5e-6, "aod", r"312 samples, below the card's shortest segment of 384 samples with 1 channel"),
    ],
)
def test_a_slot_the_card_cannot_play_is_refused_with_the_fix(rate_hz: float, slot_s: float, trap_source: str,
                                                             match: str) -> None:
    with pytest.raises(ValueError, match=match):
        config_from_dict({"waveforms": {"sample_rate_hz": rate_hz, "slot_duration_s": slot_s},
                          "array": {"trap_source": trap_source, "x_tones": {"start_hz": 80e6, "spacing_hz": 2e6}}})


@pytest.mark.parametrize("path", EXAMPLES, ids=[p.name for p in EXAMPLES])
def test_the_shipped_examples_obey_the_card(path: Path) -> None:
    config = load_config(path)
    assert config.waveforms.slot_samples % card_rules.SEGMENT_STEP_SAMPLES == 0


def test_page_aligned_buffers_start_on_a_page() -> None:
    for n in (1, 6240, 100_003):
        buf = card_rules.page_aligned_zeros((n, 2), np.int16)
        assert buf.ctypes.data % card_rules.DMA_ALIGN_BYTES == 0 and buf.shape == (n, 2) and buf.flags.c_contiguous
        assert not buf.any()
