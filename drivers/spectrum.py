"""The Spectrum M4i.66xx AWG in sequence mode, behind ``engine.devices.SequenceAWG``, through the ``spcm`` package.

``spcm`` is optional (``pip install -e '.[hardware]'``) and is imported only when the adapter opens. Without the
package, or with the package but without Spectrum's driver library (``import spcm`` then raises a bare
``Exception``), opening raises ``DeviceError`` saying what to install.

Vendor semantics this adapter relies on. Sources: the Spectrum M4i.66xx manual, chapter "Sequence Mode"
(tables "sequence mode registers for segment handling", "sequence mode step registers and register setup",
"sequence mode start register", "sequence mode segment status register", and the sections "Changing
sequences or step parameters during runtime" / "Changing data patterns during runtime"); chapter
"Multi Purpose I/O Lines" (``SPCM_XX_ASYNCIO``); and the ``spcm`` package's ``classes_sequence.py``
(``Sequence.step_memory``, ``Segment.update``), which encodes the same layout:

- A step is one 64-bit word at ``SPC_SEQMODE_STEPMEM0 + step``. Low 32 bits: ``next_step << 16 | segment``
  (``SPCSEQ_NEXTSTEPMASK = 0xFFFF0000``, ``SPCSEQ_SEGMENTMASK = 0x0000FFFF``). High 32 bits: ``flags | loops``
  (``SPCSEQ_LOOPMASK = 0x000FFFFF``; ``SPCSEQ_ENDLOOPALWAYS = 0``: go to next after ``loops`` passes;
  ``SPCSEQ_ENDLOOPONTRIG = 0x40000000``: after ``loops`` passes keep repeating until a trigger has been seen
  (a trigger during the step is remembered until the step's end); ``SPCSEQ_END = 0x80000000``: stop the card
  after this step, never used here: the card plays until ``stop()``).
- Step memory is read-before-write: any step may be rewritten while the card plays; an entered step plays the
  segment and loops it had when entered, and leaves to the next step its word names when the step ends. The
  streamer's pointer updates (``engine/streaming.py``) rest on this.
- Data memory is not: a segment must not be written while it plays (the caller's duty; it is not checked
  here because checking would cost a register read per upload).
- ``SPC_SEQMODE_MAXSEGMENTS`` (a power of two, at least 2) partitions the memory into equal segments and
  discards everything written before; it is set once, in ``configure()``, before any upload.
- An upload: ``SPC_SEQMODE_WRITESEGMENT`` (select the segment; must come first), ``SPC_SEQMODE_SEGMENTSIZE``
  (samples per channel), ``spcm_dwDefTransfer_i64(SPCM_BUF_DATA, SPCM_DIR_PCTOCARD, ...)`` on the caller's
  buffer, then ``M2CMD_DATA_STARTDMA | M2CMD_DATA_WAITDMA`` (blocking; other segments keep playing).
  Samples are int16, channels multiplexed sample by sample, which is exactly a C-contiguous ``[n, ch]`` array.
- "Remember to update the sequence step entries if the segment length has changed, so that the driver can
  re-calculate the internal start-addresses": after an upload that changes a segment's length, every step
  that plays that segment is rewritten (from a shadow copy of the step words).
- Segment length, step-word fields, partition and DMA alignment: ``engine/card_rules.py`` (one statement
  of the card's rules, shared with the simulated AWG and the tests' fake card).
- DMA reads host memory in place from page-aligned buffers (Spectrum's examples allocate 4 KiB-aligned
  buffers); a caller's buffer that is not aligned is copied into the adapter's own aligned buffer first.
- Opening: ``spcm.Card(device).open()`` and then a check of ``function_type()``. Passing ``card_type`` to
  ``spcm.Card`` with a device name makes ``Card.open()`` compare the type before reading it, so it always
  raises "not the correct type" (spcm 1.13).
- ``SPC_SEQMODE_STATUS``: the step playing now. ``M2CMD_CARD_START | ENABLETRIGGER | FORCETRIGGER`` starts
  playback at ``SPC_SEQMODE_STARTSTEP`` at once; ``M2CMD_CARD_FORCETRIGGER`` later is a software trigger.
- X0..X2 set to ``SPCM_XMODE_ASYNCOUT`` are driven through ``SPCM_XX_ASYNCIO`` (bit k drives Xk); mode changes
  take effect at the next ``M2CMD_CARD_WRITESETUP`` (or start).

Threading: like every device, the adapter belongs to the engine thread; it takes no locks on the hot path.
"""

from __future__ import annotations

import ctypes
import importlib
import time
from types import ModuleType
from typing import Any

import numpy as np

from engine import card_rules
from engine.aod_limits import SegmentGuard
from engine.config import AWGConfig, DevicesConfig
from engine.devices import DeviceError, StepInfo

__all__ = ["SpectrumAWG", "import_spcm"]

SpectrumSettings = DevicesConfig.SpectrumSettings

INSTALL_SPCM = (
    "install it with pip install -e '.[hardware]' (or pip install spcm), then check with 'llrs devices'"
)
INSTALL_DRIVER = (
    "install the Spectrum driver for your card (kernel module and libspcm_linux.so, or spcm_win64.dll on Windows) "
    "from https://spectrum-instrumentation.com/support/downloads.php, then check with 'llrs devices'"
)


def import_spcm() -> ModuleType:
    """Import ``spcm``, turning each way it can fail into a ``DeviceError`` that says what to install."""
    try:
        return importlib.import_module("spcm")
    except ModuleNotFoundError as err:
        if err.name in ("spcm", "spcm_core"):
            raise DeviceError(f"Spectrum AWG: the 'spcm' Python package is not installed; {INSTALL_SPCM}") from None
        raise DeviceError(
            f"Spectrum AWG: the 'spcm' package is installed but its dependency {err.name!r} is missing; {INSTALL_SPCM}"
        ) from None
    except ImportError as err:  # e.g. SPCM_NO_DLL=1: spcm_core loads without the library, spcm then cannot
        raise DeviceError(
            f"Spectrum AWG: the 'spcm' package is installed but cannot use the Spectrum driver library ({err}); "
            f"{INSTALL_DRIVER}"
        ) from None
    except Exception as err:  # noqa: BLE001 - spcm raises a bare Exception when its driver library is missing
        first_line = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        raise DeviceError(
            f"Spectrum AWG: the 'spcm' package is installed but the Spectrum driver library could not be loaded "
            f"(spcm says: {first_line}); {INSTALL_DRIVER}"
        ) from None


class SpectrumAWG:
    """``SequenceAWG`` on a Spectrum M4i.66xx card (see the module docstring for the vendor rules it follows).

    ``spcm_module`` replaces ``import spcm`` (the tests pass the real package loaded over a fake C library).
    ``open()`` is called by ``configure()`` if it was not called before; the factory opens explicitly so that
    a missing driver shows up when the devices are built, not at the first shot.
    """

    def __init__(
        self, settings: SpectrumSettings | None = None, *, spcm_module: ModuleType | None = None,
        rf_guard: SegmentGuard | None = None,
    ) -> None:
        self.settings = settings if settings is not None else SpectrumSettings()
        self.rf_guard = rf_guard  # the channels' RF limits, checked on every upload (None: the card's range only)
        self._spcm = spcm_module
        self._card: Any = None
        self._running = False
        self.n_channels = 0  # the enabled channels and the sample rate (engine.devices.SequenceAWG), set by configure
        self.sample_rate_hz = 0.0
        self._n_segments = 0
        self._n_steps = 0
        self._seg_len: list[int] = []
        self._step_seg = np.zeros(0, dtype=np.int32)
        self._step_hit = np.zeros(0, dtype=bool)
        self._step_words: list[int] = []
        self._xio = 0
        self._staging = np.zeros(0, dtype=np.uint8)  # page-aligned copy of an unaligned upload
        self.staged_uploads = 0  # uploads that had to be copied (the caller's buffer was not page-aligned)
        self.info: dict[str, Any] = {}

    # --- life cycle ------------------------------------------------------------------------------------

    @property
    def is_open(self) -> bool:
        return self._card is not None

    def open(self) -> None:
        """Import ``spcm``, open the card, and read what it can do (sequence option, memory, limits)."""
        if self._card is not None:
            return
        spcm = self._spcm if self._spcm is not None else import_spcm()
        self._spcm = spcm
        dev = self.settings.device
        try:
            card = spcm.Card(dev)  # no card_type: see the module docstring
            card.open()
        except Exception as err:  # noqa: BLE001 - spcm raises SpcmException and friends
            raise DeviceError(
                f"Spectrum AWG: cannot open {dev!r}: {err}; check devices.spectrum.device, that the card appears "
                "in Spectrum Control Center, and that no other program holds it"
            ) from None
        try:
            if int(card.function_type()) != spcm.SPCM_TYPE_AO:
                raise DeviceError(
                    f"Spectrum AWG: {dev!r} is a {card.product_name()}, not an analog output card "
                    f"(function type {int(card.function_type()):#x}); set devices.spectrum.device to the AWG"
                )
            self._bind(spcm)
            features = int(card.get_i(spcm.SPC_PCIFEATURES))
            if not features & spcm.SPCM_FEAT_SEQUENCE:
                raise DeviceError(f"Spectrum AWG: the card at {dev!r} has no sequence-mode option (SPCM_FEAT_SEQUENCE)")
            self.info = {
                "product": str(card.product_name()),
                "serial": int(card.sn()),
                "demo_card": bool(card.is_demo_card()),
                "channels": int(card.num_channels()),
                "memory_bytes": int(card.get_i(spcm.SPC_PCIMEMSIZE)),
                "max_segments": int(card.get_i(spcm.SPC_SEQMODE_AVAILMAXSEGMENT)),
                "max_steps": int(card.get_i(spcm.SPC_SEQMODE_AVAILMAXSTEPS)),
                "max_sample_value": int(card.max_sample_value()),
            }
        except DeviceError:
            card.close()
            raise
        except Exception as err:  # noqa: BLE001 - spcm raises SpcmException and friends; all become DeviceError
            card.close()
            raise DeviceError(f"Spectrum AWG: {dev!r} opened but cannot be queried: {err}") from None
        self._card = card

    def _bind(self, spcm: ModuleType) -> None:
        """Resolve the registers and commands once (no attribute look-ups on the hot path)."""
        self._R_WRITESEGMENT = spcm.SPC_SEQMODE_WRITESEGMENT
        self._R_SEGMENTSIZE = spcm.SPC_SEQMODE_SEGMENTSIZE
        self._R_STEPMEM0 = spcm.SPC_SEQMODE_STEPMEM0
        self._R_STATUS = spcm.SPC_SEQMODE_STATUS
        self._R_ASYNCIO = spcm.SPCM_XX_ASYNCIO
        self._C_DMA = spcm.M2CMD_DATA_STARTDMA | spcm.M2CMD_DATA_WAITDMA
        self._C_STARTDMA = spcm.M2CMD_DATA_STARTDMA
        self._C_WAITDMA = spcm.M2CMD_DATA_WAITDMA
        self._BUF_DATA = spcm.SPCM_BUF_DATA
        self._DIR_PCTOCARD = spcm.SPCM_DIR_PCTOCARD
        self._ERR_OK = spcm.ERR_OK
        self._def_transfer = spcm.spcm_dwDefTransfer_i64

    def close(self) -> None:
        """Stop playback and release the card."""
        if self._card is None:
            return
        try:
            self.stop()
        finally:
            card, self._card = self._card, None
            try:
                card.close()
            except Exception as err:  # noqa: BLE001 - spcm raises SpcmException and friends; all become DeviceError
                raise DeviceError(f"Spectrum AWG: closing the card failed: {err}") from None

    # --- protocol: properties and setup ----------------------------------------------------------------

    @property
    def max_segment_samples(self) -> int:
        """Longest segment (samples per channel) the current partition allows."""
        return self._max_seg

    @property
    def min_segment_samples(self) -> int:
        return self._min_seg

    def configure(self, config: AWGConfig, *, n_channels: int, sample_rate_hz: float) -> None:
        """Reset the card and program mode, channels, clock, trigger, X lines and the memory partition."""
        self.open()
        spcm, card, s = self._spcm, self._card, self.settings
        assert spcm is not None
        if n_channels not in card_rules.CHANNEL_COUNTS or n_channels > self.info["channels"]:
            raise DeviceError(
                f"Spectrum AWG: {n_channels} channels requested; the card enables 1, 2 or 4 "
                f"(it has {self.info['channels']})"
            )
        rate = int(round(sample_rate_hz))
        if abs(rate - sample_rate_hz) > 1e-6:
            raise DeviceError(
                "Spectrum AWG: the sample rate must be a whole number of Hz "
                f"(waveforms.sample_rate_hz = {sample_rate_hz!r})"
            )
        max_segments = card_rules.segment_partition(config.n_segments)
        if max_segments > self.info["max_segments"]:
            raise DeviceError(
                f"Spectrum AWG: awg.n_segments = {config.n_segments} needs {max_segments} segments; the card has "
                f"at most {self.info['max_segments']}"
            )
        if config.n_steps > self.info["max_steps"]:
            raise DeviceError(
                f"Spectrum AWG: awg.n_steps = {config.n_steps} but the card has {self.info['max_steps']} steps"
            )
        amps = s.amplitude_mv if isinstance(s.amplitude_mv, list) else [s.amplitude_mv] * n_channels
        if len(amps) < n_channels:
            raise DeviceError(
                f"Spectrum AWG: devices.spectrum.amplitude_mv lists {len(amps)} amplitudes for {n_channels} channels"
            )
        self._running = False
        try:
            card.cmd(spcm.M2CMD_CARD_STOP)
            card.cmd(spcm.M2CMD_CARD_RESET)
            card.set_i(spcm.SPC_CARDMODE, spcm.SPC_REP_STD_SEQUENCE)
            mask = 0
            for ch in range(n_channels):
                mask |= getattr(spcm, f"CHANNEL{ch}")
            card.set_i(spcm.SPC_CHENABLE, mask)
            stop_level = spcm.SPCM_STOPLVL_ZERO if s.stop_level == "zero" else spcm.SPCM_STOPLVL_HOLDLAST
            for ch in range(n_channels):
                card.set_i(getattr(spcm, f"SPC_ENABLEOUT{ch}"), 1)
                card.set_i(getattr(spcm, f"SPC_AMP{ch}"), int(amps[ch]))
                actual_mv = int(card.get_i(getattr(spcm, f"SPC_AMP{ch}")))
                if actual_mv > int(amps[ch]):  # the card rounds to its own steps: never above the configuration
                    card.set_i(getattr(spcm, f"SPC_ENABLEOUT{ch}"), 0)
                    raise DeviceError(
                        f"Spectrum AWG: channel {ch}'s output range came out at {actual_mv} mV, above the configured "
                        f"{amps[ch]} mV (devices.spectrum.amplitude_mv); the RF limits assume the configured range, so "
                        "the output stays off: configure a range the card sets exactly"
                    )
                card.set_i(getattr(spcm, f"SPC_CH{ch}_STOPLEVEL"), stop_level)
            if s.external_reference_hz is not None:
                card.set_i(spcm.SPC_CLOCKMODE, spcm.SPC_CM_EXTREFCLOCK)
                card.set_i(spcm.SPC_REFERENCECLOCK, int(round(s.external_reference_hz)))
            else:
                card.set_i(spcm.SPC_CLOCKMODE, spcm.SPC_CM_INTPLL)
            card.set_i(spcm.SPC_SAMPLERATE, rate)
            actual = int(card.get_i(spcm.SPC_SAMPLERATE))
            if actual != rate:
                raise DeviceError(
                    f"Spectrum AWG: asked for {rate} S/s, the card runs at {actual} S/s; choose a "
                    "waveforms.sample_rate_hz the card can make exactly (tone phases depend on it)"
                )
            card.set_i(spcm.SPC_TRIG_ANDMASK, 0)
            if s.trigger == "ext0":
                card.set_i(spcm.SPC_TRIG_ORMASK, spcm.SPC_TMASK_EXT0)
                card.set_i(spcm.SPC_TRIG_EXT0_MODE, spcm.SPC_TM_POS if s.trigger_edge == "rising" else spcm.SPC_TM_NEG)
                card.set_i(spcm.SPC_TRIG_EXT0_LEVEL0, int(s.trigger_level_mv))
                card.set_i(spcm.SPC_TRIG_TERM, 1 if s.trigger_termination_50ohm else 0)
            else:
                card.set_i(spcm.SPC_TRIG_ORMASK, spcm.SPC_TMASK_NONE)
            for line in (s.camera_line, s.resume_line):
                card.set_i(getattr(spcm, f"SPCM_X{line}_MODE"), spcm.SPCM_XMODE_ASYNCOUT)
            card.set_i(spcm.SPC_TIMEOUT, int(round(s.dma_timeout_s * 1000)))
            card.set_i(spcm.SPC_SEQMODE_MAXSEGMENTS, max_segments)
            card.set_i(spcm.SPC_SEQMODE_STARTSTEP, 0)
            card.cmd(spcm.M2CMD_CARD_WRITESETUP)  # X-line modes take effect now, before any pulse
            self._xio = 0
            card.set_i(self._R_ASYNCIO, 0)
        except DeviceError:
            raise
        except Exception as err:  # noqa: BLE001 - spcm raises SpcmException and friends; all become DeviceError
            raise DeviceError(f"Spectrum AWG: configuring the card failed: {err}") from None
        self.n_channels = n_channels
        self.sample_rate_hz = float(rate)
        self._n_segments = config.n_segments
        self._n_steps = config.n_steps
        self._max_seg = card_rules.max_segment_samples(self.info["memory_bytes"], n_channels, config.n_segments)
        self._min_seg = card_rules.min_segment_samples(n_channels)
        self._seg_len = [0] * config.n_segments
        self._step_seg = np.full(config.n_steps, -1, dtype=np.int32)
        self._step_hit = np.zeros(config.n_steps, dtype=bool)
        self._step_words = [0] * config.n_steps
        self._camera_bit = 1 << s.camera_line
        self._resume_bit = 1 << s.resume_line

    # --- protocol: memory writes (hot path) ------------------------------------------------------------

    def write_segment(self, index: int, samples: np.ndarray) -> None:
        """DMA ``samples`` (int16[n, n_channels], C-contiguous, used in place) into segment ``index``; blocks."""
        self._upload(index, samples, self._C_DMA)

    def start_upload(self, index: int, samples: np.ndarray) -> None:
        """Start the DMA of ``samples`` into segment ``index`` (``M2CMD_DATA_STARTDMA``) and return; the card
        reads ``samples`` in place until ``wait_upload`` returns."""
        self._upload(index, samples, self._C_STARTDMA)

    def wait_upload(self, *, timeout_s: float) -> None:
        """``M2CMD_DATA_WAITDMA``: block until the DMA started last is done (the card's own timeout applies)."""
        try:
            self._card.cmd(self._C_WAITDMA)
        except Exception as err:  # noqa: BLE001 - SpcmException / SpcmTimeout
            raise DeviceError(f"Spectrum AWG: waiting for the segment upload failed: {err}") from None

    def _upload(self, index: int, samples: np.ndarray, command: int) -> None:
        if not self._n_segments:
            raise DeviceError("Spectrum AWG: write_segment before configure()")
        problem = card_rules.segment_samples_problem(index, samples, self._n_segments, self.n_channels)
        if problem is not None:
            raise DeviceError(f"Spectrum AWG: {problem}")
        n = samples.shape[0]
        problem = card_rules.segment_length_problem(n, self.n_channels, self._max_seg)
        if problem is not None:
            raise DeviceError(
                f"Spectrum AWG: segment {index}: {problem}; the card needs a multiple of "
                f"{card_rules.SEGMENT_STEP_SAMPLES} between {self._min_seg} and {self._max_seg}"
            )
        if not samples.flags.c_contiguous:
            raise DeviceError(
                f"Spectrum AWG: segment {index}: samples must be C-contiguous (the DMA reads them in place)"
            )
        problem = None if self.rf_guard is None else self.rf_guard.problem(samples)
        if problem is not None:
            raise DeviceError(f"Spectrum AWG: segment {index} refused by the RF limits: {problem}")
        pointer = self._dma_pointer(samples)
        card = self._card
        try:
            card.set_i(self._R_WRITESEGMENT, index)
            card.set_i(self._R_SEGMENTSIZE, n)
            err = self._def_transfer(
                card.handle(), self._BUF_DATA, self._DIR_PCTOCARD, 0, ctypes.c_void_p(pointer), 0, samples.nbytes
            )
            if err != self._ERR_OK:
                raise DeviceError(f"Spectrum AWG: defining the DMA buffer for segment {index} failed (error {err:#x})")
            card.cmd(command)
        except DeviceError:
            raise
        except Exception as err:  # noqa: BLE001 - SpcmException / SpcmTimeout
            raise DeviceError(f"Spectrum AWG: uploading segment {index} ({samples.nbytes} B) failed: {err}") from None
        if self._seg_len[index] != n:
            self._seg_len[index] = n
            self._refresh_steps_playing(index)

    def _dma_pointer(self, samples: np.ndarray) -> int:
        """Where the DMA reads ``samples``: in place when page-aligned, else from the adapter's aligned copy
        (the card reads it until ``wait_upload``; one DMA runs at a time, so one copy buffer serves)."""
        if samples.ctypes.data % card_rules.DMA_ALIGN_BYTES == 0:
            return int(samples.ctypes.data)
        if self._staging.nbytes < samples.nbytes:
            self._staging = card_rules.page_aligned_zeros(samples.nbytes, np.uint8)
        np.copyto(self._staging[: samples.nbytes], samples.reshape(-1).view(np.uint8))
        self.staged_uploads += 1
        return int(self._staging.ctypes.data)

    def _refresh_steps_playing(self, segment: int) -> None:
        """Rewrite every step that plays ``segment`` (its length changed; see the module docstring)."""
        np.equal(self._step_seg, segment, out=self._step_hit)
        if not self._step_hit.any():
            return
        card, base, words = self._card, self._R_STEPMEM0, self._step_words
        try:
            for step in np.flatnonzero(self._step_hit):
                card.set_i(base + int(step), words[step])
        except Exception as err:  # noqa: BLE001 - spcm raises SpcmException and friends; all become DeviceError
            raise DeviceError(f"Spectrum AWG: refreshing the steps of segment {segment} failed: {err}") from None

    def write_step(self, index: int, step: StepInfo) -> None:
        """Write one step word (takes effect the next time the card enters or leaves that step)."""
        seg, nxt, loops = step.segment, step.next_step, step.loops
        if not self._n_steps:
            raise DeviceError("Spectrum AWG: write_step before configure()")
        problem = card_rules.step_problem(index, seg, nxt, loops, self._n_steps, self._n_segments)
        if problem is not None:
            raise DeviceError(f"Spectrum AWG: {problem}")
        if self._seg_len[seg] == 0:
            raise DeviceError(
                f"Spectrum AWG: step {index} plays segment {seg}, which holds no samples yet; upload it first"
            )
        word = card_rules.encode_step(seg, nxt, loops, on_trigger=step.on_trigger)
        try:
            self._card.set_i(self._R_STEPMEM0 + index, word)
        except Exception as err:  # noqa: BLE001 - spcm raises SpcmException and friends; all become DeviceError
            raise DeviceError(f"Spectrum AWG: writing step {index} failed: {err}") from None
        self._step_words[index] = word
        self._step_seg[index] = seg

    # --- protocol: playback ----------------------------------------------------------------------------

    def start(self, entry_step: int) -> None:
        """Start playback at ``entry_step`` now (forced start; later triggers end ``on_trigger`` loops)."""
        if self._card is None or not 0 <= entry_step < self._n_steps or self._step_seg[entry_step] < 0:
            raise DeviceError(
                f"Spectrum AWG: cannot start at step {entry_step}: it was never written (or not configured)"
            )
        spcm = self._spcm
        assert spcm is not None
        try:
            self._card.set_i(spcm.SPC_SEQMODE_STARTSTEP, entry_step)
            self._card.cmd(spcm.M2CMD_CARD_START | spcm.M2CMD_CARD_ENABLETRIGGER | spcm.M2CMD_CARD_FORCETRIGGER)
        except Exception as err:  # noqa: BLE001 - spcm raises SpcmException and friends; all become DeviceError
            raise DeviceError(f"Spectrum AWG: starting playback failed: {err}") from None
        self._running = True

    def current_step(self) -> int:
        """The step playing now (``SPC_SEQMODE_STATUS``), or -1 when stopped."""
        if not self._running:
            return -1
        try:
            return int(self._card.get_i(self._R_STATUS)) & card_rules.SPCSEQ_SEGMENTMASK
        except Exception as err:  # noqa: BLE001 - spcm raises SpcmException and friends; all become DeviceError
            raise DeviceError(f"Spectrum AWG: reading the current step failed: {err}") from None

    def wait_for_step(self, step: int, *, timeout_s: float) -> None:
        """Busy-poll the current step until it is ``step`` (polling is what keeps the latency low)."""
        if not self._running:
            raise DeviceError(f"Spectrum AWG: waiting for step {step} but playback is stopped")
        deadline = time.monotonic() + timeout_s
        while True:
            now_step = self.current_step()
            if now_step == step:
                return
            if time.monotonic() > deadline:
                raise DeviceError(
                    f"Spectrum AWG: step {step} not reached within {timeout_s:g} s (playing step {now_step}); "
                    "check the step table's next pointers"
                )

    def pulse(self, line: str) -> None:
        """Pulse an X line high for ``pulse_width_s``: ``camera`` (exposure trigger) or ``resume`` (sequencer)."""
        if line == "camera":
            bit = self._camera_bit
        elif line == "resume":
            bit = self._resume_bit
        else:
            raise DeviceError(f"Spectrum AWG: unknown pulse line {line!r}; use 'camera' or 'resume'")
        card, reg, width = self._card, self._R_ASYNCIO, self.settings.pulse_width_s
        if card is None or not self.n_channels:
            raise DeviceError("Spectrum AWG: pulse before configure(); the X lines are not set up yet")
        try:
            card.set_i(reg, self._xio | bit)
            if width > 0:
                t_end = time.perf_counter() + width
                while time.perf_counter() < t_end:
                    pass
            card.set_i(reg, self._xio)
        except Exception as err:  # noqa: BLE001 - spcm raises SpcmException and friends; all become DeviceError
            raise DeviceError(f"Spectrum AWG: pulsing the {line} line failed: {err}") from None

    def force_trigger(self) -> None:
        """A software trigger: a step waiting with ``on_trigger`` moves on after its current pass."""
        spcm = self._spcm
        if self._card is None or spcm is None:
            raise DeviceError("Spectrum AWG: force_trigger before open()")
        try:
            self._card.cmd(spcm.M2CMD_CARD_FORCETRIGGER)
        except Exception as err:  # noqa: BLE001 - spcm raises SpcmException and friends; all become DeviceError
            raise DeviceError(f"Spectrum AWG: software trigger failed: {err}") from None

    def stop(self) -> None:
        """Stop playback (the outputs go to the configured stop level). Safe to call at any time."""
        self._running = False
        if self._card is None or self._spcm is None:
            return
        try:
            self._card.cmd(self._spcm.M2CMD_CARD_STOP)
        except Exception as err:  # noqa: BLE001 - spcm raises SpcmException and friends; all become DeviceError
            raise DeviceError(f"Spectrum AWG: stopping the card failed: {err}") from None
