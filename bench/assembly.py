"""``llrs bench assembly``: how often, and how soon, a shot ends with a defect-free array.

The physicist's figure, measured the only way that can be trusted: closed-loop shots on the simulated lab
(real waveforms, samples decoded by the simulated AWG, atoms moved and lost by the simulated world, images
rendered by the simulated camera), with success judged from the world's ground truth when the shot ends,
which is when the experiment would begin. Nothing here models the loop: a Monte Carlo that disagrees with
these figures is wrong until shown otherwise.

A *cell* is one problem (a shipped example), one planner and one loss model (survival per transfer and per
step, vacuum lifetime). Every cell runs the same shot seeds (shot ``j`` is seeded from ``(seed, j)``), so
two planners are compared on the same loaded arrays, and a shot's outcome depends only on its seed and its
cell, not on which process ran it or what ran before: a sweep splits its shots into chunks and runs them on
**dask.distributed**, a local cluster by default or ``--scheduler ADDRESS`` for a real one, unchanged.

Reported per cell: success (world truth) with a 95 % Wilson interval and what the engine believed from its
last image; rearrangement cycles (mean, p90); time to a defect-free array (first exposure to the final image
that shows the target filled, successful shots: median, p90); the vacuum bound
``exp(-n_target * T_last / lifetime)`` with ``T_last`` from each shot's last exposure to its end (a shot
cannot beat the chance that no target atom dies in that time); and atoms lost per rearrangement cycle by
cause, as the world counted them.
"""

from __future__ import annotations

import argparse
import json
import math
import os
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from engine.config import SystemConfig, load_config
from engine.records import ShotRecord

__all__ = [
    "LOSS_MODELS",
    "PROBLEMS",
    "Cell",
    "CellResult",
    "add_cell_arguments",
    "cell_config",
    "csv_list",
    "format_table",
    "register",
    "run_cells",
    "outcome_cells",
    "outcome_figures",
    "print_rows",
    "run_chunk",
    "shot_seeds",
    "summarize",
    "wilson_interval",
]

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
PROBLEMS = {"1x64": "chain-1x64.yaml", "16x32": "grid-16x32.yaml", "32x64": "grid-32x64.yaml"}
LOSS_MODELS: dict[str, tuple[float, float] | None] = {
    "lossless": None,
    "0.995/0.999": (0.995, 0.999),
    "0.985/0.985": (0.985, 0.985),
}
LOSS_CAUSES = ("transfer", "step", "vacuum", "imaging", "collision", "dropped", "released", "pass_by")


@dataclass(frozen=True)
class Cell:
    """One row of the table: a problem, a planner (``None``: the example's own) and a loss model."""

    problem: str
    planner: str | None
    loss: str
    lifetime_s: float
    image_survival: float = 1.0  # per image; 1: imaging loses no atom

    def label(self) -> dict[str, Any]:
        return {
            "problem": self.problem, "planner": self.planner, "loss": self.loss, "lifetime_s": self.lifetime_s,
            "image_survival": self.image_survival,
        }


def cell_config(
    cell: Cell, *, loading: float = 0.6, max_cycles: int = 5, examples: Path = EXAMPLES
) -> SystemConfig:
    """The example's configuration with the cell's planner, loss model, lifetime and imaging survival, in replay
    time (each host stage charged its modelled duration, so a shot's outcome and timing depend only on its seed,
    not on how busy the machine running it is). Validated as any configuration."""
    if cell.problem not in PROBLEMS:
        raise ValueError(f"unknown problem {cell.problem!r}; choose from {', '.join(PROBLEMS)}")
    if cell.loss not in LOSS_MODELS:
        raise ValueError(f"unknown loss model {cell.loss!r}; choose from {', '.join(LOSS_MODELS)}")
    base = load_config(examples / PROBLEMS[cell.problem]).model_dump(mode="json")
    survival = LOSS_MODELS[cell.loss]
    sim = base["sim"]
    if not 0 < cell.image_survival <= 1:
        raise ValueError(f"image survival must be in (0, 1] (got {cell.image_survival})")
    sim.update(
        loading_probability=loading, vacuum_lifetime_s=cell.lifetime_s, lossless=survival is None, time="replay"
    )
    # imaging heats atoms out at a rate while the light is on: survival per image = exp(-rate * exposure)
    sim["imaging"]["loss_rate_hz"] = -math.log(cell.image_survival) / base["camera"]["exposure_s"]
    if survival is not None:
        sim.update(survival_transfer=survival[0], survival_step=survival[1])
    base["loop"]["max_cycles"] = max_cycles
    if cell.planner is not None:
        spec, _, routing = cell.planner.partition("/")
        base["solver"] = planner_settings(spec)  # the spec alone: no strategy or objective of the example
        if routing:
            base["array"]["routing"] = routing
    return SystemConfig.model_validate(base)


def planner_settings(spec: str) -> dict[str, Any]:
    """``solver`` settings from a planner spec ``ALGORITHM[>REPAIR@DEFECTS][:OBJECTIVE]``: e.g. ``red-rec``,
    ``repair:survival``, ``red-rec>repair@64:survival`` (red-rec while the target has more than 64 holes)."""
    spec, _, objective = spec.partition(":")
    bulk, _, repair = spec.partition(">")
    settings: dict[str, Any] = {"algorithm": bulk}
    if objective:
        settings["objective"] = objective
    if repair:
        name, at, defects = repair.partition("@")
        if not at or not defects.isdigit():
            raise ValueError(f"planner {spec!r}: write a strategy as BULK>REPAIR@DEFECTS, e.g. red-rec>repair@64")
        settings["strategy"] = {"repair": name, "repair_at_defects": int(defects)}
    return settings


def shot_seeds(seed: int, n_shots: int) -> list[int]:
    """Shot ``j``'s seed from ``(seed, j)``: the same in every cell and however the shots are chunked."""
    return [int(np.random.SeedSequence([seed, j]).generate_state(1)[0]) for j in range(n_shots)]


def _shot_summary(record: ShotRecord, lost: dict[str, int], n_target: int, lifetime_s: float) -> dict[str, Any]:
    cycles = record.cycles
    rearrangements = sum(1 for c in cycles if c.n_slots > 0)
    filled = bool(record.lab_report.get("target_filled", False))
    time_to_array_s = cycles[-1].t_image_s - cycles[0].t_start_s if (filled and record.success) else None
    t_last_s = record.duration_s - cycles[-1].t_start_s if cycles else record.duration_s
    return {
        "filled": filled,
        "engine_success": record.success,
        "outcome": record.outcome.value,
        "rearrangements": rearrangements,
        "time_to_array_s": time_to_array_s,
        "t_last_s": t_last_s,
        "vacuum_bound": math.exp(-n_target * t_last_s / lifetime_s),
        "lost": lost,
        "underruns": sum(c.underruns for c in cycles),
        "fault": record.fault,
    }


def run_chunk(config_json: str, seeds: Sequence[int]) -> list[dict[str, Any]]:
    """Run one shot per seed on a fresh simulated lab (what a dask worker executes); one summary per shot."""
    # deferred on purpose: ``llrs`` imports every benchmark to list it, and the engine with the simulated lab
    # (numba kernels, scipy) takes seconds to import
    from drivers.sim.lab import build_sim_lab
    from engine.engine import Engine

    config = SystemConfig.model_validate_json(config_json)
    devices, lab = build_sim_lab(config)
    try:
        engine = Engine(config, devices, lab=lab)
        n_target = int(engine.target.sum())
        out = []
        for seed in seeds:
            lab.reseed(seed)
            before = lab.world.counters.as_dict()
            record = engine.run_shot()
            after = lab.world.counters.as_dict()
            lost = {cause: after[f"lost_{cause}"] - before[f"lost_{cause}"] for cause in LOSS_CAUSES}
            lifetime_s = math.inf if config.sim.lossless else config.sim.vacuum_lifetime_s  # lossless: no vacuum loss
            out.append(_shot_summary(record, lost, n_target, lifetime_s))
        return out
    finally:
        devices.close()


def wilson_interval(successes: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % score interval of a binomial proportion (sensible at 0 % and 100 %, unlike the normal one)."""
    if n == 0:
        return (0.0, 1.0)
    p = successes / n
    centre = (p + z * z / (2 * n)) / (1 + z * z / n)
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / (1 + z * z / n)
    return (max(0.0, centre - half), min(1.0, centre + half))


@dataclass
class CellResult:
    cell: Cell
    shots: list[dict[str, Any]]
    error: str | None = None


def outcome_figures(shots: Sequence[dict[str, Any]], causes: Sequence[str]) -> dict[str, Any]:
    """What every assembly table reports of a cell's shots (``filled``, ``rearrangements``, ``time_to_array_s``,
    ``lost`` by cause): success with its 95 % Wilson interval, cycles, time to array and atoms lost per cycle."""
    n = len(shots)
    filled = sum(s["filled"] for s in shots)
    cycles = np.array([s["rearrangements"] for s in shots], dtype=float)
    times = np.array([s["time_to_array_s"] for s in shots if s["time_to_array_s"] is not None], dtype=float)
    total_cycles = max(int(cycles.sum()), 1)
    return {
        "shots": n,
        "success": filled / n if n else float("nan"),
        "success_ci95": list(wilson_interval(filled, n)),
        "cycles_mean": float(cycles.mean()) if n else float("nan"),
        "cycles_p90": float(np.percentile(cycles, 90)) if n else float("nan"),
        "time_to_array_ms_median": float(np.median(times) * 1e3) if times.size else None,
        "time_to_array_ms_p90": float(np.percentile(times, 90) * 1e3) if times.size else None,
        "lost_per_cycle": {c: sum(s["lost"][c] for s in shots) / total_cycles for c in causes},
    }


def summarize(result: CellResult) -> dict[str, Any]:
    """One table row from a cell's shot summaries (all shots counted, faults included)."""
    row: dict[str, Any] = result.cell.label()
    if result.error is not None:
        return {**row, "error": result.error}
    shots = result.shots
    n = len(shots)
    bound = float(np.mean([s["vacuum_bound"] for s in shots])) if shots else float("nan")
    return {
        **row,
        **outcome_figures(shots, LOSS_CAUSES),
        "engine_believed": sum(s["engine_success"] for s in shots) / n if n else float("nan"),
        "vacuum_bound": bound,
        "underruns": sum(s["underruns"] for s in shots),
        "faults": sum(1 for s in shots if s["fault"]),
    }


def run_cells(
    cells: Sequence[Cell],
    *,
    shots: int,
    seed: int = 1,
    chunk: int = 20,
    loading: float = 0.6,
    max_cycles: int = 5,
    scheduler: str | None = None,
    workers: int | None = None,
) -> list[CellResult]:
    """Run every cell's shots on a dask cluster (local unless ``scheduler`` names one); results in cell order."""
    from dask.distributed import Client, LocalCluster  # noqa: PLC0415 - the cluster stack loads only for sweeps

    seeds = shot_seeds(seed, shots)
    configs: dict[Cell, str] = {}
    results = {cell: CellResult(cell, []) for cell in cells}
    for cell in cells:
        try:
            configs[cell] = cell_config(cell, loading=loading, max_cycles=max_cycles).model_dump_json()
        except ValueError as err:
            results[cell].error = str(err)
    cluster = None
    if scheduler is None:
        cluster = LocalCluster(
            n_workers=workers or os.cpu_count() or 1, threads_per_worker=1, processes=True, dashboard_address=None
        )
    client = Client(scheduler if scheduler is not None else cluster)
    try:
        futures = [
            (cell, start, client.submit(run_chunk, cfg, seeds[start : start + chunk], pure=False))
            for cell, cfg in configs.items()
            for start in range(0, shots, chunk)
        ]
        chunks: dict[Cell, dict[int, list[dict[str, Any]]]] = {cell: {} for cell in configs}
        for cell, start, future in futures:
            try:
                chunks[cell][start] = future.result()
            except Exception as err:  # noqa: BLE001 - a cell the engine refuses is reported, the sweep goes on
                results[cell].error = f"{type(err).__name__}: {err}"
        for cell, by_start in chunks.items():
            if results[cell].error is None:
                results[cell].shots = [s for start in sorted(by_start) for s in by_start[start]]
    finally:
        client.close()
        if cluster is not None:
            cluster.close()
    return [results[cell] for cell in cells]


def _pct(x: float) -> str:
    return f"{100 * x:5.1f}"


def outcome_cells(r: dict[str, Any], causes: Sequence[str]) -> dict[str, str]:
    """``outcome_figures`` as table cells: success [CI] %, cycles mean / p90, times median / p90, lost by cause."""
    t_med, t_p90 = r["time_to_array_ms_median"], r["time_to_array_ms_p90"]
    return {
        "success": f"{_pct(r['success'])} [{_pct(r['success_ci95'][0])}, {_pct(r['success_ci95'][1])}]",
        "cycles": f"{r['cycles_mean']:.2f} / {r['cycles_p90']:.0f}",
        "times": f"{t_med:.1f} / {t_p90:.1f}" if t_med is not None else "-",
        "lost": " / ".join(f"{r['lost_per_cycle'][c]:.2f}" for c in causes),
    }


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    """The rows as a markdown table (what docs/benchmarks.md quotes)."""
    head = (
        "| problem | planner | loss (transfer/step) | lifetime s | image survival | shots | success % [95 % CI] "
        "| engine believed % | cycles mean / p90 | time to array ms median / p90 | vacuum bound % | lost per cycle: "
        + " / ".join(LOSS_CAUSES)
        + " |"
    )
    lines = [head, "|" + "---|" * 12]
    for r in rows:
        label = (
            f"| {r['problem']} | {r['planner'] or 'example'} | {r['loss']} | {r['lifetime_s']:g} "
            f"| {r['image_survival']:g} "
        )
        if "error" in r:
            lines.append(label + f"| - | refused: {r['error']} | | | | | |")
            continue
        c = outcome_cells(r, LOSS_CAUSES)
        lines.append(
            label + f"| {r['shots']} | {c['success']} | {_pct(r['engine_believed'])} | {c['cycles']} | {c['times']} "
            f"| {_pct(r['vacuum_bound'])} | {c['lost']} |"
        )
    return "\n".join(lines)


def csv_list(text: str) -> list[str]:
    """A comma-separated option as its items."""
    return [t.strip() for t in text.split(",") if t.strip()]


def _cmd(args: argparse.Namespace) -> int:
    planners: list[str | None] = [None if p == "example" else p for p in csv_list(args.planners)]
    cells = [
        Cell(problem=problem, planner=planner, loss=loss, lifetime_s=float(lifetime), image_survival=float(image))
        for problem in csv_list(args.problems)
        for planner in planners
        for loss in csv_list(args.loss)
        for lifetime in csv_list(args.lifetime)
        for image in csv_list(args.image_survival)
    ]
    results = run_cells(
        cells, shots=args.shots, seed=args.seed, chunk=args.chunk, loading=args.loading,
        max_cycles=args.max_cycles, scheduler=args.scheduler, workers=args.workers,
    )
    return print_rows(args, [summarize(r) for r in results], format_table)


def print_rows(
    args: argparse.Namespace, rows: list[dict[str, Any]], table: Callable[[list[dict[str, Any]]], str]
) -> int:
    """Print the rows as one JSON object (``--json``) or as ``table`` formats them; the command's exit status."""
    if args.json:
        print(json.dumps({"shots_per_cell": args.shots, "seed": args.seed, "rows": rows}))
    else:
        print(table(rows))
    return 0


def add_cell_arguments(p: argparse.ArgumentParser, problems: Iterable[str]) -> None:
    """The options that choose cells and shots, shared by ``assembly`` and ``assembly-bound``."""
    p.add_argument("--problems", default="32x64", help=f"comma-separated, from {', '.join(problems)} (default 32x64)")
    p.add_argument("--loss", default="0.995/0.999", help=f"comma-separated, from {', '.join(LOSS_MODELS)}")
    p.add_argument("--lifetime", default="6000", help="comma-separated vacuum lifetimes in s (default 6000)")
    p.add_argument("--image-survival", default="1", help="comma-separated survival per image (default 1: lossless)")
    p.add_argument("--shots", type=int, default=200, help="shots per cell (default 200)")
    p.add_argument("--seed", type=int, default=1, help="base seed: shot j of every cell is seeded from (seed, j)")
    p.add_argument("--loading", type=float, default=0.6, help="loading probability (default 0.6)")
    p.add_argument("--max-cycles", type=int, default=5, help="rearrangement cycles at most (default 5)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("assembly", help="closed-loop success and time to a defect-free array, on a dask cluster")
    add_cell_arguments(p, PROBLEMS)
    p.add_argument(
        "--planners", default="example",
        help="comma-separated planners ALGORITHM[>REPAIR@DEFECTS][:OBJECTIVE][/ROUTING], e.g. "
        "red-rec>repair@64:survival/interstitial (ROUTING: array.routing, lattice or interstitial); "
        "'example': the example's own",
    )  # fmt: skip
    p.add_argument("--chunk", type=int, default=20, help="shots per dask task (default 20)")
    p.add_argument("--scheduler", default=None, help="dask scheduler address (default: a local cluster)")
    p.add_argument("--workers", type=int, default=None, help="local cluster workers (default: one per core)")
    p.add_argument("--json", action="store_true", help="print one JSON object instead of the table")
    p.set_defaults(func=_cmd)
