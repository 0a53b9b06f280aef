"""Issue 13's true-model floor: truth targets of a .tlog against the vehicle's exact equations, before/after.

Flies, each in a fresh SITL with ideal sensors: the closed-loop profile from the ground (9 s; a hover
controller plus PRBS: every motor command changes every step) and paper-validate open loop from 200 m, for
`fang-chen-aero` (every effect) and `fang-chen-buaa` (the paper's vehicle). For each flight, R^2 per target of
the true model (quadsr model-from-vehicle, as `quadsr validate` computes it) against the .tlog's truth
targets made two ways: per sample with kink-aware point derivatives (the reader before issue 13's fix,
`read_tlog_dataset(step_intervals=False)`), and per step interval, the exact mean accelerations at the step's
midpoint state (identification.step_targets, the reader's default). PASS when the step-interval targets
give R^2 >= 0.999999 on all six targets of every flight.

Usage: python bench/step_targets.py [--out DIR] [--seed N]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from identification.metrics import r2  # noqa: E402
from identification.model_file import TARGET_NAMES  # noqa: E402
from identification.readers.tlog import read_tlog_dataset  # noqa: E402
from identification.segmentation import segment  # noqa: E402
from identification.true_model import true_model  # noqa: E402
from quadsr.pipeline import GROUND_SITL, OPEN_LOOP_SITL, fly_excitation  # noqa: E402

FLOOR = 0.999999
FLIGHTS = (("closed-loop", GROUND_SITL, 9.0), ("paper-validate", OPEN_LOOP_SITL, None))


def scores(path: Path, vehicle: str, step_intervals: bool) -> dict[str, float]:
    """R^2 per target of the vehicle's true model on the airborne rows of a .tlog's truth targets."""
    d = segment(read_tlog_dataset(path, targets="truth", step_intervals=step_intervals))
    pred = true_model(vehicle).accelerations(d.xi, d.u)
    return {n: r2(d.targets[:, j], pred[:, j]) for j, n in enumerate(TARGET_NAMES)}


def main() -> int:
    """Fly, score both ways, print the table; 0 when the floor holds."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/step_targets", help="folder for the flights")
    ap.add_argument("--seed", type=int, default=2, help="seed of the excitation")
    args = ap.parse_args()
    out = Path(args.out)
    print("| vehicle | flight | targets | " + " | ".join(TARGET_NAMES) + " | lowest |")
    print("|---|---|---|" + "---|" * (len(TARGET_NAMES) + 1))
    ok = True
    for vehicle in ("fang-chen-aero", "fang-chen-buaa"):
        for profile, sitl, duration in FLIGHTS:
            tlog = out / f"{vehicle}-{profile}.tlog"
            fly_excitation(profile, tlog, sitl_args=[*sitl, "--sensors", "ideal", "--vehicle", vehicle],
                           seed=args.seed, duration=duration, vehicle=vehicle,
                           log_path=out / f"{tlog.stem}.log")
            for label, steps in (("point (kink-aware)", False), ("step intervals", True)):
                fit = scores(tlog, vehicle, steps)
                low = min(fit.values())
                if steps:
                    ok &= low >= FLOOR
                cells = " | ".join(f"{fit[n]:.8f}" for n in TARGET_NAMES)
                print(f"| {vehicle} | {profile} | {label} | {cells} | {low:.8f} |", flush=True)
    print(f"{'PASS' if ok else 'FAIL'}: step-interval targets R^2 >= {FLOOR} on every target of every flight")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
