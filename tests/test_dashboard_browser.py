"""End to end, as a person would: ``llrs serve`` in a subprocess on the simulated lab (real engine, 1x64 chain),
the dashboard opened in headless Chromium (Debian's, driven by playwright), the API used over HTTP and
websockets, and a screenshot of the dashboard once it shows a completed shot.

The screenshot goes to the test's temporary folder; set ``LLRS_DASHBOARD_PNG=docs/dashboard.png`` to refresh
the README's picture. ``scripts/dev.sh test`` installs Chromium when it is missing; the test skips (saying
why) only where no Chromium can be found at all.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest

from conftest import wait_until
from engine.config import load_config
from engine.psf import frame_shape

ROOT = Path(__file__).resolve().parent.parent
CHROMIUM = os.environ.get("LLRS_CHROMIUM") or shutil.which("chromium") or "/usr/bin/chromium"
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-quic",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
START_TIMEOUT_S = 240  # a cold numba cache compiles every kernel first

if not Path(CHROMIUM).exists():
    pytest.skip(
        f"no Chromium at {CHROMIUM} (bash scripts/dev.sh test installs Debian's chromium; or set LLRS_CHROMIUM)",
        allow_module_level=True,
    )
sync_playwright = pytest.importorskip("playwright.sync_api", reason="playwright is in the dev extra").sync_playwright


class Served:
    def __init__(self, proc: subprocess.Popen[str], api: str, dashboard: str, lines: list[str]) -> None:
        self.proc, self.api, self.dashboard, self.lines = proc, api, dashboard, lines


@contextmanager
def llrs_serve(*args: str, env: dict[str, str]) -> Iterator[Served]:
    """``llrs serve --port 0 --dashboard-port 0 *args`` in a subprocess, yielded once it has printed its URLs
    (the test fails with its output if it does not), stopped with Ctrl-C at the end; its output is kept in
    ``Served.lines``."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "server.cli", "serve", "--port", "0", "--dashboard-port", "0", *args],
        cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
    )
    lines: list[str] = []
    api = dashboard = None
    deadline = time.monotonic() + START_TIMEOUT_S
    assert proc.stdout is not None
    while time.monotonic() < deadline and (api is None or dashboard is None):
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if m := re.match(r"\s+dashboard\s+(http://\S+)", line):
            dashboard = m.group(1)
        if m := re.match(r"\s+API\s+(http://\S+?)/?\s", line):
            api = m.group(1)
    if api is None or dashboard is None:
        proc.kill()
        pytest.fail("llrs serve did not print its URLs:\n" + "".join(lines))
    try:
        yield Served(proc, api, dashboard, lines)
    finally:
        proc.send_signal(signal.SIGINT)
        try:
            out, _ = proc.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
        lines.append(out)


@pytest.fixture(scope="module")
def served(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Served]:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.pop("LLRS_TOKEN", None)
    with llrs_serve("--runs-dir", str(tmp_path_factory.mktemp("runs")), "--pause", "0.3", env=env) as running:
        yield running


@pytest.fixture(scope="module")
def browser(served: Served) -> Iterator[object]:
    with sync_playwright() as p:
        b = p.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            yield b
        finally:
            b.close()


def test_serve_prints_urls_and_runs_shots_on_the_simulated_lab(served: Served) -> None:
    assert served.api.startswith("http://127.0.0.1:") and served.dashboard.startswith("http://127.0.0.1:")
    index = httpx.get(served.api + "/").text
    assert f'href="{served.dashboard}"' in index  # GET / links the dashboard
    wait_until(lambda: httpx.get(served.api + "/api/status").json()["shots_done"] >= 2, timeout_s=60,
               what="two shots on the served lab")
    status = httpx.get(served.api + "/api/status").json()
    assert status["state"] == "running" and status["devices"]["camera"] == "sim"
    assert status["last_shot"]["target_filled"] is not None  # the simulated world's ground truth


def test_dashboard_shows_a_completed_shot(served: Served, browser: object, tmp_path: Path) -> None:
    page = browser.new_page(viewport={"width": 1440, "height": 900})  # type: ignore[attr-defined]
    try:
        t0 = time.monotonic()
        page.goto(served.dashboard)
        page.wait_for_selector("#atom-map[data-outcome]", timeout=60_000)
        seconds = time.monotonic() - t0
        # A shot run over REST shows up in the dashboard (stop first, so nothing replaces it on screen).
        httpx.post(served.api + "/api/stop")
        for _ in range(8):  # a defect-free shot for the picture (about 2 in 3 are, with losses on)
            shot = httpx.post(served.api + "/api/shots", timeout=60).json()
            if shot["outcome"] == "success":
                break
        page.wait_for_selector(f"#atom-map[data-shot-id='{shot['shot_id']}']", timeout=20_000)
        shown = page.eval_on_selector(
            "#atom-map",
            """e => ({outcome: e.dataset.outcome, cycles: +e.dataset.cycles,
                     maps: e.querySelectorAll('svg.atom-map').length,
                     traps: e.querySelector('svg.atom-map').querySelectorAll('circle').length,
                     missing: [...e.querySelectorAll('.cycle')].map(c => +c.dataset.missing)})""",
        )
        # one map per cycle (before each rearrangement, then the final image), 64 traps each
        assert shown["outcome"] == shot["outcome"] and shown["maps"] == shown["cycles"] == len(shot["cycles"])
        assert shown["traps"] == 64
        assert shown["missing"] == [c["defects"] for c in shot["cycles"]]
        if shot["outcome"] == "success":
            assert shown["missing"][-1] == 0
        page.wait_for_selector("#timing tr[data-stage='I.acquire']")
        page.wait_for_selector(f"#lab-status[data-shots='{shot['shot_id'] + 1}']")
        # viser's notice that headless Chromium renders WebGL in software is not part of our dashboard
        page.add_style_tag(content=".mantine-Notifications-root { display: none !important; }")
        page.wait_for_timeout(1500)  # let the plots and the camera image settle
        out = tmp_path / "dashboard.png"
        page.screenshot(path=str(out))
        assert out.stat().st_size > 20_000
        if target := os.environ.get("LLRS_DASHBOARD_PNG"):
            shutil.copyfile(out, ROOT / target)
        print(f"atom map shown {seconds:.1f} s after opening the page; screenshot {out}")
    finally:
        page.close()
        httpx.post(served.api + "/api/run")


def test_dashboard_physicist_panels_with_real_data(served: Served, browser: object, tmp_path: Path) -> None:
    """After a few shots on the simulated lab: the imaging histogram with two fitted populations and the
    threshold, per-trap maps with the array's shape, the assembly panel, and a recorded shot stepped through."""
    deadline = time.monotonic() + 120
    while httpx.get(served.api + "/api/status").json()["shots_done"] < 6:
        assert time.monotonic() < deadline
        time.sleep(0.3)
    stats = httpx.get(served.api + "/api/stats").json()
    assert stats["shape"] == [1, 64] and stats["imaging"]["fit"] is not None
    page = browser.new_page(viewport={"width": 1440, "height": 900})  # type: ignore[attr-defined]
    try:
        page.goto(served.dashboard)
        page.wait_for_selector("#atom-map[data-outcome]", timeout=60_000)
        page.add_style_tag(content=".mantine-Notifications-root { display: none !important; }")
        page.get_by_role("tab", name="Traps").click()
        page.wait_for_selector("#trap-maps svg.heatmap[data-rows='1'][data-cols='64']", timeout=30_000)
        assert page.eval_on_selector("#trap-maps svg.heatmap", "e => e.querySelectorAll('rect title').length") == 64
        page.get_by_role("tab", name="Assembly").click()
        page.wait_for_selector("#assembly[data-shots]:not([data-shots='0'])", timeout=30_000)
        page.get_by_text("Cycles per shot (histogram)").wait_for(timeout=10_000)
        page.get_by_role("tab", name="History").click()
        page.get_by_role("button", name="List run files").click()
        page.wait_for_selector("#history[data-shot-id]", timeout=30_000)
        cycles = int(page.eval_on_selector("#history", "e => e.dataset.cycles"))
        for cycle in range(1, cycles):  # step through the recorded shot's cycles
            field = page.get_by_role("textbox", name="Cycle", exact=True)
            field.fill(str(cycle))
            field.press("Enter")
            page.wait_for_selector(f"#history[data-cycle='{cycle}']", timeout=20_000)
        page.get_by_role("tab", name="Imaging").click()
        page.wait_for_selector("#imaging[data-fit='1']", timeout=30_000)
        page.get_by_text("threshold in use").first.wait_for(timeout=10_000)
        page.wait_for_timeout(1500)  # let the plots settle
        out = tmp_path / "dashboard_physics.png"
        page.screenshot(path=str(out))
        assert out.stat().st_size > 20_000
        if target := os.environ.get("LLRS_DASHBOARD_PHYSICS_PNG"):
            shutil.copyfile(out, ROOT / target)
    finally:
        page.close()


def test_dashboard_controls_reach_the_service(served: Served, browser: object) -> None:
    """Stop and one shot from the browser; the API sees the effect."""
    page = browser.new_page(viewport={"width": 1440, "height": 900})  # type: ignore[attr-defined]
    try:
        page.goto(served.dashboard)
        page.wait_for_selector("#atom-map[data-outcome]", timeout=60_000)
        page.get_by_role("button", name="Stop").click()
        page.wait_for_selector("#lab-status[data-state='idle']", timeout=20_000)
        done = httpx.get(served.api + "/api/status").json()["shots_done"]
        page.get_by_role("button", name="One shot").click()
        page.wait_for_selector(f"#lab-status[data-shots='{done + 1}']", timeout=20_000)
        status = httpx.get(served.api + "/api/status").json()
        assert status["shots_done"] == done + 1 and status["state"] == "idle"
        page.get_by_role("button", name="Run continuously").click()
        page.wait_for_selector("#lab-status[data-state='running']", timeout=20_000)
    finally:
        page.close()


def test_sequencer_shot_over_rest_and_live_websocket(served: Served) -> None:
    """What the README shows: a sequencer's one shot per experimental cycle, and the live feed."""
    from websockets.sync.client import connect

    ws_url = served.api.replace("http://", "ws://") + "/api/live"
    with connect(ws_url, open_timeout=10) as ws:
        first = json.loads(ws.recv(timeout=30))
        assert first["type"] == "cycle" and len(first["occupancy"][0]) == 64
    httpx.post(served.api + "/api/stop")
    r = httpx.post(served.api + "/api/shots", json={"config": {"sim": {"loading_probability": 0.9}}}, timeout=60)
    assert r.status_code == 200
    shot = r.json()
    assert shot["atoms_loaded"] > 40 and shot["cycles"][0]["stage_us"]["I.acquire"] > 20_000  # 20 ms exposure
    last = len(shot["cycles"]) - 1
    png = httpx.get(f"{served.api}/api/shots/{shot['shot_id']}/image/{last}")  # the final frame is kept
    assert png.status_code == 200 and png.headers["content-type"] == "image/png"
    height, width = frame_shape(load_config(ROOT / "examples/chain-1x64.yaml").camera)  # the served example's
    assert png.content[16:24] == width.to_bytes(4, "big") + height.to_bytes(4, "big")  # IHDR: ROI, binned
    r = httpx.get(f"{served.api}/api/shots/{shot['shot_id']}/image/{last + 1}")
    assert r.status_code == 404 and "final frame" in r.json()["detail"]
    r = httpx.patch(served.api + "/api/config", json={"sim": {"loading_probability": 2}})
    assert r.status_code == 422 and r.json()["detail"][0]["loc"] == ["body", "sim", "loading_probability"]
    httpx.post(served.api + "/api/run")


def test_serve_stops_cleanly(served: Served) -> None:
    served.proc.send_signal(signal.SIGINT)
    out, _ = served.proc.communicate(timeout=30)
    assert served.proc.returncode == 0, out
    assert "llrs serve: stopped." in out
