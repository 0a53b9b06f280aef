"""Trajectories users write: segments (hold, step, ramp, move, expressions) and min-jerk waypoint legs with
time allocation from the limits; continuity, limits, the step, and clear errors."""

from __future__ import annotations

import numpy as np
import pytest

from bridge.errors import UserError
from controller.trajectories import describe, load_trajectory, trajectory_from_dict


def _sample(traj, t0: float, t1: float, n: int = 4001) -> tuple[np.ndarray, np.ndarray]:
    ts = np.linspace(t0, t1, n)
    return ts, np.array([traj.values(float(t)) for t in ts])


SEGMENTS = {"name": "mission", "segments": [
    {"kind": "hold", "position": [0, 0, -2], "duration": 2, "yaw": 0.0},
    {"kind": "ramp", "position": [2, 0, -2], "duration": 2},
    {"kind": "move", "position": [2, 2, -3], "duration": 3, "yaw": 1.0},
    {"kind": "expressions", "duration": 4, "x": "2 + sin(t)", "y": "2", "z": "-3"},
    {"kind": "hold", "duration": 1},
    {"kind": "step", "position": [0, 0, -2], "duration": 2},
]}


def test_segments_join_where_they_should_and_step_where_asked():
    traj = trajectory_from_dict(SEGMENTS, "mission.yaml")
    assert traj.end_time == pytest.approx(14.0) and describe(traj).kind == "segments"
    at = traj.values
    assert at(1.0)[0:3] == [0, 0, -2]
    assert at(3.0)[0:6] == pytest.approx([1.0, 0.0, -2.0, 1.0, 0.0, 0.0])  # ramp: half way, at 1 m/s
    # move: starts where the ramp ended, rest-to-rest minimum jerk, yaw turned to 1 rad
    assert at(4.0)[0:3] == pytest.approx([2, 0, -2]) and at(7.0 - 1e-9)[0:3] == pytest.approx([2, 2, -3])
    assert at(7.0 - 1e-9)[15] == pytest.approx(1.0)
    ts, v = _sample(traj, 4.0, 7.0 - 1e-9)
    assert np.abs(np.diff(v[:, 0:3], axis=0)).max() < 1e-2  # continuous inside
    assert np.abs(v[[0, -1], 3:9]).max() < 1e-6  # at rest at both ends
    # expressions: t counts from the segment's start (x = 2 + sin(t) starts at 2, continuing the move)
    assert at(7.0)[0] == pytest.approx(2.0) and at(7.0)[3] == pytest.approx(1.0)
    # the hold keeps the previous end; the step jumps and holds; after the end it holds
    end_expr = 2.0 + np.sin(4.0)
    assert at(11.5)[0:3] == pytest.approx([end_expr, 2, -3])
    assert at(12.0)[0:3] == pytest.approx([0, 0, -2]) and at(100.0)[0:3] == pytest.approx([0, 0, -2])
    assert at(12.5)[3:15] == [0.0] * 12


def test_a_step_is_a_step_not_a_43_m_swing():
    """The issue: a 4-waypoint quintic spline for a 0 -> 3 m step swung out to 43.7 m. A step segment is a
    jump, and min-jerk waypoints stay between their ends."""
    step = trajectory_from_dict({"segments": [{"kind": "hold", "position": [0, 0, -2], "duration": 5},
                                              {"kind": "step", "position": [3, 0, -2], "duration": 5}]}, "s")
    ts, v = _sample(step, 0.0, 10.0)
    assert set(np.round(v[:, 0], 12)) == {0.0, 3.0} and np.all(v[:, 3:15] == 0.0)
    wp = trajectory_from_dict({"interpolation": "min-jerk", "waypoints": [
        {"t": 0, "position": [0, 0, -2]}, {"t": 5, "position": [0, 0, -2]},
        {"t": 7, "position": [3, 0, -2]}, {"t": 12, "position": [3, 0, -2]}]}, "w")
    ts, v = _sample(wp, 0.0, 12.0)
    assert v[:, 0].min() >= -1e-12 and v[:, 0].max() <= 3.0 + 1e-12
    # continuous through acceleration: per 3 ms sample, at most the peak jerk (22.5 m/s^3) times the sample
    assert np.abs(np.diff(v[:, 0:9], axis=0)).max() < 22.5 * (ts[1] - ts[0]) * 1.05
    quintic = trajectory_from_dict({"max_speed": 100, "max_acceleration": 1000, "waypoints": [
        {"t": 0, "position": [0, 0, -2]}, {"t": 5, "position": [0, 0, -2]},
        {"t": 7, "position": [3, 0, -2]}, {"t": 12, "position": [3, 0, -2]}]}, "q")
    assert _sample(quintic, 0.0, 12.0)[1][:, 0].max() > 3.5  # the C4 spline swings out past the step


def test_min_jerk_waypoints_allocate_time_within_the_limits():
    data = {"interpolation": "min-jerk", "max_speed": 3.0, "max_acceleration": 2.0, "waypoints": [
        {"position": [0, 0, -2]}, {"position": [10, 0, -2]}, {"position": [10, 1, -2.5], "yaw": 1.5},
        {"position": [0, 0, -2]}]}
    traj = trajectory_from_dict(data, "mission.yaml")
    assert describe(traj).kind == "waypoints"
    ts, v = _sample(traj, 0.0, traj.end_time)
    speed = np.linalg.norm(v[:, 3:6], axis=1).max()
    accel = np.linalg.norm(v[:, 6:9], axis=1).max()
    assert speed <= 0.8 * 3.0 + 1e-6 and accel <= 0.8 * 2.0 + 1e-6  # planned to 80 % of the limits
    assert speed > 0.7 * 3.0  # and not needlessly slow on the long leg
    assert v[-1, 15] == pytest.approx(1.5)  # yaw held from the waypoint that set it
    for name, value in (("max_speed", 2.0), ("max_acceleration", 1.0)):  # tighter limits: longer
        slower = trajectory_from_dict({**data, name: value}, "m")
        assert slower.end_time > traj.end_time


@pytest.mark.parametrize(("data", "words"), [
    ({"segments": [{"kind": "hover", "duration": 1, "position": [0, 0, -1]}]}, "segments[0].kind"),
    ({"segments": [{"kind": "hold", "duration": 1}]}, "segments[0].position' is missing"),
    ({"segments": [{"kind": "ramp", "position": [0, 0, -1]}]}, "segments[0].duration' is missing"),
    ({"segments": [{"kind": "hold", "duration": 1, "position": [0, 0, -1]},
                   {"kind": "ramp", "duration": 0.5, "position": [20, 0, -1]}]}, "speed 40.00 m/s"),
    ({"segments": [{"kind": "expressions", "duration": 1, "x": "t", "y": "0"}]}, "segments[0].z' is missing"),
    ({"segments": [{"kind": "hold", "duration": 1, "position": [0, 0, -1], "x": "1"}]}, "segments[0].x"),
    ({"interpolation": "min-jerk", "waypoints": [{"t": 0, "position": [0, 0, 0]}, {"position": [1, 0, 0]}]},
     "for every waypoint or for none"),
    ({"interpolation": "cubic",
      "waypoints": [{"t": 0, "position": [0, 0, 0]}, {"t": 1, "position": [1, 0, 0]}]}, "interpolation"),
    ({"interpolation": "min-jerk", "expressions": {"x": "0", "y": "0", "z": "0"}}, "only applies"),
    ({"expressions": {"x": "0", "y": "0", "z": "0"}, "segments": []}, "exactly one of"),
])
def test_bad_segment_files_name_the_file_and_key(tmp_path, data, words):
    path = tmp_path / "bad.yaml"
    import yaml

    path.write_text(yaml.safe_dump(data), encoding="utf-8")
    with pytest.raises(UserError) as exc:
        load_trajectory(path)
    assert str(path) in str(exc.value) and words in str(exc.value)
