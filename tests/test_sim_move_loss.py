"""Speed-dependent move loss: the trap physics of drivers/sim/move_loss.py and the world that uses it."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.special import gammainc

from drivers.sim.move_loss import (
    ALPHA_HOLD,
    TrapParameters,
    _ramp_q,
    barrier_fraction,
    move_survival,
    step_survival,
    transfer_survival,
)
from drivers.sim.world import World
from sim_signals import chain_config, grid_config


def rb87(**over: float) -> TrapParameters:
    """Rubidium-87 in 1 mK, 1 um-waist traps at 15 uK (the MoveLossConfig defaults), with ``over`` changed."""
    values = {"tweezer_depth_mk": 1.0, "static_depth_mk": 1.0, "waist_um": 1.0, "temperature_uk": 15.0}
    return TrapParameters(**{**values, **over}, atom_mass_amu=86.909)


RB87 = rb87()
WARM = rb87(temperature_uk=40.0)


def test_shorter_slots_lose_more_atoms_per_step() -> None:
    """5 us, 10 us and 100 us one-site steps (a 400x range in peak acceleration): strictly ordered losses, and
    the 5 us step exceeds what the trap can hold at all."""
    loss = {t: 1.0 - step_survival(t, "min-jerk", 6.0, 1.0, WARM) for t in (5e-6, 10e-6, 100e-6)}
    assert loss[5e-6] > loss[10e-6] > loss[100e-6]
    assert loss[5e-6] == 1.0  # peak acceleration 2.3e5 m/s^2 > a_hold = 1.21 U / (m w) = 1.16e5 m/s^2
    assert 1e-3 < loss[10e-6] < 0.1
    assert loss[100e-6] < 1e-6
    # steeper shapes at the same duration reach a higher peak acceleration, so they lose more
    assert step_survival(15e-6, "tanh", 6.0, 4.0, RB87) < step_survival(15e-6, "min-jerk", 6.0, 4.0, RB87)
    # and a wider spacing at the same duration is a faster move
    assert step_survival(15e-6, "min-jerk", 6.0, 4.0, RB87) < step_survival(15e-6, "min-jerk", 6.0, 2.0, RB87)


def test_barrier_of_the_tilted_trap() -> None:
    assert barrier_fraction(0.0) == 1.0
    # small tilt: the barrier falls linearly, by alpha times the barrier's distance (in waists) at first order
    alpha = 1e-3
    assert barrier_fraction(alpha) == pytest.approx(1.0 - alpha * 1.8, abs=5e-4)
    assert 0.0 < barrier_fraction(0.99 * ALPHA_HOLD) < 0.01
    assert barrier_fraction(ALPHA_HOLD) == 0.0
    values = [barrier_fraction(a) for a in np.linspace(0, ALPHA_HOLD, 30)]
    assert all(b >= a for a, b in zip(values[1:], values[:-1], strict=True))  # monotonic


def test_depth_ramps_are_sudden_when_short_and_adiabatic_when_long() -> None:
    """Husimi's Q: the closed form (w_i^2 + w_f^2) / (2 w_i w_f) for a sudden change, 1 for a slow one."""
    wi, wf = RB87.radial_omega(2.0), RB87.radial_omega(1.0)
    sudden = (wi * wi + wf * wf) / (2 * wi * wf)
    assert _ramp_q(2.0, 1.0, 1e-9, "min-jerk", 6.0, RB87) == pytest.approx(sudden, rel=1e-4)
    assert _ramp_q(2.0, 1.0, 100e-6, "min-jerk", 6.0, RB87) == 1.0
    assert 1.0 < _ramp_q(2.0, 1.0, 3e-6, "min-jerk", 6.0, RB87) < sudden


def test_fast_implant_into_a_shallow_static_trap_loses_atoms() -> None:
    shallow = rb87(static_depth_mk=0.3, temperature_uk=40.0)
    fast = transfer_survival(1e-6, "min-jerk", 6.0, shallow)
    slow = transfer_survival(100e-6, "min-jerk", 6.0, shallow)
    assert fast < slow < 1.0
    # the slow limit: adiabatic compression (kT grows as omega, by sqrt(1.3 / 0.3)) then decompression back to
    # the initial thermal state in U_s: P(E < U) = gammainc(3, U / kT) for each, the transfer the pair's root
    extract = gammainc(3, 1.3e-3 / (40e-6 * math.sqrt(1.3 / 0.3)))
    implant = 1.0 - math.exp(-7.5) * (1 + 7.5 + 7.5**2 / 2)  # gammainc(3, 0.3 mK / 40 uK)
    assert slow == pytest.approx(math.sqrt(extract * implant), rel=1e-5)


def test_world_charges_the_speed_model_on_top_of_the_configured_survival() -> None:
    moves = {"site_spacing_um": 1.0, "temperature_uk": 40.0}
    off = World(chain_config(8, sim={"survival_step": 0.99}))
    assert off.survival_step == 0.99  # no spacing: the model is off
    for slot_s in (10e-6, 100e-6):
        cfg = chain_config(8, sim={"survival_step": 0.99, "moves": moves}, waveforms={"slot_duration_s": slot_s})
        p_transfer, p_step = move_survival(slot_s, "min-jerk", 6.0, 1.0, WARM)
        world = World(cfg)
        assert world.survival_step == pytest.approx(0.99 * p_step)
        assert world.survival_transfer == pytest.approx(cfg.sim.survival_transfer * p_transfer)


def test_world_loses_steps_at_the_rate_the_model_gives() -> None:
    """Monte Carlo: every atom of a 64-site chain steps right and back 200 times at 10 us."""
    moves = {"site_spacing_um": 1.0, "temperature_uk": 40.0}
    cfg = chain_config(64, sim={"survival_step": 1.0, "vacuum_lifetime_s": 1e9, "moves": moves})
    world = World(cfg, rng=np.random.default_rng(3))
    p = world.survival_step
    assert 0.9 < p < 0.999
    right = np.array([(k, k + 1, 1, 1) for k in range(0, 63, 2)], dtype=np.float32)
    left = np.array([(k + 1, k, 1, 1) for k in range(0, 63, 2)], dtype=np.float32)
    for _ in range(200):
        atoms = np.zeros(64, bool)
        atoms[0::2] = True
        world.set_occupancy(atoms[None, :])
        world.apply_slot(right, None)
        world.apply_slot(left, None)
    steps, lost = world.counters.steps, world.counters.lost_step
    assert abs(lost / steps - (1 - p)) < 4 * math.sqrt(p * (1 - p) / steps)


def test_grid_world_uses_it_too() -> None:
    cfg = grid_config(8, 6, sim={"moves": {"site_spacing_um": 4.0}})
    assert World(cfg).survival_step == 0.0  # 4 um in 10 us: beyond what a 1 mK, 1 um tweezer holds
