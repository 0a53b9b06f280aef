"""`quadsr identify --fleet`: one identification per log on a local Dask cluster, and the fleet tables, on the
shared real PX4 logs (../shared/logs) and on our own .tlog."""

from __future__ import annotations

import math
from pathlib import Path

import pandas as pd
import pytest

from identification.fleet import expand_logs
from quadsr.cli import main

REPO = Path(__file__).resolve().parents[1]
LOGS = REPO.parent / "shared" / "logs"


def test_expand_logs_takes_folders_globs_and_files(tmp_path):
    for name in ("b.ulg", "a.tlog", "notes.txt"):
        (tmp_path / name).write_bytes(b"x")
    assert [p.name for p in expand_logs([str(tmp_path)])] == ["a.tlog", "b.ulg"]
    assert [p.name for p in expand_logs([str(tmp_path / "*.ulg"), str(tmp_path / "b.ulg")])] == ["b.ulg"]
    with pytest.raises(Exception, match="does not exist"):
        expand_logs([str(tmp_path / "missing.ulg")])
    with pytest.raises(Exception, match="no logs found"):
        expand_logs([str(tmp_path / "*.bin")])


@pytest.mark.e2e
def test_fleet_table_on_the_shared_logs(tmp_path, capsys):
    out = tmp_path / "fleet"
    shared = sorted(p.name for p in LOGS.glob("*.ulg"))
    assert len(shared) >= 3, f"the shared PX4 logs are missing from {LOGS}"
    code = main(["identify", "--fleet", str(LOGS), "-o", str(out), "--engine", "sparse", "--budget", "5",
                 "--motor-curve", "1148,-141.4", "--workers", "2", "--no-progress"])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    table = pd.read_csv(out / "fleet.csv")
    assert list(table["log"]) == shared  # one row per log, sorted
    for _, row in table.iterrows():
        if row["status"] == "ok":
            assert row["rows"] > 0
            assert all(math.isfinite(row[f"r2_{t}"]) for t in ("ax", "ay", "az", "dwx", "dwy", "dwz"))
            assert (out / "models" / f"{Path(row['log']).stem}.yaml").is_file()
        else:  # a log that cannot be identified says why, naming the log and not a temporary path
            assert row["status"] == "failed" and row["log"] in row["reason"] and "/tmp" not in row["reason"]
    assert (table["status"] == "ok").any()
    assert code == (0 if (table["status"] == "ok").all() else 1)
    terms = pd.read_csv(out / "fleet_terms.csv")
    ok_logs = set(table.loc[table["status"] == "ok", "log"])
    assert set(terms["log"]) == ok_logs and terms["coefficient"].notna().all()
    assert set(terms["target"]) == {"ax", "ay", "az", "dwx", "dwy", "dwz"}


def test_fleet_output_must_be_a_folder(tmp_path, capsys):
    (tmp_path / "model.yaml").write_text("x")
    code = main(["identify", "--fleet", str(LOGS), "-o", str(tmp_path / "model.yaml")])
    assert code == 2 and "with --fleet, -o names the output folder" in capsys.readouterr().err
