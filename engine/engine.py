"""The five-module loop: image, detect, solve, synthesize, stream, until the target is defect-free.

``Engine`` runs shots on one device set and owns every buffer the loop touches; they are sized when a
configuration is applied, so a cycle allocates no array. ``EngineThread`` gives the engine its own thread
and a command queue, so a web server or a CLI can drive it without ever blocking the loop.
"""

from __future__ import annotations

import gc
import queue
import threading
from collections.abc import Callable
from concurrent.futures import Future
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from engine import move_model as mm
from engine.config import SystemConfig
from engine.devices import DeviceError, DeviceSet
from engine.host import EngineCommands
from engine.imaging import Detector, calibration_frames
from engine.operations import Operations
from engine.records import CycleRecord, Outcome, ShotRecord, atom_moves, atom_paths, atoms_in_flight
from engine.routing import positions_of, positions_per_site
from engine.solvers import LossWeights, Planner, Solver, UnsolvableError
from engine.streaming import Streamer
from engine.targets import build_target, target_filled
from engine.timing import StageTimer
from engine.waveforms import WaveformBank

__all__ = ["Engine", "EngineThread", "Lab", "ShotWatchdogExpired"]


class Lab(Protocol):
    """What the engine asks of a lab besides its devices, where there is such a lab (the simulated one; on
    hardware there is none: the experiment loads the atoms and nobody reports on them).

    The engine does not know what the lab is: it lets it adopt each configuration, load atoms before each
    shot, stand in for the planner (a lab may inject planner faults), and carries what it reports after a
    shot, unread, in ``ShotRecord.lab_report``.
    """

    def configure(self, config: SystemConfig) -> None:
        """Adopt a configuration the engine is applying (array, loss model, injected faults)."""
        ...

    def planner(self, planner: Planner, config: SystemConfig) -> Planner:
        """The planner the engine is to use under ``config``: ``planner`` itself, or one the lab puts in its place."""
        ...

    def prepare_shot(self) -> None: ...

    def shot_report(self, target: np.ndarray) -> dict[str, Any]:
        """After a shot: what the lab has to say about it (JSON-ready; ``target`` is the shot's ``bool[ny, nx]``)."""
        ...

    def cycle_reports(self, n_cycles: int) -> list[dict[str, Any]]:
        """After a shot: what the lab has to say about each of its ``n_cycles`` cycles (JSON-ready, one dict per
        cycle), carried unread in ``CycleRecord.lab_report``. Asked once the shot is over, never during a cycle."""
        ...


def _slot_table(ops: Operations) -> tuple[np.ndarray, ...]:
    """A copy of a plan's slots (kind, y sites and deltas, x sites and deltas): ~30 us for a 32x64 plan, so the
    cycle keeps it and the pick-ups are counted after the shot, not before the next image."""
    n = len(ops)
    return tuple(a[:n].copy() for a in (ops.kind, ops.y_site, ops.y_delta, ops.x_site, ops.x_delta))


def _pickups(slots: tuple[np.ndarray, ...], occupancy: np.ndarray, *, chain: bool, half: int = 1) -> int:
    """Atoms the plan takes into a tweezer (extracts and captures; an atom taken twice counts twice): its slots
    played through the move model (losses off, no atom identities) from the detected ``occupancy``. The
    validator's replay counts the same but checks every slot's grammar in Python, ~35 ms for a 32x64 plan, longer
    than the plan plays; this is the numba kernel alone. ``half``: positions per site of the plan's slots
    (``engine.routing``; 2 under interstitial routing)."""
    kind, y_site, y_delta, x_site, x_delta = slots
    state = mm.MoveState(y_site.shape[1], x_site.shape[1])
    state.load(positions_of(occupancy, half))
    events = mm.new_events()
    mm.replay_operations(
        kind, y_site, y_delta, x_site, x_delta, 0, len(kind), chain, half,
        state.static, state.held, state.held_mark, state.ids, state.atom_stats, False, state.arrivals,
        state.tweezers, state.chain_scratch, state.y_tracks, state.x_tracks, events, False, False,
    )  # fmt: skip
    return int(events[mm.EV_PICKED] + events[mm.EV_CAPTURED])


class ShotWatchdogExpired(RuntimeError):
    """A shot ran past its watchdog (``Engine.shot_watchdog_s``): it ends as a fault with the atoms held."""


def _solver(config: SystemConfig) -> Solver:
    """Module III as configured: the planner (or bulk + repair strategy); the survival objective weighs moves by
    the configured loss model (``sim.survival_*``, ``sim.vacuum_lifetime_s``) at ``waveforms.slot_duration_s``."""
    sim, strategy = config.sim, config.solver.strategy
    loss = LossWeights(
        survival_transfer=sim.survival_transfer,
        survival_step=sim.survival_step,
        slot_duration_s=config.waveforms.slot_duration_s,
        vacuum_lifetime_s=sim.vacuum_lifetime_s,
    )
    return Solver(
        nx=config.array.nx, ny=config.array.ny, algorithm=config.solver.algorithm,
        trap_source=config.array.trap_source, objective=config.solver.objective, loss=loss,
        repair_algorithm=None if strategy is None else strategy.repair,
        repair_at_defects=0 if strategy is None else strategy.repair_at_defects, routing=config.array.routing,
    )  # fmt: skip


@dataclass
class _Pipeline:
    """Everything built from one configuration; swapped in whole so a bad config never half-applies."""

    config: SystemConfig
    target: np.ndarray
    detector: Detector
    solver: Planner
    bank: WaveformBank
    streamer: Streamer
    image: np.ndarray
    occupancy: np.ndarray
    scratch_occupancy: np.ndarray  # the rehearsal's detection goes here, never into ``occupancy``
    history: np.ndarray  # bool[max_cycles + 1, ny, nx]
    timer: StageTimer
    counts_history: np.ndarray  # float32[max_cycles + 1, n_traps]: each cycle's PSF-weighted counts
    steps_history: list[np.ndarray | None]  # each cycle's plan steps, copied once its playback has started
    slots_history: list[tuple[np.ndarray, ...] | None]  # each cycle's plan slots, for the pick-ups after the shot
    in_flight_history: list[list[list[list[int]]]]  # per cycle, per underrun: the atoms its failsafe held
    kept_frames: np.ndarray | None = None  # uint16[max_cycles + 1, h, w] this shot's frames (loop.keep_frames)
    frames_read: int = 0  # cycles of this shot whose frame has arrived


class Engine:
    """Runs shots. Not thread-safe: one thread owns it (see ``EngineThread``)."""

    def __init__(self, config: SystemConfig, devices: DeviceSet, *, lab: Lab | None = None) -> None:
        self.devices = devices
        self.lab = lab
        self.shots_done = 0
        self._p: _Pipeline | None = None
        self.apply(config)

    @property
    def config(self) -> SystemConfig:
        assert self._p is not None
        return self._p.config

    @property
    def target(self) -> np.ndarray:
        assert self._p is not None
        return self._p.target

    def apply(self, config: SystemConfig) -> None:
        """Build the pipeline for ``config``, compile every kernel, then program the devices.

        If anything fails the previous configuration stays in force and the error propagates.
        """
        dev = self.devices
        arr = config.array
        target = build_target(config.target, nx=arr.nx, ny=arr.ny)
        bank = WaveformBank(config)
        pipeline = _Pipeline(
            config=config,
            target=target,
            detector=Detector(config),
            solver=_solver(config),
            bank=bank,
            streamer=Streamer(config, bank, dev.awg, dev.clock),
            image=np.zeros(dev.camera.frame_shape, dtype=np.uint16),
            occupancy=np.zeros((arr.ny, arr.nx), dtype=bool),
            scratch_occupancy=np.zeros((arr.ny, arr.nx), dtype=bool),
            history=np.zeros((config.loop.max_cycles + 1, arr.ny, arr.nx), dtype=bool),
            timer=StageTimer(dev.clock.now_s, config.loop.max_cycles + 1, charge=getattr(dev.clock, "charge", None)),
            counts_history=np.zeros((config.loop.max_cycles + 1, arr.n_traps), dtype=np.float32),
            steps_history=[None] * (config.loop.max_cycles + 1),
            slots_history=[None] * (config.loop.max_cycles + 1),
            in_flight_history=[[] for _ in range(config.loop.max_cycles + 1)],
        )
        pipeline.solver.check_target(target)
        target_filled(pipeline.occupancy, target)  # compile (or load) before the engine reports ready
        if self.lab is not None:
            pipeline.solver = self.lab.planner(pipeline.solver, config)
        try:
            self._program_devices(pipeline)
            running = self._p.detector if self._p is not None else None
            if not pipeline.detector.has_thresholds and not pipeline.detector.keep_calibration(running):
                # imaging.threshold: null, and the camera or the imaging changed: calibrate from frames now
                pipeline.detector.calibrate(self._acquire(pipeline, calibration_frames(arr.n_traps)))
        except Exception:
            if self._p is not None:  # put the devices back the way the running configuration wants them
                self._program_devices(self._p)
            raise
        self._p = pipeline

    def _program_devices(self, pipeline: _Pipeline) -> None:
        dev = self.devices
        config = pipeline.config
        if self.lab is not None:
            self.lab.configure(config)
        dev.camera.configure(config.camera)
        if dev.camera.frame_shape != pipeline.image.shape:
            pipeline.image = np.zeros(dev.camera.frame_shape, dtype=np.uint16)
        dev.awg.stop()
        dev.awg.configure(
            config.awg, n_channels=pipeline.bank.n_channels, sample_rate_hz=config.waveforms.sample_rate_hz
        )
        pipeline.streamer.program_idle()
        dev.awg.start(pipeline.streamer.layout.idle_step)

    def shot_watchdog_s(self) -> float:
        """How long a shot may run before it is ended as a fault: ``loop.watchdog_factor`` times the longest a
        healthy shot takes (each cycle: an exposure, a frame read up to ``camera.timeout_s``, and the longest
        plan the AWG layout holds, uploaded and played). Checked after every cycle, so a device that keeps
        being slow (late uploads, a slow camera) cannot hold the engine, and the commands waiting for it, for
        minutes."""
        p = self._p
        assert p is not None
        cfg = p.config
        slot_bytes = 2 * p.bank.slot_samples * p.bank.n_channels
        plan_s = p.streamer.max_slots * (cfg.waveforms.slot_duration_s + slot_bytes / cfg.awg.upload_bytes_per_s)
        cycle_s = cfg.camera.exposure_s + cfg.camera.timeout_s + plan_s
        return cfg.loop.watchdog_factor * (cfg.loop.max_cycles + 1) * cycle_s

    def run_shot(self, shot_id: int | None = None) -> ShotRecord:
        """Run one shot: load (simulated lab), then cycles until success, unsolvable or max_cycles (or a fault,
        the watchdog's included)."""
        p = self._p
        assert p is not None
        watchdog_s = self.shot_watchdog_s()
        shot_id = self.shots_done if shot_id is None else shot_id
        record = ShotRecord(
            shot_id=shot_id, config_digest=p.config.digest(), algorithm=p.config.solver.algorithm, target=p.target
        )
        clock = self.devices.clock
        record.t_start_s = clock.now_s()
        self._back_to_idle(p)
        if self.lab is not None:
            self.lab.prepare_shot()
        p.timer.reset()
        p.steps_history[:] = [None] * len(p.steps_history)
        p.slots_history[:] = [None] * len(p.slots_history)
        p.in_flight_history[:] = [[] for _ in p.in_flight_history]
        p.frames_read = 0
        n_slots = p.config.loop.max_cycles + 1
        p.kept_frames = np.empty((n_slots, *p.image.shape), dtype=np.uint16) if p.config.loop.keep_frames else None
        latencies = np.zeros(p.config.loop.max_cycles + 1)
        cycle_times = np.zeros((p.config.loop.max_cycles + 1, 2))  # cycle began, image in memory (clock s)
        plan_stats = np.zeros((p.config.loop.max_cycles + 1, 4), dtype=np.int64)  # slots, steps, underruns, pick-ups
        planners = [""] * (p.config.loop.max_cycles + 1)  # the planner each cycle used (a strategy switches)
        n_cycles = 0
        gc_was_enabled = gc.isenabled()
        gc.disable()
        try:
            for cycle in range(p.config.loop.max_cycles + 1):
                p.timer.cycle = cycle
                n_cycles = cycle + 1
                try:
                    outcome = self._cycle(p, cycle, latencies, plan_stats, cycle_times, planners)
                finally:
                    p.streamer.realtime.leave()  # a cycle that ends before streaming leaves it here
                if outcome is not None:
                    record.outcome = outcome
                    break
                elapsed_s = clock.now_s() - record.t_start_s
                if elapsed_s > watchdog_s:
                    raise ShotWatchdogExpired(
                        f"watchdog: the shot ran {elapsed_s:.3g} s after {cycle + 1} cycles, over its "
                        f"{watchdog_s:.3g} s limit (loop.watchdog_factor x the longest healthy shot); atoms held"
                    )
        except Exception as err:  # a device, the solver or a bug: the shot ends, the engine lives on
            record.outcome = Outcome.FAULT
            record.fault = f"{type(err).__name__}: {err}"
            self._hold_atoms()
        finally:
            if gc_was_enabled:
                gc.enable()
        record.duration_s = clock.now_s() - record.t_start_s
        # The shot ends here: the lab reads its truth and the sequencer hears the array is ready before the
        # records are built (moves, routes, pick-ups: milliseconds of Python on a bulk plan that would otherwise
        # be vacuum time for every target atom between the last image and the experiment).
        cycle_reports = self.lab.cycle_reports(n_cycles) if self.lab is not None else [{} for _ in range(n_cycles)]
        if self.lab is not None:
            record.lab_report = self.lab.shot_report(p.target)
        try:
            self.devices.awg.pulse("resume")  # tell the lab's sequencer the array is ready
        except DeviceError as err:
            record.fault = record.fault or f"DeviceError: resume pulse: {err}"
        if p.kept_frames is not None and p.frames_read:
            if p.frames_read == n_cycles:  # the last cycle's frame arrived whole (a failed read is not kept)
                p.kept_frames[n_cycles - 1] = p.image
            record.images = list(p.kept_frames[: p.frames_read])
        half = positions_per_site(p.config.array.routing)
        for c in range(n_cycles):
            occ = p.history[c].copy()
            record.cycles.append(
                CycleRecord(
                    index=c,
                    occupancy=occ,
                    atoms=int(occ.sum()),
                    defects=int((p.target & ~occ).sum()),
                    stage_s=p.timer.cycle_dict(c),
                    n_slots=int(plan_stats[c, 0]),
                    n_steps=int(plan_stats[c, 1]),
                    underruns=int(plan_stats[c, 2]),
                    latency_s=float(latencies[c]),
                    t_start_s=float(cycle_times[c, 0] - record.t_start_s),
                    t_image_s=float(cycle_times[c, 1] - record.t_start_s),
                    counts=p.counts_history[c].copy(),
                    moves=atom_moves(steps, nx=p.config.array.nx, half=half)
                    if (steps := p.steps_history[c]) is not None
                    else None,
                    paths=atom_paths(steps, nx=p.config.array.nx, half=half) if steps is not None else None,
                    planner=planners[c],
                    in_flight=p.in_flight_history[c],
                    pickups=_pickups(slots, occ, chain=p.config.array.trap_source == "aod", half=half)
                    if (slots := p.slots_history[c]) is not None
                    else 0,
                    lab_report=cycle_reports[c],
                )
            )
        self.shots_done += 1
        return record

    @property
    def has_trigger_input(self) -> bool:
        """Whether the AWG has a trigger input the engine can wait on (the devices answer: only an AWG with
        ``wait_trigger`` has one)."""
        return hasattr(self.devices.awg, "wait_trigger")

    def wait_trigger(self, *, timeout_s: float) -> bool:
        """Between shots, armed on ``loop.trigger: hardware``: wait for the sequencer's trigger line at the AWG.

        True if it fired. Raises ``DeviceError`` when the AWG has no trigger input to wait on.
        """
        wait = getattr(self.devices.awg, "wait_trigger", None)
        if wait is None:
            raise DeviceError(
                f"{type(self.devices.awg).__name__} cannot wait for a hardware trigger; "
                "set loop.trigger to 'software' and trigger shots over REST"
            )
        return bool(wait(timeout_s=timeout_s))

    def _cycle(
        self,
        p: _Pipeline,
        cycle: int,
        latencies: np.ndarray,
        plan_stats: np.ndarray,
        cycle_times: np.ndarray,
        planners: list[str],
    ) -> Outcome | None:
        dev = self.devices
        timer = p.timer
        cycle_times[cycle, 0] = timer.start()
        dev.awg.pulse("camera")
        dev.camera.trigger()
        if p.kept_frames is not None and cycle > 0:
            p.kept_frames[cycle - 1] = p.image  # the last cycle's frame, copied while the camera exposes
        self._rehearse(p)
        dev.camera.read(p.image, timeout_s=p.config.camera.timeout_s)
        p.frames_read = cycle + 1
        p.streamer.realtime.enter()  # image to last link at real-time priority (engine.streaming)
        t_image = timer.lap("I.acquire")
        cycle_times[cycle, 1] = t_image
        p.detector.sum(p.image)
        timer.lap("II.detect")
        p.detector.classify(p.occupancy)
        timer.lap("II.threshold")
        p.history[cycle] = p.occupancy
        p.counts_history[cycle] = p.detector.counts
        if target_filled(p.occupancy, p.target):
            return Outcome.SUCCESS
        if cycle == p.config.loop.max_cycles:
            return Outcome.MAX_CYCLES
        try:
            p.solver.solve_moves(p.occupancy, p.target)
        except UnsolvableError:
            return Outcome.UNSOLVABLE
        timer.lap("III.solve")
        plan = p.solver.batch()
        timer.lap("III.batch")
        report = p.streamer.stream(plan.operations, timer)
        latencies[cycle] = report.t_started_s - t_image
        p.steps_history[cycle] = plan.steps.copy()  # after playback started: off the latency path
        p.slots_history[cycle] = _slot_table(plan.operations)  # pick-ups counted after the shot
        plan_stats[cycle] = (report.n_slots, plan.n_steps, report.underruns, 0)
        planners[cycle] = plan.algorithm
        chain = p.config.array.trap_source == "aod"  # after playback ended: off the latency path
        p.in_flight_history[cycle] = [
            atoms_in_flight(plan.operations, p.occupancy, n, chain=chain).tolist() for n in report.failsafe_after_slots
        ]
        return None

    def _rehearse(self, p: _Pipeline) -> None:
        """While the camera exposes (the host waits ~20 ms for the frame anyway), run the latency-critical path
        once on the previous cycle's frame and occupancy, so that its code, numba dispatchers, tables and
        buffers are in the CPU caches when the new frame arrives. Cold, every stage ran 3-10x slower than
        warm. The results are thrown away; nothing here touches a device."""
        try:
            p.detector.sum(p.image)
            p.detector.classify(p.scratch_occupancy)
            p.solver.solve_moves(p.occupancy, p.target)
            p.streamer.rehearse(p.solver.batch().operations)
        except Exception:  # noqa: BLE001 - a rehearsal never fails a shot; the real run reports errors
            pass

    def _hold_atoms(self) -> None:
        """After a fault: make the card loop the hold waveform so every trapped atom stays trapped.

        If playback is already past idle, the card falls into the failsafe step after the last uploaded
        control segment and loops there, holding the tweezers (and any atoms in them) where that segment
        left them, until the next shot starts (``Streamer.recover``).
        """
        p = self._p
        assert p is not None
        try:
            p.streamer.rest()
        except DeviceError:
            pass  # the card itself failed; the fault already says why

    def _back_to_idle(self, p: _Pipeline) -> None:
        """Before a shot: find the card resting in an idle step, or restart it there after a fault."""
        try:
            p.streamer.recover()
        except DeviceError:
            pass  # the shot's first stream will report the card's fault

    # -- between shots: frames for calibration and for display ----------------------------------------------

    def acquire_images(self, n: int) -> np.ndarray:
        """``uint16[n, h, w]``: ``n`` frames taken back to back between shots, for calibration.

        With a lab (the simulated one) each frame is of a freshly loaded array; on hardware the experiment
        keeps whatever atoms it loaded. Raises ``DeviceError`` if the camera fails.
        """
        assert self._p is not None
        return self._acquire(self._p, n)

    def _acquire(self, p: _Pipeline, n: int) -> np.ndarray:
        if n < 1:
            raise ValueError(f"acquire_images needs n >= 1 (got {n})")
        frames = np.empty((n, *p.image.shape), dtype=np.uint16)
        self._back_to_idle(p)
        for frame in frames:
            if self.lab is not None:
                self.lab.prepare_shot()
            self.devices.awg.pulse("camera")
            self.devices.camera.trigger()
            self.devices.camera.read(frame, timeout_s=p.config.camera.timeout_s)
        return frames

    def last_frame(self) -> np.ndarray:
        """A copy of the latest camera frame (after a shot: the image its last cycle saw)."""
        assert self._p is not None
        return self._p.image.copy()


class EngineThread(EngineCommands):
    """Owns an ``Engine`` on a dedicated thread; other threads send it commands and get futures back
    (``engine.host.EngineHost``).

    Commands run strictly one after another, so two callers asking for a shot at once are serialized.
    """

    shares_interpreter = True

    def __init__(self, build: Callable[[], Engine], *, name: str = "llrs-engine") -> None:
        self._build = build
        self._commands: queue.Queue[tuple[Callable[[Engine], Any], Future[Any]] | None] = queue.Queue()
        self._ready = threading.Event()
        self._error: BaseException | None = None
        self.engine: Engine | None = None
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    def start(self, *, timeout_s: float = 300.0) -> EngineThread:
        """Start the thread and wait until the engine is built and every kernel compiled."""
        self._thread.start()
        if not self._ready.wait(timeout_s):
            raise TimeoutError(f"the engine was not ready after {timeout_s} s")
        if self._error is not None:
            raise self._error
        return self

    @property
    def config(self) -> SystemConfig | None:
        """The engine's configuration (``None`` before ``start``)."""
        return self.engine.config if self.engine is not None else None

    @property
    def has_trigger_input(self) -> bool:
        """Whether the engine's devices can wait for a hardware trigger (``Engine.has_trigger_input``)."""
        return self.engine is not None and self.engine.has_trigger_input

    @property
    def alive(self) -> bool:
        return self._thread.is_alive() and self.engine is not None

    @property
    def exit_reason(self) -> str | None:
        if self.alive or not self._ready.is_set():
            return None
        return "the engine thread has stopped" if self._error is None else f"the engine failed to start: {self._error}"

    def submit(self, command: Callable[[Engine], Any]) -> Future[Any]:
        future: Future[Any] = Future()
        self._commands.put((command, future))
        return future

    def run_shots(self, n: int) -> Future[list[ShotRecord]]:
        """``n`` shots one after another, numbered by the engine (``llrs run``)."""
        return self.submit(lambda engine: [engine.run_shot() for _ in range(n)])

    def close(self, *, timeout_s: float = 10.0) -> None:
        """Finish the command in progress and close the devices; a thread stuck in a command for longer than
        ``timeout_s`` is left behind (a thread cannot be killed)."""
        if self._thread.is_alive():
            self._commands.put(None)
            self._thread.join(timeout=timeout_s)

    def _run(self) -> None:
        try:
            self.engine = self._build()
        except BaseException as err:  # reported to the caller of start()
            self._error = err
            self._ready.set()
            return
        self._ready.set()
        engine = self.engine
        while True:
            item = self._commands.get()
            if item is None:
                break
            command, future = item
            if not future.set_running_or_notify_cancel():
                continue
            try:
                future.set_result(command(engine))
            except BaseException as err:
                future.set_exception(err)
        self.devices_close(engine)

    @staticmethod
    def devices_close(engine: Engine) -> None:
        try:
            engine.devices.close()
        except DeviceError:
            pass
