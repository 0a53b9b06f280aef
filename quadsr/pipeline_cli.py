"""Whole-pipeline subcommands: `quadsr paper` (the paper end to end) and `quadsr hover-check` (a hover)."""

from __future__ import annotations

import argparse
import shlex
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    """Add the pipeline subcommands to the quadsr parser."""
    p = sub.add_parser("hover-check", help="start a SITL, take off over MAVLink, and check the hover",
                       formatter_class=argparse.ArgumentDefaultsHelpFormatter,
                       description="Starts `quadsr sitl` as a child process on free ports (lockstep), takes "
                                   "off to --altitude and holds it, and checks the hold: RMS altitude error "
                                   "< 2 cm, tilt < 0.01 rad, final speed < 2 cm/s. Exit 0 when it passes.")
    p.add_argument("--vehicle", default="fang-chen-buaa", help="vehicle name or YAML file")
    p.add_argument("--altitude", type=float, default=2.0, help="hover altitude above the ground [m]")
    p.add_argument("--duration", type=float, default=10.0, help="flight time [s, simulated]")
    p.add_argument("--out", type=Path, default=None, help="folder for hover.tlog and sitl.log")
    p.set_defaults(func=_hover_check)

    p = sub.add_parser(
        "paper", help="the paper end to end: excite, identify, validate, fly Case I and II -> report.md",
        description="Starts `quadsr sitl` children (lockstep, free ports) as it needs them, flies the "
                    "paper-train and paper-validate excitations, identifies the model (default engine), "
                    "validates it against the true model, flies Case I and II with backstepping on the "
                    "learned and on the true model, the PID cascade and SE(3), and writes report.md (Table I "
                    "and the equations beside the paper's, the tracking table, stage wall times, versions), "
                    "the figures (PNG), model.yaml, true-model.yaml, every .tlog and the metrics (CSV) to "
                    "--out. Exit 0 when every stage ran; 1 when a stage failed (report.md then holds what "
                    "completed), 130 on Ctrl-C.")
    p.add_argument("--out", type=Path, default=Path("results"), metavar="DIR",
                   help="output folder (default results/)")
    p.add_argument("--quick", action="store_true",
                   help="smaller budgets: 16 s paper-train (1000 samples per speed group), SR budget 10 "
                        "generations per target, 12 s tracking flights (default: 32 s, 60, 20 s)")
    p.add_argument("--seed", type=int, default=0, metavar="N",
                   help="seed of every random draw: excitation, SR engine, SITL (default 0)")
    p.add_argument("--vehicle", default="fang-chen-buaa", metavar="NAME|FILE",
                   help="vehicle flown and modelled (default fang-chen-buaa, the paper's)")
    p.set_defaults(func=_paper)


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


def _paper(args: argparse.Namespace) -> int:
    from quadsr.pipeline import StageFailed, StageInterrupted, prepare_run, run_paper
    from quadsr.report import checks, tracking_markdown

    command = "quadsr " + " ".join(shlex.quote(a) for a in sys.argv[1:]) if sys.argv[1:] else "quadsr paper"
    run = prepare_run(args.out, args.seed, args.quick, args.vehicle, command)
    print(f"quadsr paper: seed {run.seed}, {run.settings.describe()}; output in {run.out}", flush=True)
    report = run.out / "report.md"
    try:
        run_paper(run)
    except StageFailed as exc:
        print(f"quadsr paper: {exc}", file=sys.stderr, flush=True)
        print(f"quadsr paper: what completed is in {report}", file=sys.stderr, flush=True)
        return 1
    except StageInterrupted as exc:
        print(f"quadsr paper: {exc}; every SITL child stopped; what completed is in {report}",
              file=sys.stderr, flush=True)
        return exc.exit_code
    if run.validation is not None:
        from identification.validate import table_markdown

        print("\nTable I on the validation flight (ours beside the paper's):\n")
        print(table_markdown(run.validation.metrics, paper=True))
    print(tracking_markdown(run.tracking))
    for what, ok in checks(run):
        print(f"{'PASS' if ok else 'FAIL'}: {what}")
    print(f"\nquadsr paper: done in {run.total_wall_s:.1f} s; report: {report}", flush=True)
    return 0
