"""Which implementation drives each device, and each real device's settings (``devices`` in the configuration).

``engine.config`` composes ``DevicesConfig`` into ``SystemConfig`` and re-exports it, so
``from engine.config import DevicesConfig`` keeps working.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from engine.config_base import _Model

__all__ = ["DevicesConfig"]


class DevicesConfig(_Model):
    """Which implementation drives each device, and what each real device needs to be opened.

    ``sim`` everywhere is the simulated lab (no vendor software needed). On a lab PC choose
    ``camera: andor`` (the iXon through Andor's SDK), ``frame_source: activesilicon`` (frames over Camera Link
    through the FireBird grabber) or ``andor`` (frames read straight from the SDK, no grabber), and
    ``awg: spectrum`` (the M4i through the ``spcm`` package). ``llrs devices`` says which of these can be
    opened on this machine. The settings of a device are only used when that device is selected, so their
    defaults never get in the way of the simulated lab.
    """

    class SpectrumSettings(_Model):
        """The Spectrum M4i.66xx AWG in sequence mode (``drivers/spectrum.py``)."""

        device: str = Field(
            default="/dev/spcm0", min_length=1, max_length=256,
            description="card to open: '/dev/spcmN' or 'TCPIP::<ip>::inst0::INSTR'"
        )
        amplitude_mv: Annotated[int, Field(ge=80, le=2500)] | list[Annotated[int, Field(ge=80, le=2500)]] = Field(
            default=140,
            description="output amplitude per channel in mV (one value for all channels, or one per channel)"
        )
        external_reference_hz: Annotated[float, Field(gt=0, le=1e9)] | None = Field(
            default=None, description="frequency of an external reference clock (e.g. 10e6); null = internal PLL"
        )
        trigger: Literal["ext0", "software"] = Field(
            default="ext0",
            description="what ends a step that waits for a trigger: the EXT0 input (the lab sequencer) or software "
            "only",
        )
        trigger_edge: Literal["rising", "falling"] = "rising"
        trigger_level_mv: Annotated[int, Field(ge=-10000, le=10000)] = 1500
        trigger_termination_50ohm: bool = False
        camera_line: Annotated[int, Field(ge=0, le=2)] = Field(
            default=0, description="X line pulsed to trigger the camera"
        )
        resume_line: Annotated[int, Field(ge=0, le=2)] = Field(
            default=1, description="X line pulsed to resume the lab sequencer when a shot ends"
        )
        pulse_width_s: Annotated[float, Field(ge=0, le=0.01)] = Field(
            default=10e-6, description="how long an X-line pulse stays high"
        )
        stop_level: Literal["zero", "hold_last"] = Field(
            default="zero", description="what the outputs do when the card is stopped"
        )
        dma_timeout_s: Annotated[float, Field(gt=0, le=600)] = Field(
            default=5.0, description="a segment upload that takes longer is a fault"
        )

        @model_validator(mode="after")
        def _distinct_lines(self) -> DevicesConfig.SpectrumSettings:
            if self.camera_line == self.resume_line:
                raise ValueError(
                    "devices.spectrum.camera_line and resume_line must be different X lines "
                    f"(both are X{self.camera_line})"
                )
            return self

    class AndorSettings(_Model):
        """The Andor iXon EMCCD through Andor's Python SDK wrapper ``pyAndorSDK2`` (``drivers/andor.py``)."""

        index: Annotated[int, Field(ge=0, le=7)] = Field(default=0, description="which Andor camera (0 = the first)")
        sdk_path: str = Field(
            default="", max_length=4096, description="directory handed to the SDK's Initialize ('' = its default)"
        )
        temperature_c: Annotated[int, Field(ge=-120, le=30)] = -60
        cooler: bool = True
        keep_cooling_on_close: bool = Field(
            default=True, description="leave the cooler running after the SDK shuts down (no thermal shock)"
        )
        wait_for_temperature_s: Annotated[float, Field(ge=0, le=3600)] = Field(
            default=0.0, description="at open, wait up to this long for the temperature to stabilize (0 = do not wait)"
        )
        roi_offset_px: tuple[Annotated[int, Field(ge=0, le=16384)], Annotated[int, Field(ge=0, le=16384)]] = Field(
            default=(0, 0), description="(x, y) sensor pixel of the ROI's first column and row"
        )
        hs_speed_index: Annotated[int, Field(ge=0, le=64)] = Field(
            default=0, description="horizontal shift speed index"
        )
        vs_speed_index: Annotated[int, Field(ge=0, le=64)] | None = Field(
            default=None, description="vertical shift speed index; null = the index of camera.vertical_shift_s"
        )
        preamp_gain_index: Annotated[int, Field(ge=0, le=64)] = 0
        em_gain_mode: Literal["dac255", "dac4095", "linear", "real"] = "real"
        frame_transfer: bool = True
        trigger: Literal["external", "software", "internal"] = Field(
            default="external", description="'external': the AWG's camera line starts each exposure"
        )
        crop_mode: bool = Field(default=False, description="isolated crop mode (faster readout of a small ROI)")
        baseline_clamp: bool = True
        shutter: Literal["open", "auto", "closed"] = "open"

    class ActiveSiliconSettings(_Model):
        """The Active Silicon FireBird Camera Link grabber through its C library (``drivers/activesilicon.py``)."""

        config_file: str | None = Field(
            default=None, max_length=4096, description="the grabber's camera configuration file (.pcf) for the iXon"
        )
        library: str | None = Field(
            default=None, max_length=4096,
            description="path of the PHX library; null = search the usual install locations"
        )
        board: Annotated[int, Field(ge=1, le=7)] = 1
        channel: Annotated[int, Field(ge=1, le=2)] = 1

    camera: Literal["sim", "andor"] = "sim"
    frame_source: Literal["auto", "sim", "andor", "activesilicon"] = Field(
        default="auto",
        description=(
            "where frames come from: 'activesilicon' (Camera Link grabber), 'andor' (straight from the SDK), "
            "'sim'; 'auto' = the camera's own choice (sim for sim, andor for andor)"
        ),
    )
    awg: Literal["sim", "spectrum"] = "sim"
    spectrum: SpectrumSettings = SpectrumSettings()
    andor: AndorSettings = AndorSettings()
    activesilicon: ActiveSiliconSettings = ActiveSiliconSettings()

    @property
    def resolved_frame_source(self) -> Literal["sim", "andor", "activesilicon"]:
        """The frame source after resolving ``auto``."""
        if self.frame_source == "auto":
            return "sim" if self.camera == "sim" else "andor"
        return self.frame_source

    @property
    def simulated(self) -> bool:
        """True when every device is simulated (the simulated lab's hooks then tell the truth)."""
        return self.camera == "sim" and self.awg == "sim"

    @model_validator(mode="after")
    def _consistent_devices(self) -> DevicesConfig:
        source = self.resolved_frame_source
        if self.camera == "sim" and source != "sim":
            raise ValueError(
                f"devices.frame_source '{source}' reads a real camera but devices.camera is 'sim'; "
                "use frame_source 'sim' (or 'auto'), or camera 'andor'"
            )
        if self.camera == "andor" and source == "sim":
            raise ValueError(
                "devices.frame_source 'sim' cannot read the Andor camera; use 'activesilicon' (Camera Link grabber), "
                "'andor' (straight from the SDK) or 'auto'"
            )
        if source == "activesilicon" and not self.activesilicon.config_file:
            raise ValueError(
                "devices.activesilicon.config_file is required with frame_source 'activesilicon' "
                "(the grabber's .pcf camera file for the iXon)"
            )
        return self
