"""The Spectrum adapter through the real ``spcm`` package over a fake of Spectrum's C library, a register-level
card that records every call and enforces the manual's sequence-mode rules (see ``tests/fake_spcm.py``):
opening, step words, the order of uploads and pointer updates, the card setup, DMA alignment, the X-line
pulses, and what opening says when the package or its driver is missing."""

from __future__ import annotations

import ctypes
import sys
import time
from typing import Any

import numpy as np
import pytest

from drivers.spectrum import SpectrumAWG
from engine.card_rules import DMA_ALIGN_BYTES, decode_step, encode_step, page_aligned_zeros
from engine.config import AWGConfig, DevicesConfig, config_from_dict
from engine.devices import DeviceError, StepInfo
from tests.fake_spcm import DRIVER_MISSING_TEXT, C, decode, install_broken_spcm, is_step_register, make_fake_spcm

N = 384  # samples per channel of one test slot: a multiple of 32 and the 1-channel minimum


def open_awg(n_channels: int = 1, *, settings: dict[str, Any] | None = None, awg: dict[str, Any] | None = None,
             rate: float = 624e6, **card: Any) -> tuple[SpectrumAWG, Any]:
    mod = make_fake_spcm(**card)
    dev = SpectrumAWG(DevicesConfig.SpectrumSettings(**(settings or {})), spcm_module=mod)
    dev.configure(AWGConfig(**(awg or {"n_segments": 16, "n_steps": 64})), n_channels=n_channels, sample_rate_hz=rate)
    return dev, mod.fake.cards["/dev/spcm0"]


def samples(value: int, n: int = N, ch: int = 1) -> np.ndarray:
    """A segment in a page-aligned buffer, as the streamer allocates them (the card DMAs it in place)."""
    out = page_aligned_zeros((n, ch), np.int16)
    out[:] = np.arange(ch, dtype=np.int16) + value
    return out


# --- step words -------------------------------------------------------------------------------------------

def test_step_word_layout_is_the_manuals() -> None:
    # low 32 bits: next << 16 | segment; high 32 bits: flags | loops (SPCSEQ_ENDLOOPONTRIG = 0x40000000)
    assert encode_step(5, 7, 1) == (1 << 32) | (7 << 16) | 5
    assert encode_step(5, 7, 3, on_trigger=True) == ((0x40000000 | 3) << 32) | (7 << 16) | 5
    assert encode_step(0, 0, 1, end=True) >> 32 == 0x80000000 | 1
    assert encode_step(4095, 4095, 0xFFFFF) == (0xFFFFF << 32) | (4095 << 16) | 4095
    for seg, nxt, loops, trig in [(0, 0, 1, False), (255, 4095, 2, True), (17, 3, 1000, False)]:
        word = encode_step(seg, nxt, loops, on_trigger=trig)
        assert decode(word) == (seg, nxt, loops, 0x40000000 if trig else 0)  # the fake's independent decoder
        assert decode_step(word) == {"segment": seg, "next_step": nxt, "loops": loops, "on_trigger": trig, "end": False}


def test_write_step_writes_exact_words_and_never_the_end_flag() -> None:
    awg, card = open_awg()
    awg.write_segment(2, samples(1))
    cases = [
        (0, StepInfo(segment=2, next_step=0)),
        (3, StepInfo(segment=2, next_step=4, loops=1, on_trigger=True)),
        (63, StepInfo(segment=2, next_step=1, loops=7)),
    ]
    for index, info in cases:
        awg.write_step(index, info)
        expected = encode_step(info.segment, info.next_step, info.loops, on_trigger=info.on_trigger)
        assert card.steps[index] == expected
        assert ("set_i", C.SPC_SEQMODE_STEPMEM0 + index, expected) in card_log(awg)
        assert not decode(expected)[3] & C.SPCSEQ_END
    assert card.violations == []


def card_log(awg: SpectrumAWG) -> list[tuple[Any, ...]]:
    return awg._spcm.fake.log  # type: ignore[union-attr]


# --- opening ----------------------------------------------------------------------------------------------

def test_open_without_the_package_says_what_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "spcm", None)  # import spcm -> ModuleNotFoundError
    with pytest.raises(DeviceError) as err:
        SpectrumAWG().open()
    assert "'spcm' Python package is not installed" in str(err.value)
    assert "pip install -e '.[hardware]'" in str(err.value)


def test_open_with_the_package_but_no_driver_says_to_install_the_driver(monkeypatch: pytest.MonkeyPatch) -> None:
    install_broken_spcm(monkeypatch)
    with pytest.raises(Exception) as raw:  # the behaviour we wrap: a bare Exception from import
        import spcm  # noqa: F401
    assert type(raw.value) is Exception
    with pytest.raises(DeviceError) as err:
        SpectrumAWG().open()
    msg = str(err.value)
    assert "installed but the Spectrum driver library could not be loaded" in msg
    assert DRIVER_MISSING_TEXT.splitlines()[0] in msg
    assert "spectrum-instrumentation.com/support/downloads" in msg


def test_open_a_missing_card_names_the_device_setting() -> None:
    mod = make_fake_spcm(device="/dev/spcm1")
    with pytest.raises(DeviceError, match=r"cannot open '/dev/spcm0'.*devices\.spectrum\.device"):
        SpectrumAWG(spcm_module=mod).open()


def test_open_works_through_the_real_spcm_whose_card_type_check_cannot_pass() -> None:
    """``spcm.Card(device, card_type=...)`` compares the type before reading it (spcm 1.13): it never opens.
    The adapter opens without it and checks ``function_type()`` itself."""
    mod = make_fake_spcm()
    with pytest.raises(mod.SpcmException, match="not the correct type"):
        mod.Card("/dev/spcm0", card_type=mod.SPCM_TYPE_AO).open()
    awg = SpectrumAWG(spcm_module=mod)
    awg.open()
    assert awg.info["product"] == "M4i.6622-x8" and awg.info["channels"] == 4 and awg.info["max_sample_value"] == 32767
    awg.close()


def test_a_card_that_is_not_an_awg_is_refused_and_closed() -> None:
    mod = make_fake_spcm(function_type=C.SPCM_TYPE_AI)
    with pytest.raises(DeviceError, match=r"not an analog output card.*devices\.spectrum\.device"):
        SpectrumAWG(spcm_module=mod).open()
    assert not mod.fake.cards["/dev/spcm0"].opened


def test_the_fake_card_refuses_what_the_manual_forbids_through_spcm_itself() -> None:
    """Below the adapter: writes straight through ``spcm`` meet the card's rules (``engine.card_rules``)."""
    mod = make_fake_spcm()
    card = mod.Card("/dev/spcm0").open()
    card.set_i(C.SPC_CHENABLE, C.CHANNEL0)
    card.set_i(C.SPC_SEQMODE_MAXSEGMENTS, 16)
    card.set_i(C.SPC_SEQMODE_WRITESEGMENT, 0)
    with pytest.raises(mod.SpcmException, match="6250 samples per channel is not a multiple of 32"):
        card.set_i(C.SPC_SEQMODE_SEGMENTSIZE, 6250)  # 625 MS/s x 10 us
    with pytest.raises(mod.SpcmException, match="not a power of two"):
        card.set_i(C.SPC_SEQMODE_MAXSEGMENTS, 24)
    state = mod.fake.cards["/dev/spcm0"]
    state.running = True
    with pytest.raises(mod.SpcmException, match="SPC_SAMPLERATE written while the card runs"):
        card.set_i(C.SPC_SAMPLERATE, 625_000_000)
    assert len(state.violations) == 3
    with pytest.raises(ctypes.ArgumentError):  # what ctypes cannot pass to the C function, the fake refuses
        mod.spcm_dwDefTransfer_i64(card.handle(), C.SPCM_BUF_DATA, C.SPCM_DIR_PCTOCARD, 0, 4096.0, 0, 64)
    card.close()


def test_a_card_without_the_sequence_option_is_refused_and_closed() -> None:
    mod = make_fake_spcm(features=0)
    with pytest.raises(DeviceError, match="no sequence-mode option"):
        SpectrumAWG(spcm_module=mod).open()
    assert not mod.fake.cards["/dev/spcm0"].opened


# --- card setup -------------------------------------------------------------------------------------------

def test_configure_programs_sequence_mode_before_any_data() -> None:
    settings = {"amplitude_mv": [140, 200], "trigger_edge": "falling", "trigger_level_mv": 2000,
                "external_reference_hz": 10e6, "camera_line": 0, "resume_line": 2}
    awg, card = open_awg(2, settings=settings, awg={"n_segments": 200, "n_steps": 512})
    writes = awg._spcm.fake.register_writes()  # type: ignore[union-attr]
    names = [n for n, _ in writes]
    values = dict(writes)
    assert writes[0] == ("SPC_M2CMD", C.M2CMD_CARD_STOP) and writes[1] == ("SPC_M2CMD", C.M2CMD_CARD_RESET)
    assert values["SPC_CARDMODE"] == C.SPC_REP_STD_SEQUENCE
    assert values["SPC_SEQMODE_MAXSEGMENTS"] == 256  # the next power of two >= 200
    assert values["SPC_CHENABLE"] == C.CHANNEL0 | C.CHANNEL1
    assert values["SPC_AMP0"] == 140 and values["SPC_AMP1"] == 200
    assert values["SPC_ENABLEOUT0"] == 1 and values["SPC_ENABLEOUT1"] == 1
    assert values["SPC_CH0_STOPLEVEL"] == C.SPCM_STOPLVL_ZERO
    assert values["SPC_CLOCKMODE"] == C.SPC_CM_EXTREFCLOCK and values["SPC_REFERENCECLOCK"] == 10_000_000
    assert values["SPC_SAMPLERATE"] == 624_000_000
    assert values["SPC_TRIG_ORMASK"] == C.SPC_TMASK_EXT0 and values["SPC_TRIG_EXT0_MODE"] == C.SPC_TM_NEG
    assert values["SPC_TRIG_EXT0_LEVEL0"] == 2000
    assert values["SPCM_X0_MODE"] == C.SPCM_XMODE_ASYNCOUT and values["SPCM_X2_MODE"] == C.SPCM_XMODE_ASYNCOUT
    # X-line modes only take effect at WRITESETUP, which must follow them
    last_x = max(i for i, n in enumerate(names) if n.startswith("SPCM_X") and n.endswith("_MODE"))
    setup = [i for i, (n, v) in enumerate(writes) if n == "SPC_M2CMD" and v & C.M2CMD_CARD_WRITESETUP]
    assert setup and setup[0] > last_x
    assert awg.n_channels == 2 and awg.sample_rate_hz == 624e6
    assert awg.min_segment_samples == 192 and awg.max_segment_samples == 2**32 // (2 * 2 * 256)
    # the partition is written before any upload or step (changing it later discards the memory)
    awg.write_segment(0, samples(3, ch=2))
    awg.write_step(0, StepInfo(0, 0))
    names = [n for n, _ in awg._spcm.fake.register_writes()]  # type: ignore[union-attr]
    assert names.index("SPC_SEQMODE_MAXSEGMENTS") < names.index("SPC_SEQMODE_WRITESEGMENT") < names.index("STEPMEM0+0")
    assert card.violations == []


def test_a_sample_rate_the_card_cannot_make_is_refused() -> None:
    with pytest.raises(DeviceError, match="asked for 624000001 S/s"):
        open_awg(rate=624_000_001, rate_quantum_hz=8)


@pytest.mark.parametrize(
    ("awg_cfg", "n_channels", "match"),
    [
        ({"n_segments": 16, "n_steps": 64}, 3, "1, 2 or 4"),
        ({"n_segments": 16, "n_steps": 4096}, 1, "awg.n_steps = 4096 but the card has 1024"),
        ({"n_segments": 2048, "n_steps": 4096}, 1, "awg.n_segments = 2048 needs 2048 segments"),
    ],
)
def test_configure_checks_what_the_card_can_do(awg_cfg: dict[str, int], n_channels: int, match: str) -> None:
    with pytest.raises(DeviceError, match=match):
        open_awg(n_channels, awg=awg_cfg, max_steps=1024, max_segments=1024)


# --- uploads ----------------------------------------------------------------------------------------------

def test_upload_selects_sizes_defines_the_buffer_then_runs_a_blocking_dma() -> None:
    awg, card = open_awg(2)
    data = samples(100, n=640, ch=2)
    start = len(card_log(awg))
    awg.write_segment(5, data)
    calls = card_log(awg)[start:]
    assert [c[0] for c in calls] == ["set_i", "set_i", "DefTransfer", "set_i"]
    assert calls[0][1:] == (C.SPC_SEQMODE_WRITESEGMENT, 5)
    assert calls[1][1:] == (C.SPC_SEQMODE_SEGMENTSIZE, 640)
    _, buf, direction, notify, pointer, offset, length = calls[2]
    assert (buf, direction, notify, offset, length) == (C.SPCM_BUF_DATA, C.SPCM_DIR_PCTOCARD, 0, 0, data.nbytes)
    assert pointer.value == data.ctypes.data  # the caller's buffer, in place: no copy
    assert calls[3][1:] == (C.SPC_M2CMD, C.M2CMD_DATA_STARTDMA | C.M2CMD_DATA_WAITDMA)
    np.testing.assert_array_equal(card.segments[5], data)  # channels multiplexed sample by sample
    assert card.violations == []


def test_an_unaligned_buffer_reaches_the_card_from_page_aligned_memory() -> None:
    """Spectrum's DMA reads page-aligned host memory; numpy gives no alignment, so the adapter copies."""
    awg, card = open_awg(2)
    backing = page_aligned_zeros(640 * 2 * 2 + 2, np.uint8)
    data = backing[2:].view(np.int16).reshape(640, 2)  # 2 B past a page boundary
    data[:] = samples(7, n=640, ch=2)
    awg.write_segment(3, data)
    pointer = next(c for c in reversed(card_log(awg)) if c[0] == "DefTransfer")[4].value
    assert pointer % DMA_ALIGN_BYTES == 0 and pointer != data.ctypes.data
    np.testing.assert_array_equal(card.segments[3], data)
    assert awg.staged_uploads == 1 and card.violations == []
    awg.write_segment(4, samples(8, n=640, ch=2))  # aligned: read in place, no copy
    assert awg.staged_uploads == 1


def test_a_resized_segment_gets_its_steps_rewritten_after_the_dma() -> None:
    awg, card = open_awg()
    awg.write_segment(1, samples(1, n=N * 4))
    awg.write_step(1, StepInfo(segment=1, next_step=2))
    awg.write_step(7, StepInfo(segment=1, next_step=7))
    awg.write_segment(2, samples(2))
    awg.write_step(2, StepInfo(segment=2, next_step=2))
    start = len(card_log(awg))
    awg.write_segment(1, samples(9, n=N * 2))  # shorter: the driver must recompute from the step entries
    after = card_log(awg)[start:]
    dma = next(i for i, c in enumerate(after) if c[0] == "set_i" and c[1] == C.SPC_M2CMD)
    rewritten = {c[1] - C.SPC_SEQMODE_STEPMEM0: c[2] for c in after[dma:] if c[0] == "set_i" and is_step_register(c[1])}
    assert rewritten == {1: card.steps[1], 7: card.steps[7]}
    start = len(card_log(awg))
    awg.write_segment(1, samples(4, n=N * 2))  # same length: nothing to rewrite
    assert not [c for c in card_log(awg)[start:] if c[0] == "set_i" and is_step_register(c[1])]
    awg.start(1)
    card.play(4)
    assert card.violations == []


@pytest.mark.parametrize(
    ("index", "data", "match"),
    [
        (16, samples(0), "out of range"),
        (0, samples(0).astype(np.float32), "int16"),
        (0, samples(0, ch=2), "int16\\[n, 1\\]"),
        (0, samples(0, n=N + 16), "multiple of 32"),
        (0, samples(0, n=352), "multiple of 32 between 384"),
        (0, np.zeros((2 * N, 2), np.int16)[:, :1], "C-contiguous"),
    ],
)
def test_bad_uploads_fail_clearly_and_touch_nothing(index: int, data: np.ndarray, match: str) -> None:
    awg, card = open_awg()
    start = len(card_log(awg))
    with pytest.raises(DeviceError, match=match):
        awg.write_segment(index, data)
    assert card_log(awg)[start:] == []


@pytest.mark.parametrize(
    ("index", "info", "match"),
    [
        (64, StepInfo(0, 0), "step index 64"),
        (0, StepInfo(16, 0), "segment 16 out of range"),
        (0, StepInfo(0, 64), "next_step 64"),
        (0, StepInfo(0, 0, loops=0), "loops must be"),
        (0, StepInfo(3, 0), "holds no samples yet"),
    ],
)
def test_bad_steps_fail_clearly(index: int, info: StepInfo, match: str) -> None:
    awg, _ = open_awg()
    awg.write_segment(0, samples(0))
    with pytest.raises(DeviceError, match=match):
        awg.write_step(index, info)


# --- playback, triggers, pulses ---------------------------------------------------------------------------

def test_start_current_step_and_a_step_that_waits_for_a_trigger() -> None:
    awg, card = open_awg()
    awg.write_segment(0, samples(0))
    awg.write_segment(1, samples(1))
    awg.write_step(0, StepInfo(segment=0, next_step=1, on_trigger=True))
    awg.write_step(1, StepInfo(segment=1, next_step=1))
    assert awg.current_step() == -1
    start = len(card_log(awg))
    awg.start(0)
    cmds = [c[2] for c in card_log(awg)[start:] if c[0] == "set_i" and c[1] == C.SPC_M2CMD]
    assert cmds == [C.M2CMD_CARD_START | C.M2CMD_CARD_ENABLETRIGGER | C.M2CMD_CARD_FORCETRIGGER]
    for _ in range(5):
        assert awg.current_step() == 0  # loops until a trigger
    card.external_trigger()
    assert awg.current_step() == 0  # the pass in progress finishes first
    awg.wait_for_step(1, timeout_s=1.0)
    awg.write_step(0, StepInfo(segment=0, next_step=1, on_trigger=True))
    awg.write_step(1, StepInfo(segment=1, next_step=0))
    awg.wait_for_step(0, timeout_s=1.0)
    awg.force_trigger()  # a software trigger counts too
    awg.wait_for_step(1, timeout_s=1.0)
    with pytest.raises(DeviceError, match="step 5 not reached"):
        awg.wait_for_step(5, timeout_s=0.01)
    awg.stop()
    assert awg.current_step() == -1
    with pytest.raises(DeviceError, match="playback is stopped"):
        awg.wait_for_step(0, timeout_s=0.01)
    assert card.violations == []


def test_pulses_drive_the_configured_x_lines_high_then_low() -> None:
    awg, card = open_awg(settings={"camera_line": 0, "resume_line": 1, "pulse_width_s": 0.0})
    awg.pulse("camera")
    awg.pulse("resume")
    assert card.pulses == [0, 0b001, 0, 0b010, 0]  # configure drives all low first
    with pytest.raises(DeviceError, match="unknown pulse line"):
        awg.pulse("shutter")
    assert card.violations == []


def test_close_stops_the_card_and_releases_it() -> None:
    awg, card = open_awg()
    awg.write_segment(0, samples(0))
    awg.write_step(0, StepInfo(0, 0))
    awg.start(0)
    awg.close()
    assert not card.running and not card.opened and not awg.is_open
    awg.close()  # twice is fine
    awg.stop()


# --- the engine's streaming sequence on the fake card ------------------------------------------------------

class _Ops:
    """Stands in for ``engine.operations.Operations``: one value per slot (the streamer only takes len())."""

    def __init__(self, values: list[int]) -> None:
        self.values = values

    def __len__(self) -> int:
        return len(self.values)


class _Bank:
    """Stands in for ``engine.waveforms.WaveformBank``: slot i renders as the constant ``values[i]`` and its
    failsafe as ``-values[i]``, so what the card played can be read back slot by slot."""

    n_channels = 1
    slot_samples = N

    def max_keys(self, n_slots: int) -> int:
        return max(n_slots, 1)

    def hold(self) -> np.ndarray:
        return np.zeros((N, 1), dtype=np.int16)

    def lookup(self, ops: _Ops, first: int, count: int, keys: np.ndarray) -> None:
        self._looked_up = ops  # render() reads the slots of the last lookup, as the real bank does

    def render(self, first: int, count: int, out: np.ndarray) -> None:
        for i in range(count):
            out[i * N:(i + 1) * N, 0] = self._looked_up.values[first + i]

    def render_failsafe(self, ops: _Ops, i: int, out: np.ndarray) -> None:
        out[:N, 0] = -ops.values[i]


class _Clock:
    def now_s(self) -> float:
        return time.monotonic()


@pytest.mark.parametrize("segment_growth", [1.0, 2.0])
@pytest.mark.parametrize("passes_per_dma", [0, 1, 3])
def test_the_streamers_uploads_and_pointer_updates_obey_the_card(passes_per_dma: int, segment_growth: float) -> None:
    """Plans streamed back to back through the real ``engine.streaming.Streamer``: the card never plays a
    segment being written or a step whose segment is stale, never plays a previous plan's data, and plays
    every slot once, in order, through the failsafe steps when the host is late; with growing control segments
    (4, 4, 8, 16 slots) as with equal ones."""
    try:
        from engine.streaming import Streamer
    except Exception as err:  # noqa: BLE001 - the engine is being finished elsewhere; this test needs only streaming
        pytest.skip(f"engine.streaming does not import yet: {err}")
    config = config_from_dict({"awg": {"n_segments": 16, "n_steps": 64, "waveforms_per_segment": 4,
                                       "segment_growth": segment_growth, "max_waveforms_per_segment": 16}})
    awg, card = open_awg(passes_per_dma=passes_per_dma)
    streamer = Streamer(config, _Bank(), awg, _Clock())  # type: ignore[arg-type]
    lay = streamer.layout
    streamer.program_idle()
    awg.start(lay.idle_step)
    controls = {lay.control_step(k) for k in range(lay.n_control)} | {lay.short_step}
    failsafes = {lay.failsafe_step(k) for k in range(lay.n_control)}
    plans = [list(range(1, 26)), list(range(101, 126)), list(range(201, 207)), list(range(301, 329))]
    seen_failsafe = 0
    for values in plans:
        card.played.clear()
        report = streamer.stream(_Ops(values))  # type: ignore[arg-type]
        played = [p for p in card.played if p.step in controls]
        assert np.concatenate([p.data[:, 0] for p in played]).tolist() == np.repeat(values, N).tolist()
        # at rest: a step that loops the hold segment on itself
        assert decode(card.steps[card.step])[:2] == (lay.idle_segment, card.step)
        assert report.short_path == (len(values) <= 2 * streamer.slots_per_segment)
        for p in card.played:
            if p.step in failsafes:  # an underrun holds the tones where the previous segment left them
                seen_failsafe += 1
                assert p.data[0, 0] < 0
    assert card.violations == []
    # every pointer to a control step is written after that step's own word and its segment's upload
    uploaded: dict[int, int] = {}
    written: dict[int, int] = {}
    wseg = None
    for i, c in enumerate(card_log(awg)):
        if c[0] != "set_i":
            continue
        if c[1] == C.SPC_SEQMODE_WRITESEGMENT:
            wseg = c[2]
        elif c[1] == C.SPC_M2CMD and c[2] & C.M2CMD_DATA_STARTDMA:
            uploaded[wseg] = i  # type: ignore[index]
        elif is_step_register(c[1]):
            step = c[1] - C.SPC_SEQMODE_STEPMEM0
            seg, nxt, _, _ = decode(c[2])
            assert uploaded[seg] < i, f"step {step} written before segment {seg} was uploaded"
            if nxt in controls and nxt != step:
                assert written[nxt] < i and uploaded[decode(card_log(awg)[written[nxt]][2])[0]] < written[nxt]
            written[step] = i
    assert (seen_failsafe > 0) == (passes_per_dma > 0)  # a card faster than the uploads pauses in failsafes
    assert awg.staged_uploads <= 1  # at most the idle hold is copied: the streamer's buffers are page-aligned
