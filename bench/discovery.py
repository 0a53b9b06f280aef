"""Discovery benchmark (issue 12): does identification find physics its library does not hold?

Cases (CASES below): synthetic flights generated in-process from written-down physics
(identification.effects_physics: the paper vehicle's equations plus one effect each, or all together), and
the real SITL's paper-vehicle flights (paper-train for training, paper-validate for validation, open loop
from 200 m, ideal sensors, truth targets). A case may name a SITL vehicle file with effects (the SITL issue's
`fang-chen-aero`, ...): it runs when that file exists and is listed as not run otherwise. Every case trains
on one flight and validates on another (synthetic: another seed).
CLOSED_LOOP_CASES: closed-loop flights from the ground (the closed-loop profile: hover stabiliser, PRBS on
every motor; ideal sensors, truth targets), trained on one flight and validated on another.

Engines, same data, same run: ours (`discovery`, the default: body frame, features from primitives), the
old library engine (`sparse`), and the baselines: PySINDy (STLSQ) with the physics library (quadsr's
identification.library, the terms of the SITL's own equations), PySINDy with a generic polynomial library
(degree 2 in the 16 variables), ordinary least squares on a 3-term physics library per target, and pyoperon
alone. No effect is handed to any engine as a feature: ours only gets the body-frame primitives.

One table: case, engine, validation R^2 per target, true terms found / missing / extra (expanded monomials of
the six NED targets against the case's true model), largest coefficient error, wall time. Floors, for ours
on every case: the true terms and no others (so at most 1.5x the true term count), coefficients within 5%,
validation R^2 >= 0.9999 on every target, a lowest R^2 at least every baseline's, and a SITL flight of 60 s
identified in under 2 minutes. PASS only when every floor holds.

Realistic-sensor cases (`... realistic sensors`): flown with `--sensors realistic`, targets from the IMU.
Ours runs twice: `discovery` on the default per-axis Savitzky-Golay targets (validation R^2 against the
validation flight's Savitzky-Golay targets, pointwise), and `discovery-weak`, the weak form that quadsr
identify uses by default on sensor targets (validation R^2 of the weak form: the validation flight's raw
sensor targets and the model both integrated against the same test functions). The floors (coefficients
within 15 %, validation R^2 >= 0.995) are on `discovery-weak`; the baselines get the Savitzky-Golay targets.

Usage: python bench/discovery.py [--cases NAME,...] [--engines NAME,...] [--rows N] [--seed N]
                                 [--operon-generations N] [--train-duration S] [--out DIR]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from dataclasses import dataclass, field
from itertools import combinations_with_replacement
from pathlib import Path

import numpy as np
import sympy

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from identification.body_frame import compose_ned, to_variables  # noqa: E402
from identification.dataset import Dataset, load_dataset  # noqa: E402
from identification.effects_physics import Effects, body_expressions, flight_rows  # noqa: E402
from identification.identify import DEFAULT_BUDGET, identify  # noqa: E402
from identification.kinematics import rotation_matrix_sym  # noqa: E402
from identification.library import DEFAULT_GROUPS, Feature, build_library, compile_features  # noqa: E402
from identification.metrics import weak_metrics  # noqa: E402
from identification.model_file import SYMBOLS, TARGET_NAMES, VARIABLE_NAMES, Model  # noqa: E402
from identification.true_model import motor_combinations_sym, true_model  # noqa: E402
from identification.validate import compare_models, evaluate_model  # noqa: E402
from identification.weak_form import RAW_SENSOR_TARGETS, WeakSettings, weak_rows  # noqa: E402

ENGINES = ("discovery", "sparse", "pysindy-physics", "pysindy-poly2", "ols-3term", "operon")
BASELINES = ("pysindy-physics", "pysindy-poly2", "ols-3term", "operon")


@dataclass(frozen=True)
class Case:
    """One benchmark case: synthetic (effects on a vehicle) or flown in the SITL (a vehicle file)."""

    name: str
    effects: Effects = field(default_factory=Effects)
    sitl_vehicle: str | None = None  # fly the SITL with this vehicle (name or file) instead of synthetic rows
    height: tuple[float, float] = (2.0, 50.0)  # synthetic: height above ground range, m
    sensors: bool = False  # SITL: realistic sensor preset, targets from the IMU (floors 15 % / 0.995)


CASES: tuple[Case, ...] = (
    Case("paper vehicle"),
    Case("rotor drag", Effects(rotor_drag=2e-4)),
    Case("weak rotor 3 (-8%)", Effects(rotor_scale=(1.0, 1.0, 0.92, 1.0))),
    Case("ground effect", Effects(ground_effect=0.08), height=(0.3, 3.0)),
    Case("frame drag v abs(v)", Effects(frame_drag=0.02)),
    Case("linear thrust", Effects(linear_thrust=4e-3, quadratic_thrust=False)),
    Case("all effects", Effects(rotor_drag=2e-4, rotor_scale=(1.0, 1.0, 0.92, 1.0), ground_effect=0.08,
                                frame_drag=0.02, linear_thrust=1e-3), height=(0.3, 3.0)),
    Case("sitl paper flights", sitl_vehicle="fang-chen-buaa"),
    Case("sitl fang-chen-aero", sitl_vehicle="fang-chen-aero"),  # the SITL issue's vehicle with effects
    Case("sitl paper flights realistic sensors", sitl_vehicle="fang-chen-buaa", sensors=True),
    Case("sitl fang-chen-aero realistic sensors", sitl_vehicle="fang-chen-aero", sensors=True),
)
VEHICLE = "fang-chen-buaa"


def reference_model(effects: Effects) -> Model:
    """The written physics of a synthetic case as a Model of the six NED/FRD targets."""
    body = body_expressions(VEHICLE, effects)
    from bridge.vehicle import load_vehicle

    g = load_vehicle(VEHICLE).gravity
    return Model({**compose_ned(body, g), **{n: to_variables(body[n]) for n in ("dwx", "dwy", "dwz")}})


def synthetic(case: Case, n: int, seed: int) -> Dataset:
    """n rows of the case's written physics (250 Hz timeline)."""
    xi, u, y = flight_rows(n, seed, VEHICLE, case.effects, case.height)
    return Dataset(t=np.arange(n) * 0.004, xi=xi, u=u, targets=y, source=f"synthetic {case.name} seed {seed}",
                   format="synthetic", target_source="truth")


def vehicle_file(name: str) -> Path | None:
    """The SITL vehicle file for a name or path, None when it does not exist (yet)."""
    p = Path(name)
    if p.suffix == ".yaml":
        return p if p.exists() else None
    p = REPO / "sitl" / "vehicles" / f"{name}.yaml"
    return p if p.exists() else None


def sitl_flights(case: Case, out: Path, seed: int, duration: float) -> tuple[Dataset, Dataset, list[Path]]:
    """Fly paper-train (duration s) and paper-validate in fresh SITLs with the case's vehicle; the datasets
    (truth targets, or with realistic sensors the default sensor targets) and the two .tlog paths."""
    from quadsr.pipeline import OPEN_LOOP_SITL, fly_excitation

    path = vehicle_file(case.sitl_vehicle or "")
    preset = "realistic" if case.sensors else "ideal"
    args = [*OPEN_LOOP_SITL, "--sensors", preset, "--vehicle", str(path)]
    logs, tlogs = [], []
    for profile, dur in (("paper-train", duration), ("paper-validate", None)):
        tlog = out / f"{case.sitl_vehicle}-{preset}-{profile}.tlog"
        fly_excitation(profile, tlog, sitl_args=args, seed=seed, duration=dur, vehicle=str(path),
                       log_path=out / f"sitl-{case.sitl_vehicle}-{preset}-{profile}.log")
        logs.append(load_dataset(tlog, targets="sensors" if case.sensors else "truth"))
        tlogs.append(tlog)
    return logs[0], logs[1], tlogs


# ---------------------------------------------------------------------------------------------------
# Closed-loop cases (issue 12, closed-loop identifiability): flown from the ground by quadsr's companion with
# the closed-loop profile (the hover stabiliser flying a slow Lissajous path with a turning heading, per-motor
# PRBS superposed), ideal sensors, truth targets; trained on one flight (SITL and excitation seed s) and
# validated on another (seed s + 1). The attitude controller ties rotor speeds to angles and rates, so the
# regressors are collinear: the engine must still return the physics' terms, not tied combinations.

CLOSED_LOOP_CASES: tuple[Case, ...] = (
    Case("sitl closed loop", sitl_vehicle="fang-chen-buaa"),
    Case("sitl closed loop fang-chen-aero", sitl_vehicle="fang-chen-aero"),
)


def closed_loop_flights(case: Case, out: Path, seed: int,
                        duration: float) -> tuple[Dataset, Dataset, list[Path]]:
    """Fly the closed-loop profile twice from the ground (training: duration s, seed; validation: the
    profile's own duration, seed + 1), each in a fresh SITL with the case's vehicle and ideal sensors."""
    from quadsr.pipeline import GROUND_SITL, fly_excitation

    path = vehicle_file(case.sitl_vehicle or "")
    logs, tlogs = [], []
    for role, s, dur in (("train", seed, duration), ("validate", seed + 1, None)):
        tlog = out / f"{case.sitl_vehicle}-closed-loop-{role}.tlog"
        args = [*GROUND_SITL, "--sensors", "ideal", "--vehicle", str(path), "--seed", str(s)]
        fly_excitation("closed-loop", tlog, sitl_args=args, seed=s, duration=dur, vehicle=str(path),
                       log_path=out / f"sitl-{case.sitl_vehicle}-closed-loop-{role}.log")
        logs.append(load_dataset(tlog))
        tlogs.append(tlog)
    return logs[0], logs[1], tlogs


# ---------------------------------------------------------------------------------------------------
# Baselines (NED targets, fitted as a user would with these tools)


def _linear_model(features: list[Feature], coef: np.ndarray) -> Model:
    """Six targets as sum coefficient x feature (coef: (6, n_features))."""
    exprs = {}
    for j, name in enumerate(TARGET_NAMES):
        pairs = zip(coef[j], features, strict=True)
        exprs[name] = sympy.Add(*[sympy.Float(float(c)) * f.expression for c, f in pairs if c != 0])
    return Model(exprs)


def _pysindy(features: list[Feature], train: Dataset) -> Model:
    """PySINDy STLSQ over the given features; the threshold picked per target on the last 20% of train."""
    import pysindy as ps

    theta = compile_features(features)(np.hstack([train.xi, train.u]))
    cut = int(0.8 * len(train))
    best = np.zeros((6, len(features)))
    best_loss = np.full(6, np.inf)
    for thr in np.geomspace(1e-6, 1e-1, 6):
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            model = ps.SINDy(feature_library=ps.IdentityLibrary(),
                             optimizer=ps.STLSQ(threshold=float(thr), normalize_columns=True))
            model.fit(theta[:cut], t=0.004, x_dot=train.targets[:cut])
        coef = model.coefficients()
        err = np.mean(np.abs(theta[cut:] @ coef.T - train.targets[cut:]), axis=0)
        better = err < best_loss
        best[better], best_loss[better] = coef[better], err[better]
    return _linear_model(features, best)


def polynomial_features(degree: int) -> list[Feature]:
    """Every monomial of the 16 variables up to `degree` (a generic library)."""
    syms = [SYMBOLS[n] for n in VARIABLE_NAMES]
    feats = [Feature("1", sympy.Integer(1), "poly")]
    for d in range(1, degree + 1):
        feats += [Feature("", sympy.Mul(*c), "poly") for c in combinations_with_replacement(syms, d)]
    return feats


def ols_three_terms(train: Dataset) -> Model:
    """Ordinary least squares per target on 3 physics terms (thrust, drag / coupling, offset / damping)."""
    s = SYMBOLS
    comb = motor_combinations_sym(s)
    rot = rotation_matrix_sym(s["phi"], s["theta"], s["psi"])
    terms = {
        "ax": [comb["f1"] * rot[0, 2], s["vx"] * sympy.Abs(s["vx"]), sympy.Integer(1)],
        "ay": [comb["f1"] * rot[1, 2], s["vy"] * sympy.Abs(s["vy"]), sympy.Integer(1)],
        "az": [comb["f1"] * rot[2, 2], s["vz"] * sympy.Abs(s["vz"]), sympy.Integer(1)],
        "dwx": [comb["f2"], s["wy"] * s["wz"], s["wx"]],
        "dwy": [comb["f3"], s["wx"] * s["wz"], s["wy"]],
        "dwz": [comb["f4"], s["wx"] * s["wy"], s["wz"]],
    }
    X = np.hstack([train.xi, train.u])
    exprs = {}
    for j, name in enumerate(TARGET_NAMES):
        feats = [Feature("", e, "ols") for e in terms[name]]
        theta = compile_features(feats)(X)
        c = np.linalg.lstsq(theta, train.targets[:, j], rcond=None)[0]
        exprs[name] = sympy.Add(*[sympy.Float(float(ci)) * e for ci, e in zip(c, terms[name], strict=True)])
    return Model(exprs)


def fit(engine: str, train: Dataset, seed: int, gravity: float, budget: int,
        operon_generations: int) -> Model:
    """One engine's model of the six targets from the training flight (budget: GP generations)."""
    if engine in ("discovery", "sparse", "operon"):
        generations = operon_generations if engine == "operon" else budget
        return identify(train, engine=engine, budget=generations, seed=seed, progress=False, gravity=gravity)
    if engine == "pysindy-physics":
        return _pysindy(build_library(DEFAULT_GROUPS), train)
    if engine == "pysindy-poly2":
        return _pysindy(polynomial_features(2), train)
    if engine == "ols-3term":
        return ols_three_terms(train)
    raise SystemExit(f"unknown engine {engine!r} (known: {', '.join(ENGINES)})")


@dataclass
class Row:
    """One table row."""

    case: str
    engine: str
    r2: dict[str, float]
    found: int
    missing: int
    extra: int
    reference_terms: int
    max_error: float
    wall_s: float


def score(case: str, engine: str, model: Model, val: Dataset, reference: Model, wall: float,
          weak: bool = False) -> Row:
    """Validation R^2 and the term comparison against the reference (weak: R^2 of the weak form, the
    validation flight's raw sensor targets and the model both integrated against the test functions)."""
    if weak:
        op = weak_rows(val.t, val.flight, WeakSettings())
        pred = np.atleast_2d(model.evaluate(val.xi, val.u))
        metrics = {n: weak_metrics(val.targets[:, TARGET_NAMES.index(n)], pred[:, j], op)
                   for j, n in enumerate(model.target_names)}
    else:
        _, metrics = evaluate_model(model, val)
    comps = compare_models(model, reference)
    found = sum(sum(1 for r in c.rows if r.status == "both") for c in comps)
    errs = [c.max_relative_error for c in comps if c.max_relative_error is not None]
    ref_terms = sum(sum(1 for r in c.rows if r.reference is not None) for c in comps)
    return Row(case, engine, {n: metrics[n]["r2"] for n in TARGET_NAMES}, found,
               sum(len(c.missing) for c in comps), sum(len(c.extra) for c in comps), ref_terms,
               max(errs) if errs else float("nan"), wall)


def table(rows: list[Row]) -> str:
    """The benchmark table as Markdown."""
    head = ("| case | engine | " + " | ".join(f"R^2 {n}" for n in TARGET_NAMES)
            + " | true terms found / missing / extra (of N) | largest coef. error | wall [s] |")
    lines = [head, "|" + "---|" * (len(TARGET_NAMES) + 5)]
    for r in rows:
        r2 = " | ".join(f"{r.r2[n]:.6f}" for n in TARGET_NAMES)
        lines.append(f"| {r.case} | {r.engine} | {r2} | {r.found} / {r.missing} / {r.extra} "
                     f"(of {r.reference_terms}) | {r.max_error:.2e} | {r.wall_s:.1f} |")
    return "\n".join(lines)


def main() -> int:
    """Run the cases and engines, print the table and the floors; 0 when every floor holds."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=None, help="comma-separated case names (default: all)")
    ap.add_argument("--engines", default=",".join(ENGINES), help=f"comma-separated, of {', '.join(ENGINES)}")
    ap.add_argument("--rows", type=int, default=4000, help="synthetic rows per flight (250 Hz: 16 s)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--operon-generations", type=int, default=60, help="the pyoperon-alone baseline's budget")
    ap.add_argument("--budget", type=int, default=DEFAULT_BUDGET,
                    help="the discovery engine's genetic-programming generations per target")
    ap.add_argument("--train-duration", type=float, default=60.0, help="SITL training flight, s simulated")
    ap.add_argument("--out", default="results/discovery", help="folder for SITL flights")
    args = ap.parse_args()
    engines = [e.strip() for e in args.engines.split(",") if e.strip()]
    cases = [c for c in (*CASES, *CLOSED_LOOP_CASES) if args.cases is None or c.name in args.cases.split(",")]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[Row] = []
    floors: list[tuple[str, bool]] = []
    for case in cases:
        if case.sitl_vehicle is not None:
            if vehicle_file(case.sitl_vehicle) is None:
                print(f"== {case.name}: vehicle {case.sitl_vehicle!r} not in this checkout: not run")
                continue
            from bridge.vehicle import load_vehicle

            flights = closed_loop_flights if case in CLOSED_LOOP_CASES else sitl_flights
            train, val, tlogs = flights(case, out, args.seed, args.train_duration)
            reference = true_model(load_vehicle(str(vehicle_file(case.sitl_vehicle))))
            gravity = load_vehicle(str(vehicle_file(case.sitl_vehicle))).gravity
        else:
            train = synthetic(case, args.rows, args.seed)
            val = synthetic(case, args.rows // 2, args.seed + 1000)
            reference = reference_model(case.effects)
            from bridge.vehicle import load_vehicle

            gravity = load_vehicle(VEHICLE).gravity
        print(f"== {case.name}: {len(train)} training rows, {len(val)} validation rows")
        case_rows = []
        for engine in engines:
            start = time.perf_counter()
            model = fit(engine, train, args.seed, gravity, args.budget, args.operon_generations)
            wall = time.perf_counter() - start
            row = score(case.name, engine, model, val, reference, wall)
            if case.sensors and engine == "discovery":  # ours, also in the weak form (quadsr's default there)
                case_rows.append(row)
                print(f"  {engine} (point SG targets): lowest R^2 {min(row.r2.values()):.6f}, terms "
                      f"{row.found}/{row.missing}/{row.extra} of {row.reference_terms}, coef. error "
                      f"{row.max_error:.2e}, {wall:.1f} s", flush=True)
                raw_train, raw_val = (load_dataset(p, targets="sensors", sensor_settings=RAW_SENSOR_TARGETS)
                                      for p in tlogs)
                start = time.perf_counter()
                model = identify(raw_train, budget=args.budget, seed=args.seed, progress=False,
                                 gravity=gravity, weak=WeakSettings())
                wall = time.perf_counter() - start
                row = score(case.name, "discovery-weak", model, raw_val, reference, wall, weak=True)
            case_rows.append(row)
            print(f"  {row.engine}: lowest R^2 {min(row.r2.values()):.6f}, terms {row.found}/{row.missing}/"
                  f"{row.extra} of {row.reference_terms}, coef. error {row.max_error:.2e}, {wall:.1f} s",
                  flush=True)
        rows += case_rows
        ours = next((r for r in case_rows if r.engine == ("discovery-weak" if case.sensors else "discovery")),
                    None)
        if ours is None:
            continue
        low = min(ours.r2.values())
        coef_floor, r2_floor = (0.15, 0.995) if case.sensors else (0.05, 0.9999)
        floors.append((f"{case.name}: the true terms and no others", ours.missing == 0 and ours.extra == 0))
        floors.append((f"{case.name}: coefficients within {coef_floor:.0%}", ours.max_error <= coef_floor))
        floors.append((f"{case.name}: validation R^2 >= {r2_floor} on every target", low >= r2_floor))
        floors.append((f"{case.name}: at most 1.5x the true term count",
                       ours.found + ours.extra <= 1.5 * ours.reference_terms))
        others = [r for r in case_rows if r.engine in BASELINES]
        floors.append((f"{case.name}: lowest R^2 at least every baseline's",
                       all(low >= min(r.r2.values()) - 1e-9 for r in others)))
        if case.sitl_vehicle is not None and args.train_duration >= 60:
            floors.append((f"{case.name}: a 60 s flight identified in under 2 minutes", ours.wall_s < 120))
    print()
    print(table(rows))
    print()
    for label, ok in floors:
        print(f"[{'PASS' if ok else 'FAIL'}] {label}")
    ok = bool(floors) and all(ok for _, ok in floors)
    print("PASS" if ok else "FAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
