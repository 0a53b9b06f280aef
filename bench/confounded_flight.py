"""Closed-loop collinearity in the SITL: does `quadsr identify` name what a confounded flight cannot give?

Two flights from the ground with the closed-loop profile's hover stabiliser (ideal sensors, truth targets):
- confounded: the profile with its per-motor PRBS turned off (amplitude 0), so every rotor speed is what the
  stabiliser commands from the angles, rates and position: the regressors are tied together;
- excited: the bundled closed-loop profile (PRBS of 100 rad/s on every motor).
Each is identified with the default engine; per target the learned expression is compared with the true
model (missing / extra terms, largest coefficient error) beside the identifiability warnings written to the
model file (terms with VIF > 10 among the model's terms; model terms confused with a left-out candidate,
VIF > 100).

PASS when on both flights every target whose structure is wrong (a true term missing or a term too many)
carries a warning, and the excited flight has fewer warned targets than the confounded one. Coefficient
errors of a target with the right terms are printed but not required to be warned: a weakly excited term
(rate damping in a hover) can be biased without being collinear with anything.

Usage: python bench/confounded_flight.py [--out DIR] [--seed N] [--duration S]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import yaml

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "bench"))

from identify_paper import CLOSED_LOOP  # noqa: E402

from bridge.vehicle import load_vehicle  # noqa: E402
from bridge.yaml_file import load_yaml_file  # noqa: E402
from identification.dataset import load_dataset  # noqa: E402
from identification.identify import identify  # noqa: E402
from identification.model_file import save_model  # noqa: E402
from identification.true_model import true_model  # noqa: E402
from identification.validate import compare_models  # noqa: E402
from quadsr.pipeline import fly_excitation  # noqa: E402


def confounded_profile(out: Path) -> Path:
    """The closed-loop profile with its motor excitation off, written to out/confounded.yaml."""
    data = load_yaml_file(REPO / "identification" / "profiles" / "closed-loop.yaml", "closed-loop profile")
    data["name"] = "confounded"
    data["description"] = "the closed-loop profile without motor excitation: the stabiliser alone"
    data["excitation"]["amplitude"] = 0.0
    path = out / "confounded.yaml"
    path.write_text(yaml.safe_dump(data, sort_keys=False))
    return path


def run(name: str, profile: str, out: Path, seed: int, duration: float) -> int:
    """Fly, identify, print the table for one flight; the number of targets with a warning."""
    log = out / f"{name}.tlog"
    start = time.perf_counter()
    fly_excitation(profile, log, sitl_args=CLOSED_LOOP, seed=seed, duration=duration,
                   log_path=out / f"sitl-{name}.log")
    print(f"\n== {name}: flew {duration:g} s in {time.perf_counter() - start:.1f} s")
    gravity = load_vehicle("fang-chen-buaa").gravity  # the SITL's (9.8), not identify's default 9.80665
    model = identify(load_dataset(log), engine="default", seed=seed, progress=False, gravity=gravity)
    save_model(model, out / f"model-{name}.yaml")
    info = model.extra["identifiability"]["targets"]
    print("| target | same terms | missing | extra | max coef. error | warned terms |")
    print("| --- | --- | --- | --- | --- | --- |")
    warned, uncovered = 0, []
    for c in compare_models(model, true_model("fang-chen-buaa")):
        # a body-frame model (the default engine) is checked per fx fy fz: ax ay az are composed of all three
        keys = [c.target] if c.target in info else ["fx", "fy", "fz"]
        flagged = [x["term"] for k in keys for x in info[k]["not_identifiable"]] + [
            f"{x['term']} ~ {x['candidate']}" for k in keys for x in info[k]["confused_with_candidates"]
        ]
        warned += bool(flagged)
        err = c.max_relative_error or 0.0
        if not c.same_terms and not flagged:
            uncovered.append(c.target)
        print(
            f"| {c.target} | {'yes' if c.same_terms else 'no'} | {len(c.missing)} | {len(c.extra)} | "
            f"{100 * err:.2f}% | {len(flagged)}: {'; '.join(f[:60] for f in flagged[:3])} |"
        )
    print(f"  targets with a warning: {warned}; wrong targets without one: {uncovered or 'none'}")
    return warned if not uncovered else -1


def main() -> int:
    """Both flights; 0 when the warnings cover every error on the confounded one."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", default="results/confounded_flight", help="folder for flights and models")
    ap.add_argument("--seed", type=int, default=0, help="seed of the excitation, SITL and engines")
    ap.add_argument("--duration", type=float, default=30.0, help="s simulated per flight")
    args = ap.parse_args()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    confounded = run("confounded", str(confounded_profile(out)), out, args.seed, args.duration)
    excited = run("excited", "closed-loop", out, args.seed, args.duration)
    ok = confounded > 0 and 0 <= excited < confounded
    print("\nPASS" if ok else "\nFAIL")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
