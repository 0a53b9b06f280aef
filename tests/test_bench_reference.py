"""bench/discovery.py's reference physics for a realistic-sensor case flown near the ground: splitting off the
ground law keeps the accelerometer's bias as a true constant of fx fy fz (it is in the measured specific
force), as the reference of the same case without a ground law has it."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest
import sympy

REPO = Path(__file__).resolve().parent.parent


def _bench():
    """bench/discovery.py as a module (the one test_bench_baselines loaded, when it did)."""
    if "bench_discovery" in sys.modules:
        return sys.modules["bench_discovery"]
    spec = importlib.util.spec_from_file_location("bench_discovery", REPO / "bench" / "discovery.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_discovery"] = module  # its dataclasses look their module up there
    spec.loader.exec_module(module)
    return module


def test_a_sensor_case_with_a_ground_law_keeps_the_accelerometer_bias_in_its_reference():
    bench = _bench()
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
