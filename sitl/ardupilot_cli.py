"""`quadsr ardupilot-params` and `quadsr ardupilot`: ArduCopter set up for, and flown against, the SITL."""

from __future__ import annotations

import argparse
from pathlib import Path

from bridge.errors import UserError

DEFAULT_VEHICLE = "fang-chen-buaa"
DEFAULT_ARDUPILOT_DIR = "../shared/ardupilot"


def register(subparsers: argparse._SubParsersAction) -> None:
    """Add the `ardupilot-params` and `ardupilot` subcommands."""
    p = subparsers.add_parser(
        "ardupilot-params",
        help="write ArduCopter parameters matched to a quadsr vehicle (.parm)",
        description="Write FRAME_CLASS/TYPE, MOT_THST_EXPO (fitted to the vehicle's thrust curve), "
                    "MOT_THST_HOVER, MOT_SPIN_ARM/MIN, MOT_PWM_MIN/MAX and battery parameters, for "
                    "arducopter --defaults.",
    )
    p.add_argument("--vehicle", default=DEFAULT_VEHICLE, metavar="FILE|NAME",
                   help=f"vehicle YAML file or bundled name (default {DEFAULT_VEHICLE})")
    p.add_argument("-o", "--output", required=True, metavar="FILE.parm", help="the parameter file to write")
    p.set_defaults(func=run_params)

    p = subparsers.add_parser(
        "ardupilot",
        help="start ArduCopter SITL and quadsr's simulator as its JSON physics (like sim_vehicle.py)",
        description="Start quadsr's SITL as ArduPilot's JSON physics and the real ArduCopter SITL stepping "
                    "it in lockstep; print the MAVLink ports; stop both on Ctrl-C or SIGTERM, or when either "
                    "exits. ArduCopter runs as a child that exits with this process.",
    )
    p.add_argument("--ardupilot", default=DEFAULT_ARDUPILOT_DIR, metavar="DIR",
                   help=f"folder holding arducopter, copter.parm and copter-X.parm (default "
                        f"{DEFAULT_ARDUPILOT_DIR})")
    p.add_argument("--vehicle", default=DEFAULT_VEHICLE, metavar="FILE|NAME",
                   help=f"vehicle YAML file or bundled name (default {DEFAULT_VEHICLE})")
    p.add_argument("-I", "--instance", type=int, default=0, metavar="N",
                   help="ArduPilot instance 0..255: ports + 10*N (MAVLink TCP 5760+10N, JSON UDP 9002+10N)")
    p.add_argument("--speedup", type=float, default=1.0, metavar="X",
                   help="ArduPilot's --speedup: simulated seconds per wall second it aims for (default 1)")
    p.add_argument("--workdir", default=None, metavar="DIR",
                   help="ArduPilot's working folder (eeprom.bin, logs/); default ardupilot-I<N> here")
    p.add_argument("--log", default=None, metavar="FILE.tlog", help="the SITL's truth .tlog")
    p.add_argument("--sensors", choices=("realistic", "ideal"), default=None,
                   help="sensor noise preset (default: the vehicle file's)")
    p.add_argument("--seed", type=int, default=None, help="sensor noise seed (default: the vehicle file's)")
    p.add_argument("--param", action="append", default=[], metavar="FILE.parm",
                   help="extra ArduCopter parameter files, applied after the vehicle's (repeatable)")
    p.add_argument("--wipe", action="store_true", help="start ArduPilot from its defaults (-w: new eeprom)")
    p.set_defaults(func=run_launcher)


def run_params(args: argparse.Namespace) -> int:
    """Write the .parm file and print how its values were derived."""
    from bridge.vehicle import load_vehicle
    from sitl.ardupilot_params import write_parm

    out = Path(args.output)
    if out.is_dir():
        raise UserError(f"-o {out} is a directory", hint="give a file name such as quad.parm")
    notes = write_parm(load_vehicle(args.vehicle), out)
    for note in notes:
        print(f"quadsr ardupilot-params: {note}")
    print(f"quadsr ardupilot-params: wrote {out}")
    return 0


def run_launcher(args: argparse.Namespace) -> int:
    """Run ArduCopter and the SITL until Ctrl-C/SIGTERM or until one of them exits."""
    from sitl.ardupilot_launcher import Launcher, launcher_options

    return Launcher(launcher_options(args)).run()
