"""``llrs bench load``: does the engine's latency hold while people use the server?

The server (API in this process, the engine in a process of its own pinned to a core of its own, as
``llrs serve`` runs it; ``--engine thread`` puts it on a thread of this process instead) runs shots
continuously on the simulated lab. First it runs with nobody connected (the idle baseline), then while a
client process opens 20 websocket subscriptions to ``/api/live`` (one of them never reads) and polls the
REST API at a fixed total rate (status, the shot list, single shots). With ``--dashboard`` the load phase
also serves the viser dashboard (started at the load phase, as ``llrs serve`` runs it beside the API) and
opens it in headless Chromium, which steps through its tabs (Atoms, Imaging, Traps, Assembly, History) while
it draws every shot; ``--rate 0 --ws 0`` leaves the dashboard as the only load. Reported: the software
latency (II + III + IV.lookup, and with IV.render; per rearranging cycle) idle and under load, and the API's
own latency percentiles.

Loopback only, and bounded: each phase lasts ``--seconds`` and stops by itself; the clients run in a
separate process so that their own Python work does not share the server's interpreter.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np

from bench.runtime import REPO, SOFTWARE_STAGES_WITH_RENDER, cpu_hogs, software_latencies_us
from engine.config import load_config
from engine.records import ShotRecord
from server.runstore import RunStore
from server.serve import engine_cpu_arg, engine_host_factory, start_dashboard

__all__ = ["CHROMIUM", "register", "run_load_bench", "run_load_clients"]

#: The browser ``--dashboard`` drives (Debian's chromium, which ``scripts/dev.sh`` installs; or LLRS_CHROMIUM).
CHROMIUM = os.environ.get("LLRS_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
#: The dashboard's tabs the browser steps through, one every ``TAB_PERIOD_S``.
DASHBOARD_TABS = ("Imaging", "Traps", "Assembly", "History", "Atoms")
TAB_PERIOD_S = 1.0


def _pct(values: list[float]) -> dict[str, float]:
    if not values:
        return {"n": 0, "median": float("nan"), "p95": float("nan"), "p99": float("nan"), "max": float("nan")}
    v = np.asarray(values)
    return {"n": int(v.size), "median": float(np.median(v)), "p95": float(np.percentile(v, 95)),
            "p99": float(np.percentile(v, 99)), "max": float(v.max())}


# --- the client side (run in its own process) ------------------------------------------------------------


#: How long the browser may take to start and draw the first shot (Chromium on a loaded 2-core machine is slow).
BROWSER_START_S = 120.0


async def _open_dashboard(stack: contextlib.AsyncExitStack, url: str) -> tuple[Any, dict[str, Any]]:
    """The dashboard open in headless Chromium, once it has drawn a shot: ``(page, what it saw)``; ``page`` is
    ``None`` (and the reason is in what it saw) if it could not be opened."""
    from playwright.async_api import async_playwright  # deferred on purpose: only --dashboard needs a browser

    t0 = time.perf_counter()
    seen: dict[str, Any] = {"url": url, "error": None, "tab_clicks": 0}
    try:
        p = await stack.enter_async_context(async_playwright())
        browser = await p.chromium.launch(
            executable_path=CHROMIUM, args=["--headless", "--no-sandbox", "--disable-gpu", "--no-first-run"]
        )
        stack.push_async_callback(browser.close)
        page = await browser.new_page(viewport={"width": 1400, "height": 1000})
        await page.goto(url)
        await page.wait_for_selector("#atom-map[data-outcome]", timeout=BROWSER_START_S * 1e3)
    except Exception as err:  # noqa: BLE001 - reported: a phase without the browser must not pass for one with it
        seen["error"] = f"{type(err).__name__}: {err}"[:300]
        return None, seen
    seen["first_shot_drawn_s"] = time.perf_counter() - t0
    return page, seen


async def _step_tabs(page: Any, seen: dict[str, Any], deadline: float) -> None:
    """Click the dashboard's tabs in turn, one every ``TAB_PERIOD_S``, until ``deadline`` (each tab draws its
    panels when shown), then note the last shot the page shows."""
    from playwright.async_api import TimeoutError as PageTimeout  # deferred, as in _open_dashboard

    try:
        while (left_s := deadline - time.perf_counter()) > 0:
            tab = page.get_by_role("tab", name=DASHBOARD_TABS[seen["tab_clicks"] % len(DASHBOARD_TABS)])
            try:
                await tab.click(timeout=max(1.0, left_s) * 1e3)  # a loaded machine's browser is slow to answer
            except PageTimeout:
                break  # the phase is over before the page took the click
            seen["tab_clicks"] += 1
            await asyncio.sleep(min(TAB_PERIOD_S, max(0.0, deadline - time.perf_counter())))
        shown = await page.get_attribute("#atom-map", "data-shot-id", timeout=10_000)
        seen["last_shot_shown"] = None if shown is None else int(shown)
    except Exception as err:  # noqa: BLE001 - reported, as above
        seen["error"] = f"{type(err).__name__}: {err}"[:300]


async def _clients(
    base: str, seconds: float, rate_hz: float, n_ws: int, dashboard: str | None, stack: contextlib.AsyncExitStack
) -> dict[str, Any]:
    """The load: REST pollers and websocket subscribers (and the dashboard open in a browser) for ``seconds``,
    counted from when everything is open; prints ``ready`` then, so that the server side starts measuring."""
    import httpx  # deferred on purpose: only the client process needs these
    import websockets

    page, seen = await _open_dashboard(stack, dashboard) if dashboard else (None, None)
    print("ready", flush=True)
    ws_url = base.replace("http://", "ws://") + "/api/live"
    deadline = time.perf_counter() + seconds
    received = [0] * n_ws
    ws_errors: list[str] = []

    async def subscriber(i: int) -> None:
        try:
            async with websockets.connect(ws_url, max_queue=None if i else 1) as ws:
                while time.perf_counter() < deadline:
                    if i == 0:  # the stalled browser tab: connected, never reads
                        await asyncio.sleep(0.1)
                        continue
                    try:
                        await asyncio.wait_for(ws.recv(), timeout=max(0.01, deadline - time.perf_counter()))
                        received[i] += 1
                    except TimeoutError:
                        break
        except Exception as err:  # noqa: BLE001 - reported, not fatal
            ws_errors.append(f"{type(err).__name__}: {err}")

    latencies_ms: dict[str, list[float]] = {"status": [], "shots": [], "shot": []}
    errors = 0
    last_id: list[int] = []

    async def one(client: httpx.AsyncClient, kind: str) -> None:
        nonlocal errors
        if kind == "status":
            url = "/api/status"
        elif kind == "shots" or not last_id:
            kind, url = "shots", "/api/shots?limit=5"
        else:
            url = f"/api/shots/{last_id[0]}"
        t0 = time.perf_counter()
        try:
            r = await client.get(url)
            ok = r.status_code == 200
            if ok and kind == "shots":
                items = r.json().get("shots", [])
                if items:
                    last_id[:] = [items[0]["shot_id"]]
        except Exception:  # noqa: BLE001
            ok = False
        latencies_ms[kind].append((time.perf_counter() - t0) * 1e3)
        if not ok:
            errors += 1

    async def poller() -> None:
        period = 1.0 / rate_hz
        kinds = ("status", "shots", "status", "shot")
        tasks: set[asyncio.Task[None]] = set()
        async with httpx.AsyncClient(base_url=base, timeout=5.0, limits=httpx.Limits(max_connections=32)) as client:
            i = 0
            t_next = time.perf_counter()
            while t_next < deadline:
                task = asyncio.create_task(one(client, kinds[i % len(kinds)]))
                tasks.add(task)
                task.add_done_callback(tasks.discard)
                i += 1
                t_next += period
                await asyncio.sleep(max(0.0, t_next - time.perf_counter()))
            if tasks:
                await asyncio.wait(tasks, timeout=5.0)

    loads = [*([poller()] if rate_hz > 0 else []), *(subscriber(i) for i in range(n_ws))]
    await asyncio.gather(*loads, *([_step_tabs(page, seen, deadline)] if page is not None and seen else []))
    all_ms = [v for vs in latencies_ms.values() for v in vs]
    return {
        "requests": len(all_ms),
        "errors": errors,
        "rate_hz": len(all_ms) / seconds,
        "api_ms": _pct(all_ms),
        "api_ms_by_route": {k: _pct(v) for k, v in latencies_ms.items()},
        "ws_clients": n_ws,
        "ws_messages_per_reading_client": float(np.mean(received[1:])) if n_ws > 1 else 0.0,
        "ws_errors": ws_errors[:5],
        "browser": seen,
    }


def run_load_clients(
    base: str, seconds: float, rate_hz: float, n_ws: int, dashboard: str | None = None
) -> dict[str, Any]:
    async def run() -> dict[str, Any]:
        async with contextlib.AsyncExitStack() as stack:  # the browser, closed once the figures are in
            return await _clients(base, seconds, rate_hz, n_ws, dashboard, stack)

    return asyncio.run(run())


# --- the server side ---------------------------------------------------------------------------------------


def _serve(config_path: str, runs_dir: str, *, in_process: bool, cpu: int | None):  # noqa: ANN202 - (service, server, thread, url)
    # deferred on purpose: ``llrs`` imports every benchmark to list it, and the web stack (fastapi, uvicorn,
    # the lab service: about 2 s to import) should load only when this benchmark runs
    import uvicorn

    from server.app import create_app
    from server.service import LabService

    config = load_config(config_path)
    host = engine_host_factory(in_process=in_process, cpu=cpu)
    service = LabService(engine_thread=host(config), store=RunStore(runs_dir), pause_s=0.0)
    service.start(run=False)
    app = create_app(service=service)
    server = uvicorn.Server(uvicorn.Config(app, host="127.0.0.1", port=0, log_level="warning"))
    thread = threading.Thread(target=server.run, name="bench-uvicorn", daemon=True)
    thread.start()
    while not server.started:
        time.sleep(0.01)
    port = server.servers[0].sockets[0].getsockname()[1]
    return service, server, thread, f"http://127.0.0.1:{port}"


def _collect(service, seconds: float) -> list[ShotRecord]:  # noqa: ANN001
    records: list[ShotRecord] = []
    service.add_listener(records.append)
    time.sleep(seconds)
    service.remove_listener(records.append)
    return list(records)


def run_load_bench(
    config_path: str, seconds: float, rate_hz: float, n_ws: int, *, in_process: bool = True, cpu: int | None = None,
    hogs: int = 0, dashboard: bool = False,
) -> dict[str, Any]:
    """Idle phase, then the load phase, each ``seconds`` long, with ``hogs`` CPU-bound processes running beside
    the server in both; with ``dashboard`` the load phase also serves the dashboard, open in headless
    Chromium. The figures ``llrs bench load --json`` prints."""
    if dashboard and not Path(CHROMIUM).exists():
        raise FileNotFoundError(f"--dashboard needs Chromium, and there is none at {CHROMIUM} "
                                "(bash scripts/dev.sh installs Debian's chromium; or set LLRS_CHROMIUM)")
    served_dashboard = None
    with tempfile.TemporaryDirectory(prefix="llrs-load-") as runs, cpu_hogs(hogs):
        service, server, thread, base = _serve(config_path, runs, in_process=in_process, cpu=cpu)
        try:
            service.run()
            _collect(service, min(2.0, seconds / 4))  # warm up: caches, the run file, the first shots
            idle = _collect(service, seconds)
            command = [sys.executable, "-m", "bench.load", "--clients-only", base, "--seconds", str(seconds),
                       "--rate", str(rate_hz), "--ws", str(n_ws)]
            if dashboard:
                served_dashboard = start_dashboard(service, host="127.0.0.1", port=0, api_url=base)
                command += ["--dashboard", f"http://127.0.0.1:{served_dashboard.port}/"]
                drawn_before = served_dashboard.updates
            proc = subprocess.Popen(command, stdout=subprocess.PIPE, cwd=REPO, text=True)
            assert proc.stdout is not None
            proc.stdout.readline()  # "ready": the clients are up (the browser has drawn a shot), or they failed
            loaded = _collect(service, seconds)
            try:  # the clients finish their last requests and close the browser: slow on a loaded machine
                out, _ = proc.communicate(timeout=seconds + 180)
            except subprocess.TimeoutExpired:
                proc.kill()
                raise
            clients = json.loads(out.strip().splitlines()[-1])
            if served_dashboard is not None:
                clients["dashboard_updates"] = served_dashboard.updates - drawn_before
        finally:
            service.stop()
            server.should_exit = True
            thread.join(timeout=10)
            if served_dashboard is not None:
                served_dashboard.stop()
            service.close()
    result: dict[str, Any] = {
        "config": str(config_path),
        "engine": f"process on core {cpu}" if in_process and cpu is not None else "process" if in_process else "thread",
        "seconds_per_phase": seconds,
        "cpu_hogs": hogs,
        "dashboard": dashboard,
    }
    for phase, records in (("idle", idle), ("load", loaded)):
        result[phase] = {
            "shots": len(records),
            "underruns": sum(c.underruns for r in records for c in r.cycles),
            "software_latency_us": _pct(software_latencies_us(records)),
            "software_latency_with_render_us": _pct(software_latencies_us(records, SOFTWARE_STAGES_WITH_RENDER)),
        }
    result["load"]["clients"] = clients
    for key, growth in (("software_latency_us", "p99_growth"),
                        ("software_latency_with_render_us", "p99_growth_with_render")):
        p_idle, p_load = result["idle"][key]["p99"], result["load"][key]["p99"]
        result[growth] = (p_load / p_idle - 1.0) if p_idle and np.isfinite(p_idle) else float("nan")
    return result


def _print(r: dict[str, Any]) -> None:
    print(f"config {r['config']}, engine: {r['engine']}, {r['seconds_per_phase']:g} s per phase, "
          f"{r['cpu_hogs']} CPU hogs beside it")
    for key, what, growth in (("software_latency_us", "II+III+IV.lookup", "p99_growth"),
                              ("software_latency_with_render_us", "... + IV.render", "p99_growth_with_render")):
        for phase in ("idle", "load"):
            s = r[phase][key]
            print(f"{phase:5s}: {r[phase]['shots']:4d} shots, {s['n']:4d} rearranging cycles, "
                  f"{r[phase]['underruns']} underruns; {what} median "
                  f"{s['median']:.1f} us, p99 {s['p99']:.1f} us, max {s['max']:.1f} us")
        print(f"p99 growth under load ({what}): {100 * r[growth]:+.1f} %")
    c = r["load"]["clients"]
    a = c["api_ms"]
    print(f"API: {c['requests']} requests at {c['rate_hz']:.0f}/s, {c['errors']} errors; latency median "
          f"{a['median']:.2f} ms, p95 {a['p95']:.2f} ms, p99 {a['p99']:.2f} ms, max {a['max']:.2f} ms")
    print(f"websockets: {c['ws_clients']} clients (one never reads), "
          f"{c['ws_messages_per_reading_client']:.0f} messages each; errors {c['ws_errors']}")
    if (b := c.get("browser")) is not None:
        seen = (f"first shot drawn after {b['first_shot_drawn_s']:.1f} s, {b['tab_clicks']} tab clicks, "
                f"{c.get('dashboard_updates', 0)} dashboard updates" if b["error"] is None else f"ERROR {b['error']}")
        print(f"dashboard {b['url']} open in headless Chromium: {seen}")


def _cmd(args: argparse.Namespace) -> int:
    result = run_load_bench(
        args.config, args.seconds, args.rate, args.ws, in_process=args.engine == "process", cpu=args.engine_cpu,
        hogs=args.cpu_hogs, dashboard=args.dashboard,
    )
    print(json.dumps(result)) if args.json else _print(result)
    return 0


def register(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser("load", help="engine latency idle vs while websocket and REST clients use the server")
    p.add_argument("--config", default=str(REPO / "examples/grid-32x64.yaml"),
                   help="configuration (default 32x64 red-rec)")
    p.add_argument("--seconds", type=float, default=20.0, help="length of each phase (default 20 s)")
    p.add_argument("--rate", type=float, default=200.0, help="REST requests per second in total (default 200)")
    p.add_argument("--ws", type=int, default=20, help="websocket subscribers, one of which never reads (default 20)")
    p.add_argument("--engine", choices=("process", "thread"), default="process",
                   help="the engine in a process of its own (default, as llrs serve) or on a thread of the server's")
    p.add_argument("--engine-cpu", type=engine_cpu_arg, default="auto",
                   help="core for the engine process ('auto': the last of two or more, a number, or 'none')")
    p.add_argument("--cpu-hogs", type=int, default=0, metavar="N",
                   help="run N CPU-bound processes beside the server in both phases (a busy lab PC; default 0)")
    p.add_argument("--dashboard", action="store_true",
                   help="in the load phase also serve the dashboard and open it in headless Chromium (with --rate 0 "
                   "--ws 0: the dashboard alone)")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd)


def _clients_main(argv: list[str]) -> None:
    p = argparse.ArgumentParser()
    p.add_argument("--clients-only", required=True)
    p.add_argument("--seconds", type=float, required=True)
    p.add_argument("--rate", type=float, required=True)
    p.add_argument("--ws", type=int, required=True)
    p.add_argument("--dashboard", default=None)
    a = p.parse_args(argv)
    print(json.dumps(run_load_clients(a.clients_only, a.seconds, a.rate, a.ws, a.dashboard)))


if __name__ == "__main__":
    _clients_main(sys.argv[1:])
