"""A campaign's results on disk: one JSON file per finished task (what resuming skips), and the tables.

OUT/tasks/<task id>.json is written atomically by the client as each task comes back, so an interrupted
campaign keeps every finished task. results.parquet and results.csv hold one row per task, sorted by task
id, with only what does not depend on the machine (parameters, status, reason, metrics): the same campaign
gives the same table on 1 or N workers. Machine-dependent columns (wall time, control step times) go to
timings.csv.
"""

from __future__ import annotations

import json
import math
import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

from bridge.errors import UserError
from quadsr.campaign.task_run import TIMING_FIELDS

STATE_FILE = "campaign.json"


def _json_value(value: Any) -> Any:
    if isinstance(value, float) and not math.isfinite(value):
        return None
    if isinstance(value, tuple):
        return [_json_value(v) for v in value]
    return value


class ResultStore:
    """OUT/tasks/*.json: the rows of finished tasks; OUT/campaign.json: which campaign they belong to."""

    def __init__(self, out: Path, fingerprint: str, name: str):
        self.out = Path(out)
        self.tasks_dir = self.out / "tasks"
        self.tasks_dir.mkdir(parents=True, exist_ok=True)
        state = self.out / STATE_FILE
        if state.exists():
            try:
                old = json.loads(state.read_text())
            except (OSError, ValueError):
                old = {}
            if old.get("fingerprint") != fingerprint:
                raise UserError(f"{self.out} holds the results of another campaign ({old.get('name', '?')}) "
                                "or of this one with another vehicle, model or pipeline",
                                hint="use another --out, or --restart to discard those results")
        else:
            self._write_json(state, {"name": name, "fingerprint": fingerprint})

    @staticmethod
    def _write_json(path: Path, data: Any) -> None:
        tmp = path.with_suffix(path.suffix + ".tmp")
        tmp.write_text(json.dumps(data, sort_keys=True, indent=1, default=_json_value))
        os.replace(tmp, path)

    def done_ids(self) -> set[str]:
        """Ids of the tasks whose rows are on disk."""
        return {p.stem for p in self.tasks_dir.glob("*.json")}

    def save(self, row: dict[str, Any]) -> None:
        """Write one task's row (atomically: a killed client leaves either the whole row or none)."""
        clean = {k: _json_value(v) for k, v in row.items()}
        self._write_json(self.tasks_dir / f"{row['task_id']}.json", clean)

    def rows(self, ids: Iterable[str]) -> list[dict[str, Any]]:
        """The stored rows of these tasks, sorted by task id."""
        out = []
        for tid in sorted(ids):
            path = self.tasks_dir / f"{tid}.json"
            if path.exists():
                out.append(json.loads(path.read_text()))
        return out


def write_tables(rows: list[dict[str, Any]], columns: list[str], out: Path) -> dict[str, Path]:
    """results.parquet, results.csv (deterministic columns) and timings.csv; their paths."""
    import pandas as pd

    out = Path(out)
    table_cols = [c for c in columns if c not in TIMING_FIELDS]
    frame = pd.DataFrame([{c: r.get(c) for c in table_cols} for r in rows], columns=table_cols)
    for c in table_cols:  # lists (vector vehicle keys) as text: Parquet and CSV both take them
        if frame[c].map(lambda v: isinstance(v, list)).any():
            frame[c] = frame[c].map(lambda v: json.dumps(v) if isinstance(v, list) else v)
    files = {"parquet": out / "results.parquet", "csv": out / "results.csv", "timings": out / "timings.csv"}
    frame.to_parquet(files["parquet"], index=False)
    frame.to_csv(files["csv"], index=False, float_format="%.9g")
    timing = pd.DataFrame([{c: r.get(c) for c in ("task_id", *TIMING_FIELDS)} for r in rows])
    timing.to_csv(files["timings"], index=False, float_format="%.6g")
    return files
