"""``llrs bench solvers``: every planner on seeded random instances, replayed by the validator.

Problems: the paper's three (1x64 -> 32, 16x32 -> 16x16, 32x64 -> 32x32 at loading 0.6), the two grids at
loading 0.5, and a scaling series of ``n x 2n`` grids up to 64x128 (band targets of half the traps). For
each planner and problem it reports

- planning time (``solve_moves`` + ``batch``, the engine's III.solve + III.batch) median and p99 in us, the
  best of ``--repeats`` calls per instance (this 2-core machine is shared, so single calls carry other
  processes' noise);
- one-site steps, atoms moved and the most pick-ups of one atom (from the validator's replay);
- waveform slots and the reconfiguration time = planning + slots x 10 us (the slot duration);
- lossless success: the share of solvable instances whose plan the validator accepts and that fill the
  target (``invalid`` counts plans it rejects: the goal is zero).

How often a shot ends with a defect-free array under loss is not measured here: a plan-level Monte Carlo
that charges only the streaming time misses the images, the detection and the vacuum loss between them, and
claimed success rates the closed loop does not reach. ``llrs bench assembly`` measures that figure in the
closed loop on the simulated lab.

Instances are ``numpy.random.default_rng(seed)`` fillings with seeds from 0 up, keeping the solvable ones
(``solvable_fillings``, which ``llrs bench redrec`` draws from too).

    llrs bench solvers [--instances N] [--json] [--problems 32x64,...] [--planners ...] [--plots DIR]
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from engine.solvers import Solver
from engine.solvers.validate import InvalidPlan, validate
from engine.targets import centre_target

__all__ = [
    "PLANNERS", "PROBLEMS", "Problem", "bench_solvers", "plot_scaling", "register", "solvable_fillings",
]


@dataclass(frozen=True)
class Problem:
    name: str
    nx: int
    ny: int
    loading: float
    group: str  # "paper", "loading" or "scaling"

    @property
    def trap_source(self) -> str:
        return "aod" if self.ny == 1 else "slm"

    def target(self) -> np.ndarray:
        return centre_target(nx=self.nx, ny=self.ny, count=self.nx * self.ny // 2)


PROBLEMS: tuple[Problem, ...] = (
    Problem("1x64", 64, 1, 0.6, "paper"),
    Problem("16x32", 16, 32, 0.6, "paper"),
    Problem("32x64", 32, 64, 0.6, "paper"),
    Problem("16x32@0.5", 16, 32, 0.5, "loading"),
    Problem("32x64@0.5", 32, 64, 0.5, "loading"),
    Problem("8x16", 8, 16, 0.6, "scaling"),
    Problem("24x48", 24, 48, 0.6, "scaling"),
    Problem("48x96", 48, 96, 0.6, "scaling"),
    Problem("64x128", 64, 128, 0.6, "scaling"),
)

#: label -> (algorithm, objective). A chain (ny = 1) only has exact-1d.
PLANNERS: dict[str, tuple[str, str]] = {
    "exact-1d": ("exact-1d", "slots"),
    "red-rec": ("red-rec", "slots"),
    "red-rec-wide": ("red-rec-wide", "slots"),
    "aod-parallel": ("aod-parallel", "slots"),
    "aod-parallel/transfers": ("aod-parallel", "transfers"),
    "assignment": ("assignment", "slots"),
}

ASSIGNMENT_MAX_TRAPS = 2048  # its O(n^3) assignment is for arrays up to about 32 x 64


def _applies(label: str, problem: Problem) -> bool:
    algorithm = PLANNERS[label][0]
    if problem.ny == 1:
        return algorithm == "exact-1d"
    if algorithm == "exact-1d":
        return False
    if algorithm == "assignment":
        return problem.nx * problem.ny <= ASSIGNMENT_MAX_TRAPS
    return True


def solvable_fillings(ny: int, nx: int, n: int, *, loading: float, need: int) -> tuple[list[np.ndarray], int]:
    """The first ``n`` fillings ``default_rng(seed).random((ny, nx)) < loading`` (seeds 0, 1, ...) holding at
    least ``need`` atoms, and how many seeds had too few on the way. Every benchmark that compares planners
    draws its instances here, so their figures are over the same fillings."""
    out: list[np.ndarray] = []
    seed = 0
    unsolvable = 0
    while len(out) < n:
        occ = np.random.default_rng(seed).random((ny, nx)) < loading
        seed += 1
        if occ.sum() >= need:
            out.append(occ)
        else:
            unsolvable += 1
    return out, unsolvable


def _pct(values: Sequence[float] | np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else float("nan")


def bench_one(
    label: str, problem: Problem, occs: list[np.ndarray], *, repeats: int = 3, slot_s: float = 10e-6,
) -> dict[str, Any]:
    """All figures for one planner on one problem (``occs``: solvable instances)."""
    algorithm, objective = PLANNERS[label]
    target = problem.target()
    t0 = time.perf_counter()
    solver = Solver(nx=problem.nx, ny=problem.ny, algorithm=algorithm, trap_source=problem.trap_source,
                    objective=objective)  # fmt: skip
    build_s = time.perf_counter() - t0
    solver.check_target(target)
    for occ in occs[: min(5, len(occs))]:  # warm caches
        solver.solve_moves(occ, target)
        solver.batch()
    plan_us, solve_us, batch_us = [], [], []
    slots, steps, moved, pickups = [], [], [], []
    invalid = 0
    failures: list[str] = []
    for occ in occs:
        best = (math.inf, 0.0, 0.0)
        for _ in range(max(1, repeats)):
            a = time.perf_counter_ns()
            solver.solve_moves(occ, target)
            b = time.perf_counter_ns()
            plan = solver.batch()
            c = time.perf_counter_ns()
            if c - a < best[0]:
                best = (c - a, b - a, c - b)
        plan_us.append(best[0] / 1e3)
        solve_us.append(best[1] / 1e3)
        batch_us.append(best[2] / 1e3)
        try:
            report = validate(plan, occ, target, trap_source=problem.trap_source)
        except InvalidPlan as err:
            invalid += 1
            if len(failures) < 3:
                failures.append(str(err))
            continue
        slots.append(plan.n_slots)
        steps.append(report.steps)
        moved.append(report.atoms_moved)
        pickups.append(report.max_pickups_per_atom)
    reconf_us = np.asarray(plan_us)[: len(slots)] + np.asarray(slots) * slot_s * 1e6 if slots else np.zeros(0)
    out: dict[str, Any] = {
        "planner": label,
        "algorithm": algorithm,
        "objective": objective,
        "problem": problem.name,
        "nx": problem.nx,
        "ny": problem.ny,
        "loading": problem.loading,
        "instances": len(occs),
        "build_s": build_s,
        "plan_us": {"median": _pct(plan_us, 50), "p99": _pct(plan_us, 99), "max": float(max(plan_us))},
        "solve_us_median": _pct(solve_us, 50),
        "batch_us_median": _pct(batch_us, 50),
        "steps_median": _pct(steps, 50),
        "atoms_moved_median": _pct(moved, 50),
        "max_pickups": {"median": _pct(pickups, 50), "max": int(max(pickups)) if pickups else None},
        "slots": {"median": _pct(slots, 50), "p95": _pct(slots, 95), "max": int(max(slots)) if slots else None},
        "reconfiguration_us": {"median": _pct(reconf_us, 50), "p99": _pct(reconf_us, 99)},
        "lossless_success": (len(occs) - invalid) / len(occs) if occs else float("nan"),
        "invalid": invalid,
    }
    if failures:
        out["invalid_examples"] = failures
    return out


def bench_solvers(
    *, instances: int = 100, problems: list[str] | None = None, planners: list[str] | None = None,
    repeats: int = 3, scaling_instances: int | None = None, progress: Any = None,
) -> dict[str, Any]:
    """Run the benchmark; returns one JSON-able object (``results``: one entry per planner and problem)."""
    chosen = [p for p in PROBLEMS if problems is None or p.name in problems]
    unknown = set(problems or []) - {p.name for p in PROBLEMS}
    if unknown:
        raise ValueError(f"unknown problems {sorted(unknown)}; choose from {[p.name for p in PROBLEMS]}")
    labels = list(PLANNERS) if planners is None else planners
    bad = set(labels) - set(PLANNERS)
    if bad:
        raise ValueError(f"unknown planners {sorted(bad)}; choose from {list(PLANNERS)}")
    results = []
    seeds_unsolvable = {}
    for problem in chosen:
        n = instances if problem.group != "scaling" or scaling_instances is None else scaling_instances
        occs, unsolvable = solvable_fillings(problem.ny, problem.nx, n, loading=problem.loading,
                                             need=int(problem.target().sum()))
        seeds_unsolvable[problem.name] = unsolvable
        for label in labels:
            if not _applies(label, problem):
                continue
            res = bench_one(label, problem, occs, repeats=repeats)
            res["unsolvable_seeds_skipped"] = unsolvable
            results.append(res)
            if progress is not None:
                progress(res)
    return {
        "benchmark": "solvers",
        "machine": f"{platform.processor() or platform.machine()}, {platform.system()} {platform.release()}",
        "python": platform.python_version(),
        "instances": instances,
        "repeats": repeats,
        "results": results,
    }


_HEADER = (
    f"{'problem':<11}{'planner':<23}{'plan med':>9}{'p99':>8}{'steps':>7}{'moved':>7}{'pick':>5}"
    f"{'slots med':>10}{'max':>6}{'reconf ms':>10}{'lossless':>9}"
)


def format_row(r: dict[str, Any]) -> str:
    return (
        f"{r['problem']:<11}{r['planner']:<23}{r['plan_us']['median']:>9.0f}{r['plan_us']['p99']:>8.0f}"
        f"{r['steps_median']:>7.0f}{r['atoms_moved_median']:>7.0f}{r['max_pickups']['max']:>5}"
        f"{r['slots']['median']:>10.0f}{r['slots']['max']:>6}{r['reconfiguration_us']['median'] / 1e3:>10.2f}"
        f"{r['lossless_success']:>9.2f}"
    )


def plot_scaling(data: dict[str, Any], out_dir: Path) -> list[Path]:
    """Slots and planning time against array size (traps) per planner: two PNGs (needs matplotlib)."""
    import matplotlib  # deferred on purpose: an optional (dev) dependency, and slow to import

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    series: dict[str, list[tuple[int, float, float]]] = {}
    for r in data["results"]:
        if r["loading"] != 0.6 or r["ny"] == 1:
            continue
        series.setdefault(r["planner"], []).append((r["nx"] * r["ny"], r["slots"]["median"], r["plan_us"]["median"]))
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = []
    for idx, (ylabel, fname) in enumerate(
        (("waveform slots (median)", "solvers_slots.png"), ("planning time, us (median)", "solvers_planning.png")), 1
    ):
        fig, ax = plt.subplots(figsize=(6.4, 4.2))
        for label, pts in sorted(series.items()):
            pts.sort()
            ax.plot([p[0] for p in pts], [p[idx] for p in pts], marker="o", label=label)
        ax.set_xscale("log", base=2)
        ax.set_yscale("log")
        ax.set_xlabel("traps (n x 2n grids, band of half the traps, loading 0.6)")
        ax.set_ylabel(ylabel)
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=8)
        fig.tight_layout()
        path = out_dir / fname
        fig.savefig(path, dpi=110)
        plt.close(fig)
        paths.append(path)
    return paths


def _cmd(args: argparse.Namespace) -> int:
    problems = args.problems.split(",") if args.problems else None
    planners = args.planners.split(",") if args.planners else None
    if not args.json:
        print(_HEADER)

    def progress(r: dict[str, Any]) -> None:
        if not args.json:
            print(format_row(r), flush=True)

    data = bench_solvers(
        instances=args.instances, problems=problems, planners=planners, repeats=args.repeats,
        scaling_instances=args.scaling_instances, progress=progress,
    )  # fmt: skip
    if args.plots:
        data["plots"] = [str(p) for p in plot_scaling(data, Path(args.plots))]
    if args.json:
        print(json.dumps(data))
    else:
        invalid = sum(r["invalid"] for r in data["results"])
        print(f"\n{invalid} invalid plans over all planners and instances"
              + (f"; plots: {', '.join(data['plots'])}" if args.plots else ""))
    return 0


def register(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser(
        "solvers", help="every planner on seeded random instances, validated (success under loss: bench assembly)"
    )
    p.add_argument("--instances", type=int, default=100, help="solvable instances per problem (default 100)")
    p.add_argument(
        "--scaling-instances", type=int, default=None, help="instances per scaling problem (default: --instances)"
    )
    p.add_argument("--repeats", type=int, default=3, help="timed calls per instance, the fastest kept (default 3)")
    p.add_argument("--problems", default=None, help=f"comma-separated subset of {','.join(p.name for p in PROBLEMS)}")
    p.add_argument("--planners", default=None, help=f"comma-separated subset of {','.join(PLANNERS)}")
    p.add_argument("--plots", default=None, help="write PNG plots of slots and planning time vs size into this folder")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd)
