"""The companion through real PX4 OFFBOARD: `quadsr fly --autopilot` against `quadsr px4 --mode realtime`.

One PX4 boot (real-time pacing, as a companion on a real vehicle lives) serves the module, in order: Case II
to within 10 cm of (2, 4, z_d) by 8 s (quadsr's truth), PX4's ULog of it read by `quadsr identify`, then
PX4's own offboard-loss failsafe (the companion
frozen with SIGSTOP until PX4 reports it left OFFBOARD), then a forced disarm. Instance N <= 9 so that every
companion run answers from PX4's offboard remote port 14540+N (PX4 keeps its first partner).
"""

from __future__ import annotations

import contextlib
import os
import re
import signal
import subprocess
import sys

import pytest
import yaml
from conftest import assert_case2_tracked
from px4_run import PX4_DIR, REPO, Gcs, QuadsrPx4, mav

from bridge.vehicle import load_vehicle
from identification.true_model import write_true_model
from quadsr.px4_launch import Px4Ports

OFFBOARD = 6 << 16  # PX4 main mode in HEARTBEAT.custom_mode


@pytest.fixture(scope="module")
def px4_rt(tmp_path_factory):
    """`quadsr px4 --mode realtime` (ideal sensors) ready for takeoff, a GCS on it, the true model file."""
    work = tmp_path_factory.mktemp("px4rt")
    model = work / "true.yaml"
    write_true_model(load_vehicle("fang-chen-buaa"), model)
    run = QuadsrPx4("--px4", str(PX4_DIR), "--instance", "1-9", "--work", str(work), "--sensors",
                    "ideal", "--mode", "realtime")
    instance = run.instance
    try:
        run.wait_for("ready for takeoff", 90.0)
        gcs = Gcs(Px4Ports(instance).gcs, instance + 1)
        gcs.connect()
        yield run, gcs, work, model, Px4Ports(instance).offboard
        gcs.close()
    finally:
        run.stop()


def in_offboard(gcs: Gcs) -> bool:
    """True if PX4's last HEARTBEAT said OFFBOARD."""
    return gcs.custom_mode is not None and gcs.custom_mode & 0xFF0000 == OFFBOARD


def fly(work, model, port, out, trajectory="case2", duration=8.5) -> subprocess.Popen:
    """`quadsr fly --autopilot` as a separate process."""
    return subprocess.Popen(
        [sys.executable, "-m", "quadsr.cli", "fly", "--model", str(model), "--trajectory", str(trajectory),
         "--duration", str(duration), "--autopilot", f"udp:127.0.0.1:{port}", "--truth",
         str(work / "truth.tlog"), "--out", str(out), "--no-progress"],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def started(proc: subprocess.Popen) -> str:
    """The companion's output up to its start line (printed once its law is derived, before it connects):
    its start-up (imports, sympy, C compiler) then does not count against a budget of simulated time."""
    head = ""
    while "through PX4 OFFBOARD at" not in head:
        line = proc.stdout.readline()
        if not line:
            raise AssertionError(f"quadsr fly ended before it started flying:\n{head}")
        head += line
    return head


@contextlib.contextmanager
def companion_killed_on_failure(proc: subprocess.Popen, head: str):
    """On a failed wait the companion is killed (it would hold PX4's offboard port for the next test) and its
    output joins the failure."""
    try:
        yield
    except AssertionError as exc:
        proc.kill()
        raise AssertionError(f"{exc}\nquadsr fly said:\n{head}{proc.communicate()[0]}") from None


@pytest.fixture(scope="module")
def case2_flight(px4_rt, tmp_path_factory):
    """Case II flown once through PX4 OFFBOARD: (the companion's exit code, its output, its --out folder).
    A fixture, so that the ULog test has its flight whichever tests are selected."""
    run, gcs, work, model, port = px4_rt
    out = tmp_path_factory.mktemp("case2") / "case2"
    proc = fly(work, model, port, out)
    output, _ = proc.communicate(timeout=120)
    return proc.returncode, output, out


def test_case2_through_px4_offboard(case2_flight):
    returncode, output, out = case2_flight
    assert returncode == 0, output
    assert_case2_tracked(out, settle_s=8.0, tolerance_m=0.10)
    assert "(truth)" in output


def test_px4_ulog_of_the_flight_is_read_by_quadsr_identify(px4_rt, case2_flight, tmp_path):
    run, gcs, work, model, port = px4_rt
    assert case2_flight[0] == 0, case2_flight[1]
    ulogs = sorted((work / "rootfs" / "log").rglob("*.ulg"))
    assert ulogs, "PX4 wrote no ULog"
    done = subprocess.run([sys.executable, "-m", "quadsr.cli", "identify", str(ulogs[-1]), "-o",
                           str(tmp_path / "model.yaml"), "--motor-curve", "fang-chen-buaa", "--engine",
                           "sparse", "--targets", "az", "--no-progress"],
                          cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    said = done.stderr + done.stdout
    # PX4 SITL's esc_status is made up: not used; quadsr's airframe logs actuator_motors at the control rate
    assert "motor commands from actuator_motors" in said
    rows = int(re.search(r"(\d+) rows from 1 log", said).group(1))
    assert rows > 1000  # boot, take-off and Case II on one timeline (the log is still being written)
    learned = yaml.safe_load((tmp_path / "model.yaml").read_text())
    assert learned["targets"]["az"]["expression"]


def test_offboard_loss_failsafe_ends_the_flight_with_a_clear_message(px4_rt, tmp_path):
    run, gcs, work, model, port = px4_rt
    hold = tmp_path / "hold.yaml"
    hold.write_text('name: hold\nduration: 60\nexpressions: {x: "2", y: "4", z: "-2.5", yaw: "0"}\n')
    gcs.drain()
    proc = fly(work, model, port, tmp_path / "loss", hold, 60)
    head = started(proc)
    gcs.drain()
    with companion_killed_on_failure(proc, head):
        gcs.run_until(in_offboard, sim_s=30.0)
        os.kill(proc.pid, signal.SIGSTOP)  # the companion freezes: no more setpoints
        try:
            gcs.run_until(lambda g: not in_offboard(g), sim_s=10.0)
        finally:
            os.kill(proc.pid, signal.SIGCONT)
    output = head + proc.communicate(timeout=60)[0]
    assert proc.returncode == 4, output
    # the companion sees PX4 leave OFFBOARD, or (its queue overflowed while frozen) that its setpoints
    # stopped for longer than PX4's offboard-loss timeout
    assert "PX4 left OFFBOARD" in output or "past PX4's offboard-loss timeout" in output, output
    assert "Traceback" not in output
    assert gcs.armed  # PX4's failsafe keeps flying (hold or land), the companion stopped commanding


def test_disarm_ends_the_flight_with_a_clear_message(px4_rt, tmp_path):
    run, gcs, work, model, port = px4_rt
    hold = tmp_path / "hold.yaml"
    hold.write_text('name: hold\nduration: 60\nexpressions: {x: "2", y: "4", z: "-1.0", yaw: "0"}\n')
    gcs.drain()
    proc = fly(work, model, port, tmp_path / "disarm", hold, 60)
    head = started(proc)
    gcs.drain()
    with companion_killed_on_failure(proc, head):
        gcs.run_until(lambda g: in_offboard(g) and g.armed, sim_s=30.0)
        gcs.run_until(lambda g: g.position[2] < -0.5, sim_s=20.0)
    assert gcs.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 21196) == mav.MAV_RESULT_ACCEPTED  # forced
    output = head + proc.communicate(timeout=60)[0]
    assert proc.returncode == 4, output
    assert "PX4 disarmed" in output and "Traceback" not in output
