"""`quadsr paper` end to end: the whole pipeline as a subprocess, with its SITL children, over real UDP.

One --quick run is checked from its outputs (report tables, PNGs, model files, tlogs, the learned model's
accuracy recomputed from the validation flight, the tracking error recomputed from the logged steps). The
failure paths are real too: a SITL child killed mid-flight, Ctrl-C, and a bad vehicle file.
"""

from __future__ import annotations

import csv
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from conftest import run_watched

REPO = Path(__file__).resolve().parent.parent
# the quick run is watched for hangs by run_watched (600 s of silence), not by a budget on its wall time
pytestmark = [pytest.mark.e2e, pytest.mark.timeout(1800)]

TARGETS = ("ax", "ay", "az", "dwx", "dwy", "dwz")
CONTROLLERS = ("backstepping (learned)", "backstepping (true model)", "pid", "se3")
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "quadsr.cli", "paper", *args]


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONUNBUFFERED": "1"}


def _section(text: str, heading: str) -> str:
    """The text of a '## heading' section of report.md, up to the next '## '."""
    start = text.index(heading)
    end = text.find("\n## ", start + len(heading))
    return text[start:end if end >= 0 else None]


def _table_rows(text: str) -> list[list[str]]:
    """Cells of the Markdown table rows in text (header and separator rows left out)."""
    rows = []
    for line in text.splitlines():
        if line.startswith("|") and not line.startswith("|---") and not line.startswith("| ---"):
            rows.append([c.strip() for c in line.strip().strip("|").split("|")])
    return rows[1:] if rows else rows


def _check_png(path: Path) -> None:
    import matplotlib.image

    assert path.is_file(), f"{path} is missing"
    assert path.read_bytes()[:8] == PNG_MAGIC, f"{path} is not a PNG"
    image = matplotlib.image.imread(path)  # decodes the whole file
    assert image.ndim == 3 and image.shape[0] > 100 and image.shape[1] > 100, (path, image.shape)
    assert float(image[..., :3].std()) > 0.01, f"{path} is blank"


def _children(pid: int) -> list[int]:
    """PIDs of the running processes whose parent is pid (from /proc)."""
    out = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text()
        except OSError:
            continue
        if int(stat.rsplit(")", 1)[1].split()[1]) == pid:
            out.append(int(entry.name))
    return out


def _alive(pid: int) -> bool:
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return False
    return stat.rsplit(")", 1)[1].split()[0] != "Z"


def _sitl_children(pid: int) -> list[int]:
    found = []
    for child in _children(pid):
        try:
            cmdline = Path(f"/proc/{child}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        if b"sitl" in cmdline:
            found.append(child)
    return found


def _wait_for_line(proc: subprocess.Popen, pattern: str, timeout: float) -> list[str]:
    """Read proc's stdout until a line matches pattern; the lines read. Fails after timeout s."""
    rx = re.compile(pattern)
    lines: list[str] = []
    deadline = time.monotonic() + timeout
    assert proc.stdout is not None
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        if not line:
            break
        lines.append(line)
        if rx.search(line):
            return lines
    raise AssertionError(f"no line matching {pattern!r}; got:\n{''.join(lines)}")


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory) -> tuple[subprocess.CompletedProcess, Path]:
    out = tmp_path_factory.mktemp("paper") / "results"
    # a stage prints its line as it starts and its result as it ends: 600 s of silence is a hang
    proc = run_watched(_cmd("--quick", "--out", str(out), "--seed", "0"), stall_s=600.0, cwd=REPO, env=_env())
    return proc, out


def test_quick_run_writes_the_report_figures_models_and_logs(quick_run):
    proc, out = quick_run
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr
    for i, stage in enumerate(("true-model", "fly-train", "fly-validate", "identify", "validate", "track",
                               "figures"), 1):
        assert re.search(rf"^\[{i}/7\] {stage}: done in \d+\.\d s", proc.stdout, re.M), stage

    report = (out / "report.md").read_text(encoding="utf-8")
    assert "**Complete**" in report
    # Table I: six rows, ours beside the paper's numbers
    table1 = _table_rows(_section(report, "## Identification: Table I"))
    assert [re.search(r"\((\w+)\)", r[0]).group(1) for r in table1] == list(TARGETS)
    assert [r[6] for r in table1] == ["0.9707", "0.8781", "0.9907", "1.0000", "1.0000", "1.0000"]
    assert all(float(r[3]) >= 0.999 for r in table1)
    # the equations: learned, paper and true model, as display math
    equations = _section(report, "## Learned equations")
    assert equations.count("$$") >= 2 * 3 * 6
    assert r"\dot\omega_x = 8.33 \cdot 10^{-5} f_2 + 0.697 \omega_y \omega_z" in equations  # paper zeta_10
    # tracking: every controller on both cases, flown to the end
    tracking = _table_rows(_section(report, "## Tracking"))
    assert {(r[0], r[1]) for r in tracking} == {(c, k) for c in CONTROLLERS for k in ("case1", "case2")}
    assert all(r[12] == "yes" for r in tracking), tracking
    # the floors, checked in the report (the step time depends on the machine's load: listed)
    for case in ("case1", "case2"):
        assert (f"- PASS: backstepping on the learned model, {case}: RMS after 5 s <= 1.2 x the true-model "
                "controller's") in report
        assert re.search(rf"- (PASS|FAIL): backstepping on the learned model, {case}: median control step "
                         "< 200 us", report)
    assert "- PASS: backstepping on the learned model, case2: within 5 cm of the reference by 4 s" in report
    assert "| quadsr |" in report and "| pyoperon |" in report and "seed: 0" in report

    # every figure linked from the report exists and is a valid PNG
    links = re.findall(r"\]\(([^)]+\.png)\)", report)
    for name in ("validation/fig3_targets.png", "fig4_case1_tracking.png", "fig5_paths3d.png",
                 "fig6_case2_tracking.png"):
        assert name in links
    for link in set(links):
        _check_png(out / link)

    from identification.model_file import load_model

    learned = load_model(out / "model.yaml")
    truth = load_model(out / "true-model.yaml")
    assert learned.kind == "learned" and truth.kind == "true-model"
    assert learned.target_names == TARGETS and truth.target_names == TARGETS
    tlogs = sorted(p.relative_to(out).as_posix() for p in out.rglob("*.tlog"))
    assert "flights/paper-train.tlog" in tlogs and "flights/paper-validate.tlog" in tlogs
    assert len(tlogs) == 2 + 8 and all((out / t).stat().st_size > 10_000 for t in tlogs)
    with (out / "identification.csv").open(newline="") as fh:
        assert [row["target"] for row in csv.DictReader(fh)] == list(TARGETS)


def test_quick_run_learned_model_fits_the_validation_flight_and_tracks_within_a_centimetre(quick_run):
    proc, out = quick_run
    assert proc.returncode == 0, proc.stderr[-3000:]
    from identification.dataset import load_dataset
    from identification.model_file import load_model
    from identification.validate import evaluate_model

    # R^2 recomputed here from the validation flight's log, not read from the report
    validation = load_dataset(out / "flights/paper-validate.tlog")
    _, metrics = evaluate_model(load_model(out / "model.yaml"), validation)
    assert all(metrics[t]["r2"] >= 0.999 for t in TARGETS), metrics

    with (out / "tracking.csv").open(newline="") as fh:
        rows = {(r["controller"], r["case"]): r for r in csv.DictReader(fh)}
    assert set(rows) == {(c, k) for c in CONTROLLERS for k in ("case1", "case2")}
    for case in ("case1", "case2"):
        row = rows[("backstepping (learned)", case)]
        assert float(row["rms_after_5s_m"]) < 0.01, row
        # and from the logged steps: true position against the reference, t >= 5 s
        steps = out / "tracking" / row["flight_dir"] / "steps.csv"
        with steps.open(newline="") as fh:
            data = list(csv.DictReader(fh))
        t = np.array([float(d["t"]) for d in data])
        err = np.array([[float(d[f"true_{a}"]) - float(d[f"ref_{a}"]) for a in "xyz"] for d in data])
        assert t[-1] >= 11.9
        rms = float(np.sqrt(np.mean(np.sum(err[t >= 5.0] ** 2, axis=1))))
        assert rms < 0.01, (case, rms)


def test_a_killed_sitl_child_fails_the_stage_and_leaves_a_report(tmp_path):
    out = tmp_path / "results"
    proc = subprocess.Popen(_cmd("--quick", "--out", str(out)), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=REPO, env=_env())
    killed: set[int] = set()
    sitl_log = out / "flights" / "sitl-paper-train.log"
    try:
        _wait_for_line(proc, r"^\[2/7\] fly-train:", timeout=60)
        deadline = time.monotonic() + 30
        while "listening" not in (sitl_log.read_text() if sitl_log.exists() else ""):
            assert time.monotonic() < deadline and proc.poll() is None, "the training SITL never listened"
            time.sleep(0.02)
        # the SITL child is up and the training flight under way: kill it (and any later one) from outside
        deadline = time.monotonic() + 90
        while proc.poll() is None and time.monotonic() < deadline:
            for child in _sitl_children(proc.pid):
                os.kill(child, signal.SIGKILL)
                killed.add(child)
            time.sleep(0.05)
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert killed, "no SITL child was seen"
    assert proc.returncode == 1, stderr
    # killed mid-flight, or between its start and the companion's connection: the link is lost either way
    assert re.search(r"quadsr paper: stage 'fly-train' failed: no (step from the SITL|SITL answered)", stderr)
    assert "had exited with code -9" in stderr
    assert "Traceback" not in stderr
    report = (out / "report.md").read_text(encoding="utf-8")
    assert "Incomplete: stage 'fly-train' failed" in report
    stages = {r[1]: r[3] for r in _table_rows(_section(report, "## Stages")) if r[0]}
    assert stages["true-model"] == "done" and stages["fly-train"] == "**failed**"
    assert stages["identify"] == "not run"
    assert (out / "true-model.yaml").is_file()
    assert not any(_alive(pid) for pid in killed)


def test_ctrl_c_stops_the_sitl_child_and_exits_130(tmp_path):
    out = tmp_path / "results"
    proc = subprocess.Popen(_cmd("--quick", "--out", str(out)), stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, cwd=REPO, env=_env())
    try:
        _wait_for_line(proc, r"^\[2/7\] fly-train:", timeout=60)
        deadline = time.monotonic() + 30
        sitl: list[int] = []
        while not sitl and time.monotonic() < deadline:
            sitl = _sitl_children(proc.pid)
            time.sleep(0.05)
        assert sitl, "no SITL child was seen"
        time.sleep(0.3)
        proc.send_signal(signal.SIGINT)  # to the pipeline only: it must stop its child itself
        stdout, stderr = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 130, stderr
    assert re.search(r"quadsr paper: interrupted \(SIGINT\) during stage '(fly-train|fly-validate)'",
                     stderr), stderr
    assert "Traceback" not in stderr
    assert not any(_alive(pid) for pid in sitl)
    assert "Incomplete: interrupted (SIGINT) during stage" in (out / "report.md").read_text(encoding="utf-8")


def test_a_bad_vehicle_file_is_a_user_error_before_any_stage(tmp_path):
    bad = tmp_path / "vehicle.yaml"
    bad.write_text("mass: -1\n")
    proc = subprocess.run(_cmd("--quick", "--out", str(tmp_path / "results"), "--vehicle", str(bad)),
                          capture_output=True, text=True, timeout=60, cwd=REPO, env=_env())
    assert proc.returncode == 2, proc.stderr
    assert "quadsr paper: error:" in proc.stderr and str(bad) in proc.stderr
    assert "Traceback" not in proc.stderr
    assert not (tmp_path / "results" / "report.md").exists()
