"""The compiled state derivative (sitl._derivative) is the Python derivative, bit for bit: the same floats
(==) at many random states for every bundled vehicle and each effect off in turn, and the same flight."""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from bridge.vehicle import load_vehicle
from sitl import compiled_physics
from sitl.dynamics import Quadrotor, make_derivative
from tests.test_fused_wrench import random_inputs, variants

BENCH_VEHICLES = Path(__file__).resolve().parent.parent / "bench" / "vehicles"
# the bundled vehicles (the paper's closed form; every effect), and the discovery suite's (bench/vehicles)
BUNDLED = ("fang-chen-buaa", "fang-chen-aero", *sorted(str(p) for p in BENCH_VEHICLES.glob("*.yaml")))


def vehicles() -> dict[str, object]:
    """Bundled vehicles (the paper's closed form and the fused wrench), and fang-chen-aero's variants."""
    out = {Path(name).stem: load_vehicle(name) for name in BUNDLED}
    buaa = load_vehicle("fang-chen-buaa")
    out["fang-chen-buaa with body drag"] = dataclasses.replace(buaa, drag=dataclasses.replace(
        buaa.drag, body_quadratic=(0.1, 0.12, 0.3)))
    out.update({f"aero: {k}": v for k, v in variants().items()})
    return out


def test_the_extension_is_built_by_the_install():
    assert compiled_physics.available(), "pip install did not build sitl._derivative (a C compiler?)"


@pytest.mark.parametrize("name", list(vehicles()))
def test_the_compiled_derivative_is_bit_identical_to_the_python_one(name):
    vehicle = vehicles()[name]
    quad = Quadrotor(vehicle)
    wind = [0.0, 0.0, 0.0]
    fast = make_derivative(vehicle, quad.motors, quad.mixer, wind, compiled=True)
    python = make_derivative(vehicle, quad.motors, quad.mixer, wind, compiled=False)
    rng = np.random.default_rng(31)
    for i in range(600):
        w, args = random_inputs(rng)
        wind[:] = w if i % 3 else (0.0, 0.0, 0.0)
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        s = [0.0, 0.0, args[0], *args[1:4], *(float(x) for x in q), *args[4:7], *args[7:11]]
        cmd = tuple(float(x) for x in rng.uniform(0.0, 1000.0, 4))
        got, want = fast(s, cmd), python(s, cmd)
        assert len(got) == 17
        assert tuple(got) == tuple(want), f"{name}: state {i} differs"


def test_a_flight_is_the_same_with_either_derivative(monkeypatch):
    vehicle = load_vehicle("fang-chen-aero").with_overrides(initial_position=(0.0, 0.0, -0.5))
    quads = [Quadrotor(vehicle)]
    monkeypatch.setenv("QUADSR_PHYSICS", "python")
    assert not compiled_physics.available()
    quads.append(Quadrotor(vehicle))
    for k in range(1500):  # 6 s: take-off from the ground effect, a climb and a roll
        th = 0.62 + 0.05 * math.sin(k * 0.01)
        throttles = (th + 0.01 * math.sin(k * 0.03), th, th, th - 0.01 * math.sin(k * 0.03))
        for quad in quads:
            quad.step(throttles)
        assert quads[0].state == quads[1].state, f"step {k}"
        assert quads[0].specific_force_body() == quads[1].specific_force_body()
    assert quads[0].position[2] < -1.0  # it flew


@pytest.mark.parametrize(("args", "message"), [
    ((b"x" * 8, [0.0] * 3, [0.0] * 17, [0.0] * 4), "constants"),
    (("wind", [0.0] * 3, [0.0] * 17, [0.0] * 4), "constants"),
    (None, "state: expected 17"),
    ("wind", "wind: expected 3"),
    ("not a float", "must be real number"),
])
def test_bad_arguments_raise_instead_of_crashing(args, message):
    vehicle = load_vehicle("fang-chen-aero")
    quad = Quadrotor(vehicle)
    f = make_derivative(vehicle, quad.motors, quad.mixer, compiled=True)
    constants, wind = f.args
    if args is None:
        args = (constants, wind, [0.0] * 16, [0.0] * 4)
    elif args == "wind":
        args = (constants, [0.0] * 2, [0.0] * 17, [0.0] * 4)
    elif args == "not a float":
        args = (constants, wind, [0.0] * 16 + ["x"], [0.0] * 4)
    with pytest.raises((ValueError, TypeError), match=message):
        f.func(*args)


def test_the_python_derivative_is_chosen_by_the_environment():
    code = "from sitl import compiled_physics as c; print(c.available())"
    out = subprocess.run([sys.executable, "-c", code], env={"QUADSR_PHYSICS": "python", "PATH": ""},
                         capture_output=True, text=True, check=True, cwd=str(BENCH_VEHICLES.parent.parent))
    assert out.stdout.strip() == "False"


@pytest.mark.parametrize("physics", ["", "python"])
def test_the_sitl_says_when_its_physics_runs_in_python(physics):
    env = {**os.environ, "QUADSR_PHYSICS": physics}
    proc = subprocess.Popen([sys.executable, "-m", "quadsr.cli", "sitl", "--hil", "udp:127.0.0.1:0",
                             "--status-interval", "0"], stdout=subprocess.PIPE, text=True, env=env,
                            cwd=str(BENCH_VEHICLES.parent.parent))
    try:
        line = proc.stdout.readline()
    finally:
        proc.kill()
        proc.wait(timeout=10)
    assert "listening for the companion" in line
    assert ("physics in Python" in line) == (physics == "python"), line
