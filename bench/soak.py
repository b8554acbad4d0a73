"""``llrs bench soak``: many shots through the whole server stack; memory must stay flat, every shot recorded.

Runs the lab service (the engine in its own process as ``llrs serve`` runs it, or on a thread with ``--engine
thread``; continuous runner; run store writing HDF5) on the simulated lab with simulated time for ``--shots``
shots, sampling the resident memory of the server and engine processes together as it goes. Reported: memory
after warm-up and at the end (the growth is what matters: a leak shows as a slope), shots per second, and
the number of shots found in the run files afterwards, which must equal the number run.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import threading
import time
from pathlib import Path
from typing import Any

import h5py

from bench.runtime import REPO
from engine.config import load_config
from engine.records import ShotRecord
from server.runstore import RunStore
from server.serve import engine_host_factory

__all__ = ["register", "rss_mb", "run_soak"]


def rss_mb(pid: int | str = "self") -> float:
    """Resident set size of process ``pid`` (default: this one) in MiB (Linux /proc)."""
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def shots_on_disk(runs_dir: Path) -> int:
    total = 0
    for path in sorted(runs_dir.glob("*.h5")):
        with h5py.File(path, "r", swmr=True) as f:
            total += int(f["shot_id"].shape[0])
    return total


def run_soak(
    config_path: str, shots: int, *, warmup: int, sample_every: int, progress: bool, in_process: bool = True
) -> dict[str, Any]:
    # deferred on purpose: ``llrs`` imports every benchmark to list it; the lab service (about 1.3 s to import)
    # loads only when this benchmark runs
    from server.service import LabService

    config = load_config(config_path)
    config = config.model_copy(update={"sim": config.sim.model_copy(update={"time": "simulated"})})

    with tempfile.TemporaryDirectory(prefix="llrs-soak-") as tmp:
        runs = Path(tmp)
        host = engine_host_factory(in_process=in_process, cpu=None)(config)
        service = LabService(engine_thread=host, store=RunStore(runs), pause_s=0.0)

        def rss_total_mb() -> float:
            pid = getattr(host, "pid", None)
            return rss_mb() + (rss_mb(pid) if pid is not None else 0.0)

        done = threading.Event()
        count = [0]
        samples: list[tuple[int, float]] = []
        outcomes: dict[str, int] = {}

        def on_shot(record: ShotRecord) -> None:
            count[0] += 1
            outcomes[record.outcome.value] = outcomes.get(record.outcome.value, 0) + 1
            n = count[0]
            if n == warmup or n % sample_every == 0:
                samples.append((n, rss_total_mb()))
                if progress:
                    print(f"  {n} shots, RSS {samples[-1][1]:.1f} MiB", flush=True)
            if n >= shots:
                service.stop()
                done.set()

        service.start(run=False)
        service.add_listener(on_shot)
        t0 = time.perf_counter()
        service.run()
        done.wait()
        wall = time.perf_counter() - t0
        service.close()  # flushes and closes the run file
        on_disk = shots_on_disk(runs)
    base = next((mb for n, mb in samples if n >= warmup), samples[0][1] if samples else float("nan"))
    end = samples[-1][1] if samples else float("nan")
    return {
        "config": str(config_path),
        "engine": "process" if in_process else "thread",
        "shots": count[0],
        "shots_on_disk": on_disk,
        "outcomes": outcomes,
        "wall_s": wall,
        "shots_per_s": count[0] / wall,
        "rss_after_warmup_mb": base,
        "rss_end_mb": end,
        "rss_growth_mb": end - base,
        "rss_samples": samples,
    }


def _cmd(args: argparse.Namespace) -> int:
    result = run_soak(args.config, args.shots, warmup=min(args.warmup, args.shots),
                      sample_every=max(1, args.shots // 20), progress=not args.json,
                      in_process=args.engine == "process")
    if args.json:
        print(json.dumps(result))
    else:
        print(f"{result['shots']} shots ({result['shots_per_s']:.1f}/s), {result['shots_on_disk']} in the run files; "
              f"RSS {result['rss_after_warmup_mb']:.1f} MiB after warm-up -> {result['rss_end_mb']:.1f} MiB "
              f"(growth {result['rss_growth_mb']:+.1f} MiB); outcomes {result['outcomes']}")
    return 0 if result["shots_on_disk"] == result["shots"] else 1


def register(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser("soak", help="many shots through the server stack: memory growth, every shot recorded")
    p.add_argument("--config", default=str(REPO / "examples/grid-16x32.yaml"), help="configuration (default 16x32)")
    p.add_argument("--shots", type=int, default=20000, help="number of shots (default 20000)")
    p.add_argument("--warmup", type=int, default=500, help="shots before the memory baseline (default 500)")
    p.add_argument("--engine", choices=("process", "thread"), default="process",
                   help="the engine in its own process (default, as llrs serve) or on a thread of the server's")
    p.add_argument("--json", action="store_true", help="print one JSON object")
    p.set_defaults(func=_cmd)
