"""`quadsr excite`: fly an excitation profile against a running SITL and record the flight to a .tlog."""

from __future__ import annotations

import argparse
import os
import sys

from bridge.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `excite` subcommand."""
    from identification.excitation import list_profiles

    names = ", ".join(list_profiles())
    p = sub.add_parser(
        "excite",
        help="fly an identification excitation against a running SITL and log it to a .tlog",
        description=(
            "Connect to a running `quadsr sitl` as the companion, fly an excitation profile in lockstep "
            "(motor speeds sent as throttles through the vehicle's motor curve) and record every frame to a "
            f".tlog for `quadsr identify`. Bundled profiles: {names}. paper-train and paper-validate fly "
            "open loop from altitude: start the SITL with --ground none --initial-position 0,0,-200. "
            "closed-loop takes off from the ground: start the SITL with its default ground. With --autopilot "
            "the flight goes through real PX4 OFFBOARD (quadsr px4): exit 4 if PX4 refuses or leaves "
            "OFFBOARD, 3 if it goes silent."
        ),
    )
    p.add_argument(
        "--profile", required=True, metavar="NAME|FILE", help=f"profile name ({names}) or YAML file"
    )
    p.add_argument(
        "--hil",
        default="udp:127.0.0.1:4560",
        metavar="udp:HOST:PORT",
        help="the SITL's HIL address (default udp:127.0.0.1:4560)",
    )
    p.add_argument(
        "--autopilot",
        default=None,
        metavar="udp:HOST:PORT",
        help="fly through real PX4's offboard link instead of the HIL link (quadsr px4 instance N: "
        "udp:127.0.0.1:14580+N): body-rate and thrust setpoints from a closed-loop profile (px4-offboard); "
        "--out then logs that link, PX4 writes its ULog and quadsr px4 the truth .tlog",
    )
    p.add_argument(
        "--duration",
        type=float,
        default=None,
        metavar="S",
        help="flight duration in s (default: the profile's; paper-train splits it evenly over its groups, "
        "closed-loop counts the climb and settling in it)",
    )
    p.add_argument(
        "--seed", type=int, default=0, metavar="N", help="seed of the random excitation (default 0)"
    )
    p.add_argument(
        "--vehicle",
        default="fang-chen-buaa",
        metavar="NAME|FILE",
        help="vehicle file whose motor curve turns speeds into throttles; the SITL's (default "
        "fang-chen-buaa)",
    )
    p.add_argument("--out", required=True, metavar="FILE.tlog", help="telemetry log to write")
    p.add_argument("--signing-key", default=None, metavar="FILE", help="MAVLink 2 signing key, as the SITL's")
    p.add_argument(
        "--timeout",
        type=float,
        default=1.0,
        metavar="S",
        help="seconds to wait for each step before giving up (default 1)",
    )
    p.add_argument(
        "--connect-timeout",
        type=float,
        default=10.0,
        metavar="S",
        help="seconds to wait for the SITL to answer (default 10)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Fly the profile and print the summary; user mistakes raise UserError."""
    from identification.excite import fly

    if args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    for flag, value in (("--timeout", args.timeout), ("--connect-timeout", args.connect_timeout)):
        if not value > 0:
            raise UserError(f"{flag} must be a positive number of seconds, got {value}")
    if args.autopilot:
        return _run_offboard(args)
    summary = fly(
        profile=args.profile,
        out=args.out,
        hil=args.hil,
        duration=args.duration,
        seed=args.seed,
        vehicle=args.vehicle,
        signing_key=args.signing_key,
        step_timeout=args.timeout,
        connect_timeout=args.connect_timeout,
        progress=not args.no_progress,
    )
    _print(summary.lines())
    return 0


def _run_offboard(args: argparse.Namespace) -> int:
    """`quadsr excite --autopilot`: the flight through PX4 OFFBOARD; exit 0, 3 (silent), 4 (refused/left)."""
    from bridge.link import parse_endpoint
    from identification.offboard_excite import OffboardExcitationSettings, fly_offboard

    if args.signing_key:
        raise UserError("--signing-key signs the HIL link; PX4's offboard link (--autopilot) is not signed",
                        hint="leave out --signing-key with --autopilot")
    parse_endpoint(args.autopilot)
    settings = OffboardExcitationSettings(autopilot=args.autopilot, connect_timeout=max(args.connect_timeout,
                                                                                         30.0))
    print(f"quadsr excite: profile {args.profile} through PX4 OFFBOARD at {args.autopilot}, logging to "
          f"{args.out}", flush=True)
    flight = fly_offboard(args.profile, args.out, settings, args.duration, args.seed, args.vehicle)
    _print(flight.lines())
    if flight.message:
        print(f"quadsr excite: {flight.message}", file=sys.stderr, flush=True)
        return 3 if flight.link_lost else 4
    return 0


def _print(lines: list[str]) -> None:
    """Print the summary lines; a closed pipe (`| head`) is not an error."""
    try:
        for line in lines:
            print(line)
        sys.stdout.flush()
    except BrokenPipeError:  # `quadsr excite ... | head`: the flight and its log are complete anyway
        sys.stdout = open(os.devnull, "w")  # stdout must stay a valid file until the interpreter exits
