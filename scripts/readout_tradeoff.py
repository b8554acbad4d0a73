"""Image acquisition against detection error for camera readout settings (the table in docs/simulation.md).

    .venv/bin/python scripts/readout_tradeoff.py examples/grid-32x64.yaml [--frames 100] [--seed 1]

For each setting below, applied to the example's camera: the acquisition time of the readout model
(``I.acquire``: exposure, frame transfer, row readout, DMA), the per-trap detection error measured against
the truth (freshly loaded arrays at ``sim.loading_probability``, imaging loss off so that every atom is
there for the whole exposure; the threshold calibrated from frames as the engine does) and the error the
simulator's two-population model predicts at that threshold. ``--frames`` sets the readings:
frames x traps (100 x 2048 resolves 5e-5 at ~10 expected errors).
"""

from __future__ import annotations

import argparse

import numpy as np

from drivers.sim.camera import SimCamera, predicted_sum_statistics
from drivers.sim.clock import SimClock
from drivers.sim.readout import clock_induced_charge, read_noise, readout_time
from engine.config import SystemConfig, load_config
from engine.imaging import Detector, calibration_frames
from engine.imaging_calibration import error_probability

#: (label, camera settings) tried, from the paper's to the fastest
SETTINGS: list[tuple[str, dict[str, object]]] = [
    ("4.33 us, 30 MHz, 1x1 (paper)", {}),
    ("4.33 us, 30 MHz, 1x16", {"binning": (1, 16)}),
    ("2.2 us, 30 MHz, 1x8", {"vertical_shift_s": 2.2e-6, "binning": (1, 8), "origin_px": (8.0, 4.0)}),
    ("2.2 us, 30 MHz, 1x16", {"vertical_shift_s": 2.2e-6, "binning": (1, 16)}),
    ("2.2 us, 20 MHz, 1x16", {"vertical_shift_s": 2.2e-6, "horizontal_rate_hz": 20e6, "binning": (1, 16)}),
    ("1.13 us +2, 30 MHz, 1x16", {"vertical_shift_s": 1.13e-6, "vertical_clock_voltage": 2, "binning": (1, 16)}),
    ("0.6 us +4, 30 MHz, 1x16", {"vertical_shift_s": 0.6e-6, "vertical_clock_voltage": 4, "binning": (1, 16)}),
    ("0.6 us +4, 30 MHz, 2x16", {"vertical_shift_s": 0.6e-6, "vertical_clock_voltage": 4, "binning": (2, 16)}),
    ("0.6 us +4, 10 MHz, 1x16", {"vertical_shift_s": 0.6e-6, "vertical_clock_voltage": 4, "horizontal_rate_hz": 10e6,
                                 "binning": (1, 16)}),
]
SETTINGS += [  # the exposure, the other lever: fewer photons per atom
    (f"0.6 us +4, 30 MHz, 2x16, {ms} ms exposure",
     {"vertical_shift_s": 0.6e-6, "vertical_clock_voltage": 4, "binning": (2, 16), "exposure_s": ms * 1e-3})
    for ms in (10, 5, 3, 2)
]


#: The paper's readout, which every setting above starts from
PAPER_READOUT: dict[str, object] = {
    "vertical_shift_s": 4.33e-6, "vertical_clock_voltage": 0, "horizontal_rate_hz": 30e6, "binning": (1, 1)
}


def with_camera(config: SystemConfig, **camera: object) -> SystemConfig:
    data = config.model_dump()
    data["camera"].update(PAPER_READOUT)
    data["camera"].update(camera)
    data["imaging"]["threshold"] = None
    return SystemConfig.model_validate(data)


def frames_and_truth(config: SystemConfig, n_frames: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    occupancy = np.zeros((config.array.ny, config.array.nx), dtype=bool)
    camera = SimCamera(config, atoms=lambda *_: occupancy, clock=SimClock(), rng=rng)
    frames = np.empty((n_frames, *camera.frame_shape), dtype=np.uint16)
    truth = np.empty((n_frames, *occupancy.shape), dtype=bool)
    for i in range(n_frames):
        occupancy[:] = rng.random(occupancy.shape) < config.sim.loading_probability
        truth[i] = occupancy
        camera.trigger()
        camera.read(frames[i], timeout_s=1.0)
    return frames, truth


def measure(config: SystemConfig, n_frames: int, seed: int) -> tuple[float, int, int, float]:
    """(I.acquire s, errors, readings, predicted error) for ``config``."""
    rng = np.random.default_rng(seed)
    detector = Detector(config)
    detector.calibrate(frames_and_truth(config, calibration_frames(config.array.n_traps), rng)[0])
    frames, truth = frames_and_truth(config, n_frames, rng)
    detected = np.empty(truth.shape[1:], dtype=bool)
    errors = 0
    for frame, true in zip(frames, truth, strict=True):
        detector.detect(frame, detected)
        errors += int((detected != true).sum())
    empty, atom = predicted_sum_statistics(config, detector.psf)
    thresholds = detector.thresholds.astype(np.float64)
    predicted = float(error_probability(thresholds, empty, atom, config.sim.loading_probability).mean())
    return readout_time(config.camera).total_s, errors, truth.size, predicted


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", help="a configuration file (YAML)")
    parser.add_argument("--frames", type=int, default=100, help="frames measured per setting (default 100)")
    parser.add_argument("--seed", type=int, default=1)
    args = parser.parse_args()
    base = load_config(args.config)
    base = base.model_copy(update={"sim": base.sim.model_copy(update={"lossless": True})})
    print("| Settings (vertical shift, horizontal rate, binning x*y) | I.acquire (ms) | CIC (e-/px) | read noise (e-) "
          "| errors / readings | measured error | predicted error |")
    print("|---|---|---|---|---|---|---|")
    for label, camera in SETTINGS:
        config = with_camera(base, **camera)
        acquire_s, errors, readings, predicted = measure(config, args.frames, args.seed)
        img = config.sim.imaging
        print(f"| {label} | {acquire_s * 1e3:.2f} | {clock_induced_charge(config.camera, img):.4f} | "
              f"{read_noise(config.camera, img):.0f} | {errors} / {readings} | {errors / readings:.1e} | "
              f"{predicted:.1e} |", flush=True)


if __name__ == "__main__":
    main()
