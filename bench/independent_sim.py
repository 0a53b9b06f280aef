"""A quadrotor from an independent simulator (RotorPy), identified as a new user would (issue 12).

RotorPy 3.0.0 (`pip install -e .[bench]`) flies its AscTec Hummingbird with its aerodynamics on (rotor drag
k_d/k_z at each hub, translational lift k_h, parasitic drag c_D |v| v, first-order motor lag tau_m) under
its own SE(3) controller following a Lissajous path with a turning heading, with seeded per-motor PRBS added
to the commanded rotor speeds (so the rotors are not tied to the attitude). Two flights with different
seeds: one to identify, one to validate. Each is converted to quadsr's conventions and written in quadsr's
documented table format (README, "Tables from anywhere"): RotorPy's world is z-up and its body FLU, quadsr's
NED and FRD; both flips are the rotation by pi about x, T = diag(1, -1, -1):
  p_NED = T p_world, v_NED = T v_world, R_NED<-FRD = T R_world<-FLU T, q = (w, x, -y, -z) (scalar first),
  w_FRD = T w_FLU, accelerations likewise; rotors to PX4 Quad-X order (u1 front-right, u2 rear-left,
  u3 front-left, u4 rear-right) from RotorPy's r1 front-left, r2 front-right, r3 rear-right, r4 rear-left.
The accelerations written (ax ay az NED m/s^2, dwx dwy dwz FRD rad/s^2) are RotorPy's own state derivative
(`Multirotor.statedot`) at each logged state, as RotorPy's simulate returns them (truth targets).
RotorPy's g is 9.81 m/s^2, given to `quadsr identify --gravity 9.81` as a user who knows their
simulator's would (without it 9.80665 is removed and 0.00335 R^T e_z m/s^2 is left in fx fy fz, no
function of the default primitives); a true term the training flight cannot pin down even given the true
structure (t below selection.min_t, bench/discovery.py's unidentifiable_terms) is listed apart.

Then quadsr as a new user runs it, in separate processes: `quadsr identify train.csv -o model.yaml
--gravity 9.81` (defaults otherwise) and `quadsr validate model.yaml validate.csv`. The learned body-frame
expressions are compared with RotorPy's true physics written out from its parameters
(`true_body_physics`, checked here against RotorPy's own derivative on every logged row), monomial by
monomial. Baselines on the same data, from bench/discovery.py: OLS on a 3-term physics library and
PySINDy with the physics library. One table
(OUT/independent_sim.md, .csv), a PNG (OUT/independent_sim.png), PASS/FAIL per the issue's floors (truth
targets: R^2 >= 0.9999 on the other flight, coefficients within 5 %, the true terms and no others, at
most 1.5x the true term count, at least as good as every baseline; a 60 s flight in under 2 CPU minutes).

Usage: python bench/independent_sim.py [--duration S] [--seed N] [--out DIR] [--reuse-flights]
"""

from __future__ import annotations

import argparse
import resource
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import sympy

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from identification.body_frame import (  # noqa: E402
    PRIMITIVE_SYMBOLS,
    body_targets,
    compose_ned,
    primitive_matrix,
    to_variables,
)
from identification.dataset import load_dataset  # noqa: E402
from identification.engine_settings import SelectionSettings  # noqa: E402
from identification.model_file import TARGET_NAMES, Model, load_model  # noqa: E402

FLIP = np.diag([1.0, -1.0, -1.0])  # z-up world -> NED, FLU body -> FRD (rotation by pi about x)
ROTORPY_GRAVITY = 9.81  # m/s^2, Multirotor.g; quadsr identify without --vehicle removes 9.80665
ROTOR_ORDER = (1, 3, 0, 2)  # PX4 Quad-X u1..u4 <- RotorPy rotor index (r2 FR, r4 RL, r1 FL, r3 RR)
STEP = 0.004  # s, RotorPy step and logging interval (250 Hz)
COLUMNS = ("t", "x", "y", "z", "vx", "vy", "vz", "qw", "qx", "qy", "qz", "wx", "wy", "wz",
           "u1", "u2", "u3", "u4", "ax", "ay", "az", "dwx", "dwy", "dwz")


def to_ned_frd(x: np.ndarray, v: np.ndarray, q_xyzw: np.ndarray, w: np.ndarray, rotor_speeds: np.ndarray,
               vdot: np.ndarray, wdot: np.ndarray) -> dict[str, np.ndarray]:
    """quadsr's table columns from RotorPy's arrays (N,3 world z-up m, m/s, m/s^2; N,4 quaternion FLU->world
    scalar last; N,3 body FLU rad/s, rad/s^2; N,4 rotor speeds rad/s in RotorPy's order)."""
    x, v, vdot = (np.asarray(a, dtype=float) @ FLIP for a in (x, v, vdot))
    w, wdot = (np.asarray(a, dtype=float) @ FLIP for a in (w, wdot))
    q = np.asarray(q_xyzw, dtype=float)
    sign = np.where(q[:, 3:4] < 0, -1.0, 1.0)  # scalar part >= 0: one of the two equal quaternions
    qw, qx, qy, qz = (sign[:, 0] * c for c in (q[:, 3], q[:, 0], -q[:, 1], -q[:, 2]))
    u = np.asarray(rotor_speeds, dtype=float)[:, list(ROTOR_ORDER)]
    cols = dict(zip(("x", "y", "z"), x.T, strict=True)) | dict(zip(("vx", "vy", "vz"), v.T, strict=True))
    cols |= {"qw": qw, "qx": qx, "qy": qy, "qz": qz}
    cols |= dict(zip(("wx", "wy", "wz"), w.T, strict=True)) | {f"u{i + 1}": u[:, i] for i in range(4)}
    cols |= dict(zip(("ax", "ay", "az"), vdot.T, strict=True))
    cols |= dict(zip(("dwx", "dwy", "dwz"), wdot.T, strict=True))
    return cols


def true_body_physics(params: dict) -> dict[str, sympy.Expr]:
    """RotorPy's body wrench (Multirotor.compute_body_wrench, aero on, still air) written out from its
    parameters in quadsr's primitives: fx fy fz specific force FRD (m/s^2), dwx dwy dwz FRD (rad/s^2)."""
    P = PRIMITIVE_SYMBOLS
    flip = sympy.Matrix(FLIP.astype(int))
    va = flip * sympy.Matrix([P["ub"], P["vb"], P["wb"]])  # body airspeed FLU
    w = flip * sympy.Matrix([P["wx"], P["wy"], P["wz"]])  # body rates FLU
    f = sympy.Float
    speeds = {rp: P[f"u{i + 1}"] for i, rp in enumerate(ROTOR_ORDER)}  # RotorPy index -> primitive
    drag = sympy.diag(f(params["k_d"]), f(params["k_d"]), f(params["k_z"]))
    force, moment = sympy.zeros(3, 1), sympy.zeros(3, 1)
    for i, key in enumerate(params["rotor_pos"]):
        r = sympy.Matrix([f(c) for c in params["rotor_pos"][key]])
        vi = va + w.cross(r)  # the hub's airspeed FLU
        om = speeds[i]
        thrust = f(params["k_eta"]) * om**2 + f(params["k_h"]) * (vi[0] ** 2 + vi[1] ** 2)
        fi = sympy.Matrix([0, 0, thrust]) - om * (drag * vi)
        force += fi
        moment += r.cross(fi)
        moment[2] += f(params["rotor_directions"][i] * params["k_m"]) * om**2
    speed = sympy.sqrt(P["ub"] ** 2 + P["vb"] ** 2 + P["wb"] ** 2)
    force -= speed * sympy.diag(f(params["c_Dx"]), f(params["c_Dy"]), f(params["c_Dz"])) * va
    inertia = np.array([[params["Ixx"], params["Ixy"], params["Ixz"]],
                        [params["Ixy"], params["Iyy"], params["Iyz"]],
                        [params["Ixz"], params["Iyz"], params["Izz"]]], dtype=float)
    jmat = sympy.Matrix(3, 3, lambda a, b: f(inertia[a, b]))
    jinv = sympy.Matrix(3, 3, lambda a, b: f(np.linalg.inv(inertia)[a, b]))
    dw = jinv * (moment - w.cross(jmat * w))
    fb, dwb = flip * force / f(params["mass"]), flip * dw
    names = ("fx", "fy", "fz", "dwx", "dwy", "dwz")
    return {n: sympy.expand(e) for n, e in zip(names, [*fb, *dwb], strict=True)}


def fly(seed: int, duration: float) -> dict[str, np.ndarray]:
    """One RotorPy Hummingbird flight (aero on), SE(3) control on a seeded Lissajous with a turning heading
    plus per-motor PRBS on the commanded speeds; quadsr's table columns at STEP."""
    from rotorpy.controllers.quadrotor_control import SE3Control
    from rotorpy.trajectories.lissajous_traj import TwoDLissajous
    from rotorpy.vehicles.hummingbird_params import quad_params
    from rotorpy.vehicles.multirotor import Multirotor

    rng = np.random.default_rng(seed)
    hover = float(np.sqrt(quad_params["mass"] * 9.81 / (4 * quad_params["k_eta"])))  # rad/s
    traj = TwoDLissajous(A=rng.uniform(2, 4), B=rng.uniform(2, 4), a=rng.uniform(0.6, 1.0),
                         b=rng.uniform(0.4, 0.8), delta=rng.uniform(0, np.pi), height=10.0, yaw_bool=True)
    start = traj.update(0.0)
    state = {"x": np.array(start["x"], dtype=float), "v": np.array(start["x_dot"], dtype=float),
             "q": np.array([0.0, 0.0, 0.0, 1.0]), "w": np.zeros(3), "wind": np.zeros(3),
             "rotor_speeds": np.full(4, hover)}
    quad = Multirotor(quad_params, initial_state=state, control_abstraction="cmd_motor_speeds", aero=True)
    ctrl = SE3Control(quad_params)
    n = int(round(duration / STEP))
    sizes = (("x", 3), ("v", 3), ("q", 4), ("w", 3), ("r", 4), ("vd", 3), ("wd", 3))
    rec = {k: np.empty((n, d)) for k, d in sizes}
    prbs = np.zeros(4)
    for k in range(n):
        if k % 10 == 0:  # a new level every 40 ms with probability 1/2 per motor: +-8 % of hover speed
            switch = rng.random(4) < 0.5
            prbs[switch] = rng.choice([-0.08 * hover, 0.08 * hover], size=int(switch.sum()))
        cmd = ctrl.update(k * STEP, state, traj.update(k * STEP))
        speeds = np.clip(cmd["cmd_motor_speeds"] + prbs, 0.0, quad_params["rotor_speed_max"])
        cmd = {"cmd_motor_speeds": speeds}
        sd = quad.statedot(state, cmd, STEP)
        for key, val in (("x", state["x"]), ("v", state["v"]), ("q", state["q"]), ("w", state["w"]),
                         ("r", state["rotor_speeds"]), ("vd", sd["vdot"]), ("wd", sd["wdot"])):
            rec[key][k] = val
        state = quad.step(state, cmd, STEP)
    cols = to_ned_frd(rec["x"], rec["v"], rec["q"], rec["w"], rec["r"], rec["vd"], rec["wd"])
    return {"t": np.arange(n) * STEP, **cols}


def write_table(path: Path, cols: dict[str, np.ndarray]) -> None:
    """quadsr's CSV table (README "Tables from anywhere"), full float precision."""
    data = np.column_stack([cols[c] for c in COLUMNS])
    np.savetxt(path, data, delimiter=",", header=",".join(COLUMNS), comments="", fmt="%.17g")


def physics_check(cols: dict[str, np.ndarray], body: dict[str, sympy.Expr]) -> float:
    """Largest |written physics - RotorPy's derivative| over the rows, in the body frame (m/s^2, rad/s^2)."""
    names = ("ub", "vb", "wb", "wx", "wy", "wz", "u1", "u2", "u3", "u4")
    euler = _euler(cols)
    X = np.column_stack([cols[c] for c in ("x", "y", "z", "vx", "vy", "vz")] + list(euler.T)
                        + [cols[c] for c in ("wx", "wy", "wz", "u1", "u2", "u3", "u4")])
    prim = primitive_matrix(X, names)
    targets = np.column_stack([cols[c] for c in TARGET_NAMES])
    meas = body_targets(X[:, :12], targets, ROTORPY_GRAVITY)
    worst = 0.0
    for j, name in enumerate(("fx", "fy", "fz", "dwx", "dwy", "dwz")):
        fn = sympy.lambdify([PRIMITIVE_SYMBOLS[s] for s in names], body[name], "numpy")
        worst = max(worst, float(np.max(np.abs(fn(*prim.T) - meas[:, j]))))
    return worst


def _euler(cols: dict[str, np.ndarray]) -> np.ndarray:
    from bridge.rotations import euler_from_quaternions

    return euler_from_quaternions(np.column_stack([cols[c] for c in ("qw", "qx", "qy", "qz")]))


def quadsr(*args: str, log: Path) -> tuple[int, float, float]:
    """Run `python -m quadsr.cli ARGS` as a user would; (exit code, wall s, CPU s of the child)."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    start = time.perf_counter()
    with log.open("w", encoding="utf-8") as fh:
        rc = subprocess.run([sys.executable, "-m", "quadsr.cli", *args], cwd=REPO, stdout=fh,
                            stderr=subprocess.STDOUT, check=False).returncode
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return rc, time.perf_counter() - start, cpu


def plot(rows: list, out: Path) -> None:
    """OUT/independent_sim.png: 1 - R^2 per target and engine (log), and term counts."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (a, b) = plt.subplots(1, 2, figsize=(12, 4.5))
    width = 0.8 / len(rows)
    for i, r in enumerate(rows):
        vals = [max(1.0 - r.r2[n], 1e-9) for n in TARGET_NAMES]
        a.bar(np.arange(6) + i * width, vals, width, label=r.engine)
    a.axhline(1e-4, color="k", ls="--", lw=1, label="floor (R^2 = 0.9999)")
    a.set_yscale("log")
    a.set_xticks(np.arange(6) + 0.4 - width / 2, TARGET_NAMES)
    a.set_ylabel("1 - R^2 on the validation flight")
    a.legend(fontsize=8)
    a.set_title("RotorPy Hummingbird (aero on): validation")
    b.bar([r.engine for r in rows], [r.found for r in rows], label="true terms found")
    b.bar([r.engine for r in rows], [r.extra for r in rows], bottom=[r.found for r in rows], label="extra")
    b.scatter([r.engine for r in rows], [r.reference_terms for r in rows], marker="_", s=900, color="k",
              zorder=3, label="true term count (in that frame)")
    b.set_yscale("log")
    b.set_ylabel("terms")
    b.legend(fontsize=8)
    b.set_title("terms (ours: body frame; baselines: NED)")
    fig.tight_layout()
    fig.savefig(out / "independent_sim.png", dpi=110)


def main() -> int:
    """Fly, convert, identify as a user, compare; print the table and PASS only when every floor holds."""
    import discovery as disc  # bench/discovery.py: scoring, baselines, table, floors
    from rotorpy.vehicles.hummingbird_params import quad_params

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--duration", type=float, default=60.0, help="each flight, s simulated")
    ap.add_argument("--seed", type=int, default=0, help="training flight seed (validation: seed + 1)")
    ap.add_argument("--out", default="results/independent_sim")
    ap.add_argument("--reuse-flights", action="store_true",
                    help="read the tables a previous run left in --out")
    args = ap.parse_args()
    out = Path(args.out).resolve()
    out.mkdir(parents=True, exist_ok=True)
    body = true_body_physics(quad_params)
    paths = [out / f"rotorpy-hummingbird-{role}-seed{args.seed + k}.csv" for k, role in enumerate(("train",
                                                                                                  "validate"))]
    worst = 0.0
    for k, path in enumerate(paths):
        if not (args.reuse_flights and path.exists()):
            start = time.perf_counter()
            cols = fly(args.seed + k, args.duration)
            write_table(path, cols)
            took = time.perf_counter() - start
            print(f"flew {path.name}: {len(cols['t'])} rows in {took:.1f} s", flush=True)
        cols = {c: np.loadtxt(path, delimiter=",", skiprows=1, usecols=COLUMNS.index(c)) for c in COLUMNS}
        worst = max(worst, physics_check(cols, body))
    print(f"written physics against RotorPy's own derivative, largest difference: {worst:.2e}")
    model_path = out / "model.yaml"
    rc, wall, cpu = quadsr("identify", str(paths[0]), "-o", str(model_path), "--no-progress",
                           "--gravity", f"{ROTORPY_GRAVITY:g}", log=out / "identify.log")
    print(f"quadsr identify: exit {rc}, {wall:.1f} s wall, {cpu:.1f} s CPU (log {out / 'identify.log'})")
    if rc != 0:
        print("FAIL")
        return 1
    rc_v, _, _ = quadsr("validate", str(model_path), str(paths[1]), "--out", str(out / "validation"),
                        log=out / "validate.log")
    print(f"quadsr validate: exit {rc_v} (log {out / 'validate.log'})")
    train, val = load_dataset(paths[0]), load_dataset(paths[1])
    reference = Model({**compose_ned(body, ROTORPY_GRAVITY),
                       **{n: to_variables(body[n]) for n in ("dwx", "dwy", "dwz")}})
    learned_ref = body  # identify is given RotorPy's g (--gravity): nothing of it is left to learn
    hidden = disc.unidentifiable_terms(learned_ref, train, ROTORPY_GRAVITY, weak=False)
    for name, terms in hidden.items():
        if terms:
            print(f"  {name}: true terms this training flight cannot pin down (t < "
                  f"{SelectionSettings().min_t:g} given the true structure): {', '.join(terms)}")
    case = disc.Case("rotorpy hummingbird")
    rows = [disc.score(case.name, "discovery", load_model(model_path), val, reference, learned_ref, wall, cpu,
                       unidentifiable=hidden)]
    for engine in ("ols-3term", "pysindy-physics"):
        start, cpu_start = time.perf_counter(), time.process_time()
        model = disc.fit(engine, train, args.seed, ROTORPY_GRAVITY, 0, 0)
        rows.append(disc.score(case.name, engine, model, val, reference, body, time.perf_counter() - start,
                               time.process_time() - cpu_start))
    floors = disc.case_floors(case, rows, 0.0)
    floors += [(f"written physics equals RotorPy's derivative (largest difference {worst:.1e})",
                worst < 1e-6),
               (f"a {args.duration:g} s flight identified in under 2 minutes of CPU ({cpu:.1f} s CPU, "
                f"{wall:.1f} s wall)", cpu < 120 and args.duration >= 60)]
    disc.write_outputs(rows, floors, out, stem="independent_sim")
    plot(rows, out)
    print()
    print(disc.table(rows))
    print()
    for r in rows[:1]:  # ours (body frame); the baselines' NED lists are in OUT/independent_sim.csv's counts
        if r.missing_terms or r.extra_terms:
            print(f"{r.engine}: missing {', '.join(r.missing_terms) or '-'}")
            print(f"  extra {', '.join(r.extra_terms) or '-'}")
    for label, ok in floors:
        print(f"[{'PASS' if ok else 'FAIL'}] {label}")
    ok = all(ok for _, ok in floors)
    print("PASS" if ok else "FAIL")
    print(f"(table: {out / 'independent_sim.md'}, {out / 'independent_sim.csv'}; "
          f"figure {out / 'independent_sim.png'})")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
