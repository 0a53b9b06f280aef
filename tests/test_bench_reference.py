"""bench/discovery.py's reference physics for a realistic-sensor case: the law of what the sensors measure.
The accelerometer's bias is a true constant of fx fy fz (it is in the measured specific force); the gyro's
bias is in none of the data: a flown realistic log's rate regressors are its true rates, not the gyro's,
and its angular-acceleration targets are the gyro's differences, where a constant bias cancels. Splitting
off the ground law keeps the constants beside it, as the reference of the same case without a law has
them."""

from __future__ import annotations

import numpy as np
import pytest
import sympy
from bench_module import bench_module
from conftest import SitlProcess, altitude_sitl_args
from physics_targets import physics_targets

from bridge.tlog import read_tlog
from identification.body_frame import PRIMITIVE_SYMBOLS
from identification.dataset import load_dataset
from identification.excite import fly
from identification.validate import expression_terms
from identification.weak_form import RAW_SENSOR_TARGETS

WX, WY, WZ = (PRIMITIVE_SYMBOLS[n] for n in ("wx", "wy", "wz"))


def test_a_sensor_case_reference_holds_the_accelerometers_bias_beside_a_ground_law():
    bench = bench_module("discovery.py", "bench_discovery")
    loop = {"sitl_vehicle": "fang-chen-aero", "open_loop": False, "profiles": ("closed-loop", "closed-loop")}
    sensors = bench.Case("realistic", sensors="realistic", targets="sensors", **loop)
    ideal = bench.Case("ideal", **loop)
    rest, law = bench.height_law_reference(sensors)
    rest_ideal, law_ideal = bench.height_law_reference(ideal)
    imu = bench.flown_vehicle(sensors).with_overrides(sensors="realistic").sensors.effective()
    accel, gyro = imu.accel.bias, imu.gyro.bias  # m/s^2 and rad/s, FRD
    assert all(b != 0.0 for b in gyro) and any(b != 0.0 for b in accel)
    for k, name in enumerate(("fx", "fy", "fz", "dwx", "dwy", "dwz")):
        offset = accel[k] if k < 3 else 0.0
        difference = expression_terms(rest[name] - rest_ideal[name])
        assert difference.pop(1, 0.0) == pytest.approx(offset, abs=1e-12)
        assert all(abs(c) < 1e-12 for c in difference.values()), (name, difference)  # float rounding only
    assert WZ not in expression_terms(rest["dwx"])  # no bare yaw rate from the gyro's pitch bias
    for name in law:
        assert sympy.expand(law[name] - law_ideal[name]) == 0, name
    assert sympy.expand(law["fz"]) != 0


@pytest.mark.timeout(120)
def test_a_realistic_logs_rates_are_its_true_ones_and_its_rate_targets_hold_no_gyro_bias(tmp_path):
    """What the reference rests on, flown: a 3 s paper-train flight of the realistic preset (gyro bias b_g
    and 0.01 rad/s noise per sample) read as the weak form reads it. The rows' rates are the log's true
    rates, not the gyro's (their mean offset from the gyro is -b_g), and the angular-acceleration targets
    scatter about the SITL's dynamics at those rates with no offset of the bias's size per step."""
    args = altitude_sitl_args(4)
    args[args.index("--sensors") + 1] = "realistic"
    sitl = SitlProcess(args)
    try:
        out = fly("paper-train", tmp_path / "train.tlog", hil=sitl.hil, duration=3.0, seed=6,
                  progress=False).out
    finally:
        sitl.stop()
    ds = load_dataset(out, targets="sensors", sensor_settings=RAW_SENSOR_TARGETS, gravity=9.8)
    truth, gyro = {}, {}
    for _, msg in read_tlog(out):
        kind = msg.get_type()
        if kind == "HIL_STATE_QUATERNION":
            truth[msg.time_usec] = (msg.rollspeed, msg.pitchspeed, msg.yawspeed)
        elif kind == "HIL_SENSOR":
            gyro[msg.time_usec] = (msg.xgyro, msg.ygyro, msg.zgyro)
    times = np.array(sorted(set(truth) & set(gyro)))
    at = {n: np.column_stack([np.interp(ds.t, times * 1e-6, np.array([d[t] for t in times])[:, k])
                              for k in range(3)]) for n, d in (("truth", truth), ("gyro", gyro))}
    rates = ds.xi[:, 9:12]
    bias = np.mean(np.array([gyro[t] for t in times]) - np.array([truth[t] for t in times]), axis=0)
    assert len(ds) > 600 and np.all(np.abs(bias) > 3e-4), bias  # the preset's bias, 0.5-1.5 mrad/s
    assert np.all(np.abs(np.mean(rates - at["truth"], axis=0)) < 0.1 * np.abs(bias))
    assert np.allclose(np.mean(rates - at["gyro"], axis=0), -bias, atol=0.2 * np.min(np.abs(bias)))
    # a step's gyro difference over dt: a constant bias cancels, and the mean over the flight's steps is the
    # gyro's change end to end over the time (its noise telescopes); a bias left in would be b_g / dt
    error = np.mean(ds.targets[:, 3:] - physics_targets(ds)[:, 3:], axis=0)  # rad/s^2
    assert np.all(np.abs(error) < 0.25 * np.min(np.abs(bias)) / 0.004), (error, bias / 0.004)


def test_a_truth_case_reference_is_the_vehicles_physics():
    bench = bench_module("discovery.py", "bench_discovery")
    case = bench.Case("ideal", sitl_vehicle="fang-chen-aero")
    vehicle = bench.flown_vehicle(case)
    body = {"fx": WX * WY, "dwx": WY * WZ + WZ}
    assert bench.sensor_reference(case, vehicle, body) == body
