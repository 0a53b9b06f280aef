"""`quadsr identify`, `quadsr validate`, `quadsr model-from-vehicle`: logs to a model file, and its checks."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from bridge.errors import UserError


def register(sub: argparse._SubParsersAction) -> None:
    """Add the identify, validate and model-from-vehicle subcommands."""
    from identification.engine import ENGINE_NAMES

    p = sub.add_parser(
        "identify",
        help="learn the six accelerations from flight logs with symbolic regression -> model.yaml",
        description=(
            "Read one or more flight logs (.tlog, PX4 .ulg, ArduPilot .bin), learn x'', y'', z'' (NED) and "
            "wx', wy', wz' (FRD) as expressions of the 12 states and 4 rotor speeds, and write model.yaml. "
            "Each target gets a Pareto front (complexity against error) from the engine; the final pick is "
            "made on the held-out last part of each flight."
        ),
    )
    p.add_argument("logs", nargs="+", metavar="LOG", help="flight logs (.tlog, .ulg, .bin)")
    p.add_argument("-o", "--out", required=True, metavar="MODEL.yaml", help="model file to write")
    p.add_argument(
        "--engine",
        default="default",
        choices=ENGINE_NAMES,
        help="default: sparse regression, then pyoperon where the library does not explain a target",
    )
    p.add_argument(
        "--budget", type=float, default=60.0, metavar="SECONDS", help="time budget per target (60)"
    )
    p.add_argument("--targets", default=None, metavar="ax,ay,...", help="targets to learn (default: all six)")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="seed (default 0)")
    p.add_argument(
        "--holdout",
        type=float,
        default=0.2,
        metavar="FRACTION",
        help="last fraction of each flight held out for the final pick and validation metrics (0.2)",
    )
    p.add_argument(
        "--loss",
        default="absolute",
        choices=("absolute", "squared"),
        help="absolute (MAE, the paper's fitness) or squared (RMSE)",
    )
    p.add_argument(
        "--targets-from",
        default="truth",
        choices=("truth", "sensors"),
        help="targets from the true state (default) or from the IMU (specific force, gyro derivative)",
    )
    p.add_argument(
        "--motor-curve",
        default=None,
        metavar="VEHICLE|SLOPE,OFFSET",
        help="throttle -> rotor speed for logs without rotor speeds (a vehicle name/file or 'Cr,wb')",
    )
    p.add_argument(
        "--settings",
        default=None,
        metavar="FILE.yaml",
        help="engine settings (YAML, every key optional: sparse, operon, pysr, selection, discovery; see "
        "identification.engine_settings)",
    )
    p.add_argument(
        "--vehicle", default=None, metavar="NAME|FILE", help="vehicle flown, recorded in the model file "
        "(its gravity is used for body-frame learning)"
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.set_defaults(func=run_identify)

    p = sub.add_parser(
        "validate",
        help="Table I (RMSE, MAE, R^2), Fig. 3 and a term comparison of a model on a flight log",
        description=(
            "Evaluate a model file on a flight log: print and write the paper's Table I (table1.md, "
            "table1.csv), "
            "the targets true vs model over time (fig3_targets.png) and, with --reference, each expression "
            "against the reference model's (compare.md, compare.csv: same terms, coefficient errors)."
        ),
    )
    p.add_argument("model", metavar="MODEL", help="model file (quadsr-model/1)")
    p.add_argument("log", metavar="LOG", help="flight log (.tlog, .ulg, .bin)")
    p.add_argument("--out", default="validation", metavar="DIR", help="output folder (default ./validation)")
    p.add_argument(
        "--reference", default=None, metavar="MODEL", help="reference model (e.g. model-from-vehicle)"
    )
    p.add_argument("--targets-from", default="truth", choices=("truth", "sensors"), help="as for identify")
    p.add_argument("--motor-curve", default=None, metavar="VEHICLE|SLOPE,OFFSET", help="as for identify")
    p.set_defaults(func=run_validate)

    p = sub.add_parser(
        "model-from-vehicle",
        help="write the SITL's exact equations for a vehicle as a model file (kind: true-model)",
        description="Write the true model (the SITL's equations of motion) of a vehicle file as model.yaml.",
    )
    p.add_argument(
        "--vehicle",
        default="fang-chen-buaa",
        metavar="NAME|FILE",
        help="bundled vehicle name or vehicle YAML (default fang-chen-buaa)",
    )
    p.add_argument("-o", "--out", required=True, metavar="MODEL.yaml", help="model file to write")
    p.set_defaults(func=run_model_from_vehicle)


def _output_path(text: str, flag: str) -> Path:
    path = Path(text)
    if path.is_dir():
        raise UserError(f"{flag} {text} is a directory", hint="give a file name such as model.yaml")
    parent = path.parent if str(path.parent) else Path(".")
    if parent.exists() and not parent.is_dir():
        raise UserError(f"{flag} {text}: {parent} is not a directory")
    return path


def _load(logs: list[str], targets_from: str, motor_curve: str | None):
    from identification.dataset import Dataset, load_dataset

    datasets = []
    for log in logs:
        d = load_dataset(log, targets=targets_from, motor_curve=motor_curve)
        for w in d.warnings:
            print(f"warning: {log}: {w}", file=sys.stderr)
        if d.dropped_rows:
            print(f"{log}: dropped {d.dropped_rows} rows", file=sys.stderr)
        if len(d) == 0:
            raise UserError(f"flight log {log} gave no usable rows", hint="check the log holds a flight")
        datasets.append(d)
    return datasets[0] if len(datasets) == 1 else Dataset.concat(datasets)


def run_identify(args: argparse.Namespace) -> int:
    """Identify the model and write it."""
    from identification.body_frame import STANDARD_GRAVITY
    from identification.engine_settings import load_engine_settings
    from identification.identify import identify, parse_targets
    from identification.model_file import save_model
    from identification.validate import table_markdown

    targets = parse_targets(args.targets)
    if not (math.isfinite(args.budget) and args.budget > 0):
        raise UserError(f"--budget must be a positive number of seconds, got {args.budget}")
    if not (0.0 < args.holdout < 1.0):
        raise UserError(f"--holdout must be a fraction between 0 and 1, got {args.holdout}")
    if args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    out = _output_path(args.out, "-o")
    settings = load_engine_settings(args.settings)
    if args.engine == "pysr":
        from identification.pysr_engine import require_pysr

        require_pysr(settings.pysr.probe_timeout_s)  # fail before reading the logs
    vehicle = None
    gravity = STANDARD_GRAVITY  # body-frame learning removes it; the vehicle's when given
    if args.vehicle:
        from bridge.vehicle import load_vehicle
        from identification.true_model import vehicle_provenance

        flown = load_vehicle(args.vehicle)
        vehicle, gravity = vehicle_provenance(flown), flown.gravity
    dataset = _load(args.logs, args.targets_from, args.motor_curve)
    print(
        f"{len(dataset)} rows from {len(args.logs)} log(s); engine {args.engine}, budget {args.budget:g} s "
        f"per target, seed {args.seed}",
        file=sys.stderr,
    )
    model = identify(
        dataset,
        engine=args.engine,
        targets=targets,
        budget_s=args.budget,
        seed=args.seed,
        holdout=args.holdout,
        loss=args.loss,
        settings=settings,
        vehicle=vehicle,
        progress=not args.no_progress,
        gravity=gravity,
    )
    save_model(model, out)
    metrics = {n: t.metrics.get("validation", t.metrics.get("train")) for n, t in model.targets.items()}
    print(f"held-out metrics ({args.holdout:.0%} of each flight):")
    print(table_markdown(metrics), end="")
    for name, t in model.targets.items():
        print(f"{name} = {t.expression}")
    print(f"wrote {out}")
    return 0


def run_validate(args: argparse.Namespace) -> int:
    """Validate a model on a log; print Table I (and the comparison)."""
    from identification.model_file import load_model
    from identification.validate import comparison_markdown, table_markdown, validate

    model = load_model(args.model)
    reference = load_model(args.reference) if args.reference else None
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory", hint="give a folder for the outputs")
    dataset = _load([args.log], args.targets_from, args.motor_curve)
    report = validate(model, dataset, out, reference)
    print(f"Table I: {args.model} on {args.log} ({len(dataset)} rows)")
    print(table_markdown(report.metrics), end="")
    if report.comparisons is not None:
        print(f"\nagainst the reference {args.reference}:")
        print(comparison_markdown(report.comparisons), end="")
    written = [report.table_md, report.table_csv, report.figure]
    if report.compare_md:
        written += [report.compare_md, report.compare_csv]
    print("wrote " + ", ".join(str(p) for p in written))
    return 0


def run_model_from_vehicle(args: argparse.Namespace) -> int:
    """Write the vehicle's true model."""
    from identification.true_model import write_true_model

    out = _output_path(args.out, "-o")
    path = write_true_model(args.vehicle, out)
    print(f"wrote {path} (true model of {args.vehicle})")
    return 0
