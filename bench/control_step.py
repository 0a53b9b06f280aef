"""Control step compute time in-process: each controller's update() replayed over the states of a flight.

The states come from an in-process closed-loop flight of each case (the true model as the plant, the
vehicle's motor lag); each controller is then reset and its update() timed over those same inputs, repeated.
Backstepping is timed with its loop functions compiled (controller.native) and as math-module Python
(QUADSR_NATIVE=0), measured in the same run: the ratio is the speed-up of the compiled functions. Printed:
median and p99 per call [us], medians over the repeats.

The in-flight figure (the companion's step time inside a lockstep flight, bench/track_paper.py) is higher
than this one: between two calls the companion parses MAVLink, logs and waits, so caches are colder.

Usage: python bench/control_step.py [--duration 20] [--repeats 5]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from bridge.vehicle import load_vehicle  # noqa: E402
from controller.registry import make_controller  # noqa: E402
from controller.simulate import ModelPlant, simulate  # noqa: E402
from controller.trajectories import load_trajectory  # noqa: E402
from identification.true_model import true_model  # noqa: E402


def record_states(case: str, duration: float, vehicle) -> list:
    """(t, state, reference) of every step of a backstepping flight of the case."""
    ctl = make_controller("backstepping", true_model(vehicle), vehicle)
    plant = ModelPlant(true_model(vehicle), motor_time_constant=vehicle.motor.time_constant)
    states = []
    update = ctl.update

    def record(t, state, ref):
        states.append((t, state, ref))
        return update(t, state, ref)

    ctl.update = record
    simulate(ctl, load_trajectory(case), plant, duration)
    return states


def time_controller(ctl, states: list, repeats: int) -> tuple[float, float]:
    """(median, p99) [us] of update() over the states, each the median over the repeats."""
    medians, p99s = [], []
    for _ in range(repeats):
        ctl.reset()
        times = []
        for t, state, ref in states:
            c0 = time.perf_counter()
            ctl.update(t, state, ref)
            times.append(time.perf_counter() - c0)
        times.sort()
        medians.append(times[len(times) // 2] * 1e6)
        p99s.append(times[int(0.99 * (len(times) - 1))] * 1e6)
    return statistics.median(medians), statistics.median(p99s)


def main(argv: list[str] | None = None) -> int:
    """Print one table: controller, case, median and p99 update time."""
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--duration", type=float, default=20.0, help="seconds of flight per case (default 20)")
    ap.add_argument("--repeats", type=int, default=5, help="timed passes over the states (default 5)")
    ap.add_argument("--vehicle", default="fang-chen-buaa")
    args = ap.parse_args(argv)
    vehicle = load_vehicle(args.vehicle)
    print("| controller | case | steps | median [us] | p99 [us] |\n|---|---|---|---|---|")
    for case in ("case1", "case2"):
        states = record_states(case, args.duration, vehicle)
        rows = {}
        for label, name, native_on in (("backstepping (compiled)", "backstepping", "1"),
                                       ("backstepping (python)", "backstepping", "0"),
                                       ("pid", "pid", "1"), ("se3", "se3", "1")):
            os.environ["QUADSR_NATIVE"] = native_on
            ctl = make_controller(name, true_model(vehicle) if name == "backstepping" else None, vehicle)
            rows[label] = time_controller(ctl, states, args.repeats)
            print(f"| {label} | {case} | {len(states)} | {rows[label][0]:.0f} | {rows[label][1]:.0f} |",
                  flush=True)
        ratio = rows["backstepping (python)"][0] / rows["backstepping (compiled)"][0]
        print(f"| compiled speed-up (median) | {case} | | {ratio:.2f}x | |", flush=True)
    os.environ.pop("QUADSR_NATIVE", None)
    return 0


if __name__ == "__main__":
    sys.exit(main())
