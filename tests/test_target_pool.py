"""Targets fitted side by side (identification.target_pool): the same model file from one process or two,
a worker's UserError reaching the caller whole, the workers dying with their parent, and the cases where
identify must not fork. Forks run in fresh interpreters (subprocess), as `quadsr identify` runs: pytest's
own process may hold other tests' threads."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml
from synthetic_data import synthetic_dataset

from bridge.errors import UserError
from identification.identify import identify
from identification.target_pool import processes_for

REPO = Path(__file__).resolve().parent.parent

IDENTIFY = """
import sys, json
sys.path.insert(0, {tests!r})
import numpy as np
from synthetic_data import synthetic_dataset
from identification.engine import EngineSettings, OperonSettings, SparseSettings
from identification.identify import identify
from identification.model_file import save_model

data = synthetic_dataset(1500, 4)
data.targets[:, 3] += 20.0 * np.sin(data.xi[:, 6]) * np.cos(data.xi[:, 6])  # outside the library: GP runs
small = EngineSettings(sparse=SparseSettings(thresholds=10, forward_terms=8),
                       operon=OperonSettings(population_size=100, max_length=15, optimizer_iterations=3))
model = identify(data, budget=4, seed=5, settings=small, progress=False, jobs={jobs})
save_model(model, {out!r})
print(json.dumps({{"processes": model.engine["processes"]}}))
"""


def _without_timings(node):
    """The model file's content without its wall times and creation time (all the processes may change)."""
    if isinstance(node, dict):
        return {k: _without_timings(v) for k, v in node.items()
                if "wall_time" not in k and k not in ("processes", "created")}
    if isinstance(node, list):
        return [_without_timings(v) for v in node]
    return node


def _python(code: str, timeout: float = 240.0) -> subprocess.CompletedProcess:
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=REPO,
                         timeout=timeout)
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-3000:]
    return run


def test_one_process_or_two_give_the_same_model_file(tmp_path):
    files = {}
    for jobs in (1, 2):
        out = tmp_path / f"jobs{jobs}.yaml"
        run = _python(IDENTIFY.format(tests=str(REPO / "tests"), jobs=jobs, out=str(out)))
        assert json.loads(run.stdout.strip().splitlines()[-1])["processes"] == jobs  # two really ran
        files[jobs] = yaml.safe_load(out.read_text())
    assert _without_timings(files[1]) == _without_timings(files[2])
    # the front holds genetic programming's expressions too: the seeded search ran in the workers alike
    assert "operon" in json.dumps(files[2])


BLAS_THREADS = """
import sys, json
sys.path.insert(0, {tests!r})
import threadpoolctl
from synthetic_data import synthetic_dataset
import identification.identify as ident
from identification.engine import EngineSettings, OperonSettings, SparseSettings

def blas_threads():
    return max(i["num_threads"] for i in threadpoolctl.threadpool_info() if i["user_api"] == "blas")

seen = []
real = ident.mark_self_feedback
def spy(*args, **kwargs):  # runs inside each target's job, outside the engine's own one-thread sections
    seen.append(blas_threads())
    return real(*args, **kwargs)
ident.mark_self_feedback = spy
small = EngineSettings(sparse=SparseSettings(thresholds=10, forward_terms=8),
                       operon=OperonSettings(population_size=100, max_length=15, optimizer_iterations=3))
with threadpoolctl.threadpool_limits(limits=2, user_api="blas"):
    outside = blas_threads()
    ident.identify(synthetic_dataset(800, 4), targets="dwx,dwz", budget=2, seed=5, settings=small,
                   progress=False, jobs=1)
    after = blas_threads()
print(json.dumps({{"outside": outside, "seen": seen, "after": after}}))
"""


def test_each_target_is_fitted_with_blas_on_one_thread():
    # the target jobs share the cores: BLAS's own threads would only contend (and change the rounding
    # with the machine's core count)
    run = _python(BLAS_THREADS.format(tests=str(REPO / "tests")))
    got = json.loads(run.stdout.strip().splitlines()[-1])
    assert got["outside"] == 2 and got["after"] == 2  # the caller's setting, before and after
    assert got["seen"] and set(got["seen"]) == {1}


def test_a_workers_user_error_reaches_the_caller_with_its_hint():
    code = """
from bridge.errors import UserError
from identification.target_pool import map_targets

def job(name):
    if name == "dwy":
        raise UserError("no expression for dwy", hint="raise --budget", exit_code=3)
    return name.upper()

got = []
try:
    for name, r in map_targets(job, ["fx", "fy", "dwy", "dwz"], 2):
        assert r == name.upper()
        got.append(name)
except UserError as e:
    print(",".join(got), "/", str(e).replace(chr(10), " | "), e.exit_code)
"""
    run = _python(code)
    got, error = run.stdout.strip().split(" / ")
    assert error == "no expression for dwy |   hint: raise --budget 3", run.stdout
    assert "dwy" not in got.split(","), run.stdout  # the results before it came back whole


def test_the_targets_named_first_start_first_and_every_result_comes_back_with_its_name(tmp_path):
    started = tmp_path / "started"
    code = f"""
import os, time
from identification.target_pool import map_targets

def job(name):
    fd = os.open({str(started)!r}, os.O_WRONLY | os.O_APPEND | os.O_CREAT)
    os.write(fd, (name + chr(10)).encode())
    os.close(fd)
    time.sleep(0.8)
    return name * 2

print(sorted(map_targets(job, ["fx", "fy", "fz", "dwx"], 2, first=("dwx", "fz", "az"))))
"""
    run = _python(code)
    assert run.stdout.strip() == "[('dwx', 'dwxdwx'), ('fx', 'fxfx'), ('fy', 'fyfy'), ('fz', 'fzfz')]"
    # two workers take the queue's first two together, then the next two once those are done
    order = started.read_text().split()
    assert set(order[:2]) == {"dwx", "fz"} and set(order[2:]) == {"fx", "fy"}, order


SLEEPING_WORKERS = """
import os, sys, time
from bridge.shutdown import StopSignals
from identification.target_pool import map_targets

def job(name):
    with open({pids!r}, "a") as f:
        f.write(str(os.getpid()) + chr(10))
    time.sleep(600)
"""


def _sleeping_workers(tmp_path: Path, main: str, **popen) -> tuple[subprocess.Popen, list[int]]:
    """A parent process running `main` after SLEEPING_WORKERS, and its two workers' pids once both run."""
    pids = tmp_path / "pids"
    parent = subprocess.Popen([sys.executable, "-c", SLEEPING_WORKERS.format(pids=str(pids)) + main],
                              cwd=REPO, **popen)
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline and (not pids.exists() or len(pids.read_text().split()) < 2):
        time.sleep(0.05)
    workers = [int(p) for p in pids.read_text().split()] if pids.exists() else []
    return parent, workers


def test_the_workers_die_with_their_parent(tmp_path):
    parent, workers = _sleeping_workers(tmp_path, 'list(map_targets(job, ["a", "b"], 2))')
    try:
        assert len(workers) == 2 and parent.pid not in workers
    finally:
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
    deadline = time.monotonic() + 10
    alive = workers
    while alive and time.monotonic() < deadline:
        alive = [p for p in workers if _running(p)]
        time.sleep(0.05)
    assert not alive, f"workers {alive} outlived their parent"


def test_ctrl_c_ends_the_workers_without_a_traceback(tmp_path):
    """Ctrl-C reaches the whole process group, as in a terminal: the parent (with the CLI's StopSignals) ends
    the pool and says so once; the workers, which inherited its handlers, print nothing and are gone."""
    main = """
with StopSignals(raise_interrupt=True):
    try:
        list(map_targets(job, ["a", "b"], 2))
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        sys.exit(130)
"""
    parent, workers = _sleeping_workers(tmp_path, main, start_new_session=True, stdout=subprocess.PIPE,
                                        stderr=subprocess.PIPE, text=True)
    try:
        assert len(workers) == 2
        os.killpg(parent.pid, signal.SIGINT)
        _, err = parent.communicate(timeout=30)
    finally:
        if parent.poll() is None:
            os.killpg(parent.pid, signal.SIGKILL)
            parent.wait(10)
    assert parent.returncode == 130, err
    assert err.strip() == "interrupted", err
    assert not [p for p in workers if _running(p)]


def _running(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as f:  # a zombie (dead, not yet reaped by init) is not running
        return f.read().split(")")[-1].split()[0] != "Z"


def test_identify_does_not_fork_beside_other_threads_or_for_one_target():
    assert processes_for(1, 6) == (1, "")
    assert processes_for(4, 1) == (1, "")
    stop = threading.Event()
    other = threading.Thread(target=stop.wait, daemon=True)
    other.start()
    try:
        n, why = processes_for(2, 6)
    finally:
        stop.set()
        other.join()
    assert n == 1 and "other threads" in why


def test_a_number_of_processes_below_one_is_a_clear_error():
    for bad in (0, -2, 1.5, True):
        with pytest.raises(UserError, match="number of processes"):
            identify(synthetic_dataset(300, 1), budget=1, progress=False, jobs=bad)
