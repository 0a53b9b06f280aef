"""Each effect of the SITL against an independent calculation (numpy, written from the formulas), and the true
model against the SITL's derivative with every effect on."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from bridge.airframe import (
    AeroConfig,
    GroundEffectConfig,
    RotorConfig,
    RotorDragConfig,
    allocation_matrix,
    quad_x_rotors,
)
from bridge.integration import rk4_step
from bridge.vehicle import DragConfig, MotorConfig, MotorCurve, load_vehicle
from identification.true_model import random_states, true_model
from sitl.dynamics import Quadrotor

BASE = load_vehicle("fang-chen-buaa").with_overrides(ground="none", initial_position=(0.0, 0.0, -50.0))
NO_DRAG = DragConfig(body_quadratic=(0.0, 0.0, 0.0), angular_damping=(0.0, 0.0, 0.0))
ARMS = np.array([r.position for r in quad_x_rotors(BASE.arm_length, 1.0, 1.0)])
J = np.diag([row[i] for i, row in enumerate(BASE.inertia)])
SPEEDS = np.array([520.0, 560.0, 610.0, 480.0])
VEL = np.array([3.0, -2.0, 1.0])  # NED m/s
RATES = np.array([0.4, -0.7, 0.9])  # FRD rad/s


def vehicle(**changes) -> object:
    """The paper's vehicle without its drag terms, with these fields changed (an effect switched on)."""
    return dataclasses.replace(BASE, drag=NO_DRAG, **changes)


def accelerations(v, position=(0.0, 0.0, -50.0), roll=0.0, pitch=0.0, yaw=0.0, velocity=VEL, rates=RATES,
                  speeds=SPEEDS) -> tuple[np.ndarray, np.ndarray]:
    """(linear acceleration NED, angular acceleration FRD) of the SITL at a state."""
    quad = Quadrotor(v)
    quad.reset(position=position, yaw=yaw, rotor_speeds=speeds, velocity=velocity, rates=rates, roll=roll,
               pitch=pitch)
    return np.array(quad.acceleration_earth()), np.array(quad.angular_acceleration())


def rotation(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """Body FRD -> NED, ZYX Euler angles (rad)."""
    cr, sr, cp, sp, cy, sy = (math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw),
                              math.sin(yaw))
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    return rz @ ry @ rx


def test_rotor_drag_force_and_moment_from_the_formula():
    kd, kz = 2.4e-4, 4.6e-4
    angles = (0.3, -0.2, 0.7)
    on = vehicle(aero=AeroConfig(rotor_drag=RotorDragConfig(kd, kz)))
    a_on, dw_on = accelerations(on, roll=angles[0], pitch=angles[1], yaw=angles[2])
    a_off, dw_off = accelerations(vehicle(), roll=angles[0], pitch=angles[1], yaw=angles[2])
    r = rotation(*angles)
    va = r.T @ VEL
    force = np.zeros(3)
    moment = np.zeros(3)
    for arm, w in zip(ARMS, SPEEDS, strict=True):
        f_i = -w * np.diag([kd, kd, kz]) @ (va + np.cross(RATES, arm))
        force += f_i
        moment += np.cross(arm, f_i)
    np.testing.assert_allclose(a_on - a_off, r @ force / BASE.mass, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(dw_on - dw_off, np.linalg.solve(J, moment), rtol=1e-9, atol=1e-12)
    assert np.linalg.norm(force) > 0.5  # a real force at these speeds (N), not a vanishing one


def test_translational_lift_adds_kh_times_in_plane_airspeed_squared():
    kh = 6.9e-3
    a_on, dw_on = accelerations(vehicle(aero=AeroConfig(translational_lift=kh)))
    a_off, dw_off = accelerations(vehicle())
    va = VEL  # level, yaw 0: body = NED axes
    extra = np.array([kh * ((va + np.cross(RATES, arm))[:2] ** 2).sum() for arm in ARMS])
    np.testing.assert_allclose(a_on - a_off, [0.0, 0.0, -extra.sum() / BASE.mass], rtol=1e-9, atol=1e-12)
    moment = sum(np.cross(arm, [0.0, 0.0, -t]) for arm, t in zip(ARMS, extra, strict=True))
    np.testing.assert_allclose(dw_on - dw_off, np.linalg.solve(J, moment), rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("height_over_radius,expected",
                         [(1.0, 16.0 / 15.0), (400.0, 1.0 / (1.0 - 1.0 / 1600**2)), (0.1, 4.0 / 3.0)])
def test_ground_effect_ratio_at_one_radius_far_away_and_capped(height_over_radius, expected):
    radius = 0.127
    ge = GroundEffectConfig(rotor_radius=radius, min_height=radius / 2)  # capped below R/2: 1/(1 - 1/4)
    h = height_over_radius * radius
    rest = dict(velocity=(0.0, 0.0, 0.0), rates=(0.0, 0.0, 0.0), position=(0.0, 0.0, -h))
    on = vehicle(aero=AeroConfig(ground_effect=ge)).with_overrides(ground="plane")
    a_on, _ = accelerations(on, **rest)
    a_off, _ = accelerations(vehicle().with_overrides(ground="plane"), **rest)
    thrust = BASE.thrust_coefficient * (SPEEDS**2).sum() / BASE.mass
    assert (a_on[2] - BASE.gravity) / -thrust == pytest.approx(expected, rel=1e-12)
    assert (a_off[2] - BASE.gravity) / -thrust == pytest.approx(1.0, rel=1e-12)


def test_ground_effect_needs_a_ground():
    ge = GroundEffectConfig(rotor_radius=0.127, min_height=0.0635)
    rest = dict(velocity=(0.0, 0.0, 0.0), rates=(0.0, 0.0, 0.0), position=(0.0, 0.0, -0.127))
    a_free, _ = accelerations(vehicle(aero=AeroConfig(ground_effect=ge)), **rest)  # ground: none
    a_off, _ = accelerations(vehicle(), **rest)
    assert a_free[2] == a_off[2]


def test_frame_drag_is_minus_speed_times_c_times_airspeed():
    c = (8.8e-3, 1.1e-2, 1.75e-2)
    a_on, dw_on = accelerations(vehicle(aero=AeroConfig(frame_drag=c)), yaw=0.5)
    a_off, dw_off = accelerations(vehicle(), yaw=0.5)
    r = rotation(0.0, 0.0, 0.5)
    va = r.T @ VEL
    force = -np.linalg.norm(va) * np.array(c) * va
    np.testing.assert_allclose(a_on - a_off, r @ force / BASE.mass, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(dw_on, dw_off, rtol=1e-12)  # no moment (the paper path rounds differently)


def test_a_weak_rotor_gives_the_roll_and_pitch_torque_statics_predicts():
    rotors = list(quad_x_rotors(BASE.arm_length, BASE.thrust_coefficient, BASE.moment_coefficient))
    weak = 0.92 * BASE.thrust_coefficient  # 8 % weaker
    rotors[0] = dataclasses.replace(rotors[0], thrust_coefficient=weak)
    equal = np.full(4, 560.0)
    still = dict(velocity=(0.0, 0.0, 0.0), rates=(0.0, 0.0, 0.0), speeds=equal)
    a, dw = accelerations(vehicle(rotors=tuple(rotors)), **still)
    missing = 0.08 * BASE.thrust_coefficient * 560.0**2  # N, rotor 1 (front-right) falls short by this
    x, y, _ = ARMS[0]
    torque = np.array([y * missing, -x * missing, 0.0])  # r x (0, 0, +missing): the lost upward push
    np.testing.assert_allclose(dw, np.linalg.solve(J, torque), rtol=1e-9)
    assert dw[0] > 0.0 and dw[1] < 0.0  # rolls right, pitches down toward the weak front-right rotor
    thrust = BASE.thrust_coefficient * 4 * 560.0**2 - missing
    assert a[2] == pytest.approx(BASE.gravity - thrust / BASE.mass, rel=1e-12)


def test_a_cg_offset_makes_the_hover_speeds_unequal_as_statics_predicts():
    cg = (-0.02, 0.01, 0.0)  # m FRD: 2 cm aft, 1 cm right
    v = vehicle(center_of_gravity=cg)
    # statics: A w^2 = (m g, 0, 0, 0) with A the allocation about the CG
    a_mat = allocation_matrix(v.rotor_set, cg)
    w = np.sqrt(np.linalg.solve(a_mat, [v.mass * v.gravity, 0.0, 0.0, 0.0]))
    acc, dw = accelerations(v, velocity=(0.0, 0.0, 0.0), rates=(0.0, 0.0, 0.0), speeds=w)
    np.testing.assert_allclose(np.concatenate([acc, dw]), 0.0, atol=1e-9)
    # the rear rotors (2, 4) carry more of an aft CG, the right ones (1, 4) more of a CG to the right
    assert w[1] > w[0] and w[3] > w[2] and w[3] > w[1] and w[0] > w[2]
    assert w.max() / w.min() > 1.05
    equal = np.full(4, v.hover_speed)
    _, dw_equal = accelerations(v, velocity=(0.0, 0.0, 0.0), rates=(0.0, 0.0, 0.0), speeds=equal)
    assert abs(dw_equal[1]) > 1.0  # equal speeds pitch the vehicle (rad/s^2)


def test_default_geometry_through_the_effects_path_matches_the_paper_path():
    # The Quad-X listed explicitly takes sitl.airframe_dynamics; the paper's vehicle the closed form.
    explicit = dataclasses.replace(BASE, rotors=BASE.rotor_set)
    assert BASE.paper_physics and not explicit.paper_physics
    for angles in ((0.0, 0.0, 0.0), (0.3, -0.5, 2.0)):
        a1, w1 = accelerations(BASE, roll=angles[0], pitch=angles[1], yaw=angles[2])
        a2, w2 = accelerations(explicit, roll=angles[0], pitch=angles[1], yaw=angles[2])
        np.testing.assert_allclose(a2, a1, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(w2, w1, rtol=1e-12, atol=1e-12)


@pytest.mark.parametrize("ground", ["none", "plane"])
def test_true_model_matches_the_sitl_with_every_effect_on(ground):
    aero = load_vehicle("fang-chen-aero").with_overrides(ground=ground)
    xi, u = random_states(200, seed=5)
    rng = np.random.default_rng(6)
    xi[:, 2] = rng.uniform(-1.5, -0.01, len(xi))  # near the ground: the ground effect and its cap
    quad = Quadrotor(aero)
    expected = np.empty((len(xi), 6))
    for i, (s, w) in enumerate(zip(xi, u, strict=True)):
        quad.reset(position=s[0:3], yaw=s[8], rotor_speeds=w, velocity=s[3:6], rates=s[9:12], roll=s[6],
                   pitch=s[7])
        expected[i, :3] = quad.acceleration_earth()
        expected[i, 3:] = quad.angular_acceleration()
    got = true_model(aero).accelerations(xi, u)
    scale = np.maximum(np.abs(expected), 1e-3 * np.abs(expected).max(axis=0))
    assert np.max(np.abs(got - expected) / scale) < 1e-9


def test_true_model_of_a_vehicle_with_every_effect_differs_from_the_paper_model():
    xi, u = random_states(50, seed=8)
    xi[:, 2] = -0.1
    aero = true_model("fang-chen-aero").accelerations(xi, u)
    plain = true_model("fang-chen-buaa").accelerations(xi, u)
    spread = plain.std(axis=0)
    assert (np.abs(aero - plain).mean(axis=0) > 0.01 * spread).all()  # every target feels the effects


def test_thrust_models_px4_and_polynomial_and_their_inverses():
    px4 = MotorCurve(kind="px4", full_speed=1000.0, thr_mdl_fac=0.3)
    for s in (0.0, 0.1, 0.37, 0.8, 1.0):
        assert px4.speed_for_throttle(s) == pytest.approx(1000.0 * math.sqrt(0.7 * s + 0.3 * s * s), abs=1e-9)
        assert px4.throttle_for_speed(px4.speed_for_throttle(s)) == pytest.approx(s, abs=1e-12)
    poly = MotorCurve(kind="polynomial", coefficients=(-50.0, 900.0, 150.0))
    assert poly.max_speed == 1000.0
    for s in (0.1, 0.5, 0.9):
        assert poly.speed_for_throttle(s) == pytest.approx(-50.0 + 900.0 * s + 150.0 * s * s)
        assert poly.throttle_for_speed(poly.speed_for_throttle(s)) == pytest.approx(s, abs=1e-12)
    assert poly.speed_for_throttle(0.0) == 0.0  # clipped at 0 rad/s


def test_the_sitl_uses_the_px4_thrust_model_and_a_seeded_motor_speed_noise():
    curve = MotorCurve(kind="px4", full_speed=1000.0, thr_mdl_fac=0.3)
    motor = dataclasses.replace(BASE.motor, curve=curve, speed_noise=5.0)
    v = vehicle(motor=motor)
    commands = []
    for _ in range(2):
        quad = Quadrotor(v)
        commands.append([quad.motors.commanded_speeds((0.5, 0.5, 0.5, 0.5)) for _ in range(2000)])
    c = np.array(commands)
    np.testing.assert_array_equal(c[0], c[1])  # same seed, same noise
    assert c[0].mean() == pytest.approx(curve.speed_for_throttle(0.5), abs=0.3)
    assert c[0].std() == pytest.approx(5.0, rel=0.1)
    other = dataclasses.replace(v, simulation=dataclasses.replace(v.simulation, seed=1))
    assert not np.array_equal(Quadrotor(other).motors.commanded_speeds((0.5,) * 4), c[0][0])


def test_the_one_rk4_is_fourth_order():
    # dy/dt = -y: one step of h has error ~ h^5/120; halving h divides the error by ~32
    errors = []
    for h in (0.1, 0.05):
        y = rk4_step(lambda s, u: [-s[0]], [1.0], [], h)[0]
        errors.append(abs(y - math.exp(-h)))
    assert errors[0] / errors[1] == pytest.approx(32.0, rel=0.05)


def test_motor_config_defaults_keep_the_linear_curve():
    m = MotorConfig(time_constant=0.02, curve_slope=1148.0, curve_offset=-141.4, rotor_inertia=1e-4)
    assert m.curve is None and m.speed_noise == 0.0
    assert BASE.motor_curve.kind == "linear" and BASE.motor_curve.max_speed == pytest.approx(1006.6)


def test_rotor_config_spin():
    assert RotorConfig((0.0, 0.0, 0.0), "ccw", 1.0, 1.0).spin_z == -1.0
    assert RotorConfig((0.0, 0.0, 0.0), "cw", 1.0, 1.0).spin_z == 1.0
