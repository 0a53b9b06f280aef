"""The gravity a log's data hold (identification.log_gravity): found from the accelerations and the
accelerometer, bias apart; reported only when it differs from the one assumed; a real SITL flight of a
9.8 m/s^2 vehicle identified with the default 9.80665 says so, and with 9.8 does not."""

from __future__ import annotations

import numpy as np
import pytest
from conftest import SitlProcess, altitude_sitl_args

from bridge.rotations import rotation_matrix
from bridge.vehicle import load_vehicle
from identification.dataset import load_dataset
from identification.excite import fly
from identification.identify import identify
from identification.log_gravity import gravity_note, log_gravity
from identification.targets import STANDARD_GRAVITY


def _flight(g: float, bias: tuple[float, float, float], tilts: bool, seed: int = 0):
    """(t, vel NED, euler, accel FRD, usable) of a smooth 20 s flight at 250 Hz with gravity g (m/s^2)."""
    rng = np.random.default_rng(seed)
    t = np.arange(5000) * 0.004
    w = rng.uniform(0.5, 2.0, (6, 1))  # rad/s
    phase = rng.uniform(0, 6, (3, 1))
    vel = 0.8 * np.sin(w[:3] * t + phase).T  # m/s
    acc = 0.8 * (w[:3] * np.cos(w[:3] * t + phase)).T  # dv/dt, m/s^2
    euler = (0.4 if tilts else 0.0) * np.sin(w[3:] * t).T
    R = rotation_matrix(euler[:, 0], euler[:, 1], euler[:, 2])
    f = np.einsum("nji,nj->ni", R, acc - np.array([0.0, 0.0, g]))  # R^T (a - g e_z), FRD
    return t, vel, euler, f + np.asarray(bias), np.ones(len(t), bool)


def test_the_gravity_is_found_beside_an_accelerometer_bias():
    g, se = log_gravity(*_flight(9.8, (0.05, -0.03, 0.08), tilts=True))
    assert abs(g - 9.8) < 1e-4 and se < 1e-3, (g, se)
    note = gravity_note((g, se), STANDARD_GRAVITY)
    assert note is not None and "--gravity 9.800" in note
    assert gravity_note((g, se), 9.8) is None


def test_a_level_flight_cannot_tell_gravity_from_the_bias_and_says_nothing():
    # no tilt: the bias's z part and g are one column, so the error is large or the fit is arbitrary; either
    # way no warning claims a gravity the log does not pin down
    estimate = log_gravity(*_flight(9.8, (0.0, 0.0, 0.3), tilts=False))
    assert estimate is None or gravity_note(estimate, STANDARD_GRAVITY) is None, estimate


def test_too_few_rows_give_no_estimate():
    t, vel, euler, acc, usable = _flight(9.8, (0.0, 0.0, 0.0), tilts=True)
    assert log_gravity(t[:30], vel[:30], euler[:30], acc[:30], usable[:30]) is None


@pytest.fixture(scope="module")
def flight(tmp_path_factory):
    """A 4 s paper-train flight of the default vehicle (g 9.8 m/s^2) at 200 m, ideal sensors."""
    d = tmp_path_factory.mktemp("gravity")
    sitl = SitlProcess(altitude_sitl_args(3))
    try:
        return fly("paper-train", d / "train.tlog", hil=sitl.hil, duration=4.0, seed=1, progress=False).out
    finally:
        sitl.stop()


def test_a_sitl_flight_identified_with_another_gravity_says_which_it_holds(flight, capsys):
    assert load_vehicle("fang-chen-buaa").gravity == 9.8
    ds = load_dataset(flight)
    assert len(ds.gravity_estimates) == 1
    file, g, se = ds.gravity_estimates[0]
    assert file == str(flight) and abs(g - 9.8) < 1e-3 and se < 1e-3, ds.gravity_estimates
    # sensor targets add back the g that body-frame learning removes: nothing to check
    assert load_dataset(flight, targets="sensors").gravity_estimates == []
    # identify with the default g says so, and which g to pass; with the vehicle's g it is silent
    for gravity, warned in ((STANDARD_GRAVITY, True), (9.8, False)):
        identify(ds, targets=("az",), budget=1, progress=False, gravity=gravity)
        lines = [x for x in capsys.readouterr().err.splitlines() if "agree on g" in x]
        assert len(lines) == int(warned), lines
        if warned:
            assert lines[0].startswith(f"warning: {flight}: ")
            assert abs(float(lines[0].split("--gravity ")[1].split()[0]) - 9.8) < 1e-3, lines
