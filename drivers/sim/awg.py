"""A simulated sequence-mode AWG (Spectrum M4i style) that plays in simulated time and moves the world's atoms.

Sequence memory: segments of ``int16[n, n_channels]`` samples and steps ``(segment, next_step, loops,
on_trigger)``. A step plays its segment ``loops`` times (then, if ``on_trigger``, keeps repeating it until a
trigger has arrived since the step was entered), then goes to ``next_step`` *as the step table reads at the
moment the step ends*. A step whose next is itself loops forever. Underruns are not special-cased: they fall
out of the step table exactly as on the card.

Playback is lazy: whenever a method is called (or ``sync()``), playback is advanced to the clock's now. Each
pass of a segment is decoded from its samples (``drivers/sim/decode.py``; the data that was in the segment when
the pass started) and applied to the world slot by slot, at the time each slot ends; vacuum loss runs on the
same clock. A segment that changes nothing (every tone steady) is applied once per visit, and self-loops are
fast-forwarded in O(1), so seconds of idle cost nothing.

**The world waits until someone looks.** Which step plays when follows from the step table and the clock alone;
only the atoms need the decoded samples. So the calls a streaming host makes (``start_upload``, ``wait_upload``,
``write_step``, ``current_step``) advance the step table's playback only and queue the slots played
(``_played``); the queue is decoded and applied to the world, in order and at the slots' own times, by the
calls after which the world can be observed or the host waits for the card: ``sync()`` (the camera, the truth
and the loss reports call it first), ``wait_for_step``, ``pulse``, ``start``, ``stop`` and a reconfiguration.
A real card decodes nothing; decoding on the engine's thread while it streams took, for 64x128 (803 kB
segments), ~4.4 ms of the engine's core per 0.64 ms of playback at its real-time priority and evicted its caches
between renders (a 32-slot render ~480 us in the loop against ~275 us out of it). The atoms end exactly where
they did: vacuum hits are drawn per site in advance and applied earliest first (``World.elapse_to`` applies
those due, however the calls split the time), and moves and their losses are applied in the same order at
the same times, so a seed replays.

Memory writes cost device time on the clock (``clock.advance``): an upload ``nbytes / upload_bytes_per_s +
|N(0, upload_jitter_s)|`` (+ the ``upload_delay_s`` fault knob), a step write ``step_write_s``. A write takes
effect when it completes; playback before that sees the old contents. In ``realtime`` mode samples are
decoded during the upload and the wall time that takes is charged against the modelled upload time, so the
simulator's own work does not make the host look late (if decoding takes longer than the modelled upload, the
upload takes that long). In ``simulated`` mode the clock stands still while the simulator works, and a
segment is decoded when the world is next brought up to date (above): decoding at upload, or while the host
streams, would evict its caches in the middle of its latency-critical path, which a real card's DMA does not do.
"""

from __future__ import annotations

import math
import threading
from collections import deque
from collections.abc import Iterable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass

import numpy as np

from drivers.sim.clock import SimClock
from drivers.sim.decode import DecodedSegment, SampleDecoder
from drivers.sim.world import World
from engine import card_rules
from engine.aod_limits import SegmentGuard
from engine.config import AWGConfig, SystemConfig
from engine.devices import DeviceError, StepInfo

__all__ = ["LOG_LENGTH", "PlayRecord", "SimAWG"]

#: Step visits and pulses kept for inspection (the newest); bounded so that a long run's memory stays flat.
LOG_LENGTH = 4096


@dataclass
class PlayRecord:
    """One visit of playback to a step: ``repeats`` passes of ``segment`` from ``t_start_s``."""

    step: int
    segment: int
    t_start_s: float
    repeats: int = 1


class _Segment:
    """One version of a segment's contents; decoded lazily, once (when the world is brought up to date)."""

    __slots__ = ("data", "decoded", "t_begin_s", "t_ready_s")

    def __init__(self, data: np.ndarray, t_begin_s: float, t_ready_s: float) -> None:
        self.data = data
        self.decoded: DecodedSegment | None = None
        self.t_begin_s = t_begin_s
        self.t_ready_s = t_ready_s


class SimAWG:
    """Implements ``engine.devices.SequenceAWG`` against a simulated ``World`` and ``SimClock``.

    Fault knobs (python-microscope style; set them as attributes): ``fail_next_upload`` (the next
    ``write_segment`` raises ``DeviceError`` without writing), ``fail_uploads`` (every one does, until
    cleared), ``upload_delay_s`` (extra time added to every
    upload), ``step_write_delay_s`` (extra time added to every step write).
    """

    def __init__(
        self,
        world: World,
        clock: SimClock,  # advanced by the card's modelled times and paused while the simulator computes
        config: SystemConfig,
        *,
        rng: np.random.Generator | None = None,
        full_scale: float = 32767.0,
    ) -> None:
        self.world = world
        self.clock = clock
        self.system = config
        self.full_scale = full_scale
        seed = config.sim.seed
        self.rng = rng if rng is not None else np.random.default_rng(None if seed is None else seed + 7919)
        self.fail_next_upload = False
        self.fail_uploads = False
        self.upload_delay_s = 0.0
        self.step_write_delay_s = 0.0
        self.uploads = 0
        self.bytes_uploaded = 0
        self.torn_plays = 0  # passes that started while their segment was being uploaded
        self.pulses: deque[tuple[str, float]] = deque(maxlen=LOG_LENGTH)
        self._lock = threading.RLock()
        self._trigger_in = threading.Event()
        n_ch = 1 if config.array.trap_source == "aod" else 2
        self.configure(config.awg, n_channels=n_ch, sample_rate_hz=config.waveforms.sample_rate_hz)

    # --- protocol: properties and setup ----------------------------------------------------------------

    def configure(self, config: AWGConfig, *, n_channels: int, sample_rate_hz: float) -> None:
        """Reset the card: clear sequence memory and stop playback."""
        if n_channels not in card_rules.CHANNEL_COUNTS:
            raise DeviceError(f"sim AWG: {n_channels} channels requested; the card enables 1, 2 or 4")
        with self._lock:
            if hasattr(self, "_played"):  # a reconfiguration: the world first sees what was played
                self._apply_played()
            try:
                decoder = SampleDecoder(
                    self.system, sample_rate_hz=sample_rate_hz, n_channels=n_channels, full_scale=self.full_scale
                )
            except ValueError as err:
                raise DeviceError(f"sim AWG: cannot configure: {err}") from None
            # the RF limits of the configured channels, on every upload (the engine checks too; a device that
            # plays whatever it is sent would let a bug in the engine reach the amplifier)
            limits = self.system.channel_limits(self.full_scale)[:n_channels]
            self._rf_guard = SegmentGuard(limits, decoder.slot_samples)
            self.awg_config = config
            self.n_channels = int(n_channels)
            self.sample_rate_hz = float(sample_rate_hz)
            self.decoder = decoder
            self._segments: list[_Segment | None] = [None] * config.n_segments
            self._steps: list[StepInfo | None] = [None] * config.n_steps
            self._pending: list[tuple[float, int, _Segment | StepInfo]] = []  # (t_effective, index, segment or step)
            self._log: deque[PlayRecord] = deque(maxlen=LOG_LENGTH)
            self._running = False
            self._pass_segment = -1
            self._pass_index = 0  # passes of the current step's segment (1 on entering a step)
            self._fault: str | None = None
            self._last_trigger_s: float | None = None
            self._dma_free_s = -math.inf  # when the DMA engine finishes the uploads queued so far
            # passes played but not yet applied to the world: (segment, first pass's start s, first slot, end
            # slot, passes, whether the first of them begins its step's visit); see the module docstring
            self._played: deque[tuple[_Segment, float, int, int, int, bool]] = deque()

    def set_system_config(self, config: SystemConfig) -> None:
        """Adopt a new system configuration (array, tones, waveforms) and reconfigure the card."""
        with self._lock:
            self.system = config
            n_ch = 1 if config.array.trap_source == "aod" else 2
            self.configure(config.awg, n_channels=n_ch, sample_rate_hz=config.waveforms.sample_rate_hz)

    # --- protocol: memory writes -----------------------------------------------------------------------

    def write_segment(self, index: int, samples: np.ndarray) -> None:
        """Upload ``samples`` into segment ``index`` and wait until they are in card memory."""
        self.start_upload(index, samples)
        self.wait_upload(timeout_s=math.inf)

    def start_upload(self, index: int, samples: np.ndarray) -> None:
        """Queue a DMA of ``samples`` into segment ``index`` and return at once (one DMA engine: uploads run
        one after another). The data count from when the transfer completes; ``wait_upload`` waits for it."""
        with self._card():
            self._sync(world=False)
            self._check_segment(index, samples)
            if self.fail_next_upload or self.fail_uploads:
                self.fail_next_upload = False
                raise DeviceError(
                    f"sim AWG: injected upload failure (segment {index}): the DMA transfer was refused"
                )
            now = self.clock.now_s()
            t_begin = max(now, self._dma_free_s)
            seg = _Segment(samples.copy(), t_begin, t_begin)
            if self.clock.mode == "realtime":
                self._decoded(seg)
            cost = (
                samples.nbytes / self.awg_config.upload_bytes_per_s
                + abs(float(self.rng.normal(0.0, self.awg_config.upload_jitter_s)))
                + self.upload_delay_s
            )
            seg.t_ready_s = t_begin + cost
            self._dma_free_s = seg.t_ready_s
            self._queue(seg.t_ready_s, index, seg)
            self.uploads += 1
            self.bytes_uploaded += samples.nbytes

    def wait_upload(self, *, timeout_s: float) -> None:
        """Block (in clock time) until every queued upload is in card memory."""
        with self._card():
            now = self.clock.now_s()
            if self._dma_free_s <= now:
                return
            if self._dma_free_s - now > timeout_s:
                self.clock.advance(timeout_s)
                raise DeviceError(
                    f"sim AWG: upload still running after {timeout_s:g} s; "
                    "check upload_bytes_per_s and the segment size"
                )
            self.clock.advance_to(self._dma_free_s)
            self._sync(world=False)

    def _queue(self, t_effective_s: float, index: int, value: _Segment | StepInfo) -> None:
        """Add a memory write that takes effect at ``t_effective_s``, keeping ``_pending`` in time order."""
        pos = len(self._pending)
        while pos and self._pending[pos - 1][0] > t_effective_s:
            pos -= 1
        self._pending.insert(pos, (t_effective_s, index, value))

    def _check_segment(self, index: int, samples: np.ndarray) -> None:
        problem = card_rules.segment_samples_problem(index, samples, len(self._segments), self.n_channels)
        if problem is not None:
            raise DeviceError(f"sim AWG: {problem}")
        problem = card_rules.segment_length_problem(samples.shape[0], self.n_channels)
        if problem is not None:  # the card's rules (engine/card_rules.py): refuse what the card refuses
            raise DeviceError(f"sim AWG: segment {index}: {problem}; the Spectrum card would refuse it")
        problem = self._rf_guard.problem(samples)
        if problem is not None:
            raise DeviceError(f"sim AWG: segment {index} refused by the RF limits: {problem}")
        if self._running and self._pass_segment == index:
            raise DeviceError(
                f"sim AWG: segment {index} is playing right now (step {self._step}); it cannot be written"
            )
        used = sum(s.data.nbytes for i, s in enumerate(self._latest_segments()) if s is not None and i != index)
        if used + samples.nbytes > self.awg_config.max_memory_bytes:
            raise DeviceError(
                f"sim AWG: segment {index} ({samples.nbytes} B) does not fit: {used} B of "
                f"{self.awg_config.max_memory_bytes} B already used"
            )

    def write_step(self, index: int, step: StepInfo) -> None:
        with self._card():
            self._sync(world=False)
            problem = card_rules.step_problem(
                index, step.segment, step.next_step, step.loops, len(self._steps), len(self._segments)
            )
            if problem is not None:
                raise DeviceError(f"sim AWG: {problem}")
            cost = self.awg_config.step_write_s + self.step_write_delay_s
            t_eff = self.clock.now_s() + cost
            self.clock.advance(cost)
            self._queue(t_eff, index, step)

    # --- protocol: playback ----------------------------------------------------------------------------

    def start(self, entry_step: int) -> None:
        with self._card():
            self._sync()
            self._commit_pending(math.inf)  # the card starts from memory as written
            if not 0 <= entry_step < len(self._steps) or self._steps[entry_step] is None:
                raise DeviceError(f"sim AWG: cannot start at step {entry_step}: it was never written")
            now = self.clock.now_s()
            self._running = True
            self._fault = None
            self._enter(entry_step, now)

    def stop(self) -> None:
        with self._card():
            if self._running:
                self._sync()
            self._running = False

    def current_step(self) -> int:
        """The step playing now, or -1 when stopped."""
        with self._card():
            self._sync(world=False)
            return self._step if self._running else -1

    def wait_for_step(self, step: int, *, timeout_s: float) -> None:
        with self._card():
            self._sync()
            if not self._running:
                raise DeviceError(f"sim AWG: waiting for step {step} but playback is stopped")
            if self._step == step:
                return
            now = self.clock.now_s()
            t_hit = self._advance(now + timeout_s, stop_at_step=step)
            if t_hit is None:
                self.clock.advance_to(now + timeout_s)
                self._raise_fault()
                raise DeviceError(
                    f"sim AWG: step {step} not reached within {timeout_s:g} s (playing step {self._step}); "
                    "check the step table's next pointers"
                )
            self.clock.advance_to(t_hit)
            self._apply_played()
            self._raise_fault()

    def pulse(self, line: str) -> None:
        """Record a pulse on an async output line ('camera' or 'resume') at the current time."""
        with self._card():
            if line not in ("camera", "resume"):
                raise DeviceError(f"sim AWG: unknown pulse line {line!r}; use 'camera' or 'resume'")
            self._sync()
            self.pulses.append((line, self.clock.now_s()))

    def force_trigger(self) -> None:
        """A trigger event now (the sequencer's line): an ``on_trigger`` step that is waiting ends its loop
        after the current pass, and ``wait_trigger`` returns True."""
        with self._card():
            self._sync()
            self._last_trigger_s = self.clock.now_s()
        self._trigger_in.set()

    def wait_trigger(self, *, timeout_s: float) -> bool:
        """Wait (wall time: triggers come from outside) up to ``timeout_s`` for a trigger since the last one
        taken; True if one came, and it is taken."""
        fired = self._trigger_in.wait(timeout_s)
        self._trigger_in.clear()
        return fired

    def sync(self) -> None:
        """Bring playback and the world up to the clock's now."""
        with self._lock:
            self._sync()

    # --- inspection ------------------------------------------------------------------------------------

    def played_steps(self) -> list[PlayRecord]:
        """The latest ``LOG_LENGTH`` step visits (after syncing), oldest first."""
        with self._lock:
            self._sync()
            return list(self._log)

    def count_plays(self, step_indices: Iterable[int]) -> int:
        """How many visits were to any of ``step_indices`` (e.g. the failsafe steps: the underrun count)."""
        wanted = set(step_indices)
        return sum(1 for rec in self.played_steps() if rec.step in wanted)

    def clear_log(self) -> None:
        with self._lock:
            self._sync()
            last = self._log[-1] if self._running and self._log else None
            self._log.clear()
            if last is not None:
                self._log.append(last)

    def segment_samples(self, index: int) -> np.ndarray | None:
        """The samples in segment ``index`` as the card holds them now (read-only)."""
        with self._lock:
            self._sync()
            seg = self._segments[index]
            if seg is None:
                return None
            view = seg.data.view()
            view.flags.writeable = False
            return view

    # --- internals -------------------------------------------------------------------------------------

    @contextmanager
    def _card(self) -> Iterator[None]:
        """One protocol call: the card's lock, and the clock frozen while the simulator computes (checks,
        copies, decoding, replay), so only the modelled device times (``clock.advance``) count as card time."""
        with self._lock, self.clock.paused():
            yield

    def _latest_segments(self) -> list[_Segment | None]:
        latest = list(self._segments)
        for _, index, value in self._pending:
            if isinstance(value, _Segment):
                latest[index] = value
        return latest

    def _raise_fault(self) -> None:
        if self._fault is not None:
            msg = self._fault
            self._fault = None
            raise DeviceError(msg)

    def _sync(self, *, world: bool = True) -> None:
        """Advance playback to the clock's now; with ``world``, also apply what was played to the world."""
        now = self.clock.now_s()
        with self.clock.paused():  # replaying playback into the world is the simulator's work, not the card's
            if self._running:
                self._advance(now)
            else:
                self._commit_pending(now)
            if world:
                self._apply_played()
                self.world.elapse_to(now)
        if self._running:
            self._raise_fault()

    def _apply_played(self) -> None:
        """Decode the passes played since the last call and move the world's atoms slot by slot, at the time
        each slot starts; a repeated pass of a segment that changes nothing (every tone steady) moves nothing."""
        slot_s = self.decoder.slot_s
        while self._played:
            seg, t0, first_slot, end_slot, passes, visit_start = self._played.popleft()
            dec = self._decoded(seg)
            if dec.stationary and not visit_start:
                continue
            dur = seg.data.shape[0] / self.sample_rate_hz
            for p in range(passes):
                t_pass = t0 + p * dur
                for i in range(first_slot, min(end_slot, dec.n_slots)):
                    self.world.elapse_to(t_pass + i * slot_s)
                    self.world.apply_slot(*dec.slot(i))

    def _commit_pending(self, t_s: float) -> None:
        """Apply memory writes that have taken effect by ``t_s`` (they are in time order)."""
        n = 0
        for t_eff, index, value in self._pending:
            if t_eff > t_s:
                break
            if isinstance(value, _Segment):
                self._segments[index] = value
            else:
                self._steps[index] = value
            n += 1
        if n:
            del self._pending[:n]

    def _decoded(self, seg: _Segment) -> DecodedSegment:
        if seg.decoded is None:
            seg.decoded = self.decoder.decode(seg.data)
        return seg.decoded

    def _enter(self, step: int, t_s: float) -> None:
        """Begin a visit to ``step`` at ``t_s``."""
        self._step = step
        self._visit_t0 = t_s
        self._log.append(PlayRecord(step=step, segment=-1, t_start_s=t_s, repeats=0))
        self._begin_pass(t_s, first=True)

    def _begin_pass(self, t_s: float, *, first: bool) -> None:
        info = self._steps[self._step]
        if info is None:
            self._fault = f"sim AWG: playback reached step {self._step}, which was never written; stopped"
            self._running = False
            return
        seg = self._segments[info.segment]
        if seg is None:
            self._fault = f"sim AWG: step {self._step} plays segment {info.segment}, which holds no data; stopped"
            self._running = False
            return
        for t_eff, index, value in self._pending:
            if isinstance(value, _Segment) and index == info.segment and value.t_begin_s <= t_s < t_eff:
                self.torn_plays += 1
        rec = self._log[-1]
        rec.segment = info.segment
        rec.repeats += 1
        self._pass_t0 = t_s
        self._pass_seg = seg
        self._pass_segment = info.segment
        self._pass_index = 1 if first else self._pass_index + 1
        self._pass_first = first
        self._slot_done = 0

    def _pass_duration(self) -> float:
        return self._pass_seg.data.shape[0] / self.sample_rate_hz

    def _play_slots(self, t_until: float) -> None:
        """Queue the slots of the current pass that have ended by ``t_until`` for the world (``_played``)."""
        n_slots = self._pass_seg.data.shape[0] // self.decoder.slot_samples
        slot_s = self.decoder.slot_s
        done = self._slot_done
        while done < n_slots and self._pass_t0 + (done + 1) * slot_s <= t_until:  # as the pass's end is computed
            done += 1
        if done > self._slot_done:
            self._played.append((self._pass_seg, self._pass_t0, self._slot_done, done, 1, self._pass_first))
            self._slot_done = done

    def _advance(self, t_until: float, stop_at_step: int | None = None) -> float | None:
        """Play until ``t_until``; with ``stop_at_step``, stop when that step is entered and return the time."""
        while self._running:
            dur = self._pass_duration()
            t_end = self._pass_t0 + dur
            self._play_slots(min(t_until, t_end))
            if t_end > t_until:
                return None
            self._commit_pending(t_end)
            info = self._steps[self._step]
            assert info is not None
            repeat = self._pass_index < info.loops
            if not repeat and info.on_trigger:
                trig = self._last_trigger_s
                if trig is not None and self._visit_t0 <= trig <= t_end:
                    self._last_trigger_s = None
                else:
                    repeat = True
            if repeat or info.next_step == self._step:
                self._fast_forward(t_end, t_until, dur)
                if not self._running:
                    return None
                continue
            self._enter(info.next_step, t_end)
            if stop_at_step is not None and info.next_step == stop_at_step and self._running:
                return t_end
        return None

    def _fast_forward(self, t_end: float, t_until: float, dur: float) -> None:
        """Start the next pass of the same step at ``t_end``, skipping whole steady passes up to the horizon."""
        info = self._steps[self._step]
        assert info is not None
        seg = self._segments[info.segment]
        skip = 0
        steady_loop = info.next_step == self._step or info.on_trigger
        if seg is self._pass_seg and seg is not None and steady_loop and dur > 0:
            horizon = t_until
            if self._pending:
                horizon = min(horizon, self._pending[0][0])
            if info.next_step != self._step:
                # a trigger wait: only while the loop count is spent and no trigger is latched for this visit
                trig = self._last_trigger_s
                latched = trig is not None and self._visit_t0 <= trig
                if self._pass_index < info.loops or latched:
                    horizon = t_end
            skip = max(0, int((horizon - t_end) // dur) - 1)
        if skip:  # whole passes of the same data (the pass's own): one entry (a steady one moves nothing)
            n_slots = self._pass_seg.data.shape[0] // self.decoder.slot_samples
            self._played.append((self._pass_seg, t_end, 0, n_slots, skip, False))
            self._log[-1].repeats += skip
            self._pass_index += skip
            t_end += skip * dur
        self._begin_pass(t_end, first=False)
