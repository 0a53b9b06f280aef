"""Datasets from a real PX4 ULog (../shared/logs/px4_sitl_quad_takeoff.ulg): rows, rotor speeds, targets, and
clear errors for cut, corrupt, empty and incomplete logs (real bytes of the real file)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from bridge.errors import UserError
from identification.dataset import load_dataset

REPO = Path(__file__).resolve().parent.parent
LOG = REPO.parent / "shared" / "logs" / "px4_sitl_quad_takeoff.ulg"

pytestmark = pytest.mark.skipif(
    not LOG.is_file(), reason=f"the shared PX4 log {LOG} is absent (a user's own clone)"
)


@pytest.fixture(scope="module")
def truth():
    return load_dataset(LOG)


# Hand-labelled from the log (z, vz, az and the motor commands at 0.5 s steps): lift-off at 19.0 s (z starts
# to fall, az -1.2 m/s^2), touch-down at about 26.3 s (the commands start to fall while the estimator's z,
# which drifted by +0.4 m, still descends); the land detector clears `landed` at 16.75 s, before lift-off.
LIFT_OFF, TOUCH_DOWN = 19.0, 26.3


def test_rows_are_the_airborne_part_on_the_angular_velocity_timeline(truth):
    ds = truth
    assert ds.format == "ulog" and ds.target_source == "truth"
    assert LIFT_OFF <= ds.t[0] < LIFT_OFF + 1.0 and TOUCH_DOWN - 1.5 < ds.t[-1] <= TOUCH_DOWN
    assert 250 <= len(ds) <= 365  # 50 Hz over at most the 7.3 s airborne
    assert np.median(np.diff(ds.t)) == pytest.approx(0.02, rel=0.05)
    assert ds.drop_reasons["on the ground (the log's land detector)"] > 100
    assert ds.drop_reasons["below 0.15 m above the take-off point"] > 50
    text = "\n".join(ds.segments)
    assert "kept" in text and "cross-check: the detectors disagree" in text
    assert ds.dropped_rows == sum(ds.drop_reasons.values())
    assert np.isfinite(ds.xi).all() and np.isfinite(ds.u).all() and np.isfinite(ds.targets).all()
    # it climbs to about 2 m (z up to -2 NED) and stays near level
    assert -2.6 < ds.xi[:, 2].min() < -1.5
    assert np.degrees(np.abs(ds.xi[:, 6:8])).max() < 15.0


def test_esc_rotor_speeds_are_hover_like(truth):
    u = truth.u
    assert any("esc_status" in w for w in truth.warnings)
    mean = u.mean(axis=0)
    # four motors share the load within 5%, and turn at a steady speed around a hover value
    assert mean.max() / mean.min() < 1.05
    assert 200.0 < mean.mean() < 400.0  # rad/s (the log's ESCs report ~2,500-3,300 rpm)
    middle = u[len(u) // 4 : 3 * len(u) // 4]  # between the spin-up after take-off and the landing
    assert middle.min() > 0.8 * mean.mean()


def test_actuator_outputs_through_a_motor_curve_give_hover_throttle():
    ds = load_dataset(LOG, motor_curve="1000,0")
    assert any("PWM" in w for w in ds.warnings)
    throttle = ds.u / 1000.0
    # PX4's hover throttle for this airframe is MPC_THR_HOVER = 0.5; in flight the mean sits near it
    assert 0.35 < throttle.mean() < 0.6
    assert throttle.max() <= 1.0 and throttle.min() >= 0.0
    with pytest.raises(UserError, match="slope,offset"):
        load_dataset(LOG, motor_curve="-3,1")


def test_accelerations_are_consistent_with_the_velocity(truth):
    ds = truth
    # over 1 s windows the velocity change equals the integral of the logged acceleration (NED)
    dt = np.diff(ds.t)
    for j in range(3):
        a, v = ds.targets[:, j], ds.xi[:, 3 + j]
        integral = np.concatenate(([0.0], np.cumsum(0.5 * (a[1:] + a[:-1]) * dt)))
        step = 50
        dv = v[step:] - v[:-step]
        di = integral[step:] - integral[:-step]
        assert np.sqrt(np.mean((dv - di) ** 2)) < 0.1, j
    # vertical: the climb and descent dominate, so the pointwise derivative agrees too
    dvz = np.gradient(ds.xi[:, 5], ds.t)
    assert np.corrcoef(dvz, ds.targets[:, 2])[0, 1] > 0.95
    # one airborne segment: the mean vertical acceleration is the change of vz over it
    assert ds.targets[:, 2].mean() == pytest.approx(
        (ds.xi[-1, 5] - ds.xi[0, 5]) / (ds.t[-1] - ds.t[0]), abs=0.05
    )


def test_sensor_targets_agree_with_the_estimator(truth):
    ds = load_dataset(LOG, targets="sensors")
    assert ds.target_source == "sensors"
    assert abs(len(ds) - len(truth)) < 10
    common, ia, ib = np.intersect1d(ds.t, truth.t, return_indices=True)
    # specific force rotated to NED plus g: vertical acceleration matches the estimator's
    assert np.corrcoef(ds.targets[ia, 2], truth.targets[ib, 2])[0, 1] > 0.95
    assert abs(ds.targets[ia, 2].mean() - truth.targets[ib, 2].mean()) < 0.05


def test_uniform_timeline_at_a_chosen_rate():
    ds = load_dataset(LOG, rate_hz=100.0, airborne=False)
    assert np.allclose(np.diff(ds.t)[np.diff(ds.t) < 0.0101], 0.01)
    assert 1900 <= len(ds) <= 2200  # valid local position ~9.7..31 s


def test_truncated_log_yields_what_it_holds_with_a_warning(tmp_path):
    data = LOG.read_bytes()
    cut = tmp_path / "cut.ulg"
    cut.write_bytes(data[: int(len(data) * 0.8)])
    ds = load_dataset(cut)
    assert any("truncated" in w for w in ds.warnings)
    assert 100 < len(ds) < 600 and ds.t[-1] < 27.0


def test_damaged_and_empty_logs_are_clear_errors(tmp_path):
    data = LOG.read_bytes()
    empty = tmp_path / "empty.ulg"
    empty.write_bytes(b"")
    with pytest.raises(UserError, match="empty.ulg is empty"):
        load_dataset(empty)
    garbage = tmp_path / "garbage.ulg"
    garbage.write_bytes(data[:16] + np.random.default_rng(1).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    with pytest.raises(UserError, match="garbage.ulg is corrupt"):
        load_dataset(garbage)
    header_only = tmp_path / "header.ulg"
    header_only.write_bytes(data[:2000])
    with pytest.raises(UserError, match="header.ulg holds no logged data"):
        load_dataset(header_only)


def test_a_missing_topic_is_named(tmp_path):
    from pyulog import ULog

    ulog = ULog(str(LOG))
    ulog._data_list = [d for d in ulog.data_list if d.name != "vehicle_attitude"]
    path = tmp_path / "no_attitude.ulg"
    ulog.write_ulog(str(path))
    with pytest.raises(
        UserError, match="no_attitude.ulg has no topic 'vehicle_attitude'; it is needed for the attitude"
    ):
        load_dataset(path)


def test_angular_velocity_without_its_derivative_is_differentiated(tmp_path):
    """vehicle_angular_velocity without xyz_derivative (zeros): read, wx' etc. by differentiation."""
    from pyulog import ULog

    ulog = ULog(str(LOG))
    for d in ulog.data_list:
        if d.name == "vehicle_angular_velocity":
            for i in range(3):
                d.data[f"xyz_derivative[{i}]"][:] = 0.0
    path = tmp_path / "no_derivative.ulg"
    ulog.write_ulog(str(path))
    ds = load_dataset(path)
    assert any("no xyz_derivative" in w for w in ds.warnings)
    assert abs(len(ds) - len(load_dataset(LOG))) < 10
    # the documented fallback: identification.targets.stream_derivative of the rates, at their own times
    from identification.targets import stream_derivative

    av = {d.name: d for d in ulog.data_list}["vehicle_angular_velocity"].data
    t = (av["timestamp_sample"].astype(np.int64) - np.int64(ulog.start_timestamp)) * 1e-6
    dw = stream_derivative(t, np.column_stack([av[f"xyz[{i}]"] for i in range(3)]).astype(float))
    k = np.searchsorted(t, ds.t)
    assert np.allclose(t[k], ds.t) and np.allclose(ds.targets[:, 3:6], dw[k], atol=1e-9)


def test_motor_commands_replace_4_hz_rpm_when_they_explain_the_thrust_better(truth):
    """jMAVSim's rpm (4 Hz, thrust not quadratic in it) against actuator_outputs through a fitted curve."""
    from identification.motor_model import apply_thrust_curve, choose_motor_model, thrust_direction_r2

    train, _ = truth.split(0.2)
    curve, why = choose_motor_model(train)
    assert curve is not None and "using the commands" in why
    measured, _ = thrust_direction_r2(train, train.u)
    assert curve.r2 > 0.95 and measured < 0.8  # measured on this log: 0.982 against 0.488
    assert curve.k == 0.0  # jMAVSim's thrust is linear in the command
    remade = apply_thrust_curve(truth, curve)
    assert remade.u_from_throttle and np.allclose(
        remade.u[:, 0], 1000.0 * np.sqrt(truth.aux["throttle"][:, 0])
    )
