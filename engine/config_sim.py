"""The simulated lab's settings (``sim`` in the system configuration): atoms, loss, time, faults and imaging.

The engine never reads these; only ``drivers/sim/`` does. ``engine.config`` composes ``SimConfig`` into
``SystemConfig`` and re-exports every class here, so ``from engine.config import SimConfig`` keeps working.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, field_validator, model_validator

from engine.config_base import Fraction, _Model
from engine.timing import REPLAY_HOST_S, STAGES

__all__ = ["FaultConfig", "MoveLossConfig", "SimConfig", "SimImagingConfig"]


class FaultConfig(_Model):
    """Faults injected into the simulated lab, for testing how the system fails (python-microscope style).

    Each stays in force until it is set back, so a test (or a person at the dashboard) can break a device,
    watch the engine end shots in a defined state, clear the fault and see the next shot work.
    """

    camera: Literal["none", "timeout", "corrupt"] = Field(
        default="none", description="every frame read times out, or arrives torn (the grabber reports it)"
    )
    awg_upload: Literal["none", "fail"] = Field(default="none", description="every segment upload fails")
    upload_delay_s: Annotated[float, Field(ge=0, le=1)] = Field(
        default=0.0,
        description="extra time added to every segment upload: plans streamed through more than two segments "
        "underrun (the card holds in the failsafe until the data arrives); a plan that fits the short path is "
        "uploaded before it starts, so there the delay shows as IV.upload time; over the streamer's 1 s upload "
        "timeout it is a device fault",
    )
    solver: Literal["none", "exception"] = Field(
        default="none", description="the planner raises an unexpected exception (a bug) in every solve"
    )
    disk_full: bool = Field(default=False, description="writing shot records fails as on a full disk")


class SimImagingConfig(_Model):
    """What the simulated lab's camera sees: the atoms' light, the sensor's noise, and what imaging costs atoms.

    The engine never reads these (its detection is configured or calibrated from frames); they are the
    simulated world's hidden truth. Defaults and their sources: ``docs/simulation.md`` (Imaging).
    """

    scattering_rate_hz: Annotated[float, Field(gt=0, le=1e8)] = Field(
        default=5.0e5, description="photons an atom scatters per second under the imaging light"
    )
    collection_efficiency: Annotated[float, Field(gt=0, le=1)] = Field(
        default=0.04, description="fraction of scattered photons that reach the sensor (objective NA x optics)"
    )
    background_photons_per_px_per_s: Annotated[float, Field(ge=0, le=1e9)] = Field(
        default=25.0, description="stray light reaching each sensor pixel per second of exposure"
    )
    clock_induced_charge_e: Annotated[float, Field(ge=0, le=10)] = Field(
        default=0.005, description="mean spurious electrons per sensor pixel per readout (EMCCD clock-induced charge)"
    )
    quantum_efficiency: Annotated[float, Field(gt=0, le=1)] = 0.9
    read_noise_e: Annotated[float, Field(ge=0, le=1e4)] = Field(
        default=60.0, description="rms read noise at 30 MHz (electrons); 0 for a noise-free readout, else >= 1e-3"
    )
    bias_counts: Annotated[float, Field(ge=0, le=65535)] = 500.0
    electrons_per_count: Annotated[float, Field(ge=1e-3, le=1e6)] = Field(
        default=20.0, description="electrons per ADC count after the EM register's output (>= 1e-3)"
    )
    loss_rate_hz: Annotated[float, Field(ge=0, le=1e4)] = Field(
        default=0.5,
        description="probability per second of exposure that an imaged atom is heated out (0.5: 1 % per 20 ms)",
    )
    brightness_spread: Annotated[float, Field(ge=0, le=1)] = Field(
        default=0.05, description="relative rms trap-to-trap variation of an atom's brightness (trap depth), seeded"
    )
    beam_edge_brightness: Annotated[float, Field(gt=0, le=1)] = Field(
        default=0.9, description="brightness at the array's corners relative to its centre (Gaussian imaging beam)"
    )

    @field_validator("read_noise_e")
    @classmethod
    def _noise_free_or_physical(cls, value: float) -> float:
        # the camera model divides by the read noise; below 1e-3 e it is no physical amplifier and overflows
        if 0.0 < value < 1e-3:
            raise ValueError(
                f"sim.imaging.read_noise_e {value:g} e is below 1e-3 e: use 0 for a noise-free readout, or a real "
                "amplifier's noise (the iXon 888: ~60 e at 30 MHz before EM gain)"
            )
        return value


class MoveLossConfig(_Model):
    """How the speed of a move costs atoms in the simulated lab (``drivers/sim/move_loss.py``).

    With ``site_spacing_um`` set, every transfer and step survives with ``sim.survival_*`` (everything that does
    not depend on speed) times the survival the trap physics gives for ``waveforms.slot_duration_s`` and
    ``waveforms.shape``: spilling over the barrier the move's peak acceleration leaves, the oscillation the
    move leaves behind, and the non-adiabatic depth ramps of extract/implant. Defaults: rubidium-87 in a
    1 mK, 1 um-waist tweezer at 15 uK (docs/simulation.md gives the sources). Left unset (the default), the
    model is off and ``sim.survival_*`` apply at any speed, as the examples' 10 us slots need: with these
    defaults and 4 um between sites, a one-site min-jerk move needs about 20 us.
    """

    site_spacing_um: Annotated[float, Field(gt=0, le=1000)] | None = Field(
        default=None, description="distance between neighbouring sites at the atoms; null turns the speed model off"
    )
    tweezer_depth_mk: Annotated[float, Field(gt=0, le=100)] = 1.0
    static_depth_mk: Annotated[float, Field(gt=0, le=100)] = Field(
        default=1.0, description="depth of the static (SLM) traps an atom is implanted into"
    )
    waist_um: Annotated[float, Field(gt=0, le=100)] = 1.0
    temperature_uk: Annotated[float, Field(gt=0, le=10000)] = 15.0
    atom_mass_amu: Annotated[float, Field(gt=0, le=1000)] = Field(default=86.909, description="rubidium-87")
    pass_by_survival: Annotated[float, Field(ge=0, le=1)] = Field(
        default=1.0,
        description="interstitial routing (array.routing): survival of an atom in a static trap that a moving loaded "
        "tweezer passes half a site away, per pass (1: no cost); drawn by the simulated world only",
    )


class SimConfig(_Model):
    """The simulated lab: atoms, loss and time."""

    seed: Annotated[int, Field(ge=0, le=2**63 - 1)] | None = 1
    loading_probability: Fraction = 0.6
    survival_transfer: Fraction = 0.985
    survival_step: Fraction = 0.985
    vacuum_lifetime_s: Annotated[float, Field(gt=0, le=1e9)] = 60.0
    lossless: bool = False
    time: Literal["simulated", "realtime", "replay"] = Field(
        default="simulated",
        description="simulated: device waits skipped, host computation at wall-clock speed; realtime: device waits "
        "really waited; replay: no wall clock at all, each host stage charged replay_host_s (a seed replays exactly)",
    )
    replay_host_s: dict[str, Annotated[float, Field(ge=0, le=1)]] = Field(
        default_factory=lambda: dict(REPLAY_HOST_S),
        description="replay time only: seconds charged per host stage (engine.timing.STAGES names); unlisted stages "
        "cost nothing but their device waits",
    )
    moves: MoveLossConfig = MoveLossConfig()
    faults: FaultConfig = FaultConfig()
    imaging: SimImagingConfig = SimImagingConfig()

    @model_validator(mode="after")
    def _known_replay_stages(self) -> SimConfig:
        unknown = sorted(set(self.replay_host_s) - set(STAGES))
        if unknown:
            raise ValueError(f"sim.replay_host_s names unknown stages {unknown}; stages are {list(STAGES)}")
        return self
