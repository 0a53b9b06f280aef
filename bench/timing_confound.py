"""How far a flight pins down the rate dampings against the timing of its rotor speeds.

The rate damping of wx', wy', wz' (-c w, c ~ 0.005 1/s on the paper's vehicle) is about 1e-4 of those
targets' spread, which the rotor torques (k (u_i^2 - u_j^2), rad/s^2) carry. In closed loop the rate
controller makes the torque follow the rates, so a small shift in time of the rotor speeds against the
IMU's rates changes the torque columns by a part that looks like a damping term. This script measures it:
for each realistic-sensor flight, the true model's structure (identification.true_model, the flown
vehicle's) is fitted by least squares to the weak-form targets (identification.weak_form, the raw IMU
targets integrated against the default test functions, as quadsr identify does on sensor targets) with the
logged rotor speeds moved in time by a fraction of the 250 Hz sample interval (linear interpolation), and
prints each damping coefficient's error against the truth and the fit's residual RMS (rad/s^2) per shift.

A flight pins a damping down when the residual rises clearly as the shift leaves zero and the coefficient
barely moves; when the residual stays flat over shifts that move the coefficient by tens of percent, the
flight cannot tell the damping from the rotor speeds' timing (a motor's lag, a log's timestamps), whatever
its t ratio says. Measured figures only, no floor.

Default flights: closed-loop (from the ground, hover stabiliser with per-motor PRBS) and paper-train (open
loop, the paper's motor steps), both with `--sensors realistic`, flown in the SITL (separate `quadsr sitl`
processes). --logs takes existing .tlog files instead (with --vehicle, the vehicle they were flown with).

Usage: python bench/timing_confound.py [--out DIR] [--seed N] [--logs A.tlog,B.tlog] [--vehicle NAME]
                                       [--shifts F,F,...]
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

import numpy as np  # noqa: E402
import sympy  # noqa: E402
from identify_paper import CLOSED_LOOP, OPEN_LOOP, fly_profile  # noqa: E402

from bridge.vehicle import load_vehicle  # noqa: E402
from identification.body_frame import body_targets, expression_columns  # noqa: E402
from identification.collinearity import term_shapes  # noqa: E402
from identification.dataset import load_dataset  # noqa: E402
from identification.true_model import true_body_expressions  # noqa: E402
from identification.weak_form import RAW_SENSOR_TARGETS, WeakSettings, weak_rows  # noqa: E402

RATE_TARGETS = (("dwx", 3, "wx"), ("dwy", 4, "wy"), ("dwz", 5, "wz"))  # body target, column, its damping
DEFAULT_SHIFTS = (-0.02, -0.01, -0.005, 0.0, 0.005, 0.01, 0.02)  # fractions of the sample interval


def damping_rows(log: Path, vehicle: str, shifts: tuple[float, ...]) -> list[dict[str, object]]:
    """Per shift and rate target: the damping's relative error and the residual RMS (rad/s^2) of the true
    structure fitted to the log's weak-form sensor targets with the rotor speeds moved by shift samples."""
    veh = load_vehicle(vehicle)
    truth = true_body_expressions(veh)
    ds = load_dataset(str(log), targets="sensors", gravity=veh.gravity, sensor_settings=RAW_SENSOR_TARGETS)
    dt = float(np.median(np.diff(ds.t)))
    Y = body_targets(ds.xi, ds.targets, veh.gravity)
    structure = {}  # per target: its true terms, the damping's index among them, the damping's true value
    for target, _, damping in RATE_TARGETS:
        expr = sympy.expand(truth[target])
        shapes = term_shapes(expr)
        k = [str(s) for s in shapes].index(damping)
        structure[target] = (shapes, k, float(expr.coeff(shapes[k])))
    operators: dict[bytes, np.ndarray] = {}  # the weak form's test functions, per set of usable rows
    rows = []
    for shift in shifts:
        u = np.column_stack([np.interp(ds.t + shift * dt, ds.t, ds.u[:, i]) for i in range(4)])
        X = np.column_stack([ds.xi, u])
        for target, col, _ in RATE_TARGETS:
            shapes, k, true_c = structure[target]
            A = expression_columns(shapes, X)
            y = Y[:, col]
            ok = np.all(np.isfinite(A), axis=1) & np.isfinite(y)
            key = ok.tobytes()
            if key not in operators:
                operators[key] = weak_rows(ds.t[ok], ds.flight[ok], WeakSettings())
            op = operators[key]
            Aw, yw = op @ A[ok], op @ y[ok]
            coef = np.linalg.lstsq(Aw, yw, rcond=None)[0]
            rows.append({"flight": log.stem, "shift_us": round(shift * dt * 1e6, 2), "target": target,
                         "damping_error": float(coef[k] / true_c - 1.0),
                         "residual_rms": float(np.sqrt(np.mean((yw - Aw @ coef) ** 2)))})
    return rows


def main() -> int:
    """Fly (or read) the flights, fit at every shift, print and write the table; 0 always (no floor)."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/timing_confound", help="folder for flights and the table")
    ap.add_argument("--seed", type=int, default=0, help="seed of the excitation and the SITL")
    ap.add_argument("--logs", default=None, help="comma-separated .tlog files to use instead of flying")
    ap.add_argument("--vehicle", default="fang-chen-buaa", help="the vehicle flown (its true model)")
    ap.add_argument("--shifts", default=",".join(str(s) for s in DEFAULT_SHIFTS),
                    help="rotor-speed shifts, fractions of the sample interval (+: later samples)")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    shifts = tuple(float(s) for s in args.shifts.split(","))
    if args.logs:
        logs = [Path(p) for p in args.logs.split(",")]
    else:
        sitl = ["--vehicle", args.vehicle]
        logs = [fly_profile("closed-loop", out, "realistic", [*CLOSED_LOOP, *sitl], args.seed),
                fly_profile("paper-train", out, "realistic", [*OPEN_LOOP, *sitl], args.seed)]
    rows = [row for log in logs for row in damping_rows(log, args.vehicle, shifts)]
    lines = ["| flight | rotor speeds shifted [us] | " + " | ".join(
        f"{t} damping error | {t} residual RMS [rad/s^2]" for t, _, _ in RATE_TARGETS) + " |",
             "|---|---|" + "---|---|" * len(RATE_TARGETS)]
    for log in logs:
        for shift in sorted({r["shift_us"] for r in rows if r["flight"] == log.stem}):
            cells = {r["target"]: r for r in rows if r["flight"] == log.stem and r["shift_us"] == shift}
            figures = " | ".join(f"{cells[t]['damping_error']:+.1%} | {cells[t]['residual_rms']:.5f}"
                                 for t, _, _ in RATE_TARGETS)
            lines.append(f"| {log.stem} | {shift:+.1f} | {figures} |")
    print("\n".join(lines))
    (out / "timing_confound.md").write_text("\n".join(lines) + "\n")
    with open(out / "timing_confound.csv", "w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    print(f"(table: {out / 'timing_confound.md'}, {out / 'timing_confound.csv'})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
