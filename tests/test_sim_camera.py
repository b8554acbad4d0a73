"""The simulated EMCCD: readout-time model (paper Table 1), image statistics, ROI/binning, saturation, faults."""

from __future__ import annotations

import time

import numpy as np
import pytest

from drivers.sim.camera import SimCamera
from drivers.sim.clock import SimClock
from drivers.sim.readout import readout_time
from engine.config import CameraConfig, SystemConfig
from engine.devices import Camera, DeviceError


def grid_config(
    ny: int, nx: int, roi_h: int, roi_w: int, imaging: dict | None = None, **camera: object
) -> SystemConfig:
    return SystemConfig.model_validate(
        {
            "array": {"nx": nx, "ny": ny, "trap_source": "slm"},
            "camera": {"roi_width_px": roi_w, "roi_height_px": roi_h, **camera},
            "target": {"count": nx},
            "sim": {"imaging": {**UNIFORM, **(imaging or {})}},
        }
    )


def chain_config(imaging: dict | None = None, **camera: object) -> SystemConfig:
    return SystemConfig.model_validate({"camera": camera, "sim": {"imaging": {**UNIFORM, **(imaging or {})}}})


#: every trap equally bright, so that per-trap expectations are one number (the spread has its own test)
UNIFORM = {"brightness_spread": 0.0, "beam_edge_brightness": 1.0}


def atom_counts(config: SystemConfig) -> float:
    """Mean counts (above bias) of a whole-exposure atom of brightness 1, from the documented photon budget."""
    img, cam = config.sim.imaging, config.camera
    electrons = img.scattering_rate_hz * cam.exposure_s * img.collection_efficiency * img.quantum_efficiency
    return electrons * cam.em_gain / img.electrons_per_count


def background_e(config: SystemConfig) -> float:
    """Mean electrons of an unbinned pixel without atom light: stray light over the exposure plus CIC."""
    img = config.sim.imaging
    stray_e = img.background_photons_per_px_per_s * config.camera.exposure_s * img.quantum_efficiency
    return stray_e + img.clock_induced_charge_e


def make_camera(config: SystemConfig, occupancy: np.ndarray, seed: int = 0) -> tuple[SimCamera, SimClock]:
    clock = SimClock()
    return SimCamera(config, atoms=lambda *_: occupancy, clock=clock, rng=np.random.default_rng(seed)), clock


def grab(camera: SimCamera) -> np.ndarray:
    out = np.empty(camera.frame_shape, dtype=np.uint16)
    camera.trigger()
    camera.read(out, timeout_s=1.0)
    return out


@pytest.mark.parametrize(
    ("roi_h", "roi_w", "table_ms"), [(16, 1024, 0.677), (256, 512, 5.923), (512, 1024, 20.549)]
)
def test_readout_model_matches_paper_table1(roi_h: int, roi_w: int, table_ms: float) -> None:
    t = readout_time(CameraConfig(roi_height_px=roi_h, roi_width_px=roi_w))
    assert t.row_readout_s * 1e3 == pytest.approx(table_ms, rel=0.01)
    assert t.frame_transfer_s * 1e3 == pytest.approx(4.499, rel=0.01)
    assert t.exposure_s == 0.020
    assert t.dma_s == pytest.approx(roi_h * roi_w * 2 / 1.431e9)
    assert t.total_s == pytest.approx(t.exposure_s + t.frame_transfer_s + t.row_readout_s + t.dma_s)


def test_readout_binning_vertical_halves_rows_horizontal_changes_only_dma() -> None:
    base = readout_time(CameraConfig(roi_height_px=512, roi_width_px=1024))
    offset_s = (468 + 604 + 16) / 30e6
    v2 = readout_time(CameraConfig(roi_height_px=512, roi_width_px=1024, binning=(1, 2)))
    assert v2.row_readout_s - offset_s == pytest.approx((base.row_readout_s - offset_s) / 2)
    h2 = readout_time(CameraConfig(roi_height_px=512, roi_width_px=1024, binning=(2, 1)))
    assert h2.row_readout_s == pytest.approx(base.row_readout_s)
    assert h2.dma_s == pytest.approx(base.dma_s / 2)


def test_implements_camera_protocol_and_read_advances_clock() -> None:
    config = chain_config()
    camera, clock = make_camera(config, np.zeros((1, 64), dtype=bool))
    assert isinstance(camera, Camera)
    out = np.empty(camera.frame_shape, dtype=np.uint16)
    for index in range(2):
        camera.trigger()
        t0 = clock.now_s()
        info = camera.read(out, timeout_s=1.0)
        assert info.frame_index == index
        assert info.t_exposure_start_s == pytest.approx(t0, abs=1e-3)
        assert info.exposure_s == 0.020
        assert info.readout_s == pytest.approx(camera.readout.readout_s)
        assert clock.now_s() >= info.t_exposure_start_s + camera.readout.total_s
        assert clock.now_s() - t0 < camera.readout.total_s + 0.05


def test_camera_renders_each_atom_for_the_part_of_the_exposure_it_was_there() -> None:
    asked: list[tuple[float, float]] = []
    presence = np.zeros((1, 64))
    presence[0, 0::4], presence[0, 1::4], presence[0, 2::4] = 1.0, 0.5, 0.25  # column 3 of 4: empty

    def atoms(t0_s: float, exposure_s: float) -> np.ndarray:
        asked.append((t0_s, exposure_s))
        return presence

    config = chain_config()
    clock = SimClock()
    camera = SimCamera(config, atoms=atoms, clock=clock, rng=np.random.default_rng(2))
    t0 = clock.now_s()
    frames = np.stack([grab(camera) for _ in range(100)]).astype(np.float64)
    assert asked[0] == (pytest.approx(t0, abs=1e-3), 0.020)  # the lab is asked about this exposure
    img = config.sim.imaging
    empty = img.bias_counts + background_e(config) * config.camera.em_gain / img.electrons_per_count
    per_trap = (frames - empty).reshape(100, 16, 64, 16).sum(axis=(1, 3)).mean(axis=0)
    for column, fraction in enumerate((1.0, 0.5, 0.25, 0.0)):
        measured = per_trap[column::4].mean()
        assert measured == pytest.approx(fraction * atom_counts(config), abs=0.02 * atom_counts(config))


def test_same_seed_same_frame() -> None:
    occupancy = np.random.default_rng(3).random((1, 64)) < 0.5
    a = grab(make_camera(chain_config(), occupancy, seed=5)[0])
    b = grab(make_camera(chain_config(), occupancy, seed=5)[0])
    np.testing.assert_array_equal(a, b)


def test_empty_frame_matches_emccd_statistics() -> None:
    config = grid_config(16, 32, 256, 512)
    cam, img = config.camera, config.sim.imaging
    frame = grab(make_camera(config, np.zeros((16, 32), dtype=bool))[0]).astype(np.float64)
    lam = background_e(config)
    mean = img.bias_counts + lam * cam.em_gain / img.electrons_per_count
    var = (2 * lam * cam.em_gain**2 + img.read_noise_e**2) / img.electrons_per_count**2
    assert frame.mean() == pytest.approx(mean, abs=0.3)
    assert frame.var() == pytest.approx(var, rel=0.05)
    assert frame.dtype == np.float64 and frame.min() >= 0


def test_atom_signal_mean_and_position() -> None:
    config = grid_config(16, 32, 256, 512)
    cam, img = config.camera, config.sim.imaging
    camera, _ = make_camera(config, np.ones((16, 32), dtype=bool))
    frame = grab(camera).astype(np.float64)
    empty = img.bias_counts + background_e(config) * cam.em_gain / img.electrons_per_count
    stamps = (frame - empty).reshape(16, 16, 32, 16)  # [row, y in cell, col, x in cell]
    per_atom = stamps.sum(axis=(1, 3))
    assert per_atom.mean() == pytest.approx(atom_counts(config), rel=0.03)
    brightest = stamps.mean(axis=(0, 2))
    assert np.unravel_index(np.argmax(brightest), brightest.shape) == (8, 8)  # trap centre (8, 8) in each cell


def test_roi_and_binning() -> None:
    occupancy = np.zeros((1, 64), dtype=bool)
    occupancy[0, 10] = True
    config = chain_config(binning=(2, 2))
    cam, img = config.camera, config.sim.imaging
    camera, _ = make_camera(config, occupancy)
    assert camera.frame_shape == (8, 512)
    frames = np.stack([grab(camera) for _ in range(200)]).astype(np.float64)
    bg_e = 4 * background_e(config)
    empty = img.bias_counts + bg_e * cam.em_gain / img.electrons_per_count
    assert frames[:, :, 300:].mean() == pytest.approx(empty, abs=0.5)
    # on-chip binning: one read noise per binned pixel, and the atom's charge summed before the EM register
    var = (2 * bg_e * cam.em_gain**2 + img.read_noise_e**2) / img.electrons_per_count**2
    assert frames[:, :, 300:].var() == pytest.approx(var, rel=0.05)
    signal = frames - empty
    x_binned = (8 + 10 * 16 + 0.5) / 2 - 0.5  # 83.75
    assert np.argmax(signal.mean(axis=(0, 1))) == round(x_binned)
    total = signal[:, :, 80:88].sum(axis=(1, 2)).mean()
    assert total == pytest.approx(atom_counts(config), rel=0.03)


def test_configure_changes_roi_and_rejects_traps_outside() -> None:
    config = chain_config()
    camera, _ = make_camera(config, np.zeros((1, 64), dtype=bool))
    camera.configure(config.camera.model_copy(update={"roi_height_px": 32, "binning": (1, 4)}))
    assert camera.frame_shape == (8, 1024)
    assert grab(camera).shape == (8, 1024)
    with pytest.raises(ValueError, match="outside"):
        camera.configure(config.camera.model_copy(update={"roi_width_px": 512}))


def test_saturation_clips_at_adc_maximum() -> None:
    bright = {"scattering_rate_hz": 2.5e6, "collection_efficiency": 1.0, "quantum_efficiency": 1.0}
    config = chain_config({**bright, "electrons_per_count": 1}, em_gain=1000)  # 50,000 e- per atom
    camera, _ = make_camera(config, np.ones((1, 64), dtype=bool))
    frame = grab(camera)
    assert frame.dtype == np.uint16
    assert frame.max() == 65535
    assert (frame[8, 8::16] == 65535).all()  # the brightest pixels saturate, never wrap around


@pytest.mark.bench
def test_render_time_full_frame() -> None:
    """A speed figure, so a bench smoke run (one process, after the parallel suite), not a unit test."""
    config = grid_config(32, 64, 512, 1024)
    occupancy = np.random.default_rng(1).random((32, 64)) < 0.6
    camera, _ = make_camera(config, occupancy)
    out = np.empty(camera.frame_shape, dtype=np.uint16)
    grab(camera)  # compile
    t0 = time.perf_counter()
    camera.trigger()
    camera.read(out, timeout_s=1.0)
    elapsed_s = time.perf_counter() - t0
    print(f"32x64 full-frame render: {elapsed_s * 1e3:.1f} ms")
    assert elapsed_s < 0.2  # ~25-30 ms on one core; generous for a loaded CI machine


def test_read_without_trigger_raises() -> None:
    camera, _ = make_camera(chain_config(), np.zeros((1, 64), dtype=bool))
    out = np.empty(camera.frame_shape, dtype=np.uint16)
    with pytest.raises(DeviceError, match="trigger"):
        camera.read(out, timeout_s=1.0)
    grab(camera)
    with pytest.raises(DeviceError, match="trigger"):  # a frame is read once
        camera.read(out, timeout_s=1.0)


def test_timeout_raises_and_costs_the_timeout() -> None:
    camera, clock = make_camera(chain_config(), np.zeros((1, 64), dtype=bool))
    out = np.empty(camera.frame_shape, dtype=np.uint16)
    camera.trigger()
    t0 = clock.now_s()
    with pytest.raises(DeviceError, match="no frame within 5.0 ms"):
        camera.read(out, timeout_s=0.005)
    assert clock.now_s() - t0 >= 0.005
    with pytest.raises(DeviceError, match="trigger"):
        camera.read(out, timeout_s=1.0)


@pytest.mark.parametrize(("kind", "message"), [("timeout", "no frame within"), ("corrupt", "corrupt")])
def test_fault_knob_fails_next_read_once(kind: str, message: str) -> None:
    camera, _ = make_camera(chain_config(), np.zeros((1, 64), dtype=bool))
    out = np.empty(camera.frame_shape, dtype=np.uint16)
    camera.fail_next_read = kind  # type: ignore[assignment]  # each failure kind, as the test parametrizes
    camera.trigger()
    with pytest.raises(DeviceError, match=message):
        camera.read(out, timeout_s=1.0)
    assert camera.fail_next_read is None
    assert grab(camera).min() > 0


def test_bad_arguments() -> None:
    camera, _ = make_camera(chain_config(), np.zeros((1, 64), dtype=bool))
    with pytest.raises(ValueError, match="fail_next_read"):
        camera.fail_next_read = "explode"  # type: ignore[assignment]  # a bad value on purpose
    camera.trigger()
    with pytest.raises(ValueError, match="uint16"):
        camera.read(np.empty((16, 1024), dtype=np.int32), timeout_s=1.0)
    bad, _ = make_camera(chain_config(), np.zeros((2, 64), dtype=bool))
    with pytest.raises(ValueError, match="atoms"):
        bad.trigger()
