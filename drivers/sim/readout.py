"""The simulated EMCCD's readout model: how long a frame takes to read, which readout settings the camera has,
and the noise each setting adds (clock-induced charge, read noise). ``drivers/sim/camera.py`` renders frames
with it; ``llrs devices`` and ``scripts/readout_tradeoff.py`` quote its times.

Readout timing (paper Sec. III.A, Table 1 I.2-I.4): frame transfer of ``1039`` rows, then per read-out row one
vertical shift plus ``width + 48`` horizontal shifts (image columns, 32 dark references, 16 overscan), a
constant ``468 + 604 + 16`` shifts through the dump/gain chain, and the DMA of the binned frame at
``transfer_bytes_per_s``. The horizontal shift count uses the *unbinned* ROI width: the paper measures that
horizontal binning does not change the readout time (Fig. 3d), while vertical binning halves it per doubling.

The camera's readout options (iXon Ultra 888, the paper's camera; Andor's hardware guide, "Variable vertical
shift speed" and "Variable horizontal readout rate") and what each costs here:
- vertical shift speed (``VERTICAL_SHIFT_OPTIONS_S``): faster rows shorten the frame transfer and every
  row's readout; a faster clock moves a bright pixel's charge completely only at a higher vertical clock
  voltage (each speed has a lowest ``vertical_clock_voltage``, enforced: charge left behind, i.e. smear,
  is not modelled), and a higher voltage raises the clock-induced charge by ``CIC_PER_VOLTAGE_STEP`` per
  step; at a fixed voltage a faster clock lowers it a little (``sqrt`` of the shift time, a model choice);
- horizontal readout rate (``HORIZONTAL_RATE_OPTIONS_HZ``): faster pixels shorten every row; read noise
  grows as the square root of the rate (the amplifier's bandwidth; white-noise model);
- binning: vertical binning reads fewer rows; both directions put a spot's light in fewer binned pixels,
  each with one read noise but the stray light and CIC of all its sensor pixels;
- region of interest: fewer rows read, fewer columns shifted per row.
``sim.imaging.clock_induced_charge_e`` and ``read_noise_e`` are the sensor's values at the slowest, normal
voltage shift (4.33 us) and at 30 MHz (``REFERENCE_VERTICAL_SHIFT_S``, ``REFERENCE_HORIZONTAL_RATE_HZ``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from engine.config import CameraConfig, SimImagingConfig
from engine.psf import frame_shape

__all__ = [
    "CIC_PER_VOLTAGE_STEP",
    "HORIZONTAL_RATE_OPTIONS_HZ",
    "READOUT_OFFSET_SHIFTS",
    "ROW_EXTRA_SHIFTS",
    "VERTICAL_SHIFT_OPTIONS_S",
    "ReadoutTime",
    "check_readout_options",
    "clock_induced_charge",
    "read_noise",
    "readout_time",
]

FRAME_TRANSFER_ROWS = 1037 + 2  # storage section + transition rows (CCD201-20)
ROW_EXTRA_SHIFTS = 32 + 16  # dark reference + overscan pixels shifted with every row
READOUT_OFFSET_SHIFTS = 468 + 604 + 16  # distribution chain + multiplication chain + overscan, once per frame
BYTES_PER_PIXEL = 2

#: iXon Ultra 888 vertical shift speeds (seconds per row) -> the lowest vertical clock voltage step that moves
#: a bright pixel's charge completely at that speed (an estimate: Andor advises raising the voltage for the
#: fastest speeds; a lab checks for vertical smear and sets its own)
VERTICAL_SHIFT_OPTIONS_S: dict[float, int] = {0.6e-6: 4, 1.13e-6: 2, 2.2e-6: 0, 4.33e-6: 0}
#: iXon Ultra 888 horizontal readout rates of the EM amplifier (pixels per second)
HORIZONTAL_RATE_OPTIONS_HZ: tuple[float, ...] = (30e6, 20e6, 10e6, 1e6)
#: Settings at which ``sim.imaging.clock_induced_charge_e`` and ``read_noise_e`` hold
REFERENCE_VERTICAL_SHIFT_S = 4.33e-6
REFERENCE_HORIZONTAL_RATE_HZ = 30e6
#: Clock-induced charge grows by this factor per vertical clock voltage step (order of magnitude: CIC rises
#: steeply with the clock swing; Daigle et al. and Andor's guides)
CIC_PER_VOLTAGE_STEP = 2.0


@dataclass(frozen=True)
class ReadoutTime:
    """The paper's acquisition-time model split as in Table 1 (seconds)."""

    exposure_s: float
    frame_transfer_s: float  # I.2
    row_readout_s: float  # I.3
    dma_s: float  # I.4 (model: binned frame bytes / transfer rate)

    @property
    def readout_s(self) -> float:
        """Everything after the exposure until the frame is in host memory."""
        return self.frame_transfer_s + self.row_readout_s + self.dma_s

    @property
    def total_s(self) -> float:
        return self.exposure_s + self.readout_s


def readout_time(camera: CameraConfig) -> ReadoutTime:
    """Acquisition time of one frame under ``camera`` (see the module docstring for the model)."""
    h, w = frame_shape(camera)
    shift_s = 1.0 / camera.horizontal_rate_hz
    return ReadoutTime(
        exposure_s=camera.exposure_s,
        frame_transfer_s=FRAME_TRANSFER_ROWS * camera.vertical_shift_s,
        row_readout_s=h * (camera.vertical_shift_s + (camera.roi_width_px + ROW_EXTRA_SHIFTS) * shift_s)
        + READOUT_OFFSET_SHIFTS * shift_s,
        dma_s=h * w * BYTES_PER_PIXEL / camera.transfer_bytes_per_s,
    )


def _option(value: float, options: tuple[float, ...] | list[float]) -> float | None:
    """The camera option ``value`` stands for (floats from YAML: 1 part in 1e6), or None."""
    return next((o for o in options if math.isclose(value, o, rel_tol=1e-6)), None)


def check_readout_options(camera: CameraConfig) -> None:
    """Raise ``ValueError`` unless ``camera`` asks for readout settings the iXon Ultra 888 has, with a vertical
    clock voltage high enough for its shift speed."""
    speed = _option(camera.vertical_shift_s, list(VERTICAL_SHIFT_OPTIONS_S))
    if speed is None:
        speeds = ", ".join(f"{s * 1e6:g}e-6" for s in VERTICAL_SHIFT_OPTIONS_S)
        raise ValueError(
            f"camera.vertical_shift_s = {camera.vertical_shift_s:g} s is not a vertical shift speed of the "
            f"iXon Ultra 888; use one of {speeds}"
        )
    if _option(camera.horizontal_rate_hz, HORIZONTAL_RATE_OPTIONS_HZ) is None:
        rates = ", ".join(f"{r:.0e}" for r in HORIZONTAL_RATE_OPTIONS_HZ)
        raise ValueError(
            f"camera.horizontal_rate_hz = {camera.horizontal_rate_hz:g} is not a readout rate of the iXon Ultra "
            f"888's EM amplifier; use one of {rates}"
        )
    needed = VERTICAL_SHIFT_OPTIONS_S[speed]
    if camera.vertical_clock_voltage < needed:
        raise ValueError(
            f"camera.vertical_shift_s = {speed * 1e6:g} us leaves charge behind at vertical clock voltage "
            f"+{camera.vertical_clock_voltage}; set camera.vertical_clock_voltage to at least {needed} "
            "(more clock-induced charge) or shift slower"
        )


def clock_induced_charge(camera: CameraConfig, imaging: SimImagingConfig) -> float:
    """Mean clock-induced electrons per sensor pixel per readout at the camera's vertical clocking: the
    sensor's value at 4.33 us and normal voltage, times ``CIC_PER_VOLTAGE_STEP`` per voltage step, times
    ``sqrt(shift time / 4.33 us)`` (a shorter clock pulse makes a little less)."""
    speed = math.sqrt(camera.vertical_shift_s / REFERENCE_VERTICAL_SHIFT_S)
    return imaging.clock_induced_charge_e * speed * CIC_PER_VOLTAGE_STEP**camera.vertical_clock_voltage


def read_noise(camera: CameraConfig, imaging: SimImagingConfig) -> float:
    """Read noise (electrons rms) at the camera's horizontal readout rate: the sensor's 30 MHz value scaled
    by ``sqrt(rate / 30 MHz)`` (the output amplifier's white noise over its bandwidth)."""
    return imaging.read_noise_e * math.sqrt(camera.horizontal_rate_hz / REFERENCE_HORIZONTAL_RATE_HZ)
