"""`quadsr fly` end to end: the SITL and the companion as separate processes over real UDP on 127.0.0.1.

Also: a lost link (the SITL killed mid-flight) and bad inputs (controller, trajectory, model, state source),
which must each end with a clear message and a non-zero exit code, never a traceback.
"""

from __future__ import annotations

import csv
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
import yaml

from quadsr.cli import main

REPO = Path(__file__).resolve().parent.parent
pytestmark = pytest.mark.e2e
# a loaded CI machine can stall a process for a second: a long lockstep wait keeps the SITL from failsafe
PATIENT = ("--lockstep-timeout", "20")


def _fly_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "quadsr.cli", "fly", "--no-progress", *args]


def _env() -> dict[str, str]:
    return {**os.environ, "PYTHONUNBUFFERED": "1"}


def _last_row(path: Path) -> dict[str, str]:
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    return rows[-1]


@pytest.fixture(scope="module")
def true_model(tmp_path_factory) -> Path:
    from identification.true_model import write_true_model

    path = tmp_path_factory.mktemp("model") / "true-model.yaml"
    write_true_model("fang-chen-buaa", path)
    return path


def test_fly_case2_against_the_sitl_ends_on_the_reference(start_sitl, true_model, tmp_path):
    sitl = start_sitl("--no-gcs", "--sensors", "ideal", *PATIENT)
    out = tmp_path / "flight"
    proc = subprocess.run(
        _fly_cmd("--controller", "backstepping", "--model", str(true_model), "--trajectory", "case2",
                 "--duration", "8", "--hil", sitl.hil, "--out", str(out), "--link-timeout", "10"),
        capture_output=True, text=True, timeout=120, cwd=REPO, env=_env(),
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "Traceback" not in proc.stderr and "warning" not in proc.stdout
    # how the law was built, with the loop functions compiled (this machine has a C compiler)
    assert re.search(r"quadsr fly: law: outer: newton in thrust mode .* (\d) of \1 loop functions compiled; "
                     r"model-error observer: compiled", proc.stdout), proc.stdout
    for name in ("flight.tlog", "steps.csv", "metrics.md", "metrics.csv", "tracking.png", "path3d.png"):
        assert (out / name).stat().st_size > 0, name
    for name in ("tracking.png", "path3d.png"):
        assert (out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    last = _last_row(out / "steps.csv")
    t = float(last["t"])
    assert t == pytest.approx(8.0 - 0.004)
    x, y, z = (float(last[k]) for k in ("true_x", "true_y", "true_z"))
    err = ((x - 2.0) ** 2 + (y - 4.0) ** 2 + (z + 0.3 * t) ** 2) ** 0.5
    assert err < 0.05
    with (out / "metrics.csv").open(newline="") as fh:
        metrics = next(csv.DictReader(fh))
    assert metrics["controller"] == "backstepping" and metrics["completed"] == "True"
    assert float(metrics["final_m"]) < 0.05
    # the tlog holds both directions: the SITL's steps and our actuator replies, one per step
    from bridge.tlog import read_tlog

    kinds: dict[str, int] = {}
    for _, msg in read_tlog(out / "flight.tlog"):
        kinds[msg.get_type()] = kinds.get(msg.get_type(), 0) + 1
    assert kinds["HIL_ACTUATOR_CONTROLS"] == 2000
    assert kinds["HIL_SENSOR"] >= 2000


def test_fly_on_estimated_state_with_realistic_sensors(start_sitl, tmp_path):
    sitl = start_sitl("--no-gcs", "--sensors", "realistic", "--seed", "4", *PATIENT)
    out = tmp_path / "flight"
    proc = subprocess.run(
        _fly_cmd("--controller", "se3", "--trajectory", "case2", "--state", "sensors", "--duration", "6",
                 "--hil", sitl.hil, "--out", str(out), "--link-timeout", "10"),
        capture_output=True, text=True, timeout=120, cwd=REPO, env=_env(),
    )
    assert proc.returncode == 0, proc.stdout + proc.stderr
    last = _last_row(out / "steps.csv")
    true_p = [float(last[k]) for k in ("true_x", "true_y", "true_z")]
    est_p = [float(last[k]) for k in ("x", "y", "z")]
    ref_p = [float(last[k]) for k in ("ref_x", "ref_y", "ref_z")]
    assert max(abs(a - b) for a, b in zip(true_p, ref_p, strict=True)) < 0.1
    assert max(abs(a - b) for a, b in zip(true_p, est_p, strict=True)) < 0.1


def test_lost_link_is_reported_within_half_a_second_and_exits_nonzero(start_sitl, tmp_path):
    sitl = start_sitl("--no-gcs", "--sensors", "ideal")
    out = tmp_path / "flight"
    proc = subprocess.Popen(
        _fly_cmd("--controller", "se3", "--trajectory", "case1", "--duration", "600", "--hil", sitl.hil,
                 "--out", str(out)),
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO, env=_env(),
    )
    lines: list[tuple[float, str]] = []

    def read() -> None:
        assert proc.stderr is not None
        for line in proc.stderr:
            lines.append((time.monotonic(), line))

    reader = threading.Thread(target=read, daemon=True)
    reader.start()
    try:
        deadline = time.monotonic() + 60
        steps = out / "steps.csv"
        while not (steps.exists() and steps.read_text().count("\n") > 300):  # flushed each 250 steps
            assert time.monotonic() < deadline and proc.poll() is None, "".join(line for _, line in lines)
            time.sleep(0.05)
        killed = time.monotonic()
        sitl.proc.kill()
        rc = proc.wait(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
    reader.join(5)
    stdout = proc.stdout.read() if proc.stdout else ""
    lost = [(t, line) for t, line in lines if "link lost" in line]
    assert rc == 3, stdout + "".join(line for _, line in lines)
    assert lost, "".join(line for _, line in lines)
    assert lost[0][0] - killed < 1.5  # 0.5 s without a sensor message, plus process scheduling
    text = "".join(line for _, line in lines)
    assert "no sensor message from the SITL" in text and "stopped commanding" in text
    assert "Traceback" not in text
    # the partial flight is still written up
    assert "| flown to the end | no |" in (out / "metrics.md").read_text()
    assert (out / "tracking.png").stat().st_size > 0


def test_unknown_controller_and_state_list_the_choices(capsys, tmp_path):
    assert main(["fly", "--controller", "lqr", "--trajectory", "case2", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "unknown controller 'lqr'" in err and "backstepping, pid, se3" in err
    assert main(["fly", "--controller", "se3", "--state", "psychic", "--trajectory", "case2",
                 "--out", str(tmp_path)]) == 2
    assert "truth, sensors" in capsys.readouterr().err


def test_unknown_or_bad_trajectory_is_refused(capsys, tmp_path):
    assert main(["fly", "--controller", "se3", "--trajectory", "case3", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "case3" in err and "case1, case2" in err
    bad = tmp_path / "traj.yaml"
    bad.write_text("expressions: {x: '2', y: '4', z: '-0.3*t'}\nspeed: 3\n")
    assert main(["fly", "--controller", "se3", "--trajectory", str(bad), "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert str(bad) in err and "speed" in err and "Traceback" not in err


def test_model_the_controller_cannot_invert_is_refused_with_the_reason(capsys, true_model, tmp_path):
    data = yaml.safe_load(true_model.read_text())
    data["targets"]["az"]["expression"] = "9.8 - 0.0393*vz*Abs(vz)"  # thrust no longer depends on the motors
    bad = tmp_path / "no-thrust.yaml"
    bad.write_text(yaml.safe_dump(data, sort_keys=False))
    args = ["fly", "--controller", "backstepping", "--model", str(bad), "--trajectory", "case2",
            "--hil", "udp:127.0.0.1:9", "--out", str(tmp_path / "out")]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "cannot hover" in err or "depend on" in err
    assert not (tmp_path / "out" / "flight.tlog").exists()  # refused at start, before connecting
    assert main(["fly", "--controller", "backstepping", "--trajectory", "case2", "--out", str(tmp_path)]) == 2
    assert "needs a model file" in capsys.readouterr().err
    assert main(["fly", "--controller", "backstepping", "--model", str(tmp_path / "missing.yaml"),
                 "--trajectory", "case2", "--out", str(tmp_path)]) == 2
    assert "does not exist" in capsys.readouterr().err


def test_no_sitl_listening_is_a_clear_error(capsys, tmp_path, udp_port):
    args = ["fly", "--controller", "se3", "--trajectory", "case2", "--hil", f"udp:127.0.0.1:{udp_port}",
            "--connect-timeout", "0.5", "--out", str(tmp_path / "out")]
    assert main(args) == 2
    assert "no SITL answered" in capsys.readouterr().err
