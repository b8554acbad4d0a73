"""The simulated lab: one world of atoms shared by a simulated camera and a simulated AWG.

``build_sim_lab(config)`` returns the device set the engine drives and the lab hooks (``engine.engine.Lab``:
load atoms before a shot, report the world's truth after it, inject planner faults). The engine cannot tell
these devices from hardware: the camera renders the world's atoms, and the AWG moves them by decoding the
samples it plays.
"""

from __future__ import annotations

from dataclasses import fields, replace
from typing import Any

import numpy as np

from drivers.sim.awg import SimAWG
from drivers.sim.camera import SimCamera
from drivers.sim.clock import SimClock
from drivers.sim.world import World, WorldCounters
from engine.config import FaultConfig, SystemConfig
from engine.devices import DeviceSet
from engine.operations import Plan
from engine.records import occupancy_to_rows
from engine.solvers import Planner

__all__ = ["LOSS_CAUSES", "InjectedSolverFault", "SimLab", "build_sim_lab"]

# the world's loss counters (``WorldCounters.lost_*``), named by their cause: the keys of ``lost_by_cause``
LOSS_CAUSES = tuple(f.name.removeprefix("lost_") for f in fields(WorldCounters) if f.name.startswith("lost_"))


class InjectedSolverFault(Exception):
    """Raised by the planner when ``sim.faults.solver`` asks for it: stands in for a bug in a planner."""


class _FailingPlanner:
    """Wraps the configured planner and fails every solve (``sim.faults.solver: exception``)."""

    def __init__(self, planner: Planner) -> None:
        self._planner = planner
        self.nx, self.ny = planner.nx, planner.ny

    def check_target(self, target: np.ndarray) -> None:
        self._planner.check_target(target)

    def solve_moves(self, occupancy: np.ndarray, target: np.ndarray) -> int:
        raise InjectedSolverFault("injected solver fault (sim.faults.solver = 'exception')")

    def batch(self) -> Plan:
        return self._planner.batch()


class SimLab:
    """Lab hooks for the engine (see ``engine.engine.Lab``) plus access to the world for tests."""

    def __init__(self, world: World, awg: SimAWG, camera: SimCamera) -> None:
        self.world = world
        self.awg = awg
        self.camera = camera
        self.faults = FaultConfig()
        # the world's counters just before each exposure of this shot: the bounds of its cycles' losses
        self._counters_at_exposure: list[WorldCounters] = []

    def configure(self, config: SystemConfig) -> None:
        """Adopt a configuration the engine is applying: array, tones, loss model and injected faults."""
        self.world.reconfigure(config)
        self.camera.set_system_config(config)
        self.awg.set_system_config(config)
        self.faults = config.sim.faults  # they strike from the next shot on, not while the engine programs
        self._arm(FaultConfig())

    def _arm(self, faults: FaultConfig) -> None:
        self.camera.fault = None if faults.camera == "none" else faults.camera
        self.awg.fail_uploads = faults.awg_upload == "fail"
        self.awg.upload_delay_s = faults.upload_delay_s

    def prepare_shot(self) -> None:
        """Arm the configured faults, throw away the previous atoms and load a fresh array (Bernoulli per trap)."""
        self._arm(self.faults)
        self.awg.sync()
        self.world.load()
        self._counters_at_exposure.clear()

    def expose(self, t0_s: float, exposure_s: float) -> np.ndarray:
        """The camera's view of the world: the AWG's playback applied up to now, then the exposure (which may
        lose atoms to imaging). The world's counters are noted first, so each cycle's losses run from its image
        to the next."""
        self.awg.sync()
        self._counters_at_exposure.append(replace(self.world.counters))
        return self.world.expose(t0_s, exposure_s)

    def planner(self, planner: Planner, config: SystemConfig) -> Planner:
        """The engine's planner, or one that fails every solve when ``config.sim.faults.solver`` injects it."""
        return _FailingPlanner(planner) if config.sim.faults.solver == "exception" else planner

    def ground_truth(self) -> np.ndarray:
        """``bool[ny, nx]``: the world's atoms now (the AWG's playback so far applied), a copy."""
        self.awg.sync()
        return self.world.occupancy().copy()

    def shot_report(self, target: np.ndarray) -> dict[str, Any]:
        """After a shot: the world's atoms (one '0'/'1' string per row) and whether they fill ``target``,
        the success the engine could only judge from its images."""
        truth = self.ground_truth()
        return {"occupancy_rows": occupancy_to_rows(truth), "target_filled": bool(np.all(truth[target]))}

    def cycle_reports(self, n_cycles: int) -> list[dict[str, Any]]:
        """After a shot, one report per cycle: ``lost_by_cause``, the atoms the world lost from the cycle's image
        (its exposure included) to the next image, or to the end of the shot for the last cycle, per cause
        (``LOSS_CAUSES``). A cycle that took no image (a camera fault) reports nothing."""
        self.awg.sync()
        bounds = [*self._counters_at_exposure[:n_cycles], self.world.counters]
        reports: list[dict[str, Any]] = []
        for before, after in zip(bounds, bounds[1:], strict=False):
            lost = (getattr(after, f"lost_{cause}") - getattr(before, f"lost_{cause}") for cause in LOSS_CAUSES)
            reports.append({"lost_by_cause": dict(zip(LOSS_CAUSES, lost, strict=True))})
        return reports + [{} for _ in range(n_cycles - len(reports))]  # one dict each: records own theirs

    def reseed(self, seed: int) -> None:
        """Restart the world's and the camera's random numbers from ``seed``, as ``build_sim_lab`` seeds them.

        The next shot then depends only on ``seed`` and the configuration, not on the shots run before it, so a
        sweep may split its shots across processes or machines and still get the same outcomes.
        """
        world_rng, camera_rng, awg_rng = _generators(seed)
        self.world.reseed(world_rng)
        self.camera.rng = camera_rng
        self.awg.rng = awg_rng


def _generators(seed: int | None) -> tuple[np.random.Generator, np.random.Generator, np.random.Generator]:
    """One stream per device, derived from one seed (the world splits its own per kind of event), so that no
    device's draws shift another's: (world, camera, AWG)."""
    world_seed, camera_seed, awg_seed = np.random.SeedSequence(seed).spawn(3)
    return np.random.default_rng(world_seed), np.random.default_rng(camera_seed), np.random.default_rng(awg_seed)


def build_sim_lab(config: SystemConfig) -> tuple[DeviceSet, SimLab]:
    clock = SimClock(config.sim.time, config.sim.replay_host_s)
    world_rng, camera_rng, awg_rng = _generators(config.sim.seed)
    world = World(config, clock=clock, rng=world_rng)
    awg = SimAWG(world, clock, config, rng=awg_rng)

    def exposure(t0_s: float, exposure_s: float) -> np.ndarray:
        return lab.expose(t0_s, exposure_s)  # the lab is built below, before the camera exposes

    camera = SimCamera(config, atoms=exposure, clock=clock, rng=camera_rng)
    lab = SimLab(world, awg, camera)
    lab.configure(config)
    return DeviceSet(camera=camera, awg=awg, clock=clock), lab
