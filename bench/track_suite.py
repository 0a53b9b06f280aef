"""Issue 15's tracking suite: every controller on every trajectory under every condition, one table, floors.

Trajectories (bench/trajectories/ and the built-in cases): the paper's Case I and II, a figure-eight with yaw,
a 3 m step, the aggressive circle (4.8 m/s, ~31 deg), a 2 m hover hold, a waypoint mission, and an infeasible
circle (16 m/s^2, limits raised in its file) for the governor. Those starting in the air begin with the
companion's take-off phase from the ground.

Conditions:
  ideal     noise-free sensors, the SITL's true state fed back
  sensors   realistic sensor noise, the state estimated from HIL_SENSOR/HIL_GPS (--state sensors)
  mismatch  the SITL flies a vehicle 20 % heavier, with 20 % more inertia and 10 % less thrust than the
            vehicle file the controllers (and the true model) are built from; true state fed back
  wind      steady 5 m/s toward north (NED) with moderate Dryden turbulence, seeded (--wind-seed); the
            controllers know nothing of it (the models hold no wind); true state fed back
Controllers: backstepping on the learned model and on the true model, PID cascade, SE(3). The learned model
is --model, or with --learn one `quadsr identify` (default engine, 60 generations, seed 0) learns on a 32 s
paper-train flight of the nominal vehicle (as quadsr/campaign/examples/robustness.yaml does).

Floors: on every feasible case, backstepping never crashes, its RMS after 5 s is at most 1.2 x SE(3)'s
+ 2 mm and its take-off overshoot at most 5 cm; under mismatch (and wind) its RMS after 5 s is at most
SE(3)'s (+ 2 mm); the infeasible reference is flown slower (the reference's speed stays below the 8 m/s
written) without a crash by every controller. The paper's own floors are bench/track_paper.py's.

Usage: python bench/track_suite.py [--model learned.yaml | --learn] [--cases a,b] [--conditions ideal,sensors]
       [--controllers true,pid,se3] [--out DIR]
       python bench/track_suite.py --collect DIR [DIR ...]    (one table and the floors of flights already
       flown by parts of the suite run side by side, each with its own --out; a later DIR's flight wins)
Each flight starts its own SITL; the whole table is 8 x 3 x 4 flights of 15-25 s simulated (long: pick).
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from bridge.errors import UserError  # noqa: E402
from bridge.yaml_file import load_yaml_file  # noqa: E402
from quadsr.pipeline import (  # noqa: E402
    GROUND_SITL,
    LEARNED_LABEL,
    TRUE_LABEL,
    TrackingRow,
    controller_specs,
    flight_dir_name,
    fly_tracking,
)

TRAJ_DIR = REPO / "bench" / "trajectories"
CASES = {  # name -> (trajectory, flight length [s] including the take-off phase, feasible)
    "case1": ("case1", 20.0, True),
    "case2": ("case2", 20.0, True),
    "figure8-yaw": (str(TRAJ_DIR / "figure8-yaw.yaml"), 24.0, True),
    "step": (str(TRAJ_DIR / "step.yaml"), 19.0, True),
    "aggressive-circle": (str(TRAJ_DIR / "aggressive-circle.yaml"), 24.0, True),
    "hover-2m": (str(TRAJ_DIR / "hover-2m.yaml"), 14.0, True),
    "mission": (str(TRAJ_DIR / "mission.yaml"), 23.0, True),
    "infeasible-circle": (str(TRAJ_DIR / "infeasible-circle.yaml"), 18.0, False),
}
CONDITIONS = ("ideal", "sensors", "mismatch", "wind")
WRITTEN_SPEED = 8.0  # m/s, the infeasible circle's speed as written
MISMATCH = {"mass": 1.2, "inertia": 1.2, "thrust_coefficient": 0.9}
WIND_SITL = ("--wind", "5,0,0", "--turbulence", "moderate", "--wind-seed", "0")  # m/s NED; Dryden preset


@dataclass
class SuiteRow:
    """One cell of the table: a flight (or why it was not flown) and its figures."""

    case: str
    condition: str
    row: TrackingRow | None
    note: str = ""
    max_ref_speed: float = math.nan  # m/s, the fastest reference the controller was given


def mismatched_vehicle(source: Path, out: Path) -> Path:
    """A copy of the vehicle file with mass, inertia and thrust coefficient scaled by MISMATCH."""
    data = load_yaml_file(source, f"vehicle file {source}")
    data["name"] = f"{data['name']}-mismatch"
    data["mass"] = data["mass"] * MISMATCH["mass"]
    data["inertia"] = [v * MISMATCH["inertia"] for v in data["inertia"]]
    data["thrust_coefficient"] = data["thrust_coefficient"] * MISMATCH["thrust_coefficient"]
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    return out


def _max_ref_speed(flight_dir: Path | None) -> float:
    if flight_dir is None or not (flight_dir / "steps.csv").is_file():
        return math.nan
    with (flight_dir / "steps.csv").open(newline="") as fh:
        return max((math.sqrt(float(r["ref_vx"]) ** 2 + float(r["ref_vy"]) ** 2 + float(r["ref_vz"]) ** 2)
                    for r in csv.DictReader(fh)), default=math.nan)


def fly_cell(spec, case: str, condition: str, out: Path, vehicle: Path, built: dict) -> SuiteRow:
    """Fly one controller on one case under one condition (controllers kept in `built`, by label)."""
    traj, duration, _ = CASES[case]
    try:
        row = _fly(spec, traj, duration, condition, out, vehicle, built)
    except UserError as exc:  # a SITL child that did not start: the cell is not flown, and says why
        return SuiteRow(case, condition, None, f"{spec.label}: not flown: {str(exc).splitlines()[0]}")
    return SuiteRow(case, condition, row, row.message, _max_ref_speed(row.flight_dir))


def _fly(spec, traj: str, duration: float, condition: str, out: Path, vehicle: Path,
         built: dict) -> TrackingRow:
    """One flight under the condition's SITL (wind, mismatched vehicle, realistic sensors or ideal)."""
    if condition == "wind":
        row = fly_tracking(spec, traj, duration=duration, out=out / condition, vehicle=str(vehicle),
                           sitl_args=[*GROUND_SITL, *WIND_SITL], built=built)
    elif condition == "mismatch":
        other = mismatched_vehicle(vehicle, out / "vehicle-mismatch.yaml")
        row = fly_tracking(spec, traj, duration=duration, out=out / condition, vehicle=str(vehicle),
                           sitl_args=[*GROUND_SITL, "--vehicle", str(other)], built=built)
    elif condition == "sensors":
        row = fly_tracking(spec, traj, duration=duration, out=out / condition, vehicle=str(vehicle),
                           sensors="realistic", state="sensors", built=built)
    else:
        row = fly_tracking(spec, traj, duration=duration, out=out / condition, vehicle=str(vehicle),
                           built=built)
    return row


def collect(dirs: list[Path]) -> list[SuiteRow]:
    """The cells of flights already flown under the --out folders `dirs` (DIR/case/condition/flight/)."""
    from controller.metrics import metrics_from_csv

    found: dict[tuple[str, str, str], SuiteRow] = {}
    for top in dirs:
        for case in CASES:
            for condition in CONDITIONS:
                state = "sensors" if condition == "sensors" else "truth"
                for label in (LEARNED_LABEL, TRUE_LABEL, "pid", "se3"):
                    flight = top / case / condition / flight_dir_name(label, CASES[case][0], state)
                    if (flight / "metrics.csv").is_file():
                        m = metrics_from_csv(flight / "metrics.csv")
                        row = TrackingRow(label, case, state, m, "", flight, m.completed, m.crashed)
                        found[case, condition, label] = SuiteRow(case, condition, row, "",
                                                                 _max_ref_speed(flight))
    return [found[k] for k in sorted(found, key=lambda k: (list(CASES).index(k[0]), CONDITIONS.index(k[1])))]


def _mm(v: float | None) -> str:
    return "n/a" if v is None or not math.isfinite(v) else f"{v * 1000:.2f}"


def print_table(cells: list[SuiteRow]) -> None:
    """The issue's table: RMS after 5 s, max error, overshoot, motor-limit share, crash."""
    print("\n| case | condition | controller | RMS after 5 s [mm] | max [mm] | max after 5 s [mm] | "
          "overshoot [mm] | motor limits | crash | note |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for c in cells:
        if c.row is None:
            print(f"| {c.case} | {c.condition} | all | | | | | | | {c.note} |")
            continue
        m = c.row.metrics
        if m is None:
            print(f"| {c.case} | {c.condition} | {c.row.label} | | | | | | | {c.note} |")
            continue
        note = c.note
        if CASES[c.case][2] is False:
            note = f"reference at most {c.max_ref_speed:.2f} m/s (written {WRITTEN_SPEED:g}) {note}".strip()
        print(f"| {c.case} | {c.condition} | {c.row.label} | {_mm(m.rms_after_5s_m)} | {_mm(m.max_m)} | "
              f"{_mm(m.max_after_5s_m)} | {_mm(m.overshoot_m)} | {m.motor_limit_share:.1%} | "
              f"{'yes' if m.crashed else 'no'} | {note} |")
    sys.stdout.flush()


def check_floors(cells: list[SuiteRow]) -> list[str]:
    """The issue's floors as PASS/FAIL lines (a floor whose flights are missing is not checked)."""
    lines = []
    by = {(c.case, c.condition, c.row.label): c for c in cells if c.row is not None and c.row.metrics}
    subjects = [label for label in (LEARNED_LABEL, TRUE_LABEL) if any(k[2] == label for k in by)]
    lines += [f"FAIL {c.case} {c.condition}: {c.note}" for c in cells if c.row is None]
    lines += [f"FAIL {c.row.label} {c.case} {c.condition}: no metrics ({c.note})" for c in cells
              if c.row is not None and c.row.metrics is None]
    for (case, condition, label), c in sorted(by.items()):
        m = c.row.metrics
        feasible = CASES[case][2]
        if not feasible:
            ok = not m.crashed and c.row.completed and c.max_ref_speed < 0.9 * WRITTEN_SPEED
            lines.append(f"{'PASS' if ok else 'FAIL'} {label} {case} {condition}: flown slower "
                         f"(reference <= {c.max_ref_speed:.2f} m/s of {WRITTEN_SPEED:g}), "
                         f"{'crashed' if m.crashed else 'no crash'}")
            continue
        if label not in subjects:
            continue
        ok = c.row.completed and not m.crashed
        lines.append(f"{'PASS' if ok else 'FAIL'} {label} {case} {condition}: flown to the end, no crash")
        if case not in ("case1", "case2"):  # those start on the ground with the reference: no take-off
            ok = m.overshoot_m <= 0.05
            lines.append(f"{'PASS' if ok else 'FAIL'} {label} {case} {condition}: overshoot "
                         f"{_mm(m.overshoot_m)} mm (<= 50)")
        se3 = by.get((case, condition, "se3"))
        if se3 is not None and m.rms_after_5s_m is not None and se3.row.metrics.rms_after_5s_m is not None:
            ref = se3.row.metrics.rms_after_5s_m
            factor = 1.0 if condition in ("mismatch", "wind") else 1.2
            ok = m.rms_after_5s_m <= factor * ref + 0.002
            lines.append(f"{'PASS' if ok else 'FAIL'} {label} {case} {condition}: RMS after 5 s "
                         f"{_mm(m.rms_after_5s_m)} mm <= {factor:g} x SE(3)'s {_mm(ref)} + 2 mm")
    return lines


def main(argv: list[str] | None = None) -> int:
    """Fly the chosen part of the table, print it and the floors; exit 1 if a floor fails."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, help="learned model file (backstepping on it is flown too)")
    ap.add_argument("--learn", action="store_true",
                    help="learn the model first: paper-train (32 s, seed 0), identify's default engine")
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma list among {', '.join(CASES)}")
    ap.add_argument("--conditions", default="ideal,sensors,mismatch,wind",
                    help=f"comma list among {', '.join(CONDITIONS)}")
    ap.add_argument("--controllers", default="learned,true,pid,se3",
                    help="comma list among learned, true, pid, se3")
    ap.add_argument("--vehicle", type=Path, default=REPO / "sitl" / "vehicles" / "fang-chen-buaa.yaml")
    ap.add_argument("--out", type=Path, help="keep every flight here (default: a temporary folder)")
    ap.add_argument("--collect", type=Path, nargs="+", metavar="DIR",
                    help="fly nothing: the table and floors of the flights under these --out folders")
    args = ap.parse_args(argv)
    if args.collect:
        return report(collect(args.collect))
    cases = [c for c in args.cases.split(",") if c]
    conditions = [c for c in args.conditions.split(",") if c]
    bad = [c for c in cases if c not in CASES] + [c for c in conditions if c not in CONDITIONS]
    if bad:
        print(f"track_suite: unknown case or condition {bad[0]!r}", file=sys.stderr)
        return 2
    out = args.out or Path(tempfile.mkdtemp(prefix="track_suite_"))
    out.mkdir(parents=True, exist_ok=True)
    from identification.true_model import write_true_model

    true_path = out / "true-model.yaml"
    write_true_model(str(args.vehicle), true_path)
    learned = args.model
    if args.learn and learned is None:
        from quadsr.campaign.runner import learn_nominal_model

        print("track_suite: learning the model (paper-train, 32 s, default engine, 60 generations)",
              flush=True)
        learned = out / "learned-model.yaml"
        learned.write_text(learn_nominal_model(args.vehicle.read_text(encoding="utf-8"), args.vehicle.stem,
                                               "paper-train", 32.0, 0, 60), encoding="utf-8")
    specs = controller_specs(learned, true_path, args.controllers.split(","))
    print(f"track_suite: {len(specs)} controllers x {len(cases)} cases x {len(conditions)} conditions, "
          f"outputs in {out}", flush=True)
    cells: list[SuiteRow] = []
    built: dict = {}  # controllers by label, built once
    for case in cases:
        for condition in conditions:
            for spec in specs:
                cell = fly_cell(spec, case, condition, out / case, args.vehicle, built)
                m = cell.row.metrics if cell.row is not None else None
                figure = "no data" if m is None else f"RMS after 5 s {_mm(m.rms_after_5s_m)} mm"
                print(f"  {case} {condition} {spec.label}: {figure}", flush=True)
                cells.append(cell)
    return report(cells)


def report(cells: list[SuiteRow]) -> int:
    """Print the table and the floors; 0 when every floor passed, else 1."""
    print_table(cells)
    lines = check_floors(cells)
    print("\n### Floors\n")
    for line in lines:
        print(f"- {line}")
    return 0 if all(line.startswith("PASS") for line in lines) else 1


if __name__ == "__main__":
    sys.exit(main())
