"""How close sensor-derived targets get to the true model, per differentiator, on realistic-sensor flights.

Flies paper-train, paper-validate and closed-loop in the SITL with `--sensors realistic` (the vehicle's
default noise: 250 Hz IMU), derives the six targets from the IMU with each differentiator setting, and
scores them against the SITL's exact equations evaluated at the logged true states and rotor speeds
(R^2 of the targets against the true model, per axis): the noise and smoothing error a learned model
would have to fit. Settings compared:

- 5-point: the raw 4th-order 5-point stencil on the gyro, raw specific force (no smoothing);
- fixed windows: Savitzky-Golay of 0.036 s (order 2), 0.1 s (order 2) and 0.2 s (order 4) on every axis;
- auto (the default, identification.targets.choose_savgol): per axis the window and order of least
  estimated error from the signal's spectrum and the noise floor.

PASS when, on every flight and axis, auto is within 0.002 of the best setting tried there (so the default
needs no tuning per flight) and far better than the raw stencil on the worst axis.

Usage: python bench/sensor_targets.py [--out DIR] [--seed N]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from identify_paper import CLOSED_LOOP, OPEN_LOOP, fly_profile  # noqa: E402

from identification.metrics import r2  # noqa: E402
from identification.model_file import TARGET_NAMES  # noqa: E402
from identification.readers.tlog import read_tlog_dataset  # noqa: E402
from identification.targets import SensorTargetSettings  # noqa: E402
from identification.true_model import true_model  # noqa: E402

SETTINGS = {
    "5-point": SensorTargetSettings(window_s=0.02, polyorder=4, smooth_accel=False),
    "SG 0.036 s p2": SensorTargetSettings(window_s=0.036, polyorder=2),
    "SG 0.1 s p2": SensorTargetSettings(window_s=0.1, polyorder=2),
    "SG 0.2 s p4": SensorTargetSettings(window_s=0.2, polyorder=4),
    "auto": SensorTargetSettings(),
}


def score(path: Path, settings: SensorTargetSettings) -> dict[str, float]:
    """R^2 per target of the sensor targets of a log against the true model at its true states."""
    d = read_tlog_dataset(path, targets="sensors", sensor_settings=settings)
    exact = true_model("fang-chen-buaa").accelerations(d.xi, d.u)
    return {n: r2(exact[:, j], d.targets[:, j]) for j, n in enumerate(TARGET_NAMES)}


def main() -> int:
    """Fly, score every setting, print the table; 0 when the floor holds."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/sensor_targets", help="folder for the flights")
    ap.add_argument("--seed", type=int, default=0, help="seed of the excitation and the SITL")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    flights = {
        "paper-train": fly_profile("paper-train", out, "realistic", OPEN_LOOP, args.seed),
        "paper-validate": fly_profile("paper-validate", out, "realistic", OPEN_LOOP, args.seed),
        "closed-loop": fly_profile("closed-loop", out, "realistic", CLOSED_LOOP, args.seed),
    }
    ok = True
    for flight, path in flights.items():
        table = {name: score(path, s) for name, s in SETTINGS.items()}
        print(f"\n{flight}: R^2 of the sensor targets against the true model")
        print("| setting | " + " | ".join(TARGET_NAMES) + " | worst |")
        print("| --- |" + " --- |" * (len(TARGET_NAMES) + 1))
        for name, row in table.items():
            cells = " | ".join(f"{row[t]:.5f}" for t in TARGET_NAMES)
            print(f"| {name} | {cells} | {min(row.values()):.5f} |")
        for t in TARGET_NAMES:
            best = max(row[t] for row in table.values())
            if table["auto"][t] < best - 0.002:
                ok = False
                print(f"  auto is {best - table['auto'][t]:.4f} below the best setting on {t}")
        raw_worst, auto_worst = min(table["5-point"].values()), min(table["auto"].values())
        print(f"  worst axis: 5-point {raw_worst:.4f} -> auto {auto_worst:.4f}")
        ok = ok and auto_worst > raw_worst
    print("\nPASS" if ok else "\nFAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
