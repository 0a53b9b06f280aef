"""`quadsr px4-airframe` (a PX4 airframe matched to a vehicle) and `quadsr px4` (real PX4 flying the SITL)."""

from __future__ import annotations

import argparse
import math
import signal
import sys
import time
from pathlib import Path

from bridge.errors import UserError

DEFAULT_PX4 = "../shared/px4"
CONNECTED = "autopilot connected"
READY = "Ready for takeoff"
DISCONNECTED = "autopilot disconnected"
NOTICE_S = 5.0  # wall s the SITL gets to log PX4's dropped link before it is stopped


def register(sub: argparse._SubParsersAction) -> None:
    """Add the px4-airframe and px4 subcommands."""
    p = sub.add_parser(
        "px4-airframe", help="write a PX4 airframe file matched to a quadsr vehicle",
        description="Writes a PX4 airframe (init script) for the vehicle: rotor positions and moment ratios "
                    "(CA_ROTOR*), the thrust model fitted to the motor curve (THR_MDL_FAC), the hover thrust "
                    "(MPC_THR_HOVER) and limits matched to the thrust-to-weight ratio. Put it in PX4's "
                    "etc/init.d-posix/airframes as <id>_none_quadsr_<vehicle> and start PX4 with "
                    "PX4_SIM_MODEL=none_quadsr_<vehicle> (quadsr px4 does this for you).")
    p.add_argument("--vehicle", default="fang-chen-buaa", metavar="NAME|FILE",
                   help="vehicle YAML file or bundled name (default fang-chen-buaa)")
    p.add_argument("-o", "--out", type=Path, required=True, metavar="FILE", help="airframe file to write")
    p.set_defaults(func=_airframe)

    p = sub.add_parser(
        "px4", help="run real PX4 SITL flying quadsr's simulated vehicle (like make px4_sitl for Gazebo)",
        description="Starts quadsr's SITL listening on tcp:127.0.0.1:4560+N and PX4 SITL instance N from a "
                    "PX4 build (bin/px4 and etc/) with an airframe matched to the vehicle, prints the "
                    "MAVLink ports for QGroundControl, MAVSDK and MAVProxy, and runs until Ctrl-C or SIGTERM "
                    "(both stopped; PX4 also dies if this process is killed). Exit 0 after Ctrl-C/SIGTERM, "
                    "1 if PX4 does not connect or either process stops by itself.")
    p.add_argument("--px4", default=DEFAULT_PX4, metavar="DIR",
                   help=f"PX4 SITL build folder with bin/px4 and etc/ (default {DEFAULT_PX4})")
    p.add_argument("--vehicle", default="fang-chen-buaa", metavar="NAME|FILE",
                   help="vehicle YAML file or bundled name (default fang-chen-buaa)")
    p.add_argument("--instance", default="0", metavar="N|FIRST-LAST",
                   help="PX4 instance: simulator tcp 4560+N, GCS udp 18570+N, offboard udp 14580+N, "
                        "system id N+1 (default 0); FIRST-LAST: the first free one in that range (held, so "
                        "runs started at once take different ones)")
    p.add_argument("--work", type=Path, default=None, metavar="DIR",
                   help="work folder: PX4's ROMFS copy, parameters, ULogs (rootfs/log), truth.tlog, logs "
                        "(default quadsr-px4-N in the current folder)")
    p.add_argument("--sensors", choices=("realistic", "ideal"), default=None,
                   help="sensor noise preset of the SITL (default: the vehicle file's)")
    p.add_argument("--seed", type=int, default=None, help="sensor noise seed (default: the vehicle file's)")
    p.add_argument("--mode", choices=("lockstep", "realtime"), default="lockstep",
                   help="lockstep: as fast as PX4 answers (default); realtime: lockstep at most as fast as "
                        "the wall clock, for an offboard companion or a person at QGroundControl")
    p.add_argument("--max-rtf", type=float, default=None, metavar="R",
                   help="lockstep at most R times real time (realtime is 1). PX4's estimators (three EKF2 "
                        "instances in SITL) are not part of its lockstep: at full speed on a loaded machine "
                        "they fall behind and their start-up differs from run to run; a limit leaves them "
                        "room (default: none in lockstep)")
    p.add_argument("--connect-timeout", type=float, default=60.0, metavar="S",
                   help="wall seconds PX4 gets to connect to the simulator (default 60)")
    p.add_argument("--lockstep-timeout", type=float, default=5.0, metavar="S",
                   help="wall seconds the SITL waits for PX4's reply before its failsafe (default 5)")
    p.set_defaults(func=_px4)


def _airframe(args: argparse.Namespace) -> int:
    from bridge.vehicle import load_vehicle
    from quadsr.px4_airframe import AIRFRAME_ID, airframe_for

    vehicle = load_vehicle(args.vehicle)
    frame = airframe_for(vehicle)
    source = str(vehicle.source_path or vehicle.name)
    out = Path(args.out)
    if out.is_dir():
        raise UserError(f"-o {out} is a directory", hint=f"give a file name such as {frame.file_name()}")
    try:
        out.write_text(frame.text(source))
    except OSError as exc:
        raise UserError(f"cannot write {out}: {exc.strerror}") from None
    print(f"quadsr px4-airframe: wrote {out} (thrust-to-weight {frame.thrust_to_weight:.2f}, THR_MDL_FAC "
          f"{frame.params['THR_MDL_FAC']}, MPC_THR_HOVER {frame.params['MPC_THR_HOVER']}); install it as "
          f"etc/init.d-posix/airframes/{frame.file_name(AIRFRAME_ID)} and run PX4 with "
          f"PX4_SIM_MODEL={frame.model_name()}")
    return 0


def _px4(args: argparse.Namespace) -> int:
    from bridge.vehicle import load_vehicle
    from quadsr.px4_airframe import airframe_for
    from quadsr.px4_launch import Px4Ports, Px4Process, check_build, claim_free_instance, prepare_work
    from quadsr.sitl_process import SitlProcess

    first, last = _instance_range(args.instance)
    timeouts = (("--connect-timeout", args.connect_timeout), ("--lockstep-timeout", args.lockstep_timeout))
    for flag, value in timeouts:
        if not value > 0:
            raise UserError(f"{flag} must be a positive number of seconds, got {value}")
    if args.max_rtf is not None and not (math.isfinite(args.max_rtf) and args.max_rtf > 0):
        raise UserError(f"--max-rtf must be a positive number, got {args.max_rtf}")
    if args.max_rtf is not None and args.mode == "realtime":
        raise UserError("--max-rtf and --mode realtime both set the pace",
                        hint="give one of them (realtime is --max-rtf 1)")
    build = check_build(Path(args.px4))
    vehicle = load_vehicle(args.vehicle)
    try:
        args.instance, held = claim_free_instance(first, last)  # held until this process ends
    except UserError:
        if first != last:
            raise
        ports = Px4Ports(first)
        raise UserError(
            f"ports of PX4 instance {first} are in use (tcp {ports.simulator}, udp "
            f"{', '.join(map(str, ports.udp_local))}) or another quadsr px4 holds it",
            hint="is another PX4 or simulator running? pick another --instance, or a range: --instance 1-9",
        ) from None
    ports = Px4Ports(args.instance)
    _say(f"using PX4 instance {args.instance}")
    work = (args.work or Path(f"quadsr-px4-{args.instance}")).resolve()
    tree = prepare_work(build, work, airframe_for(vehicle), str(vehicle.source_path or vehicle.name))
    sitl_args = ["--vehicle", str(vehicle.source_path or vehicle.name), "--companion-sysid",
                 str(ports.system_id()), "--lockstep-timeout", str(args.lockstep_timeout),
                 "--log", str(work / "truth.tlog")]
    max_rtf = 1.0 if args.mode == "realtime" else args.max_rtf
    if max_rtf is not None:
        sitl_args += ["--max-rtf", f"{max_rtf:g}"]
    if args.sensors:
        sitl_args += ["--sensors", args.sensors]
    if args.seed is not None:
        sitl_args += ["--seed", str(args.seed)]
    stop = {"signal": None}

    def on_signal(signum, frame) -> None:
        stop["signal"] = signum

    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    sitl = SitlProcess(sitl_args, log_path=work / "sitl.log", hil=f"tcp:127.0.0.1:{ports.simulator}")
    px4 = None
    try:
        sitl.start()
        px4 = Px4Process(tree, args.instance, work / "px4.log")
        _say(f"started PX4 (pid {px4.proc.pid}) and the SITL (pid {sitl.proc.pid}); waiting for PX4 to "
             "connect")
        return _supervise(args, ports, work, tree.model, sitl, px4, stop)
    finally:
        if px4 is not None:
            px4.stop()
        sitl.stop()
        for s, handler in previous.items():
            signal.signal(s, handler)
        print("quadsr px4: PX4 and the SITL stopped", flush=True)


def _supervise(args, ports, work: Path, model: str, sitl, px4, stop: dict) -> int:
    """Wait for PX4 to connect, print the ports, then run until a signal or a child stops."""
    say = _say
    deadline = time.monotonic() + args.connect_timeout
    while not any(CONNECTED in line for line in sitl.output):
        if stop["signal"] is not None:
            return 0
        if px4.proc.poll() is not None:
            say(f"error: PX4 exited (code {px4.proc.returncode}) before it connected to the simulator; "
                f"its last output ({work / 'px4.log'}):\n{px4.tail()}", err=True)
            return 1
        if time.monotonic() > deadline:
            say(f"error: PX4 did not connect to the simulator on tcp:127.0.0.1:{ports.simulator} within "
                f"{args.connect_timeout:g} s; its last output ({work / 'px4.log'}):\n{px4.tail()}", err=True)
            return 1
        time.sleep(0.05)
    n = ports.instance
    say(f"PX4 instance {n} (system id {ports.system_id()}, airframe {model}) is flying quadsr's SITL "
        f"on tcp:127.0.0.1:{ports.simulator}. MAVLink:\n"
        f"  QGroundControl: PX4 sends to udp 14550 (QGC's default) from 127.0.0.1:{ports.gcs}\n"
        f"  MAVSDK:         udpin://0.0.0.0:{ports.offboard_remote} (PX4's offboard link, local port "
        f"{ports.offboard})\n"
        f"  MAVProxy:       mavproxy.py --master=udpout:127.0.0.1:{ports.gcs}\n"
        f"  quadsr fly:     --autopilot udp:127.0.0.1:{ports.offboard}\n"
        f"  logs:           ULogs in {work / 'rootfs' / 'log'}, truth {work / 'truth.tlog'}, "
        f"{work / 'px4.log'}, {work / 'sitl.log'}\n"
        f"Ctrl-C stops both.")
    ready_said = False
    while stop["signal"] is None:
        if not ready_said and any(READY in line for line in px4.lines):
            say("PX4 is ready for takeoff")
            ready_said = True
        if px4.proc.poll() is not None:
            # The SITL's log should say why its vehicle stopped: wait (bounded) for it to see the link drop.
            deadline = time.monotonic() + NOTICE_S
            while (not any(DISCONNECTED in line for line in sitl.output) and sitl.proc.poll() is None
                   and time.monotonic() < deadline):
                time.sleep(0.05)
            say(f"error: PX4 exited (code {px4.proc.returncode}); stopping the SITL. Its last output "
                f"({work / 'px4.log'}):\n{px4.tail()}", err=True)
            return 1
        if sitl.proc.poll() is not None:
            say(f"error: the SITL exited (code {sitl.proc.returncode}); stopping PX4. Its last output "
                f"({work / 'sitl.log'}):\n{''.join(sitl.output[-10:])}", err=True)
            return 1
        time.sleep(0.1)
    say(f"stopping on {signal.Signals(stop['signal']).name}")
    return 0


def _instance_range(text: str) -> tuple[int, int]:
    """--instance N or FIRST-LAST as (first, last), each in 0..200; UserError otherwise."""
    parts = str(text).split("-")
    if len(parts) not in (1, 2) or not all(p.strip().isdigit() for p in parts):
        raise UserError(f"--instance must be a number N or a range FIRST-LAST, got {text!r}")
    first, last = int(parts[0]), int(parts[-1])
    if not 0 <= first <= last <= 200:
        raise UserError(f"--instance must be within 0..200 (FIRST <= LAST), got {text}")
    return first, last


def _say(text: str, err: bool = False) -> None:
    print(f"quadsr px4: {text}", file=sys.stderr if err else sys.stdout, flush=True)
