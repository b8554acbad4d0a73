"""Builds the devices a configuration selects (``config.devices``), and says which ones this machine can open.

``open_devices(config)`` is what the composition root (``server/``) calls: the simulated lab when every
device is ``sim`` (with its lab hooks), otherwise the real adapters, opened at once so that a missing driver
or an absent card is reported when the devices are built, with a message that says what to install or
check, and not at the first shot. A real device may be combined with a simulated one (e.g. a real AWG on a
scope with the simulated camera); the simulated part then runs in real time, and no lab hooks are returned
because the simulated world no longer tells the truth about the atoms.

``available_devices()`` backs ``llrs devices``: for every implementation of every role, whether it can be
imported and (with ``probe``) opened here, and why not.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from types import ModuleType
from typing import TYPE_CHECKING, Any, Protocol, TypeVar

from engine.aod_limits import SegmentGuard
from engine.config import DevicesConfig, SystemConfig
from engine.devices import Camera, DeviceError, DeviceSet, SequenceAWG

if TYPE_CHECKING:
    from engine.engine import Lab

__all__ = ["HostClock", "available_devices", "open_devices"]


class _Openable(Protocol):
    def open(self) -> None: ...


_Device = TypeVar("_Device", bound=_Openable)

class HostClock:
    """Wall time on hardware: the host's monotonic high-resolution clock."""

    def now_s(self) -> float:
        return time.perf_counter()


class _HardwareDeviceSet(DeviceSet):
    """A device set that also releases the AWG card when closed (``DeviceSet.close`` only stops it)."""

    def close(self) -> None:
        try:
            super().close()
        finally:
            closer = getattr(self.awg, "close", None)
            if closer is not None:
                closer()


def open_devices(
    config: SystemConfig,
    *,
    spcm_module: ModuleType | None = None,
    andor_module: ModuleType | None = None,
    phx_library: Any = None,
) -> tuple[DeviceSet, Lab | None]:
    """The devices ``config.devices`` selects, opened, and the lab hooks (simulated lab only, else ``None``).

    The keyword arguments replace the vendor modules (tests pass fakes). Raises ``DeviceError`` (having
    closed whatever it had opened) when a device cannot be opened.
    """
    from drivers.sim.lab import build_sim_lab

    d: DevicesConfig = config.devices
    if d.simulated:
        devices, lab = build_sim_lab(config)
        return devices, lab
    sim_parts: DeviceSet | None = None
    if d.camera == "sim" or d.awg == "sim":
        realtime = config.model_copy(update={"sim": config.sim.model_copy(update={"time": "realtime"})})
        sim_parts, _ = build_sim_lab(realtime)
    clock = HostClock()
    opened: list[Any] = []
    try:
        awg: SequenceAWG
        if d.awg == "spectrum":
            from drivers.spectrum import SpectrumAWG

            guard = SegmentGuard(config.channel_limits(), config.waveforms.slot_samples)
            awg = _opened(SpectrumAWG(d.spectrum, spcm_module=spcm_module, rf_guard=guard), opened)
        else:
            assert sim_parts is not None
            awg = sim_parts.awg
        camera: Camera
        if d.camera == "andor":
            from drivers.andor import AndorCamera, FrameSource

            source: FrameSource | None = None
            if d.resolved_frame_source == "activesilicon":
                from drivers.activesilicon import ActiveSiliconFrameSource

                source = ActiveSiliconFrameSource(d.activesilicon, library=phx_library)
            camera = _opened(AndorCamera(d.andor, frame_source=source, sdk_module=andor_module, clock=clock), opened)
        else:
            assert sim_parts is not None
            camera = sim_parts.camera
    except BaseException:
        for dev in reversed(opened):
            try:
                dev.close()
            except DeviceError:
                pass
        raise
    return _HardwareDeviceSet(camera=camera, awg=awg, clock=clock), None


def _opened(device: _Device, opened: list[Any]) -> _Device:
    """``device`` opened, and listed in ``opened`` (closed again if a later device fails to open)."""
    device.open()
    opened.append(device)
    return device


def _entry(role: str, name: str, selected: bool, available: bool, detail: str) -> dict[str, Any]:
    return {"role": role, "name": name, "selected": selected, "available": available, "detail": detail}


def _probe_with(
    load: Callable[[], Any], probe: bool, loaded: str, check: Callable[[Any], tuple[bool, str]]
) -> tuple[bool, str]:
    """``(available, detail)`` of one vendor device: its module loads (``load``; without ``probe`` that is the
    whole check, and ``loaded`` says so), then ``check(module)`` looks at the device itself."""
    try:
        mod = load()
    except DeviceError as err:
        return False, str(err)
    if not probe:
        return True, loaded
    return check(mod)


def _probe_spectrum(d: DevicesConfig, probe: bool, spcm_module: ModuleType | None) -> tuple[bool, str]:
    from drivers.spectrum import SpectrumAWG, import_spcm

    def check(mod: ModuleType) -> tuple[bool, str]:
        awg = SpectrumAWG(d.spectrum, spcm_module=mod)
        try:
            awg.open()
        except DeviceError as err:
            return False, str(err)
        try:
            i = awg.info
            demo = " (demo card)" if i.get("demo_card") else ""
            return True, (
                f"{i['product']}{demo} s/n {i['serial']} at {d.spectrum.device}: {i['channels']} channels, "
                f"{i['memory_bytes'] / 2**30:.1f} GiB, {i['max_segments']} segments, {i['max_steps']} steps"
            )
        finally:
            awg.close()

    return _probe_with(
        lambda: spcm_module if spcm_module is not None else import_spcm(), probe,
        "spcm and the Spectrum driver library load (card not opened: --no-probe)", check,
    )  # fmt: skip


def _probe_andor(d: DevicesConfig, probe: bool, andor_module: ModuleType | None) -> tuple[bool, str]:
    from drivers.andor import import_andor, status_name

    def check(mod: ModuleType) -> tuple[bool, str]:
        try:
            sdk = mod.atmcd()
            ret, n = sdk.GetAvailableCameras()  # allowed before Initialize; does not disturb a running camera
        except Exception as err:  # noqa: BLE001 - the vendor wrapper raises what its library raises
            return False, f"Andor camera: pyAndorSDK2 imports but the SDK library could not be used ({err})"
        if ret != 20002:
            return False, f"Andor camera: GetAvailableCameras failed with {status_name(ret)}"
        if d.andor.index >= n:
            return False, f"Andor camera: the SDK sees {n} camera(s); devices.andor.index is {d.andor.index}"
        return True, f"the SDK sees {n} camera(s); devices.andor.index {d.andor.index} (not initialized by this check)"

    return _probe_with(
        lambda: andor_module if andor_module is not None else import_andor(), probe,
        "pyAndorSDK2 imports (SDK library not loaded: --no-probe)", check,
    )  # fmt: skip


def _probe_activesilicon(d: DevicesConfig, probe: bool, phx_library: Any) -> tuple[bool, str]:
    from drivers.activesilicon import ActiveSiliconFrameSource, load_library

    def check(lib: Any) -> tuple[bool, str]:
        if not d.activesilicon.config_file:
            return True, "the PHX library loads; set devices.activesilicon.config_file to also open the board"
        source = ActiveSiliconFrameSource(d.activesilicon, library=lib)
        try:
            source.open()
        except DeviceError as err:
            return False, str(err)
        source.close()
        grabber = d.activesilicon
        return True, f"board {grabber.board} channel {grabber.channel} opens with {grabber.config_file}"

    return _probe_with(
        lambda: phx_library if phx_library is not None else load_library(d.activesilicon.library), probe,
        "the PHX library loads (board not opened: --no-probe)", check,
    )  # fmt: skip


def available_devices(
    devices: DevicesConfig | None = None,
    *,
    probe: bool = True,
    spcm_module: ModuleType | None = None,
    andor_module: ModuleType | None = None,
    phx_library: Any = None,
) -> list[dict[str, Any]]:
    """Every implementation of every role: ``{role, name, selected, available, detail}``.

    ``selected`` marks what ``devices`` (default: the defaults) chooses; ``detail`` says what was found, or
    why the device is not available and what to install. With ``probe`` the real devices are opened and
    closed again (a device held by a running server then shows as unavailable); without it, only their
    software is loaded.
    """
    d = devices if devices is not None else DevicesConfig()
    out: list[dict[str, Any]] = []
    sim = "the simulated lab (always available)"
    out.append(_entry("awg", "sim", d.awg == "sim", True, sim))
    ok, detail = _probe_spectrum(d, probe, spcm_module)
    out.append(_entry("awg", "spectrum", d.awg == "spectrum", ok, detail))
    out.append(_entry("camera", "sim", d.camera == "sim", True, sim))
    andor_ok, andor_detail = _probe_andor(d, probe, andor_module)
    out.append(_entry("camera", "andor", d.camera == "andor", andor_ok, andor_detail))
    source = d.resolved_frame_source
    out.append(_entry("frame_source", "sim", source == "sim", True, sim))
    out.append(_entry("frame_source", "andor", source == "andor", andor_ok,
                      "frames read from the Andor SDK; " + andor_detail if andor_ok else andor_detail))
    ok, detail = _probe_activesilicon(d, probe, phx_library)
    out.append(_entry("frame_source", "activesilicon", source == "activesilicon", ok, detail))
    return out
