"""bridge.rotations, the one rotation toolkit: its scalar and array forms agree and invert each other."""

from __future__ import annotations

import numpy as np

from bridge.rotations import (
    euler_from_quaternion,
    euler_from_quaternions,
    quaternion_from_euler,
    quaternion_from_rotation,
    rotation_from_euler,
    rotation_from_quaternion,
    rotation_matrix,
)


def test_every_form_agrees_on_random_attitudes():
    rng = np.random.default_rng(16)
    euler = np.column_stack((rng.uniform(-3, 3, 200), rng.uniform(-1.5, 1.5, 200), rng.uniform(-3, 3, 200)))
    quats = np.array([quaternion_from_euler(*e) for e in euler])
    matrices = rotation_matrix(euler[:, 0], euler[:, 1], euler[:, 2])
    np.testing.assert_allclose(euler_from_quaternions(quats), euler, atol=1e-9)
    for e, q, r in zip(euler, quats, matrices, strict=True):
        np.testing.assert_allclose(np.reshape(rotation_from_euler(*e), (3, 3)), r, atol=0)
        np.testing.assert_allclose(np.reshape(rotation_from_quaternion(*q), (3, 3)), r, atol=1e-12)
        back = np.array(quaternion_from_rotation(r))
        np.testing.assert_allclose(back * np.sign(back[0] * q[0]), q, atol=1e-12)
        np.testing.assert_allclose(euler_from_quaternion(q), e, atol=1e-9)
    # body x of a 90 deg yaw points east (NED)
    np.testing.assert_allclose(rotation_matrix(0.0, 0.0, np.pi / 2)[:, 0], [0.0, 1.0, 0.0], atol=1e-15)
