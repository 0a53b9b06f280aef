"""bench/discovery.py's reference physics for a realistic-sensor case flown near the ground: splitting off the
ground law keeps the accelerometer's bias as a true constant of fx fy fz (it is in the measured specific
force), as the reference of the same case without a ground law has it."""

from __future__ import annotations

import pytest
import sympy
from bench_module import bench_module


def test_a_sensor_case_with_a_ground_law_keeps_the_accelerometer_bias_in_its_reference():
    bench = bench_module("discovery.py", "bench_discovery")
    loop = {"sitl_vehicle": "fang-chen-aero", "open_loop": False, "profiles": ("closed-loop", "closed-loop")}
    sensors = bench.Case("realistic", sensors="realistic", targets="sensors", **loop)
    ideal = bench.Case("ideal", **loop)
    rest, law = bench.height_law_reference(sensors)
    rest_ideal, law_ideal = bench.height_law_reference(ideal)
    vehicle = bench.flown_vehicle(sensors)
    bias = vehicle.with_overrides(sensors="realistic").sensors.effective().accel.bias  # m/s^2, FRD
    assert any(b != 0.0 for b in bias)
    for k, name in enumerate(("fx", "fy", "fz")):
        assert float(sympy.expand(rest[name] - rest_ideal[name])) == pytest.approx(bias[k], abs=1e-12)
    for name in ("dwx", "dwy", "dwz"):
        assert sympy.expand(rest[name] - rest_ideal[name]) == 0
    assert law == law_ideal and sympy.expand(law["fz"]) != 0  # the ground law itself is the same
