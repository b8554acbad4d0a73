"""The ``llrs`` command line: run shots on the simulated lab (``llrs run``).

The web server (``llrs serve``) and benchmarks hang off the same entry point.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence

from bench import cli as bench_cli
from engine.config import ConfigError, load_config
from engine.records import ShotRecord, occupancy_to_rows
from engine.timing import STAGES, summarize_us

__all__ = ["main"]


def _build_engine_thread(config):  # noqa: ANN001, ANN202 - small composition helper
    from drivers.sim.lab import build_sim_lab
    from engine.engine import Engine, EngineThread

    def build() -> Engine:
        devices, lab = build_sim_lab(config)
        return Engine(config, devices, lab=lab)

    return EngineThread(build)


def run_summary(records: list[ShotRecord]) -> dict:
    """The figures ``llrs run --json`` prints: successes judged from the simulated world's ground truth."""
    samples: dict[str, list[float]] = {}
    for record in records:
        for cycle in record.cycles:
            for stage, seconds in cycle.stage_s.items():
                samples.setdefault(stage, []).append(seconds)
    stages = summarize_us(samples)
    rearrangements = [sum(1 for c in r.cycles if c.n_slots > 0) for r in records]
    return {
        "shots": len(records),
        "successes": sum(1 for r in records if r.lab_report.get("target_filled", False)),
        "engine_successes": sum(1 for r in records if r.success),
        "cycles_mean": sum(rearrangements) / max(len(records), 1),
        "outcomes": {
            o: sum(1 for r in records if r.outcome.value == o) for o in sorted({r.outcome.value for r in records})
        },
        "underruns": sum(c.underruns for r in records for c in r.cycles),
        "stages": {k: {"median_us": v["median_us"], "p99_us": v["p99_us"]} for k, v in stages.items()},
        "per_shot": [_shot_summary(r) for r in records],
    }


def _shot_summary(record: ShotRecord) -> dict:
    """One shot as ``llrs run --json`` lists it: enough to tell whether two runs played the same atoms."""
    return {
        "shot": record.shot_id,
        "outcome": record.outcome.value,
        "target_filled": record.lab_report.get("target_filled", False),
        "rearrangements": sum(1 for c in record.cycles if c.n_slots > 0),
        "slots": [c.n_slots for c in record.cycles],
        "underruns": sum(c.underruns for c in record.cycles),
        "occupancy": [occupancy_to_rows(c.occupancy) for c in record.cycles],  # as detected, per cycle
        "truth": record.lab_report.get("occupancy_rows", []),  # the world's atoms after the shot
    }


def _print_table(summary: dict, records: list[ShotRecord]) -> None:
    for r in records:
        truth = r.lab_report.get("target_filled")
        cycles = sum(1 for c in r.cycles if c.n_slots > 0)
        slots = ",".join(str(c.n_slots) for c in r.cycles if c.n_slots > 0) or "-"
        fault = f"  ({r.fault})" if r.fault else ""
        print(f"shot {r.shot_id:4d}: {r.outcome.value:10s} rearrangements={cycles} slots={slots:12s} "
              f"world target filled={truth}{fault}")
    print()
    print(f"{summary['successes']}/{summary['shots']} shots filled the target (world ground truth); "
          f"mean rearrangement cycles {summary['cycles_mean']:.2f}; underruns {summary['underruns']}")
    print()
    print(f"{'stage':14s} {'median us':>12s} {'p99 us':>12s}")
    for stage in STAGES:
        if stage in summary["stages"]:
            s = summary["stages"][stage]
            print(f"{stage:14s} {s['median_us']:12.1f} {s['p99_us']:12.1f}")


def _cmd_run(args: argparse.Namespace) -> int:
    config = load_config(args.config)
    if args.seed is not None:
        config = config.model_copy(update={"sim": config.sim.model_copy(update={"seed": args.seed})})
    if args.time is not None:
        config = config.model_copy(update={"sim": config.sim.model_copy(update={"time": args.time})})
    with _build_engine_thread(config) as engine_thread:
        records = engine_thread.run_shots(args.shots).result()
    summary = run_summary(records)
    if args.json:
        print(json.dumps(summary))
    else:
        _print_table(summary, records)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="llrs", description="Low-latency reconfiguration system for tweezer arrays")
    sub = parser.add_subparsers(dest="command", required=True)
    run = sub.add_parser("run", help="run shots on the simulated lab and print outcomes and stage timings")
    run.add_argument("--config", required=True, help="YAML configuration (see examples/)")
    run.add_argument("--shots", type=int, default=10, help="number of shots (default 10)")
    run.add_argument("--seed", type=int, default=None, help="seed of the simulated lab (overrides sim.seed)")
    run.add_argument(
        "--time",
        choices=["simulated", "realtime", "replay"],
        default=None,
        help="simulated lab's clock (overrides sim.time); replay charges modelled host times: a seed replays exactly",
    )
    run.add_argument(
        "--json", action="store_true", help="print one JSON object (summary and, per shot, outcome and occupancies)"
    )
    run.set_defaults(func=_cmd_run)
    bench = sub.add_parser("bench", help="benchmarks that print figures (see docs/benchmarks.md)")
    bench_sub = bench.add_subparsers(dest="bench", required=True)
    bench_cli.register(bench_sub)
    from server import devices_cmd

    devices_cmd.register(sub)
    from server import serve  # noqa: PLC0415 - the web stack loads only when serving

    serve.add_parser(sub)
    args = parser.parse_args(argv)
    if getattr(args, "shots", 1) < 1:
        parser.error("--shots must be at least 1")
    try:
        return args.func(args)
    except ConfigError as err:
        print(f"llrs: {err}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
