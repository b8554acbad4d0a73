"""``llrs bench solvers``: the figures it reports on small seeded runs, zero invalid plans, the JSON and table
output, and clear errors for unknown names."""

from __future__ import annotations

import json

import pytest

from bench.solvers import PROBLEMS, bench_solvers, format_row, plot_scaling
from server.cli import main


@pytest.fixture(scope="module")
def small() -> dict:
    return bench_solvers(instances=4, problems=["1x64", "16x32"], repeats=1)


def test_every_planner_runs_and_validates(small) -> None:
    rows = {(r["problem"], r["planner"]): r for r in small["results"]}
    assert set(rows) == {
        ("1x64", "exact-1d"),
        *(("16x32", p) for p in ("red-rec", "red-rec-wide", "aod-parallel", "aod-parallel/transfers", "assignment")),
    }
    for r in rows.values():
        assert r["invalid"] == 0 and r["lossless_success"] == 1.0
        assert r["plan_us"]["median"] > 0 and r["slots"]["median"] > 0 and r["steps_median"] > 0
        # reconfiguration time = planning + 10 us per slot, instance by instance
        assert r["reconfiguration_us"]["median"] >= 0.9 * (10 * r["slots"]["median"] + r["plan_us"]["median"])
        assert "loss_mc" not in r  # success under loss is the closed loop's figure (llrs bench assembly)
    # the transfers objective picks atoms up fewer times than the slots objective
    transfers, balanced = rows[("16x32", "aod-parallel/transfers")], rows[("16x32", "aod-parallel")]
    assert transfers["max_pickups"]["max"] <= balanced["max_pickups"]["max"]
    assert "16x32" in format_row(rows[("16x32", "aod-parallel")])


def test_cli_json_and_errors(capsys) -> None:
    assert main(["bench", "solvers", "--instances", "2", "--problems", "8x16", "--planners", "aod-parallel",
                 "--repeats", "1", "--json"]) == 0  # fmt: skip
    data = json.loads(capsys.readouterr().out)
    assert data["benchmark"] == "solvers" and len(data["results"]) == 1
    assert data["results"][0]["planner"] == "aod-parallel" and data["results"][0]["invalid"] == 0
    with pytest.raises(ValueError, match="unknown problems"):
        bench_solvers(instances=1, problems=["3x3"])
    with pytest.raises(ValueError, match="unknown planners"):
        bench_solvers(instances=1, problems=["8x16"], planners=["teleport"])
    assert {p.name for p in PROBLEMS} >= {"1x64", "16x32", "32x64", "32x64@0.5", "64x128"}


def test_plots(tmp_path, small) -> None:
    pytest.importorskip("matplotlib")
    paths = plot_scaling(small, tmp_path)
    assert [p.name for p in paths] == ["solvers_slots.png", "solvers_planning.png"]
    assert all(p.stat().st_size > 1000 for p in paths)
