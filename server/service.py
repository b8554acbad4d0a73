"""The lab service: the one command interface the REST API and the dashboard both drive.

It wraps an ``EngineThread`` (which owns the engine and its devices) and adds what a lab server needs around it:
continuous shots with a pause between them, one-off shots with a per-shot configuration, validated config
changes applied between shots, the shot history in memory and on disk, and listeners for live data.

Every command to the engine is sent under one lock, so that the commands of one request (apply an override,
run the shot, restore the config) are never interleaved with another request's or with the continuous runner's.
Shots run strictly one after another: two callers asking for a shot at once get two consecutive shots.
"""

from __future__ import annotations

import threading
from collections import deque
from collections.abc import Callable
from typing import Any

from pydantic import ValidationError

from engine.config import SystemConfig
from engine.engine import EngineThread
from engine.records import Outcome, ShotRecord
from server.models import DevicesOut, StatusOut, shot_summary
from server.runstore import RunStore

__all__ = ["ConfigRejected", "LabService", "deep_merge"]


class ConfigRejected(ValueError):
    """A configuration the service refused; ``errors`` say where and why (FastAPI's error shape)."""

    def __init__(self, errors: list[dict[str, Any]]) -> None:
        super().__init__("; ".join(f"{'.'.join(map(str, e['loc']))}: {e['msg']}" for e in errors))
        self.errors = errors


def deep_merge(base: dict[str, Any], patch: dict[str, Any]) -> dict[str, Any]:
    """``base`` with ``patch`` merged in: nested mappings merge key by key, anything else replaces.

    Unlike RFC 7396, ``null`` is a value, not a deletion: ``imaging.threshold: null`` is a real setting.
    """
    merged = dict(base)
    for key, value in patch.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def _validate(data: Any) -> SystemConfig:
    try:
        return SystemConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigRejected(
            [{"loc": ["body", *e["loc"]], "msg": e["msg"], "type": e["type"]} for e in err.errors()]
        ) from None


class LabService:
    """Owns the engine thread, the continuous runner, the shot history and the run store."""

    def __init__(
        self,
        *,
        engine_thread: EngineThread,
        store: RunStore | None = None,
        pause_s: float = 0.5,
        history: int = 2000,
    ) -> None:
        self._et = engine_thread
        self._store = store
        self.pause_s = pause_s
        self._lock = threading.Lock()  # serializes commands to the engine
        self._state_lock = threading.Lock()  # guards the fields below
        self._history: deque[ShotRecord] = deque(maxlen=history)
        self._by_id: dict[int, ShotRecord] = {}
        self._shots = 0
        self._successes = 0
        self._truth_successes: int | None = None
        self._fault: str | None = None
        self._busy = 0
        self._listeners: list[Callable[[ShotRecord], None]] = []
        self._want_run = threading.Event()
        self._closing = threading.Event()
        self._config: SystemConfig | None = None
        self._runner = threading.Thread(target=self._run_loop, name="llrs-runner", daemon=True)

    # -- life cycle -------------------------------------------------------------------------------------------

    def start(self, *, run: bool = False) -> LabService:
        """Build the engine (compiles every kernel), then start the runner; ``run`` starts continuous shots."""
        self._et.add_listener(self._on_shot)
        self._et.start()
        engine = self._et.engine
        assert engine is not None
        self._config = engine.config
        if self._store is not None:
            self._store.note_config(self._config)
        self._runner.start()
        if run:
            self.run()
        return self

    def close(self) -> None:
        """Stop shots, the runner, the engine (closing its devices) and the run store."""
        self._want_run.clear()
        self._closing.set()
        self._want_run.set()  # wake the runner so it sees _closing
        if self._runner.is_alive():
            self._runner.join(timeout=30)
        self._et.close()
        if self._store is not None:
            self._store.close()

    def add_listener(self, callback: Callable[[ShotRecord], None]) -> None:
        """``callback(record)`` after every shot, on the engine thread: keep it short (hand work elsewhere)."""
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
        new = config if isinstance(config, SystemConfig) else _validate(config)
        with self._lock:
            self._apply(new)
        return new

    def patch_config(self, patch: dict[str, Any]) -> SystemConfig:
        """Deep-merge ``patch`` into the running configuration, validate, apply (see ``replace_config``)."""
        with self._lock:
            new = _validate(deep_merge(self.config.model_dump(mode="json"), patch))
            self._apply(new)
        return new

    def run(self) -> None:
        """Start continuous shots (a pause of ``pause_s`` between them)."""
        with self._state_lock:
            self._fault = None
        self._want_run.set()

    def stop(self) -> None:
        """Stop after the shot in progress."""
        self._want_run.clear()

    @property
    def running(self) -> bool:
        return self._want_run.is_set() and not self._closing.is_set()

    def shot(self, *, override: dict[str, Any] | None = None) -> ShotRecord:
        """Run one shot now (after the one in progress) and return its record.

        ``override`` is a partial configuration deep-merged into the running one for this shot only.
        """
        with self._lock:
            if not override:
                return self._one_shot()
            base = self.config
            special = _validate(deep_merge(base.model_dump(mode="json"), override))
            self._apply(special, remember=False)
            try:
                return self._one_shot()
            finally:
                self._apply(base)

    # -- queries ----------------------------------------------------------------------------------------------

    def shots(self, *, limit: int, offset: int) -> tuple[int, list[ShotRecord]]:
        """``(total held, records)`` newest first."""
        with self._state_lock:
            newest_first = list(reversed(self._history))
        return len(newest_first), newest_first[offset : offset + limit]

    def get_shot(self, shot_id: int) -> ShotRecord | None:
        with self._state_lock:
            return self._by_id.get(shot_id)

    def status(self) -> StatusOut:
        cfg = self.config
        with self._state_lock:
            last = self._history[-1] if self._history else None
            shots, successes, truth, fault, busy = (
                self._shots,
                self._successes,
                self._truth_successes,
                self._fault,
                self._busy,
            )
        if fault is not None:
            state = "fault"
        elif self.running or busy:
            state = "running"
        else:
            state = "idle"
        run_file = self._store.current_path if self._store is not None else None
        return StatusOut(
            state=state,
            reason=fault,
            running=self.running,
            pause_s=self.pause_s,
            devices=DevicesOut(camera=cfg.devices.camera, awg=cfg.devices.awg, time=cfg.sim.time),
            config_name=cfg.name,
            config_digest=cfg.digest(),
            shots_done=shots,
            successes=successes,
            success_rate=successes / shots if shots else None,
            truth_successes=truth,
            last_shot=shot_summary(last) if last is not None else None,
            run_file=str(run_file) if run_file is not None else None,
        )

    def last_record(self) -> ShotRecord | None:
        with self._state_lock:
            return self._history[-1] if self._history else None

    # -- internals --------------------------------------------------------------------------------------------

    def _apply(self, config: SystemConfig, *, remember: bool = True) -> None:
        """Apply on the engine thread (between shots); raise ``ConfigRejected`` if the engine refuses it."""
        if self._store is not None:
            self._store.note_config(config)
        try:
            self._et.submit(lambda engine: engine.apply(config)).result()
        except (ValueError, KeyError, NotImplementedError) as err:
            raise ConfigRejected([{"loc": ["body"], "msg": f"{type(err).__name__}: {err}", "type": "engine_refused"}]) from None
        if remember:
            self._config = config

    def _one_shot(self) -> ShotRecord:
        with self._state_lock:
            self._busy += 1
        try:
            return self._et.run_shots(1).result()[0]
        finally:
            with self._state_lock:
                self._busy -= 1

    def _on_shot(self, record: ShotRecord) -> None:
        with self._state_lock:
            if len(self._history) == self._history.maxlen:
                self._by_id.pop(self._history[0].shot_id, None)
            self._history.append(record)
            self._by_id[record.shot_id] = record
            self._shots += 1
            self._successes += record.success
            filled = record.truth.get("target_filled")
            if filled is not None:
                self._truth_successes = (self._truth_successes or 0) + bool(filled)
            self._fault = record.fault if record.outcome is Outcome.FAULT else None
        if self._store is not None:
            self._store.put(record)
        for listener in list(self._listeners):
            listener(record)

    def _run_loop(self) -> None:
        while True:
            self._want_run.wait()
            if self._closing.is_set():
                return
            with self._lock:
                if self._want_run.is_set() and not self._closing.is_set():
                    try:
                        if self._one_shot().outcome is Outcome.FAULT:
                            self._want_run.clear()  # a device failed: hold the atoms, let a person look
                    except Exception as err:  # the engine thread died or raised: stop and report it
                        with self._state_lock:
                            self._fault = f"{type(err).__name__}: {err}"
                        self._want_run.clear()
            self._closing.wait(self.pause_s)
