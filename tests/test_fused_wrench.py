"""The fused airframe wrench (sitl.fused_wrench, the SITL's fast path) equals the per-effect reference
(sitl.airframe_dynamics.airframe_wrench) at many random states, near the ground and in wind, for every effect
on and for each effect switched off."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from bridge.airframe import AeroConfig
from bridge.vehicle import DragConfig, load_vehicle
from sitl.airframe_dynamics import airframe_wrench
from sitl.dynamics import Quadrotor, make_derivative
from sitl.fused_wrench import fused_airframe_wrench

AERO = load_vehicle("fang-chen-aero")


def variants() -> dict[str, object]:
    """fang-chen-aero with every effect on, with each effect off in turn, and without a ground."""
    aero = AERO.aero
    no_drag = DragConfig(body_quadratic=(0.0, 0.0, 0.0), angular_damping=AERO.drag.angular_damping)
    return {
        "every effect": AERO,
        "free space": AERO.with_overrides(ground="none"),
        "no rotor drag": dataclasses.replace(AERO, aero=dataclasses.replace(aero, rotor_drag=None)),
        "no lift": dataclasses.replace(AERO, aero=dataclasses.replace(aero, translational_lift=0.0)),
        "no ground effect": dataclasses.replace(AERO, aero=dataclasses.replace(aero, ground_effect=None)),
        "no frame drag": dataclasses.replace(AERO, drag=no_drag,
                                             aero=dataclasses.replace(aero, frame_drag=(0.0, 0.0, 0.0))),
        "geometry only": dataclasses.replace(AERO, drag=no_drag, aero=AeroConfig()),
    }


def random_inputs(rng: np.random.Generator) -> tuple[list[float], list[float]]:
    """(wind NED m/s, the wrench's 20 arguments) at a random state: 0-5 m above the ground, any attitude."""
    q = rng.normal(size=4)
    qw, qx, qy, qz = q / np.linalg.norm(q)
    r = [1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy),
         2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx),
         2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)]
    z = -rng.uniform(0.0, 5.0)  # m NED: inside, at and beyond the ground effect's reach and its cap
    v = rng.normal(0.0, 6.0, 3)  # m/s NED
    rates = rng.normal(0.0, 2.0, 3)  # rad/s FRD
    speeds = rng.uniform(0.0, 1000.0, 4)  # rad/s
    wind = rng.normal(0.0, 5.0, 3)  # m/s NED
    return [float(x) for x in wind], [float(x) for x in (z, *v, *rates, *speeds, *r)]


@pytest.mark.parametrize("name", list(variants()))
def test_the_fused_wrench_equals_the_per_effect_reference(name):
    vehicle = variants()[name]
    wind = [0.0, 0.0, 0.0]
    fast, reference = fused_airframe_wrench(vehicle, wind), airframe_wrench(vehicle, wind)
    rng = np.random.default_rng(13)
    worst = 0.0
    for i in range(2000):
        w, args = random_inputs(rng)
        wind[:] = w if i % 4 else (0.0, 0.0, 0.0)  # in wind, and a quarter without
        got, want = fast(*args), reference(*args)
        assert len(got) == len(want) == 7
        for g, e in zip(got, want, strict=True):
            worst = max(worst, abs(g - e) / max(abs(e), 1e-3))
    assert worst <= 1e-12, f"{name}: largest relative difference {worst:.3g}"


def test_each_effect_changes_the_fused_wrench():
    # the equality above is not between two wrenches blind to an effect: switching one off changes the result
    rng = np.random.default_rng(4)
    wind, args = random_inputs(rng)
    args[0] = -0.1  # 10 cm up: in the ground effect
    every = fused_airframe_wrench(AERO, wind)(*args)
    for name, vehicle in variants().items():
        if name in ("every effect", "free space"):
            continue
        other = fused_airframe_wrench(vehicle, wind)(*args)
        assert max(abs(a - b) for a, b in zip(every, other, strict=True)) > 1e-3, name


def test_the_sitl_derivative_in_wind_equals_the_reference_derivative():
    vehicle = AERO.with_overrides(initial_position=(0.0, 0.0, -0.3))
    quad = Quadrotor(vehicle)
    wind = [4.0, -2.0, 0.5]
    fast = make_derivative(vehicle, quad.motors, quad.mixer, wind, compiled=False)
    reference = make_derivative(vehicle, quad.motors, quad.mixer, wind, reference=True)
    rng = np.random.default_rng(7)
    for _ in range(500):
        _, args = random_inputs(rng)
        quad.reset(position=(0.0, 0.0, args[0]), velocity=args[1:4], rates=args[4:7], rotor_speeds=args[7:11],
                   roll=rng.uniform(-1, 1), pitch=rng.uniform(-1, 1), yaw=rng.uniform(-math.pi, math.pi))
        s, cmd = list(quad.state), list(rng.uniform(0.0, 1000.0, 4))
        np.testing.assert_allclose(fast(s, cmd), reference(s, cmd), rtol=1e-12, atol=1e-12)
