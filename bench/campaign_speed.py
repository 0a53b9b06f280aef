"""Campaign throughput on Dask: the same campaign on 1 and on 2 local workers, and the example campaign.

Prints:
  throughput    tasks per minute of one campaign (--tasks flights of --duration s, realistic sensors, state
                estimated) on a local cluster of 1 worker and of 2 workers, in the same run, timed from the
                first task submitted to the last row saved; the ratio (floor 1.7 on a 2-core machine)
  identical     whether the two runs' results tables are equal (floor: yes)
  example       the wall time of quadsr/campaign/examples/robustness.yaml (200 tasks) on 2 workers, from the
                command's start (cluster, model learning, tasks, tables, report) (floor: under 600 s)

Usage: python bench/campaign_speed.py [--tasks 24] [--duration 6] [--skip-example] [--out DIR]
The machine should be otherwise idle: the floors are about this project's 2-core machine alone.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

THROUGHPUT_CAMPAIGN = """
name: throughput
seed: 7
grid:
  controller: [pid, se3]
fixed:
  duration: {duration}
  trajectory: case1
  sensors: realistic
  state: sensors
samples: {samples}
random:
  mass: {{scale: [0.9, 1.1]}}
"""


def main() -> int:
    """Run the measurements and print them with PASS/FAIL per floor."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tasks", type=int, default=24, help="tasks of the throughput campaign (even)")
    parser.add_argument("--duration", type=float, default=6.0, help="s simulated per throughput flight")
    parser.add_argument("--skip-example", action="store_true", help="do not run the 200-task example")
    parser.add_argument("--out", default=None, help="keep the outputs here (default: a temporary folder)")
    args = parser.parse_args()

    import pandas as pd

    from quadsr.campaign.report import write_report
    from quadsr.campaign.runner import run_campaign
    from quadsr.campaign.spec import load_campaign

    out = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="quadsr-campaign-bench-"))
    out.mkdir(parents=True, exist_ok=True)
    spec_path = out / "throughput.yaml"
    spec_path.write_text(THROUGHPUT_CAMPAIGN.format(duration=args.duration, samples=max(1, args.tasks // 2)))
    spec = load_campaign(spec_path)
    rates = {}
    for workers in (1, 2):
        run = run_campaign(spec, out / f"throughput-{workers}", workers=workers, progress=False, restart=True)
        bad = [r for r in run.rows if r["status"] != "ok"]
        rates[workers] = 60.0 * len(run.rows) / run.tasks_wall_s
        print(f"throughput  {workers} worker(s): {len(run.rows)} tasks in {run.tasks_wall_s:.1f} s = "
              f"{rates[workers]:.1f} tasks/min ({len(bad)} not ok)", flush=True)
    ratio = rates[2] / rates[1]
    print(f"throughput  2 workers / 1 worker = {ratio:.2f} (floor 1.7): {'PASS' if ratio >= 1.7 else 'FAIL'}")
    one = pd.read_parquet(out / "throughput-1" / "results.parquet")
    two = pd.read_parquet(out / "throughput-2" / "results.parquet")
    same = one.equals(two)
    print(f"identical   results tables of 1 and 2 workers: {'yes' if same else 'no'}: "
          f"{'PASS' if same else 'FAIL'}")
    ok = ratio >= 1.7 and same
    if not args.skip_example:
        example = REPO / "quadsr" / "campaign" / "examples" / "robustness.yaml"
        start = time.perf_counter()
        run = run_campaign(load_campaign(example), out / "example", workers=2, progress=False, restart=True)
        write_report(run, f"quadsr campaign {example} --out {out / 'example'} --workers 2")
        wall = time.perf_counter() - start
        c = run.counts()
        print(f"example     {len(run.rows)} tasks (ok {c['ok']}, crashed {c['crashed']}, "
              f"failed {c['failed']}) in {wall:.0f} s on 2 workers (floor 600 s): "
              f"{'PASS' if wall < 600 else 'FAIL'}")
        print(f"            report: {out / 'example' / 'report.md'}")
        ok = ok and wall < 600
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
