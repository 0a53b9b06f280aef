"""A fleet of logs: one identification per log on a Dask cluster, and the fleet tables that compare them.

fleet.csv (and .parquet): one row per log: file, format, SHA-256, rows used and dropped, the R^2 of every
target on the log's held-out rows, and the chosen expression per target (or the reason the log failed).
fleet_terms.csv: one row per (log, target, term) with the term's coefficient (SI units of the target per
unit of the term), so that an engineer sees which vehicles differ, term by term. Each log's model is written
to OUT/models/<log stem>.yaml.
"""

from __future__ import annotations

import glob
import math
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bridge.errors import UserError

LOG_SUFFIXES = (".tlog", ".ulg", ".bin", ".BIN", ".csv", ".parquet")


@dataclass(frozen=True)
class FleetSettings:
    """How each log is identified: targets source, motor curve, engine, budget [generations/target], seed."""

    targets: str = "truth"
    motor_curve: str | None = None
    engine: str = "default"
    budget: int = 60  # genetic-programming generations per target
    seed: int = 0


def expand_logs(inputs: list[str]) -> list[Path]:
    """The log files named by paths, folders (their logs, sorted) and globs; UserError if none."""
    found: list[Path] = []
    for item in inputs:
        p = Path(item)
        if p.is_dir():
            found += sorted(f for f in p.iterdir() if f.is_file() and f.suffix in LOG_SUFFIXES)
        elif any(ch in item for ch in "*?["):
            found += sorted(Path(m) for m in glob.glob(item) if Path(m).is_file())
        elif p.is_file():
            found.append(p)
        else:
            raise UserError(f"log {item} does not exist", hint="give log files, folders of logs, or a glob")
    unique = list(dict.fromkeys(f.resolve() for f in found))
    if not unique:
        raise UserError(f"no logs found in {', '.join(inputs)}",
                        hint=f"logs end in {', '.join(sorted(set(s.lower() for s in LOG_SUFFIXES)))}")
    return unique


def identify_log(data: bytes, name: str, settings: FleetSettings) -> dict[str, Any]:
    """One log identified on a worker (its bytes travel with the task): its fleet row; never raises."""
    import tempfile

    start = time.perf_counter()
    row: dict[str, Any] = {"log": name, "status": "failed", "reason": ""}
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / name
        path.write_bytes(data)
        try:
            from identification.dataset import file_sha256, load_dataset
            from identification.identify import identify
            from identification.model_file import expression_to_string, save_model

            dataset = load_dataset(path, targets=settings.targets, motor_curve=settings.motor_curve)
            row.update(format=dataset.format, sha256=file_sha256(path), rows=int(len(dataset)),
                       dropped=int(dataset.dropped_rows))
            model = identify(dataset, engine=settings.engine, budget=settings.budget, seed=settings.seed,
                             progress=False)
            terms = []
            for target, tm in model.targets.items():
                metrics = tm.metrics.get("validation", tm.metrics.get("train", {}))
                row[f"r2_{target}"] = float(metrics.get("r2", math.nan))
                row[f"expr_{target}"] = expression_to_string(tm.expression)
                for term, coef in tm.expression.as_coefficients_dict().items():
                    terms.append({"log": name, "target": target, "term": str(term),
                                  "coefficient": float(coef)})
            row["model_yaml"] = save_model(model, Path(tmp) / "model.yaml").read_text()
            row["terms"] = terms
            row["status"] = "ok"
        except UserError as exc:
            row["reason"] = str(exc).replace(str(path), name)
        except Exception as exc:  # one bad log must not lose the fleet
            trace = traceback.format_exc(limit=3).replace("\n", " ")
            row["reason"] = f"{type(exc).__name__}: {exc} | {trace}".replace(str(path), name)
    row["wall_s"] = time.perf_counter() - start
    return row


def identify_fleet(logs: list[Path], out: Path, settings: FleetSettings, *, workers: int | None = 2,
                   scheduler: str | None = None) -> list[dict[str, Any]]:
    """Identify every log on a Dask cluster; write fleet.csv/.parquet, fleet_terms.csv, models/; the rows."""
    import pandas as pd
    from dask.distributed import as_completed

    from identification.cluster import dask_client

    out = Path(out)
    (out / "models").mkdir(parents=True, exist_ok=True)
    names = [p.name for p in logs]
    if len(set(names)) != len(names):  # same file name in two folders: keep them apart
        names = [f"{p.parent.name}_{p.name}" for p in logs]
    rows: list[dict[str, Any]] = []
    with dask_client(workers, scheduler) as client:
        futures = {client.submit(identify_log, p.read_bytes(), n, settings, pure=False): n
                   for p, n in zip(logs, names, strict=True)}
        for k, f in enumerate(as_completed(futures), 1):
            try:
                row = f.result()
            except Exception as exc:  # a worker died on it repeatedly
                row = {"log": futures[f], "status": "failed", "reason": f"{type(exc).__name__}: {exc}"}
            rows.append(row)
            what = "ok" if row["status"] == "ok" else f"failed: {row['reason'][:120]}"
            print(f"fleet: [{k}/{len(futures)}] {row['log']}: {what}", file=sys.stderr, flush=True)
    rows.sort(key=lambda r: r["log"])
    terms = []
    for row in rows:
        model_yaml = row.pop("model_yaml", None)
        if model_yaml:
            (out / "models" / f"{Path(row['log']).stem}.yaml").write_text(model_yaml)
        terms += row.pop("terms", [])
    table = pd.DataFrame(rows)
    table = table.drop(columns=["wall_s"], errors="ignore")  # machine-dependent
    table.to_csv(out / "fleet.csv", index=False, float_format="%.9g")
    table.to_parquet(out / "fleet.parquet", index=False)
    pd.DataFrame(terms, columns=["log", "target", "term", "coefficient"]).to_csv(
        out / "fleet_terms.csv", index=False, float_format="%.9g")
    return rows
