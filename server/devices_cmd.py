"""``llrs devices``: which device implementations this machine can use, and why not; ``llrs devices check``:
a bring-up sequence on the devices a configuration selects.

``llrs devices`` lists, for each role (AWG, camera, frame source), every implementation, marks the one the
configuration selects, and says whether its vendor software loads and (unless ``--no-probe``) whether the
device opens. The exit status is 0 when every selected device is available and 1 otherwise, so a lab PC's
start-up script can check the hardware before starting the server.

``llrs devices check`` opens the selected devices and runs the same sequence on real devices and on the
simulated lab (so the simulated run is what the tests exercise): the idle waveform is checked against the
configured RF limits *before* anything plays, then the AWG is configured, the idle segment uploaded and
played, a short step sequence followed and rewritten while playing, and the card's status read; the camera
is configured at the configured region, frames are acquired (through the grabber when one is configured),
the measured readout time is compared with the readout model (the paper's image-acquisition figure:
frame transfer + row readout + DMA), and the camera's temperature and gain are reported. Only the idle
waveform (the static traps the engine holds between shots, or silence for crossed AODs) is ever played,
so the check is safe for trapped atoms and for the RF amplifier. It prints a pass/fail table with, for each
failure, the reason and the fix; the exit status is 0 when everything passed.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from engine.config import SystemConfig
from engine.devices import DeviceError, DeviceSet, StepInfo

__all__ = ["CheckResult", "bring_up", "cmd_check", "cmd_devices", "format_checks", "format_table", "register"]

#: The measured readout may differ from the model by this factor before the check fails (the model's
#: constants are the iXon 888's; a camera read out at other speeds than configured differs far more).
READOUT_TOLERANCE = 1.5
#: Each AWG step of the bring-up sequence must be reached within this time (a hold segment lasts a slot).
STEP_TIMEOUT_S = 1.0


def register(sub: argparse._SubParsersAction) -> None:
    """Add the ``devices`` subcommand to the ``llrs`` parser."""
    p = sub.add_parser(
        "devices",
        help="list the AWG, camera and frame-source implementations available on this machine ('llrs devices "
        "check': run the bring-up sequence on the selected devices)",
    )
    p.add_argument("action", nargs="?", choices=["list", "check"], default="list",
                   help="'list' (default): what is available; 'check': open, play the idle waveform, acquire frames")
    p.add_argument("--config", help="YAML configuration (default: built-in defaults): its 'devices' section to "
                   "list; for check, everything (waveforms, awg, camera) the sequence uses")
    p.add_argument("--no-probe", action="store_true",
                   help="list only: load the vendor software; do not open the devices")
    p.add_argument("--frames", type=int, default=5, help="check only: frames to acquire (default 5)")
    p.add_argument("--json", action="store_true", help="print a JSON list instead of a table")
    p.set_defaults(func=_dispatch)


def _dispatch(args: argparse.Namespace) -> int:
    return cmd_check(args) if args.action == "check" else cmd_devices(args)


def format_table(entries: list[dict[str, Any]]) -> str:
    """The human-readable listing: one line per implementation, the selected ones marked with ``*``."""
    lines = [f"{'role':13s} {'device':14s} {'sel':3s} {'available':9s} detail"]
    for e in entries:
        mark = " * " if e["selected"] else "   "
        avail = "yes" if e["available"] else "NO"
        lines.append(f"{e['role']:13s} {e['name']:14s} {mark} {avail:9s} {e['detail']}")
    return "\n".join(lines)


def cmd_devices(args: argparse.Namespace) -> int:
    """Run ``llrs devices``; returns the exit status."""
    from drivers.factory import available_devices
    from engine.config import DevicesConfig, load_config

    devices = load_config(args.config).devices if args.config else DevicesConfig()
    entries = available_devices(devices, probe=not args.no_probe)
    if args.json:
        print(json.dumps(entries, indent=2))
    else:
        print(format_table(entries))
    missing = [e for e in entries if e["selected"] and not e["available"]]
    if missing and not args.json:
        names = ", ".join(f"{e['role']} '{e['name']}'" for e in missing)
        print(f"\nllrs: selected device(s) not available: {names}", file=sys.stderr)
    return 1 if missing else 0


# --- llrs devices check -------------------------------------------------------------------------------------

@dataclass
class CheckResult:
    """One line of the bring-up table: what was checked, whether it passed, what was seen, and the fix."""

    name: str
    passed: bool
    detail: str
    fix: str = ""


class _Stop(Exception):
    """A failed step after which the sequence cannot go on (its result is already recorded)."""


def _idle_within_limits(config: SystemConfig, hold: np.ndarray) -> CheckResult:
    """The idle waveform's peak per channel against the configured RF limit: the sum of the tone amplitudes of
    that channel's axis as the samples carry them (compensated for the DAC's sinc roll-off when so configured:
    the most the engine ever asks of the amplifier), and full scale."""
    from engine.waveforms import axis_tones, tone_sample_amplitudes

    axes = ("x",) if config.array.trap_source == "aod" else ("x", "y")
    parts, ok = [], True
    for ch, axis in enumerate(axes):
        limit = min(float(np.sum(tone_sample_amplitudes(config, axis_tones(config, axis)))), 1.0)
        peak = float(np.max(np.abs(hold[:, ch]))) / 32767.0
        ok &= peak <= limit + 1.0 / 32767.0
        mv = ""
        if config.devices.awg == "spectrum":
            amps = config.devices.spectrum.amplitude_mv
            amp = amps[ch] if isinstance(amps, list) else amps
            mv = f" = {peak * amp:.0f} mV of {amp} mV"
        parts.append(f"channel {ch} ({axis}): peak {100 * peak:.1f} % of full scale{mv}, limit {100 * limit:.1f} %")
    return CheckResult("idle waveform within the RF limits", ok, "; ".join(parts),
                       "" if ok else "the idle waveform exceeds array.*_tones.amplitude: do not play it; report a bug")


def _awg_sequence(config: SystemConfig, devices: DeviceSet, out: list[CheckResult]) -> None:
    """Configure the AWG, upload and play the idle segment, follow and rewrite a short step sequence."""
    from engine.card_rules import page_aligned_zeros
    from engine.waveforms import WaveformBank

    lean = config.model_copy(update={"waveforms": config.waveforms.model_copy(update={"table_max_bytes": 0})})
    bank = WaveformBank(lean, prefix=False)  # only the hold waveform is needed: no move tables
    idle = bank.hold()
    hold = page_aligned_zeros(idle.shape, np.int16)  # DMA-ready, as the streamer's buffers
    hold[:] = idle
    limits = _idle_within_limits(config, hold)
    out.append(limits)
    if not limits.passed:
        raise _Stop
    awg = devices.awg
    rate = config.waveforms.sample_rate_hz

    def configure() -> None:
        awg.stop()
        awg.configure(config.awg, n_channels=bank.n_channels, sample_rate_hz=rate)

    _step(out, "AWG configured", configure,
          lambda _: f"{awg.n_channels} channel(s) at {awg.sample_rate_hz / 1e6:g} MS/s, {config.awg.n_segments} "
                    f"segments, {config.awg.n_steps} steps",
          "check the devices.spectrum settings against the card (llrs devices lists what it has)")
    _step(out, "idle segment uploaded", lambda: awg.write_segment(0, hold),
          lambda _: f"{hold.shape[0]} samples x {hold.shape[1]} channel(s) ({hold.nbytes} B) into segment 0",
          "the card refused the segment: see the message; waveforms.sample_rate_hz x slot_duration_s sets its length")

    def play() -> None:
        awg.write_step(0, StepInfo(segment=0, next_step=1))
        awg.write_step(1, StepInfo(segment=0, next_step=2))
        awg.write_step(2, StepInfo(segment=0, next_step=2))  # rests here, looping the hold waveform
        awg.start(0)
        awg.wait_for_step(2, timeout_s=STEP_TIMEOUT_S)

    _step(out, "idle played through steps 0 -> 1 -> 2", play, lambda _: "the card followed the next-step pointers",
          "check the card's trigger set-up (devices.spectrum.trigger) and that nothing else drives the card")

    def rewrite() -> int:
        awg.write_step(2, StepInfo(segment=0, next_step=0))  # step memory rewritten while the card plays
        awg.write_step(0, StepInfo(segment=0, next_step=0))
        awg.wait_for_step(0, timeout_s=STEP_TIMEOUT_S)
        return awg.current_step()

    _step(out, "steps rewritten while playing", rewrite, lambda step: f"the card now loops step {step}",
          "the card did not take a step written during playback: check the driver version")
    info = getattr(awg, "info", None)
    card = f"{info.get('product')} s/n {info.get('serial')}: " if info else ""
    out.append(CheckResult("AWG status", awg.current_step() == 0, f"{card}playing step {awg.current_step()}",
                           "the card left the idle loop: stop it and check the step table"))


def _camera_sequence(config: SystemConfig, devices: DeviceSet, n_frames: int, out: list[CheckResult]) -> None:
    """Configure the camera at the configured region, acquire frames, compare readout with the model."""
    from drivers.sim.readout import readout_time

    camera, awg, cam = devices.camera, devices.awg, config.camera
    _step(out, "camera configured", lambda: camera.configure(cam),
          lambda _: f"frames of {camera.frame_shape[1]} x {camera.frame_shape[0]} px (ROI {cam.roi_width_px} x "
                    f"{cam.roi_height_px}, binning {cam.binning[0]} x {cam.binning[1]}), "
                    f"exposure {cam.exposure_s * 1e3:g} ms",
          "check camera.roi_*/binning against the sensor and devices.andor.roi_offset_px")
    frame = np.zeros(camera.frame_shape, dtype=np.uint16)
    readouts: list[float] = []

    def acquire() -> str:
        for _ in range(n_frames):
            awg.pulse("camera")
            camera.trigger()
            readouts.append(camera.read(frame, timeout_s=cam.timeout_s).readout_s)
        return f"{n_frames} frame(s); last frame mean {float(frame.mean()):.1f} counts, max {int(frame.max())}"

    _step(out, "frames acquired", acquire, lambda detail: detail,
          "check the trigger cable from the AWG's camera line, devices.andor.trigger, Camera Link mode and the "
          "grabber's camera file; raise camera.timeout_s if the exposure is long")
    model_s = readout_time(cam).readout_s
    measured_s = float(np.median(readouts))
    ratio = measured_s / model_s if model_s > 0 else math.inf
    ok = 1.0 / READOUT_TOLERANCE <= ratio <= READOUT_TOLERANCE
    out.append(CheckResult(
        "readout time vs model", ok,
        f"measured {measured_s * 1e3:.2f} ms (median of {len(readouts)}), model {model_s * 1e3:.2f} ms "
        f"(frame transfer + rows + DMA), ratio {ratio:.2f}",
        "" if ok else "set camera.vertical_shift_s / horizontal_rate_hz / transfer_bytes_per_s to what the camera "
                      "runs at (devices.andor.vs_speed_index, hs_speed_index), or look for a slow transfer",
    ))
    status = getattr(camera, "status", None)
    if callable(status):
        st = status()
        temp_ok = st.get("temperature_status") == "DRV_TEMP_STABILIZED"
        out.append(CheckResult(
            "camera temperature and gain", temp_ok,
            f"{st.get('temperature_c')} C ({st.get('temperature_status')}), EM gain {st.get('em_gain')} "
            f"(camera.em_gain {cam.em_gain:g})",
            "" if temp_ok else "wait for the cooler (devices.andor.wait_for_temperature_s) before taking data",
        ))
    else:
        out.append(CheckResult("camera temperature and gain", True,
                               f"{type(camera).__name__}: no cooler to report, EM gain x{cam.em_gain:g}"))


def _step(out: list[CheckResult], name: str, action: Callable[[], Any], describe: Callable[[Any], str],
          fix: str) -> None:
    """Run ``action``; record a pass with ``describe(result)`` or a failure with the device's message and
    ``fix``; a failure ends the sequence (what follows depends on it)."""
    try:
        result = action()
    except DeviceError as err:
        out.append(CheckResult(name, False, str(err), fix))
        raise _Stop from None
    out.append(CheckResult(name, True, describe(result)))


def bring_up(config: SystemConfig, devices: DeviceSet, *, n_frames: int = 5) -> list[CheckResult]:
    """The bring-up sequence on opened ``devices`` (see the module docstring); the AWG is stopped at the end
    whatever happened. The camera part runs even if the AWG part failed before playing anything."""
    out: list[CheckResult] = []
    try:
        try:
            _awg_sequence(config, devices, out)
        except _Stop:
            pass
        try:
            _camera_sequence(config, devices, n_frames, out)
        except _Stop:
            pass
    finally:
        devices.awg.stop()
    return out


def format_checks(results: list[CheckResult]) -> str:
    """The pass/fail table: one line per check, the fix under each failure."""
    width = max(len(r.name) for r in results)
    lines = []
    for r in results:
        lines.append(f"{'PASS' if r.passed else 'FAIL'}  {r.name:{width}s}  {r.detail}")
        if not r.passed and r.fix:
            lines.append(f"{'':6s}{'':{width}s}  fix: {r.fix}")
    return "\n".join(lines)


def cmd_check(args: argparse.Namespace) -> int:
    """Run ``llrs devices check``; returns the exit status (0: every check passed)."""
    from drivers.factory import open_devices
    from engine.config import load_config

    config = load_config(args.config) if args.config else SystemConfig()
    if args.frames < 1:
        print("llrs: --frames must be at least 1", file=sys.stderr)
        return 2
    try:
        devices, lab = open_devices(config)
    except DeviceError as err:
        results = [CheckResult("devices opened", False, str(err), "run 'llrs devices' to see what is missing")]
    else:
        try:
            if lab is not None:
                lab.prepare_shot()  # the simulated lab loads atoms (and arms its injected faults) as before a shot
            results = [CheckResult("devices opened", True, f"awg {config.devices.awg}, camera {config.devices.camera}, "
                                                           f"frames from {config.devices.resolved_frame_source}")]
            results += bring_up(config, devices, n_frames=args.frames)
        finally:
            devices.close()
    if args.json:
        print(json.dumps([asdict(r) for r in results], indent=2))
    else:
        print(format_checks(results))
    return 0 if all(r.passed for r in results) else 1
