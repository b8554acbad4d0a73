"""Module III runtime and plan size for red-rec on the paper's grids (16x32 -> 16x16, 32x64 -> 32x32, eps 0.6).

For each batching prints, over seeded instances (after warm-up): median / p99 of ``solve_moves`` and of
``batch`` in microseconds, median / max waveform slots and median one-site steps.

    llrs bench redrec [--instances 200] [--repeats 5] [--eps 0.6]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.solvers import solvable_fillings
from engine.solvers.redrec import BATCHINGS, RedRecPlanner
from engine.targets import centre_target

__all__ = ["register"]

GRIDS = ((32, 16), (64, 32))  # (ny, nx): 16x32 -> 16x16 and 32x64 -> 32x32


def _cmd(args: argparse.Namespace) -> int:
    print(f"{'problem':<18}{'batching':<14}{'solve med':>10}{'p99':>8}{'batch med':>10}{'p99':>8}"
          f"{'plan med':>10}{'p99':>8}{'slots med':>10}{'max':>6}{'steps med':>10}")
    for ny, nx in GRIDS:
        target = centre_target(nx=nx, ny=ny, count=nx * ny // 2)
        occs, _ = solvable_fillings(ny, nx, args.instances, loading=args.eps, need=int(target.sum()))
        for batching in BATCHINGS:
            planner = RedRecPlanner(nx, ny, batching=batching)
            for occ in occs[:10]:
                planner.solve_moves(occ, target)
                planner.batch()
            solve_us = np.empty(len(occs))
            batch_us = np.empty(len(occs))
            plan_us = np.empty(len(occs))
            slots = np.empty(len(occs), dtype=int)
            steps = np.empty(len(occs), dtype=int)
            for i, occ in enumerate(occs):
                best = (np.inf, np.inf, np.inf)
                for _ in range(args.repeats):
                    t0 = time.perf_counter_ns()
                    steps[i] = planner.solve_moves(occ, target)
                    t1 = time.perf_counter_ns()
                    slots[i] = planner.batch().n_slots
                    t2 = time.perf_counter_ns()
                    if t2 - t0 < best[2]:
                        best = ((t1 - t0) / 1e3, (t2 - t1) / 1e3, (t2 - t0) / 1e3)
                solve_us[i], batch_us[i], plan_us[i] = best
            name = f"{nx}x{ny}->{nx}x{ny // 2}"
            print(f"{name:<18}{batching:<14}"
                  f"{np.median(solve_us):>10.1f}{np.percentile(solve_us, 99):>8.1f}"
                  f"{np.median(batch_us):>10.1f}{np.percentile(batch_us, 99):>8.1f}"
                  f"{np.median(plan_us):>10.1f}{np.percentile(plan_us, 99):>8.1f}"
                  f"{np.median(slots):>10.0f}{slots.max():>6}{np.median(steps):>10.0f}")
    return 0


def register(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser("redrec", help="red-rec's batchings on the paper's grids: solve and batch time, plan size")
    p.add_argument("--instances", type=int, default=200, help="solvable instances per grid (default 200)")
    p.add_argument("--repeats", type=int, default=5, help="timed calls per instance (the minimum is kept)")
    p.add_argument("--eps", type=float, default=0.6, help="loading probability (default 0.6)")
    p.set_defaults(func=_cmd)
