"""`quadsr campaign`: the campaign file's checks, task ids and seeds, and real runs on a local Dask cluster
(resume, a worker killed mid-task, a failing task, identical tables on 1 and 2 workers)."""

from __future__ import annotations

import os
import signal
import threading
import time
from pathlib import Path

import pandas as pd
import pytest

from bridge.errors import UserError
from quadsr.campaign.runner import run_campaign
from quadsr.campaign.spec import load_campaign
from quadsr.campaign.tasks import expand, task_id, task_seed
from quadsr.cli import main


def _spec(tmp_path: Path, text: str, name: str = "c.yaml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


SMALL = """
name: small
seed: 3
fixed: {duration: 1.0, trajectory: case2}
grid:
  controller: [pid, se3]
samples: 2
random:
  mass: {scale: [0.9, 1.1]}
"""


@pytest.mark.parametrize("text, expected", [
    ("grid: {controller: [pid]}\nfoo: 1\n", "unknown key 'foo'"),
    ("grid: {heft: [1, 2]}\n", "unknown parameter 'grid.heft'"),
    ("grid: {controller: [pid, lqr]}\n", "'grid.controller[1]' must be one of"),
    ("grid: {controller: [pid, pid]}\n", "lists a value twice"),
    ("random: {mass: {uniform: [1, 2]}}\n", "'samples' is not"),
    ("samples: 2\nrandom: {mass: {gauss: [1, 2]}}\n", "unknown distribution 'gauss'"),
    ("samples: 2\nrandom: {mass: {scale: [1.2, 0.8]}}\n", "low end 1.2 is above the high end 0.8"),
    ("samples: 2\nrandom: {wind_speed: {scale: [0, 1]}}\n", "scale multiplies a vehicle-file value"),
    ("samples: 2\nrandom: {inertia: {uniform: [0, 1]}}\n", "is a list; vary it with scale"),
    ("fixed: {turbulence: moderate}\n", "turbulence is asked for without a wind speed"),
    ("fixed: {turbulence: light}\nsamples: 2\nrandom: {wind_speed: {uniform: [0, 6]}}\n",
     "'random.wind_speed' can be 0 m/s with turbulence"),
    ("fixed: {duration: -1}\n", "must be > 0 s"),
    ("grid: {mass: [1.0]}\nfixed: {mass: 1.2}\n", "both in 'grid' and in 'fixed'"),
    ("samples: 0\n", "'samples' must be an integer >= 1"),
    ("grid: {motor: [1]}\n", "is a section, not a value"),
    ("models: {learned: missing.yaml}\n", "missing.yaml does not exist"),
    ("grid: [1, 2]\n", "key 'grid' must be a mapping"),
    ("grid: {controller: [pid]\n", "YAML syntax error at line"),
])
def test_campaign_file_mistakes_are_named(tmp_path, text, expected):
    with pytest.raises(UserError) as err:
        load_campaign(_spec(tmp_path, text))
    assert expected in str(err.value)
    assert "c.yaml" in str(err.value)


def test_cli_exits_2_with_the_message(tmp_path, capsys):
    code = main(["campaign", str(_spec(tmp_path, "grid: {heft: [1]}\n")), "--out", str(tmp_path / "o")])
    err = capsys.readouterr().err
    assert code == 2
    assert "unknown parameter 'grid.heft'" in err and "Traceback" not in err
    assert main(["campaign", str(tmp_path / "absent.yaml"), "--out", str(tmp_path / "o")]) == 2


def test_task_ids_and_seeds_depend_on_parameters_only(tmp_path):
    spec = load_campaign(_spec(tmp_path, SMALL))
    tasks = expand(spec, spec.nominal_values())
    assert len(tasks) == spec.task_count == 4
    assert len({t.task_id for t in tasks}) == 4 and len({t.seed for t in tasks}) == 4
    # the grid written in another order gives the same tasks (ids, seeds, parameters)
    reordered = SMALL.replace("[pid, se3]", "[se3, pid]")
    other = expand(load_campaign(_spec(tmp_path, reordered, "d.yaml")), spec.nominal_values())
    assert {(t.task_id, t.seed, tuple(sorted(t.params.items()))) for t in tasks} == \
        {(t.task_id, t.seed, tuple(sorted(t.params.items()))) for t in other}
    # common random numbers: both controllers fly the same draws
    by_sample = {}
    for t in tasks:
        by_sample.setdefault(t.sample, set()).add(t.params["mass"])
    assert all(len(masses) == 1 for masses in by_sample.values())
    assert all(1.4 * 0.9 <= t.params["mass"] <= 1.4 * 1.1 for t in tasks)
    # the seed and id are functions of (campaign seed, parameters)
    t = tasks[0]
    assert task_seed(3, t.params) == t.seed and task_id(3, t.params) == t.task_id
    assert task_seed(4, t.params) != t.seed
    changed = dict(t.params, mass=t.params["mass"] + 0.01)
    assert task_seed(3, changed) != t.seed


def _table(out: Path) -> pd.DataFrame:
    return pd.read_parquet(out / "results.parquet")


@pytest.mark.e2e
def test_runs_resumes_and_gives_the_same_table_on_one_and_two_workers(tmp_path):
    spec = load_campaign(_spec(tmp_path, SMALL))
    one = run_campaign(spec, tmp_path / "one", workers=1, progress=False)
    assert [r["status"] for r in one.rows] == ["ok"] * 4, [r.get("reason") for r in one.rows]
    table = _table(tmp_path / "one")
    assert list(table["task_id"]) == sorted(table["task_id"])
    assert table["max_m"].notna().all() and (table["max_m"] > 0).all()
    # the controllers differ, the draws differ: the rows are real flights
    assert table["final_m"].nunique() == 4
    # resume: two rows lost, the same command runs only those two and writes the same table
    for path in sorted((tmp_path / "one" / "tasks").glob("*.json"))[:2]:
        path.unlink()
    again = run_campaign(spec, tmp_path / "one", workers=1, progress=False)
    assert again.skipped == 2
    pd.testing.assert_frame_equal(_table(tmp_path / "one"), table)
    # a worker killed mid-task on a 2-worker cluster: no task lost, the same table
    from dask.distributed import Client, LocalCluster

    cluster = LocalCluster(n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None)
    killed: list[int] = []
    try:
        with Client(cluster) as watcher:
            def kill_one_busy_worker() -> None:
                deadline = time.monotonic() + 120
                while time.monotonic() < deadline and not killed:
                    busy = [w for w, keys in watcher.processing().items()
                            if any(str(k).startswith("quadsr-task-") for k in keys)]
                    if busy:
                        time.sleep(0.5)  # mid-flight
                        pid = watcher.run(os.getpid, workers=[busy[0]])[busy[0]]
                        os.kill(pid, signal.SIGKILL)
                        killed.append(pid)
                    time.sleep(0.05)

            killer = threading.Thread(target=kill_one_busy_worker, daemon=True)
            killer.start()
            two = run_campaign(spec, tmp_path / "two", scheduler=cluster.scheduler_address, progress=False)
            killer.join(5)
    finally:
        cluster.close()
    assert killed, "no worker was busy with a task to kill"
    assert [r["status"] for r in two.rows] == ["ok"] * 4, [r.get("reason") for r in two.rows]
    pd.testing.assert_frame_equal(_table(tmp_path / "two"), table)


@pytest.mark.e2e
def test_a_failing_task_is_a_row_with_its_reason(tmp_path):
    text = """
name: failing
fixed: {duration: 0.5, controller: pid}
samples: 2
random:
  motor.time_constant: {uniform: [-0.02, -0.01]}
"""
    run = run_campaign(load_campaign(_spec(tmp_path, text)), tmp_path / "out", workers=1, progress=False)
    assert [r["status"] for r in run.rows] == ["failed", "failed"]
    assert all("motor.time_constant" in r["reason"] for r in run.rows)
    csv = pd.read_csv(tmp_path / "out" / "results.csv")
    assert list(csv["status"]) == ["failed", "failed"]
    from quadsr.campaign.report import write_report

    report = write_report(run, "quadsr campaign c.yaml --out out").read_text()
    assert "## Failures" in report and "motor.time_constant" in report


def test_wind_parameters_become_sitl_flags():
    from quadsr.campaign.task_run import wind_args

    assert wind_args({"wind_speed": 0.0}, 5) == []
    args = wind_args({"wind_speed": 4.0, "wind_direction": 3.141592653589793, "turbulence": "moderate"}, 5)
    assert args[0] == "--wind=-4,4.89859e-16,0"  # towards south: a negative north, written with '='
    assert args[1:] == ["--turbulence", "moderate", "--wind-seed", "5"]
