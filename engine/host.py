"""Where an engine runs, as one written contract: ``EngineHost``.

An engine runs on a thread of this process (``engine.engine.EngineThread``) or in a process of its own
(``engine.process.EngineProcess``); the lab service drives either through this protocol and never asks which
one it has. Every command returns a future, runs on the engine's own thread (or process) strictly one after
another, and fails with the exception the engine raised. The commands themselves are written once, in
``EngineCommands``, in terms of ``submit``; each host only says how a command reaches its engine.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from concurrent.futures import Future
from functools import partial
from operator import methodcaller
from typing import Any, Protocol, Self

import numpy as np

from engine.config import SystemConfig
from engine.records import ShotRecord

__all__ = ["EngineCommands", "EngineHost", "shot_with_frame"]


def shot_with_frame(engine: Any, shot_id: int | None = None) -> tuple[ShotRecord, np.ndarray | None]:
    """One shot (numbered ``shot_id``; ``None``: the engine's own count) and its final camera frame (``None``
    if the engine offers none): module-level so that it can be sent to an engine process."""
    record = engine.run_shot(shot_id)
    last_frame = getattr(engine, "last_frame", None)
    return record, (last_frame() if last_frame is not None else None)


class EngineHost(Protocol):
    """An engine on a thread or in a process of its own, driven by commands that return futures."""

    @property
    def config(self) -> SystemConfig | None:
        """The configuration the engine was built with (``None`` before ``start``)."""
        ...

    @property
    def has_trigger_input(self) -> bool:
        """Whether the engine's devices can wait for the sequencer's hardware trigger (they answer it)."""
        ...

    @property
    def alive(self) -> bool:
        """False once the engine's thread or process has ended (or before ``start``)."""
        ...

    @property
    def exit_reason(self) -> str | None:
        """How the engine ended, for a person (``None`` while it runs)."""
        ...

    @property
    def shares_interpreter(self) -> bool:
        """True if the engine runs on a thread of this interpreter (and so shares its lock)."""
        ...

    def start(self) -> EngineHost:
        """Build the engine (compiling every kernel); raises what the build raised."""
        ...

    def close(self, *, timeout_s: float = 10.0) -> None:
        """Finish the command in progress, close the devices, end the thread or process; a process that
        has not ended after ``timeout_s`` is killed (a thread cannot be, and is left behind)."""
        ...

    def submit(self, command: Callable[[Any], Any]) -> Future[Any]:
        """Run ``command(engine)`` on the engine, after the commands before it."""
        ...

    def configure(self, config: SystemConfig) -> Future[None]:
        """Apply ``config`` between shots (the engine refuses it, and keeps the running one, on any error)."""
        ...

    def run_shot(self, shot_id: int) -> Future[tuple[ShotRecord, np.ndarray | None]]:
        """Run one shot numbered ``shot_id``; its record and final camera frame."""
        ...

    def wait_trigger(self, *, timeout_s: float) -> Future[bool]:
        """Wait up to ``timeout_s`` for the hardware trigger (only where ``has_trigger_input``)."""
        ...

    def acquire_images(self, n: int) -> Future[np.ndarray]:
        """``n`` fresh camera frames, between shots (calibration)."""
        ...

    def shot_watchdog_s(self) -> Future[float]:
        """How long a shot may run before the engine ends it as a fault (``Engine.shot_watchdog_s``)."""
        ...


class EngineCommands(ABC):
    """The commands of ``EngineHost`` written once over ``submit`` (commands pickle, for a process)."""

    @abstractmethod
    def submit(self, command: Callable[[Any], Any]) -> Future[Any]: ...

    @abstractmethod
    def start(self) -> EngineCommands: ...

    @abstractmethod
    def close(self, *, timeout_s: float = 10.0) -> None: ...

    def __enter__(self) -> Self:
        """``with host:`` starts the engine and closes it at the end."""
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def configure(self, config: SystemConfig) -> Future[None]:
        return self.submit(methodcaller("apply", config))

    def run_shot(self, shot_id: int) -> Future[tuple[ShotRecord, np.ndarray | None]]:
        return self.submit(partial(shot_with_frame, shot_id=shot_id))

    def wait_trigger(self, *, timeout_s: float) -> Future[bool]:
        return self.submit(methodcaller("wait_trigger", timeout_s=timeout_s))

    def acquire_images(self, n: int) -> Future[np.ndarray]:
        return self.submit(methodcaller("acquire_images", n))

    def shot_watchdog_s(self) -> Future[float]:
        return self.submit(methodcaller("shot_watchdog_s"))
