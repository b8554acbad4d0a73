"""What stands in for the engine while the devices cannot be opened (or the engine's process died).

The lab service keeps serving status, configuration and history then; every command to the engine raises
``DevicesUnavailable`` (503 over REST) with the reason, until a configuration whose devices open is applied.
"""

from __future__ import annotations

from collections.abc import Callable
from concurrent.futures import Future
from typing import Any

from engine.host import EngineCommands

__all__ = ["DevicesUnavailable", "NoEngine", "devices_reason"]


def devices_reason(err: BaseException) -> str:
    return (
        f"the devices could not be opened ({type(err).__name__}: {err}); the server keeps serving: fix `devices` "
        "in the configuration (PUT or PATCH /api/config), or check them with `llrs devices`"
    )


class DevicesUnavailable(RuntimeError):
    """The configured devices could not be opened: the server keeps serving (status, config, history) and
    runs no shot until a configuration whose devices open is applied."""


class NoEngine(EngineCommands):
    """An ``EngineHost`` that stands in for the engine while the devices cannot be opened (or its process
    died): every command says why."""

    config = None
    has_trigger_input = False
    alive = False
    shares_interpreter = False

    def __init__(self, reason: str) -> None:
        self.exit_reason = reason

    def start(self) -> NoEngine:
        raise DevicesUnavailable(self.exit_reason)

    def submit(self, command: Callable[[Any], Any]) -> Future[Any]:
        future: Future[Any] = Future()
        future.set_exception(DevicesUnavailable(self.exit_reason))
        return future

    def close(self, *, timeout_s: float = 10.0) -> None:
        pass
