"""`quadsr sitl`: run the simulated quadrotor and serve its HIL and ground-tool links."""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import TYPE_CHECKING

from bridge.airframe import TURBULENCE_PRESETS
from bridge.errors import UserError
from bridge.link import LOCKSTEP_SPIN_S

if TYPE_CHECKING:
    from bridge.airframe import WindConfig
    from bridge.link import Endpoint
    from bridge.vehicle import VehicleConfig
    from sitl.ardupilot_server import ArduPilotOptions
    from sitl.server import SitlOptions

DEFAULT_VEHICLE = "fang-chen-buaa"
DEFAULT_HIL = "udp:127.0.0.1:4560"
DEFAULT_GCS = "udp:127.0.0.1:14550"
DEFAULT_ARDUPILOT = "udp:127.0.0.1:9002"


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the `sitl` subcommand."""
    p = subparsers.add_parser(
        "sitl",
        help="run the simulated quadrotor (HIL link for a companion, ground link for GCS/offboard tools)",
        description=(
            "Simulate a quadrotor and serve PX4's simulator protocol over UDP MAVLink 2. A companion (the "
            "identification client or the controller) connects to the HIL address and steps the simulation; "
            "ground tools (QGroundControl, MAVSDK) receive PX4-like telemetry on the ground link."
        ),
    )
    p.add_argument("--vehicle", default=DEFAULT_VEHICLE, metavar="FILE|NAME",
                   help=f"vehicle YAML file or bundled name (default {DEFAULT_VEHICLE})")
    p.add_argument("--hil", default=DEFAULT_HIL, metavar="udp:HOST:PORT|tcp:HOST:PORT|udpout:HOST:PORT",
                   help=f"address to listen on for the companion (default {DEFAULT_HIL}); for PX4: "
                        "tcp:127.0.0.1:4560+N to listen for PX4 instance N (simulator_mavlink -c), "
                        "udpout:HOST:PORT to send first to a PX4 started with simulator_mavlink -u PORT")
    p.add_argument("--gcs", default=DEFAULT_GCS, metavar="udp:HOST:PORT",
                   help=f"ground station to send telemetry to (default {DEFAULT_GCS})")
    p.add_argument("--offboard", default=None, metavar="udp:HOST:PORT",
                   help="second ground-tool address, e.g. udp:127.0.0.1:14540 for MAVSDK (default none)")
    p.add_argument("--no-gcs", action="store_true", help="do not send to the --gcs address")
    p.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep",
                   help="lockstep: one step per companion reply (default); realtime: paced to the wall clock")
    p.add_argument("--log", default=None, metavar="FILE.tlog", help="record every HIL frame to a .tlog file")
    p.add_argument("--seed", type=int, default=None, help="sensor noise seed (default: the vehicle file's)")
    p.add_argument("--signing-key", default=None, metavar="FILE",
                   help="MAVLink 2 signing key (32 raw bytes or 64 hex digits): refuse unsigned commands")
    p.add_argument("--sensors", choices=("realistic", "ideal"), default=None,
                   help="sensor noise preset (default: the vehicle file's); ideal is noise-free")
    p.add_argument("--ground", choices=("plane", "none"), default=None,
                   help="ground model (default: the vehicle file's); none for excitation started at altitude")
    p.add_argument("--initial-position", default=None, metavar="N,E,D",
                   help="start position NED in m, e.g. 0,0,-50 (default: the vehicle file's); "
                        "write --initial-position=-5,0,-50 when N is negative")
    p.add_argument("--wind", default=None, metavar="N,E,D",
                   help="steady wind in m/s NED, e.g. 5,0,0 for a 5 m/s wind blowing toward north "
                        "(default: the vehicle file's wind section, else none); write --wind=-5,0,0 "
                        "when N < 0")
    p.add_argument("--turbulence", default=None, choices=TURBULENCE_PRESETS,
                   help="Dryden turbulence preset (MIL-F-8785C low altitude; needs a wind speed)")
    p.add_argument("--gust", action="append", default=None, metavar="T0,DURATION,N,E,D",
                   help="a 1-cosine gust starting at T0 s of simulated time, lasting DURATION s, peaking at "
                        "N,E,D m/s (repeat the flag for several gusts)")
    p.add_argument("--wind-seed", type=int, default=None, metavar="N",
                   help="seed of the turbulence (default: the vehicle file's wind.seed, else 0)")
    p.add_argument("--initial-rotor-speed", default="0", metavar="W|hover",
                   help="start rotor speed in rad/s, or 'hover' (trimmed hover, e.g. with --ground none)")
    p.add_argument("--lockstep-timeout", type=float, default=1.0, metavar="S",
                   help="lockstep: wall seconds to wait for a reply before the failsafe (default 1)")
    p.add_argument("--lockstep-spin-us", type=float, default=LOCKSTEP_SPIN_S * 1e6, metavar="US",
                   help="lockstep: microseconds to poll for a reply before sleeping for it (default "
                        f"{LOCKSTEP_SPIN_S * 1e6:g}; 0: sleep at once, for a machine whose cores are busy)")
    p.add_argument("--realtime-timeout", type=float, default=0.2, metavar="S",
                   help="realtime: simulated seconds without commands before the failsafe (default 0.2)")
    p.add_argument("--status-interval", type=float, default=5.0, metavar="S",
                   help="wall seconds between status lines (default 5; 0 turns them off)")
    p.add_argument("--max-steps", type=int, default=None, metavar="N", help="exit after N steps")
    p.add_argument("--ardupilot", nargs="?", const=DEFAULT_ARDUPILOT, default=None, metavar="udp:HOST:PORT",
                   help="be ArduPilot's JSON physics instead of PX4's HIL simulator: listen for its servo "
                        f"packets there (default {DEFAULT_ARDUPILOT}; 9002+10*N for arducopter -I N)")
    p.add_argument("--max-rtf", type=float, default=0.0, metavar="R",
                   help="with tcp:/udpout: lockstep, but at most R times real time (1: paced to the wall "
                        "clock, for an offboard companion beside PX4); default 0, as fast as the autopilot")
    p.add_argument("--companion-sysid", type=int, default=None, metavar="ID",
                   help="system id the companion sends from (default 1; with tcp:/udpout: any, PX4 "
                        "instance N sends from N+1); other ids are dropped")
    p.set_defaults(func=run)


def options_from_args(args: argparse.Namespace) -> SitlOptions:
    """Validate the parsed flags into SitlOptions (UserError naming the flag on a bad value)."""
    from bridge.link import parse_endpoint
    from bridge.signing import load_key
    from bridge.vehicle import load_vehicle
    from sitl.server import SitlOptions

    initial_position = _triple(args.initial_position, "--initial-position") if args.initial_position else None
    if args.seed is not None and args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    vehicle = load_vehicle(args.vehicle)
    vehicle = vehicle.with_overrides(
        ground=args.ground, initial_position=initial_position, sensors=args.sensors, seed=args.seed,
        wind=_wind(args, vehicle.wind),
    )
    rotor_speed = _rotor_speed(args.initial_rotor_speed, vehicle)
    timeouts = (("--lockstep-timeout", args.lockstep_timeout), ("--realtime-timeout", args.realtime_timeout))
    for flag, value in timeouts:
        if not (math.isfinite(value) and value > 0):
            raise UserError(f"{flag} must be a positive number of seconds, got {value}")
    if not (math.isfinite(args.lockstep_spin_us) and 0 <= args.lockstep_spin_us <= 1e6):
        raise UserError(f"--lockstep-spin-us must be 0..1000000 microseconds, got {args.lockstep_spin_us}")
    if not (math.isfinite(args.status_interval) and args.status_interval >= 0):
        raise UserError(f"--status-interval must be >= 0 seconds, got {args.status_interval}")
    if not (math.isfinite(args.max_rtf) and args.max_rtf >= 0):
        raise UserError(f"--max-rtf must be >= 0 (0: no limit), got {args.max_rtf}")
    if args.max_steps is not None and args.max_steps < 0:
        raise UserError(f"--max-steps must be >= 0, got {args.max_steps}")
    if args.companion_sysid is not None and not 1 <= args.companion_sysid <= 255:
        raise UserError(f"--companion-sysid must be 1..255, got {args.companion_sysid}")
    ground_endpoints = []
    if not args.no_gcs:
        ground_endpoints.append(parse_endpoint(args.gcs))
    if args.offboard:
        ground_endpoints.append(parse_endpoint(args.offboard))
    log = Path(args.log) if args.log else None
    if log is not None and log.is_dir():
        raise UserError(f"--log {log} is a directory", hint="give a file name such as flight.tlog")
    return SitlOptions(
        vehicle=vehicle,
        hil=parse_hil_address(args.hil),
        ground=ground_endpoints,
        mode=args.mode,
        log=log,
        signing_key=load_key(args.signing_key) if args.signing_key else None,
        initial_rotor_speed=rotor_speed,
        lockstep_timeout=args.lockstep_timeout,
        lockstep_spin=args.lockstep_spin_us * 1e-6,
        realtime_timeout=args.realtime_timeout,
        status_interval=args.status_interval,
        max_steps=args.max_steps,
        companion_sysid=args.companion_sysid or 1,
    )


def parse_hil_address(text: str) -> Endpoint:
    """--hil: udp:/udpin: (a companion), tcp: (listen for PX4) or udpout: (send first to PX4)."""
    from bridge.link import parse_endpoint
    from bridge.stream_link import is_tcp_address, parse_tcp_endpoint

    return parse_tcp_endpoint(text) if is_tcp_address(text) else parse_endpoint(text)


def run(args: argparse.Namespace) -> int:
    """Run the SITL until SIGINT/SIGTERM (exit 0) or --max-steps."""
    from sitl.autopilot_server import AutopilotSitlServer, serves_autopilot
    from sitl.server import SitlServer

    options = options_from_args(args)
    if args.ardupilot is not None:
        from sitl.ardupilot_server import ArduPilotServer

        return ArduPilotServer(ardupilot_options(args, options)).run()
    if serves_autopilot(options):
        return AutopilotSitlServer(options, autopilot_sysid=args.companion_sysid, max_rtf=args.max_rtf).run()
    return SitlServer(options).run()


def ardupilot_options(args: argparse.Namespace, sitl: SitlOptions) -> ArduPilotOptions:
    """The JSON-physics server's options: --ardupilot's address plus the SITL flags that apply to it."""
    from bridge.link import parse_endpoint
    from sitl.ardupilot_server import ArduPilotOptions

    for flag, given in (("--mode realtime", args.mode != "lockstep"), ("--signing-key", args.signing_key),
                        ("--offboard", args.offboard)):
        if given:
            raise UserError(f"{flag} does not apply with --ardupilot (ArduPilot steps the physics in "
                            "lockstep over its JSON interface and serves MAVLink itself)",
                            hint=f"drop {flag.split()[0]}")
    return ArduPilotOptions(
        vehicle=sitl.vehicle,
        endpoint=parse_endpoint(args.ardupilot),
        log=sitl.log,
        initial_rotor_speed=sitl.initial_rotor_speed,
        status_interval=sitl.status_interval,
        max_steps=sitl.max_steps,
    )


def _numbers(text: str, what: str, count: int, flag: str, example: str) -> tuple[float, ...]:
    """`count` finite comma-separated numbers from a flag's text; a UserError saying `what` otherwise."""
    parts = text.replace(" ", "").split(",")
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        values = ()
    if len(values) != count or not all(math.isfinite(v) for v in values):
        raise UserError(f"{flag} must be {what}, got {text!r}", hint=f"e.g. {flag} {example}")
    return values


def _triple(text: str, flag: str, unit: str = "m", example: str = "0,0,-50") -> tuple[float, float, float]:
    return _numbers(text, f"three numbers N,E,D in {unit}", 3, flag, example)  # type: ignore[return-value]


def _wind(args: argparse.Namespace, base: WindConfig) -> WindConfig | None:
    """The vehicle file's wind with the --wind, --turbulence, --gust, --wind-seed flags (None: no flag)."""
    from bridge.airframe import GustConfig, wind_config

    if args.wind is None and args.turbulence is None and args.gust is None and args.wind_seed is None:
        return None
    steady = _triple(args.wind, "--wind", "m/s", "5,0,0") if args.wind is not None else base.steady
    gusts = base.gusts
    if args.gust is not None:
        gusts = tuple(GustConfig(v[0], v[1], (v[2], v[3], v[4]))
                      for v in (_numbers(g, "five numbers T0,DURATION,N,E,D (s, s, m/s NED)", 5, "--gust",
                                         "2,1.5,0,4,0") for g in args.gust))
    if args.wind_seed is not None and args.wind_seed < 0:
        raise UserError(f"--wind-seed must be >= 0, got {args.wind_seed}")
    return wind_config(
        "quadsr sitl flags", steady, args.turbulence or base.turbulence, base.reference_altitude, gusts,
        base.seed if args.wind_seed is None else args.wind_seed, key="wind",
    )


def _rotor_speed(text: str, vehicle: VehicleConfig) -> float:
    if text.strip().lower() == "hover":
        return vehicle.hover_speed
    try:
        w = float(text)
    except ValueError:
        w = math.nan
    if not (math.isfinite(w) and 0.0 <= w <= vehicle.motor_curve.max_speed):
        raise UserError(
            f"--initial-rotor-speed must be 'hover' or a speed in rad/s within [0, "
            f"{vehicle.motor_curve.max_speed:.1f}], got {text!r}"
        )
    return w
