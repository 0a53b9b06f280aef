"""The baseline controllers (PX4-style PID cascade, SE(3) geometric) on the SITL's own physics, in process.

Floors (Case II, 10 s, noise-free, from the ground at the origin; the SITL's rigid body, drag, motor lag and
ground plane through controller.simulate):
  se3: RMS 3-D error after 5 s < 2 mm, final error < 1 mm, within 5 cm from 4 s on
  pid: RMS after 5 s < 8 cm, final error < 5 cm, max tilt < 46 deg (PX4's 45 deg tilt limit)
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.errors import UserError
from bridge.vehicle import load_vehicle
from controller.baselines.pid_cascade import (
    PidCascadeController,
    PidCascadeGains,
    Px4Mixer,
    body_z_to_attitude,
)
from controller.baselines.se3 import Se3Controller, Se3Gains
from controller.metrics import settle_time
from controller.plugin import Reference, VehicleState
from controller.registry import make_controller
from controller.simulate import simulate
from controller.trajectories import case1, case2
from sitl.dynamics import Quadrotor

VEHICLE = load_vehicle("fang-chen-buaa")


class SitlPlant:
    """sitl.dynamics.Quadrotor as a controller.simulate plant: commanded speeds -> throttles (motor curve)."""

    def __init__(self, vehicle=VEHICLE, **reset):
        self.quad = Quadrotor(vehicle)
        self.curve = vehicle.motor_curve
        self._reset = reset

    def reset(self) -> None:
        self.quad.reset(**self._reset)

    def step(self, commanded_speeds) -> None:
        self.quad.step([self.curve.throttle_for_speed(float(w)) for w in commanded_speeds])

    def observe(self) -> VehicleState:
        q = self.quad
        xi = np.concatenate((q.position, q.velocity, q.euler, q.rates))
        return VehicleState(xi, np.array(q.rotor_speeds), np.array(q.quaternion))


def test_se3_tracks_case2_on_sitl_physics():
    res = simulate(Se3Controller(VEHICLE), case2(), SitlPlant(), 10.0)
    err = res.error
    assert res.rms_after(5.0) < 2e-3
    assert err[-1] < 1e-3
    assert settle_time(res.t, err) < 4.0
    assert res.max_tilt_deg < 46.0


def test_se3_tracks_case1_after_its_3_7_m_start():
    res = simulate(Se3Controller(VEHICLE), case1(), SitlPlant(), 8.0)
    assert res.error[0] > 3.6  # the reference starts 3.7 m away
    assert res.rms_after(5.0) < 2e-3


def test_pid_cascade_tracks_case2_on_sitl_physics():
    res = simulate(PidCascadeController(VEHICLE), case2(), SitlPlant(), 10.0)
    assert res.rms_after(5.0) < 0.08
    assert res.error[-1] < 0.05
    assert res.max_tilt_deg < 46.0
    # it climbs with the reference: no crash back to the ground
    assert res.xi[-1, 2] < -2.5


def test_se3_commands_hover_speed_at_hover():
    """At rest on the reference, level, the law asks exactly the hover thrust and no torque."""
    ctrl = Se3Controller(VEHICLE)
    hover = VEHICLE.hover_speed
    xi = np.zeros(12)
    xi[2] = -1.0
    cmd = ctrl.update(0.0, VehicleState(xi, np.full(4, hover)), Reference(np.array((0.0, 0.0, -1.0))))
    assert np.allclose(cmd.rotor_speeds, hover, rtol=1e-9)
    assert not cmd.saturated


def test_se3_feedforward_rates_match_the_reference_rotation():
    """W_c from central differences equals the body rate of the feedforward attitude along Case I."""
    ctrl = Se3Controller(VEHICLE)
    traj = case1()
    t, h = 3.0, 1e-4
    w, _ = ctrl._feedforward_rates(traj.reference(t))
    r = [ctrl._feedforward_attitude(traj.reference(t + d).acceleration, 0.0) for d in (-h, 0.0, h)]
    w_hat = r[1].T @ (r[2] - r[0]) / (2 * h)
    assert np.allclose(w, (w_hat[2, 1], w_hat[0, 2], w_hat[1, 0]), atol=1e-6)
    assert np.linalg.norm(w) > 0.01  # a real rotation, not a trivially zero check


def test_px4_mixer_keeps_outputs_in_range_and_gives_up_yaw_first():
    mixer = Px4Mixer(VEHICLE)
    out, clipped = mixer.mix(0.5, np.array((0.0, 0.0, 0.0)))
    assert np.allclose(out, 0.5) and not clipped
    # a yaw demand that cannot be met at this thrust: outputs stay in [0, 1], roll keeps its sign and size
    out, _ = mixer.mix(0.3, np.array((0.2, 0.0, 0.9)))
    assert np.all(out >= 0.0) and np.all(out <= 1.0)
    roll = float(out @ mixer.ROLL) / float(mixer.ROLL @ mixer.ROLL)
    assert roll == pytest.approx(0.2, rel=1e-6)
    # PX4's normalised authority of this vehicle: 2 sqrt(2) k w_max^2 roll torque per unit
    w2 = VEHICLE.motor_curve.max_speed ** 2
    assert mixer.torque_max[0] == pytest.approx(2 * math.sqrt(2) * VEHICLE.mixer_gain * w2)


def test_body_z_to_attitude_level_and_yawed():
    q = body_z_to_attitude((0.0, 0.0, 1.0), 0.7)
    assert q[0] == pytest.approx(math.cos(0.35)) and q[3] == pytest.approx(math.sin(0.35))


def test_gain_mappings_reject_unknown_and_bad_values():
    with pytest.raises(UserError, match="unknown parameter 'MPC_XY_PP'"):
        PidCascadeGains.from_mapping({"MPC_XY_PP": 1.0})
    with pytest.raises(UserError, match="must be a number"):
        PidCascadeGains.from_mapping({"MC_ROLL_P": "fast"})
    with pytest.raises(UserError, match="unknown gain 'kx'"):
        Se3Gains.from_mapping({"kx": 3.0})
    assert Se3Gains.from_mapping({"position_wn": 3}).position_wn == 3.0


def test_registry_names_and_sections(tmp_path):
    with pytest.raises(UserError, match="backstepping, pid, se3"):
        make_controller("lqr", None, VEHICLE)
    with pytest.raises(UserError, match="needs a model file"):
        make_controller("backstepping", None, VEHICLE)
    gains = tmp_path / "gains.yaml"
    gains.write_text("se3: {position_wn: 3.0}\npid: {MPC_XY_P: 1.2}\n")
    assert make_controller("se3", None, VEHICLE, gains).gains.position_wn == 3.0
    assert make_controller("pid", None, VEHICLE, gains).gains.MPC_XY_P == 1.2
    gains.write_text("position_wn: 3.0\nMPC_XY_P: 1.0\n")
    with pytest.raises(UserError, match="unknown gain 'MPC_XY_P'"):
        make_controller("se3", None, VEHICLE, gains)
