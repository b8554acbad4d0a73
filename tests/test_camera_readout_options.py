"""The iXon Ultra 888's readout options in the simulated camera: what each costs in time (the readout model)
and in noise (clock-induced charge, read noise, pixels per spot), and the shipped examples' choice."""

from __future__ import annotations

import numpy as np
import pytest

from drivers.sim.camera import SimCamera
from drivers.sim.clock import SimClock
from drivers.sim.readout import (
    CIC_PER_VOLTAGE_STEP,
    READOUT_OFFSET_SHIFTS,
    ROW_EXTRA_SHIFTS,
    clock_induced_charge,
    read_noise,
    readout_time,
)
from engine.config import CameraConfig, SimImagingConfig, SystemConfig, load_config
from scripts.readout_tradeoff import measure

FAST: dict[str, object] = {"vertical_shift_s": 0.6e-6, "vertical_clock_voltage": 4}


def dark_config(imaging: dict, **camera: object) -> SystemConfig:
    """A 1x4 chain on a 64x16 ROI with no atoms' light reaching it unless ``imaging`` says so."""
    return SystemConfig.model_validate({
        "array": {"nx": 4, "ny": 1},
        "target": {"count": 2},
        "camera": {"roi_width_px": 64, "roi_height_px": 16, **camera},
        "sim": {"seed": 3, "imaging": {"background_photons_per_px_per_s": 0.0, **imaging}},
    })


def frames(config: SystemConfig, n: int, occupied: bool = False) -> np.ndarray:
    occupancy = np.full((config.array.ny, config.array.nx), occupied)
    camera = SimCamera(config, atoms=lambda *_: occupancy, clock=SimClock(), rng=np.random.default_rng(5))
    out = np.empty((n, *camera.frame_shape), dtype=np.uint16)
    for frame in out:
        camera.trigger()
        camera.read(frame, timeout_s=1.0)
    return out


def test_each_readout_option_changes_the_time_as_the_model_says() -> None:
    """Vertical shift: frame transfer (1039 rows) and one shift per read row; horizontal rate: every row's
    ROI width + 48 pixels and the gain chain's offset; vertical binning: fewer rows; horizontal binning: only
    the transfer of fewer bytes; ROI height: rows."""
    base = CameraConfig(roi_width_px=1024, roi_height_px=512)
    t0 = readout_time(base)
    fast = readout_time(base.model_copy(update=FAST))
    assert t0.frame_transfer_s - fast.frame_transfer_s == pytest.approx(1039 * (4.33e-6 - 0.6e-6))
    assert t0.row_readout_s - fast.row_readout_s == pytest.approx(512 * (4.33e-6 - 0.6e-6))
    slow = readout_time(base.model_copy(update={"horizontal_rate_hz": 10e6}))
    shifts = 512 * (1024 + ROW_EXTRA_SHIFTS) + READOUT_OFFSET_SHIFTS
    assert slow.row_readout_s - t0.row_readout_s == pytest.approx(shifts * (1 / 10e6 - 1 / 30e6))
    binned = readout_time(base.model_copy(update={"binning": (2, 16)}))
    assert binned.frame_transfer_s == t0.frame_transfer_s
    assert binned.row_readout_s - READOUT_OFFSET_SHIFTS / 30e6 == pytest.approx(
        (t0.row_readout_s - READOUT_OFFSET_SHIFTS / 30e6) / 16
    )
    assert binned.dma_s == pytest.approx(t0.dma_s / 32)
    half = readout_time(base.model_copy(update={"roi_height_px": 256}))
    assert t0.row_readout_s - half.row_readout_s == pytest.approx(256 * (4.33e-6 + 1072 / 30e6))


def test_faster_vertical_shift_needs_voltage_and_raises_clock_induced_charge() -> None:
    img = SimImagingConfig()
    cic = {
        (s, v): clock_induced_charge(CameraConfig(vertical_shift_s=s, vertical_clock_voltage=v), img)
        for s, v in ((4.33e-6, 0), (2.2e-6, 0), (1.13e-6, 2), (0.6e-6, 4))
    }
    assert cic[(4.33e-6, 0)] == img.clock_induced_charge_e
    assert cic[(2.2e-6, 0)] < cic[(4.33e-6, 0)]  # same voltage: a shorter clock pulse makes a little less
    assert cic[(0.6e-6, 4)] > cic[(1.13e-6, 2)] > cic[(4.33e-6, 0)]  # at the voltage each speed needs: more
    raised = clock_induced_charge(CameraConfig(vertical_shift_s=2.2e-6, vertical_clock_voltage=2), img)
    assert raised / cic[(2.2e-6, 0)] == pytest.approx(CIC_PER_VOLTAGE_STEP**2)  # per voltage step
    # and the frames carry it: the mean dark excess over the bias scales as the clock-induced charge
    excess = []
    for camera in ({}, FAST):
        config = dark_config({"read_noise_e": 0.0, "clock_induced_charge_e": 0.02}, **camera)
        excess.append(frames(config, 200).mean() - config.sim.imaging.bias_counts)
    expected = clock_induced_charge(CameraConfig.model_validate(FAST), img) / img.clock_induced_charge_e
    assert excess[1] / excess[0] == pytest.approx(expected, rel=0.1)


def test_slower_horizontal_rate_lowers_the_read_noise_of_the_frames() -> None:
    stds = {}
    for rate in (30e6, 1e6):
        config = dark_config({"clock_induced_charge_e": 0.0, "read_noise_e": 200.0}, horizontal_rate_hz=rate)
        stds[rate] = frames(config, 20).std() * config.sim.imaging.electrons_per_count
        assert stds[rate] == pytest.approx(read_noise(config.camera, config.sim.imaging), rel=0.05)
    assert stds[1e6] < stds[30e6] / 4


def test_binning_puts_a_spot_in_fewer_pixels_with_all_its_light() -> None:
    imaging = {"clock_induced_charge_e": 0.0, "read_noise_e": 0.0, "brightness_spread": 0.0}
    lit = {}
    for binning in ((1, 1), (2, 16)):
        config = dark_config(imaging, binning=binning)
        frame = frames(config, 1, occupied=True)[0].astype(np.float64) - config.sim.imaging.bias_counts
        lit[binning] = (np.count_nonzero(frame > 0), frame.sum())
    assert lit[(2, 16)][0] < lit[(1, 1)][0] / 3  # pixels holding light: a spot's 5 rows are one binned row
    assert lit[(2, 16)][1] == pytest.approx(lit[(1, 1)][1], rel=0.15)  # the same light (EM gain noise aside)


@pytest.mark.parametrize(
    ("camera", "message"),
    [
        ({"vertical_shift_s": 1e-6}, "vertical shift speed of the iXon Ultra 888"),
        ({"horizontal_rate_hz": 15e6}, "readout rate"),
        ({"vertical_shift_s": 0.6e-6, "vertical_clock_voltage": 2}, "vertical_clock_voltage to at least 4"),
    ],
)
def test_the_simulated_camera_rejects_settings_the_camera_lacks(camera: dict, message: str) -> None:
    with pytest.raises(ValueError, match=message):
        frames(dark_config({}, **camera), 1)


def test_grid_32x64_example_images_within_25_ms_below_5e5_detection_error() -> None:
    """The issue's target for the paper's 32x64 problem at 20 ms exposure. The error part: 0 errors in
    40 x 2048 readings rejects a true error of 5e-5 (4.1 expected) at 98 % confidence, and the two-population
    model agrees with a margin of many orders of magnitude."""
    config = load_config("examples/grid-32x64.yaml")
    config = config.model_copy(update={"sim": config.sim.model_copy(update={"lossless": True})})
    assert config.camera.exposure_s == 0.020
    acquire_s, errors, readings, predicted = measure(config, n_frames=40, seed=2)
    assert acquire_s <= 0.025
    assert readings == 40 * 2048
    assert errors == 0
    assert predicted < 5e-7
