"""``llrs bench jitter``: the gap counts and the lead come from the gaps measured, and a short run on a core
at the engine's priority reports them."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bench.jitter import core_figures, lead_for_us, measure_core
from engine.streaming import RealtimeScheduling

REPO = Path(__file__).resolve().parents[1]


def test_lead_is_the_quantile_of_the_longest_gap_per_window() -> None:
    longest = np.concatenate([np.full(990, 50.0), np.full(10, 600.0)])  # 1 % of windows stall 600 us
    assert lead_for_us(longest, 257) == 600.0  # 10 in 1000 exceed 50 us: more than 1 in 257
    assert lead_for_us(np.concatenate([np.full(999, 50.0), [600.0]]), 257) == 50.0  # 1 in 1000 < 1 in 257
    assert lead_for_us(np.full(100, 80.0), 1000) == 80.0  # fewer windows than cycles: the largest seen
    assert np.isnan(lead_for_us(np.array([]), 257))


def test_core_figures_count_gaps_per_second() -> None:
    gaps = np.array([30.0, 120.0, 400.0, 1500.0])
    fig = core_figures(gaps, np.array([120.0, 1500.0]), spin_s=2.0, cpu=1)
    assert fig["gaps"] == {">100us": 3, ">350us": 2, ">1000us": 1}
    assert fig["gaps_per_s"][">100us"] == 1.5
    assert fig["max_gap_us"] == 1500.0 and fig["largest_gaps_us"][0] == 1500.0


@pytest.mark.bench
def test_measure_core_spins_at_the_engine_priority_on_the_pinned_core() -> None:
    cpu = sorted(os.sched_getaffinity(0))[-1]
    before = os.sched_getaffinity(0)
    fig = measure_core(cpu, seconds=0.05, window_s=0.005, sleep_s=0.001, realtime=RealtimeScheduling(10))
    assert os.sched_getaffinity(0) == before and os.sched_getscheduler(0) == os.SCHED_OTHER  # all put back
    assert fig["cpu"] == cpu and fig["windows"] == 10
    assert fig["spin_s"] == pytest.approx(0.05)
    assert fig["max_gap_us"] >= fig["lead_for_1_in_257_us"] >= 0.0


@pytest.mark.bench
def test_jitter_cli_prints_one_json_object() -> None:
    out = subprocess.run(
        [sys.executable, "-m", "server.cli", "bench", "jitter", "--problem", "1x64", "--seconds", "0.05",
         "--engine-cpu", "0", "--json"],
        cwd=REPO, capture_output=True, text=True, timeout=300, check=True,
    ).stdout
    fig = json.loads(out)
    assert [c["cpu"] for c in fig["cores"]] == [0]
    assert fig["window_us"] > 0 and fig["sleep_us"] == pytest.approx(20_000)
    assert set(fig["cores"][0]["gaps_per_s"]) == {">100us", ">350us", ">1000us"}
