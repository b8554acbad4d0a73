"""The whole system's configuration: one validated pydantic model, loadable from YAML or JSON.

Everything that crosses a boundary (a YAML file, the REST API, a shot record) goes through these models,
so a bad value fails in one place with a message naming the field and what is allowed.

Conventions used everywhere in the engine:
- the trap array has ``ny`` rows and ``nx`` columns; a trap's flat index is ``row * nx + col`` (row-major);
- a 1D chain is one row (``ny = 1``) along the x AOD;
- frequencies in Hz, times in seconds, unless a name says otherwise (``_us``, ``_px``).
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal

import numpy as np
import yaml
from pydantic import Field, ValidationError, model_validator

from engine.aod_limits import (
    ChannelLimits,
    band_problem,
    comb_power_w,
    dbm_to_w,
    resolution_problem,
    sample_amplitudes,
    w_to_dbm,
)
from engine.card_rules import slot_length_problem
from engine.config_base import Fraction, _Model
from engine.config_devices import DevicesConfig
from engine.config_sim import FaultConfig, MoveLossConfig, SimConfig, SimImagingConfig
from engine.errors import ConfigError
from engine.targets import build_target
from engine.tones import check_below_nyquist

__all__ = [
    "ArrayConfig",
    "AWGConfig",
    "CameraConfig",
    "ConfigError",
    "DevicesConfig",
    "FaultConfig",
    "ImagingConfig",
    "LoopConfig",
    "MoveLossConfig",
    "RFLimitsConfig",
    "SimConfig",
    "SimImagingConfig",
    "SolverConfig",
    "SystemConfig",
    "TargetConfig",
    "ToneAxisConfig",
    "WaveformConfig",
    "deep_merge",
    "load_config",
    "save_config",
]


#: A pixel position or step on the camera (the largest sensors are a few thousand pixels across).
PixelCoordinate = Annotated[float, Field(ge=-1e5, le=1e5)]


class RFLimitsConfig(_Model):
    """RF limits of one AWG channel (the amplifier and AOD it drives), checked when a configuration is applied
    and on every segment before upload (``engine.aod_limits``). Power is the mean power into ``load_ohm`` with
    a full-scale sample at ``devices.spectrum.amplitude_mv`` (the simulated AWG models the same output), from the
    samples themselves: with ``waveforms.compensate_dac_sinc`` those carry the compensated tone amplitudes, and the
    DAC's hold only lowers what reaches the amplifier, so every limit is checked on the larger figure."""

    max_peak_amplitude: Fraction = Field(default=1.0, description="largest |sample| as a fraction of full scale")
    max_summed_amplitude: Annotated[float, Field(gt=0, le=1)] = Field(
        default=1.0, description="largest sum of the static tones' sample amplitudes, compensated for the DAC's "
        "sinc roll-off when waveforms.compensate_dac_sinc (bounds the peak whatever the phases; at most 1, where "
        "the AWG would clip)"
    )
    max_rf_power_dbm: Annotated[float, Field(ge=-100, le=60)] | None = Field(
        default=None, description="largest mean RF power into the amplifier in dBm (or give max_rf_power_mw)"
    )
    max_rf_power_mw: Annotated[float, Field(gt=0, le=1e6)] | None = Field(
        default=None, description="largest mean RF power into the amplifier in mW (or give max_rf_power_dbm)"
    )
    max_tones: Annotated[int, Field(ge=1, le=4096)] | None = Field(
        default=None, description="most tones on the channel"
    )
    load_ohm: Annotated[float, Field(gt=0, le=1e6)] = Field(default=50.0, description="the amplifier's input impedance")

    @model_validator(mode="after")
    def _one_power_unit(self) -> RFLimitsConfig:
        if self.max_rf_power_dbm is not None and self.max_rf_power_mw is not None:
            raise ValueError("give the RF power limit once: max_rf_power_dbm or max_rf_power_mw, not both")
        return self

    @property
    def max_power_w(self) -> float | None:
        if self.max_rf_power_dbm is not None:
            return dbm_to_w(self.max_rf_power_dbm)
        return None if self.max_rf_power_mw is None else 1e-3 * self.max_rf_power_mw


class ToneAxisConfig(_Model):
    """Static RF tones of one AOD axis: tone k places the traps of row/column k.

    Either an evenly spaced comb (``start_hz + k * spacing_hz``) or a CSV file with columns
    ``alpha,nu,phi`` (amplitude as a fraction of full scale, frequency in Hz, phase in rad), one row per trap.
    Every frequency must be a whole number of cycles per waveform slot (a multiple of 1/slot_duration_s),
    so that static tones are phase-continuous from one slot to the next.
    """

    start_hz: Annotated[float, Field(gt=0, le=10e9)] = 80e6
    spacing_hz: Annotated[float, Field(gt=0, le=1e9)] = 1e6
    amplitude: Annotated[float, Field(gt=0, le=1)] = Field(
        default=0.014, description="each tone's delivered amplitude (fraction of full scale); 64 tones from 80 MHz "
        "at 1 MHz, compensated for the DAC's sinc roll-off at 624 MS/s, sum to 0.95"
    )
    phases: Literal["continuous", "schroeder", "zero"] = Field(
        default="continuous",
        description="continuous: site phases chosen so that every one-site move is a pure min-jerk (or tanh/erf) "
        "frequency ramp that ends exactly on the next site's phase (the comb is then a time-shifted zero-phase "
        "comb: peak = sum of amplitudes, never clipping); schroeder / zero: low / high crest factor, and moves "
        "carry an end-pinned phase correction (up to ~0.94/slot_duration_s Hz off the shape mid-move)",
    )
    csv: str | None = Field(
        default=None, max_length=4096, description="path to an alpha,nu,phi CSV; overrides the comb"
    )
    aod_centre_hz: Annotated[float, Field(gt=0, le=10e9)] | None = Field(
        default=None, description="the AOD's centre frequency; with aod_bandwidth_hz the comb must lie in its band "
        "and the DAC's images (sample rate - tone) outside it; null: the band is not checked"
    )
    aod_bandwidth_hz: Annotated[float, Field(gt=0, le=10e9)] | None = Field(
        default=None, description="the AOD's RF bandwidth (full width) around aod_centre_hz"
    )
    rf: RFLimitsConfig = RFLimitsConfig()

    @model_validator(mode="after")
    def _band_complete(self) -> ToneAxisConfig:
        if (self.aod_centre_hz is None) != (self.aod_bandwidth_hz is None):
            raise ValueError("give the AOD's band as both aod_centre_hz and aod_bandwidth_hz, or neither")
        return self


class ArrayConfig(_Model):
    """The trap array and how the AODs address it."""

    nx: Annotated[int, Field(ge=1, le=1024)] = 64
    ny: Annotated[int, Field(ge=1, le=1024)] = 1
    trap_source: Literal["aod", "slm"] = Field(
        default="aod",
        description=(
            "'aod': the static traps are the AOD's own tones (a 1D chain made by one AOD; moves are "
            "conveyor-style block shifts). 'slm': static traps come from elsewhere (an SLM) and the crossed "
            "AODs make mobile tweezers that extract, shift and implant atoms."
        ),
    )
    x_tones: ToneAxisConfig = ToneAxisConfig()
    y_tones: ToneAxisConfig = ToneAxisConfig(start_hz=80e6)
    routing: Literal["lattice", "interstitial"] = Field(
        default="lattice",
        description=(
            "'lattice': tweezers move from site to site, so a loaded one cannot pass an occupied trap. "
            "'interstitial' (slm only): each AOD also plays the frequency halfway between neighbouring tones, "
            "tweezers move half a site per slot, and a loaded one travels along the channels between rows and "
            "columns of traps, passing occupied traps (engine/routing.py)."
        ),
    )

    @model_validator(mode="after")
    def _chain_needs_one_row(self) -> ArrayConfig:
        if self.trap_source == "aod" and self.ny != 1:
            raise ValueError(
                f"trap_source 'aod' makes a 1D chain and needs ny = 1 (got ny = {self.ny}); "
                "use trap_source 'slm' for a 2D grid"
            )
        if self.routing == "interstitial" and self.trap_source != "slm":
            raise ValueError(
                "routing 'interstitial' carries atoms between static traps with crossed AODs; a 1D AOD chain "
                "(trap_source 'aod') has no channels between its traps: use routing 'lattice' or trap_source 'slm'"
            )
        if self.routing == "interstitial" and min(self.nx, self.ny) < 2:
            raise ValueError(
                f"routing 'interstitial' needs channels between rows and between columns: nx and ny must be at "
                f"least 2 (got {self.nx} x {self.ny}); use routing 'lattice'"
            )
        return self

    @property
    def n_traps(self) -> int:
        return self.nx * self.ny


class CameraConfig(_Model):
    """EMCCD settings, trap-to-pixel geometry and the readout-time model (paper, Sec. III.A).

    Only what a real camera is configured with; the sensor's and the atoms' hidden properties (photon rates,
    quantum efficiency, noise, gain calibration) belong to the simulated lab (``sim.imaging``).
    """

    roi_width_px: Annotated[int, Field(ge=1, le=4096)] = 1024
    roi_height_px: Annotated[int, Field(ge=1, le=4096)] = 16
    binning: tuple[Annotated[int, Field(ge=1, le=16)], Annotated[int, Field(ge=1, le=16)]] = (1, 1)
    origin_px: tuple[PixelCoordinate, PixelCoordinate] = Field(
        default=(8.0, 8.0), description="(x, y) pixel of trap (row 0, col 0)"
    )
    col_step_px: tuple[PixelCoordinate, PixelCoordinate] = Field(
        default=(16.0, 0.0), description="(x, y) pixel step from column c to c+1"
    )
    row_step_px: tuple[PixelCoordinate, PixelCoordinate] = Field(
        default=(0.0, 16.0), description="(x, y) pixel step from row r to r+1"
    )
    psf_sigma_px: Annotated[float, Field(gt=0, le=100)] = 1.2
    exposure_s: Annotated[float, Field(gt=0, le=60)] = 0.020
    em_gain: Annotated[float, Field(ge=1, le=1000)] = 300.0
    vertical_shift_s: Annotated[float, Field(gt=0, le=1e-3)] = Field(
        default=4.33e-6, description="time per row shift (iXon Ultra 888: 0.6, 1.13, 2.2 or 4.33 us)"
    )
    vertical_clock_voltage: Annotated[int, Field(ge=0, le=4)] = Field(
        default=0,
        description="vertical clock voltage amplitude above normal (Andor's 'Normal', '+1'..'+4'): fast vertical "
        "shifts need it to move all the charge, and every step raises the clock-induced charge",
    )
    horizontal_rate_hz: Annotated[float, Field(ge=1e3, le=1e10)] = Field(
        default=30e6, description="pixel readout rate (iXon Ultra 888 EM amplifier: 30, 20, 10 or 1 MHz)"
    )
    transfer_bytes_per_s: Annotated[float, Field(ge=1e3, le=1e12)] = 1.431e9
    timeout_s: Annotated[float, Field(gt=0, le=600)] = 0.6

    def trap_pixel_xy(self, row: int, col: int) -> tuple[float, float]:
        x = self.origin_px[0] + col * self.col_step_px[0] + row * self.row_step_px[0]
        y = self.origin_px[1] + col * self.col_step_px[1] + row * self.row_step_px[1]
        return x, y


class ImagingConfig(_Model):
    """Module II: per-trap PSF-weighted sums and the occupancy threshold."""

    psf_box_px: Annotated[int, Field(ge=1, le=31)] = 7
    threshold: float | None = Field(
        default=None,
        ge=-1e12,
        le=1e12,
        description=(
            "counts above which a trap is occupied; null = calibrate from frames taken when the configuration "
            "is applied (a two-population fit, engine.imaging_calibration)"
        ),
    )

    @model_validator(mode="after")
    def _odd_box(self) -> ImagingConfig:
        if self.psf_box_px % 2 == 0:
            raise ValueError(f"psf_box_px must be odd so the box is centred on the trap (got {self.psf_box_px})")
        return self


class TargetConfig(_Model):
    """Which traps must be filled.

    ``centre``: ``count`` traps in the middle of a chain, or a full-width band of ``count / nx`` rows in the
    middle of a grid (the paper's centre-compact target). ``rectangle``: rows ``row0..row0+rows-1`` x columns
    ``col0..col0+cols-1``. ``mask``: an explicit list of strings of '0'/'1', one per row.
    """

    kind: Literal["centre", "rectangle", "mask"] = "centre"
    count: Annotated[int, Field(ge=1, le=1024 * 1024)] | None = 32
    row0: Annotated[int, Field(ge=0, le=1023)] = 0
    col0: Annotated[int, Field(ge=0, le=1023)] = 0
    rows: Annotated[int, Field(ge=1, le=1024)] | None = None
    cols: Annotated[int, Field(ge=1, le=1024)] | None = None
    mask: list[Annotated[str, Field(max_length=1024)]] | None = Field(default=None, max_length=1024)


class SolverStrategyConfig(_Model):
    """A per-cycle strategy: ``solver.algorithm`` (the bulk planner) while the target has many empty traps,
    ``repair`` once it has at most ``repair_at_defects``."""

    repair: str = Field(default="repair", min_length=1, max_length=64, description="the planner for few defects")
    repair_at_defects: Annotated[int, Field(ge=0, le=1_000_000)] = Field(
        default=64, description="a cycle whose target has at most this many empty traps goes to the repair planner"
    )


class SolverConfig(_Model):
    """Module III: which planner turns occupancy + target into waveform slots."""

    algorithm: str = Field(default="exact-1d", min_length=1, max_length=64)
    objective: Literal["slots", "transfers", "survival"] = Field(
        default="slots",
        description="what the planner minimises where it can choose: waveform slots (time), pick-ups per "
        "atom (every transfer risks losing the atom), or atoms expected lost (survival: transfers, steps and "
        "vacuum time weighed by sim.survival_transfer, sim.survival_step and sim.vacuum_lifetime_s); see "
        "docs/benchmarks.md for the trade-off",
    )
    strategy: SolverStrategyConfig | None = Field(
        default=None, description="null: solver.algorithm plans every cycle; set: bulk planner, then repair"
    )


class WaveformConfig(_Model):
    """Module IV: waveform slots and the transition shape used for every move."""

    sample_rate_hz: Annotated[float, Field(ge=1e3, le=10e9)] = 624e6
    slot_duration_s: Annotated[float, Field(ge=1e-7, le=1e-2)] = 10e-6
    shape: Literal["min-jerk", "tanh", "erf"] = "min-jerk"
    shape_sharpness: Annotated[float, Field(gt=0, le=50)] = Field(
        default=6.0, description="tanh/erf steepness in units of 1/slot_duration_s (v*T); ignored by min-jerk"
    )
    table_max_bytes: Annotated[int, Field(ge=0, le=2**34)] = Field(
        default=512 * 2**20, description="lookup-table budget; moves not in the table are synthesized directly"
    )
    compensate_dac_sinc: bool = Field(
        default=True,
        description="render every tone at its amplitude / sinc(f / sample_rate_hz), so that after the DAC's "
        "zero-order hold each delivers its configured amplitude (0.67 of it at 295 MHz and 624 MS/s without); the "
        "RF limits are checked on the compensated (larger) sample amplitudes. false: traps near Nyquist are shallower",
    )

    @property
    def slot_samples(self) -> int:
        return int(round(self.sample_rate_hz * self.slot_duration_s))


class AWGConfig(_Model):
    """Module V: sequence-memory layout and (for the simulated card) the upload model."""

    n_segments: Annotated[int, Field(ge=8, le=4096)] = 256
    n_steps: Annotated[int, Field(ge=8, le=4096)] = 4096
    waveforms_per_segment: Annotated[int, Field(ge=1, le=1024)] = Field(
        default=32,
        description="waveform slots of each of the two control segments uploaded before a plan starts (their DMA "
        "is the streaming part of the latency), and of the first segments streamed after them",
    )
    segment_growth: Annotated[float, Field(ge=1, le=4)] = Field(
        default=1.0,
        description="each control segment after the second holds this many times the slots of the one before, "
        "up to max_waveforms_per_segment: larger segments spend the fixed per-segment host work (failsafe "
        "upload, step words) over more playback and let one layout hold longer plans, but the host links a "
        "segment only once its whole DMA is done, so a segment that grows faster than the DMA's spare time "
        "(playback minus upload) eats the lead. 1: every segment waveforms_per_segment slots",
    )
    max_waveforms_per_segment: Annotated[int, Field(ge=1, le=65536)] = Field(
        default=128, description="the most waveform slots one control segment grows to (segment_growth)"
    )
    upload_bytes_per_s: Annotated[float, Field(ge=1e3, le=1e12)] = 1.58e9
    upload_jitter_s: Annotated[float, Field(ge=0, le=1e-2)] = 5e-6
    step_write_s: Annotated[float, Field(ge=0, le=1e-2)] = 4e-6
    max_memory_bytes: Annotated[int, Field(ge=1, le=2**40)] = 2**32
    stream_priority: Annotated[int, Field(ge=0, le=98)] = Field(
        default=10,
        description="real-time (SCHED_FIFO) priority the engine streams a plan at, from its first render to its "
        "last link, so that a busy core cannot preempt it into an underrun; 0: normal priority. Needs "
        "CAP_SYS_NICE or RLIMIT_RTPRIO; where the OS refuses, plans stream at normal priority",
    )

    @model_validator(mode="after")
    def _segment_sizes(self) -> AWGConfig:
        if self.max_waveforms_per_segment < self.waveforms_per_segment:
            raise ValueError(
                f"awg.max_waveforms_per_segment = {self.max_waveforms_per_segment} is below awg.waveforms_per_segment "
                f"= {self.waveforms_per_segment}: segments grow from waveforms_per_segment up to the maximum; raise "
                "max_waveforms_per_segment (or leave segment_growth at 1)"
            )
        return self

    def control_segment_slots(self, n_control: int) -> tuple[int, ...]:
        """Waveform slots of each of ``n_control`` control segments: two of ``waveforms_per_segment`` (the
        latency), then growing by ``segment_growth`` up to ``max_waveforms_per_segment``."""
        slots = [self.waveforms_per_segment] * min(2, n_control)
        size = float(self.waveforms_per_segment)
        while len(slots) < n_control:
            size = min(size * self.segment_growth, float(self.max_waveforms_per_segment))
            slots.append(int(size))
        return tuple(slots)


class LoopConfig(_Model):
    """The engine's shot loop."""

    max_cycles: Annotated[int, Field(ge=1, le=100)] = 5
    trigger: Literal["software", "hardware"] = "software"
    keep_frames: bool = Field(
        default=False,
        description="attach every cycle's camera frame to the shot record (run files keep them as llrs serve "
        "--keep-frames says); each is copied while the next exposure runs, off the latency path",
    )
    watchdog_factor: Annotated[float, Field(ge=1, le=1000)] = Field(
        default=4.0,
        description="a shot running longer than this multiple of the longest healthy shot (every cycle's frame "
        "at camera.timeout_s, the longest plan the AWG holds uploaded and played) ends as a fault, atoms held",
    )


class SystemConfig(_Model):
    """Everything the engine needs to run shots."""

    name: str = Field(default="llrs", max_length=200)
    array: ArrayConfig = ArrayConfig()
    camera: CameraConfig = CameraConfig()
    imaging: ImagingConfig = ImagingConfig()
    target: TargetConfig = TargetConfig()
    solver: SolverConfig = SolverConfig()
    waveforms: WaveformConfig = WaveformConfig()
    awg: AWGConfig = AWGConfig()
    loop: LoopConfig = LoopConfig()
    sim: SimConfig = SimConfig()
    devices: DevicesConfig = DevicesConfig()

    @model_validator(mode="after")
    def _consistent(self) -> SystemConfig:
        wf = self.waveforms
        if wf.sample_rate_hz * wf.slot_duration_s > 1e6:
            raise ValueError(
                f"waveforms: a slot of {wf.slot_duration_s:g} s at {wf.sample_rate_hz:g} S/s is "
                f"{wf.sample_rate_hz * wf.slot_duration_s:.3g} samples; at most 1e6 per slot"
            )
        if abs(wf.sample_rate_hz * wf.slot_duration_s - wf.slot_samples) > 1e-6:
            raise ValueError(
                "waveforms: sample_rate_hz * slot_duration_s must be a whole number of samples "
                f"(got {wf.sample_rate_hz * wf.slot_duration_s:g})"
            )
        # every device, simulated or not, refuses what the card would refuse at its first upload
        problem = slot_length_problem(wf.sample_rate_hz, wf.slot_duration_s, self.n_channels)
        if problem is not None:
            raise ValueError(problem)
        grid_hz = 1.0 / wf.slot_duration_s
        for axis in ("x_tones", "y_tones"):
            tones: ToneAxisConfig = getattr(self.array, axis)
            if tones.csv is not None:
                continue  # checked when the CSV is loaded
            if self._n_tones(axis) > 1:  # before the whole-cycles rule, which a finer spacing also breaks
                problem = resolution_problem(wf.slot_duration_s, tones.spacing_hz, where=f"array.{axis}.spacing_hz")
                if problem is not None:
                    raise ValueError(problem)
            for name in ("start_hz", "spacing_hz"):
                cycles = getattr(tones, name) / grid_hz
                if abs(cycles - round(cycles)) > 1e-6:
                    raise ValueError(
                        f"array.{axis}.{name} = {getattr(tones, name):g} Hz must be a multiple of "
                        f"1/slot_duration_s = {grid_hz:g} Hz so static tones stay phase-continuous"
                    )
            half_cycles = tones.spacing_hz / grid_hz / 2
            if self.array.routing == "interstitial" and abs(half_cycles - round(half_cycles)) > 1e-6:
                raise ValueError(
                    f"array.{axis}.spacing_hz = {tones.spacing_hz:g} Hz: routing 'interstitial' plays the tone "
                    f"halfway between neighbours, which must also be a whole number of cycles per slot; use a "
                    f"multiple of 2/slot_duration_s = {2 * grid_hz:g} Hz"
                )
            top = tones.start_hz + tones.spacing_hz * (self._n_tones(axis) - 1)
            check_below_nyquist(tones.start_hz, top, wf.sample_rate_hz, where=f"array.{axis}", error=ValueError,
                                fix="lower start_hz/spacing_hz or raise waveforms.sample_rate_hz")
            for problem in self._comb_problems(axis, tones, top):
                raise ValueError(problem)
        cam = self.camera
        for r, c in ((0, 0), (self.array.ny - 1, 0), (0, self.array.nx - 1), (self.array.ny - 1, self.array.nx - 1)):
            x, y = cam.trap_pixel_xy(r, c)
            if not (0 <= x < cam.roi_width_px and 0 <= y < cam.roi_height_px):
                raise ValueError(
                    f"camera: trap (row {r}, col {c}) images at pixel ({x:g}, {y:g}), outside the "
                    f"{cam.roi_width_px}x{cam.roi_height_px} ROI; adjust origin_px/col_step_px/row_step_px or the ROI"
                )
        if self.awg.n_steps < 2 * self.awg.n_segments:
            raise ValueError(
                f"awg: n_steps ({self.awg.n_steps}) must be at least 2 * n_segments ({2 * self.awg.n_segments}): "
                "every control step is paired with a failsafe step"
            )
        build_target(self.target, nx=self.array.nx, ny=self.array.ny)
        return self

    def _n_tones(self, axis: str) -> int:
        return self.array.nx if axis == "x_tones" else self.array.ny

    def _comb_problems(self, axis: str, tones: ToneAxisConfig, top_hz: float) -> list[str]:
        """What the AOD's band, the DAC's images and the channel's RF limits refuse in an evenly spaced comb (see
        ``engine.aod_limits``); physical limits only (the simulated lab's decoder checks its own)."""
        n, rf, where = self._n_tones(axis), tones.rf, f"array.{axis}"
        problems = []
        if tones.aod_centre_hz is not None and tones.aod_bandwidth_hz is not None:
            problem = band_problem(tones.start_hz, top_hz, tones.aod_centre_hz, tones.aod_bandwidth_hz,
                                   self.waveforms.sample_rate_hz, where=where)
            if problem is not None:
                problems.append(problem)
        if rf.max_tones is not None and n > rf.max_tones:
            problems.append(f"{where}: {n} tones, above {where}.rf.max_tones = {rf.max_tones}")
        wf = self.waveforms
        freq = tones.start_hz + tones.spacing_hz * np.arange(n, dtype=np.float64)
        amps = sample_amplitudes(freq, np.full(n, tones.amplitude), wf.sample_rate_hz, wf.compensate_dac_sinc)
        gain = float(n * tones.amplitude / np.sum(amps))  # the hold's mean gain, to scale the advice
        compensated = (
            f" (compensated for the DAC's sinc roll-off, waveforms.compensate_dac_sinc: each tone at amplitude / "
            f"sinc(f / sample_rate_hz), {np.max(amps) / tones.amplitude:.3g}x at {freq[-1] / 1e6:g} MHz)"
            if wf.compensate_dac_sinc else ""
        )
        summed = float(np.sum(amps))
        if summed > rf.max_summed_amplitude * (1 + 1e-9):
            problems.append(
                f"{where}.amplitude = {tones.amplitude:g} x {n} tones = {summed:.4g} of full scale{compensated}, above "
                f"{where}.rf.max_summed_amplitude = {rf.max_summed_amplitude:g} (1: the AWG would clip when every tone "
                f"is on); use at most {rf.max_summed_amplitude * gain / n:.4g}"
            )
        if rf.max_power_w is not None:
            full_scale_v = self.full_scale_v(0 if axis == "x_tones" else 1)
            power_w = comb_power_w(amps, full_scale_v, rf.load_ohm)
            if power_w > rf.max_power_w * (1 + 1e-9):
                problems.append(
                    f"{where}: {n} tones of amplitude {tones.amplitude:g}{compensated} at a full scale of "
                    f"{full_scale_v * 1e3:g} mV deliver {w_to_dbm(power_w):.2f} dBm ({power_w * 1e3:.4g} mW) into "
                    f"{rf.load_ohm:g} ohm, above {where}.rf's limit of {w_to_dbm(rf.max_power_w):.2f} dBm; lower the "
                    "amplitude or devices.spectrum.amplitude_mv"
                )
        return problems

    @property
    def n_channels(self) -> int:
        """AWG channels in use: x, and y for crossed AODs."""
        return 1 if self.array.trap_source == "aod" else 2

    def full_scale_v(self, channel: int) -> float:
        """Peak volts at the load of a full-scale sample on ``channel``: the card's output range."""
        amps = self.devices.spectrum.amplitude_mv
        mv = amps[min(channel, len(amps) - 1)] if isinstance(amps, list) else amps
        return 1e-3 * mv

    def channel_limits(self, full_scale_counts: float = 32767.0) -> list[ChannelLimits]:
        """Each channel's limits for the per-segment check (``engine.aod_limits.SegmentGuard``)."""
        out = []
        for channel, axis in enumerate(("x_tones", "y_tones")[: self.n_channels]):
            rf = getattr(self.array, axis).rf
            out.append(ChannelLimits(channel, f"array.{axis}.rf", full_scale_counts, self.full_scale_v(channel),
                                     rf.load_ohm, rf.max_peak_amplitude, rf.max_power_w))
        return out

    def digest(self) -> str:
        """A short stable hash of the configuration, stored with every shot."""
        blob = json.dumps(self.model_dump(mode="json"), sort_keys=True).encode()
        return hashlib.sha256(blob).hexdigest()[:16]


def deep_merge(base: dict[str, Any], patch: Mapping[str, Any]) -> dict[str, Any]:
    """``base`` with ``patch`` merged in: nested mappings merge key by key, anything else replaces.

    Unlike RFC 7396, ``null`` is a value, not a deletion: ``imaging.threshold: null`` is a real setting.
    """
    merged = dict(base)
    for key, value in patch.items():
        if isinstance(value, Mapping) and isinstance(merged.get(key), dict):
            merged[key] = deep_merge(merged[key], value)
        else:
            merged[key] = value
    return merged


def _format_validation_error(err: ValidationError, source: str) -> str:
    lines = [f"invalid configuration in {source}:"]
    for e in err.errors():
        where = ".".join(str(p) for p in e["loc"]) or "(top level)"
        lines.append(f"  {where}: {e['msg']}")
    return "\n".join(lines)


def config_from_dict(data: dict[str, Any], *, source: str = "<dict>") -> SystemConfig:
    try:
        return SystemConfig.model_validate(data)
    except ValidationError as err:
        raise ConfigError(_format_validation_error(err, source)) from None


def load_config(path: str | Path) -> SystemConfig:
    """Load and validate a YAML (or JSON) configuration file."""
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as err:
        raise ConfigError(f"cannot read configuration file {path}: {err.strerror}") from None
    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as err:
        raise ConfigError(f"{path} is not valid YAML: {err}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"{path} must hold a mapping of sections (array, camera, ...), not {type(data).__name__}")
    return config_from_dict(data, source=str(path))


def save_config(config: SystemConfig, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(config.model_dump(mode="json"), sort_keys=False))
