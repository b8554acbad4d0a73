"""``llrs bench streaming``: the paper's streaming figure, underrun probability and upload time against
waveforms per segment, on the simulated card.

For each segment size it streams the plans of ``--plans`` random fillings of one of the paper's problems
(the planner of its example config) through the engine's own ``Streamer`` and the simulated AWG, and reports
per size: the modelled DMA time of one segment against its playback time, the fraction of reconfigurations
with at least one underrun (the card fell into a failsafe), the smallest slack the host left the card (how
long before the card would have reached a failsafe each segment was linked: ``StreamReport.min_slack_s``),
and the latency from the first render to the pointer that starts playback. Small segments start sooner but
leave the host less time per segment; segments whose DMA is slower than their playback underrun however
fast the host is.

``--stream-priority 0`` streams at normal priority (the design before ``awg.stream_priority``) and
``--cpu-hogs N`` runs N CPU-bound processes beside it, to see what the real-time window buys.
"""

from __future__ import annotations

import argparse
import gc
import json
import os
from typing import Any

import numpy as np

from bench.runtime import PROBLEMS, cpu_hogs, problem_config
from bench.solvers import solvable_fillings
from engine.config import SystemConfig
from engine.operations import Operations
from engine.targets import build_target
from server.serve import engine_cpu_arg

__all__ = ["problem_plans", "register", "stream_plans", "streaming_figures"]

#: Segment sizes of the paper's figure (waveforms per segment).
DEFAULT_SIZES = (4, 8, 16, 32, 64)


def problem_plans(config: SystemConfig, n: int) -> list[Operations]:
    """The plans of ``n`` solvable random fillings of ``config``'s array for its planner and target."""
    from engine.solvers import solve  # deferred on purpose: planners load only when the benchmark runs

    arr = config.array
    target = build_target(config.target, nx=arr.nx, ny=arr.ny)
    fillings, _ = solvable_fillings(arr.ny, arr.nx, n, loading=config.sim.loading_probability,
                                    need=int(target.sum()))
    plans = [solve(occ, target, algorithm=config.solver.algorithm, trap_source=arr.trap_source).operations
             for occ in fillings]
    return [ops for ops in plans if len(ops) > 0]


def _sized(config: SystemConfig, waveforms_per_segment: int, longest: int, stream_priority: int,
           growth: float = 1.0) -> SystemConfig:
    """``config`` with ``waveforms_per_segment``, segments growing by ``growth`` (up to the config's
    ``max_waveforms_per_segment``, or the first segments' size if that is larger), and enough control segments
    (and steps) for ``longest`` slots."""
    n_control = max(2, -(-longest // waveforms_per_segment))
    awg = config.awg.model_copy(update={
        "waveforms_per_segment": waveforms_per_segment,
        "segment_growth": growth,
        "max_waveforms_per_segment": max(waveforms_per_segment, config.awg.max_waveforms_per_segment),
        "n_segments": max(8, 2 * n_control + 2),
        "n_steps": max(8, 2 * (2 * n_control + 2)),
        "stream_priority": stream_priority,
    })
    return config.model_copy(update={"awg": awg})


def stream_plans(config: SystemConfig, plans: list[Operations]) -> list[dict[str, float]]:
    """Stream every plan through a fresh simulated card with ``config``'s layout; one report per plan."""
    from drivers.sim.lab import build_sim_lab  # deferred on purpose: the simulated lab loads only when run
    from engine.streaming import Streamer
    from engine.waveforms import WaveformBank

    devices, _ = build_sim_lab(config)
    try:
        bank = WaveformBank(config)
        streamer = Streamer(config, bank, devices.awg, devices.clock)
        streamer.program_idle()
        devices.awg.start(streamer.layout.idle_step)
        streamer.stream(plans[0])  # warm caches and code paths; not counted
        out = []
        gc.disable()  # as the engine does during a shot
        for ops in plans:
            report = streamer.stream(ops)
            out.append({"underruns": report.underruns, "min_slack_s": report.min_slack_s,
                        "latency_s": report.latency_s, "max_upload_s": report.max_upload_s,
                        "n_segments": report.n_segments})
        refused = streamer.realtime_refused
    finally:
        gc.enable()
        devices.close()
    for row in out:
        row["realtime"] = refused is None
    return out


def streaming_figures(config: SystemConfig, plans: list[Operations], sizes: tuple[int, ...],
                      stream_priority: int, growths: tuple[float, ...] = (1.0,)) -> list[dict[str, Any]]:
    """Per segment size (of the first two segments) and growth: DMA and playback time of one such segment,
    underrun probability, slack and latency."""
    longest = max(len(ops) for ops in plans)
    slot_s = config.waveforms.slot_duration_s
    slot_bytes = 2 * round(config.waveforms.sample_rate_hz * slot_s) * (1 if config.array.trap_source == "aod" else 2)
    rows = []
    for size, growth in ((size, growth) for growth in growths for size in sizes):
        sized = _sized(config, size, longest, stream_priority, growth)
        reports = stream_plans(sized, plans)
        streamed = [r for r in reports if r["n_segments"] > 2]  # the short path cannot underrun
        slack_us = np.array([r["min_slack_s"] for r in streamed]) * 1e6
        rows.append({
            "waveforms_per_segment": size,
            "segment_growth": growth,
            "max_waveforms_per_segment": sized.awg.max_waveforms_per_segment,
            "segment_upload_us": size * slot_bytes / config.awg.upload_bytes_per_s * 1e6,
            "segment_playback_us": size * slot_s * 1e6,
            "max_upload_wait_us": max(r["max_upload_s"] for r in reports) * 1e6,
            "plans": len(reports),
            "streamed_plans": len(streamed),
            "underrun_probability": sum(r["underruns"] > 0 for r in reports) / len(reports),
            "underruns": int(sum(r["underruns"] for r in reports)),
            "min_slack_us": float(slack_us.min()) if slack_us.size else float("nan"),
            "p1_slack_us": float(np.percentile(slack_us, 1)) if slack_us.size else float("nan"),
            "latency_median_us": float(np.median([r["latency_s"] for r in reports])) * 1e6,
            "realtime": all(r["realtime"] for r in reports),
        })
    return rows


def _print(problem: str, rows: list[dict[str, Any]], hogs: int) -> None:
    print(f"== {problem}: {rows[0]['plans']} plans per size, {hogs} CPU hogs, "
          f"real-time streaming {'on' if rows[0]['realtime'] else 'off'}")
    print(f"{'wf/seg':>6s} {'growth':>6s} {'DMA us':>8s} {'play us':>8s} {'P(underrun)':>11s} {'underruns':>9s} "
          f"{'min slack':>10s} {'p1 slack':>9s} {'latency':>8s}   (us; DMA and playback of the first segments)")
    for r in rows:
        print(f"{r['waveforms_per_segment']:6d} {r['segment_growth']:6.2f} {r['segment_upload_us']:8.1f} "
              f"{r['segment_playback_us']:8.1f} "
              f"{r['underrun_probability']:11.4f} {r['underruns']:9d} {r['min_slack_us']:10.1f} "
              f"{r['p1_slack_us']:9.1f} {r['latency_median_us']:8.1f}")


def plot(rows: list[dict[str, Any]], path: str) -> None:
    """The paper's figure: underrun probability and segment upload time against waveforms per segment."""
    import matplotlib  # deferred on purpose: an optional (dev) dependency, and slow to import

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = [r for r in rows if r["segment_growth"] == rows[0]["segment_growth"]]  # the figure: one growth
    sizes = [r["waveforms_per_segment"] for r in rows]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot(sizes, [max(r["underrun_probability"], 1e-4) for r in rows], "o-", label="underrun probability")
    ax.set_xscale("log", base=2)
    ax.set_yscale("log")
    ax.set_xlabel("waveforms per segment")
    ax.set_ylabel("underrun probability per reconfiguration (floor 1e-4)")
    ax2 = ax.twinx()
    ax2.plot(sizes, [r["segment_upload_us"] for r in rows], "s--", color="C1", label="segment upload (DMA)")
    ax2.plot(sizes, [r["segment_playback_us"] for r in rows], ":", color="C2", label="segment playback")
    ax2.set_ylabel("time per segment (us)")
    fig.legend(loc="upper center", fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _cmd(args: argparse.Namespace) -> int:
    if args.problem not in PROBLEMS:
        raise SystemExit(f"llrs bench streaming: unknown problem {args.problem!r}; choose from {', '.join(PROBLEMS)}")
    try:
        sizes = tuple(int(s) for s in args.sizes.split(",") if s.strip())
    except ValueError:
        raise SystemExit(f"llrs bench streaming: --sizes takes comma-separated integers, not {args.sizes!r}") from None
    try:
        growths = tuple(float(g) for g in args.growth.split(",") if g.strip())
    except ValueError:
        raise SystemExit(f"llrs bench streaming: --growth takes comma-separated numbers, not {args.growth!r}") from None
    if not growths or min(growths) < 1:
        raise SystemExit(f"llrs bench streaming: --growth factors must be >= 1 (awg.segment_growth), "
                         f"got {args.growth!r}")
    config = problem_config(args.problem, seed=args.seed)
    plans = problem_plans(config, args.plans)
    allowed = os.sched_getaffinity(0) if args.engine_cpu is not None else None
    with cpu_hogs(args.cpu_hogs):
        try:
            if args.engine_cpu is not None:
                os.sched_setaffinity(0, {args.engine_cpu})
            rows = streaming_figures(config, plans, sizes, args.stream_priority, growths)
        finally:
            if allowed is not None:
                os.sched_setaffinity(0, allowed)
    if args.json:
        print(json.dumps({"problem": args.problem, "cpu_hogs": args.cpu_hogs, "rows": rows}))
    else:
        _print(args.problem, rows, args.cpu_hogs)
    if args.plot:
        plot(rows, args.plot)
    return 0


def register(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser("streaming", help="underrun probability and upload time against waveforms per segment")
    p.add_argument("--problem", default="32x64", help=f"one of {', '.join(PROBLEMS)} (default 32x64)")
    p.add_argument("--plans", type=int, default=100, help="random fillings to plan and stream per size (default 100)")
    p.add_argument("--sizes", default=",".join(str(s) for s in DEFAULT_SIZES),
                   help="comma-separated waveforms per segment (default %(default)s)")
    p.add_argument("--growth", default="1",
                   help="comma-separated awg.segment_growth factors: each size is streamed with each (default 1)")
    p.add_argument("--stream-priority", type=int, default=SystemConfig().awg.stream_priority,
                   help="SCHED_FIFO priority while streaming (0: normal priority; default %(default)s)")
    p.add_argument("--cpu-hogs", type=int, default=0, metavar="N", help="CPU-bound processes to run beside it")
    p.add_argument("--seed", type=int, default=1, help="seed of the simulated lab")
    p.add_argument("--engine-cpu", type=engine_cpu_arg, default="auto",
                   help="core to stream on, as llrs serve pins its engine ('auto', a number, or 'none')")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.add_argument("--plot", default=None, help="also write the figure (PNG) here")
    p.set_defaults(func=_cmd)
