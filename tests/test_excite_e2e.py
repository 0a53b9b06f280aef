"""End to end: `quadsr sitl` and `quadsr excite` as separate processes over real UDP; the .tlog each flight
leaves is read back with load_dataset and checked against the physics and the profile's limits."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from conftest import REPO, SitlProcess, altitude_sitl_args
from physics_targets import physics_targets, r2

from identification.dataset import load_dataset
from identification.excitation import load_profile
from identification.segmentation import SegmentationSettings

pytestmark = pytest.mark.e2e


def excite(*args: str, timeout: float = 120.0) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, "-m", "quadsr.cli", "excite", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        cwd=REPO,
    )


@pytest.fixture(scope="module")
def sitl_at_altitude():
    sitl = SitlProcess(altitude_sitl_args(7))
    yield sitl
    sitl.stop()


@pytest.fixture(scope="module")
def sitl_on_ground():
    sitl = SitlProcess(
        [
            "--hil",
            "udp:127.0.0.1:0",
            "--no-gcs",
            "--sensors",
            "ideal",
            "--seed",
            "8",
            "--status-interval",
            "0",
        ]
    )
    yield sitl
    sitl.stop()


def test_closed_loop_refuses_a_start_in_the_air(sitl_at_altitude, tmp_path):
    run = excite(
        "--profile",
        "closed-loop",
        "--hil",
        sitl_at_altitude.hil,
        "--out",
        str(tmp_path / "x.tlog"),
        "--no-progress",
    )
    assert run.returncode == 2 and "not resting on the ground" in run.stderr


def test_paper_profiles_fly_open_loop_from_altitude(sitl_at_altitude, tmp_path):
    train = tmp_path / "train.tlog"
    run = excite(
        "--profile",
        "paper-train",
        "--hil",
        sitl_at_altitude.hil,
        "--duration",
        "2",
        "--seed",
        "11",
        "--out",
        str(train),
    )
    assert run.returncode == 0, run.stderr
    assert "500 steps, 2.000 s simulated" in run.stdout and "final state" in run.stdout
    assert "excite paper-train" in run.stderr and "100%" in run.stderr  # the progress bar, on stderr
    ds = load_dataset(train)
    # the SITL's logged true accelerations: every step a row, none dropped (a SITL still waiting for its
    # client resends its time-0 datagram, which the log may hold once more: a duplicate, not a step)
    steps = {k: v for k, v in ds.drop_reasons.items() if not k.startswith("duplicate time-0 datagram")}
    assert len(ds) == 501 and not steps, ds.drop_reasons
    fit = r2(ds.targets, physics_targets(ds, "none"))
    assert (fit > 1 - 1e-9).all(), fit
    # the rotor speeds are the SITL's true (lagged) speeds, spread over the groups' ranges
    assert ds.u.max() > 800.0 and ds.u.min() < 50.0

    val = tmp_path / "val.tlog"
    run = excite(
        "--profile",
        "paper-validate",
        "--hil",
        sitl_at_altitude.hil,
        "--duration",
        "2",
        "--out",
        str(val),
        "--no-progress",
    )
    assert run.returncode == 0, run.stderr
    assert run.stderr == ""
    ds = load_dataset(val)
    assert (r2(ds.targets, physics_targets(ds, "none")) > 1 - 1e-9).all()
    # the true speeds are the paper's sinusoids through the motor lag (Tm = 0.02 s, command held per step),
    # as logged per step (one row per step from the flight's first: the logged accelerations need no stencil)
    assert np.allclose(np.diff(ds.t), 0.004)
    t = ds.t - ds.t[0]
    decay = math.exp(-0.004 / 0.02)
    for i, p in enumerate((0.0, math.pi / 4, math.pi / 3, math.pi / 6)):
        command = 300.0 + 300.0 * np.sin(10.0 * t + p)
        lagged = np.empty_like(command)
        lagged[0] = ds.u[0, i]
        for k in range(1, len(t)):
            lagged[k] = command[k - 1] + (lagged[k - 1] - command[k - 1]) * decay
        assert np.abs(ds.u[:, i] - lagged).max() < 0.5


def test_open_loop_profile_refuses_a_vehicle_on_the_ground(sitl_on_ground, tmp_path):
    run = excite(
        "--profile",
        "paper-validate",
        "--hil",
        sitl_on_ground.hil,
        "--out",
        str(tmp_path / "x.tlog"),
        "--no-progress",
    )
    assert run.returncode == 2
    assert (
        "not in the air above the ground" in run.stderr
        and "--ground none --initial-position 0,0,-200" in run.stderr
    )
    assert "Traceback" not in run.stderr
    assert not (tmp_path / "x.tlog").exists()  # nothing flown, no log left behind


def test_closed_loop_takes_off_and_holds_its_limits(sitl_on_ground, tmp_path):
    prof = load_profile("closed-loop")
    out = tmp_path / "closed.tlog"
    run = excite(
        "--profile",
        "closed-loop",
        "--hil",
        sitl_on_ground.hil,
        "--duration",
        "9",
        "--seed",
        "2",
        "--out",
        str(out),
        "--no-progress",
    )
    assert run.returncode == 0, run.stderr
    assert "excitation backed off" in run.stdout
    ds = load_dataset(out)
    assert ds.drop_reasons.get("resting on the ground", 0) > 0  # it started on the ground
    # the lift-off goes as in any log (segmentation's edge margin): within centimetres of the ground, below
    # where the SITL holds its ground-effect law, a few rows would own any law in 1/h
    everything = load_dataset(out, airborne=False)
    margin = SegmentationSettings().edge_margin_s
    assert (everything.aux["ground_s"] <= margin).sum() > 10
    assert ds.drop_reasons.get(f"within {margin:g} s of lift-off or touch-down", 0) > 10
    assert ds.aux["ground_s"].min() > margin
    fit = r2(ds.targets, physics_targets(ds, "plane"))
    assert (fit > 0.9999).all(), fit
    exciting = ds.t >= prof.excitation_start
    assert exciting.sum() > 1000
    x = ds.xi[exciting]
    assert np.abs(x[:, :2]).max() < prof.box_half_width
    lo, hi = prof.box_altitude
    assert lo < (-x[:, 2]).min() and (-x[:, 2]).max() < hi
    tilt = np.degrees(np.arccos(np.cos(ds.xi[:, 6]) * np.cos(ds.xi[:, 7])))
    assert tilt.max() < prof.tilt_limit
    # excited: each rotor's speed jumps by the PRBS amplitude (through the lag) well beyond the hover trim
    assert (np.std(ds.u[exciting], axis=0) > 30.0).all()


def test_user_mistakes_exit_2_without_a_traceback(tmp_path):
    for args, message in (
        (["--profile", "wobble"], "excitation profile 'wobble': not found"),
        (["--profile", "paper-train", "--duration", "-1"], "--duration must be a positive"),
        (["--profile", "closed-loop", "--duration", "3"], "leaves no excitation"),
        (
            ["--profile", "paper-train", "--vehicle", "no-such-vehicle"],
            "vehicle file no-such-vehicle: not found",
        ),
    ):
        run = excite(*args, "--out", str(tmp_path / "x.tlog"), "--hil", "udp:127.0.0.1:9", "--no-progress")
        assert run.returncode == 2, (args, run.stderr)
        assert message in run.stderr and "Traceback" not in run.stderr, run.stderr
