"""bench/discovery.py's reference physics for a realistic-sensor case: the law of what the sensors measure.
The accelerometer's bias is a true constant of fx fy fz (it is in the measured specific force), and the
rates a model reads are the gyro's, w + b_g, so the physics holds w - b_g: the inertia coupling c wy wz of
wx' brings a bare -c b_gy wz into the data. Splitting off the ground law keeps both, as the reference of
the same case without a ground law has them."""

from __future__ import annotations

import pytest
import sympy
from bench_module import bench_module

from identification.body_frame import PRIMITIVE_SYMBOLS
from identification.validate import expression_terms

WX, WY, WZ = (PRIMITIVE_SYMBOLS[n] for n in ("wx", "wy", "wz"))


def test_a_sensor_case_reference_holds_the_imu_biases_and_keeps_them_beside_a_ground_law():
    bench = bench_module("discovery.py", "bench_discovery")
    loop = {"sitl_vehicle": "fang-chen-aero", "open_loop": False, "profiles": ("closed-loop", "closed-loop")}
    sensors = bench.Case("realistic", sensors="realistic", targets="sensors", **loop)
    ideal = bench.Case("ideal", **loop)
    rest, law = bench.height_law_reference(sensors)
    rest_ideal, law_ideal = bench.height_law_reference(ideal)
    imu = bench.flown_vehicle(sensors).with_overrides(sensors="realistic").sensors.effective()
    accel, gyro = imu.accel.bias, imu.gyro.bias  # m/s^2 and rad/s, FRD
    assert all(b != 0.0 for b in gyro) and any(b != 0.0 for b in accel)
    back = {WX: WX + gyro[0], WY: WY + gyro[1], WZ: WZ + gyro[2]}  # measured rates -> the physics' rates
    for k, name in enumerate(("fx", "fy", "fz", "dwx", "dwy", "dwz")):
        offset = accel[k] if k < 3 else 0.0
        difference = expression_terms(rest[name].xreplace(back) - rest_ideal[name])
        assert difference.pop(1, 0.0) == pytest.approx(offset, abs=1e-12)
        assert all(abs(c) < 1e-12 for c in difference.values()), (name, difference)  # float rounding only
    # wx''s bare yaw rate: the coupling's share of the gyro's pitch bias, no such term in the ideal physics
    ideal_terms, terms = expression_terms(rest_ideal["dwx"]), expression_terms(rest["dwx"])
    assert WZ not in ideal_terms and ideal_terms[WY * WZ] < 0.0
    assert terms[WZ] == pytest.approx(-ideal_terms[WY * WZ] * gyro[1], rel=1e-9)
    for name in law:
        difference = sympy.expand(law[name].xreplace(back) - law_ideal[name])
        assert all(abs(float(c)) < 1e-12 for c in difference.as_coefficients_dict().values()), name
    assert sympy.expand(law["fz"]) != 0


def test_a_truth_case_reference_is_the_vehicles_physics():
    bench = bench_module("discovery.py", "bench_discovery")
    case = bench.Case("ideal", sitl_vehicle="fang-chen-aero")
    vehicle = bench.flown_vehicle(case)
    body = {"fx": WX * WY, "dwx": WY * WZ + WZ}
    assert bench.sensor_reference(case, vehicle, body) == body
