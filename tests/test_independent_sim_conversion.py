"""bench/independent_sim.py's conversion of RotorPy's conventions (world z-up, body FLU, scalar-last
quaternion, its rotor order) to quadsr's (NED, FRD, scalar first, PX4 Quad-X order), on hand-made samples
with known answers; and RotorPy's physics written out in quadsr's primitives. Needs no rotorpy."""

from __future__ import annotations

import numpy as np
import pytest
import sympy
from bench_module import bench_module
from scipy.spatial.transform import Rotation

from bridge.rotations import euler_from_quaternions, rotation_matrix
from identification.body_frame import PRIMITIVE_SYMBOLS, body_targets, primitive_matrix
from identification.model_file import TARGET_NAMES

sim = bench_module("independent_sim.py", "independent_sim")

# RotorPy 3.0.0's Hummingbird parameters (rotorpy/vehicles/hummingbird_params.py), written here so the
# test needs no rotorpy
D = 0.17 * np.sqrt(0.5)
HUMMINGBIRD = {
    "mass": 0.5, "Ixx": 3.65e-3, "Iyy": 3.68e-3, "Izz": 7.03e-3, "Ixy": 0.0, "Iyz": 0.0, "Ixz": 0.0,
    "rotor_pos": {"r1": np.array([D, D, 0]), "r2": np.array([D, -D, 0]), "r3": np.array([-D, -D, 0]),
                  "r4": np.array([-D, D, 0])},
    "rotor_directions": np.array([1, -1, 1, -1]),
    "c_Dx": 0.5e-2, "c_Dy": 0.5e-2, "c_Dz": 1e-2, "k_eta": 5.57e-06, "k_m": 1.36e-07, "k_d": 1.19e-04,
    "k_z": 2.32e-04, "k_h": 3.39e-3,
}


def convert(q_xyzw, v=(0.0, 0.0, 0.0), w=(0.0, 0.0, 0.0), rotors=(1.0, 2.0, 3.0, 4.0), vdot=(0.0, 0.0, 0.0)):
    """One RotorPy sample through the conversion."""
    one = np.zeros((1, 3))
    return sim.to_ned_frd(one, np.array([v]), np.array([q_xyzw], dtype=float), np.array([w]),
                          np.array([rotors]), np.array([vdot]), one)


def euler(cols) -> np.ndarray:
    return euler_from_quaternions(np.column_stack([cols[c] for c in ("qw", "qx", "qy", "qz")]))[0]


def test_heading_roll_and_pitch_of_hand_made_attitudes():
    """Nose to world +y (z-up yaw +90 deg) is heading -90 deg in NED; FLU roll +a (left side up) is FRD roll
    +a; FLU pitch +b about the left axis (nose down) is FRD pitch -b."""
    yaw = convert([0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)])
    assert euler(yaw) == pytest.approx([0.0, 0.0, -np.pi / 2], abs=1e-12)
    roll = convert([np.sin(0.15), 0, 0, np.cos(0.15)])
    assert euler(roll) == pytest.approx([0.3, 0.0, 0.0], abs=1e-12)
    pitch = convert([0, np.sin(0.1), 0, np.cos(0.1)])
    assert euler(pitch) == pytest.approx([0.0, -0.2, 0.0], abs=1e-12)
    assert pitch["qw"][0] > 0  # scalar first, non-negative


def test_flying_nose_first_is_forward_body_velocity_and_climbing_is_negative_z():
    """Nose to world +y, flying to world +y and climbing at 2 m/s: ub = +1 m/s, vz = wb = -2 m/s (down)."""
    cols = convert([0, 0, np.sin(np.pi / 4), np.cos(np.pi / 4)], v=(0.0, 1.0, 2.0))
    assert (cols["vx"][0], cols["vy"][0], cols["vz"][0]) == pytest.approx((0.0, -1.0, -2.0))
    X = np.array([[0, 0, 0, cols["vx"][0], cols["vy"][0], cols["vz"][0], *euler(cols), 0, 0, 0, 1, 1, 1, 1]])
    assert primitive_matrix(X, ("ub", "vb", "wb"))[0] == pytest.approx([1.0, 0.0, -2.0], abs=1e-12)


def test_quaternion_is_the_flipped_rotation_for_random_attitudes():
    """R_NED<-FRD = T R_world<-FLU T with T = diag(1, -1, -1), for 50 random attitudes."""
    q = Rotation.random(50, random_state=3).as_quat()  # scalar last, as RotorPy
    zeros = np.zeros((50, 3))
    cols = sim.to_ned_frd(zeros, zeros, q, zeros, np.ones((50, 4)), zeros, zeros)
    e = euler_from_quaternions(np.column_stack([cols[c] for c in ("qw", "qx", "qy", "qz")]))
    ours = rotation_matrix(e[:, 0], e[:, 1], e[:, 2])
    flip = np.diag([1.0, -1.0, -1.0])
    assert np.allclose(ours, flip @ Rotation.from_quat(q).as_matrix() @ flip, atol=1e-12)


def test_rotors_go_to_px4_quad_x_order():
    """RotorPy r1 front-left, r2 front-right, r3 rear-right, r4 rear-left -> u1 FR, u2 RL, u3 FL, u4 RR."""
    cols = convert([0, 0, 0, 1], rotors=(11.0, 22.0, 33.0, 44.0))
    assert [cols[f"u{i}"][0] for i in range(1, 5)] == [22.0, 44.0, 11.0, 33.0]


def test_rates_and_accelerations_flip_y_and_z():
    """A FLU rate (1, 2, 3) rad/s is FRD (1, -2, -3); a climb acceleration +1 m/s^2 (z up) is az = -1."""
    cols = convert([0, 0, 0, 1], w=(1.0, 2.0, 3.0), vdot=(0.0, 0.0, 1.0))
    assert (cols["wx"][0], cols["wy"][0], cols["wz"][0]) == (1.0, -2.0, -3.0)
    assert cols["az"][0] == -1.0


def test_written_physics_has_quad_x_signs_and_hover_thrust():
    """Thrust along -z FRD (k_eta/m per rotor), rotor 1 (front-right) rolls left and pitches up, rotors 1 and
    2 (spin CCW seen from above) yaw the body clockwise (+dwz FRD), rotor drag is -sum(u) k_d/m ub."""
    body = sim.true_body_physics(HUMMINGBIRD)
    P = PRIMITIVE_SYMBOLS
    u1, u3 = P["u1"], P["u3"]
    fz = sympy.Poly(body["fz"], u1)
    assert float(fz.coeff_monomial(u1**2)) == pytest.approx(-5.57e-6 / 0.5)
    assert float(body["dwx"].coeff(u1**2)) < 0 < float(body["dwx"].coeff(u3**2))
    assert float(body["dwy"].coeff(u1**2)) > 0 > float(body["dwy"].coeff(P["u2"] ** 2))
    assert float(body["dwz"].coeff(u1**2)) == pytest.approx(1.36e-7 / 7.03e-3)
    assert float(body["dwz"].coeff(u3**2)) == pytest.approx(-1.36e-7 / 7.03e-3)
    assert float(body["fx"].coeff(u1 * P["ub"])) == pytest.approx(-1.19e-4 / 0.5)
    # Euler's coupling, FRD: wx' = (Iyy - Izz)/Ixx wy wz
    assert float(body["dwx"].coeff(P["wy"] * P["wz"])) == pytest.approx((3.68e-3 - 7.03e-3) / 3.65e-3)


def test_written_physics_matches_the_conversion_of_a_hand_computed_wrench():
    """Level, nose to world +x, moving forward at 3 m/s with all rotors at 500 rad/s: RotorPy's body force
    (FLU) is thrust 4 (k_eta 500^2 + k_h 3^2) up (translational lift), rotor drag -4 k_d 500 * 3 and
    parasitic drag -c_Dx 3^2 along x; in NED and FRD that is ax = (-4 k_d 500 3 - c_Dx 9)/m and
    az = g - thrust / m, and the written physics gives the same specific force."""
    g = 9.81
    fx = (-4 * 1.19e-4 * 500 * 3 - 0.5e-2 * 9) / 0.5
    fz_up = 4 * (5.57e-6 * 500**2 + 3.39e-3 * 9) / 0.5
    cols = convert([0, 0, 0, 1], v=(3.0, 0.0, 0.0), rotors=(500.0,) * 4, vdot=(fx, 0.0, fz_up - g))
    X = np.array([[0, 0, 0, cols["vx"][0], cols["vy"][0], cols["vz"][0], *euler(cols), 0, 0, 0,
                   *(cols[f"u{i}"][0] for i in range(1, 5))]])
    targets = np.array([[cols[n][0] for n in TARGET_NAMES]])
    measured = body_targets(X[:, :12], targets, g)[0]
    body = sim.true_body_physics(HUMMINGBIRD)
    values = {P: v for P, v in zip([PRIMITIVE_SYMBOLS[n] for n in ("ub", "vb", "wb", "wx", "wy", "wz")],
                                   [3.0, 0, 0, 0, 0, 0], strict=True)}
    values |= {PRIMITIVE_SYMBOLS[f"u{i}"]: 500.0 for i in range(1, 5)}
    written = [float(body[n].subs(values)) for n in ("fx", "fy", "fz")]
    assert measured[:3] == pytest.approx(written, abs=1e-9)
    assert measured[:3] == pytest.approx([fx, 0.0, -fz_up], abs=1e-9)
