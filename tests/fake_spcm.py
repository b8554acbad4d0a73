"""A fake of Spectrum's C driver library (``libspcm_linux.so``) under the real ``spcm`` package.

The tests run the real ``spcm`` / ``spcm_core`` Python code (installed with the ``dev`` extra); only the C
functions ``spcm_core`` loads from the driver library (``spcm_hOpen``, ``spcm_dwSetParam_i64``,
``spcm_dwGetParam_i64``, ``spcm_dwDefTransfer_i64``, ...) are replaced, by a register-level model of an
M4i.66xx in sequence mode. ``load_spcm()`` imports ``spcm`` once per process with ``ctypes.cdll.LoadLibrary``
answering the driver's name with ``LIBRARY``; what the package does above the C calls (``Card.open``'s
checks, its error handling, the argument conversions of ``spcm_core``'s wrappers) is the vendor's own code.

The model enforces the rules of the manual's "Sequence Mode" chapter, the numbers taken from
``engine/card_rules.py`` (the same statement the simulated AWG uses). A write the card refuses returns an
error code (``spcm`` then raises ``SpcmException`` with the fake's text from ``spcm_dwGetErrorInfo_i32``);
every breach, refused or not, is appended to ``card.violations`` (tests assert it stays empty):

- ``SPC_SEQMODE_MAXSEGMENTS`` is a power of two >= 2 within the card's limit, and discards the memory;
- an upload is WRITESEGMENT, SEGMENTSIZE (a valid segment length for the enabled channels and the
  partition), ``spcm_dwDefTransfer_i64`` (data buffer, PC to card, page-aligned memory, the length
  SEGMENTSIZE * channels * 2 bytes), then ``M2CMD_DATA_STARTDMA``; the data are read from the pointer;
- setup registers (mode, channels, clock, trigger, partition) cannot change while the card runs; step
  memory, the segment registers, DMA and the X lines can;
- data memory is not read-before-write: a DMA into the segment that is playing is a breach ("torn");
- step words are decoded with the manual's masks; loops within ``SPCSEQ_LOOPMASK``; a step played after its
  segment changed length without the step being rewritten is a breach ("stale step");
- playback: an entered step plays the segment and loops it had when entered; at its end the *current*
  memory decides where to go (read-before-write step memory); ``SPCSEQ_ENDLOOPONTRIG`` repeats until a
  trigger (FORCETRIGGER or ``card.external_trigger()``) was seen during the step;
- X lines pulse through ``SPCM_XX_ASYNCIO`` only in ``SPCM_XMODE_ASYNCOUT`` after WRITESETUP or start.

With ``auto_advance`` (default) every read of ``SPC_SEQMODE_STATUS`` returns the step playing and then lets
one pass of it finish, so a host that polls the status sees playback move at a pace set by its own polling;
``passes_per_dma`` lets the card play on while each upload runs (a late host: playback falls into failsafes).
"""

from __future__ import annotations

import ctypes
import importlib
import sys
import types
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from engine import card_rules

DRIVER_NAMES = ("libspcm_linux.so", "spcm_win64.dll")
# Exported by the driver library, bound by spcm_core at import, never needed by the adapter.
EXPORTED_UNMODELLED = frozenset({
    "spcm_dwGetErrorInfo_i64", "spcm_dwGetErrorInfo_d64", "spcm_dwGetParam_i32", "spcm_dwGetParam_d64",
    "spcm_dwSetParam_i32", "spcm_dwSetParam_d64", "spcm_dwSetParam_i64m", "spcm_dwInvalidateBuf",
    "spcm_dwGetContBuf_i64", "spcm_dwDiscovery", "spcm_dwSendIDNRequest",
})
DRIVER_VERSION = (7 << 24) | (6 << 16) | 22000  # v7.6 build 22000: new enough for spcm_core's log message


class FakeSpcmLibrary:
    """Stands in for the driver library: ``spcm_core`` looks up each C function by name with ``getattr``.

    Cards come from the newest ``FakeSpcm`` (``make_fake_spcm``); a handle stays bound to the card it opened.
    """

    def __init__(self) -> None:
        self.lab: FakeSpcm | None = None
        self._handles: dict[int, CardState] = {}
        self._next_handle = 1

    def __getattr__(self, name: str) -> _CFunction:
        impl = getattr(type(self), "_" + name, None)
        if impl is not None:
            return _CFunction(name, impl.__get__(self))
        if name in EXPORTED_UNMODELLED:
            return _CFunction(name, _unmodelled(name))
        raise AttributeError(name)  # spcm_core treats a missing symbol as an older driver

    def _card(self, handle: Any) -> CardState:
        return self._handles[int(handle.contents.value)]

    def _log(self, *entry: Any) -> None:
        if self.lab is not None:
            self.lab.log.append(entry)

    # --- the C functions ------------------------------------------------------------------------------

    def _spcm_hOpen(self, name: Any) -> Any:
        device = bytes(name.value).decode()
        self._log("open", device)
        card = self.lab.cards.get(device) if self.lab is not None else None
        if card is None:
            return ctypes.POINTER(ctypes.c_uint64)()  # NULL: no such device
        number = self._next_handle
        self._next_handle += 1
        self._handles[number] = card
        card.opened = True
        return ctypes.pointer(ctypes.c_uint64(number))

    def _spcm_vClose(self, handle: Any) -> None:
        if not handle:
            return
        card = self._handles.pop(int(handle.contents.value))
        self._log("close", card.device)
        card.running = False
        card.opened = False

    def _spcm_dwGetErrorInfo_i32(self, handle: Any, reg: Any, value: Any, text: Any) -> int:
        card = self._card(handle)
        register, val, message = card.last_error
        reg._obj.value, value._obj.value = register, val
        encoded = message.encode()[: int(C.ERRORTEXTLEN) - 1]
        ctypes.memmove(text._obj, encoded + b"\0", len(encoded) + 1)
        return card.last_error_code

    def _spcm_dwGetParam_i64(self, handle: Any, reg: int, out: Any) -> int:
        if not handle:  # spcm_core asks the driver's version while it is imported (before C exists)
            regs = sys.modules["spcm_core.regs"]
            out._obj.value = DRIVER_VERSION if reg == regs.SPC_GETDRVVERSION else 0
            return 0  # ERR_OK
        self._log("get_i", int(reg))
        code, value = self._card(handle).get(int(reg))
        out._obj.value = value
        return code

    def _spcm_dwSetParam_i64(self, handle: Any, reg: int, value: Any) -> int:
        if not handle:  # spcm's Card.__del__ stops a card whose open found nothing; nothing to do
            return 0  # ERR_OK
        word = int(value.value) & ((1 << 64) - 1)
        self._log("set_i", int(reg), word)
        return self._card(handle).set(int(reg), word)

    def _spcm_dwGetParam_ptr(self, handle: Any, reg: int, out: Any, length: int) -> int:
        card = self._card(handle)
        if reg != C.SPC_PCITYP:
            return card.refuse(C.ERR_REG, int(reg), 0, f"register {reg} holds no string on this card")
        text = card.product.encode()[: int(length) - 1] + b"\0"
        ctypes.memmove(out._obj, text, len(text))
        return C.ERR_OK

    def _spcm_dwSetParam_ptr(self, handle: Any, reg: int, pointer: Any, length: int) -> int:
        if not handle:  # spcm_core writes its version to the driver's log while it is imported
            regs = sys.modules["spcm_core.regs"]
            return 0 if reg == regs.SPC_WRITE_TO_LOG else 0x0100  # ERR_OK, ERR_REG
        return self._card(handle).refuse(C.ERR_REG, int(reg), 0, f"pointer register {reg} is not modelled")

    def _spcm_dwDefTransfer_i64(self, handle: Any, buf_type: int, direction: int, notify: Any, pointer: Any,
                                offset: Any, length: Any) -> int:
        self._log("DefTransfer", int(buf_type), int(direction), int(notify.value), pointer, int(offset.value),
                  int(length.value))
        return self._card(handle).def_transfer(int(buf_type), int(direction), pointer, int(offset.value),
                                               int(length.value))


_BYREF = type(ctypes.byref(ctypes.c_int()))
_C_ARGUMENT = (type(None), int, bytes, ctypes._SimpleCData, ctypes.Structure, ctypes.Union, ctypes.Array,
               ctypes._Pointer, _BYREF)


class _CFunction:
    """A C function as ``spcm_core`` sees it: callable, and it sets ``argtype``/``restype`` on it (spcm_core
    writes ``argtype``, which ctypes ignores, so arguments go through ctypes' default conversion: what that
    conversion refuses, a float or a numpy scalar, is refused here too)."""

    def __init__(self, name: str, impl: Callable[..., Any]) -> None:
        self.__name__ = name
        self._impl = impl
        self.argtype: Any = None
        self.restype: Any = None

    def __call__(self, *args: Any) -> Any:
        for i, arg in enumerate(args, 1):
            if not isinstance(arg, _C_ARGUMENT):
                raise ctypes.ArgumentError(f"argument {i}: TypeError: Don't know how to convert parameter {i} "
                                           f"({type(arg).__name__}) in {self.__name__}")
        return self._impl(*args)


def _unmodelled(name: str) -> Callable[..., Any]:
    def call(*args: Any) -> Any:
        raise AssertionError(f"{name} was called, but the fake card does not model it (the adapter does not use it)")

    return call


LIBRARY = FakeSpcmLibrary()


def _forget_spcm() -> None:
    for name in [m for m in sys.modules if m == "spcm" or m.startswith(("spcm.", "spcm_core"))]:
        del sys.modules[name]


def load_spcm() -> types.ModuleType:
    """The real ``spcm`` package, imported over ``LIBRARY`` once per process.

    The module is handed only to those who ask for it (``spcm_module=``): it is taken out of ``sys.modules``
    again, so a plain ``import spcm`` elsewhere in the test session still meets the machine as it is (no
    Spectrum driver here) instead of the fake card."""
    global _LOADED
    if _LOADED is not None:
        return _LOADED
    _forget_spcm()
    loader = ctypes.cdll
    real_load = loader.LoadLibrary

    def load_library(name: str) -> Any:
        return LIBRARY if name in DRIVER_NAMES else real_load(name)

    loader.LoadLibrary = load_library  # type: ignore[method-assign]  # the fake replaces ctypes' loader on purpose
    try:
        _LOADED = importlib.import_module("spcm")
    finally:
        del loader.LoadLibrary  # the instance attribute goes; the class's method is back
        _forget_spcm()
    return _LOADED


_LOADED: types.ModuleType | None = None
C: Any = load_spcm()  # every register and constant under its real name, from the vendor's own package


def is_step_register(reg: int) -> bool:
    """``SPC_SEQMODE_STEPMEM0 + i`` (the step registers end where the other sequence registers begin)."""
    return C.SPC_SEQMODE_STEPMEM0 <= reg < C.SPC_SEQMODE_AVAILMAXSEGMENT


_X_MODE = {C.SPCM_X0_MODE: 0, C.SPCM_X1_MODE: 1, C.SPCM_X2_MODE: 2}


def register_name(reg: int) -> str:
    """A readable name for a register number (step registers as ``STEPMEM0+i``)."""
    if is_step_register(reg):
        return f"STEPMEM0+{reg - C.SPC_SEQMODE_STEPMEM0}"
    return _REGISTER_NAMES.get(reg, str(reg))


def _setup_register_names() -> list[str]:
    names = ["SPC_CARDMODE", "SPC_CHENABLE", "SPC_SAMPLERATE", "SPC_CLOCKMODE", "SPC_REFERENCECLOCK",
             "SPC_SEQMODE_MAXSEGMENTS", "SPC_TRIG_ORMASK", "SPC_TRIG_ANDMASK", "SPC_TRIG_EXT0_MODE",
             "SPC_TRIG_EXT0_LEVEL0", "SPC_TRIG_TERM", "SPCM_X0_MODE", "SPCM_X1_MODE", "SPCM_X2_MODE"]
    names += [f"SPC_{kind}{ch}" for kind in ("AMP", "ENABLEOUT") for ch in range(4)]
    return names + [f"SPC_CH{ch}_STOPLEVEL" for ch in range(4)]


# the card takes these only while stopped (the manual's setup registers)
_SETUP_REGISTERS = frozenset(getattr(C, n) for n in _setup_register_names())
# names for the log (spcm_core gives some numbers several names; these are the ones the adapter uses)
_REGISTER_NAMES = {getattr(C, n): n for n in [*_setup_register_names(), "SPC_M2CMD", "SPC_SEQMODE_WRITESEGMENT",
                                              "SPC_SEQMODE_SEGMENTSIZE", "SPC_SEQMODE_STARTSTEP",
                                              "SPC_SEQMODE_STATUS", "SPCM_XX_ASYNCIO", "SPC_TIMEOUT"]}


def decode(word: int) -> tuple[int, int, int, int]:
    """``(segment, next_step, loops, flags)`` from a step word, with the manual's masks."""
    fields = card_rules.decode_step(word)
    high = (word & ((1 << 64) - 1)) >> 32
    return int(fields["segment"]), int(fields["next_step"]), int(fields["loops"]), high & ~card_rules.SPCSEQ_LOOPMASK


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
    features: int | None = None  # default: the sequence-mode option
    function_type: int | None = None  # default: SPCM_TYPE_AO (an AWG)
    product: str = "M4i.6622-x8"
    serial: int = 12345
    demo: bool = False
    rate_quantum_hz: int = 1  # the card's sample-rate resolution; the fake rounds to it
    amp_quantum_mv: int = 1  # the card's output-range resolution; the fake rounds up to it
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
    last_error: tuple[int, int, str] = (0, 0, "")
    last_error_code: int = 0
    _entry_seg: int = -1
    _entry_loops: int = 0
    _passes: int = 0
    _trigger_seen: bool = False
    _xmodes_pending: dict[int, int] = field(default_factory=dict)
    _xmodes: dict[int, int] = field(default_factory=dict)

    def refuse(self, code: int, reg: int, value: int, reason: str) -> int:
        """Record a breach the card refuses, and return its error code (``spcm`` raises with ``reason``)."""
        self.violations.append(reason)
        self.last_error = (reg, value & 0x7FFFFFFF, reason)
        self.last_error_code = code
        return code

    # --- register access ------------------------------------------------------------------------------

    def set(self, reg: int, value: int) -> int:
        if reg == C.SPC_M2CMD:
            return self._command(value)
        if is_step_register(reg):
            return self._write_step(reg - C.SPC_SEQMODE_STEPMEM0, value)
        if self.running and reg in _SETUP_REGISTERS:
            return self.refuse(C.ERR_SEQUENCE, reg, value, f"{register_name(reg)} written while the card runs")
        if reg == C.SPC_SEQMODE_MAXSEGMENTS:
            if value < 2 or value & (value - 1) or value > self.max_segments:
                return self.refuse(C.ERR_VALUE, reg, value, f"MAXSEGMENTS {value}: not a power of two in "
                                                            f"[2, {self.max_segments}]")
            if self.segments or self.steps:
                self.violations.append("MAXSEGMENTS written after data: the memory is discarded")
                self.segments.clear()
        if reg == C.SPC_SEQMODE_WRITESEGMENT and value >= self.registers.get(C.SPC_SEQMODE_MAXSEGMENTS, 0):
            return self.refuse(C.ERR_VALUE, reg, value, f"WRITESEGMENT {value} outside MAXSEGMENTS")
        if reg == C.SPC_SEQMODE_SEGMENTSIZE:
            if C.SPC_SEQMODE_WRITESEGMENT not in self.registers:
                return self.refuse(C.ERR_SEQUENCE, reg, value, "SEGMENTSIZE before WRITESEGMENT")
            limit = card_rules.max_segment_samples(self.memory_bytes, max(self.channels_enabled, 1),
                                                   self.registers.get(C.SPC_SEQMODE_MAXSEGMENTS, 2))
            problem = card_rules.segment_length_problem(value, max(self.channels_enabled, 1), limit)
            if problem is not None:
                return self.refuse(C.ERR_VALUE, reg, value, f"SEGMENTSIZE: {problem}")
        if reg == C.SPC_CHENABLE and bin(value).count("1") not in card_rules.CHANNEL_COUNTS:
            return self.refuse(C.ERR_VALUE, reg, value, f"CHENABLE {value:#x}: the card enables 1, 2 or 4 channels")
        if reg == C.SPC_SAMPLERATE:
            value = int(round(value / self.rate_quantum_hz)) * self.rate_quantum_hz
        if reg in (C.SPC_AMP0, C.SPC_AMP1, C.SPC_AMP2, C.SPC_AMP3):
            value = -(-value // self.amp_quantum_mv) * self.amp_quantum_mv
        if reg in _X_MODE:
            self._xmodes_pending[_X_MODE[reg]] = value
        if reg == C.SPCM_XX_ASYNCIO:
            for bit in range(3):
                if value >> bit & 1 and self._xmodes.get(bit) != C.SPCM_XMODE_ASYNCOUT:
                    self.violations.append(f"X{bit} driven high but it is not an active async output")
            self.pulses.append(value)
        self.registers[reg] = value
        return C.ERR_OK

    def get(self, reg: int) -> tuple[int, int]:
        identity = {
            C.SPC_FNCTYPE: C.SPCM_TYPE_AO if self.function_type is None else self.function_type,
            C.SPC_PCITYP: C.TYP_M4I6622_X8,
            C.SPC_PCIFEATURES: C.SPCM_FEAT_SEQUENCE if self.features is None else self.features,
            C.SPC_PCIEXTFEATURES: 0,
            C.SPC_MIINST_MAXADCVALUE: 32767,
            C.SPC_MIINST_ISDEMOCARD: int(self.demo),
            C.SPC_PCISERIALNO: self.serial,
            C.SPC_MIINST_MODULES: 1,
            C.SPC_MIINST_CHPERMODULE: self.n_channels,
            C.SPC_PCIMEMSIZE: self.memory_bytes,
            C.SPC_SEQMODE_AVAILMAXSEGMENT: self.max_segments,
            C.SPC_SEQMODE_AVAILMAXSTEPS: self.max_steps,
            C.SPC_SEQMODE_AVAILMAXLOOP: card_rules.SPCSEQ_LOOPMASK,
        }
        if reg in identity:
            return C.ERR_OK, identity[reg]
        if reg == C.SPC_SEQMODE_STATUS:
            now = self.step if self.running else 0
            if self.running and self.auto_advance:
                self.finish_pass()
            return C.ERR_OK, now
        if reg == C.SPC_M2STATUS:
            return C.ERR_OK, 0 if self.running else C.M2STAT_CARD_READY
        return C.ERR_OK, self.registers.get(reg, 0)

    def def_transfer(self, buf_type: int, direction: int, pointer: Any, offset: int, length: int) -> int:
        if buf_type != C.SPCM_BUF_DATA or direction != C.SPCM_DIR_PCTOCARD or offset != 0:
            return self.refuse(C.ERR_INVALIDPARAM, 0, buf_type,
                               f"DefTransfer({buf_type}, {direction}, offset {offset}): not a PC-to-card data buffer")
        ptr = pointer.value if isinstance(pointer, ctypes.c_void_p) else int(pointer)
        if ptr % card_rules.DMA_ALIGN_BYTES:
            self.violations.append(f"DMA buffer at {ptr:#x} is not aligned to {card_rules.DMA_ALIGN_BYTES} B")
        self.dma = (ptr, int(length))
        return C.ERR_OK

    # --- the model -------------------------------------------------------------------------------------

    @property
    def channels_enabled(self) -> int:
        return bin(self.registers.get(C.SPC_CHENABLE, 0)).count("1")

    def _command(self, cmd: int) -> int:
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
            code = self._dma()
            if code != C.ERR_OK:
                return code
        if cmd & C.M2CMD_CARD_START:
            if self.registers.get(C.SPC_CARDMODE) != C.SPC_REP_STD_SEQUENCE:
                return self.refuse(C.ERR_SEQUENCE, C.SPC_M2CMD, cmd, "card started outside sequence mode")
            start = self.registers.get(C.SPC_SEQMODE_STARTSTEP, 0)
            self.running = True
            if cmd & C.M2CMD_CARD_FORCETRIGGER or not cmd & C.M2CMD_CARD_ENABLETRIGGER:
                self._enter(start)
            return C.ERR_OK
        if cmd & C.M2CMD_CARD_FORCETRIGGER and self.running:
            self._trigger_seen = True
        return C.ERR_OK

    def _dma(self) -> int:
        if self.dma is None:
            return self.refuse(C.ERR_SEQUENCE, C.SPC_M2CMD, C.M2CMD_DATA_STARTDMA,
                               "STARTDMA without a DefTransfer buffer")
        ptr, length = self.dma
        self.dma = None
        seg = self.registers.get(C.SPC_SEQMODE_WRITESEGMENT)
        size = self.registers.get(C.SPC_SEQMODE_SEGMENTSIZE)
        nch = self.channels_enabled
        if seg is None or size is None or nch == 0:
            return self.refuse(C.ERR_SEQUENCE, C.SPC_M2CMD, C.M2CMD_DATA_STARTDMA,
                               "DMA without WRITESEGMENT/SEGMENTSIZE/CHENABLE")
        self.play(self.passes_per_dma)
        if length != size * nch * card_rules.BYTES_PER_SAMPLE:
            return self.refuse(C.ERR_VALUE, C.SPC_M2CMD, length,
                               f"DMA of {length} B into segment {seg} of {size} samples x {nch} channels")
        if self.running and self.step >= 0 and self._entry_seg == seg:
            self.violations.append(f"torn: DMA into segment {seg} while step {self.step} plays it")
        raw = ctypes.string_at(ptr, length)
        self.segments[seg] = np.frombuffer(raw, dtype=np.int16).reshape(-1, nch).copy()
        return C.ERR_OK

    def _write_step(self, index: int, word: int) -> int:
        reg = C.SPC_SEQMODE_STEPMEM0 + index
        if index >= self.max_steps:
            return self.refuse(C.ERR_VALUE, reg, word, f"step {index} beyond the step memory")
        seg, nxt, loops, flags = decode(word)
        if flags & ~(card_rules.SPCSEQ_ENDLOOPONTRIG | card_rules.SPCSEQ_END):
            return self.refuse(C.ERR_VALUE, reg, word, f"step {index}: unknown flags {flags:#x}")
        if loops < 1:
            return self.refuse(C.ERR_VALUE, reg, word, f"step {index}: loops {loops} < 1")
        if nxt >= self.max_steps:
            return self.refuse(C.ERR_VALUE, reg, word, f"step {index}: next {nxt} beyond the step memory")
        self.steps[index] = word
        self.step_written_with_size[index] = len(self.segments[seg]) if seg in self.segments else 0
        return C.ERR_OK

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
        if flags & card_rules.SPCSEQ_ENDLOOPONTRIG and not self._trigger_seen:
            return
        if flags & card_rules.SPCSEQ_END:
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
    """One test's cards and the log of every C call made on them."""

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
        """``(register name, value)`` of every register write, in order (commands appear as ``SPC_M2CMD``)."""
        return [(register_name(c[1]), c[2]) for c in self.log if c[0] == "set_i"]


def make_fake_spcm(*, with_card: bool = True, **card_kwargs: Any) -> types.ModuleType:
    """The real ``spcm`` package over the fake library, with a new set of cards (one at ``/dev/spcm0`` unless
    ``with_card`` is false). Returned as a module view whose ``fake`` attribute holds the cards and the log;
    everything else is ``spcm``'s own."""
    spcm = load_spcm()
    fake = FakeSpcm()
    if with_card:
        fake.add_card(**card_kwargs)
    LIBRARY.lab = fake
    view = types.ModuleType("spcm")
    view.__dict__.update({k: v for k, v in vars(spcm).items() if not k.startswith("__")})
    view.fake = fake  # type: ignore[attr-defined]  # the test reaches the fake through the view
    return view


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
