"""The paper's tracking experiments flown against the SITL: every controller on Case I and Case II, one table.

For each case and controller a fresh `quadsr sitl` (noise-free sensors, lockstep, free loopback ports) is
started and the companion (controller.companion, in this process) flies the trajectory from the ground at the
origin, feeding back the SITL's true state. Controllers: backstepping on the learned model (when --model is
given), backstepping on the true model (written from the vehicle file), the PX4-style PID cascade, SE(3).

With --sensors (default on) every controller also flies each case against a SITL with the realistic sensor
noise, feeding back the state estimated from HIL_SENSOR/HIL_GPS (--state sensors).

Floors checked (issue 4): learned (or true-model) backstepping RMS after 5 s < 1 cm on both cases and
<= 1.2 x the true-model controller's; Case II within 5 cm by 4 s; median control step < 200 us; with realistic
sensors every flight completed without a crash and RMS after 5 s < 0.5 m (the overall RMS includes the
take-off from 3.7 m / 4.5 m away and is printed too).

Usage: python bench/track_paper.py [--model learned.yaml] [--duration 20] [--out DIR] [--no-sensors]
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from quadsr.pipeline import CASES, TRUE_LABEL, TrackingRow, controller_specs, fly_tracking  # noqa: E402
from quadsr.report import millimetres as _mm  # noqa: E402
from quadsr.report import tracking_markdown  # noqa: E402


def print_table(rows: list[TrackingRow], title: str) -> None:
    """One Markdown table of the rows."""
    print(f"\n### {title}\n")
    print(tracking_markdown(rows, state_column=True), end="")
    for label, law in {r.label: r.law for r in rows if r.law}.items():
        print(f"- {label}: {law}")
    sys.stdout.flush()


def check_floors(rows: list[TrackingRow], sensor_rows: list[TrackingRow], learned: bool) -> list[str]:
    """The issue's floors, each as a PASS/FAIL line."""
    lines = []
    by = {(r.label, r.case): r.metrics for r in rows}
    subject = "backstepping (learned)" if learned else "backstepping (true model)"
    for case in CASES:
        m = by.get((subject, case))
        ref = by.get((TRUE_LABEL, case))
        if m is None or m.rms_after_5s_m is None:
            lines.append(f"FAIL {subject} {case}: no data")
            continue
        lines.append(f"{'PASS' if m.rms_after_5s_m < 0.01 else 'FAIL'} {subject} {case}: RMS after 5 s "
                     f"{m.rms_after_5s_m * 1000:.2f} mm < 10 mm")
        if learned and ref is not None and ref.rms_after_5s_m:
            ratio = m.rms_after_5s_m / ref.rms_after_5s_m
            lines.append(f"{'PASS' if ratio <= 1.2 else 'FAIL'} {subject} {case}: {ratio:.2f} x the "
                         f"true-model controller's RMS after 5 s (<= 1.2)")
        lines.append(f"{'PASS' if m.step_median_us < 200 else 'FAIL'} {subject} {case}: median control step "
                     f"{m.step_median_us:.0f} us < 200 us")
    m = by.get((subject, "case2"))
    if m is not None:
        ok = m.settle_time_s is not None and m.settle_time_s <= 4.0
        lines.append(f"{'PASS' if ok else 'FAIL'} {subject} case2: within 5 cm from "
                     f"{'never' if m.settle_time_s is None else f'{m.settle_time_s:.2f} s'} (by 4 s)")
    for r in sensor_rows:
        m = r.metrics
        ok = m is not None and m.completed and not m.crashed and m.rms_after_5s_m is not None \
            and m.rms_after_5s_m < 0.5
        figure = "no data" if m is None else \
            f"RMS after 5 s {_mm(m.rms_after_5s_m)} mm, overall {_mm(m.rms_m)} mm"
        lines.append(f"{'PASS' if ok else 'FAIL'} {r.label} {r.case} with realistic sensors and --state "
                     f"sensors: flown to the end without a crash, {figure} (< 500 mm)")
    return lines


def main(argv: list[str] | None = None) -> int:
    """Fly the table; exit 1 if a floor fails."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--model", type=Path, help="learned model file (backstepping on it is the subject)")
    ap.add_argument("--duration", type=float, default=20.0, help="seconds per flight (default 20)")
    ap.add_argument("--vehicle", default="fang-chen-buaa")
    ap.add_argument("--out", type=Path, help="keep every flight's outputs here (default: a temporary folder)")
    ap.add_argument("--no-sensors", action="store_true",
                    help="skip the realistic-sensor, estimated-state runs")
    ap.add_argument("--controllers", default="learned,true,pid,se3",
                    help="comma list among learned, true, pid, se3 (default all)")
    args = ap.parse_args(argv)
    out = args.out or Path(tempfile.mkdtemp(prefix="track_paper_"))
    out.mkdir(parents=True, exist_ok=True)
    from identification.true_model import write_true_model

    true_path = out / "true-model.yaml"
    write_true_model(args.vehicle, true_path)
    wanted = args.controllers.split(",")
    specs = controller_specs(args.model, true_path, wanted)
    print(f"track_paper: {len(specs)} controllers x {len(CASES)} cases, {args.duration:g} s each, "
          f"outputs in {out}", flush=True)
    rows = [fly_tracking(spec, case, duration=args.duration, out=out, vehicle=args.vehicle)
            for spec in specs for case in CASES]
    print_table(rows, "Noise-free SITL, lockstep, true state fed back")
    sensor_rows: list[TrackingRow] = []
    if not args.no_sensors:
        sensor_rows = [fly_tracking(spec, case, duration=args.duration, out=out, vehicle=args.vehicle,
                                    sensors="realistic", state="sensors") for spec in specs for case in CASES]
        print_table(sensor_rows, "Realistic sensor noise, state estimated from HIL_SENSOR + HIL_GPS")
    lines = check_floors(rows, sensor_rows, args.model is not None)
    print("\n### Floors\n")
    for line in lines:
        print(f"- {line}")
    return 0 if all(line.startswith("PASS") for line in lines) else 1


if __name__ == "__main__":
    sys.exit(main())
