"""Imaging physics of the simulated lab (issue 12): imaging costs atoms at the configured rate, an atom lost
mid-exposure is bright for the part of the exposure it was there, traps differ in brightness, the EMCCD adds
clock-induced charge at every readout, photons scale with the exposure, and the engine's threshold is its own
(configured or fitted to frames), whatever the simulated camera's hidden parameters."""

from __future__ import annotations

import math

import numpy as np
import pytest

from drivers.sim.camera import SimCamera, trap_brightness
from drivers.sim.clock import SimClock
from drivers.sim.lab import build_sim_lab
from drivers.sim.world import World
from engine.config import SystemConfig
from engine.engine import Engine
from engine.imaging import Detector
from sim_signals import chain_config


def grid(ny: int = 32, nx: int = 32, imaging: dict | None = None, **camera: object) -> SystemConfig:
    """A slm grid imaged 16 px per trap; vacuum loss negligible, so every atom lost is imaging's."""
    return SystemConfig.model_validate(
        {
            "array": {"nx": nx, "ny": ny, "trap_source": "slm"},
            "camera": {"roi_width_px": 16 * nx, "roi_height_px": 16 * ny, **camera},
            "target": {"count": nx},
            "sim": {"imaging": imaging or {}, "seed": 3, "vacuum_lifetime_s": 1e9},
        }
    )


def full_world(config: SystemConfig) -> World:
    world = World(config)
    world.set_occupancy(np.ones((config.array.ny, config.array.nx), dtype=bool))
    return world


@pytest.mark.parametrize(("rate_hz", "exposure_s"), [(0.5, 0.020), (5.0, 0.020), (5.0, 0.040)])
def test_imaging_loses_atoms_at_the_configured_rate(rate_hz: float, exposure_s: float) -> None:
    """Over 20 images of 1,024 atoms the lost fraction is ``1 - exp(-rate * exposure)`` within 4 binomial
    standard deviations (the default 0.5/s loses 1 % of the atoms per 20 ms image)."""
    config = grid(imaging={"loss_rate_hz": rate_hz})
    p_loss = -math.expm1(-rate_hz * exposure_s)
    world = World(config)
    imaged = 0
    for _ in range(20):  # one world, refilled: its imaging stream runs on (a new world would replay it)
        world.set_occupancy(np.ones((config.array.ny, config.array.nx), dtype=bool))
        lost_before = world.counters.lost_imaging
        world.expose(0.0, exposure_s)
        imaged += config.array.n_traps
        assert world.counters.lost_imaging - lost_before == config.array.n_traps - world.n_atoms
    lost = world.counters.lost_imaging
    assert abs(lost - imaged * p_loss) <= 4 * math.sqrt(imaged * p_loss * (1 - p_loss)), (lost, imaged * p_loss)


def test_an_atom_lost_mid_exposure_is_there_for_part_of_it() -> None:
    """Presence is 1 for survivors, 0 for empty traps, and ``t / exposure`` for a lost atom, with ``t`` from
    the exponential law truncated to the exposure: at ``rate * exposure = 1`` its mean is
    ``1 - e^-1 / (1 - e^-1) = 0.418`` (a uniform loss time would give 0.5)."""
    config = grid(imaging={"loss_rate_hz": 50.0})
    world = full_world(config)
    occupancy = world.occupancy().copy()
    occupancy[::2] = False
    world.set_occupancy(occupancy)
    presence = world.expose(0.0, 0.020)
    lost = occupancy & ~world.occupancy()
    assert (presence[~occupancy] == 0).all()
    assert (presence[world.occupancy()] == 1).all()
    fractions = presence[lost]
    assert ((fractions > 0) & (fractions < 1)).all()
    expected = 1 - math.exp(-1) / (1 - math.exp(-1))
    spread = math.sqrt(1 / 12) / math.sqrt(fractions.size)  # at most a uniform's spread
    assert fractions.mean() == pytest.approx(expected, abs=4 * spread)
    p_loss = 1 - math.exp(-1)
    n = occupancy.sum()
    assert lost.sum() / n == pytest.approx(p_loss, abs=4 * math.sqrt(p_loss * (1 - p_loss) / n))  # 4 binomial sd


def test_lossless_and_zero_rate_image_without_loss() -> None:
    for config in (grid(imaging={"loss_rate_hz": 50.0}).model_copy(deep=True), grid(imaging={"loss_rate_hz": 0.0})):
        world = World(config, lossless=config.sim.imaging.loss_rate_hz > 0)
        world.set_occupancy(np.ones((32, 32), dtype=bool))
        assert (world.expose(0.0, 0.020) == 1).all() and world.n_atoms == 1024


def test_imaging_losses_replay_whatever_the_other_streams_drew() -> None:
    """Imaging draws from a stream of its own: extra draws by the other streams (here: loadings that were
    thrown away) change nothing about which atoms an image loses."""
    config = grid(imaging={"loss_rate_hz": 5.0})
    a, b = full_world(config), full_world(config)
    for _ in range(3):
        b.load()
    b.set_occupancy(a.occupancy())
    np.testing.assert_array_equal(a.expose(0.0, 0.02), b.expose(0.0, 0.02))
    np.testing.assert_array_equal(a.occupancy(), b.occupancy())


def test_the_lab_camera_images_through_the_world_and_costs_atoms() -> None:
    config = grid(imaging={"loss_rate_hz": 5.0})
    devices, lab = build_sim_lab(config)
    lab.world.set_occupancy(np.ones((32, 32), dtype=bool))
    frame = np.empty(devices.camera.frame_shape, dtype=np.uint16)
    for _ in range(5):
        devices.camera.trigger()
        devices.camera.read(frame, timeout_s=1.0)
    lost = lab.world.counters.lost_imaging
    assert lost == 1024 - lab.world.n_atoms
    expected = 1024 * (1 - math.exp(-5.0 * 0.1))  # five 20 ms images
    assert abs(lost - expected) <= 4 * math.sqrt(expected)


def mean_sums(config: SystemConfig, occupancy: np.ndarray, n_frames: int, seed: int = 1) -> np.ndarray:
    """Per-trap weighted sums (the detector's), averaged over ``n_frames`` frames of a fixed occupancy."""
    camera = SimCamera(config, atoms=lambda *_: occupancy, clock=SimClock(), rng=np.random.default_rng(seed))
    detector = Detector(config, thresholds=0.0)
    frame = np.empty(camera.frame_shape, dtype=np.uint16)
    total = np.zeros(config.array.n_traps)
    for _ in range(n_frames):
        camera.trigger()
        camera.read(frame, timeout_s=1.0)
        detector.sum(frame)
        total += detector.counts
    return total / n_frames


def test_per_trap_brightness_spread_shows_in_the_per_trap_means() -> None:
    """With a 10 % spread and a beam falling to 80 % at the corners, the per-trap mean signal follows the
    seeded pattern (correlation > 0.95) and spreads across the array as much as the pattern does."""
    config = grid(16, 32, imaging={"brightness_spread": 0.10, "beam_edge_brightness": 0.8})
    pattern = trap_brightness(config)
    assert pattern.std() / pattern.mean() == pytest.approx(math.hypot(0.10, 0.06), abs=0.03)
    ones = np.ones((16, 32), dtype=bool)
    signal = mean_sums(config, ones, 20) - mean_sums(config, ~ones, 5)
    assert np.corrcoef(signal, pattern)[0, 1] > 0.95
    assert signal.std() / signal.mean() == pytest.approx(pattern.std() / pattern.mean(), rel=0.15)
    corners = pattern.reshape(16, 32)[[0, 0, -1, -1], [0, -1, 0, -1]]
    assert corners.mean() < pattern.reshape(16, 32)[6:10, 12:20].mean()  # the beam's edge is dimmer
    np.testing.assert_array_equal(pattern, trap_brightness(config))  # fixed for a seed
    other = config.model_copy(update={"sim": config.sim.model_copy(update={"seed": 4})})
    assert not np.array_equal(pattern, trap_brightness(other))


def test_clock_induced_charge_comes_with_every_readout_whatever_the_exposure() -> None:
    """No light at all: the dark frame's mean above the bias is ``cic * gain / electrons_per_count``, the
    same for a 1 ms and a 20 ms exposure, and zero without CIC; stray light and atom light scale with the
    exposure instead."""
    dark = {"background_photons_per_px_per_s": 0.0, "clock_induced_charge_e": 0.05}
    nothing = np.zeros((1, 64), dtype=bool)

    def frame_mean(imaging: dict, exposure_s: float, occupancy: np.ndarray = nothing) -> float:
        config = chain_config(64, camera={"exposure_s": exposure_s}, sim={"imaging": imaging})
        camera = SimCamera(config, atoms=lambda *_: occupancy, clock=SimClock(), rng=np.random.default_rng(5))
        frames = np.empty((20, *camera.frame_shape), dtype=np.uint16)
        for frame in frames:
            camera.trigger()
            camera.read(frame, timeout_s=1.0)
        return float(frames.mean()) - config.sim.imaging.bias_counts

    cic_counts = 0.05 * 300 / 20
    for exposure_s in (0.001, 0.020):
        assert frame_mean(dark, exposure_s) == pytest.approx(cic_counts, abs=0.05)
    assert frame_mean({**dark, "clock_induced_charge_e": 0.0}, 0.020) == pytest.approx(0.0, abs=0.05)
    stray = {"background_photons_per_px_per_s": 50.0, "clock_induced_charge_e": 0.0}
    assert frame_mean(stray, 0.020) == pytest.approx(2 * frame_mean(stray, 0.010), rel=0.05)
    full = np.ones((1, 64), dtype=bool)
    no_bg = {"background_photons_per_px_per_s": 0.0, "clock_induced_charge_e": 0.0, "brightness_spread": 0.0}
    assert frame_mean(no_bg, 0.020, full) == pytest.approx(2 * frame_mean(no_bg, 0.010, full), rel=0.03)


def test_the_engine_threshold_is_its_own_not_the_simulated_cameras() -> None:
    """The engine calibrates once from frames when it applies ``imaging.threshold: null``; changing only the
    simulated camera's hidden parameters (``sim.imaging``) leaves its threshold exactly as it was (a lab's
    engine cannot see its atoms grow dimmer either), and a fresh fit to frames is what moves it."""
    config = chain_config(24, sim={"seed": 2, "lossless": True})
    devices, lab = build_sim_lab(config)
    engine = Engine(config, devices, lab=lab)
    detector = engine._p.detector  # noqa: SLF001 - the test reads the engine's own detection parameters
    assert detector.calibration is not None
    before = detector.thresholds.copy()
    hidden = {"scattering_rate_hz": 2.5e5, "read_noise_e": 90.0, "bias_counts": 520.0, "brightness_spread": 0.2}
    changed = config.model_copy(
        update={"sim": config.sim.model_copy(update={"imaging": config.sim.imaging.model_copy(update=hidden)})}
    )
    engine.apply(changed)
    np.testing.assert_array_equal(engine._p.detector.thresholds, before)  # noqa: SLF001 - as above
    refit = Detector(changed)
    refit.calibrate(engine.acquire_images(20))
    assert abs(float(refit.thresholds[0]) - float(before[0])) > 5.0  # the dimmer, noisier camera needs another
    devices.close()
