"""The companion through the real ArduCopter's GUIDED mode: `quadsr fly --autopilot tcp:...` (a separate
process, MAVLink 2 over TCP) against `quadsr ardupilot` (ArduCopter + quadsr's SITL). One ArduPilot boot
serves the module: first ArduCopter refuses to arm (a pre-arm check made to fail by a GCS on its second
MAVLink port) and the companion says so; then, the check passing again, Case II within 15 cm of
(2, 4, -0.3 t) by 10 s (quadsr's truth). Bounds are in ArduPilot's simulated time (the companion's waits
and --duration); ArduPilot runs at --speedup 4 so that the companion keeps up on a loaded machine."""

from __future__ import annotations

import subprocess
import sys

import pytest

from bridge.vehicle import load_vehicle
from identification.ardupilot_flight import ArduCopterLink
from identification.true_model import write_true_model
from quadsr.ardupilot_process import TCP_BASE, ArduPilotProcess
from sitl.ardupilot_params import ardupilot_parameters
from tests.conftest import REPO, assert_case2_tracked

ARDUPILOT = REPO.parent / "shared" / "ardupilot"


@pytest.fixture(scope="module")
def arducopter(tmp_path_factory):
    """`quadsr ardupilot` at 4x, a GCS on its SERIAL1 (tcp 5762+10N), the true model file."""
    work = tmp_path_factory.mktemp("guided")
    model = work / "true.yaml"
    write_true_model(load_vehicle("fang-chen-buaa"), model)
    launched = ArduPilotProcess(ARDUPILOT, work / "ap", work / "truth.tlog", speedup=4.0)
    gcs = None
    try:
        gcs = ArduCopterLink(f"tcp:127.0.0.1:{TCP_BASE + 2 + 10 * launched.instance}", wall_timeout=60.0)
        gcs.wait_ekf_gps(sim_seconds=120.0)
        yield launched, gcs, work, model
    finally:
        if gcs is not None:
            gcs.close()
        launched.stop()


def fly(launched, work, model, out, duration=10.5) -> subprocess.CompletedProcess:
    """`quadsr fly --autopilot tcp:...` as a separate process, to its end."""
    return subprocess.run(
        [sys.executable, "-m", "quadsr.cli", "fly", "--model", str(model), "--trajectory", "case2",
         "--duration", str(duration), "--autopilot", launched.mavlink, "--truth", str(work / "truth.tlog"),
         "--out", str(out), "--no-progress"],
        cwd=REPO, capture_output=True, text=True, timeout=300)


@pytest.mark.e2e
def test_refused_arming_then_case2_through_guided(arducopter, tmp_path):
    launched, gcs, work, model = arducopter
    spin_arm = ardupilot_parameters(load_vehicle("fang-chen-buaa"))[0]["MOT_SPIN_ARM"]
    gcs.set_param("MOT_SPIN_ARM", 0.5)  # above MOT_SPIN_MIN: ArduCopter's pre-arm motor check fails
    gcs.fly_for(1.0)
    run = fly(launched, work, model, tmp_path / "refused")
    output = run.stdout + run.stderr
    assert run.returncode == 4, output
    assert "ArduPilot refused to arm in GUIDED" in output and "MOT_SPIN_ARM > MOT_SPIN_MIN" in output, output
    assert "Traceback" not in output

    gcs.set_param("MOT_SPIN_ARM", spin_arm)
    gcs.fly_for(1.0)
    run = fly(launched, work, model, tmp_path / "case2")
    output = run.stdout + run.stderr
    assert run.returncode == 0, output
    assert "through ArduPilot GUIDED" in output and "(truth)" in output
    assert_case2_tracked(tmp_path / "case2", settle_s=10.0, tolerance_m=0.15)


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--autopilot", "tcp:127.0.0.1:5760", "--autopilot-type", "inav"], "is not px4 or ardupilot"),
        (["--autopilot", "tcp:127.0.0.1"], "tcp:HOST:PORT"),
    ],
)
def test_fly_autopilot_refuses_bad_input_clearly(flags, message, tmp_path):
    model = tmp_path / "true.yaml"
    write_true_model(load_vehicle("fang-chen-buaa"), model)
    argv = [sys.executable, "-m", "quadsr.cli", "fly", "--model", str(model), "--trajectory", "case2",
            "--out", str(tmp_path / "o"), *flags]
    run = subprocess.run(argv, capture_output=True, text=True, cwd=REPO, timeout=60)
    assert run.returncode == 2 and message in run.stderr and "Traceback" not in run.stderr, run.stderr
