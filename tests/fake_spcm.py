"""A fake ``spcm`` package for testing ``drivers/spectrum.py`` without a card.

It records every call (``fake.log``) and models the parts of an M4i.66xx in sequence mode that the adapter
relies on, enforcing the rules of the Spectrum manual's "Sequence Mode" chapter; every breach is appended to
``card.violations`` (tests assert it stays empty):

- ``SPC_SEQMODE_MAXSEGMENTS`` is a power of two >= 2 and discards the memory when changed;
- an upload is WRITESEGMENT, SEGMENTSIZE, ``spcm_dwDefTransfer_i64`` (buffer type data, PC to card), then
  ``M2CMD_DATA_STARTDMA | M2CMD_DATA_WAITDMA``; the DMA length must be SEGMENTSIZE * channels * 2 bytes; the
  size a multiple of 32 between 384 / channels and the partition size; the data are read from the pointer;
- data memory is not read-before-write: a DMA into the segment that is playing is a breach ("torn");
- step words are decoded independently of the adapter (low 32 bits next << 16 | segment, high 32 bits
  flags | loops); a step played after its segment changed length without the step being rewritten is a
  breach ("stale step");
- playback: an entered step plays the segment and loops it had when entered; at its end the *current*
  memory decides where to go (read-before-write step memory); ``SPCSEQ_ENDLOOPONTRIG`` repeats until a
  trigger (FORCETRIGGER or ``card.external_trigger()``) was seen during the step; a step whose segment holds
  no data is a breach;
- X lines pulse through ``SPCM_XX_ASYNCIO`` only in ``SPCM_XMODE_ASYNCOUT`` after WRITESETUP or start.

With ``auto_advance`` (default) every read of ``SPC_SEQMODE_STATUS`` returns the step playing and then lets
one pass of it finish, so a host that polls the status sees playback move at a pace set by its own polling;
``passes_per_dma`` lets the card play on while each upload runs (a late host: playback falls into failsafes).

Register values are the real ones (``spcm_core/regs.py`` 1.0.11).
"""

from __future__ import annotations

import ctypes
import sys
import types
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

CONSTANTS: dict[str, int] = {
    "SPC_SEQMODE_STEPMEM0": 340000,
    "SPC_SEQMODE_AVAILMAXSEGMENT": 349900,
    "SPC_SEQMODE_AVAILMAXSTEPS": 349901,
    "SPC_SEQMODE_MAXSEGMENTS": 349910,
    "SPC_SEQMODE_WRITESEGMENT": 349920,
    "SPC_SEQMODE_STARTSTEP": 349930,
    "SPC_SEQMODE_SEGMENTSIZE": 349940,
    "SPC_SEQMODE_STATUS": 349950,
    "SPCSEQ_SEGMENTMASK": 0x0000FFFF,
    "SPCSEQ_NEXTSTEPMASK": 0xFFFF0000,
    "SPCSEQ_LOOPMASK": 0x000FFFFF,
    "SPCSEQ_ENDLOOPALWAYS": 0x00000000,
    "SPCSEQ_ENDLOOPONTRIG": 0x40000000,
    "SPCSEQ_END": 0x80000000,
    "SPC_CARDMODE": 9500,
    "SPC_REP_STD_SEQUENCE": 0x00040000,
    "SPC_M2CMD": 100,
    "M2CMD_CARD_RESET": 0x00000001,
    "M2CMD_CARD_WRITESETUP": 0x00000002,
    "M2CMD_CARD_START": 0x00000004,
    "M2CMD_CARD_ENABLETRIGGER": 0x00000008,
    "M2CMD_CARD_FORCETRIGGER": 0x00000010,
    "M2CMD_CARD_STOP": 0x00000040,
    "M2CMD_DATA_STARTDMA": 0x00010000,
    "M2CMD_DATA_WAITDMA": 0x00020000,
    "M2CMD_DATA_STOPDMA": 0x00040000,
    "SPCM_BUF_DATA": 1000,
    "SPCM_DIR_PCTOCARD": 0,
    "SPC_TRIG_ORMASK": 40410,
    "SPC_TRIG_ANDMASK": 40430,
    "SPC_TMASK_NONE": 0x00000000,
    "SPC_TMASK_SOFTWARE": 0x00000001,
    "SPC_TMASK_EXT0": 0x00000002,
    "SPC_TRIG_EXT0_MODE": 40510,
    "SPC_TM_POS": 0x00000001,
    "SPC_TM_NEG": 0x00000002,
    "SPC_TRIG_EXT0_LEVEL0": 42320,
    "SPC_TRIG_TERM": 40110,
    "SPC_SAMPLERATE": 20000,
    "SPC_CHENABLE": 11000,
    "CHANNEL0": 0x1,
    "CHANNEL1": 0x2,
    "CHANNEL2": 0x4,
    "CHANNEL3": 0x8,
    "SPC_ENABLEOUT0": 30091,
    "SPC_ENABLEOUT1": 30191,
    "SPC_ENABLEOUT2": 30291,
    "SPC_ENABLEOUT3": 30391,
    "SPC_AMP0": 30010,
    "SPC_AMP1": 30110,
    "SPC_AMP2": 30210,
    "SPC_AMP3": 30310,
    "SPC_CH0_STOPLEVEL": 206020,
    "SPC_CH1_STOPLEVEL": 206021,
    "SPC_CH2_STOPLEVEL": 206022,
    "SPC_CH3_STOPLEVEL": 206023,
    "SPCM_STOPLVL_HOLDLAST": 0x08,
    "SPCM_STOPLVL_ZERO": 0x10,
    "SPC_CLOCKMODE": 20200,
    "SPC_CM_INTPLL": 0x01,
    "SPC_CM_EXTREFCLOCK": 0x20,
    "SPC_REFERENCECLOCK": 20140,
    "SPC_TIMEOUT": 295130,
    "SPC_PCIFEATURES": 2120,
    "SPCM_FEAT_SEQUENCE": 0x00001000,
    "SPC_PCIMEMSIZE": 2110,
    "SPCM_X0_MODE": 600200,
    "SPCM_X1_MODE": 600201,
    "SPCM_X2_MODE": 600202,
    "SPCM_XMODE_ASYNCOUT": 0x00000002,
    "SPCM_XX_ASYNCIO": 47220,
    "SPCM_TYPE_AO": 0x02,
    "ERR_OK": 0x0000,
}
C = types.SimpleNamespace(**CONSTANTS)
_X_MODE = {C.SPCM_X0_MODE: 0, C.SPCM_X1_MODE: 1, C.SPCM_X2_MODE: 2}


def is_step_register(reg: int) -> bool:
    """``SPC_SEQMODE_STEPMEM0 + i`` (the step registers end where the other sequence registers begin)."""
    return C.SPC_SEQMODE_STEPMEM0 <= reg < C.SPC_SEQMODE_AVAILMAXSEGMENT


def register_name(reg: int) -> str:
    """A readable name for a register number (step registers as ``STEPMEM0+i``)."""
    if is_step_register(reg):
        return f"STEPMEM0+{reg - C.SPC_SEQMODE_STEPMEM0}"
    for name, value in CONSTANTS.items():
        if value == reg and name.startswith(("SPC_", "SPCM_X")) and not name.startswith(("SPC_TM", "SPC_CM", "SPC_REP")):
            return name
    return str(reg)


def decode(word: int) -> tuple[int, int, int, int]:
    """``(segment, next_step, loops, flags)`` from a step word, straight from the manual's table."""
    word &= (1 << 64) - 1
    low, high = word & 0xFFFFFFFF, word >> 32
    return low & 0xFFFF, (low >> 16) & 0xFFFF, high & 0x000FFFFF, high & 0xFFF00000


class SpcmException(Exception):
    """Stands in for ``spcm.SpcmException``."""


@dataclass
class Played:
    """One pass of one step as the fake card played it (``data`` is the segment as it was at entry)."""

    step: int
    segment: int
    data: np.ndarray


@dataclass
class CardState:
    """One fake card: registers, data and sequence memory, playback, and the rule breaches seen."""

    device: str
    n_channels: int = 4
    memory_bytes: int = 2**32
    max_segments: int = 4096
    max_steps: int = 4096
    features: int = C.SPCM_FEAT_SEQUENCE
    demo: bool = False
    rate_quantum_hz: int = 1  # the card's sample-rate resolution; the fake rounds to it
    auto_advance: bool = True
    passes_per_dma: int = 0  # passes the card plays while an upload runs (a slow host / a fast card)
    registers: dict[int, int] = field(default_factory=dict)
    segments: dict[int, np.ndarray] = field(default_factory=dict)
    steps: dict[int, int] = field(default_factory=dict)
    step_written_with_size: dict[int, int] = field(default_factory=dict)
    violations: list[str] = field(default_factory=list)
    played: list[Played] = field(default_factory=list)
    pulses: list[int] = field(default_factory=list)  # the ASYNCIO values written, in order
    dma: tuple[int, int] | None = None  # (pointer, bytes) from spcm_dwDefTransfer_i64
    running: bool = False
    opened: bool = False
    step: int = -1
    _entry_seg: int = -1
    _entry_loops: int = 0
    _passes: int = 0
    _trigger_seen: bool = False
    _xmodes_pending: dict[int, int] = field(default_factory=dict)
    _xmodes: dict[int, int] = field(default_factory=dict)

    # --- what the adapter calls ------------------------------------------------------------------------

    def set(self, reg: int, value: int) -> None:
        if reg == C.SPC_M2CMD:
            self._command(value)
            return
        if C.SPC_SEQMODE_STEPMEM0 <= reg < C.SPC_SEQMODE_STEPMEM0 + self.max_steps:
            self._write_step(reg - C.SPC_SEQMODE_STEPMEM0, value)
            return
        if reg == C.SPC_SEQMODE_MAXSEGMENTS:
            if value < 2 or value & (value - 1):
                self.violations.append(f"MAXSEGMENTS {value} is not a power of two >= 2")
            if value > self.max_segments:
                self.violations.append(f"MAXSEGMENTS {value} above the card's {self.max_segments}")
            if self.segments or self.steps:
                self.violations.append("MAXSEGMENTS written after data: the memory is discarded")
                self.segments.clear()
        if reg == C.SPC_SEQMODE_WRITESEGMENT and value >= self.registers.get(C.SPC_SEQMODE_MAXSEGMENTS, 0):
            self.violations.append(f"WRITESEGMENT {value} outside MAXSEGMENTS")
        if reg == C.SPC_SEQMODE_SEGMENTSIZE and C.SPC_SEQMODE_WRITESEGMENT not in self.registers:
            self.violations.append("SEGMENTSIZE before WRITESEGMENT")
        if reg == C.SPC_SAMPLERATE:
            value = int(round(value / self.rate_quantum_hz)) * self.rate_quantum_hz
        if reg in _X_MODE:
            self._xmodes_pending[_X_MODE[reg]] = value
        if reg == C.SPCM_XX_ASYNCIO:
            for bit in range(3):
                if value >> bit & 1 and self._xmodes.get(bit) != C.SPCM_XMODE_ASYNCOUT:
                    self.violations.append(f"X{bit} driven high but it is not an active async output")
            self.pulses.append(value)
        self.registers[reg] = value

    def get(self, reg: int) -> int:
        if reg == C.SPC_SEQMODE_STATUS:
            now = self.step if self.running else 0
            if self.running and self.auto_advance:
                self.finish_pass()
            return now
        if reg == C.SPC_PCIFEATURES:
            return self.features
        if reg == C.SPC_PCIMEMSIZE:
            return self.memory_bytes
        if reg == C.SPC_SEQMODE_AVAILMAXSEGMENT:
            return self.max_segments
        if reg == C.SPC_SEQMODE_AVAILMAXSTEPS:
            return self.max_steps
        return self.registers.get(reg, 0)

    def def_transfer(self, buf_type: int, direction: int, notify: int, pointer: Any, offset: int, length: int) -> int:
        if buf_type != C.SPCM_BUF_DATA or direction != C.SPCM_DIR_PCTOCARD or offset != 0:
            self.violations.append(f"DefTransfer({buf_type}, {direction}, offset {offset}): not a PC-to-card data buffer")
            return 0x0102  # ERR_INVALIDPARAM-like
        ptr = pointer.value if isinstance(pointer, ctypes.c_void_p) else int(pointer)
        self.dma = (ptr, int(length))
        return 0

    # --- the model -------------------------------------------------------------------------------------

    @property
    def channels_enabled(self) -> int:
        return bin(self.registers.get(C.SPC_CHENABLE, 0)).count("1")

    def _command(self, cmd: int) -> None:
        if cmd & C.M2CMD_CARD_RESET:
            self.registers.clear()
            self.segments.clear()
            self.steps.clear()
            self.step_written_with_size.clear()
            self._xmodes.clear()
            self._xmodes_pending.clear()
            self.running = False
        if cmd & C.M2CMD_CARD_STOP:
            self.running = False
        if cmd & (C.M2CMD_CARD_WRITESETUP | C.M2CMD_CARD_START):
            self._xmodes.update(self._xmodes_pending)
        if cmd & C.M2CMD_DATA_STARTDMA:
            self._dma()
        if cmd & C.M2CMD_CARD_START:
            if self.registers.get(C.SPC_CARDMODE) != C.SPC_REP_STD_SEQUENCE:
                self.violations.append("card started outside sequence mode")
            start = self.registers.get(C.SPC_SEQMODE_STARTSTEP, 0)
            self.running = True
            if cmd & C.M2CMD_CARD_FORCETRIGGER or not cmd & C.M2CMD_CARD_ENABLETRIGGER:
                self._enter(start)
            return
        if cmd & C.M2CMD_CARD_FORCETRIGGER and self.running:
            self._trigger_seen = True

    def _dma(self) -> None:
        if self.dma is None:
            self.violations.append("STARTDMA without a DefTransfer buffer")
            return
        ptr, length = self.dma
        self.dma = None
        seg = self.registers.get(C.SPC_SEQMODE_WRITESEGMENT)
        size = self.registers.get(C.SPC_SEQMODE_SEGMENTSIZE)
        nch = self.channels_enabled
        if seg is None or size is None or nch == 0:
            self.violations.append("DMA without WRITESEGMENT/SEGMENTSIZE/CHENABLE")
            return
        self.play(self.passes_per_dma)
        if length != size * nch * 2:
            self.violations.append(f"DMA of {length} B into segment {seg} of {size} samples x {nch} channels")
        maxseg = self.registers.get(C.SPC_SEQMODE_MAXSEGMENTS, 0)
        limit = self.memory_bytes // (2 * nch * maxseg) if maxseg else 0
        if size % 32 or size < 384 // nch or size > limit:
            self.violations.append(f"segment {seg}: size {size} not a multiple of 32 in [{384 // nch}, {limit}]")
        if self.running and self.step >= 0 and self._entry_seg == seg:
            self.violations.append(f"torn: DMA into segment {seg} while step {self.step} plays it")
        raw = ctypes.string_at(ptr, length)
        self.segments[seg] = np.frombuffer(raw, dtype=np.int16).reshape(-1, nch).copy()

    def _write_step(self, index: int, word: int) -> None:
        seg, nxt, loops, flags = decode(word)
        if flags & ~(C.SPCSEQ_ENDLOOPONTRIG | C.SPCSEQ_END):
            self.violations.append(f"step {index}: unknown flags {flags:#x}")
        if loops < 1:
            self.violations.append(f"step {index}: loops {loops} < 1")
        if nxt >= self.max_steps:
            self.violations.append(f"step {index}: next {nxt} beyond the step memory")
        self.steps[index] = word
        self.step_written_with_size[index] = len(self.segments[seg]) if seg in self.segments else 0

    def _enter(self, step: int) -> None:
        word = self.steps.get(step)
        if word is None:
            self.violations.append(f"playback entered step {step}, which was never written")
            self.running = False
            return
        seg, _, loops, _ = decode(word)
        data = self.segments.get(seg)
        if data is None:
            self.violations.append(f"playback entered step {step}: segment {seg} holds no data")
            self.running = False
            return
        if self.step_written_with_size.get(step) != len(data):
            self.violations.append(
                f"stale step {step}: segment {seg} is {len(data)} samples but the step was written when it was "
                f"{self.step_written_with_size.get(step)} (the manual asks to rewrite the step)"
            )
        self.step = step
        self._entry_seg = seg
        self._entry_loops = loops
        self._passes = 0
        self._trigger_seen = False

    def finish_pass(self) -> None:
        """One pass of the playing step ends; decide (from the memory as it is now) where to go."""
        if not self.running:
            return
        self.played.append(Played(self.step, self._entry_seg, self.segments[self._entry_seg]))
        self._passes += 1
        if self._passes < self._entry_loops:
            return
        _, nxt, _, flags = decode(self.steps[self.step])
        if flags & C.SPCSEQ_ENDLOOPONTRIG and not self._trigger_seen:
            return
        if flags & C.SPCSEQ_END:
            self.running = False
            return
        self._enter(nxt)

    def external_trigger(self) -> None:
        """A trigger edge on EXT0 (only counts when the OR mask includes EXT0)."""
        if self.running and self.registers.get(C.SPC_TRIG_ORMASK, 0) & C.SPC_TMASK_EXT0:
            self._trigger_seen = True

    def play(self, passes: int) -> None:
        for _ in range(passes):
            self.finish_pass()

    def step_table(self) -> dict[int, tuple[int, int, int, int]]:
        return {i: decode(w) for i, w in self.steps.items()}


class FakeSpcm:
    """The state shared by one fake ``spcm`` module: its cards and the log of every call."""

    def __init__(self) -> None:
        self.cards: dict[str, CardState] = {}
        self.log: list[tuple[Any, ...]] = []

    def add_card(self, device: str = "/dev/spcm0", **kwargs: Any) -> CardState:
        card = CardState(device=device, **kwargs)
        self.cards[device] = card
        return card

    def calls(self, kind: str | None = None) -> Iterator[tuple[Any, ...]]:
        return (c for c in self.log if kind is None or c[0] == kind)

    def register_writes(self) -> list[tuple[str, int]]:
        """``(register name, value)`` of every set_i, in order (commands appear as ``SPC_M2CMD``)."""
        return [(register_name(c[1]), c[2]) for c in self.log if c[0] == "set_i"]


def make_fake_spcm(*, with_card: bool = True, **card_kwargs: Any) -> types.ModuleType:
    """A module that can stand in for ``spcm`` (``sys.modules['spcm'] = make_fake_spcm()``); its ``fake``
    attribute holds the cards and the call log."""
    fake = FakeSpcm()
    if with_card:
        fake.add_card(**card_kwargs)
    mod = types.ModuleType("spcm")
    mod.__dict__.update(CONSTANTS)
    mod.fake = fake  # type: ignore[attr-defined]
    mod.SpcmException = SpcmException  # type: ignore[attr-defined]

    class Card:
        """The subset of ``spcm.Card`` the adapter uses."""

        def __init__(self, device_identifier: str = "", card_type: int = 0, **kwargs: Any) -> None:
            fake.log.append(("Card", device_identifier, card_type))
            self.device_identifier = device_identifier
            self.card_type = card_type
            self._state: CardState | None = None

        def open(self) -> Card:
            fake.log.append(("open", self.device_identifier))
            state = fake.cards.get(self.device_identifier)
            if state is None:
                raise SpcmException(f"{self.device_identifier} not found...")
            if self.card_type not in (0, C.SPCM_TYPE_AO):
                raise SpcmException("The card with the given device identifier is not the correct type")
            state.opened = True
            self._state = state
            return self

        def _s(self) -> CardState:
            if self._state is None:
                raise SpcmException("card is closed")
            return self._state

        def close(self) -> None:
            fake.log.append(("close", self.device_identifier))
            if self._state is not None:
                self._state.running = False
                self._state.opened = False
            self._state = None

        def handle(self) -> CardState:
            return self._s()

        def set_i(self, register: int, value: int) -> None:
            fake.log.append(("set_i", register, value))
            self._s().set(register, value)

        def get_i(self, register: int) -> int:
            fake.log.append(("get_i", register))
            return self._s().get(register)

        def cmd(self, *args: int) -> None:
            value = 0
            for a in args:
                value |= a
            self.set_i(C.SPC_M2CMD, value)

        def max_sample_value(self) -> int:
            return 32768

        def is_demo_card(self) -> bool:
            return self._s().demo

        def product_name(self) -> str:
            return "M4i.6622-x8 (fake)"

        def sn(self) -> int:
            return 12345

        def num_channels(self) -> int:
            return self._s().n_channels

    def spcm_dwDefTransfer_i64(handle: CardState, buf_type: int, direction: int, notify: int, pointer: Any,
                               offset: int, length: int) -> int:
        fake.log.append(("DefTransfer", buf_type, direction, notify, pointer, offset, length))
        return handle.def_transfer(buf_type, direction, notify, pointer, offset, length)

    mod.Card = Card  # type: ignore[attr-defined]
    mod.spcm_dwDefTransfer_i64 = spcm_dwDefTransfer_i64  # type: ignore[attr-defined]
    return mod


DRIVER_MISSING_TEXT = (
    "The Spectrum Instrumentation device driver is not found. Please install the driver and try again.\n"
    "For the newest drivers, see https://spectrum-instrumentation.com/support/downloads.php"
)


class BrokenSpcmFinder:
    """A meta-path finder that makes ``import spcm`` fail the way the real package does when it is installed
    but the driver library is missing: a bare ``Exception`` raised while the module executes."""

    def find_spec(self, name: str, path: Any = None, target: Any = None) -> Any:
        if name != "spcm":
            return None
        import importlib.machinery

        return importlib.machinery.ModuleSpec(name, self)

    def create_module(self, spec: Any) -> None:
        return None

    def exec_module(self, module: types.ModuleType) -> None:
        raise Exception(DRIVER_MISSING_TEXT)  # noqa: TRY002 - exactly what spcm_core.pyspcm does


def install_broken_spcm(monkeypatch: Any) -> None:
    """Make ``import spcm`` behave as on a machine with the package but without the driver."""
    monkeypatch.delitem(sys.modules, "spcm", raising=False)
    monkeypatch.setattr(sys, "meta_path", [BrokenSpcmFinder(), *sys.meta_path])
