"""Exact replay: the simulated world's random streams and vacuum hits, and `llrs run` in replay time."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from drivers.sim.world import World
from engine.config import ConfigError, config_from_dict
from server.cli import main as cli_main
from sim_signals import grid_config


def _tracks(*rows: tuple[float, float, float, float]) -> np.ndarray:
    return np.array(rows, dtype=np.float32).reshape(-1, 4)


def _play(world: World, slot_times_s: np.ndarray, extra_updates: np.ndarray) -> None:
    """Extract row 0, carry it down the array one row per slot, implant: with ``elapse_to`` before every slot
    (as the AWG does) and, in between, at the times ``extra_updates`` (as camera reads and syncs do)."""
    ny, nx = world.ny, world.nx
    cols = [(c, c, 1, 1) for c in range(nx)]
    for k, t in enumerate(slot_times_s):
        for t_extra in extra_updates[(extra_updates < t) & (extra_updates >= (slot_times_s[k - 1] if k else 0))]:
            world.elapse_to(float(t_extra))
        world.elapse_to(float(t))
        if k == 0:
            world.apply_slot(_tracks(*[(c, c, 0, 1) for c in range(nx)]), _tracks((0, 0, 0, 1)))
        elif k < ny:
            world.apply_slot(_tracks(*cols), _tracks((k - 1, k, 1, 1)))
        else:
            world.apply_slot(_tracks(*[(c, c, 1, 0) for c in range(nx)]), _tracks((ny - 1, ny - 1, 1, 0)))
    world.elapse_to(float(slot_times_s[-1]) + 0.5)


@pytest.mark.parametrize("reference", [False, True], ids=["kernel", "reference"])
def test_same_seed_loses_the_same_atoms_whatever_the_number_of_elapse_to_calls(reference: bool) -> None:
    # a 0.5 s lifetime so that a 1 s shot loses most atoms to vacuum: the comparison has plenty to disagree on
    cfg = grid_config(16, 12, sim={"vacuum_lifetime_s": 0.5, "survival_transfer": 0.9, "survival_step": 0.95})
    slot_times_s = np.linspace(0.01, 1.0, 13)
    outcomes = []
    for n_extra in (0, 7, 5000):
        world = World(cfg, rng=np.random.default_rng(42), reference=reference)
        world.load()
        extra = np.sort(np.random.default_rng(n_extra).uniform(0, 1.0, n_extra))
        _play(world, slot_times_s, extra)
        outcomes.append((world.occupancy().copy(), world.held().copy(), world.counters.as_dict()))
    first = outcomes[0]
    assert 20 < first[2]["lost_vacuum"] < first[2]["loaded"]  # vacuum loss is really exercised
    assert first[2]["lost_step"] > 0 and first[2]["lost_transfer"] > 0
    for occ, held, counters in outcomes[1:]:
        assert np.array_equal(occ, first[0])
        assert np.array_equal(held, first[1])
        assert counters == first[2]


def test_vacuum_survival_is_exponential_in_time_however_time_is_cut() -> None:
    """Many small steps or one big one: the fraction left after time t is exp(-t / tau) either way."""
    # 64 tones per axis up to 143 MHz at 313.6 MS/s: amplitudes that fit full scale once compensated for the DAC
    cfg = grid_config(64, 64, sim={"vacuum_lifetime_s": 1.0},
                      array={"x_tones": {"amplitude": 0.012}, "y_tones": {"amplitude": 0.012}})
    for n_steps in (1, 400):
        world = World(cfg, rng=np.random.default_rng(n_steps))
        world.set_occupancy(np.ones((64, 64), bool))
        for t in np.linspace(0, 0.7, n_steps + 1)[1:]:
            world.elapse_to(float(t))
        p = np.exp(-0.7)
        assert abs(world.occupancy().mean() - p) < 4 * np.sqrt(p * (1 - p) / 4096)


def test_loading_does_not_depend_on_what_moves_and_vacuum_drew() -> None:
    """Independent streams: a shot with more losses before it loads the same atoms in the next shot."""
    quiet = grid_config(16, 12, sim={"vacuum_lifetime_s": 1e6})
    busy = grid_config(16, 12, sim={"vacuum_lifetime_s": 0.1, "survival_transfer": 0.5})
    loads = []
    for cfg in (quiet, busy):
        world = World(cfg, rng=np.random.default_rng(9))
        world.load()
        _play(world, np.linspace(0.01, 0.5, 14), np.zeros(0))
        loads.append(world.load().copy())
    assert np.array_equal(loads[0], loads[1])


# --- llrs run in replay time -------------------------------------------------------------------------------

_BUSY_LOOP = "import time\nend = time.monotonic() + 120\nwhile time.monotonic() < end:\n    pass\n"


def test_llrs_run_replays_a_seed_exactly_under_cpu_load(capsys: pytest.CaptureFixture[str]) -> None:
    """Three runs of the same seed, the first on a quiet machine and the other two with CPU-bound processes
    competing for the cores: identical shots, atom for atom (outcomes, cycles, per-cycle occupancy, the world's
    final atoms, and even the stage times). (The busy processes burn a core each for as long as they run, so
    they run only while the loaded runs do.)"""

    def run() -> dict:
        args = ["run", "--config", "examples/grid-16x32.yaml", "--shots", "3", "--seed", "7", "--time", "replay"]
        assert cli_main([*args, "--json"]) == 0
        return json.loads(capsys.readouterr().out)

    runs = [run()]
    busy = [subprocess.Popen([sys.executable, "-c", _BUSY_LOOP]) for _ in range(2)]  # ends by itself in 120 s
    try:
        runs += [run() for _ in range(2)]
    finally:
        for process in busy:
            process.kill()
            process.wait()
    first = runs[0]
    assert len(first["per_shot"]) == 3 and first["cycles_mean"] > 0  # shots that really rearranged
    assert all(len(s["occupancy"]) == len(s["slots"]) for s in first["per_shot"])
    for run in runs[1:]:
        assert run == first


def test_replay_charges_rejects_unknown_stage_names() -> None:
    with pytest.raises(ConfigError, match="replay_host_s"):
        config_from_dict({"sim": {"replay_host_s": {"III.solver": 1e-5}}})
