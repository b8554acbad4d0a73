"""Module II runtime: ``Detector.detect`` (weighted sums + threshold) against the plain-numpy reference.

Configurations as in the paper's Table 1: 64 traps (1x64 chain, ROI 16x1024) and 2048 traps (32x64 grid,
ROI 512x1024), 7x7 PSF box, on simulated frames with ~60 % loading. Prints median and p99 per call.

    llrs bench imaging [--repeats 5000]
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from engine.config import SystemConfig

__all__ = ["register"]


def _configs() -> dict[str, SystemConfig]:
    grid = SystemConfig.model_validate(
        {
            "array": {"nx": 64, "ny": 32, "trap_source": "slm"},
            "camera": {"roi_width_px": 1024, "roi_height_px": 512},
            "imaging": {"psf_box_px": 7},
            "target": {"count": 1024},
        }
    )
    return {"64 traps (1x64, ROI 16x1024)": SystemConfig(), "2048 traps (32x64, ROI 512x1024)": grid}


def _time_us(call: Callable[[], object], repeats: int) -> tuple[float, float]:
    samples = np.empty(repeats)
    for i in range(repeats):
        t0 = time.perf_counter_ns()
        call()
        samples[i] = time.perf_counter_ns() - t0
    return float(np.median(samples)) / 1e3, float(np.percentile(samples, 99)) / 1e3


def _bench_config(name: str, config: SystemConfig, rng: np.random.Generator, repeats: int) -> None:
    """Time both implementations on one configuration's simulated frames and print a row for each.

    A function of its own so that the lambdas below close over this configuration's frame and detector only.
    """
    # deferred on purpose: ``llrs`` imports every benchmark to list it; the imaging stack (scipy: about 1.5 s to import)
    # loads only when this benchmark runs
    from drivers.sim.camera import SimCamera
    from drivers.sim.clock import SimClock
    from engine.imaging import Detector, calibration_frames, threshold_reference, weighted_sums_reference

    occupancy = rng.random((config.array.ny, config.array.nx)) < 0.6
    camera = SimCamera(config, atoms=lambda *_: occupancy, clock=SimClock(), rng=rng)
    frames = np.empty((calibration_frames(config.array.n_traps), *camera.frame_shape), dtype=np.uint16)
    for frame in frames:
        camera.trigger()
        camera.read(frame, timeout_s=1.0)
    detector = Detector(config)
    detector.calibrate(frames)  # the threshold from frames, as the engine fits it at apply
    image = frames[0]
    out = np.empty_like(occupancy)
    detector.detect(image, out)
    assert np.array_equal(out, occupancy), "benchmark frame misdetected"
    idx, w, thr = detector.psf.pixel_idx, detector.psf.weights, detector.thresholds
    rows = {
        "numba detect": lambda: detector.detect(image, out),
        "numpy reference": lambda: threshold_reference(weighted_sums_reference(image, idx, w), thr),
    }
    for impl, call in rows.items():
        median_us, p99_us = _time_us(call, repeats)
        print(f"{name:36s} {impl:16s} {median_us:10.2f} {p99_us:10.2f}")


def _cmd(args: argparse.Namespace) -> int:
    rng = np.random.default_rng(7)
    print(f"{'configuration':36s} {'implementation':16s} {'median us':>10s} {'p99 us':>10s}")
    for name, config in _configs().items():
        _bench_config(name, config, rng, args.repeats)
    return 0


def register(bench_sub: argparse._SubParsersAction) -> None:
    p = bench_sub.add_parser(
        "imaging", help="module II: numba detect against the plain-numpy reference, 64 and 2048 traps"
    )
    p.add_argument("--repeats", type=int, default=5000, help="timed calls per configuration (default 5000)")
    p.set_defaults(func=_cmd)
