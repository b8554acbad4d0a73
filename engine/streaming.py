"""Module V: play a plan's waveform slots on a sequence-mode AWG without ever leaving the atoms untrapped.

Memory layout (segments and steps of the card, fixed when a configuration is applied)::

    segment 0            idle: the hold waveform (static tones of a chain, silence for SLM traps)
    segments 1..K        control segments: the first two ``waveforms_per_segment`` slots each, then each
                         ``segment_growth`` times the one before, up to ``max_waveforms_per_segment``
    segments K+1..2K     failsafe segments: the tones where the paired control segment leaves them, steady
    segment 2K+1         the short-path segment (up to two control segments' worth of slots)

    step 0               idle A, loops the hold waveform on itself until the host points it at a plan
    step 2j+1            control step j  -> next: its failsafe step (until the next segment is uploaded)
    step 2j+2            failsafe step j -> loops on itself (until the host points it at the next control step)
    step 2K+1            the short-path step
    step 2K+2            idle B, the same hold waveform looping on itself

The card rests in one of the two idle steps (the *home* step). A plan ends in the *other* one, which
already loops on itself, so the end of a plan never races the host: with a single idle step the host must
re-point it at itself before the plan's last slot plays, or a slow host makes the card play the plan twice.
The next cycle starts from wherever the last one ended (ping-pong). The card divides its memory into equal
parts, one per segment, so the largest control segment must fit one part (checked at construction).

A cycle uploads control segments 0 and 1 (and renders segment 2 under segment 1's DMA), then points home at
control step 0: that is the latency. From then on the host uploads segment after segment as fast as the DMA
goes: for segment k it uploads the failsafe (one slot; in memory before anything can lead to it), starts
the DMA, and while it runs writes segment k's two steps (nothing leads to them yet) and renders segment
k+1. After the DMA only the *link* remains: control step k-1 pointed at k, and one read of the card's step.
If the host was late, the card has fallen into failsafe k-1, which holds the mobile tweezers where that
segment left them (a pause, not a loss); the host then points the failsafe at k too, at once, and counts an
underrun. Otherwise the failsafe's pointer is written during the next DMA (the card can no longer reach it).
Each report lists, per underrun, how many slots had played (``failsafe_after_slots``); after playback the
engine replays them through the move model to record which atoms the failsafe held (``CycleRecord.in_flight``).
Plans of at most two segments' worth of slots take the short path: one upload, one pointer, no failsafe
needed. Segments are written at their exact length (no padding to whole segments), so a 20-slot plan
streams in 20 slots, not 64.

**The worst case, not the mean.** Once playback starts, the host must link segment k before the card
finishes segment k-1. The DMA is the bottleneck (a 32-slot two-channel segment of 10 us slots uploads in
~254 us of its 320 us playback at the modelled 1.58 GB/s), so the host gains at most the DMA's spare fifth of
each segment's playback, less the fixed work per segment (failsafe upload, link, the step read, upload
jitter), on top of the lead it starts with: the two segments uploaded before the start (640 us). That lead
costs latency (every segment uploaded ahead costs its DMA before the first slot plays), which is why the first
two segments stay at ``waveforms_per_segment``. Growing later segments (``segment_growth`` > 1) spreads the
fixed work over more playback and lets one layout hold longer plans, but it does not deepen the lead: a
segment is linked only once its whole DMA is done, so a segment g times the size of the one before leaves
the host (1 - 0.79 g) of the previous segment's playback instead of 0.21, and doubling underruns even in
replayed time (``tests/test_streaming_adaptive.py``). Measured on the simulated card, growth only lowered
the least slack, so the default is 1 (``docs/benchmarks.md``, streaming). What breaks the lead is not a slow
render but a host *stalled* for longer than it: preempted for a scheduler slice (milliseconds, when a
browser or an analysis script shares the engine's core), so the streamer keeps the scheduler away: from the
first render to the plan's last link it runs at real-time priority (``SCHED_FIFO``, ``awg.stream_priority``;
the engine enters the same window when the frame arrives, so detection and planning are covered too), and
drops back to normal priority while the card plays the tail and the engine waits for the camera, so it never
holds the core longer than one plan. Where the OS refuses (no ``CAP_SYS_NICE``/``RLIMIT_RTPRIO``) it streams
at normal priority and says so (``Streamer.realtime_refused``). Each plan's report carries the smallest slack
the host left the card (``min_slack_s``: how long before the card would have reached a failsafe each link
arrived), which ``llrs bench streaming`` reports.

**How much lead a host needs** is what ``llrs bench jitter`` measures: the longest stall at this priority in
each plan-long window, and the lead that fewer than one window in 257 or 1000 exceeds. A longer lead costs
~0.8 us of latency per us (one more segment's DMA before the first slot); on the 2-vCPU development VM the
1.1 ms latency bar leaves ~175 us more lead, while one underrun in 1000 cycles would need 0.6-2.3 ms, so the
lead stays at two segments and the host is what must be quiet (``docs/hardware.md``, "The host").
"""

from __future__ import annotations

import bisect
import os
from dataclasses import dataclass, field

import numpy as np

from engine import card_rules
from engine.aod_limits import SegmentGuard
from engine.card_rules import page_aligned_zeros
from engine.config import SystemConfig
from engine.devices import Clock, SequenceAWG, StepInfo
from engine.operations import Operations
from engine.timing import StageTimer
from engine.waveforms import WaveformBank

__all__ = ["RealtimeScheduling", "SequenceLayout", "StreamReport", "Streamer"]


@dataclass(frozen=True)
class SequenceLayout:
    """Where everything lives in the card's memory (see the module docstring), and how many waveform slots
    each control segment holds (``AWGConfig.control_segment_slots``)."""

    segment_slots: tuple[int, ...]
    idle_segment: int = 0
    idle_step: int = 0
    slot_offsets: tuple[int, ...] = field(init=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "slot_offsets", tuple(int(x) for x in np.cumsum((0, *self.segment_slots))))

    @classmethod
    def for_config(cls, config: SystemConfig) -> SequenceLayout:
        n_control = (config.awg.n_segments - 2) // 2
        if n_control < 2:
            raise ValueError(f"awg.n_segments = {config.awg.n_segments} leaves fewer than 2 control segments")
        layout = cls(segment_slots=config.awg.control_segment_slots(n_control))
        if layout.park_step >= config.awg.n_steps:
            raise ValueError(
                f"the sequence layout needs {layout.park_step + 1} steps but awg.n_steps is {config.awg.n_steps}"
            )
        return layout

    @property
    def n_control(self) -> int:
        return len(self.segment_slots)

    @property
    def max_slots(self) -> int:
        """The longest plan the layout holds (waveform slots)."""
        return self.slot_offsets[-1]

    def segments_for(self, n_slots: int) -> int:
        """How many control segments a plan of ``n_slots`` fills (the last one partly)."""
        return bisect.bisect_left(self.slot_offsets, n_slots)

    def segment_span(self, k: int, n_slots: int) -> tuple[int, int]:
        """The first slot of control segment k in a plan of ``n_slots``, and how many slots it holds."""
        first = self.slot_offsets[k]
        return first, min(self.segment_slots[k], n_slots - first)

    def control_segment(self, k: int) -> int:
        return 1 + k

    def failsafe_segment(self, k: int) -> int:
        return 1 + self.n_control + k

    @property
    def short_segment(self) -> int:
        return 1 + 2 * self.n_control

    def control_step(self, k: int) -> int:
        return 1 + 2 * k

    def failsafe_step(self, k: int) -> int:
        return 2 + 2 * k

    @property
    def short_step(self) -> int:
        return 1 + 2 * self.n_control

    @property
    def park_step(self) -> int:
        """Idle B: the second hold step (see the module docstring)."""
        return 2 + 2 * self.n_control

    def is_idle_step(self, step: int) -> bool:
        return step in (self.idle_step, self.park_step)

    def is_failsafe_step(self, step: int) -> bool:
        return 2 <= step <= 2 * self.n_control and step % 2 == 0

    def slots_before_failsafe(self, step: int) -> int:
        """How many of a plan's slots the card has played when it loops failsafe ``step``: all of control
        segments 0..j, where j is the segment the failsafe holds (every segment but the last is full)."""
        if not self.is_failsafe_step(step):
            raise ValueError(f"step {step} is not a failsafe step of this layout")
        return self.slot_offsets[step // 2]


@dataclass
class StreamReport:
    """What happened while one plan streamed."""

    n_slots: int = 0
    n_segments: int = 0
    short_path: bool = False
    underruns: int = 0
    latency_s: float = 0.0  # from the start of rendering to the pointer that starts playback
    t_started_s: float = 0.0  # clock time of that pointer write
    # the least time (s) any link of segment k arrived before the card, playing without pause, would have
    # finished segment k-1 and fallen into its failsafe (negative: it did); inf for the short path
    min_slack_s: float = float("inf")
    max_upload_s: float = 0.0  # the longest wait for one segment's DMA after its render (s)
    # per underrun, the slots the card had played when it fell into a failsafe (the end of the control segment
    # whose failsafe it loops): what the shot record replays to name the atoms that were in flight
    failsafe_after_slots: list[int] = field(default_factory=list)


class RealtimeScheduling:
    """Switch the calling thread between real-time (``SCHED_FIFO`` at ``priority``) and normal scheduling.

    Probed once at construction: if the OS refuses (no privilege, or not Linux), ``refused`` says why and
    ``enter``/``leave`` do nothing. ``priority`` 0 turns it off."""

    def __init__(self, priority: int) -> None:
        self.priority = priority
        self.refused: str | None = None
        self._active = False
        if priority == 0:
            self.refused = "awg.stream_priority is 0"
        elif not hasattr(os, "sched_setscheduler"):
            self.refused = "this OS has no sched_setscheduler"
        else:
            try:
                self.enter()
                self.leave()
            except OSError as err:
                self.refused = f"SCHED_FIFO at priority {priority} refused ({err}); grant CAP_SYS_NICE or RLIMIT_RTPRIO"

    def enter(self) -> None:
        if self.refused is None and not self._active:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(self.priority))
            self._active = True

    def leave(self) -> None:
        if self._active:
            os.sched_setscheduler(0, os.SCHED_OTHER, os.sched_param(0))
            self._active = False


class Streamer:
    """Streams ``Operations`` to a ``SequenceAWG`` through a ``WaveformBank``; buffers sized at construction."""

    def __init__(self, config: SystemConfig, bank: WaveformBank, awg: SequenceAWG, clock: Clock) -> None:
        self.bank = bank
        self.awg = awg
        self.clock = clock
        self.layout = SequenceLayout.for_config(config)
        self.slots_per_segment = config.awg.waveforms_per_segment  # of the first two segments and the short path
        self.timeout_s = 1.0
        self.home = self.layout.idle_step  # the idle step the card rests in between plans
        self.realtime = RealtimeScheduling(config.awg.stream_priority)
        slot = bank.slot_samples
        ch = bank.n_channels
        largest = max(self.layout.segment_slots)
        # two segment buffers: the host renders segment k+1 into one while the card's DMA reads segment k;
        # page-aligned, so the card's DMA reads them in place (engine/card_rules.py)
        self._segment_bufs = [page_aligned_zeros((largest * slot, ch), np.int16) for _ in range(2)]
        self._short_buf = page_aligned_zeros((2 * self.slots_per_segment * slot, ch), np.int16)
        self._failsafe_buf = page_aligned_zeros((slot, ch), np.int16)
        self._keys = np.zeros(bank.max_keys(max(2 * self.slots_per_segment, largest)), dtype=np.int64)
        self._rf_guard = SegmentGuard(config.channel_limits(), slot)
        # idle + K control + K failsafe + the short-path segment, at their largest
        slot_bytes = self._failsafe_buf.nbytes
        total = slot_bytes * (1 + self.layout.max_slots + self.layout.n_control + 2 * self.slots_per_segment)
        if total > config.awg.max_memory_bytes:
            raise ValueError(
                f"the sequence layout needs {total / 2**20:.0f} MiB of AWG memory but awg.max_memory_bytes is "
                f"{config.awg.max_memory_bytes / 2**20:.0f} MiB; lower awg.n_segments, waveforms_per_segment or "
                "max_waveforms_per_segment"
            )
        # the card splits its memory into equal parts, one per segment: the longest segment must fit one
        longest = max(largest, 2 * self.slots_per_segment) * slot
        fits = card_rules.max_segment_samples(config.awg.max_memory_bytes, ch, config.awg.n_segments)
        if longest > fits:
            raise ValueError(
                f"the longest segment of the layout ({longest} samples per channel) is longer than one of the "
                f"{card_rules.segment_partition(config.awg.n_segments)} equal parts the card divides its "
                f"{config.awg.max_memory_bytes / 2**20:.0f} MiB into ({fits} samples); lower "
                "awg.max_waveforms_per_segment (or waveforms_per_segment) or awg.n_segments"
            )

    @property
    def realtime_refused(self) -> str | None:
        """Why plans stream at normal priority (``None``: they stream at real-time priority)."""
        return self.realtime.refused

    @property
    def max_slots(self) -> int:
        return self.layout.max_slots

    def program_idle(self) -> None:
        """Upload the hold waveform and make both idle steps loop on it (done when a configuration is applied)."""
        lay = self.layout
        self.awg.write_segment(lay.idle_segment, self.bank.hold())
        self.rest()
        self.home = lay.idle_step

    def rest(self) -> None:
        """Make both idle steps loop on themselves: wherever the card is now, it ends up holding the atoms."""
        lay = self.layout
        for step in (lay.idle_step, lay.park_step):
            self.awg.write_step(step, StepInfo(segment=lay.idle_segment, next_step=step))

    def recover(self) -> None:
        """Before a cycle: find the card at rest, or (after a fault left it in a failsafe loop) restart it at idle."""
        lay = self.layout
        step = self.awg.current_step()
        if lay.is_idle_step(step):
            self.home = step
            return
        self.awg.stop()
        self.rest()
        self.awg.start(lay.idle_step)
        self.home = lay.idle_step

    @property
    def away(self) -> int:
        """The idle step the next plan ends in: the one the card is not resting in."""
        lay = self.layout
        return lay.park_step if self.home == lay.idle_step else lay.idle_step

    def stream(self, ops: Operations, timer: StageTimer | None = None) -> StreamReport:
        """Play every slot of ``ops`` and return once the card rests in an idle step again."""
        n = len(ops)
        report = StreamReport(n_slots=n)
        if n == 0:
            return report
        if n > self.max_slots:
            raise ValueError(
                f"the plan has {n} waveform slots but the AWG layout holds at most {self.max_slots} "
                f"({self.layout.n_control} control segments of {self.slots_per_segment} to "
                f"{max(self.layout.segment_slots)} slots); raise awg.n_segments, awg.segment_growth or "
                "awg.max_waveforms_per_segment"
            )
        self.realtime.enter()
        try:
            if n <= 2 * self.slots_per_segment:
                self._stream_short(ops, report, timer)
            else:
                self._stream_segments(ops, report, timer)
        finally:
            self.realtime.leave()
        return report

    def rehearse(self, ops: Operations) -> None:
        """Look up and render the first segment of ``ops`` into a scratch buffer and drop it (cache warm-up
        while the camera exposes; see ``Engine._rehearse``). Touches no device."""
        count = min(len(ops), self.slots_per_segment)
        if count:
            self.bank.lookup(ops, 0, count, self._keys)
            self.bank.render(0, count, self._segment_bufs[1])

    def _lookup_and_render(
        self, ops: Operations, first: int, count: int, out: np.ndarray, timer: StageTimer | None
    ) -> None:
        self.bank.lookup(ops, first, count, self._keys)
        if timer is not None:
            timer.lap("IV.lookup")
        self.bank.render(first, count, out)
        self._rf_guard.check(out[: count * self.bank.slot_samples])  # before any upload: refuse, saying why
        if timer is not None:
            timer.lap("IV.render")

    def _start(self, step: int, report: StreamReport, t0: float) -> None:
        """Make the plan's end step loop on itself, then point home at the plan's first step."""
        lay = self.layout
        self.awg.write_step(self.away, StepInfo(segment=lay.idle_segment, next_step=self.away))
        self.awg.write_step(self.home, StepInfo(segment=lay.idle_segment, next_step=step))
        report.t_started_s = self.clock.now_s()
        report.latency_s = report.t_started_s - t0

    def _finish(self, n_slots: int) -> None:
        """Wait (at normal priority: everything is linked) until the card rests in the plan's end step, which
        becomes home."""
        self.realtime.leave()
        away = self.away
        self.awg.wait_for_step(away, timeout_s=self.timeout_s + n_slots * self._slot_s())
        self.home = away

    def _stream_short(self, ops: Operations, report: StreamReport, timer: StageTimer | None) -> None:
        lay = self.layout
        n = len(ops)
        samples = n * self.bank.slot_samples
        t0 = self.clock.now_s()
        if timer is not None:
            timer.start()
        self._lookup_and_render(ops, 0, n, self._short_buf, timer)
        self.awg.write_segment(lay.short_segment, self._short_buf[:samples])
        if timer is not None:
            timer.lap("IV.upload")
        self.awg.write_step(lay.short_step, StepInfo(segment=lay.short_segment, next_step=self.away))
        self._start(lay.short_step, report, t0)
        if timer is not None:
            timer.lap("IV.sequence")
        self._finish(n)
        if timer is not None:
            timer.lap("V.stream")
        report.short_path = True
        report.n_segments = 1

    def _slot_s(self) -> float:
        return self.bank.slot_samples / self.awg.sample_rate_hz

    def _render_segment(self, ops: Operations, k: int, timer: StageTimer | None) -> None:
        """Look up and render control segment k into buffer ``k % 2``, and the failsafe that follows it (the
        tones where its last slot leaves them) into the failsafe buffer (the last segment has none)."""
        first, count = self.layout.segment_span(k, len(ops))
        self._lookup_and_render(ops, first, count, self._segment_bufs[k % 2], timer)
        if first + count < len(ops):
            self.bank.render_failsafe(ops, first + count - 1, self._failsafe_buf)

    def _upload(self, ops: Operations, k: int) -> None:
        """Upload control segment k's failsafe (one slot; it must be in memory before the step that leads to
        it can be reached), start the DMA of control segment k, and, while that runs, write the steps of
        segment k: nothing leads to them until ``_link(k)``, so only the link is left for after the DMA."""
        lay = self.layout
        first, count = lay.segment_span(k, len(ops))
        last = first + count == len(ops)
        if not last:
            self.awg.write_segment(lay.failsafe_segment(k), self._failsafe_buf)
        self.awg.start_upload(lay.control_segment(k), self._segment_bufs[k % 2][: count * self.bank.slot_samples])
        if not last:
            self.awg.write_step(
                lay.failsafe_step(k), StepInfo(segment=lay.failsafe_segment(k), next_step=lay.failsafe_step(k))
            )
        next_step = self.away if last else lay.failsafe_step(k)
        self.awg.write_step(lay.control_step(k), StepInfo(segment=lay.control_segment(k), next_step=next_step))

    def _wait_upload(self, report: StreamReport) -> None:
        t_wait = self.clock.now_s()
        self.awg.wait_upload(timeout_s=self.timeout_s)
        report.max_upload_s = max(report.max_upload_s, self.clock.now_s() - t_wait)

    def _link(self, k: int, report: StreamReport) -> bool:
        """Point control step k-1 at control step k (segment k is in memory), then look where the card is:
        if it has already fallen into failsafe k-1 (an underrun: counted, with the slots it had played),
        point that at k as well at once and return True. Otherwise the card leaves k-1 for k and never sees
        the failsafe, whose pointer ``_link_failsafe`` writes later, off the critical path."""
        lay = self.layout
        self._link_control(k)
        step = self.awg.current_step()
        if not lay.is_failsafe_step(step):
            return False
        report.underruns += 1
        report.failsafe_after_slots.append(lay.slots_before_failsafe(step))
        self._link_failsafe(k)
        return True

    def _link_control(self, k: int) -> None:
        """Point control step k-1 at control step k."""
        lay = self.layout
        self.awg.write_step(
            lay.control_step(k - 1), StepInfo(segment=lay.control_segment(k - 1), next_step=lay.control_step(k))
        )

    def _link_failsafe(self, k: int) -> None:
        """Point failsafe step k-1 at control step k: once the card is in it, it leaves for segment k."""
        lay = self.layout
        self.awg.write_step(
            lay.failsafe_step(k - 1), StepInfo(segment=lay.failsafe_segment(k - 1), next_step=lay.control_step(k))
        )

    def _stream_segments(self, ops: Operations, report: StreamReport, timer: StageTimer | None) -> None:
        """Segments 0 and 1 before playback starts (and segment 2 rendered under segment 1's DMA), then as
        far ahead of the card as the DMA goes; every DMA overlaps the rendering of the next segment."""
        lay = self.layout
        n_segments = lay.segments_for(len(ops))
        report.n_segments = n_segments
        t0 = self.clock.now_s()
        if timer is not None:
            timer.start()
        self._render_segment(ops, 0, timer)
        self._upload(ops, 0)
        if timer is not None:
            timer.lap("IV.upload")
        self._render_segment(ops, 1, timer)  # while segment 0 uploads
        self._wait_upload(report)
        self._upload(ops, 1)
        self._render_segment(ops, 2, None)  # while segment 1 uploads: ready to go when playback starts
        self._wait_upload(report)
        self._link_control(1)  # the card is still at home: no failsafe to look at yet
        self._link_failsafe(1)
        if timer is not None:
            timer.lap("IV.upload")
        self._start(lay.control_step(0), report, t0)
        if timer is not None:
            timer.lap("IV.sequence")
        slot_s = self._slot_s()
        unlinked_failsafe = 0  # the segment whose failsafe pointer is still to write (0: none)
        for k in range(2, n_segments):
            self._upload(ops, k)
            if unlinked_failsafe:  # while segment k uploads
                self._link_failsafe(unlinked_failsafe)
            if k + 1 < n_segments:
                self._render_segment(ops, k + 1, None)
            self._wait_upload(report)
            if report.underruns == 0:  # segments 0..k-1 played without pause: the card leaves k-1 then
                slack_s = report.t_started_s + lay.slot_offsets[k] * slot_s - self.clock.now_s()
                report.min_slack_s = min(report.min_slack_s, slack_s)
            unlinked_failsafe = 0 if self._link(k, report) else k
        if unlinked_failsafe:
            self._link_failsafe(unlinked_failsafe)
        self._finish(len(ops))
        if timer is not None:
            timer.lap("V.stream")
