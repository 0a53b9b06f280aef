"""`quadsr identify`, `quadsr validate`, `quadsr model-from-vehicle`: logs to a model file, and its checks."""

from __future__ import annotations

import argparse
import math
import sys
from pathlib import Path

from bridge.errors import UserError

EXIT_BELOW_THRESHOLD = 4  # quadsr identify --strict: a target's validation R^2 is below the threshold


def register(sub: argparse._SubParsersAction) -> None:
    """Add the identify, validate and model-from-vehicle subcommands."""
    from identification.engine import ENGINE_HELP, ENGINE_NAMES

    p = sub.add_parser(
        "identify",
        help="learn the six accelerations from flight logs with symbolic regression -> model.yaml",
        description=(
            "Read one or more flight logs (.tlog, PX4 .ulg, ArduPilot .bin), learn x'', y'', z'' (NED) and "
            "wx', wy', wz' (FRD) as expressions of the 12 states and 4 rotor speeds, and write model.yaml. "
            "Each target gets a Pareto front (complexity against error) from the engine fitted on the 'fit' "
            "rows; the final pick uses the 'pick' rows and the reported validation the 'validate' rows, used "
            "for neither: whole flights (--pick-log, --validate-log) or time blocks of each flight "
            "(fit | gap | pick | gap | validate). model.yaml records which file, time range and sha256 did "
            "what, the terms this flight cannot identify (collinear regressors) and the targets whose "
            "validation R^2 is below --r2-threshold. Exit codes: 0 done, 2 bad input, "
            f"{EXIT_BELOW_THRESHOLD} with --strict when a target is below the threshold (model.yaml is still "
            "written)."
        ),
    )
    p.add_argument("logs", nargs="+", metavar="LOG", help="flight logs (.tlog, .ulg, .bin)")
    p.add_argument("-o", "--out", required=True, metavar="MODEL.yaml", help="model file to write")
    p.add_argument(
        "--engine",
        default="default",
        choices=ENGINE_NAMES,
        help=ENGINE_HELP,
    )
    p.add_argument(
        "--budget",
        type=int,
        default=60,
        metavar="GENERATIONS",
        help="genetic-programming generations per target (60; PySR: iterations): an iteration budget, "
        "so a seed gives the same model on any machine",
    )
    p.add_argument("--targets", default=None, metavar="ax,ay,...", help="targets to learn (default: all six)")
    p.add_argument("--seed", type=int, default=0, metavar="N", help="seed (default 0)")
    p.add_argument(
        "--holdout",
        type=float,
        default=0.2,
        metavar="FRACTION",
        help="fraction of each flight's time used to pick among the candidates (0.2), unless --pick-log",
    )
    p.add_argument(
        "--validate-fraction",
        type=float,
        default=0.2,
        metavar="FRACTION",
        help="fraction of each flight's time used only for validation (0.2), unless --validate-log",
    )
    p.add_argument(
        "--gap",
        type=float,
        default=None,
        metavar="SECONDS",
        help="time left out between the fit, pick and validate blocks of a flight (default and minimum: "
        "the longest differentiator window, 0.4 s)",
    )
    p.add_argument(
        "--pick-blocks",
        type=int,
        default=1,
        metavar="N",
        help="spread each flight's pick time over N blocks (fit | gap | pick | gap | fit ...), so the pick "
        "weighs the whole flight, not its last part (default 1: one block before the validation block)",
    )
    p.add_argument(
        "--pick-log",
        action="append",
        default=None,
        metavar="LOG",
        help="a different flight to pick the model on (repeatable); then no pick block is cut from LOGs",
    )
    p.add_argument(
        "--validate-log",
        action="append",
        default=None,
        metavar="LOG",
        help="a different flight to validate on (repeatable); then no validate block is cut from LOGs",
    )
    p.add_argument(
        "--r2-threshold",
        type=float,
        default=0.9,
        metavar="R2",
        help="a target whose validation R^2 is below this is flagged in model.yaml and here (0.9)",
    )
    p.add_argument(
        "--strict",
        action="store_true",
        help=f"exit {EXIT_BELOW_THRESHOLD} when any target's validation R^2 is below --r2-threshold",
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
        "--weak",
        action=argparse.BooleanOptionalAction,
        default=None,
        help="weak (integral) form: data and model integrated against test functions (1 - s^2)^4 over "
        "+-T windows, the sensor targets as raw as possible (specific force as measured, the gyro's "
        "5-sample derivative), every loss and R^2 on the weak rows; default engine only. Default: on with "
        "--targets-from sensors and the default engine, off otherwise (--no-weak turns it off)",
    )
    p.add_argument(
        "--weak-window", type=float, default=None, metavar="T",
        help="half window T of the weak form's test functions, s (default 0.2)",
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
    p.add_argument(
        "--gravity", type=float, default=None, metavar="G",
        help="the data's gravity, m/s^2 (default: the --vehicle's, else 9.80665), removed by body-frame "
        "learning: give a simulator's (RotorPy and jMAVSim: 9.81)"
    )
    _add_row_options(p)
    p.add_argument(
        "--report",
        default=None,
        metavar="DIR",
        help="model report folder (report.md, fit.png); default: <MODEL>_report beside the model file",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bars")
    p.add_argument("--jobs", type=int, default=None, metavar="N",
                   help="targets fitted side by side in up to N processes (default: every core this process "
                        "may use); the model is the same for any N, only the wall time changes")
    fleet = p.add_argument_group("fleets of logs (one model per log, on a Dask cluster)")
    fleet.add_argument("--fleet", action="store_true",
                       help="identify each log on its own (LOG may be a folder or a glob); -o is then the "
                            "output folder of fleet.csv, fleet_terms.csv and models/")
    fleet.add_argument("--workers", type=int, default=2, metavar="N", help="local Dask worker processes (2)")
    fleet.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="an existing Dask scheduler instead of a local cluster")
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
    p.add_argument("--weak", action=argparse.BooleanOptionalAction, default=None,
                   help="Table I in the weak form, as identify (default: on with --targets-from sensors)")
    p.add_argument("--weak-window", type=float, default=None, metavar="T", help="as for identify")
    _add_row_options(p)
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


def _add_row_options(p: argparse.ArgumentParser) -> None:
    """--window and --all-rows: which rows of the logs to use."""
    p.add_argument(
        "--window",
        action="append",
        default=None,
        metavar="START:END",
        help="keep only rows between START and END seconds of log time (repeatable; replaces the "
        "automatic airborne detection)",
    )
    p.add_argument(
        "--all-rows",
        action="store_true",
        help="no airborne detection: keep every complete row (ground rows too)",
    )
    p.add_argument(
        "--rate",
        type=float,
        default=None,
        metavar="HZ",
        help="rate of the common timeline every topic is interpolated onto (default: the log's natural one, "
        "e.g. ATT's for DataFlash)",
    )


def _weak_settings(args: argparse.Namespace):
    """WeakSettings from --weak/--no-weak and --weak-window (None: point targets). Default: on with
    --targets-from sensors (measured better there: README, "Targets"), off otherwise. Sets args.weak."""
    from identification.weak_form import WeakSettings

    if args.weak is None:
        args.weak = args.targets_from == "sensors" or args.weak_window is not None
    if not args.weak:
        return None
    weak = WeakSettings() if args.weak_window is None else WeakSettings(half_window_s=args.weak_window)
    weak.check()
    return weak


def _output_path(text: str, flag: str) -> Path:
    path = Path(text)
    if path.is_dir():
        raise UserError(f"{flag} {text} is a directory", hint="give a file name such as model.yaml")
    parent = path.parent if str(path.parent) else Path(".")
    if parent.exists() and not parent.is_dir():
        raise UserError(f"{flag} {text}: {parent} is not a directory")
    return path


def _load(
    logs: list[str], targets_from: str, motor_curve: str | None, args: argparse.Namespace | None = None,
    gravity: float | None = None,
):
    """Read, segment and join the logs, printing what was kept and every reason rows were dropped; gravity
    (m/s^2): what sensor targets add to the rotated specific force (the body-frame learning removes the
    same; default 9.80665)."""
    from identification.dataset import load_datasets
    from identification.segmentation import parse_window
    from identification.weak_form import RAW_SENSOR_TARGETS

    windows = [parse_window(w) for w in (getattr(args, "window", None) or [])]
    airborne = not getattr(args, "all_rows", False)
    dataset = load_datasets(
        logs, windows=windows or None, targets=targets_from, motor_curve=motor_curve, airborne=airborne,
        rate_hz=getattr(args, "rate", None), gravity=gravity,
        sensor_settings=RAW_SENSOR_TARGETS if getattr(args, "weak", False) and targets_from == "sensors"
        else None,
    )
    for line in dataset.segments:
        print(line, file=sys.stderr)
    print(dataset.summary(), file=sys.stderr)
    return dataset


def run_fleet(args: argparse.Namespace) -> int:
    """quadsr identify --fleet: one identification per log on a Dask cluster; the fleet tables."""
    from identification.fleet import FleetSettings, expand_logs, identify_fleet

    if args.budget < 1:
        raise UserError(f"--budget must be a positive number of generations, got {args.budget}")
    if args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"-o {args.out} is a file", hint="with --fleet, -o names the output folder")
    logs = expand_logs(args.logs)
    settings = FleetSettings(args.targets_from, args.motor_curve, args.engine, args.budget, args.seed)
    print(f"fleet: {len(logs)} logs -> {out}", file=sys.stderr, flush=True)
    rows = identify_fleet(logs, out, settings, workers=args.workers, scheduler=args.scheduler)
    ok = sum(r["status"] == "ok" for r in rows)
    print(f"fleet: {ok} of {len(rows)} logs identified; wrote {out / 'fleet.csv'}, {out / 'fleet_terms.csv'}")
    return 0 if ok == len(rows) else 1


def run_identify(args: argparse.Namespace) -> int:
    """Identify the model and write it (or, with --fleet, one model per log and the fleet tables)."""
    if args.fleet:
        return run_fleet(args)
    from identification.body_frame import STANDARD_GRAVITY
    from identification.data_roles import DEFAULT_GAP_S, assign_roles
    from identification.engine_settings import load_engine_settings
    from identification.identify import identify, parse_targets
    from identification.model_file import save_model
    from identification.target_pool import default_jobs
    from identification.validate import table_markdown

    targets = parse_targets(args.targets)
    if args.budget < 1:
        raise UserError(f"--budget must be a whole number of generations >= 1, got {args.budget}")
    if args.pick_blocks < 1:
        raise UserError(f"--pick-blocks must be a whole number >= 1, got {args.pick_blocks}",
                        hint="1 (the default): one pick block; 5: five blocks spread over each flight")
    for flag, value in (("--holdout", args.holdout), ("--validate-fraction", args.validate_fraction)):
        if not (0.0 < value < 1.0):
            raise UserError(f"{flag} must be a fraction between 0 and 1, got {value}")
    gap = DEFAULT_GAP_S if args.gap is None else args.gap
    if not (math.isfinite(gap) and gap >= DEFAULT_GAP_S):
        raise UserError(
            f"--gap must be at least {DEFAULT_GAP_S:g} s (the longest differentiator window), got {args.gap}",
            hint="blocks closer than one window share samples through the targets' filters",
        )
    if not (math.isfinite(args.r2_threshold) and args.r2_threshold <= 1.0):
        raise UserError(f"--r2-threshold must be a number <= 1, got {args.r2_threshold}")
    if args.seed < 0:
        raise UserError(f"--seed must be >= 0, got {args.seed}")
    out = _output_path(args.out, "-o")
    settings = load_engine_settings(args.settings)
    if args.engine == "pysr":
        from identification.pysr_engine import require_pysr

        require_pysr(settings.pysr.probe_timeout_s)  # fail before reading the logs
    vehicle = vehicle_config = None
    gravity = STANDARD_GRAVITY  # body-frame learning removes it; the vehicle's when given
    if args.vehicle:
        from bridge.vehicle import load_vehicle
        from identification.true_model import vehicle_provenance

        vehicle_config = load_vehicle(args.vehicle)
        vehicle, gravity = vehicle_provenance(vehicle_config), vehicle_config.gravity
    given_g = getattr(args, "gravity", None)
    if given_g is not None:
        if args.vehicle:
            raise UserError("--gravity and --vehicle both give the gravity",
                            hint="drop --gravity: the vehicle file's gravity is used")
        if not (math.isfinite(given_g) and 1.0 <= given_g <= 30.0):
            raise UserError(f"--gravity {given_g:g}: not a gravity in m/s^2 (1 to 30)",
                            hint="give the data's g, e.g. --gravity 9.81")
        gravity = float(given_g)
    if args.weak is None and args.engine not in ("default", "discovery"):
        args.weak = False
    weak = _weak_settings(args)
    if weak is not None:
        if args.engine not in ("default", "discovery"):
            raise UserError(f"--weak needs the default (discovery) engine, not {args.engine}",
                            hint="drop --weak or use --engine default")
    # sensor targets add the gravity the body-frame learning removes: the vehicle's (its accelerometer
    # measures a - g with that g), else the standard one
    dataset = _load(args.logs, args.targets_from, args.motor_curve, args, gravity)
    pick = _load(args.pick_log, args.targets_from, args.motor_curve, args, gravity) if args.pick_log else None
    check = (_load(args.validate_log, args.targets_from, args.motor_curve, args, gravity)
             if args.validate_log else None)

    def split_roles():
        return assign_roles(dataset, pick=pick, validate=check, pick_fraction=args.holdout,
                            validate_fraction=args.validate_fraction, gap_s=gap, pick_blocks=args.pick_blocks)

    motor = None
    if args.motor_curve is None:
        from identification.motor_model import apply_thrust_curve, choose_motor_model

        motor, why = choose_motor_model(split_roles().fit)  # chosen on the fit rows only
        if motor is not None:
            dataset = apply_thrust_curve(dataset, motor)
            pick = apply_thrust_curve(pick, motor) if pick is not None else None
            check = apply_thrust_curve(check, motor) if check is not None else None
        if why:
            print(why, file=sys.stderr)
    print(
        f"{len(dataset)} rows from {len(args.logs)} log(s); engine {args.engine}, budget {args.budget} "
        f"generations per target, seed {args.seed}",
        file=sys.stderr,
    )
    model = identify(
        dataset,
        engine=args.engine,
        targets=targets,
        budget=args.budget,
        seed=args.seed,
        pick=pick,
        validate=check,
        pick_fraction=args.holdout,
        validate_fraction=args.validate_fraction,
        gap_s=gap,
        pick_blocks=args.pick_blocks,
        r2_threshold=args.r2_threshold,
        loss=args.loss,
        settings=settings,
        vehicle=vehicle,
        progress=not args.no_progress,
        gravity=gravity,
        weak=weak,
        jobs=default_jobs() if args.jobs is None else args.jobs,
    )
    if motor is not None:
        model.engine["motor_model"] = motor.as_dict()
    save_model(model, out)
    metrics = {n: t.metrics["validation"] for n, t in model.targets.items()}
    roles = model.extra["data"]
    where = ", ".join(
        f"{b['file']} {b['t_start_s']:.2f}..{b['t_end_s']:.2f} s" for b in roles["validate"]
    )
    weak_note = f"; weak form, T = {weak.half_window_s:g} s: data and model integrated alike" if weak else ""
    print(f"validation (rows used neither to fit nor to pick: {where}{weak_note}):")
    print(table_markdown(metrics), end="")
    _print_and_report(model, motor, split_roles(), args, out, vehicle_config)
    print(f"wrote {out}")
    below = model.extra["checks"]["below_threshold"]
    if below:
        names = ", ".join(f"{n} (R^2 {r:.4f})" for n, r in below.items())
        print(f"below the validation R^2 threshold {args.r2_threshold:g}: {names}")
        if args.strict:
            print(f"--strict: exit {EXIT_BELOW_THRESHOLD}", file=sys.stderr)
            return EXIT_BELOW_THRESHOLD
    return 0


def _print_and_report(model, motor, roles, args: argparse.Namespace, out: Path, vehicle) -> None:
    """Print the grouped equations and the plausibility checks; write the model report (validation rows)."""
    from identification.model_report import equations_block, model_flags, write_model_report
    from identification.plausibility import checks_text, plausibility_checks
    from identification.quad_model import QuadrotorModel

    fitted = QuadrotorModel.from_model(model, motor)
    print(equations_block(fitted))
    train, hold = roles.fit, roles.validate
    checks = plausibility_checks(fitted, train.xi, train.u, vehicle=vehicle)
    print(checks_text(checks))
    for flag in model_flags(fitted, hold):
        print(f"flag: {flag}")
    folder = Path(args.report) if args.report else out.with_name(out.stem + "_report")
    md, png = write_model_report(fitted, train, hold, folder, checks, title=f"model report: {out.name}")
    print(f"wrote {md}, {png}")


def run_validate(args: argparse.Namespace) -> int:
    """Validate a model on a log; print Table I (and the comparison)."""
    from identification.model_file import load_model
    from identification.validate import comparison_markdown, table_markdown, validate

    model = load_model(args.model)
    reference = load_model(args.reference) if args.reference else None
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise UserError(f"--out {out} exists and is not a directory", hint="give a folder for the outputs")
    weak = _weak_settings(args)
    gravity = model.body.gravity if model.body is not None else None  # as the model was learned with
    dataset = _load([args.log], args.targets_from, args.motor_curve, args, gravity)
    if dataset.u_from_throttle or ("motor_model" in model.engine and "throttle" in dataset.aux):
        from identification.motor_model import apply_thrust_curve, curve_from_dict

        curve = curve_from_dict(model.engine.get("motor_model"), args.model)
        dataset = apply_thrust_curve(dataset, curve)
    report = validate(model, dataset, out, reference, weak)
    form = f", weak form T = {weak.half_window_s:g} s: targets and model integrated alike" if weak else ""
    print(f"Table I: {args.model} on {args.log} ({len(dataset)} rows{form})")
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
