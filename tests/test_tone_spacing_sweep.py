"""Any tone spacing the configuration accepts works: lossless shots in the simulated lab, across spacings down to
the simulated decoder's limit (10 us x 0.5 MHz = 5), array sizes and planners, lose no atom and disturb none.

Each shot's plans are rendered as waveforms, played by the simulated AWG, decoded from the samples and applied
to the world by the move model, so a comb too fine for the waveforms, the decoder or the moves (tones crossing
or merging) shows up as collisions, dropped or captured atoms. The default run sweeps a small grid and chain;
the larger sweep (the examples' 32x64 grid) is marked slow.
"""

from __future__ import annotations

import pytest

from drivers.sim.lab import build_sim_lab
from engine.config import SystemConfig
from engine.engine import Engine
from sim_signals import chain_config, grid_config

SPACINGS_HZ = (0.5e6, 0.6e6, 1.0e6)


def _spaced(config: SystemConfig, spacing_hz: float, algorithm: str, seed: int) -> SystemConfig:
    data = config.model_dump()
    for axis in ("x_tones", "y_tones"):
        data["array"][axis]["spacing_hz"] = spacing_hz
    data["solver"]["algorithm"] = algorithm
    data["sim"].update(lossless=True, seed=seed)
    return SystemConfig.model_validate(data)


def _sweep(base: SystemConfig, algorithms: tuple[str, ...], shots: int) -> None:
    """Every (spacing, planner) on one simulated lab, reconfigured between them as the server does."""
    engine: Engine | None = None
    for spacing_hz in SPACINGS_HZ:
        for algorithm in algorithms:
            config = _spaced(base, spacing_hz, algorithm, seed=int(spacing_hz / 1e5))
            if engine is None:
                devices, lab = build_sim_lab(config)
                engine = Engine(config, devices, lab=lab)
            else:
                engine.apply(config)
            counters = engine.lab.world.counters
            lost, captured, steps = counters.lost, counters.captured, counters.steps
            records = [engine.run_shot() for _ in range(shots)]
            where = f"{spacing_hz / 1e6:g} MHz, {algorithm}"
            assert all(r.fault is None for r in records), (where, [r.fault for r in records])
            assert counters.lost == lost, (where, counters.as_dict())
            assert counters.captured == captured, (where, counters.as_dict())
            assert counters.steps > steps, where  # atoms really moved
            for r in records:
                if r.cycles and r.cycles[0].atoms >= base.target.count:
                    assert r.lab_report.get("target_filled"), (where, r.outcome)


def test_a_small_grid_loses_no_atom_at_any_accepted_spacing() -> None:
    base = grid_config(12, 10, target={"kind": "centre", "count": 48},
                       awg={"n_segments": 64, "n_steps": 256, "waveforms_per_segment": 8})
    _sweep(base, ("aod-parallel", "red-rec"), shots=2)


def test_a_chain_loses_no_atom_at_any_accepted_spacing() -> None:
    _sweep(chain_config(32, awg={"n_segments": 64, "n_steps": 256, "waveforms_per_segment": 8}), ("exact-1d",),
           shots=3)


@pytest.mark.slow
def test_the_32x64_grid_loses_no_atom_at_any_accepted_spacing() -> None:
    base = grid_config(32, 64, target={"kind": "centre", "count": 1024}, array={"y_tones": {"amplitude": 0.012}},
                       awg={"n_segments": 256, "n_steps": 4096, "waveforms_per_segment": 32})
    _sweep(base, ("aod-parallel", "red-rec", "assignment"), shots=4)
