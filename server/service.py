"""The lab service: the one command interface the REST API and the dashboard both drive.

It wraps an engine host (``engine.host.EngineHost``: an ``EngineThread``, or an ``EngineProcess``, the engine
in its own process on its own core, which is how ``llrs serve`` runs it), and adds what a lab server needs around it:
continuous shots with a pause between them, one-off shots with a per-shot configuration, validated config
changes applied between shots, the shot history in memory and on disk, and listeners for live data.

Every command to the engine is sent under one lock, so that the commands of one request (apply an override,
run the shot, restore the config) are never interleaved with another request's or with the continuous runner's.
Shots run strictly one after another: two callers asking for a shot at once get two consecutive shots.

States (``status().state``): ``idle``; ``armed`` (waiting for the sequencer's trigger: ``trigger()`` over REST,
or the devices' hardware trigger line when ``loop.trigger`` is ``hardware``); ``running`` (continuous shots,
or a shot or calibration in progress); ``fault`` (a device failed; continuous shots stopped, the reason kept
until a person starts shots again).

Calibration acquires fresh frames through the engine, fits a threshold or a PSF (``server.calibration``) and
keeps the result under an id without applying it; ``apply_calibration(id)`` turns it into an ordinary config
change, refused if the configuration changed since the frames were taken.

It stays one module (about 600 lines) because what is left is one thing: the engine lock, the runner and
the state machine above, which share every field. Its other parts live in modules beside it:
``server.shot_history`` (the held shots), ``server.calibration`` (the fits and the ``CalibrationBook``),
``server.config_input`` (strict validation of a client's configuration and the tone files it names) and
``server.no_engine`` (the stand-in while devices are down).
"""

from __future__ import annotations

import itertools
import sys
import threading
from collections.abc import Callable, Iterator
from concurrent.futures import Future
from concurrent.futures import TimeoutError as FutureTimeout
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Literal

import numpy as np

from engine.config import SystemConfig, deep_merge
from engine.host import EngineHost
from engine.process import EngineProcessDied
from engine.records import Outcome, ShotRecord
from engine.trap_stats import StatsBook
from server.calibration import (
    CalibrationBook,
    CalibrationConflict,
    CalibrationFailed,
    UnknownCalibration,
    fitted,
    frame_budget_problem,
    psf_calibration,
    threshold_calibration,
)
from server.config_input import ConfigRejected, checked_tone_files, validate_strict
from server.files import confine
from server.models import DevicesOut, StatusOut, shot_summary
from server.no_engine import DevicesUnavailable, NoEngine, devices_reason
from server.runstore import RunStore
from server.shot_history import ShotHistory

__all__ = [
    "CalibrationConflict",
    "CalibrationFailed",
    "ConfigRejected",
    "DevicesUnavailable",
    "EngineBusy",
    "LabService",
    "NotArmed",
    "UnknownCalibration",
    "deep_merge",
]


#: GIL switch interval while a lab service runs (see ``LabService.start``).
SWITCH_INTERVAL_S = 2e-4

#: How long a command waits for the engine (a shot or calibration in progress) before it is refused: a
#: request must not wait for minutes and then act long after its client gave up.
COMMAND_WAIT_S = 30.0

class NotArmed(RuntimeError):
    """A trigger arrived while the server was not armed (or an arm the devices cannot honour)."""


class EngineBusy(RuntimeError):
    """The engine stayed busy (a shot, a calibration) for longer than a command may wait; nothing was done."""


class LabService:
    """Owns the engine host, the continuous runner, the shot history and the run store."""

    def __init__(
        self,
        *,
        engine_thread: EngineHost,
        store: RunStore | None = None,
        pause_s: float = 0.5,
        history: int = 2000,
        engine_factory: Callable[[SystemConfig], EngineHost] | None = None,
        config: SystemConfig | None = None,
        tone_dir: Path | None = None,
        shot_dir: Path | None = None,
    ) -> None:
        """``engine_factory`` (with ``config``, the configuration ``engine_thread`` was built for) lets the
        service survive devices that cannot be opened and re-open devices when ``devices`` changes.

        ``tone_dir``: the directory tone CSVs named in a submitted configuration must lie in; ``shot_dir``:
        the one labscript shot files must lie in (``None``: such files are refused; see ``server.files``)."""
        self._et: EngineHost = engine_thread
        self._factory = engine_factory
        self._initial_config = config
        self._store = store
        self.tone_dir = tone_dir
        self.shot_dir = shot_dir
        self.pause_s = pause_s
        # Shot ids come from here, not from the engine, so they keep increasing when devices are re-opened
        # on a new engine (the run store and the API key shots by id).
        self._shot_ids = itertools.count()
        self._shot_limit_s: float | None = None  # see _learn_shot_limit
        self._lock = threading.Lock()  # serializes commands to the engine
        self._state_lock = threading.Lock()  # guards the fields below
        self._history = ShotHistory(history)
        self._fault: str | None = None
        self._activity: list[str] = []
        self._armed = False
        self._armed_shots_left: int | None = None
        self._calibrations = CalibrationBook()
        self._listeners: list[Callable[[ShotRecord], None]] = []
        self.trap_stats = StatsBook()  # per-trap statistics per configuration (GET /api/stats, the dashboard)
        self._want_run = threading.Event()
        self._wake = threading.Event()  # the runner has something to do (or must exit)
        self._closing = threading.Event()
        self._config: SystemConfig | None = None
        self._runner = threading.Thread(target=self._run_loop, name="llrs-runner", daemon=True)

    # -- life cycle -------------------------------------------------------------------------------------------

    def start(self, *, run: bool = False) -> LabService:
        """Build the engine (compiles every kernel), then start the runner; ``run`` starts continuous shots."""
        # An engine *thread* shares the GIL with the API's and the dashboard's threads. A thread that wants the
        # GIL waits up to the switch interval (5 ms by default) for the holder to let go, so request handling
        # could add milliseconds to a cycle; 0.2 ms bounds that wait at a small cost in throughput. An engine
        # process has an interpreter of its own.
        if self._et.shares_interpreter:
            sys.setswitchinterval(min(sys.getswitchinterval(), SWITCH_INTERVAL_S))
        try:
            self._et.start()
        except Exception as err:
            if self._factory is None or self._initial_config is None:
                raise
            self._et = NoEngine(devices_reason(err))
            self._config = self._initial_config
            self._fault = self._et.exit_reason
        else:
            self._config = self._et.config
            self._learn_shot_limit()
        if self._store is not None and self._config is not None:
            self._store.note_config(self._config)
        self._runner.start()
        if run:
            self.run()
        return self

    def close(self) -> None:
        """Stop shots, the runner, the engine (closing its devices) and the run store."""
        self._want_run.clear()
        with self._state_lock:
            self._armed = False
        self._closing.set()
        self._wake.set()  # so the runner sees _closing
        if self._runner.is_alive():
            self._runner.join(timeout=30)
        self._et.close()
        if self._store is not None:
            self._store.close()

    def add_listener(self, callback: Callable[[ShotRecord], None]) -> None:
        """``callback(record)`` after every shot, on the thread that asked for it (the runner, or a request's):
        keep it short (hand work elsewhere)."""
        self._listeners.append(callback)

    def remove_listener(self, callback: Callable[[ShotRecord], None]) -> None:
        if callback in self._listeners:
            self._listeners.remove(callback)

    # -- commands ---------------------------------------------------------------------------------------------

    @property
    def config(self) -> SystemConfig:
        assert self._config is not None, "start() first"
        return self._config

    def replace_config(self, config: SystemConfig | dict[str, Any]) -> SystemConfig:
        """Validate and apply a whole configuration between shots; on any error the running one stays."""
        new = config if isinstance(config, SystemConfig) else validate_strict(config)
        new = checked_tone_files(new, self._config, self.tone_dir)
        with self._engine_turn():
            self._apply(new)
        return new

    def patch_config(self, patch: dict[str, Any]) -> SystemConfig:
        """Deep-merge ``patch`` into the running configuration, validate, apply (see ``replace_config``)."""
        with self._engine_turn():
            new = validate_strict(deep_merge(self.config.model_dump(mode="json"), patch))
            new = checked_tone_files(new, self._config, self.tone_dir)
            self._apply(new)
        return new

    def run(self) -> None:
        """Start continuous shots (a pause of ``pause_s`` between them); disarms a waiting trigger."""
        self._require_engine()
        with self._state_lock:
            self._fault = None
            self._armed = False
        self._want_run.set()
        self._wake.set()

    def stop(self) -> None:
        """Stop after the shot in progress, and disarm."""
        self._want_run.clear()
        with self._state_lock:
            self._armed = False
            self._armed_shots_left = None

    @property
    def running(self) -> bool:
        return self._want_run.is_set() and not self._closing.is_set()

    @property
    def trigger_source(self) -> Literal["rest", "hardware"]:
        """What starts a shot while armed: ``"hardware"`` (``loop.trigger: hardware``) or ``"rest"``."""
        return "hardware" if self.config.loop.trigger == "hardware" else "rest"

    def arm(self, *, shots: int | None = None) -> None:
        """Stop continuous shots and wait for the sequencer's trigger; each trigger runs one shot.

        ``shots``: disarm after that many triggered shots (``None``: stay armed until ``stop``). With
        ``loop.trigger: hardware`` the devices must have a trigger input (``engine.wait_trigger``); otherwise
        ``NotArmed`` says so and nothing changes.
        """
        self._require_engine()
        if self.trigger_source == "hardware" and not self._et.has_trigger_input:
            raise NotArmed(
                "loop.trigger is 'hardware' but these devices have no trigger input; "
                "set loop.trigger to 'software' and send POST /api/trigger"
            )
        self._want_run.clear()
        with self._state_lock:
            self._fault = None
            self._armed = True
            self._armed_shots_left = shots
        self._wake.set()

    @property
    def armed(self) -> bool:
        with self._state_lock:
            return self._armed

    @property
    def armed_shots_left(self) -> int | None:
        with self._state_lock:
            return self._armed_shots_left

    def trigger(self) -> ShotRecord:
        """The sequencer's software trigger: run one shot now (after the one in progress) if armed.

        Raises ``NotArmed`` otherwise. Triggers are serialized like every shot.
        """
        with self._engine_turn():
            self._take_trigger()
            return self._one_shot("triggered shot")

    def shot(self, *, override: dict[str, Any] | None = None) -> ShotRecord:
        """Run one shot now (after the one in progress) and return its record.

        ``override`` is a partial configuration deep-merged into the running one for this shot only.
        """
        with self._engine_turn():
            if not override:
                return self._one_shot("one shot")
            base = self.config
            special = validate_strict(deep_merge(base.model_dump(mode="json"), override))
            special = checked_tone_files(special, self._config, self.tone_dir)
            if special.devices != base.devices:
                raise ConfigRejected(
                    [{"loc": ["body", "config", "devices"], "type": "override_devices",
                      "msg": "a one-shot override cannot change the devices; "
                             "change them with PUT or PATCH /api/config"}]
                )
            self._apply(special, remember=False)
            try:
                return self._one_shot("one shot (config override)")
            finally:
                self._apply(base)

    def shot_file(self, path: str) -> ShotRecord | None:
        """Run the shot a labscript shot file describes (``server.labscript``) and write its results into it.

        Returns None when the file's ``llrs_enabled`` global is false (the skip is written into the file).
        """
        from server.labscript import run_shot_file

        path = str(confine(path, self.shot_dir, what="shot file", option="--shot-dir"))

        def run(config: SystemConfig | None) -> ShotRecord:
            return self.shot(override=config.model_dump(mode="json") if config is not None else None)

        return run_shot_file(path, run, self.config)

    # -- calibration ------------------------------------------------------------------------------------------

    def acquire_images(self, n: int) -> np.ndarray:
        """``uint16[n, h, w]`` fresh frames from the engine's camera (between shots)."""
        with self._engine_turn():
            return self._acquire(n, "acquiring frames")

    def calibrate_threshold(self, *, images: int = 40) -> dict[str, Any]:
        """Acquire ``images`` frames and fit the occupancy threshold; kept under an id, not applied."""
        return self._calibrate("threshold", threshold_calibration, images)

    def calibrate_psf(self, *, images: int = 40) -> dict[str, Any]:
        """Acquire ``images`` frames and fit the PSF and trap lattice; kept under an id, not applied."""
        return self._calibrate("PSF", psf_calibration, images)

    def _calibrate(
        self, kind: str, fit: Callable[[np.ndarray, SystemConfig], dict[str, Any]], images: int
    ) -> dict[str, Any]:
        """Acquire ``images`` frames (at most ``server.calibration.MAX_CALIBRATION_BYTES`` of them) and fit;
        ``CalibrationFailed`` when the frames cannot be fitted."""
        with self._engine_turn():
            config = self.config
            problem = frame_budget_problem(images, config)
            if problem is not None:
                raise ConfigRejected([{"loc": ["body", "images"], "type": "too_many_frames", "msg": problem}])
            frames = self._acquire(images, f"calibrating the {kind} ({images} frames)")
        return self._calibrations.keep(fitted(kind, fit, frames, config), config)

    def calibrations(self) -> list[dict[str, Any]]:
        """Calibrations held (newest last)."""
        return self._calibrations.all()

    def apply_calibration(self, calibration_id: str) -> dict[str, Any]:
        """Put a calibration's values into the running configuration (applied between shots).

        ``UnknownCalibration``: no such id. ``CalibrationConflict``: the configuration changed since its frames were
        taken (calibrate again). Applying one that is already applied changes nothing.
        """
        with self._engine_turn():
            cal = self._calibrations.to_apply(calibration_id, self.config.digest())
            if cal["applied"]:
                return cal
            self._apply(validate_strict(deep_merge(self.config.model_dump(mode="json"), cal["apply_patch"])))
            return self._calibrations.mark_applied(cal)

    # -- queries ----------------------------------------------------------------------------------------------

    def shots(self, *, limit: int, offset: int) -> tuple[int, list[ShotRecord]]:
        """``(total held, records)`` newest first."""
        return self._history.page(limit=limit, offset=offset)

    def get_shot(self, shot_id: int) -> ShotRecord | None:
        return self._history.get(shot_id)

    def status(self) -> StatusOut:
        self._notice_dead_engine()
        cfg = self.config
        last, shots, successes, truth = self._history.tallies()
        with self._state_lock:
            fault = self._fault
            activity = self._activity[-1] if self._activity else None
            armed = self._armed
        state: Literal["idle", "armed", "running", "fault"]
        if fault is not None:
            state = "fault"
        elif self.running or activity is not None:
            state = "running"
        elif armed:
            state = "armed"
        else:
            state = "idle"
        if activity is None and armed:
            activity = "waiting for the trigger"
        run_file = self._store.current_path if self._store is not None else None
        unrecorded, recording_error = self._store.write_errors() if self._store is not None else (0, None)
        return StatusOut(
            state=state,
            reason=fault,
            activity=activity,
            running=self.running,
            armed=armed,
            trigger=self.trigger_source,
            pause_s=self.pause_s,
            devices=DevicesOut(
                camera=cfg.devices.camera,
                awg=cfg.devices.awg,
                time=cfg.sim.time if cfg.devices.camera == "sim" or cfg.devices.awg == "sim" else "hardware",
            ),
            config_name=cfg.name,
            config_digest=cfg.digest(),
            shots_done=shots,
            successes=successes,
            success_rate=successes / shots if shots else None,
            truth_successes=truth,
            last_shot=shot_summary(last) if last is not None else None,
            run_file=str(run_file) if run_file is not None else None,
            unrecorded_shots=unrecorded,
            recording_error=recording_error,
        )

    @property
    def run_store(self) -> RunStore | None:
        """Where shots are recorded (``None``: not recorded), for the run-file routes."""
        return self._store

    def last_record(self) -> ShotRecord | None:
        return self._history.last()

    def frame(self, shot_id: int, cycle: int) -> np.ndarray | None:
        """A camera frame of a held shot: any cycle's if the engine kept images with the record, else the last
        cycle's (the final image) for the most recent shots. ``None`` if not kept."""
        return self._history.frame(shot_id, cycle)

    def last_frame(self) -> tuple[int, np.ndarray] | None:
        """``(shot_id, uint16[h, w])``: the last camera frame of the latest shot (the final state), if the engine
        offers it. The array is the service's own copy; do not modify it."""
        return self._history.last_frame()

    @property
    def final_frames_kept(self) -> int:
        """How many of the newest shots keep their final camera frame."""
        return self._history.final_frames_kept

    @final_frames_kept.setter
    def final_frames_kept(self, n: int) -> None:
        self._history.final_frames_kept = n

    # -- internals --------------------------------------------------------------------------------------------

    @contextmanager
    def _engine_turn(self) -> Iterator[None]:
        """The engine lock for one command, waited for at most ``COMMAND_WAIT_S`` (``EngineBusy`` then)."""
        if not self._lock.acquire(timeout=COMMAND_WAIT_S):
            with self._state_lock:
                doing = ", ".join(self._activity) or "a command"
            raise EngineBusy(
                f"the engine has been busy ({doing}) for over {COMMAND_WAIT_S:g} s; nothing was done, try again"
            )
        try:
            yield
        finally:
            self._lock.release()

    def _require_engine(self) -> None:
        self._notice_dead_engine()
        if isinstance(self._et, NoEngine):
            raise DevicesUnavailable(self._et.exit_reason or "no engine")

    def _wait(self, future: Future[Any], *, timeout_s: float | None = None) -> Any:
        """The result of an engine command; an engine process that died says so as ``DevicesUnavailable``
        (503 over REST) rather than as an internal error. A command still running after ``timeout_s``
        means an engine stuck in a device call: it is stopped (``_abandon_engine``)."""
        try:
            return future.result(timeout=timeout_s)
        except FutureTimeout:
            reason = (
                f"watchdog: the engine did not finish a shot within {timeout_s:.3g} s (twice its own watchdog, "
                "plus a second): it was stopped; the card keeps playing its hold waveform. Apply a configuration "
                "(PUT /api/config) to start a new engine"
            )
            self._abandon_engine(reason)
            raise DevicesUnavailable(reason) from None
        except EngineProcessDied:
            self._notice_dead_engine()
            raise DevicesUnavailable(self._et.exit_reason or "the engine process died") from None

    def _notice_dead_engine(self) -> None:
        """An engine process that died becomes a ``NoEngine`` with its reason: the server reports it and a
        configuration applied later starts a new engine (``_apply`` re-opens)."""
        if not isinstance(self._et, NoEngine) and not self._et.alive:
            reason = self._et.exit_reason or "the engine is gone"
            reason += "; apply a configuration (PUT /api/config) to start a new engine"
            self._et.close()
            self._et = NoEngine(reason)
            with self._state_lock:
                self._fault = reason

    def _learn_shot_limit(self) -> None:
        """How long a shot may take before the service gives up on the engine: twice the engine's own
        watchdog (which ends a slow shot between cycles) plus a second, for a device call that never returns."""
        self._shot_limit_s = 2 * float(self._wait(self._et.shot_watchdog_s())) + 1.0

    def _abandon_engine(self, reason: str) -> None:
        """Stop an engine that is stuck (its process is killed; a stuck thread is left behind)."""
        self._et.close(timeout_s=1.0)
        self._et = NoEngine(reason)
        with self._state_lock:
            self._fault = reason

    def _reopen(self, config: SystemConfig) -> None:
        """Open the devices ``config`` names on a new engine host; keep the old one if they do not open."""
        assert self._factory is not None
        thread = self._factory(config)
        try:
            thread.start()
        except Exception as err:
            raise ConfigRejected(
                [{"loc": ["body", "devices"], "msg": devices_reason(err), "type": "devices_unavailable"}]
            ) from None
        old, self._et = self._et, thread
        old.close()
        with self._state_lock:
            self._fault = None

    def _apply(self, config: SystemConfig, *, remember: bool = True) -> None:
        """Apply on the engine (between shots); raise ``ConfigRejected`` if the engine refuses it, for whatever
        reason (an overflow in a model, an unreadable tone file): the running configuration then stays.

        With an engine factory, a change of ``devices`` (or devices that failed to open before) re-opens the
        devices on a new engine host; if they do not open, the running engine and config stay. The run store
        learns a configuration only once the engine runs it."""
        self._notice_dead_engine()
        reopen = isinstance(self._et, NoEngine) or (
            self._factory is not None and self._config is not None and config.devices != self._config.devices
        )
        if reopen and self._factory is not None:
            self._reopen(config)
        else:
            try:
                self._wait(self._et.configure(config))
            except DevicesUnavailable:
                raise
            except Exception as err:
                text = f"{type(err).__name__}: {err}"
                text = text if len(text) <= 500 else text[:500] + "..."
                raise ConfigRejected([{"loc": ["body"], "msg": text, "type": "engine_refused"}]) from None
        self._learn_shot_limit()
        if self._store is not None:
            self._store.note_config(config)
        if remember:
            self._config = config

    def _take_trigger(self) -> None:
        """Consume one armed trigger (``NotArmed`` if there is none)."""
        with self._state_lock:
            if not self._armed:
                raise NotArmed("not armed: POST /api/arm first")
            if self._armed_shots_left is not None:
                self._armed_shots_left -= 1
                if self._armed_shots_left <= 0:
                    self._armed, self._armed_shots_left = False, None

    def _busy(self, what: str) -> Callable[[], None]:
        with self._state_lock:
            self._activity.append(what)

        def done() -> None:
            with self._state_lock:
                self._activity.remove(what)

        return done

    def _acquire(self, n: int, what: str) -> np.ndarray:
        done = self._busy(what)
        try:
            frames = self._wait(self._et.acquire_images(n))
        finally:
            done()
        return np.asarray(frames)

    def _one_shot(self, what: str) -> ShotRecord:
        """One shot on the engine, then the bookkeeping and the listeners on this (the caller's) thread."""
        done = self._busy(what)
        try:
            record, frame = self._wait(self._et.run_shot(next(self._shot_ids)), timeout_s=self._shot_limit_s)
        finally:
            done()
        self._on_shot(record, frame)
        return record

    def _on_shot(self, record: ShotRecord, frame: np.ndarray | None = None) -> None:
        self._history.add(record, frame)
        with self._state_lock:
            self._fault = record.fault if record.outcome is Outcome.FAULT else None
        if self._store is not None:
            self._store.put(record, frame)
        self.trap_stats.add(record)
        for listener in list(self._listeners):
            try:
                listener(record)
            except Exception:  # a broken listener (a closed dashboard) must never stop the engine
                pass
        self._history.drop_counts_of_older_shots(record)

    def _wait_hardware_trigger(self) -> bool:
        """Armed on a hardware trigger: wait a little for the line on the engine; True if it fired."""
        fired = self._wait(self._et.wait_trigger(timeout_s=0.2))
        return bool(fired)

    def _run_loop(self) -> None:
        while not self._closing.is_set():
            if not self._want_run.is_set() and not (self.armed and self.trigger_source == "hardware"):
                self._wake.wait()
                self._wake.clear()
                continue
            with self._lock:
                if self._closing.is_set():
                    return
                try:
                    if self._want_run.is_set():
                        if self._one_shot("continuous shots").outcome is Outcome.FAULT:
                            self._want_run.clear()  # a device failed: hold the atoms, let a person look
                    elif self.armed and self.trigger_source == "hardware" and self._wait_hardware_trigger():
                        self._take_trigger()
                        self._one_shot("triggered shot (hardware)")
                    else:
                        continue  # nothing fired: look again at once (the wait itself paced us)
                except NotArmed:
                    continue
                except Exception as err:  # the engine died or raised: stop and report it
                    with self._state_lock:
                        self._fault = f"{type(err).__name__}: {err}"
                        self._armed = False
                    self._want_run.clear()
                    self._notice_dead_engine()
            if self._want_run.is_set():
                self._closing.wait(self.pause_s)
