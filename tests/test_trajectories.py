"""Reference trajectories: the paper's cases, analytic derivatives, user YAML checked at load time."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from bridge.errors import UserError
from controller.trajectories import load_trajectory, trajectory_from_dict


def _fd_check(traj, times, h=1e-3, rtol=2e-5, atol=2e-6):
    """Each derivative against the central difference of the one below it (position..snap, yaw..yaw'')."""
    for t in times:
        lo, mid, hi = (np.asarray(traj.values(t + d)) for d in (-h, 0.0, h))
        for k in range(4):  # velocity..snap from position..jerk
            fd = (hi[3 * k: 3 * k + 3] - lo[3 * k: 3 * k + 3]) / (2 * h)
            assert np.allclose(mid[3 * k + 3: 3 * k + 6], fd, rtol=rtol, atol=atol), (t, k)
        for k in range(2):  # yaw rate and acceleration
            fd = (hi[15 + k] - lo[15 + k]) / (2 * h)
            assert math.isclose(mid[16 + k], fd, rel_tol=rtol, abs_tol=atol), (t, k)


def test_case1_is_the_papers_and_starts_3_7_m_away():
    tr = load_trajectory("case1")
    ref = tr.reference(0.0)
    assert np.allclose(ref.position, [3 * math.sin(math.pi / 3), 3 * math.sin(-2 * math.pi / 3), 0.0])
    assert 3.6 < np.linalg.norm(ref.position) < 3.7
    t = 7.3
    r = tr.reference(t)
    assert np.allclose(r.position, [3 * math.sin(0.5 * t + math.pi / 3),
                                    3 * math.sin(0.5 * t - 2 * math.pi / 3), -0.2 * t])
    assert np.allclose(r.snap[:2], [0.1875 * math.sin(0.5 * t + math.pi / 3),
                                    0.1875 * math.sin(0.5 * t - 2 * math.pi / 3)])
    assert r.yaw == 0.0
    _fd_check(tr, [0.5, 3.0, 11.2])


def test_case2_is_the_papers():
    tr = load_trajectory("case2")
    r = tr.reference(4.0)
    assert np.allclose(r.position, [2.0, 4.0, -1.2])
    assert np.allclose(r.velocity, [0.0, 0.0, -0.3])
    assert np.allclose(r.acceleration, 0.0) and np.allclose(r.jerk, 0.0)


def test_expression_trajectory_with_yaw_derivatives():
    tr = trajectory_from_dict({"expressions": {"x": "sin(t)*cos(0.3*t)", "y": "exp(-0.1*t)", "z": "-t^2/10",
                                               "yaw": "0.5*sin(0.7*t)"}, "duration": 10}, "mine.yaml")
    _fd_check(tr, [0.3, 2.2, 5.9])
    assert math.isclose(tr.reference(1.0).yaw_acceleration, -0.5 * 0.49 * math.sin(0.7))


def test_waypoints_are_smooth_through_snap_and_at_rest_at_the_ends():
    wps = [{"t": 0, "position": [0, 0, 0], "yaw": 0}, {"t": 3, "position": [0, 0, -1.5]},
           {"t": 6, "position": [2, 1, -2], "yaw": 0.8}, {"t": 9, "position": [2, 3, -2]}]
    tr = trajectory_from_dict({"waypoints": wps, "duration": 12}, "wp.yaml")
    for wp in wps:
        assert np.allclose(tr.reference(wp["t"]).position, wp["position"], atol=1e-9)
    assert math.isclose(tr.reference(6.0).yaw, 0.8, abs_tol=1e-9)
    for t in (0.0, 9.0):
        r = tr.reference(t)
        assert np.allclose(r.velocity, 0.0, atol=1e-9) and np.allclose(r.acceleration, 0.0, atol=1e-9)
    for knot in (3.0, 6.0):  # continuity of every derivative up to snap across the knots
        left, right = np.asarray(tr.values(knot - 1e-7)), np.asarray(tr.values(knot + 1e-7))
        assert np.allclose(left, right, atol=1e-4)
    _fd_check(tr, [1.1, 4.5, 7.7], rtol=1e-4, atol=1e-5)
    after = tr.reference(11.0)
    assert np.allclose(after.position, [2, 3, -2]) and np.allclose(after.velocity, 0)


def test_holds_before_the_start():
    tr = load_trajectory("case1")
    r = tr.reference(-1.0)
    assert np.allclose(r.position, tr.reference(0.0).position) and np.allclose(r.velocity, 0.0)


def _write(tmp_path, data, name="traj.yaml"):
    p = tmp_path / name
    p.write_text(yaml.safe_dump(data))
    return p


@pytest.mark.parametrize(
    ("data", "key", "words"),
    [
        ({"expressions": {"x": "t", "y": "0", "z": "0"}, "speed": 3}, "speed", "unknown key"),
        ({"expressions": {"x": "t", "y": "0", "z": "0", "roll": "0"}}, "expressions.roll", "unknown key"),
        ({"expressions": {"x": "3*sin(0.5*t", "y": "0", "z": "0"}}, "expressions.x", "not a formula"),
        ({"expressions": {"x": "u*t", "y": "0", "z": "0"}}, "expressions.x", "unknown name"),
        ({"expressions": {"x": "abs(t - 1)", "y": "0", "z": "0"}}, "expressions.x", "smooth"),
        ({"expressions": {"x": "t", "y": "0"}}, "expressions.z", "missing"),
        ({"expressions": {"x": "1/(t - 1)", "y": "0", "z": "0"}, "duration": 2}, "expressions", "not finite"),
        ({"waypoints": [{"t": 0, "position": [0, 0, 0]}, {"t": 0, "position": [1, 0, 0]}]}, "waypoints[1].t",
         "strictly increase"),
        ({"waypoints": [{"t": 0, "position": [0, 0, 0]}, {"t": 0.5, "position": [1, 0, 0]}]}, "waypoints",
         "acceleration"),
        ({"waypoints": [{"t": 0, "position": [0, 0]}, {"t": 2, "position": [1, 0, 0]}]},
         "waypoints[0].position", "[x, y, z]"),
        ({"waypoints": [{"t": 0, "position": [0, 0, 0], "speed": 1}, {"t": 2, "position": [1, 0, 0]}]},
         "waypoints[0].speed", "unknown key"),
        ({"waypoints": [{"t": 0, "position": [0, 0, 0]}]}, "waypoints", "at least 2"),
        ({"expressions": {"x": "0", "y": "0", "z": "0"}, "waypoints": []}, "expressions", "exactly one"),
    ],
)
def test_bad_user_files_name_the_file_and_key(tmp_path, data, key, words):
    path = _write(tmp_path, data)
    with pytest.raises(UserError) as err:
        load_trajectory(path)
    text = str(err.value)
    assert str(path) in text and key in text and words in text, text


def test_user_file_loads_and_unknown_name_is_refused(tmp_path):
    wps = [{"t": 0, "position": [0, 0, 0]}, {"t": 4, "position": [0, 0, -2]}]
    path = _write(tmp_path, {"name": "hop", "duration": 8, "waypoints": wps})
    tr = load_trajectory(path)
    assert tr.name == "hop" and tr.duration == 8.0
    assert np.isclose(tr.reference(2.0).position[2], -1.0)
    with pytest.raises(UserError, match="not found"):
        load_trajectory(tmp_path / "missing.yaml")
    with pytest.raises(UserError, match="case1"):
        load_trajectory("case3")
