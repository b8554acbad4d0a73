"""Modules III and IV for the 1x64 -> 32 chain, out of the loop: exact-1d solve + batch, lookup and render per
waveform slot, and the lookup table's size, over random instances at loading 0.6.

Lookup is reported per slot (right after rendering the previous plan, and again at once, warm) and per
table waveform (one key: one precomputed moving-tone waveform fetched; a slot fetches one per moving tone).
A chain plan is ~13 slots, so the ~2 us fixed cost of one numba call dominates the per-slot figure.

    llrs bench chain-plan [--instances N]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from bench.runtime import REPO
from engine.config import load_config
from engine.solvers import Solver
from engine.targets import build_target
from engine.waveforms import WaveformBank

__all__ = ["register"]


def _cmd(args: argparse.Namespace) -> int:
    config = load_config(REPO / "examples/chain-1x64.yaml")
    bank = WaveformBank(config)
    solver = Solver(nx=64, ny=1, algorithm="exact-1d", trap_source="aod")
    target = build_target(config.target, nx=64, ny=1)
    keys = np.zeros(bank.max_keys(64), np.int64)
    out = np.zeros((64 * bank.slot_samples, 1), np.int16)
    rng = np.random.default_rng(1)
    instances = [occ for occ in (rng.random((1, 64)) < 0.6 for _ in range(args.instances)) if occ.sum() >= target.sum()]
    # planning alone, back to back (caches warm, as after the engine's rehearsal)
    plan_s = []
    for occ in instances:
        t0 = time.perf_counter()
        solver.solve_moves(occ, target)
        solver.batch()
        plan_s.append(time.perf_counter() - t0)
    # then each plan's lookup and render (a render of a plan evicts much of the cache between instances)
    lookup_s, render_s, per_waveform_s, warm_s = [], [], [], []
    for occ in instances:
        solver.solve_moves(occ, target)
        plan = solver.batch()
        n = len(plan.operations)
        if n == 0:
            continue
        t0 = time.perf_counter()
        bank.lookup(plan.operations, 0, n, keys)
        dt = time.perf_counter() - t0
        lookup_s.append(dt / n)
        per_waveform_s.append(dt / max(1, int(sum(keys[j * bank.stride] for j in range(n)))))
        t0 = time.perf_counter()
        bank.lookup(plan.operations, 0, n, keys)  # again at once: caches warm, as after the engine's rehearsal
        warm_s.append((time.perf_counter() - t0) / n)
        t0 = time.perf_counter()
        bank.render(0, n, out)
        render_s.append((time.perf_counter() - t0) / n)
    us = lambda v, q: float(np.percentile(v, q)) * 1e6  # noqa: E731
    print(
        f"exact-1d solve + batch: median {us(plan_s, 50):.2f} us, p99 {us(plan_s, 99):.2f} us "
        f"({len(plan_s)} instances)"
    )
    print(f"lookup per slot: median {us(lookup_s, 50):.3f} us after a render, {us(warm_s, 50):.3f} us warm; "
          f"per table waveform (key): median {us(per_waveform_s, 50):.3f} us; "
          f"render per slot: median {us(render_s, 50):.2f} us")
    slot_us = config.waveforms.slot_duration_s * 1e6
    print(f"render keeps up with playback: {us(render_s, 50):.2f} us of host time per {slot_us:.0f} us slot "
          f"({us(render_s, 50) / slot_us:.2f} of real time; p99 {us(render_s, 99) / slot_us:.2f})")
    print(f"lookup table: {bank.table_bytes} bytes")
    return 0


def register(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser(
        "chain-plan", help="modules III and IV for the 1x64 chain out of the loop: plan, lookup, render"
    )
    p.add_argument("--instances", type=int, default=2000, help="random fillings drawn at loading 0.6 (default 2000)")
    p.set_defaults(func=_cmd)
