"""``llrs devices``: which device implementations this machine can use, and why not.

For each role (AWG, camera, frame source) it lists every implementation, marks the one the configuration
selects, and says whether its vendor software loads and (unless ``--no-probe``) whether the device opens.
The exit status is 0 when every selected device is available and 1 otherwise, so a lab PC's start-up
script can check the hardware before starting the server.
"""

from __future__ import annotations

import argparse
import json
import sys
from typing import Any

__all__ = ["cmd_devices", "format_table", "register"]


def register(sub: argparse._SubParsersAction) -> None:  # type: ignore[type-arg]
    """Add the ``devices`` subcommand to the ``llrs`` parser."""
    p = sub.add_parser("devices", help="list the AWG, camera and frame-source implementations available on this machine")
    p.add_argument("--config", help="YAML configuration whose 'devices' section is checked (default: built-in defaults)")
    p.add_argument("--no-probe", action="store_true", help="only load the vendor software; do not open the devices")
    p.add_argument("--json", action="store_true", help="print a JSON list instead of a table")
    p.set_defaults(func=cmd_devices)


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
