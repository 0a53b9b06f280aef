"""ArduCopter's motor outputs rebuilt at the loop rate from RATE's mixer inputs, with the mixer fitted on the
10 Hz RCOU (identification.readers.ardupilot_mixer), on outputs made as ArduCopter's mixer makes them."""

from __future__ import annotations

import numpy as np
import pytest

from identification.readers.ardupilot_mixer import (
    MIN_FIT_R2,
    actuator_of_thrust,
    fit_mixer,
    loop_rate_outputs,
    thrust_of_actuator,
)

PARAMS = {"MOT_SPIN_MIN": 0.173, "MOT_SPIN_MAX": 0.95, "MOT_THST_EXPO": 0.874}  # quadsr ardupilot-params'
# Quad-X mixer factors (roll, pitch, yaw) of motors 1..4 after ArduCopter's normalisation to 0.5
FACTORS = np.array([[-0.5, 0.5, 0.5], [0.5, -0.5, 0.5], [0.5, 0.5, -0.5], [-0.5, -0.5, -0.5]])


def flight(seconds: float = 30.0, loop_hz: float = 400.0, seed: int = 0):
    """RATE's times and inputs (AOut, ROut, POut, YOut) at the loop rate, the actuators they make (fraction of
    the PWM range) and the RCOU records of every 40th loop (10 Hz) as whole PWM microseconds."""
    rng = np.random.default_rng(seed)
    t = np.arange(0.0, seconds, 1.0 / loop_hz)
    throttle = 0.34 + 0.05 * np.sin(2 * np.pi * 0.3 * t)
    waves = ((1.7, 0.0), (2.3, 1.0), (0.9, 2.0))  # Hz, rad
    rpy = np.column_stack([0.08 * np.sin(2 * np.pi * f * t + p) for f, p in waves])
    rpy += 0.02 * rng.standard_normal(rpy.shape)  # the rate loops' fast content, which 10 Hz never sees
    thrust = throttle[:, None] + rpy @ FACTORS.T
    actuator = actuator_of_thrust(thrust, PARAMS)
    pick = np.arange(0, len(t), 40)
    rcou = np.round(1000.0 + 1000.0 * actuator[pick]) / 1000.0 - 1.0  # whole us, back to the fraction
    return t, np.column_stack((throttle, rpy)), actuator, t[pick] + 0.0005, rcou


def test_thrust_curve_round_trips():
    a = np.linspace(0.2, 0.9, 15)
    assert actuator_of_thrust(thrust_of_actuator(a, PARAMS), PARAMS) == pytest.approx(a, abs=1e-12)
    linear = {**PARAMS, "MOT_THST_EXPO": 0.0}
    assert actuator_of_thrust(np.array([0.5]), linear)[0] == pytest.approx(0.173 + 0.777 * 0.5)


def test_loop_rate_outputs_follow_the_mixer_from_ten_hertz_samples():
    t, inputs, actuator, rcou_t, rcou = flight()
    fit = fit_mixer(t, inputs, rcou_t, rcou, PARAMS)
    assert fit.usable and fit.samples == len(rcou_t) and min(fit.r2) > MIN_FIT_R2
    # the fitted maps are the mixer: throttle 1, the roll/pitch/yaw factors
    assert fit.coefficients[:, 1] == pytest.approx(1.0, abs=0.01)
    assert fit.coefficients[:, 2:] == pytest.approx(FACTORS, abs=0.01)
    now = np.column_stack([np.interp(t, rcou_t, rcou[:, j]) for j in range(4)])
    rebuilt = loop_rate_outputs(fit, t, inputs, now, PARAMS)
    assert np.max(np.abs(rebuilt - actuator)) < 2e-3  # PWM rounding to 1 us
    assert np.sqrt(np.mean((now - actuator) ** 2)) > 10 * np.sqrt(np.mean((rebuilt - actuator) ** 2))


def test_idle_motors_keep_rcou_and_a_wrong_mixer_is_refused():
    t, inputs, actuator, rcou_t, rcou = flight()
    fit = fit_mixer(t, inputs, rcou_t, rcou, PARAMS)
    idle = np.zeros((len(t), 4))  # RCOU says the motors are stopped (disarmed): no rebuilt output there
    assert np.all(loop_rate_outputs(fit, t, inputs, idle, PARAMS) == 0.0)
    # outputs that RATE's inputs do not explain (another aircraft's log, a mixer that is not linear there)
    shuffled = np.random.default_rng(1).permutation(rcou)
    bad = fit_mixer(t, inputs, rcou_t, shuffled, PARAMS)
    assert not bad.usable and "R^2" in bad.reason
    # too few unsaturated samples: all at MOT_SPIN_MAX
    full = np.full_like(rcou, PARAMS["MOT_SPIN_MAX"])
    none = fit_mixer(t, inputs, rcou_t, full, PARAMS)
    assert not none.usable and none.samples == 0 and "unsaturated" in none.reason
