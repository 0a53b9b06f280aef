"""The true model written from the vehicle file equals the SITL's numeric dynamics, term for term."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import sympy

from bridge.vehicle import DragConfig, load_vehicle
from identification.model_file import SYMBOLS, load_model
from identification.true_model import true_model, true_model_expressions, write_true_model
from sitl.dynamics import Quadrotor


def _random_states(rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
    xi = np.empty((n, 12))
    xi[:, 0:3] = rng.uniform(-50, 50, (n, 3))
    xi[:, 3:6] = rng.uniform(-15, 15, (n, 3))
    xi[:, 6] = rng.uniform(-np.pi, np.pi, n)
    xi[:, 7] = rng.uniform(-1.4, 1.4, n)
    xi[:, 8] = rng.uniform(-np.pi, np.pi, n)
    xi[:, 9:12] = rng.uniform(-8, 8, (n, 3))
    u = rng.uniform(0, 1000, (n, 4))
    return xi, u


def _sitl_accelerations(vehicle, xi: np.ndarray, u: np.ndarray) -> np.ndarray:
    quad = Quadrotor(vehicle)
    out = np.empty((len(xi), 6))
    for i, (s, w) in enumerate(zip(xi, u, strict=True)):
        quad.reset(
            position=s[0:3], yaw=s[8], rotor_speeds=w, velocity=s[3:6], rates=s[9:12], roll=s[6], pitch=s[7]
        )
        out[i, :3] = quad.acceleration_earth()
        out[i, 3:] = quad.angular_acceleration()
    return out


def _check(vehicle, tmp_path, seed: int) -> None:
    rng = np.random.default_rng(seed)
    xi, u = _random_states(rng, 300)
    expected = _sitl_accelerations(vehicle, xi, u)
    model = load_model(write_true_model(vehicle, tmp_path / "true.yaml"))
    got = model.accelerations(xi, u)
    scale = np.maximum(np.abs(expected), 1e-3 * np.abs(expected).max(axis=0))
    assert np.max(np.abs(got - expected) / scale) < 1e-9
    for i in range(0, 300, 37):  # the scalar path agrees too
        np.testing.assert_allclose(model.accelerations(xi[i], u[i]), got[i], rtol=1e-12, atol=1e-12)


def test_true_model_matches_sitl_dynamics_at_random_states(tmp_path):
    vehicle = load_vehicle("fang-chen-buaa").with_overrides(ground="none")
    _check(vehicle, tmp_path, seed=1)


def test_true_model_matches_sitl_with_full_inertia_and_per_axis_drag(tmp_path):
    base = load_vehicle("fang-chen-buaa").with_overrides(ground="none")
    inertia = ((0.03, 0.002, -0.001), (0.002, 0.04, 0.003), (-0.001, 0.003, 0.05))
    vehicle = dataclasses.replace(
        base,
        inertia=inertia,
        drag=DragConfig(body_quadratic=(0.05, 0.07, 0.2), angular_damping=(1e-3, 2e-3, 0.0)),
    )
    _check(vehicle, tmp_path, seed=2)


def test_gyroscopic_signs_are_eulers_not_the_papers():
    vehicle = load_vehicle("fang-chen-buaa")
    exprs = true_model_expressions(vehicle)
    wx, wy, wz = SYMBOLS["wx"], SYMBOLS["wy"], SYMBOLS["wz"]
    coeff = {n: sympy.expand(e).as_coefficients_dict() for n, e in exprs.items()}
    assert coeff["dwx"][wy * wz] == pytest.approx((0.0219 - 0.0366) / 0.0211)  # -0.697
    assert coeff["dwy"][wx * wz] == pytest.approx((0.0366 - 0.0211) / 0.0219)  # +0.708
    assert coeff["dwz"][wx * wy] == pytest.approx((0.0211 - 0.0219) / 0.0366)  # -0.0219
    u2 = SYMBOLS["u2"]
    assert coeff["dwx"][u2**2] == pytest.approx(np.sqrt(2) / 2 * 0.225 * 1.105e-5 / 0.0211)  # 8.33e-5 f2
    assert coeff["az"][sympy.Integer(1)] == pytest.approx(9.8)


def test_true_model_file_is_kind_true_model_with_vehicle_hash(tmp_path):
    path = write_true_model("fang-chen-buaa", tmp_path / "m.yaml")
    model = load_model(path)
    assert model.kind == "true-model"
    assert model.vehicle["name"] == "fang-chen-buaa" and len(model.vehicle["sha256"]) == 64
    assert model.target_names == ("ax", "ay", "az", "dwx", "dwy", "dwz")
    hover = load_vehicle("fang-chen-buaa").hover_speed
    a = true_model("fang-chen-buaa").accelerations(np.zeros(12), np.full(4, hover))
    np.testing.assert_allclose(a, np.zeros(6), atol=1e-9)
