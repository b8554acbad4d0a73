"""The engine in a process of its own, optionally pinned to a CPU core of its own.

Why: in one process the engine thread shares the interpreter lock with the web server, the live hub and
the dashboard. Every numba kernel releases the lock and must take it back afterwards, and while a request
handler holds it that takes up to the switch interval; the operating system may also run the server on the
engine's core, evicting the caches the cycle needs. Under a busy browser and a polling sequencer that made
the software latency's p99 several times its idle value. In its own process the engine has its own
interpreter lock and, pinned, its own core and L2 cache: the server can be as busy as it likes.

``EngineProcess`` is an ``engine.host.EngineHost``, as ``EngineThread`` is, so the service does not care
where the engine runs. What
crosses the process boundary is pickled: the engine's builder (a module-level function, or a
``functools.partial`` of one), each command (``operator.methodcaller`` or a module-level function of the
engine) and each result (shot records, frames, configurations). The child runs commands one after another
on its main thread, so commands are serialized exactly as on the engine thread. If the child dies (a
segfault in a vendor library, the OOM killer), every pending and later command fails with
``EngineProcessDied`` and the server stays up to report it.
"""

from __future__ import annotations

import itertools
import os
import pickle
import signal
import socket
import subprocess
import sys
import threading
from collections.abc import Callable
from concurrent.futures import Future
from multiprocessing.connection import Connection
from typing import Any

from engine.config import SystemConfig
from engine.host import EngineCommands, shot_with_frame

__all__ = ["EngineProcess", "EngineProcessDied", "default_engine_cpu", "shot_with_frame"]


class EngineProcessDied(RuntimeError):
    """The engine's process exited; the message says how. Restart the server (or apply a configuration
    that re-opens the devices) to get a new one."""


def default_engine_cpu() -> int | None:
    """The core to pin the engine to: the highest this process may use, if it may use at least two (the
    rest stay for the server); ``None`` on one core or where affinity cannot be set."""
    if not hasattr(os, "sched_getaffinity"):
        return None
    cpus = sorted(os.sched_getaffinity(0))
    return cpus[-1] if len(cpus) >= 2 else None


def _describe_exit(code: int | None) -> str:
    return (
        "the engine process exited"
        + (f" with code {code}" if code is not None else "")
        + (f" (signal {-code})" if code is not None and code < 0 else "")
    )


def _portable(err: BaseException) -> BaseException:
    """``err`` if it survives pickling, else a ``RuntimeError`` carrying its type and message."""
    try:
        pickle.loads(pickle.dumps(err))
        return err
    except Exception:  # noqa: BLE001 - any pickling failure
        return RuntimeError(f"{type(err).__name__}: {err}")


def _child_main(conn: Connection) -> None:
    """The engine process: receive the builder and the core, build the engine, report ready, then run
    commands until told to stop."""
    # Ctrl-C reaches the whole process group: the parent stops the engine (finishing the shot in progress,
    # closing the devices) through ``close``, so the engine must not die of the same signal first.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        build, cpu = conn.recv()
        if cpu is not None:
            os.sched_setaffinity(0, {cpu})
        engine = build()
    except BaseException as err:  # noqa: BLE001 - reported to the parent's start()
        conn.send(("failed", _portable(err)))
        return
    conn.send(("ready", (engine.config, engine.has_trigger_input)))
    try:
        while True:
            try:
                message = conn.recv()
            except (EOFError, OSError):
                break  # the parent is gone
            if message is None:
                break
            ident, command = message
            try:
                reply = (ident, True, command(engine))
            except BaseException as err:  # noqa: BLE001 - every failure goes back to the caller
                reply = (ident, False, _portable(err))
            try:
                conn.send(reply)
            except Exception as err:  # noqa: BLE001 - an unpicklable result
                conn.send((ident, False, RuntimeError(f"the engine's result could not be sent back: {err}")))
    finally:
        devices = getattr(engine, "devices", None)
        if devices is not None:
            try:
                devices.close()
            except Exception:  # noqa: BLE001 - closing is best effort on the way out
                pass


class EngineProcess(EngineCommands):
    """Owns an engine in a child process; ``submit(command)`` returns a future of ``command(engine)``.

    ``build``, ``command`` and results must pickle (see the module docstring). ``cpu``: pin the child to this
    core and this process to the others (``None``: no pinning).
    """

    shares_interpreter = False

    def __init__(self, build: Callable[[], Any], *, cpu: int | None = None, name: str = "llrs-engine") -> None:
        self._build = build
        self.cpu = cpu
        self._name = name
        self._conn: Connection | None = None
        self._process: Any = None
        self._send_lock = threading.Lock()
        self._pending: dict[int, Future[Any]] = {}
        self._pending_lock = threading.Lock()
        self._ids = itertools.count()
        self._reader: threading.Thread | None = None
        self._dead: str | None = None
        self.config: SystemConfig | None = None  # the configuration the engine was built with
        self.has_trigger_input = False

    def start(self, *, timeout_s: float = 300.0) -> EngineProcess:
        """Start the child and wait until its engine is built (every kernel compiled); raises what the build
        raised (e.g. devices that do not open)."""
        # A fresh interpreter (never fork a process that runs threads), started as ``python -m engine.process``
        # rather than through multiprocessing, which would re-run the caller's main script in the child.
        parent_sock, child_sock = socket.socketpair()
        env = dict(os.environ, PYTHONPATH=os.pathsep.join(p or os.getcwd() for p in sys.path))
        self._process = subprocess.Popen(
            [sys.executable, "-m", "engine.process", str(child_sock.fileno())],
            pass_fds=(child_sock.fileno(),),
            env=env,
        )
        child_sock.close()
        parent_conn = Connection(parent_sock.detach())
        self._conn = parent_conn
        parent_conn.send((self._build, self.cpu))
        if not parent_conn.poll(timeout_s):
            self._kill()
            raise TimeoutError(f"the engine process was not ready after {timeout_s} s")
        try:
            kind, payload = parent_conn.recv()
        except (EOFError, OSError):
            code = self._process.wait(timeout=5)
            raise EngineProcessDied(f"the engine process exited while starting (exit code {code})") from None
        if kind == "failed":
            self._process.wait(timeout=10)
            raise payload
        self.config, self.has_trigger_input = payload
        if self.cpu is not None:
            others = os.sched_getaffinity(0) - {self.cpu}
            if others:
                os.sched_setaffinity(0, others)
        self._reader = threading.Thread(target=self._read, name=f"{self._name}-results", daemon=True)
        self._reader.start()
        return self

    @property
    def pid(self) -> int | None:
        """The engine process's id (``None`` before ``start``)."""
        return self._process.pid if self._process is not None else None

    @property
    def exit_reason(self) -> str | None:
        """How the engine process ended (``None`` while it runs or before ``start``)."""
        if self._dead is None and self._process is not None and self._process.poll() is not None:
            return _describe_exit(self._process.returncode)
        return self._dead

    @property
    def alive(self) -> bool:
        return self._process is not None and self._process.poll() is None and self._dead is None

    def submit(self, command: Callable[[Any], Any]) -> Future[Any]:
        future: Future[Any] = Future()
        # exit_reason, not _dead: the results thread notes the death a moment after the process has ended, and a
        # command sent in between would fail with a bare "Broken pipe" instead of how the engine died
        dead = self.exit_reason
        if dead is not None or self._conn is None:
            future.set_exception(EngineProcessDied(dead or "the engine process was not started"))
            return future
        ident = next(self._ids)
        with self._pending_lock:
            self._pending[ident] = future
        try:
            with self._send_lock:
                self._conn.send((ident, command))
        except Exception as err:  # an unpicklable command, or the pipe is gone
            with self._pending_lock:
                self._pending.pop(ident, None)
            unpicklable = isinstance(err, (pickle.PicklingError, AttributeError, TypeError))
            if unpicklable:
                future.set_exception(err)
            else:  # the child died before the results thread noticed: name how it ended, not the pipe
                self._reap()
                future.set_exception(EngineProcessDied(self.exit_reason or str(err)))
        return future

    def close(self, *, timeout_s: float = 10.0) -> None:
        """Ask the child to close its devices and exit; kill it if it does not within ``timeout_s``."""
        if self._process is None:
            return
        if self._process.poll() is None and self._conn is not None:
            try:
                with self._send_lock:
                    self._conn.send(None)
                self._process.wait(timeout=timeout_s)
            except (OSError, subprocess.TimeoutExpired):
                pass
        self._kill()
        if self._conn is not None:
            self._conn.close()
        if self.cpu is not None and hasattr(os, "sched_setaffinity"):
            os.sched_setaffinity(0, os.sched_getaffinity(0) | {self.cpu})

    def _reap(self, timeout_s: float = 1.0) -> int | None:
        """The exit code of a child whose pipe just closed, waiting ``timeout_s`` for it to be reaped (``None``
        if it has not ended by then)."""
        assert self._process is not None
        try:
            return self._process.wait(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            return None

    def _kill(self) -> None:
        if self._process is not None and self._process.poll() is None:
            self._process.kill()
            self._process.wait(timeout=5)

    def _read(self) -> None:
        """Results thread: hand each reply to its future; when the child is gone, fail what is pending."""
        assert self._conn is not None
        while True:
            try:
                ident, ok, payload = self._conn.recv()
            except (EOFError, OSError):
                break
            with self._pending_lock:
                future = self._pending.pop(ident, None)
            if future is None or not future.set_running_or_notify_cancel():
                continue
            if ok:
                future.set_result(payload)
            else:
                future.set_exception(payload)
        self._dead = _describe_exit(self._reap())
        with self._pending_lock:
            pending, self._pending = list(self._pending.values()), {}
        for future in pending:
            if future.set_running_or_notify_cancel():
                future.set_exception(EngineProcessDied(self._dead))


if __name__ == "__main__":
    _child_main(Connection(int(sys.argv[1])))
