"""Discovery benchmark (issue 12): does identification find physics its library does not hold?

Cases (CASES below): synthetic flights generated in-process from written-down physics
(identification.effects_physics: the paper vehicle's equations plus one effect each, or all together), and
flights FLOWN IN THE SITL (separate `quadsr sitl` processes, real UDP MAVLink) with a vehicle file: the
paper's vehicle, `fang-chen-aero` (every effect on), each effect alone on the paper's vehicle, a wide
PX4-Iris-like frame with a CG offset, a heavy vehicle, and the heavy vehicle with every effect, a CG offset
and a weak rotor, and a 5-inch racer on a dead-cat frame with every effect, a CG offset and a weak rotor, each
open loop and closed loop (bench/vehicles/, each number's source in the file).
SITL cases fly the paper's open-loop flights (paper-train for training, paper-validate for validation, from
200 m with no ground), except ground effect, which needs the ground: a stabilised low hover with PRBS on
the motors (bench/profiles/near-ground.yaml), validated on a second flight of it with another seed. Ideal
sensors and truth targets, except: closed-loop cases (the closed-loop profile flown from the ground, trained
on seed s, validated on seed s + 1), and realistic-sensor cases (targets from the IMU; ours is scored in the
weak form, `discovery-weak`, quadsr identify's default on sensor targets, validated against the validation
flight's raw sensor targets integrated against the same test functions; floors R^2 0.995, coefficients
15 %). Two cases are both, as every real flight log is: the closed-loop profile flown from the ground with
realistic sensors (the paper's vehicle and `fang-chen-aero`). Every case trains on one flight and validates
on another (synthetic: another seed).

Engines, same data, same run: ours (`discovery`, the default: body frame, features from primitives), the
old library engine (`sparse`), and the baselines: PySINDy (STLSQ) with the physics library (quadsr's
identification.library, the terms of the SITL's own equations), PySINDy with a generic polynomial library
(degree 2 in the 16 variables: 153 columns), ordinary least squares on a 3-term physics library per target,
and pyoperon alone. No effect is handed to any engine as a feature: ours only gets the body-frame primitives.
Each baseline's settings are printed and written above the table (baseline_settings): PySINDy's STLSQ with
normalized columns and the threshold picked per target from 6 (1e-6 to 1e-1) on the training flight's last
20 %; pyoperon alone through `quadsr identify --engine operon` (population 500, NSGA-II on r2 and length,
constant fitting on) for --operon-generations generations per target (default 20: 10,000 individuals, about
the CPU time ours takes on a SITL case; identify's default is 60, a pyoperon-alone case then takes 4-6 CPU
minutes on 9,000 fit rows). The baselines run with BLAS on one thread, as ours and `sparse` run their fits:
OpenBLAS's two threads spin on a loaded 2-core machine (PySINDy's degree-2 fit of a 15,000-row SITL case took
51 s of CPU with two, 7.4 s with one, the same model).

One table: case, engine, validation R^2 per target, true terms found / missing / extra, largest coefficient
error (which target and term: on the coefficient floor's line and in the CSV's max_coef_term), wall and CPU
time. Terms are the expanded monomials of the BODY-FRAME expressions (fx fy fz dwx dwy dwz
in the primitives ub vb wb wx wy wz u1..u4 h) against the true body-frame physics
(identification.true_model.true_body_expressions, or the synthetic case's written physics) for every model
that has them (ours); the others (baselines, learning NED directly) are compared on the six NED targets.
The NED expansion of |v| v into R (R^T v) |R^T v| is not a structure anybody learns; in the body frame frame
drag is one monomial. A ground-effect law is no monomial of the primitives (1/(1 - (R/4h_i)^2) at each hub's
height), so for a vehicle flown with one it is judged apart (identification.height_law): the learned terms
that fall off with the height against the true height-dependent part (the true expression minus the same
vehicle's with no ground), as their relative RMS difference over the validation flight's rows, one "term"
per target that has a law (found when the learned target has height terms; its error, which must be within
5 % as a coefficient's, enters the largest error); the rest is compared monomial by monomial with the
no-ground expressions. Flights from the ground lose the rows within the segmentation's edge margin (0.3 s) of
lift-off, as identification.segmentation drops them from real logs (there h -> 0, below the SITL's
min_height, where no law in 1/h holds).
Every engine's model is written to OUT/models/<case>-<engine>.yaml. A true term that
the training flight cannot pin down even given the true structure
(least squares on every true term, t ratio below selection.min_t = 5, the t the engine's own pick demands;
unidentifiable_terms) is counted apart ("not identifiable"): not missing when left out, not held to the
coefficient floor; ours lists the ones it left out. With realistic sensors these are the terms below the
noise (on fang-chen-aero's paper-train flight: fz's w^2, vb*wz and wx*wz, wy''s wx^2 and wy^2); with
ideal sensors there are none or next to none. Ours (and `sparse` and pyoperon alone, which run through
identify) are given the case's validation flight as their validation role, as a user with two flights gives
it (`quadsr identify --validate-log`): they fit and pick on the whole training flight, as the baselines fit
on it, and are validated on the other flight; train on one flight, validate on another. With
--own-validation-block ours keeps the training flight's last fifth to validate on instead (identify's
default roles for one flight), so it fits and picks on fewer rows; the true terms the whole flight pins down
but those rows (fit_and_pick_rows) do not are then listed per case in the results md, and are still counted
missing when left out and held to the coefficient floor. Sensor cases: the body-frame reference is the
law of what the sensors measure (sensor_reference): the accelerometer's bias as the constants of fx fy fz
(it is in the data; the gyro's is not: the rates a model reads are the log's true ones, and the angular
accelerations the gyro's differences, where its bias cancels), the targets add the vehicle's
gravity (the g its accelerometer measures against), and every engine's model is scored in the weak form on
the validation flight's raw sensor targets ("(weak)" in the table), so ours and the baselines are judged
alike.
Each case also has a row "true terms refit" (true_terms_refit): the true terms with their coefficients
refit by least squares on the training flight, each monomial its own coefficient (the height law one), on
the rows ours sees (weak rows on sensor cases), scored as the engines are. It is what the flight's targets
give the exact structure, no engine; no floor is judged against it, and the coefficient floor's line quotes
its error when that is beyond the floor too (the flight, not only the engine's choice of terms, misses it
there). An engine that ties what the physics ties (ub (u1 + .. + u4) as one term) fits fewer coefficients
and can do better.
The table goes to OUT/discovery.md and OUT/discovery.csv as well. Floors, for ours
on every case: the true terms and no others (so at most 1.5x the true term count), coefficients within 5%,
validation R^2 >= 0.9999 on every target, a lowest R^2 at least every baseline's, and a SITL flight of 60 s
identified in under 2 minutes of wall time on this machine's cores (identify fits the targets side by side
in --jobs processes, default every core; the CPU over all processes is printed beside it; run it on a quiet
machine: on a loaded one the wall time is several times the CPU time). PASS only when every floor holds.

Usage: python bench/discovery.py [--cases NAME,...] [--engines NAME,...] [--rows N] [--seed N]
                                 [--operon-generations N] [--train-duration S] [--out DIR] [--reuse-flights]
                                 [--settings ENGINE_SETTINGS.yaml] [--jobs N] [--own-validation-block]
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import resource
import sys
import time
import warnings
from dataclasses import dataclass, field, replace
from itertools import combinations_with_replacement
from pathlib import Path

import numpy as np
import sympy

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from bridge.errors import UserError  # noqa: E402
from identification.body_frame import (  # noqa: E402
    BODY_TARGET_NAMES,
    PRIMITIVE_SYMBOLS,
    PRIMITIVES,
    body_targets,
    compose_ned,
    primitive_info,
    primitive_matrix,
    to_variables,
)
from identification.collinearity import offset_t_ratio, term_t_ratios  # noqa: E402
from identification.data_roles import assign_roles  # noqa: E402
from identification.dataset import Dataset, load_dataset  # noqa: E402
from identification.effects_physics import Effects, body_expressions, flight_rows  # noqa: E402
from identification.engine_settings import (  # noqa: E402
    EngineSettings,
    SelectionSettings,
    load_engine_settings,
)
from identification.height_law import body_values, height_law_error, height_terms  # noqa: E402
from identification.identify import DEFAULT_BUDGET, identify  # noqa: E402
from identification.kinematics import rotation_matrix_sym  # noqa: E402
from identification.library import DEFAULT_GROUPS, Feature, build_library, compile_features  # noqa: E402
from identification.metrics import weak_metrics  # noqa: E402
from identification.model_file import (  # noqa: E402
    SYMBOLS,
    TARGET_NAMES,
    VARIABLE_NAMES,
    BodyModel,
    Model,
    TargetModel,
    expression_to_string,
    save_model,
)
from identification.sparse import single_threaded_blas  # noqa: E402
from identification.target_pool import default_jobs  # noqa: E402
from identification.true_model import motor_combinations_sym, true_body_expressions, true_model  # noqa: E402
from identification.validate import (  # noqa: E402
    compare_expressions,
    compare_models,
    evaluate_model,
    expression_terms,
)
from identification.weak_form import RAW_SENSOR_TARGETS, WeakSettings, overlap_lag, weak_rows  # noqa: E402
from identification.weak_noise import stated_whitener  # noqa: E402

ENGINES = ("discovery", "sparse", "pysindy-physics", "pysindy-poly2", "ols-3term", "operon")
BASELINES = ("pysindy-physics", "pysindy-poly2", "ols-3term", "operon")
# a reference row beside the engines: the true terms refit on the training flight (true_terms_refit)
TRUE_TERMS_REFIT = "true terms refit"


@dataclass(frozen=True)
class Case:
    """One benchmark case: synthetic (effects on a vehicle) or flown in the SITL (a vehicle file)."""

    name: str
    effects: Effects = field(default_factory=Effects)
    sitl_vehicle: str | None = None  # fly the SITL with this vehicle (name or file) instead of synthetic rows
    height: tuple[float, float] = (2.0, 50.0)  # synthetic: height above ground range, m
    # SITL only: the training and validation profiles (names or files); open loop: from 200 m with no ground
    # (the paper's flights), else from the ground (the validation flight then uses seed + 1)
    profiles: tuple[str, str] = ("paper-train", "paper-validate")
    open_loop: bool = True
    sensors: str = "ideal"  # the SITL's sensor preset (hook: realistic)
    targets: str = "truth"  # the datasets' targets: truth | sensors (hook; the floors follow it)


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
    Case("sitl fang-chen-aero", sitl_vehicle="fang-chen-aero"),  # every effect of the SITL (ground: none)
    Case("sitl rotor drag", sitl_vehicle="buaa-rotor-drag"),
    Case("sitl translational lift", sitl_vehicle="buaa-translational-lift"),
    Case("sitl frame drag", sitl_vehicle="buaa-frame-drag"),
    Case("sitl ground effect", sitl_vehicle="buaa-ground-effect", open_loop=False,
         profiles=(str(REPO / "bench" / "profiles" / "near-ground.yaml"),) * 2),
    Case("sitl weak rotor 3 (-8%)", sitl_vehicle="buaa-weak-rotor"),
    Case("sitl px4 thrust model", sitl_vehicle="buaa-px4-thrust"),
    Case("sitl wide frame with CG offset", sitl_vehicle="iris-wide-cg"),
    Case("sitl heavy vehicle", sitl_vehicle="heavy-650"),
    # the heavy vehicle with every effect, a CG offset and a weak rotor (session 63: a vehicle the engine was
    # not tuned on), open loop and in closed loop from the ground (its ground effect too)
    Case("sitl heavy vehicle with every effect", sitl_vehicle="heavy-650-aero"),
    # a 5-inch racer on a dead-cat frame with every effect, a CG offset and a weak rotor (session 74: a third
    # airframe the engine was not tuned on), open loop and in closed loop from the ground
    Case("sitl racer with every effect", sitl_vehicle="racer-250-aero"),
    # closed loop from the ground: the closed-loop profile (hover stabiliser on a 2 m Lissajous path with a
    # turning heading, per-motor PRBS); the controller ties rotor speeds to angles and rates, so the
    # regressors are collinear and the engine must still return the physics' terms
    Case("sitl closed loop", sitl_vehicle="fang-chen-buaa", open_loop=False,
         profiles=("closed-loop", "closed-loop")),
    Case("sitl closed loop fang-chen-aero", sitl_vehicle="fang-chen-aero", open_loop=False,
         profiles=("closed-loop", "closed-loop")),
    Case("sitl closed loop heavy vehicle with every effect", sitl_vehicle="heavy-650-aero", open_loop=False,
         profiles=("closed-loop", "closed-loop")),
    Case("sitl closed loop racer with every effect", sitl_vehicle="racer-250-aero", open_loop=False,
         profiles=("closed-loop", "closed-loop")),
    # realistic sensors, targets from the IMU: ours is scored in the weak form (quadsr identify's default on
    # sensor targets) as `discovery-weak`, beside the point Savitzky-Golay targets
    Case("sitl paper flights realistic sensors", sitl_vehicle="fang-chen-buaa", sensors="realistic",
         targets="sensors"),
    Case("sitl fang-chen-aero realistic sensors", sitl_vehicle="fang-chen-aero", sensors="realistic",
         targets="sensors"),
    # both at once, as in every real log: the controller's collinearity and the IMU's noise and bias
    Case("sitl closed loop realistic sensors", sitl_vehicle="fang-chen-buaa", open_loop=False,
         profiles=("closed-loop", "closed-loop"), sensors="realistic", targets="sensors"),
    Case("sitl closed loop fang-chen-aero realistic sensors", sitl_vehicle="fang-chen-aero", open_loop=False,
         profiles=("closed-loop", "closed-loop"), sensors="realistic", targets="sensors"),
)
FLOORS = {"truth": (0.9999, 0.05), "sensors": (0.995, 0.15)}  # targets -> (lowest R^2, coefficient error)
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
    """The SITL vehicle file for a name or path (sitl/vehicles, then bench/vehicles), None when absent."""
    p = Path(name)
    if p.suffix == ".yaml":
        return p if p.exists() else None
    for folder in (REPO / "sitl" / "vehicles", REPO / "bench" / "vehicles"):
        if (folder / f"{name}.yaml").exists():
            return folder / f"{name}.yaml"
    return None


def flight_name(vehicle: str) -> str:
    """What a vehicle's flights are filed under in --out: a bundled vehicle's name, or a vehicle file's stem
    and a digest of its content (a path would put the flights beside the file; two files of one name, or one
    file edited, do not share flights with --reuse-flights)."""
    p = Path(vehicle)
    if p.suffix != ".yaml":
        return vehicle
    return f"{p.stem}-{hashlib.sha256(p.read_bytes()).hexdigest()[:8]}"


def flown_vehicle(case: Case):  # -> VehicleConfig
    """The vehicle as the SITL flies it (open loop: no ground, so no ground effect in its physics)."""
    from bridge.vehicle import load_vehicle

    vehicle = load_vehicle(str(vehicle_file(case.sitl_vehicle or "")))
    return vehicle.with_overrides(ground="none") if case.open_loop else vehicle


def sitl_flights(case: Case, out: Path, seed: int, duration: float, gravity: float,
                 reuse: bool = False) -> tuple[Dataset, Dataset, list[Path]]:
    """Fly the case's training flight (duration s) and validation flight in fresh SITLs with its vehicle
    (reuse: read the flights a previous run left in `out` instead, when both are there). Sensor targets add
    the vehicle's gravity (m/s^2), the g its accelerometer measures against and the body frame removes."""
    from quadsr.pipeline import GROUND_SITL, OPEN_LOOP_SITL, fly_excitation

    path = vehicle_file(case.sitl_vehicle or "")
    base = OPEN_LOOP_SITL if case.open_loop else GROUND_SITL
    args = [*base, "--sensors", case.sensors, "--vehicle", str(path)]
    val_seed = seed if case.open_loop else seed + 1  # open loop: paper-validate is another flight already
    flights = ((case.profiles[0], duration, seed, "train"), (case.profiles[1], None, val_seed, "validate"))
    logs, tlogs = [], []
    for profile, dur, s, role in flights:
        # the profile in the name: two cases of one vehicle (paper flights, closed loop) share an --out folder
        name = (f"{flight_name(case.sitl_vehicle or '')}-{Path(str(profile)).stem}-{case.sensors}-{role}-"
                f"{dur or 0:g}s-seed{s}")
        tlog = out / f"{name}.tlog"
        tlogs.append(tlog)
        if reuse and tlog.exists() and tlog.stat().st_size > 0:
            logs.append(load_dataset(tlog, targets=case.targets, gravity=gravity))
            continue
        # step_timeout as the SITL's own patience (--lockstep-timeout 30): a loaded machine stalls steps for
        # over 1 s (a frame-drag flight was lost at 34.7 s with load 16 on 2 cores)
        fly_excitation(profile, tlog, sitl_args=args, seed=s, duration=dur, vehicle=str(path),
                       step_timeout=30.0, log_path=out / f"sitl-{tlog.stem}.log")
        logs.append(load_dataset(tlog, targets=case.targets, gravity=gravity))
    # the lift-off's rows go as a user's identify drops them (identification.segmentation: the edge margin)
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
    for thr in PYSINDY_THRESHOLDS:
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


PYSINDY_THRESHOLDS = np.geomspace(1e-6, 1e-1, 6)  # STLSQ thresholds tried per target (normalized columns)
OPERON_GENERATIONS = 20  # pyoperon alone: generations per target (population 500: 10,000 individuals)


def baseline_settings(engines: list[str], operon_generations: int, seed: int) -> list[str]:
    """One line per baseline in `engines`: what it fitted and with which settings (for the table)."""
    from identification.engine_settings import OperonSettings

    sweep = (f"STLSQ (normalize_columns) with the threshold picked per target from {len(PYSINDY_THRESHOLDS)} "
             f"({PYSINDY_THRESHOLDS[0]:g} to {PYSINDY_THRESHOLDS[-1]:g}, geometric) by the mean absolute "
             "error on the last 20 % of the training flight (fitted on the first 80 %)")
    o = OperonSettings()
    lines = {
        "pysindy-physics": f"PySINDy, quadsr's physics library (identification.library, "
                           f"{len(build_library(DEFAULT_GROUPS))} columns), {sweep}",
        "pysindy-poly2": f"PySINDy, every monomial of degree <= 2 in the 16 variables "
                         f"({len(polynomial_features(2))} columns), {sweep}",
        "ols-3term": "ordinary least squares per target on 3 physics terms (thrust, drag or coupling, offset "
                     "or damping)",
        "operon": f"pyoperon alone (quadsr identify --engine operon, NED targets): NSGA-II on (r2, length), "
                  f"population {o.population_size}, {operon_generations} generations per target "
                  f"({o.population_size * operon_generations:,} individuals; quadsr identify's default is "
                  f"{DEFAULT_BUDGET}), Levenberg-Marquardt constant fitting {o.optimizer_iterations} "
                  f"iterations, max length {o.max_length}, depth {o.max_depth}, {o.allowed_symbols}, "
                  f"engineered inputs, {o.n_threads} threads, seed {seed}; the model picked on identify's "
                  "held-out rows",
    }
    return [f"{e}: {lines[e]}" for e in engines if e in lines]


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


def check_engine(engine: str) -> None:
    """SystemExit saying what to use instead when this bench does not run `engine`."""
    if engine == "discovery-weak":
        raise SystemExit("discovery-weak is not an engine of --engines: on realistic-sensor cases "
                         "`discovery` gives both rows, discovery (point targets) and discovery-weak")
    if engine not in ENGINES:
        raise SystemExit(f"unknown engine {engine!r} (known: {', '.join(ENGINES)})")


def fit(engine: str, train: Dataset, seed: int, gravity: float, budget: int,
        operon_generations: int, settings: EngineSettings | None = None,
        validate: Dataset | None = None, pick_blocks: int = 1, jobs: int = 1) -> Model:
    """One engine's model of the six targets from the training flight (budget: GP generations).

    validate: the case's validation flight (--validation-flight), given to the engines that hold rows out
    (ours, `sparse`, pyoperon alone through identify) as their validation role, as a user with two flights
    gives it (`quadsr identify --validate-log`): the training flight is then fit and pick rows only, no
    block of it set aside to validate; None: identify's default blocks (fit | pick | validate) of the
    training flight (the baselines fit on the whole training flight either way). pick_blocks: identify's
    (--pick-blocks), the pick rows spread over the training flight in that many blocks.

    The baselines run with BLAS on one thread, as ours and `sparse` run their fits (single_threaded_blas):
    the same numbers, but OpenBLAS's two threads spin on a loaded 2-core machine (STLSQ's least squares on
    15,000 x 153 took 7x the CPU time). settings: ours' engine settings (--settings; None: the defaults).
    jobs: the processes identify fits the targets in side by side (identification.target_pool)."""
    if engine in ("discovery", "sparse"):
        return identify(train, engine=engine, budget=budget, seed=seed, progress=False, gravity=gravity,
                        settings=settings, validate=validate, pick_blocks=pick_blocks, jobs=jobs)
    check_engine(engine)
    with single_threaded_blas():
        if engine == "operon":
            return identify(train, engine=engine, budget=operon_generations, seed=seed, progress=False,
                            gravity=gravity, validate=validate, pick_blocks=pick_blocks, jobs=jobs)
        if engine == "pysindy-physics":
            return _pysindy(build_library(DEFAULT_GROUPS), train)
        if engine == "pysindy-poly2":
            return _pysindy(polynomial_features(2), train)
        return ols_three_terms(train)


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
    cpu_s: float
    frame: str  # the terms compared: "body" (fx fy fz dwx dwy dwz in primitives) or "NED"
    missing_terms: list[str] = field(default_factory=list)
    extra_terms: list[str] = field(default_factory=list)
    # a non-monomial height law (ground effect): per target, the relative RMS error of the learned
    # height-dependent part against the true one over the validation flight's rows (None: not found)
    height_law: dict[str, float | None] = field(default_factory=dict)
    # true terms the training flight cannot pin down (unidentifiable_terms) that the model left out
    unidentifiable_missing: list[str] = field(default_factory=list)
    unidentifiable: int = 0  # true terms the training flight cannot pin down, found or not
    scored: str = "point"  # validation R^2 of point targets, or of the weak form (sensor cases)
    worst: str = ""  # where the largest coefficient error is: "target: term" (or "target: the height law")


def fit_and_pick_rows(train: Dataset) -> Dataset:
    """The training flight's rows identify fits and picks on when it keeps its own validation block (no
    validation flight given): its default data roles (identification.data_roles.assign_roles)."""
    roles = assign_roles(train)
    return Dataset.concat([roles.fit, roles.pick])


def cpu_seconds() -> float:
    """CPU seconds of this process and of its reaped children (identify's worker processes), s."""
    children = resource.getrusage(resource.RUSAGE_CHILDREN)
    return time.process_time() + children.ru_utime + children.ru_stime


def listed_terms(terms: dict[str, list[str]]) -> str:
    """Per-target term lists as one line: "fz: a, b; dwy: c" (targets without terms left out)."""
    return "; ".join(f"{k}: {', '.join(v)}" for k, v in terms.items() if v)


def _true_structure_rows(body_reference: dict[str, sympy.Expr], train: Dataset, gravity: float, weak: bool,
                         height_law: dict[str, sympy.Expr] | None, stated_noise: bool):
    """Per body-frame target with true terms: (target, its true terms but the constant, the reference's
    terms and coefficients, the columns [1, terms, law] on the rows the engine sees (weak: integrated
    against the test functions), the target there, the rows' lag for the t ratios, the stated noise's
    whitener or None, the target's height law or 0). unidentifiable_terms' and true_terms_refit's fits."""
    X = np.hstack([train.xi, train.u])
    names = tuple(PRIMITIVES)
    P = primitive_matrix(X, names)
    Y = body_targets(train.xi, train.targets, gravity)
    for j, target in enumerate(BODY_TARGET_NAMES):
        reference = expression_terms(body_reference[target])
        terms = [k for k in reference if k != 1]
        if not terms:
            continue
        fn = sympy.lambdify([PRIMITIVE_SYMBOLS[n] for n in names], terms, modules="numpy")
        with np.errstate(all="ignore"):
            cols = np.column_stack([np.broadcast_to(np.asarray(c, float), (len(X),))
                                    for c in fn(*P.T)])
        law = (height_law or {}).get(target, sympy.Integer(0))
        if law != 0:
            cols = np.column_stack([cols, body_values(law, X)])
        y = Y[:, j]
        ok = np.all(np.isfinite(cols), axis=1) & np.isfinite(y)
        cols, y = np.hstack([np.ones((int(ok.sum()), 1)), cols[ok]]), y[ok]
        lag = None  # point rows: AR(1); weak rows: the windows' overlap (collinearity.effective_rows)
        noise = None  # weak rows whose log states its targets' noise: the t ratios under it, as identify's
        if weak:
            op = weak_rows(train.t[ok], train.flight[ok], WeakSettings())
            cols, y, lag = np.asarray(op @ cols), op @ y, overlap_lag(op)
            if stated_noise:
                noise = stated_whitener(train, ok, op, j)
        yield target, terms, reference, cols, y, lag, noise, law


def unidentifiable_terms(body_reference: dict[str, sympy.Expr], train: Dataset, gravity: float,
                         weak: bool, min_t: float = SelectionSettings().min_t,
                         height_law: dict[str, sympy.Expr] | None = None,
                         stated_noise: bool = SelectionSettings().stated_noise_t) -> dict[str, list[str]]:
    """Per body-frame target, the true terms this training flight cannot pin down even given the true
    structure: least squares of the target (weak: integrated against the test functions, as the engine sees
    it) on every true term and a constant, and the terms whose t ratio (identification.collinearity, its
    effective rows AR(1) on point rows, summed over the test functions' overlap on weak rows:
    effective_rows; under the stated noise on weak rows whose log states it and stated_noise, as identify's
    pick does) is below min_t, the t the engine's pick demands of its own terms; a true constant (a
    sensor's bias) by its t as the fit's offset (offset_t_ratio). Those terms are listed
    apart and neither counted missing nor held to the coefficient floor. height_law: a ground effect's
    height-dependent part per target (height_law_reference), no monomial, so body_reference holds the
    vehicle's no-ground terms only; it is part of the true structure, one more column (with its own
    coefficient, no t asked of it): without it a flight near the ground leaves the law in the residual and
    every other term's t falls with it."""
    out: dict[str, list[str]] = {}
    for target, terms, reference, cols, y, lag, noise, _law in _true_structure_rows(
            body_reference, train, gravity, weak, height_law, stated_noise):
        t, _ = term_t_ratios(cols, y, lag, noise)
        if t is None:
            continue
        out[target] = [expression_to_string(k) for k, tk in zip(terms, t[1 : 1 + len(terms)], strict=True)
                       if not tk >= min_t]
        # the constant is a column of every fit; a true one (a sensor's bias) is asked the same t
        if 1 in reference and not offset_t_ratio(cols[:, 1:], y, lag, noise) >= min_t:
            out[target].insert(0, "1")
    return out


def true_terms_refit(body_reference: dict[str, sympy.Expr], train: Dataset, gravity: float, weak: bool,
                     height_law: dict[str, sympy.Expr] | None = None) -> tuple[Model, dict[str, float]]:
    """The true terms with their coefficients refit by least squares on the training flight, each term
    (monomial) its own coefficient, the height law one (its scale), a constant only where the reference
    has one, on the rows the engine sees (weak: integrated against the test functions): what this
    flight's targets give the coefficients of the exact structure. Returns (the model: its six targets
    with the scaled law, its body expressions without it, so that the terms compare with the no-ground
    reference; per target with a law, the law's relative error |scale - 1|, which is its relative RMS
    error as height_law_error measures it). Scored as a row beside the engines (score_true_terms_refit),
    not a baseline: no floor is judged against it; an engine that ties terms the physics ties (ub (u1 +
    .. + u4) as one term) fits fewer coefficients and can do better."""
    body: dict[str, sympy.Expr] = {}
    full: dict[str, sympy.Expr] = {}
    law_errors: dict[str, float] = {}
    for target, terms, reference, cols, y, _lag, _noise, law in _true_structure_rows(
            body_reference, train, gravity, weak, height_law, False):
        use = cols if 1 in reference else cols[:, 1:]
        coef, *_ = np.linalg.lstsq(use, y, rcond=None)
        coef = coef if 1 in reference else np.concatenate([[0.0], coef])
        parts = [sympy.Float(float(c)) * k for c, k in zip(coef[1 : 1 + len(terms)], terms, strict=True)]
        body[target] = sympy.Float(float(coef[0])) + sympy.Add(*parts)
        full[target] = body[target]
        if law != 0:
            full[target] += sympy.Float(float(coef[-1])) * law
            law_errors[target] = abs(float(coef[-1]) - 1.0)
    body = {n: body.get(n, sympy.Integer(0)) for n in BODY_TARGET_NAMES}
    full = {n: full.get(n, sympy.Integer(0)) for n in BODY_TARGET_NAMES}
    ned = {**compose_ned(full, gravity), **{n: to_variables(full[n]) for n in ("dwx", "dwy", "dwz")}}
    fitted = BodyModel({n: TargetModel(n, e, engine=TRUE_TERMS_REFIT) for n, e in body.items()},
                       primitive_info(), gravity)
    return Model(ned, body=fitted), law_errors


def score_true_terms_refit(case: str, refit: tuple[Model, dict[str, float]], val: Dataset, reference: Model,
                           body_reference: dict[str, sympy.Expr], wall: float, cpu: float, weak: bool,
                           unidentifiable: dict[str, list[str]],
                           height_reference: dict[str, sympy.Expr] | None) -> Row:
    """true_terms_refit's row: scored as an engine's (score), its terms against the no-ground reference
    and its law by its scale (a true law's expression is no sum of height terms alone: score's split of a
    learned law would take its far-field part for terms)."""
    model, law_errors = refit
    row = score(case, TRUE_TERMS_REFIT, model, val, reference, body_reference, wall, cpu, weak=weak,
                unidentifiable=unidentifiable)
    laws = {n: law_errors.get(n) for n, e in (height_reference or {}).items() if e != 0}
    if not laws:
        return row
    errors = [(e, f"{n}: the height law") for n, e in laws.items() if e is not None]
    errors += [(row.max_error, row.worst)] if np.isfinite(row.max_error) else []
    worst = max(errors, key=lambda pair: pair[0]) if errors else (row.max_error, row.worst)
    return replace(row, found=row.found + len(laws), reference_terms=row.reference_terms + len(laws),
                   height_law=laws, max_error=worst[0], worst=worst[1])


def score(case: str, engine: str, model: Model, val: Dataset, reference: Model,
          body_reference: dict[str, sympy.Expr], wall: float, cpu: float, weak: bool = False,
          unidentifiable: dict[str, list[str]] | None = None,
          height_reference: dict[str, sympy.Expr] | None = None) -> Row:
    """Validation R^2 and the term comparison against the reference (body frame where the model has one;
    weak: R^2 of the weak form, the validation flight's raw sensor targets and the model both integrated
    against the same test functions). unidentifiable: per body target, true terms the flight cannot pin
    down (unidentifiable_terms): not counted missing, not held to the coefficient floor. height_reference:
    the true height-dependent parts of a non-monomial height law (ground effect; body_reference is then the
    rest): compared over the validation rows."""
    if weak:
        op = weak_rows(val.t, val.flight, WeakSettings())
        pred = np.atleast_2d(model.evaluate(val.xi, val.u))
        metrics = {n: weak_metrics(val.targets[:, TARGET_NAMES.index(n)], pred[:, j], op)
                   for j, n in enumerate(model.target_names)}
    else:
        _, metrics = evaluate_model(model, val)
    law: dict[str, float | None] = {}
    law_found = 0
    law_extra: list[str] = []
    hidden: dict[str, list[str]] = {}
    if model.body is not None:
        learned = {n: t.expression for n, t in model.body.targets.items()}
        if height_reference is not None:
            near = {n: height_terms(e) for n, e in learned.items()}
            law = height_law_errors(learned, height_reference, val)
            learned = {n: sympy.expand(e) - near[n] for n, e in learned.items()}
            law_found = sum(1 for n, e in law.items() if e is not None)
            law_extra = [f"{n}: {t}" for n, e in near.items() if n not in law for t in sympy.Add.make_args(e)
                         if e != 0]
        comps = compare_expressions(learned, body_reference)
        frame = "body"
        hidden = unidentifiable or {}
    else:
        comps, frame = compare_models(model, reference), "NED"
    found = sum(sum(1 for r in c.rows if r.status == "both") for c in comps) + law_found
    errs = [(r.relative_error, f"{c.target}: {r.term}") for c in comps for r in c.rows
            if r.relative_error is not None and r.term not in hidden.get(c.target, ())]
    errs += [(e, f"{n}: the height law") for n, e in law.items() if e is not None]
    worst = max(errs, key=lambda pair: pair[0]) if errs else (float("nan"), "")
    ref_terms = sum(sum(1 for r in c.rows if r.reference is not None) for c in comps) + len(law)
    missing = [f"{c.target}: {t}" for c in comps for t in c.missing if t not in hidden.get(c.target, ())]
    missing += [f"{n}: the height law f(h)" for n, e in law.items() if e is None]
    unseen = [f"{c.target}: {t}" for c in comps for t in c.missing if t in hidden.get(c.target, ())]
    extra = [f"{c.target}: {t}" for c in comps for t in c.extra] + law_extra
    return Row(case, engine, {n: metrics[n]["r2"] for n in TARGET_NAMES}, found, len(missing), len(extra),
               ref_terms, worst[0], wall, cpu, frame, missing, extra,
               unidentifiable_missing=unseen, unidentifiable=sum(len(v) for v in hidden.values()),
               scored="weak" if weak else "point", height_law=law, worst=worst[1])


def height_law_errors(learned: dict[str, sympy.Expr], truth: dict[str, sympy.Expr],
                      val: Dataset) -> dict[str, float | None]:
    """Per target with a true height law: the relative RMS error of the learned height-dependent part
    against the true one over the validation flight's rows (None when the learned target has none)."""
    X = np.hstack([val.xi, val.u])
    return {n: height_law_error(learned.get(n, sympy.Integer(0)), e, X) for n, e in truth.items() if e != 0}


def table(rows: list[Row]) -> str:
    """The benchmark table as Markdown."""
    head = ("| case | engine | " + " | ".join(f"R^2 {n}" for n in TARGET_NAMES)
            + " | true terms found / missing / extra (of N, frame) | not identifiable | largest coef. error "
            "| wall [s] | CPU [s] |")
    lines = [head, "|" + "---|" * (len(TARGET_NAMES) + 7)]
    for r in rows:
        r2 = " | ".join(f"{r.r2[n]:.6f}" for n in TARGET_NAMES)
        lines.append(f"| {r.case} | {r.engine} | {r2}{' (weak)' if r.scored == 'weak' else ''} | {r.found} / "
                     f"{r.missing} / {r.extra} (of {r.reference_terms}, {r.frame}) | {r.unidentifiable} "
                     f"| {r.max_error:.2e} | {r.wall_s:.1f} | {r.cpu_s:.1f} |")
    return "\n".join(lines)


def write_outputs(rows: list[Row], floors: list[tuple[str, bool]], out: Path,
                  stem: str = "discovery", settings: list[str] | None = None,
                  notes: list[str] | None = None) -> None:
    """OUT/<stem>.md (the baselines' settings, the table, the floors, ours' missing/extra terms, the
    per-case notes) and OUT/<stem>.csv."""
    md = [*[f"- {line}" for line in settings or []], *([""] if settings else []), table(rows), "",
          *[f"- [{'PASS' if ok else 'FAIL'}] {label}" for label, ok in floors], ""]
    for r in rows:
        left_out = r.missing_terms or r.extra_terms or r.unidentifiable_missing
        if r.engine.startswith("discovery") and left_out:
            md.append(f"- {r.case} ({r.engine}): missing {', '.join(r.missing_terms) or '-'}; "
                      f"extra {', '.join(r.extra_terms) or '-'}; left out and not identifiable from the "
                      f"flight: {', '.join(r.unidentifiable_missing) or '-'}")
        if r.engine.startswith("discovery") and r.height_law:
            md.append(f"- {r.case}: height law, relative RMS error over the validation rows: " + ", ".join(
                f"{n} {'not found' if e is None else f'{e:.2%}'}" for n, e in r.height_law.items()))
    md += [f"- {line}" for line in notes or []]
    (out / f"{stem}.md").write_text("\n".join(md) + "\n", encoding="utf-8")
    with (out / f"{stem}.csv").open("w", newline="", encoding="utf-8") as fh:
        w = csv.writer(fh)
        w.writerow(["case", "engine", "scored", *[f"r2_{n}" for n in TARGET_NAMES], "found", "missing",
                    "extra", "reference_terms", "not_identifiable", "frame", "max_coef_error", "wall_s",
                    "cpu_s", "max_coef_term"])
        for r in rows:
            w.writerow([r.case, r.engine, r.scored, *[f"{r.r2[n]:.9f}" for n in TARGET_NAMES], r.found,
                        r.missing, r.extra, r.reference_terms, r.unidentifiable, r.frame,
                        f"{r.max_error:.6g}", f"{r.wall_s:.2f}", f"{r.cpu_s:.2f}", r.worst])


def case_data(case: Case, args: argparse.Namespace, out: Path):
    """(train, validation, NED reference Model, body-frame reference expressions, gravity, .tlog paths)."""
    from bridge.vehicle import load_vehicle

    if case.sitl_vehicle is not None:
        vehicle = flown_vehicle(case)
        train, val, tlogs = sitl_flights(case, out, args.seed, args.train_duration, vehicle.gravity,
                                         args.reuse_flights)
        body = sensor_reference(case, vehicle, true_body_expressions(vehicle))
        return train, val, true_model(vehicle), body, vehicle.gravity, tlogs
    train = synthetic(case, args.rows, args.seed)
    val = synthetic(case, args.rows // 2, args.seed + 1000)
    return (train, val, reference_model(case.effects), body_expressions(VEHICLE, case.effects),
            load_vehicle(VEHICLE).gravity, [])


def sensor_reference(case: Case, vehicle, body: dict[str, sympy.Expr]) -> dict[str, sympy.Expr]:
    """Body-frame reference expressions as the law of what a sensor case measures: the measured specific
    force holds the accelerometer's bias (m/s^2, FRD) as the constants of fx fy fz. The gyro's bias is in
    none of the data: the rates a model reads are the log's state (HIL_STATE_QUATERNION's, the true rates;
    identification.readers.tlog), and the angular-acceleration targets are the gyro's differences over a
    step, where a constant bias cancels (tests/test_bench_reference.py flies one and checks both). The
    identical expressions on a truth case."""
    if case.targets != "sensors":
        return body
    bias = vehicle.with_overrides(sensors=case.sensors).sensors.effective().accel.bias
    return {n: e + (sympy.Float(b) if n in ("fx", "fy", "fz") else 0) for n, e, b in
            zip(body, body.values(), (*bias, 0.0, 0.0, 0.0), strict=True)}


def height_law_reference(case: Case) -> tuple[dict[str, sympy.Expr], dict[str, sympy.Expr]] | None:
    """(the rest, the height law) of the flown vehicle's true body-frame expressions when it has a ground
    effect, which is no monomial of the primitives: the rest is the vehicle's physics with no ground (h ->
    infinity), the height law the difference (fz, dwx, dwy); None without one."""
    if case.sitl_vehicle is None:
        return None
    vehicle = flown_vehicle(case)
    if vehicle.ground != "plane" or vehicle.aero.ground_effect is None:
        return None
    # both as a sensor case measures them (case_data's reference too): the rest keeps the accelerometer's
    # bias, the law has none
    full = sensor_reference(case, vehicle, true_body_expressions(vehicle))
    far = sensor_reference(case, vehicle, true_body_expressions(vehicle.with_overrides(ground="none")))
    return far, {n: full[n] - far[n] for n in full}  # fx fy dwz: exactly 0


def case_floors(case: Case, case_rows: list[Row], train_duration: float) -> list[tuple[str, bool]]:
    """The floors of ours on one case (none when ours did not run)."""
    mine = "discovery-weak" if case.targets == "sensors" else "discovery"
    ours = next((r for r in case_rows if r.engine == mine), None)
    if ours is None:
        return []
    r2_floor, coef_floor = FLOORS[case.targets]
    low = min(ours.r2.values())
    refit = next((r for r in case_rows if r.engine == TRUE_TERMS_REFIT), None)
    floors = [
        (f"{case.name}: the true terms and no others ({ours.frame} frame)",
         ours.missing == 0 and ours.extra == 0),
        (f"{case.name}: coefficients within {coef_floor:.0%} (of the terms the flight identifies)"
         + (f": largest {ours.max_error:.2%} ({ours.worst})" if ours.worst else "")
         + (f"; the true terms refit on the training flight: {refit.max_error:.1%} ({refit.worst})"
            if refit is not None and refit.max_error > coef_floor else ""),
         ours.max_error <= coef_floor),
        (f"{case.name}: validation R^2 >= {r2_floor} on every target", low >= r2_floor),
        (f"{case.name}: at most 1.5x the true term count",
         ours.found + ours.extra <= 1.5 * ours.reference_terms),
    ]
    others = [r for r in case_rows if r.engine in BASELINES]
    if others:
        floors.append((f"{case.name}: lowest R^2 at least every baseline's ({len(others)} run)",
                       all(low >= min(r.r2.values()) - 1e-9 for r in others)))
    else:  # a floor nothing was measured against is not met: the run cannot print PASS
        floors.append((f"{case.name}: lowest R^2 at least every baseline's (not evaluated: no baseline in "
                       "--engines)", False))
    if case.sitl_vehicle is not None and train_duration >= 60:
        floors.append((f"{case.name}: a 60 s flight identified in under 2 minutes on {default_jobs()} cores "
                       f"({ours.wall_s:.1f} s wall, {ours.cpu_s:.1f} s CPU over its processes)",
                       ours.wall_s < 120))
    return floors


def report_row(row: Row) -> None:
    """Print one row as it is done (and ours' missing and extra terms)."""
    print(f"  {row.engine}: lowest R^2 {min(row.r2.values()):.6f} ({row.scored}), terms {row.found}/"
          f"{row.missing}/{row.extra} of {row.reference_terms} ({row.frame}; {row.unidentifiable} not "
          f"identifiable from the flight), coef. error {row.max_error:.2e}"
          f"{f' ({row.worst})' if row.worst else ''}, {row.wall_s:.1f} s wall, "
          f"{row.cpu_s:.1f} s CPU", flush=True)
    if row.engine.startswith("discovery") and (row.missing_terms or row.extra_terms):
        print(f"    missing: {', '.join(row.missing_terms) or '-'}\n"
              f"    extra: {', '.join(row.extra_terms) or '-'}", flush=True)
    if row.engine.startswith("discovery") and row.unidentifiable_missing:
        print(f"    left out, not identifiable from the flight: {', '.join(row.unidentifiable_missing)}",
              flush=True)
    if row.height_law:
        print("    height law, relative RMS error over the validation rows: " + ", ".join(
            f"{n} {'not found' if e is None else f'{e:.2%}'}" for n, e in row.height_law.items()), flush=True)


def main() -> int:
    """Run the cases and engines, print the table and the floors; 0 when every floor holds."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cases", default=None, help="comma-separated case names (default: all)")
    ap.add_argument("--engines", default=",".join(ENGINES), help=f"comma-separated, of {', '.join(ENGINES)}")
    ap.add_argument("--rows", type=int, default=4000, help="synthetic rows per flight (250 Hz: 16 s)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--settings", default=None,
                    help="engine settings YAML for ours and sparse (as identify's --settings; default: none)")
    ap.add_argument("--operon-generations", type=int, default=OPERON_GENERATIONS,
                    help="the pyoperon-alone baseline's generations per target")
    ap.add_argument("--budget", type=int, default=DEFAULT_BUDGET,
                    help="the discovery engine's genetic-programming generations per target")
    ap.add_argument("--train-duration", type=float, default=60.0, help="SITL training flight, s simulated")
    ap.add_argument("--out", default="results/discovery", help="folder for SITL flights and the table")
    ap.add_argument("--reuse-flights", action="store_true",
                    help="read the SITL flights a previous run left in --out (same seed and duration)")
    roles = ap.add_mutually_exclusive_group()
    roles.add_argument("--validation-flight", action="store_true",
                       help="give ours the case's validation flight as its validation role (as `quadsr "
                            "identify --validate-log`), so the whole training flight fits and picks (the "
                            "default since session 22)")
    roles.add_argument("--own-validation-block", action="store_true",
                       help="ours keeps the training flight's last fifth to validate on (identify's roles "
                            "for one flight; the bench's default until session 21)")
    ap.add_argument("--jobs", type=int, default=default_jobs(),
                    help="processes identify fits the targets in side by side (default: every core); the "
                         "models are the same for any value")
    ap.add_argument("--pick-blocks", type=int, default=1,
                    help="ours picks on the training flight's pick time spread over this many blocks "
                         "(identify --pick-blocks; docs/discovery-log.md, session 14)")
    args = ap.parse_args()
    args.validation_flight = not args.own_validation_block
    engines = [e.strip() for e in args.engines.split(",") if e.strip()]
    for e in engines:  # before any flight is flown
        check_engine(e)
    names = None if args.cases is None else [c.strip() for c in args.cases.split(",")]
    unknown = [n for n in names or [] if n not in {c.name for c in CASES}]
    if unknown:
        raise SystemExit(f"unknown case {unknown[0]!r} (known: {', '.join(c.name for c in CASES)})")
    cases = [c for c in CASES if names is None or c.name in names]
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows: list[Row] = []
    floors: list[tuple[str, bool]] = []
    notes: list[str] = []  # per-case lines for the results md beside ours' missing/extra terms
    try:
        ours = load_engine_settings(args.settings)
    except UserError as exc:
        raise SystemExit(f"error: {exc}") from None
    settings = baseline_settings(engines, args.operon_generations, args.seed)
    for line in settings:
        print(f"baseline {line}")
    if args.settings:
        settings.insert(0, f"ours and sparse with the engine settings of {args.settings}")
        print(settings[0])
    if args.pick_blocks != 1:
        settings.insert(0, f"ours, sparse and pyoperon alone pick on {args.pick_blocks} blocks spread over "
                           "the training flight")
        print(settings[0])
    if args.validation_flight:
        settings.insert(0, "ours, sparse and pyoperon alone validate on the validation flight (the whole "
                           "training flight fits and picks)")
        print(settings[0])
    for case in cases:
        if case.sitl_vehicle is not None and vehicle_file(case.sitl_vehicle) is None:
            print(f"== {case.name}: vehicle {case.sitl_vehicle!r} not in this checkout: not run")
            continue
        train, val, reference, body_reference, gravity, tlogs = case_data(case, args, out)
        split = height_law_reference(case)
        body_reference, height_reference = split if split is not None else (body_reference, None)
        print(f"== {case.name}: {len(train)} training rows, {len(val)} validation rows")
        # sensor cases: every engine's model is scored in the weak form on the validation flight's raw sensor
        # targets (the same measure for ours and the baselines); ours also learns from them (discovery-weak)
        weak_case = case.targets == "sensors"
        raw_train = raw_val = None
        if weak_case:
            raw_train, raw_val = (load_dataset(p, targets="sensors", sensor_settings=RAW_SENSOR_TARGETS,
                                               gravity=gravity) for p in tlogs)
        rule = (ours or EngineSettings()).selection  # the pick's t rule, as ours runs it
        hidden = unidentifiable_terms(body_reference, raw_train if weak_case else train, gravity, weak_case,
                                      min_t=rule.min_t, height_law=height_reference,
                                      stated_noise=rule.stated_noise_t)
        if any(hidden.values()):
            print(f"  true terms this training flight cannot pin down (t < {rule.min_t:g} "
                  f"given the true structure): {listed_terms(hidden)}")
        if not args.validation_flight:  # ours keeps its own validation block: fewer rows to fit on
            own = fit_and_pick_rows(raw_train if weak_case else train)
            fewer = unidentifiable_terms(body_reference, own, gravity, weak_case, min_t=rule.min_t,
                                         height_law=height_reference, stated_noise=rule.stated_noise_t)
            fewer = {k: [t for t in v if t not in hidden.get(k, [])] for k, v in fewer.items()}
            if any(fewer.values()):
                notes.append(f"{case.name}: true terms the whole training flight pins down but its fit and "
                             f"pick rows alone (identify's own blocks, the validation block held out) do not "
                             f"(t < {rule.min_t:g} given the true structure; still counted "
                             f"missing and held to the coefficient floor): {listed_terms(fewer)}")
                print(f"  {notes[-1]}")
        case_rows = []
        models_dir = out / "models"
        models_dir.mkdir(exist_ok=True)
        slug = "".join(ch if ch.isalnum() else "-" for ch in case.name)
        for engine in engines:
            start, cpu_start = time.perf_counter(), cpu_seconds()
            model = fit(engine, train, args.seed, gravity, args.budget, args.operon_generations, ours,
                        validate=val if args.validation_flight else None, pick_blocks=args.pick_blocks,
                        jobs=args.jobs)
            wall, cpu = time.perf_counter() - start, cpu_seconds() - cpu_start
            save_model(model, models_dir / f"{slug}-{engine}.yaml")  # to trace a row's terms afterwards
            row = score(case.name, engine, model, raw_val if weak_case else val, reference, body_reference,
                        wall, cpu, weak=weak_case, unidentifiable=hidden,
                        height_reference=height_reference)
            if weak_case and engine == "discovery":  # ours, also learned in the weak form
                case_rows.append(row)
                report_row(row)
                start, cpu_start = time.perf_counter(), cpu_seconds()
                model = identify(raw_train, budget=args.budget, seed=args.seed, progress=False,
                                 gravity=gravity, weak=WeakSettings(), settings=ours,
                                 validate=raw_val if args.validation_flight else None,
                                 pick_blocks=args.pick_blocks, jobs=args.jobs)
                wall, cpu = time.perf_counter() - start, cpu_seconds() - cpu_start
                save_model(model, models_dir / f"{slug}-discovery-weak.yaml")
                row = score(case.name, "discovery-weak", model, raw_val, reference, body_reference, wall, cpu,
                            weak=True, unidentifiable=hidden, height_reference=height_reference)
            case_rows.append(row)
            report_row(row)
        # what the flight gives the exact structure's coefficients, as a row of the table (no floor)
        start, cpu_start = time.perf_counter(), cpu_seconds()
        refit = true_terms_refit(body_reference, raw_train if weak_case else train, gravity, weak_case,
                                 height_law=height_reference)
        wall, cpu = time.perf_counter() - start, cpu_seconds() - cpu_start
        row = score_true_terms_refit(case.name, refit, raw_val if weak_case else val, reference,
                                     body_reference, wall, cpu, weak_case, hidden, height_reference)
        case_rows.append(row)
        report_row(row)
        rows += case_rows
        floors += case_floors(case, case_rows, args.train_duration)
        write_outputs(rows, floors, out, settings=settings, notes=notes)
    print()
    print("\n".join(f"- {line}" for line in settings))
    print(table(rows))
    print()
    for label, ok in floors:
        print(f"[{'PASS' if ok else 'FAIL'}] {label}")
    ok = bool(floors) and all(ok for _, ok in floors)
    print("PASS" if ok else "FAIL")
    print(f"(table: {out / 'discovery.md'}, {out / 'discovery.csv'})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
