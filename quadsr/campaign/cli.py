"""`quadsr campaign SPEC.yaml --out DIR [--workers N | --scheduler ADDRESS]`."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path


def register(sub: argparse._SubParsersAction) -> None:
    """Add the `campaign` subcommand."""
    p = sub.add_parser(
        "campaign", help="robustness study: many flights over a grid and Monte-Carlo draws, on Dask",
        description="Run a campaign file's tasks (each its own SITL and companion) on a local Dask cluster "
                    "or an existing scheduler; write results.parquet/csv, report.md and figures. Re-running "
                    "the same command skips finished tasks.",
        formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    p.add_argument("spec", metavar="SPEC.yaml", help="the campaign file (see README.md, 'Campaigns')")
    p.add_argument("--out", required=True, metavar="DIR",
                   help="output folder (results, report, resume state)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=2, metavar="N",
                       help="worker processes of the local Dask cluster")
    where.add_argument("--scheduler", default=None, metavar="ADDRESS",
                       help="an existing Dask scheduler (e.g. tcp://10.0.0.5:8786) instead of a local "
                            "cluster")
    p.add_argument("--restart", action="store_true",
                   help="discard results already in --out and run every task")
    p.add_argument("--dry-run", action="store_true", help="list the tasks (parameters, ids, seeds) and stop")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Run the campaign; 0 when every task has a row (failures included), 130 on Ctrl-C."""
    from bridge.errors import UserError
    from quadsr.campaign.spec import load_campaign

    spec = load_campaign(args.spec)
    if args.workers is not None and args.workers < 1:
        raise UserError(f"--workers must be >= 1, got {args.workers}")
    if args.dry_run:
        return _dry_run(spec)
    from quadsr.campaign.report import write_report
    from quadsr.campaign.runner import run_campaign

    command = "quadsr " + " ".join(sys.argv[1:]) if sys.argv and sys.argv[0].endswith("quadsr") else \
        f"quadsr campaign {args.spec} --out {args.out}"
    try:
        result = run_campaign(spec, Path(args.out), workers=args.workers,
                              scheduler=args.scheduler, restart=args.restart)
    except KeyboardInterrupt:
        print(f"quadsr campaign: interrupted; finished tasks are kept in {args.out}/tasks: run the same "
              "command to resume", file=sys.stderr)
        return 130
    report = write_report(result, command)
    c = result.counts()
    print(f"campaign {spec.name}: {len(result.tasks)} tasks: ok {c['ok']}, crashed {c['crashed']}, failed "
          f"{c['failed']}; {result.wall_s:.1f} s", flush=True)
    for f in (result.files["parquet"], result.files["csv"], report):
        print(f"  wrote {f}")
    return 0


def _dry_run(spec) -> int:
    from quadsr.campaign.tasks import expand

    tasks = expand(spec, spec.nominal_values())
    names = spec.parameter_names()
    print("task_id\tseed\t" + "\t".join(names))
    for t in tasks:
        print(f"{t.task_id}\t{t.seed}\t" + "\t".join(str(t.params.get(n)) for n in names))
    print(f"{len(tasks)} tasks", file=sys.stderr)
    return 0
