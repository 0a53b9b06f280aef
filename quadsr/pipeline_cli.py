"""Whole-pipeline subcommands: `quadsr hover-check` (start a SITL, fly a hover, check it)."""

from __future__ import annotations

import argparse
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    """Add the pipeline subcommands to the quadsr parser."""
    p = sub.add_parser("hover-check", help="start a SITL, take off over MAVLink, and check the hover",
                       description="Starts `quadsr sitl` as a child process on free ports (lockstep), takes "
                                   "off to --altitude and holds it, and checks the hold: RMS altitude error "
                                   "< 2 cm, tilt < 0.01 rad, final speed < 2 cm/s. Exit 0 when it passes.")
    p.add_argument("--vehicle", default="fang-chen-buaa", help="vehicle name or YAML file")
    p.add_argument("--altitude", type=float, default=2.0, help="hover altitude above the ground [m]")
    p.add_argument("--duration", type=float, default=10.0, help="flight time [s, simulated]")
    p.add_argument("--out", type=Path, default=None, help="folder for hover.tlog and sitl.log")
    p.set_defaults(func=_hover_check)


def _hover_check(args: argparse.Namespace) -> int:
    from bridge.errors import UserError
    from quadsr.hover_check import run_hover_check

    if not 0.5 <= args.altitude <= 100 or not 5.0 <= args.duration <= 600:
        raise UserError("--altitude must be within 0.5..100 m and --duration within 5..600 s",
                        hint="e.g. quadsr hover-check --altitude 2 --duration 10")
    result = run_hover_check(args.out, args.vehicle, args.altitude, args.duration)
    rows = [
        ("target altitude [m]", f"{result.target_altitude:.3f}"),
        ("final altitude [m]", f"{result.final_altitude:.4f}"),
        ("RMS altitude error over the hold [m]", f"{result.altitude_error_rms:.2e}"),
        ("max tilt over the hold [rad]", f"{result.max_tilt:.2e}"),
        ("final speed [m/s]", f"{result.final_speed:.2e}"),
        ("lockstep steps", str(result.steps)),
        ("steps per second (wall)", f"{result.steps_per_second:.0f}"),
    ]
    print("| quantity | value |\n| --- | --- |")
    for name, value in rows:
        print(f"| {name} | {value} |")
    print(f"hover check: {'PASS' if result.passed else 'FAIL'}")
    return 0 if result.passed else 1
