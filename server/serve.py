"""``llrs serve``: the lab server in one process — engine, REST/websocket API (uvicorn) and viser dashboard.

Threads: the engine thread (owns the devices), the service's runner (continuous shots), the run store's
writer, viser's websocket thread and the dashboard's drawing thread; uvicorn runs the API on the main
thread's event loop and owns Ctrl-C / SIGTERM: when it returns, the dashboard and the engine are stopped and
the run file is closed.

Security (README, "Security"): without ``LLRS_TOKEN`` anyone who can reach the port can run shots, so the
server binds only to a loopback address unless a token is set, and then answers only to loopback host names;
with a token every mutating route needs ``Authorization: Bearer`` and the dashboard's controls need the token
too. CORS stays closed unless origins are named with ``--cors-origin``. Files named by clients come only from
``--tone-dir`` and ``--shot-dir`` (``server.files``).
"""

from __future__ import annotations

import argparse
import asyncio
import ipaddress
import os
import resource
import signal
import socket
import sys
from functools import partial
from pathlib import Path
from typing import TYPE_CHECKING, Any

from engine.config import ConfigError, SystemConfig, load_config

if TYPE_CHECKING:
    from frontend.dashboard import Dashboard

__all__ = [
    "DEFAULT_CONFIG", "add_parser", "build_engine", "engine_cpu_arg", "engine_host_factory", "is_loopback", "main"
]

#: The config ``llrs serve`` uses without ``--config``: the paper's 1x64 chain (the fastest to compile and run).
DEFAULT_CONFIG = Path(__file__).resolve().parent.parent / "examples" / "chain-1x64.yaml"


def is_loopback(host: str) -> bool:
    """True for addresses only this machine can reach (127.0.0.0/8, ::1, localhost)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False


def add_parser(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    """Register ``serve`` on the ``llrs`` command line."""
    p = sub.add_parser(
        "serve",
        help="run the lab server: engine, REST API and dashboard (simulated devices by default)",
        description="Start the engine on the configured devices, the REST/websocket API and the viser dashboard. "
        "Shots run continuously from the start (--idle to wait for a command). Set LLRS_TOKEN to require a bearer "
        "token on every mutating route; it is required to bind to a non-loopback address.",
    )
    default_config = DEFAULT_CONFIG.relative_to(DEFAULT_CONFIG.parent.parent)
    p.add_argument("--config", default=None, help=f"YAML configuration (default: {default_config})")
    p.add_argument("--host", default="127.0.0.1",
                   help="address to bind the API and the dashboard to (default 127.0.0.1)")
    p.add_argument("--port", type=int, default=8000, help="API port (default 8000; 0 picks a free one)")
    p.add_argument("--dashboard-port", type=int, default=8080, help="dashboard port (default 8080; 0 picks a free one)")
    p.add_argument("--dashboard-host", default=None,
                   help="address to bind the dashboard to (default: --host); e.g. 127.0.0.1 to keep the dashboard "
                   "on this machine while the API serves the lab network")
    p.add_argument("--runs-dir", default="runs", help="where the HDF5 run files go (default ./runs)")
    p.add_argument("--keep-frames", type=int, default=0, metavar="N",
                   help="keep the camera frames of every Nth shot in the run files (0: none, the default; 1: every "
                   "shot): every cycle's when the configuration sets loop.keep_frames, else the shot's final "
                   "frame; gzip-compressed")
    p.add_argument("--keep-frames-mib", type=float, default=256.0, metavar="MIB",
                   help="at most this many MiB of raw frames per run file (default 256)")
    p.add_argument("--pause", type=float, default=0.5, help="pause between continuous shots in seconds (default 0.5)")
    p.add_argument("--idle", action="store_true", help="do not start shots at once; wait for a command")
    p.add_argument("--no-dashboard", action="store_true", help="serve the API only")
    p.add_argument("--cors-origin", action="append", default=[],
                   help="allow browsers on this origin to call the API (repeatable)")
    p.add_argument("--trusted-host", action="append", default=[],
                   help="a Host name the server answers to (repeatable); without a token only loopback names are "
                   "answered, with a token any unless these are given")
    p.add_argument("--tone-dir", type=Path, default=None,
                   help="directory that tone CSVs (array.*_tones.csv) named in configurations sent to the API must "
                   "lie in (default: none, so the API accepts no new tone file)")
    p.add_argument("--shot-dir", type=Path, default=None,
                   help="directory that labscript shot files sent to POST /api/labscript must lie in "
                   "(default: none, so the route refuses every file)")
    p.add_argument("--engine", choices=("process", "thread"), default="process",
                   help="run the engine in a process of its own (default: its latency does not suffer from API "
                   "traffic) or on a thread of the server's process")
    p.add_argument("--engine-cpu", type=engine_cpu_arg, default="auto",
                   help="core to pin the engine process to, the server keeping the others: 'auto' (default: the "
                   "last core when there are two or more), a core number, or 'none'")
    p.set_defaults(func=main)
    return p


def build_engine(config: SystemConfig):  # noqa: ANN201 - engine.engine.Engine, imported lazily
    """The engine on the devices ``config.devices`` names (hardware or simulation, ``drivers.factory``).

    Module-level so that an engine process can be told to run it (``functools.partial(build_engine, config)``
    pickles)."""
    from drivers.factory import open_devices
    from engine.engine import Engine

    devices, lab = open_devices(config)
    return Engine(config, devices, lab=lab)


def engine_host_factory(*, in_process: bool, cpu: int | None):  # noqa: ANN201 - Callable[[SystemConfig], host]
    """How the service builds an engine for a configuration: in a process of its own pinned to ``cpu``
    (the default; see ``engine.process``) or on a thread of this process (``--engine thread``)."""
    from engine.engine import EngineThread
    from engine.process import EngineProcess

    def host(config: SystemConfig):  # noqa: ANN202 - an EngineProcess or EngineThread, imported lazily above
        build = partial(build_engine, config)
        return EngineProcess(build, cpu=cpu) if in_process else EngineThread(build)

    return host


def engine_cpu_arg(value: str) -> int | None:
    from engine.process import default_engine_cpu

    if value == "auto":
        return default_engine_cpu()
    if value == "none":
        return None
    try:
        cpu = int(value)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--engine-cpu takes a core number, 'auto' or 'none', not {value!r}") from None
    allowed = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else []
    if cpu not in allowed:
        raise argparse.ArgumentTypeError(f"--engine-cpu {cpu}: this process may use cores {allowed}")
    return cpu


#: Connections and requests uvicorn serves at once; beyond it answers 503 at once instead of queueing.
MAX_CONNECTIONS = 512


def start_dashboard(service: Any, *, host: str, port: int, api_url: str, token: str | None = None) -> Dashboard:
    """The viser dashboard over ``service``, started and listening (``.port``; ``port`` 0 picks a free one);
    ``llrs serve`` serves it beside the API, ``llrs bench load --dashboard`` in its load phase."""
    from frontend.dashboard import Dashboard  # deferred on purpose: viser loads only when a dashboard is served

    dashboard = Dashboard(service, host=host, port=port, api_url=api_url, token=token)
    dashboard.start()
    return dashboard


def _raise_open_file_limit() -> None:
    """Let this process hold as many descriptors as the system allows it (the soft limit is often 1024), so
    that a flood of connections is answered 503 by uvicorn instead of failing every accept()."""
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if hard == resource.RLIM_INFINITY or hard > soft:
        resource.setrlimit(resource.RLIMIT_NOFILE, (hard if hard != resource.RLIM_INFINITY else max(soft, 65536), hard))


def _say(text: str) -> None:
    print(text, flush=True)


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt(signal.Signals(signum).name)


def main(args: argparse.Namespace) -> int:
    # SIGTERM (docker stop, systemd, a test) ends the process like Ctrl-C: through the cleanup below.
    signal.signal(signal.SIGTERM, _interrupt)
    token = os.environ.get("LLRS_TOKEN") or None
    if not is_loopback(args.host) and token is None:
        print(
            f"llrs serve: refusing to bind to {args.host}, which other machines can reach, without a token.\n"
            "  Set LLRS_TOKEN (e.g. "
            "`export LLRS_TOKEN=$(python3 -c 'import secrets; print(secrets.token_urlsafe())')`)\n"
            "  so that every mutating request needs 'Authorization: Bearer $LLRS_TOKEN', or bind to 127.0.0.1.",
            file=sys.stderr,
        )
        return 2
    dashboard_host = args.dashboard_host or args.host
    if not is_loopback(dashboard_host) and token is None:
        print(f"llrs serve: refusing to bind the dashboard to {dashboard_host} without a token (set LLRS_TOKEN)",
              file=sys.stderr)
        return 2
    try:
        if args.config is None and not DEFAULT_CONFIG.exists():  # installed without the examples
            config = SystemConfig(name="chain-1x64 (built-in default)")
        else:
            config = load_config(args.config or DEFAULT_CONFIG)
    except ConfigError as err:
        print(f"llrs serve: {err}", file=sys.stderr)
        return 2
    from server.runstore import FrameKeeping, RunStore  # deferred, as the web stack below: h5py, the sim lab

    try:
        frames = FrameKeeping(every_nth_shot=args.keep_frames, max_mib=args.keep_frames_mib)
    except ValueError as err:
        print(f"llrs serve: --keep-frames / --keep-frames-mib: {err}", file=sys.stderr)
        return 2
    family = socket.AF_INET6 if ":" in args.host else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((args.host, args.port))
        sock.listen(2048)  # connections made once the URLs are printed wait in the backlog until uvicorn accepts
    except OSError as err:
        print(f"llrs serve: cannot listen on {args.host}:{args.port}: {err.strerror} (try --port)", file=sys.stderr)
        return 2
    api_port = sock.getsockname()[1]
    shown_host = f"[{args.host}]" if family == socket.AF_INET6 else args.host
    api_url = f"http://{shown_host}:{api_port}"
    _raise_open_file_limit()

    import uvicorn

    from server.app import create_app
    from server.security import LOOPBACK_HOSTS
    from server.service import LabService

    devices = f"camera {config.devices.camera}, AWG {config.devices.awg}"
    _say(f"llrs serve: config '{config.name}' ({config.array.nx}x{config.array.ny} traps, {devices}); "
         "starting the engine (compiling kernels: the first start takes longer)...")
    factory = engine_host_factory(in_process=args.engine == "process", cpu=args.engine_cpu)
    service = LabService(
        engine_thread=factory(config),
        store=RunStore(args.runs_dir, frames=frames),
        pause_s=args.pause,
        engine_factory=factory,
        config=config,
        tone_dir=args.tone_dir,
        shot_dir=args.shot_dir,
    )
    dashboard = None
    try:
        service.start(run=False)
        dashboard_port = None
        if not args.no_dashboard:
            dashboard = start_dashboard(
                service, host=dashboard_host, port=args.dashboard_port, api_url=api_url, token=token
            )
            dashboard_port = dashboard.port
        # Without a token the server is loopback-only, and answers only to loopback names (a page of another
        # site cannot reach it by pointing a DNS name of its own at 127.0.0.1).
        trusted: tuple[str, ...] | None = (*LOOPBACK_HOSTS, args.host.strip("[]").lower(), *args.trusted_host)
        if token is not None and not args.trusted_host:
            trusted = None
        app = create_app(
            service=service, token=token, cors_origins=tuple(args.cors_origin), trusted_hosts=trusted,
            dashboard_port=dashboard_port,
        )
        server = uvicorn.Server(
            uvicorn.Config(
                app, log_level="warning", timeout_graceful_shutdown=3, ws_ping_interval=20,
                limit_concurrency=MAX_CONNECTIONS, timeout_keep_alive=5,
            )
        )
        fault = service.status().reason
        if fault is not None:
            _say(f"llrs serve: {fault}")
        elif not args.idle:
            service.run()
        _say("")
        if dashboard_port is not None:
            shown_dashboard = f"[{dashboard_host}]" if ":" in dashboard_host else dashboard_host
            _say(f"  dashboard   http://{shown_dashboard}:{dashboard_port}/"
                 + ("   (read-only until a tab logs in with the token)" if token else ""))
        _say(f"  API         {api_url}/   (docs {api_url}/docs, live cycles ws://{shown_host}:{api_port}/api/live)")
        where = "a thread of this process" if args.engine == "thread" else "its own process" + (
            f", pinned to core {args.engine_cpu} (the server keeps the others)" if args.engine_cpu is not None else "")
        _say(f"  engine      {where}")
        _say(f"  run files   {Path(args.runs_dir).resolve()}/")
        tone_files = f"{args.tone_dir.resolve()}/" if args.tone_dir else "none accepted over the API"
        shot_files = f"{args.shot_dir.resolve()}/" if args.shot_dir else "none accepted"
        _say(f"  tone files  {tone_files} (--tone-dir)")
        _say(f"  shot files  {shot_files} (--shot-dir)")
        if token:
            _say("  token       required on mutating routes and the dashboard controls (LLRS_TOKEN)")
        else:
            _say("  token       none (loopback only)")
        shots = "idle: POST /api/run or the dashboard starts them" if args.idle else "running continuously"
        _say(f"  shots       {shots}")
        _say("Ctrl-C stops the server.")
        # uvicorn handles Ctrl-C/SIGTERM while it serves, then re-raises the signal it caught once it has
        # stopped; our handlers take that re-raised signal as noted, so the cleanup below always runs.
        caught: list[int] = []
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, lambda signum, frame: caught.append(signum))
        try:
            asyncio.run(server.serve(sockets=[sock]))
        finally:
            signal.signal(signal.SIGINT, signal.default_int_handler)  # a second Ctrl-C while stopping: force
            signal.signal(signal.SIGTERM, _interrupt)
    except KeyboardInterrupt:
        pass
    finally:
        _say("llrs serve: stopping (finishing the shot in progress, closing the devices and the run file)...")
        if dashboard is not None:
            dashboard.stop()
        service.close()
        sock.close()
    _say("llrs serve: stopped.")
    return 0
