"""``llrs bench runtime`` and ``llrs bench load`` on the 1D chain, briefly: the figures they print are there,
consistent with the shot records they come from, and the load test really loads the server."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.load import CHROMIUM, run_load_bench
from bench.runtime import (
    SOFTWARE_STAGES,
    SOFTWARE_STAGES_WITH_RENDER,
    plot_stacked,
    problem_config,
    run_problem,
    runtime_figures,
    software_latencies_us,
)
from bench.soak import rss_mb, run_soak

REPO = Path(__file__).resolve().parents[1]


def test_runtime_figures_agree_with_the_records(tmp_path: Path) -> None:
    records = run_problem(problem_config("1x64", seed=3), shots=6)
    fig = runtime_figures(records, "1x64")
    plot_stacked({"1x64": fig}, tmp_path / "table1.png")
    assert (tmp_path / "table1.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert fig["shots"] == 6
    lookup = software_latencies_us(records)
    with_render = software_latencies_us(records, SOFTWARE_STAGES_WITH_RENDER)
    assert fig["rearranging_cycles"] == len(lookup) == sum(c.n_slots > 0 for r in records for c in r.cycles) > 0
    assert np.all(np.asarray(with_render) > np.asarray(lookup))  # rendering takes time
    assert fig["software_latency_us"]["median"] == pytest.approx(np.median(lookup))
    assert fig["software_latency_with_render_us"]["median"] == pytest.approx(np.median(with_render))
    for stage in SOFTWARE_STAGES:
        entry = fig["stages"][stage]
        assert entry["n"] > 0 and entry["median"] <= entry["p99"] <= entry["max"]
    assert fig["stages"]["II.detect"]["paper_mean"] == 259.0


def test_runtime_cli_prints_one_json_object_per_problem() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "server.cli", "bench", "runtime", "--problems", "1x64", "--shots", "3", "--json"],
        cwd=REPO, capture_output=True, text=True, timeout=300, check=True,
    ).stdout
    figures = json.loads(out)
    assert set(figures) == {"1x64"}
    assert set(figures["1x64"]["software_latency_us"]) == {"mean", "median", "p99", "max"}


@pytest.mark.bench
def test_load_bench_loads_the_server_and_reports_both_phases() -> None:
    result = run_load_bench(str(REPO / "examples/chain-1x64.yaml"), seconds=1.5, rate_hz=40, n_ws=3, cpu=None)
    assert result["engine"] == "process"
    for phase in ("idle", "load"):
        assert result[phase]["shots"] > 0
        assert result[phase]["software_latency_us"]["n"] > 0
    clients = result["load"]["clients"]
    # a sustained stream of answered requests (60 asked for); the rate reached is the benchmark's figure, not a
    # test's: on a busy 2-core machine the client process's own start-up eats into the 1.5 s phase
    assert clients["errors"] == 0 and clients["requests"] >= 15
    assert clients["ws_clients"] == 3 and clients["ws_messages_per_reading_client"] > 0
    assert np.isfinite(result["p99_growth"])


@pytest.mark.bench
@pytest.mark.skipif(not Path(CHROMIUM).exists(), reason=f"no Chromium at {CHROMIUM} (bash scripts/dev.sh installs it)")
def test_load_bench_opens_the_dashboard_in_a_browser_for_the_load_phase() -> None:
    """``--dashboard`` with no other client: the load phase is measured once the browser has drawn a shot,
    while the dashboard draws the shots and the browser steps through its tabs."""
    pytest.importorskip("playwright.async_api", reason="playwright is in the dev extra")
    result = run_load_bench(
        str(REPO / "examples/chain-1x64.yaml"), seconds=3.0, rate_hz=0, n_ws=0, cpu=None, dashboard=True
    )
    assert result["dashboard"] is True
    clients = result["load"]["clients"]
    browser = clients["browser"]
    assert browser["error"] is None and browser["first_shot_drawn_s"] > 0 and browser["tab_clicks"] >= 1
    assert browser["last_shot_shown"] is not None and clients["dashboard_updates"] > 0
    assert clients["requests"] == 0 and clients["ws_clients"] == 0  # the dashboard was the only load
    for phase in ("idle", "load"):
        assert result[phase]["software_latency_us"]["n"] > 0
    assert np.isfinite(result["p99_growth"])


@pytest.mark.bench
def test_soak_records_every_shot_and_samples_both_processes() -> None:
    result = run_soak(str(REPO / "examples/chain-1x64.yaml"), 40, warmup=10, sample_every=10, progress=False)
    assert result["engine"] == "process"
    assert result["shots"] == result["shots_on_disk"] >= 40
    assert [n for n, _ in result["rss_samples"]] == [10, 20, 30, 40]
    assert all(mb > rss_mb() for _, mb in result["rss_samples"])  # this process plus the engine's
    assert sum(result["outcomes"].values()) == result["shots"]
