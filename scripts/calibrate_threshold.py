"""Calibrate an example's occupancy threshold against the simulated camera, as the lab's dashboard does.

    .venv/bin/python scripts/calibrate_threshold.py examples/chain-1x64.yaml [--images 40]

Loads the configuration with its threshold cleared, builds the simulated lab and an engine on it, takes
``--images`` frames of freshly loaded arrays and fits the two populations (``server.calibration``, the code
behind ``POST /api/calibrate/threshold``). Prints the fitted threshold with its predicted fidelity; the
shipped examples' ``imaging.threshold`` values come from this command.
"""

from __future__ import annotations

import argparse

from drivers.sim.lab import build_sim_lab
from engine.config import load_config
from engine.engine import Engine
from server.calibration import threshold_calibration


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("config", help="a configuration file (YAML)")
    parser.add_argument("--images", type=int, default=40, help="frames to fit (default 40)")
    args = parser.parse_args()
    loaded = load_config(args.config)
    config = loaded.model_copy(update={"imaging": loaded.imaging.model_copy(update={"threshold": None})})
    devices, lab = build_sim_lab(config)
    engine = Engine(config, devices, lab=lab)
    result = threshold_calibration(engine.acquire_images(args.images), config)
    devices.close()
    print(
        f"{args.config}: threshold {result['threshold']:.1f} counts, predicted error {1 - result['fidelity']:.1e} "
        f"(empty {result['mean_empty']:.1f} +- {result['std_empty']:.1f}, atom {result['mean_atom']:.1f} "
        f"+- {result['std_atom']:.1f}, filled {result['fraction_filled']:.3f}, {result['images']} frames)"
    )


if __name__ == "__main__":
    main()
