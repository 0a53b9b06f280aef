"""`quadsr ardupilot-params`: ArduCopter's thrust model with the written parameters matches the vehicle."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys

import pytest

from bridge.errors import UserError
from bridge.vehicle import load_vehicle
from sitl.ardupilot_params import ardupilot_parameters, thrust_expo_fit
from tests.conftest import REPO


def ardupilot_output(params: dict, demand: float) -> float:
    """ArduPilot's motor output (fraction of the PWM range) for a thrust demand in [0, 1]
    (AP_MotorsMulticopter: x solves demand = (1 - expo) x + expo x^2, then spin_min..spin_max)."""
    e = params["MOT_THST_EXPO"]
    x = demand if e == 0 else ((e - 1) + math.sqrt((1 - e) ** 2 + 4 * e * demand)) / (2 * e)
    return params["MOT_SPIN_MIN"] + (params["MOT_SPIN_MAX"] - params["MOT_SPIN_MIN"]) * x


def test_ardupilot_thrust_model_matches_the_vehicle():
    v = load_vehicle("fang-chen-buaa")
    params, _ = ardupilot_parameters(v)
    curve = v.motor_curve
    t_max = v.thrust_coefficient * curve.speed_for_throttle(params["MOT_SPIN_MAX"]) ** 2
    for demand in (0.2, 0.4, 0.6, 0.8, 1.0):
        w = curve.speed_for_throttle(ardupilot_output(params, demand))
        assert v.thrust_coefficient * w * w == pytest.approx(demand * t_max, rel=0.03), demand
    w_hover = curve.speed_for_throttle(ardupilot_output(params, params["MOT_THST_HOVER"]))
    assert w_hover == pytest.approx(v.hover_speed, rel=0.005)
    # the rotors turn at MOT_SPIN_ARM and MOT_SPIN_MIN, and not far below them
    arm, spin = (curve.speed_for_throttle(params[k]) for k in ("MOT_SPIN_ARM", "MOT_SPIN_MIN"))
    assert 0 < arm < spin
    assert curve.speed_for_throttle(params["MOT_SPIN_ARM"] - 0.03) == 0.0
    assert (params["FRAME_CLASS"], params["FRAME_TYPE"]) == (1, 1)
    assert (params["MOT_PWM_MIN"], params["MOT_PWM_MAX"]) == (1000, 2000)
    # ArduCopter's default logging plus ATTITUDE_FAST (bit 0) and IMU_FAST (bit 18): identification's rates
    assert params["LOG_BITMASK"] == 176126 | 1 | 1 << 18


def test_expo_fit_tracks_the_curve_shape():
    v = load_vehicle("fang-chen-buaa")
    # a curve through the origin (wb = 0) from throttle 0 gives thrust ~ x^2 exactly: expo 1
    pure = dataclasses.replace(v, motor=dataclasses.replace(v.motor, curve_offset=0.0))
    expo, rms = thrust_expo_fit(pure, 0.0, 1.0)
    assert expo == pytest.approx(1.0) and rms < 1e-9
    # starting well above the curve's zero, the thrust is part linear: expo < 1 (and the quadratic with no
    # constant term fits less well)
    expo, rms = thrust_expo_fit(v, 0.3, 0.95)
    assert 0.3 < expo < 0.9 and rms < 0.03


def test_vehicle_pwm_range_goes_to_the_parameters_and_is_checked(tmp_path):
    text = (REPO / "sitl" / "vehicles" / "fang-chen-buaa.yaml").read_text()
    ranged = tmp_path / "ranged.yaml"
    ranged.write_text(text.replace("  rotor_inertia:", "  pwm_min: 1100\n  pwm_max: 1900\n  rotor_inertia:"))
    params, _ = ardupilot_parameters(load_vehicle(ranged))
    assert (params["MOT_PWM_MIN"], params["MOT_PWM_MAX"]) == (1100, 1900)
    bad = tmp_path / "bad.yaml"
    bad.write_text(text.replace("  rotor_inertia:", "  pwm_min: 2000\n  pwm_max: 1000\n  rotor_inertia:"))
    with pytest.raises(UserError, match="motor.pwm_min"):
        load_vehicle(bad)


def test_cli_writes_a_parm_file_and_refuses_bad_input(tmp_path):
    out = tmp_path / "quad.parm"
    run = subprocess.run([sys.executable, "-m", "quadsr.cli", "ardupilot-params", "-o", str(out)],
                         capture_output=True, text=True, cwd=REPO, timeout=60)
    assert run.returncode == 0, run.stderr
    values = dict(line.split() for line in out.read_text().splitlines() if not line.startswith("#"))
    assert set(values) >= {"FRAME_CLASS", "FRAME_TYPE", "MOT_THST_EXPO", "MOT_THST_HOVER", "MOT_SPIN_ARM",
                           "MOT_SPIN_MIN", "MOT_PWM_MIN", "MOT_PWM_MAX", "BATT_MONITOR"}
    assert float(values["MOT_THST_HOVER"]) == pytest.approx(ardupilot_parameters(
        load_vehicle("fang-chen-buaa"))[0]["MOT_THST_HOVER"])
    run = subprocess.run([sys.executable, "-m", "quadsr.cli", "ardupilot-params", "--vehicle", "no-such",
                          "-o", str(out)], capture_output=True, text=True, cwd=REPO, timeout=60)
    assert run.returncode == 2 and "not found" in run.stderr and "Traceback" not in run.stderr
