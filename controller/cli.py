"""`quadsr fly`: fly a trajectory with a controller as an offboard companion of a running SITL."""

from __future__ import annotations

import argparse
import dataclasses
import math
from pathlib import Path
from typing import Any

from bridge.errors import UserError

BUILTIN_DURATION = 20.0  # s, default flight length of case1 and case2
EXIT_CRASHED = 1
EXIT_LINK_LOST = 3
EXIT_REFUSED = 4  # the autopilot refused or left the offboard flight (rejected mode/arming, failsafe, disarm)


def register(sub: argparse._SubParsersAction) -> None:
    """Add `quadsr fly` to the quadsr parser."""
    p = sub.add_parser(
        "fly",
        help="fly a trajectory with a controller against a running SITL",
        description="Connect to a running SITL's HIL link as the companion (the autopilot's seat), fly a "
                    "trajectory with the chosen controller, and write flight.tlog, steps.csv, metrics.md, "
                    "metrics.csv, tracking.png and path3d.png to DIR.",
    )
    p.add_argument("--model", metavar="FILE", help="model file the backstepping controller is derived from "
                                                    "(learned model.yaml or the true model)")
    p.add_argument("--trajectory", required=True, metavar="case1|case2|FILE",
                   help="built-in trajectory name or a trajectory YAML file")
    p.add_argument("--controller", default="backstepping", metavar="backstepping|pid|se3",
                   help="controller (default backstepping)")
    p.add_argument("--hil", default="udp:127.0.0.1:4560", metavar="udp:HOST:PORT",
                   help="the SITL's HIL address (default udp:127.0.0.1:4560)")
    p.add_argument("--autopilot", default=None, metavar="udp:HOST:PORT|tcp:HOST:PORT",
                   help="fly through a real autopilot's offboard link instead of the HIL link: PX4 "
                        "(quadsr px4 instance N: udp:127.0.0.1:14580+N) in OFFBOARD, or ArduCopter "
                        "(quadsr ardupilot -I N: tcp:127.0.0.1:5760+10N) in GUIDED, the controller's "
                        "attitude and collective thrust as SET_ATTITUDE_TARGET (backstepping only)")
    p.add_argument("--autopilot-type", default=None, metavar="px4|ardupilot",
                   help="which autopilot --autopilot is (default: ardupilot for tcp:, px4 for udp:)")
    p.add_argument("--truth", default=None, metavar="FILE.tlog",
                   help="with --autopilot: quadsr's truth log (quadsr px4's WORK/truth.tlog) for the metrics "
                        "(default: the autopilot's estimate)")
    p.add_argument("--duration", type=float, metavar="S",
                   help="flight length in s (default 20 for case1/case2, else the trajectory file's)")
    p.add_argument("--state", default="truth", metavar="truth|sensors",
                   help="state fed back: the SITL's true state (default) or estimated from the sensors")
    p.add_argument("--vehicle", metavar="NAME|FILE",
                   help="vehicle file or bundled name (default: the model's vehicle, else fang-chen-buaa)")
    p.add_argument("--gains", metavar="FILE", help="gains YAML (flat, or one section per controller name)")
    p.add_argument("--out", required=True, metavar="DIR", help="output directory")
    p.add_argument("--link-timeout", type=float, default=0.5, metavar="S",
                   help="give up when no sensor message arrives for this long (default 0.5 s)")
    p.add_argument("--connect-timeout", type=float, default=10.0, metavar="S",
                   help="wait this long for the SITL's first step (default 10 s)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    p.add_argument("--no-takeoff", action="store_true",
                   help="no take-off phase (by default a reference starting in the air is preceded by a "
                        "minimum-snap climb from where the vehicle stands to its first point)")
    p.add_argument("--no-governor", action="store_true",
                   help="no time-scaling governor (by default a reference beyond the vehicle's limits is "
                        "flown slower along the same path)")
    p.set_defaults(func=run_fly)


def _vehicle_for(args: argparse.Namespace, model: Any) -> Any:
    from bridge.vehicle import load_vehicle

    if args.vehicle:
        return load_vehicle(args.vehicle)
    info = getattr(model, "vehicle", None) or {}
    name = info.get("name") if isinstance(info, dict) else None
    if name:
        try:
            return load_vehicle(name)
        except UserError:
            pass
    return load_vehicle("fang-chen-buaa")


def _positive(name: str, value: float | None) -> None:
    if value is not None and not (math.isfinite(value) and value > 0):
        raise UserError(f"{name} must be a positive number of seconds, got {value:g}")


def _fly_offboard(args: argparse.Namespace, controller: Any, trajectory: Any, vehicle: Any, duration: float,
                  out: Path) -> int:
    """`quadsr fly --autopilot`: the flight through PX4's OFFBOARD mode; exit 0, 1 (crash), 3 (link), 4."""
    from bridge.link import parse_endpoint
    from bridge.stream_link import is_tcp_address, parse_tcp_endpoint
    from controller.guided_companion import GuidedCompanion
    from controller.offboard_companion import OffboardCompanion, OffboardSettings

    tcp = is_tcp_address(args.autopilot)
    parse_tcp_endpoint(args.autopilot) if tcp else parse_endpoint(args.autopilot)
    kind = args.autopilot_type or ("ardupilot" if tcp else "px4")
    if kind not in ("px4", "ardupilot"):
        raise UserError(f"--autopilot-type {kind!r} is not px4 or ardupilot", hint="give px4 or ardupilot")
    if args.controller != "backstepping":
        raise UserError(f"--autopilot flies the backstepping controller only, not {args.controller!r}",
                        hint="drop --controller, or fly the baselines over --hil")
    truth = Path(args.truth) if args.truth else None
    if truth is not None and not truth.is_file():
        raise UserError(f"--truth {truth} does not exist", hint="give quadsr px4's WORK/truth.tlog")
    settings = OffboardSettings(autopilot=args.autopilot, duration=duration, truth=truth,
                                connect_timeout=max(args.connect_timeout, 30.0))
    flight = GuidedCompanion if kind == "ardupilot" else OffboardCompanion
    companion = flight(controller, trajectory, vehicle, settings)
    mode = f"{companion.flavour.name} {companion.flavour.offboard.name}"
    print(f"quadsr fly: {controller.name} on {trajectory.name} for {duration:g} s through {mode} at "
          f"{args.autopilot}, output in {out}", flush=True)
    for note in getattr(companion, "notes", []):
        print(f"quadsr fly: {note}", flush=True)
    result = companion.fly(out)
    m = result.metrics
    source = "truth" if truth else f"{companion.flavour.name} estimate"
    if m is not None:
        after = "n/a" if m.rms_after_5s_m is None else f"{m.rms_after_5s_m * 1000:.2f} mm"
        print(f"quadsr fly: {result.steps} setpoints, RMS {m.rms_m:.4f} m, RMS after 5 s {after}, final "
              f"{m.final_m * 1000:.2f} mm ({source})", flush=True)
    print(f"quadsr fly: wrote {', '.join(str(p) for p in result.files.values())}", flush=True)
    if result.completed:
        return 0
    print(f"quadsr fly: {result.message}", flush=True)
    if result.crashed:
        return EXIT_CRASHED
    return EXIT_LINK_LOST if result.message.startswith(("link lost", "no HEARTBEAT")) else EXIT_REFUSED


def run_fly(args: argparse.Namespace) -> int:
    """Run `quadsr fly`; returns 0 when flown to the end, 1 after a crash, 3 when the link was lost."""
    from bridge.link import parse_endpoint
    from controller.companion import STATE_SOURCES, Companion, FlightSettings
    from controller.registry import NEEDS_MODEL, check_controller_name, make_controller
    from controller.trajectories import BUILTIN, load_trajectory

    check_controller_name(args.controller)
    if args.state not in STATE_SOURCES:
        raise UserError(f"unknown state source {args.state!r}",
                        hint=f"choose one of {', '.join(STATE_SOURCES)}")
    parse_endpoint(args.hil)
    _positive("--duration", args.duration)
    _positive("--link-timeout", args.link_timeout)
    _positive("--connect-timeout", args.connect_timeout)
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory")
    trajectory = load_trajectory(args.trajectory)
    duration = args.duration or (BUILTIN_DURATION if args.trajectory in BUILTIN else trajectory.duration)
    model = None
    if args.model:
        if args.controller in NEEDS_MODEL:
            from identification.model_file import load_model

            model = load_model(args.model)
        elif not Path(args.model).is_file():
            raise UserError(f"model file {args.model} does not exist")
    vehicle = _vehicle_for(args, model)
    controller = make_controller(args.controller, model, vehicle, args.gains)
    if args.autopilot:
        return _fly_offboard(args, controller, trajectory, vehicle, duration, out)
    settings = FlightSettings(hil=args.hil, duration=duration, state=args.state,
                              link_timeout=args.link_timeout, connect_timeout=args.connect_timeout,
                              progress=not args.no_progress)
    if args.no_takeoff:
        settings = dataclasses.replace(settings, takeoff=None)
    if args.no_governor:
        settings = dataclasses.replace(settings, governor=None)
    print(f"quadsr fly: {controller.name} on {trajectory.name} for {duration:g} s, state from {args.state}, "
          f"SITL at {args.hil}, output in {out}", flush=True)
    describe = getattr(controller, "describe", None)
    if describe is not None:
        print(f"quadsr fly: law: {describe()}", flush=True)
    companion = Companion(controller, trajectory, vehicle, settings)
    result = companion.fly(out)
    if companion.flown is not None:
        from controller.reference_shaping import describe_shaping

        for line in describe_shaping(companion.flown):
            print(f"quadsr fly: {line}", flush=True)
    m = result.metrics
    if m is not None:
        after = "n/a" if m.rms_after_5s_m is None else f"{m.rms_after_5s_m * 1000:.2f} mm"
        settle = "never" if m.settle_time_s is None else f"{m.settle_time_s:.2f} s"
        print(f"quadsr fly: {result.steps} steps, RMS {m.rms_m:.4f} m, RMS after 5 s {after}, "
              f"max {m.max_m:.3f} m, overshoot {m.overshoot_m * 1000:.1f} mm, "
              f"final {m.final_m * 1000:.2f} mm, settled within 5 cm at {settle}, "
              f"control step median {m.step_median_us:.0f} us / p99 {m.step_p99_us:.0f} us", flush=True)
    for text in result.sitl_messages:
        print(f"quadsr fly: warning: the SITL said: {text}", flush=True)
    print(f"quadsr fly: wrote {', '.join(str(p) for p in result.files.values())}", flush=True)
    if result.completed:
        return 0
    if result.crashed:
        print(f"quadsr fly: {result.message}", flush=True)
        return EXIT_CRASHED
    raise UserError(result.message or "the flight stopped early",
                    hint="is the SITL still running? start it with `quadsr sitl`", exit_code=EXIT_LINK_LOST)
