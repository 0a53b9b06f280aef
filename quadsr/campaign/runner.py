"""Run a campaign's tasks on Dask distributed: a local cluster by default, or an existing scheduler.

The client (this process) expands the tasks, skips those already on disk, submits the rest, and writes each
row as it comes back. Dask re-runs the task of a worker that dies on another worker (the scheduler's
`allowed-failures`); a task that keeps killing workers, or raises, becomes a failure row with its reason.
"""

from __future__ import annotations

import hashlib
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from bridge.errors import UserError
from identification.cluster import dask_client
from quadsr.campaign.results import ResultStore, write_tables
from quadsr.campaign.spec import CampaignSpec
from quadsr.campaign.task_run import METRIC_FIELDS, TIMING_FIELDS, TaskContext, run_task
from quadsr.campaign.tasks import Task, expand

LEARNED_MODEL_FILE = "learned-model.yaml"


@dataclass
class CampaignRun:
    """What a run did: the tasks, how many were skipped (done before), the rows, files written, wall time."""

    spec: CampaignSpec
    out: Path
    tasks: list[Task]
    skipped: int = 0
    rows: list[dict[str, Any]] = field(default_factory=list)
    files: dict[str, Path] = field(default_factory=dict)
    wall_s: float = 0.0  # s, the whole run (cluster start, model learning, tasks, tables)
    tasks_wall_s: float = 0.0  # s, from the first task submitted to the last row saved
    workers: str = ""

    def counts(self) -> dict[str, int]:
        """Rows by status: ok, crashed, failed."""
        out = {"ok": 0, "crashed": 0, "failed": 0}
        for r in self.rows:
            out[r.get("status", "failed")] = out.get(r.get("status", "failed"), 0) + 1
        return out


def _true_model_text(vehicle: str) -> str:
    from identification.true_model import write_true_model

    with tempfile.TemporaryDirectory() as tmp:
        return write_true_model(vehicle, Path(tmp) / "true.yaml").read_text()


def learn_nominal_model(vehicle_yaml: str, vehicle_name: str, profile: str, duration: float, seed: int,
                        budget: int) -> str:
    """Fly `profile` on the nominal vehicle (own SITL child) and identify a model; the model file's text."""
    from identification.dataset import load_dataset
    from identification.identify import identify
    from identification.model_file import save_model
    from quadsr.pipeline import GROUND_SITL, OPEN_LOOP_SITL, fly_excitation

    with tempfile.TemporaryDirectory() as tmp:
        vehicle = Path(tmp) / f"{vehicle_name}.yaml"
        vehicle.write_text(vehicle_yaml)
        tlog = Path(tmp) / "train.tlog"
        base = OPEN_LOOP_SITL if profile.startswith("paper") else GROUND_SITL
        fly_excitation(profile, tlog, sitl_args=["--vehicle", str(vehicle), "--sensors", "ideal", *base],
                       seed=seed, duration=duration, vehicle=str(vehicle))
        model = identify(load_dataset(tlog), engine="default", budget=budget, seed=seed, progress=False)
        return save_model(model, Path(tmp) / "learned.yaml").read_text()


def _context(spec: CampaignSpec, out: Path, client: Any) -> TaskContext:
    vehicle_yaml = Path(spec.vehicle).read_text()
    learned = None
    if spec.needs_learned_model:
        if spec.learned_model.path is not None:
            learned = spec.learned_model.path.read_text()
        elif (out / LEARNED_MODEL_FILE).exists():
            learned = (out / LEARNED_MODEL_FILE).read_text()
        else:
            lm = spec.learned_model
            print(f"campaign: learning the model for backstepping-learned ({lm.profile}, {lm.duration:g} s, "
                  f"seed {lm.seed}) on a worker", flush=True)
            future = client.submit(learn_nominal_model, vehicle_yaml, Path(spec.vehicle).stem, lm.profile,
                                   lm.duration, lm.seed, spec.identify_budget, pure=False)
            try:
                learned = future.result()
            except UserError:
                raise
            except Exception as exc:
                raise UserError(f"learning the model for backstepping-learned failed: {exc}",
                                hint="give models.learned as a model file path instead") from None
            (out / LEARNED_MODEL_FILE).write_text(learned)
    keep = str((out / "flights").resolve()) if spec.keep_flights else None
    return TaskContext(Path(spec.vehicle).stem, vehicle_yaml, _true_model_text(spec.vehicle), learned,
                       spec.pipeline, spec.identify_budget, keep, spec.trajectory_files)


def fingerprint(spec: CampaignSpec) -> str:
    """What makes stored rows reusable: nominal vehicle text, pipeline, models, budgets."""
    h = hashlib.sha256()
    h.update(Path(spec.vehicle).read_bytes())
    for name, text in sorted(spec.trajectory_files.items()):
        h.update(f"{name}={text}".encode())
    lm = spec.learned_model
    learned = lm.path.read_bytes() if lm.path else f"{lm.profile}/{lm.duration}/{lm.seed}".encode()
    parts = (spec.pipeline.encode(), learned, f"{spec.identify_budget}".encode(), str(spec.seed).encode())
    for part in parts:
        h.update(part)
        h.update(b"\x1f")
    return h.hexdigest()


def columns(spec: CampaignSpec, rows: list[dict[str, Any]]) -> list[str]:
    """The table's columns: id, seed, sample, parameters, status, reason, metrics, then any extra ones."""
    base = ["task_id", "seed", "sample", *spec.parameter_names()]
    extra = sorted({k for r in rows for k in r} - set(base) - set(METRIC_FIELDS) - set(TIMING_FIELDS)
                   - {"status", "reason", "crashed", "completed"})
    cols = [*dict.fromkeys([*base, "status", "reason", "completed", "crashed", *METRIC_FIELDS, *extra,
                            *TIMING_FIELDS])]
    return cols


def _failure_row(task: Task, reason: str) -> dict[str, Any]:
    return {"task_id": task.task_id, "seed": task.seed, **task.params, "status": "failed", "reason": reason}


def run_campaign(spec: CampaignSpec, out: Path, *, workers: int | None = None, scheduler: str | None = None,
                 progress: bool = True, restart: bool = False) -> CampaignRun:
    """Run every task not yet on disk in `out` and write the tables; the CampaignRun (caller: report)."""
    import shutil

    out = Path(out)
    if restart and out.exists():
        for name in ("tasks", "campaign.json", LEARNED_MODEL_FILE):
            p = out / name
            shutil.rmtree(p, ignore_errors=True) if p.is_dir() else p.unlink(missing_ok=True)
    out.mkdir(parents=True, exist_ok=True)
    store = ResultStore(out, fingerprint(spec), spec.name)
    tasks = expand(spec, spec.nominal_values())
    done = store.done_ids()
    todo = [t for t in tasks if t.task_id not in done]
    run = CampaignRun(spec, out, tasks, skipped=len(tasks) - len(todo))
    start = time.perf_counter()
    print(f"campaign {spec.name}: {len(tasks)} tasks, {run.skipped} already done, {len(todo)} to run",
          flush=True)
    if todo:
        with dask_client(workers, scheduler) as client:
            run.workers = (scheduler or f"local cluster, {workers or 2} worker processes")
            ctx = _context(spec, out, client)
            t0 = time.perf_counter()
            _submit_all(client, todo, ctx, spec, store, progress)
            run.tasks_wall_s = time.perf_counter() - t0
    run.rows = store.rows(t.task_id for t in tasks)
    lost = {t.task_id for t in tasks} - {r["task_id"] for r in run.rows}
    if lost:  # cannot happen unless the disk refused a write: say so rather than hide it
        raise UserError(f"{len(lost)} tasks have no row in {store.tasks_dir}", hint="run the command again")
    run.files = write_tables(run.rows, columns(spec, run.rows), out)
    run.wall_s = time.perf_counter() - start
    return run


def _submit_all(client: Any, todo: list[Task], ctx: TaskContext, spec: CampaignSpec, store: ResultStore,
                progress: bool) -> None:
    from dask.distributed import as_completed

    ctx_future = client.scatter(ctx, broadcast=True)
    futures = {}
    for t in todo:
        f = client.submit(run_task, t, ctx_future, spec.vehicle_keys, key=f"quadsr-task-{t.task_id}",
                          pure=False)
        futures[f] = t
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=len(todo), unit="task", desc=spec.name, file=sys.stderr, mininterval=0.5,
                   disable=not sys.stderr.isatty())
    counts = {"ok": 0, "crashed": 0, "failed": 0}
    last_print = 0.0
    try:
        for f in as_completed(futures):
            task = futures[f]
            try:
                row = f.result()
            except Exception as exc:  # KilledWorker after repeated deaths, or a scheduler error
                row = _failure_row(task, f"{type(exc).__name__}: {exc}")
            store.save(row)
            counts[row.get("status", "failed")] = counts.get(row.get("status", "failed"), 0) + 1
            finished = sum(counts.values())
            text = (f"done {counts['ok']}, crashed {counts['crashed']}, failed {counts['failed']}, "
                    f"remaining {len(todo) - finished}")
            if bar is not None and not bar.disable:
                bar.set_postfix_str(text, refresh=False)
                bar.update(1)
            elif time.monotonic() - last_print > 5.0 or finished == len(todo):
                print(f"campaign {spec.name}: {text}", flush=True)
                last_print = time.monotonic()
    finally:
        if bar is not None:
            bar.close()
