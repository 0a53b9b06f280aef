"""Datasets from ArduPilot DataFlash logs: synthetic .bin files in the real binary format (written by
tests/dataflash_fixture.py from a flight of the SITL's dynamics) parsed by pymavlink's DFReader."""

from __future__ import annotations

import numpy as np
import pytest
from dataflash_fixture import fly_synthetic, write_flight

from bridge.errors import UserError
from identification.dataset import load_dataset

T0 = 5.0  # s, TimeUS of the first sample in the synthetic logs
CHANNELS = (3, 1, 4, 2)  # output channel of motors 1..4: not the identity, so the mapping is exercised


def r2(estimate: np.ndarray, truth: np.ndarray) -> np.ndarray:
    return 1.0 - ((estimate - truth) ** 2).sum(0) / ((truth - truth.mean(0)) ** 2).sum(0)


@pytest.fixture(scope="module")
def flight():
    return fly_synthetic(duration=3.0, seed=2)


@pytest.fixture(scope="module")
def binlog(flight, tmp_path_factory):
    return write_flight(
        tmp_path_factory.mktemp("df") / "copter.bin", flight, channel_of_motor=CHANNELS, esc_every=5
    )


def truth_rows(flight, ds):
    k = np.round((ds.t - T0) / 0.004).astype(int)
    return flight.xi[k], flight.u[k], flight.accel[k]


def test_states_in_si_units_and_rad(flight, binlog):
    ds = load_dataset(binlog)
    assert ds.format == "dataflash" and len(ds) > 600
    xi, _, _ = truth_rows(flight, ds)
    # ATT degrees -> rad (yaw logged 0..360, wrapped back), RATE deg/s -> rad/s, XKF1 core 0 (not core 1)
    assert np.abs(ds.xi[:, 6:9] - xi[:, 6:9]).max() < 1e-5
    assert np.abs(ds.xi[:, 9:12] - xi[:, 9:12]).max() < 1e-4
    assert np.abs(ds.xi[:, 0:6] - xi[:, 0:6]).max() < 0.01  # XKF1 at 25 Hz, interpolated
    assert np.abs(ds.xi[:, 8]).max() <= np.pi


def test_esc_instances_map_to_motors_by_servo_function(flight, binlog):
    ds = load_dataset(binlog)
    _, u, _ = truth_rows(flight, ds)
    # ESC at 50 Hz interpolated: each u_i follows its own motor, not another one
    for i in range(4):
        errors = [np.abs(ds.u[:, i] - u[:, j]).mean() for j in range(4)]
        assert int(np.argmin(errors)) == i and errors[i] < 3.0


def test_rcou_through_the_motor_curve(flight, binlog):
    ds = load_dataset(binlog, motor_curve="fang-chen-buaa")
    _, u, _ = truth_rows(flight, ds)
    # PWM (1 us steps) -> throttle -> the vehicle's curve and motor lag: within ~1 rad/s of the true speeds
    assert np.abs(ds.u - u).max() < 1.5
    assert ds.drop_reasons.get("motor lag settling after the start or a gap", 0) > 0


def test_sensor_targets_match_the_dynamics(flight, binlog):
    ds = load_dataset(binlog, targets="sensors", gravity=9.8)
    _, _, acc = truth_rows(flight, ds)
    fit = r2(ds.targets, acc)
    assert (fit > 0.999).all(), fit


def test_truth_targets_from_the_log_states(flight, binlog):
    ds = load_dataset(binlog, targets="truth")
    _, _, acc = truth_rows(flight, ds)
    fit = r2(ds.targets, acc)
    # body rates at 250 Hz give the angular accelerations closely; a 25 Hz EKF velocity only the slow part
    assert (fit[3:] > 0.999).all(), fit
    assert (fit[:3] > 0.99).all(), fit


def test_position_from_pos_when_there_is_no_ekf(flight, tmp_path):
    path = write_flight(tmp_path / "no_ekf.bin", flight, with_xkf1=False)
    ds = load_dataset(path)
    xi, _, _ = truth_rows(flight, ds)
    assert any("no XKF1/NKF1/EKF1" in w for w in ds.warnings)
    # local NED from the first fix: displacements match the true ones (lat/lon in 1e-7 deg: ~1 cm)
    assert np.abs((ds.xi[:, 0:3] - ds.xi[0, 0:3]) - (xi[:, 0:3] - xi[0, 0:3])).max() < 0.05
    # velocity differentiated from 25 Hz fixes quantized to 1e-7 deg (~1 cm): a few cm/s RMS
    assert np.sqrt(np.mean((ds.xi[:, 3:6] - xi[:, 3:6]) ** 2)) < 0.05


def test_missing_messages_are_named(flight, tmp_path):
    no_att = write_flight(tmp_path / "no_att.bin", flight, with_att=False)
    with pytest.raises(UserError, match="no_att.bin has no ATT messages; they are needed for the attitude"):
        load_dataset(no_att)
    bare = write_flight(tmp_path / "bare.bin", flight, with_esc=False, with_rcou=False)
    with pytest.raises(UserError, match="bare.bin has no ESC messages") as info:
        load_dataset(bare)
    assert "RCOU" in str(info.value)


def test_truncated_corrupt_and_empty_logs(binlog, tmp_path):
    data = binlog.read_bytes()
    cut = tmp_path / "cut.bin"
    cut.write_bytes(data[: int(len(data) * 0.7) + 5])
    ds = load_dataset(cut)
    assert any("truncated" in w for w in ds.warnings)
    assert ds.t[-1] < T0 + 0.75 * 3.0
    empty = tmp_path / "empty.bin"
    empty.write_bytes(b"")
    with pytest.raises(UserError, match="empty.bin is empty"):
        load_dataset(empty)
    garbage = tmp_path / "garbage.bin"
    garbage.write_bytes(np.random.default_rng(3).integers(0, 160, 3000, dtype=np.uint8).tobytes())
    with pytest.raises(UserError, match="garbage.bin is not an ArduPilot DataFlash log"):
        load_dataset(garbage)
    no_data = tmp_path / "formats_only.bin"
    first_imu = data.index(b"\xa3\x95\x83")  # IMU is the third message type the writer defines
    no_data.write_bytes(data[:first_imu])  # FMT, MSG and PARM records only
    with pytest.raises(UserError, match="formats_only.bin has no ATT messages"):
        load_dataset(no_data)


def test_old_arducopter_log_timems_ekf1_and_rc3_range(flight, tmp_path):
    """A Copter 3.2-era log: TimeMS, EKF1, RCOU Chan1..4, MOT_PWM_MIN/MAX = 0 (so RC3_MIN/MAX), no RATE."""
    from dataflash_fixture import write_old_flight

    path = write_old_flight(tmp_path / "old.bin", flight, rc3=(1100, 1900))
    ds = load_dataset(path, airborne=False)
    assert len(ds) > 100 and ds.u_from_throttle
    k = np.round((ds.t - T0) / 0.004).astype(int)
    # ATT in centidegrees, EKF1 position and velocity, rates from the IMU gyro: the true states
    assert np.abs(ds.xi[:, 6:9] - flight.xi[k, 6:9]).max() < 1e-3
    assert np.abs(ds.xi[:, 0:6] - flight.xi[k, 0:6]).max() < 0.05
    assert np.abs(ds.xi[:, 9:12] - flight.xi[k, 9:12]).max() < 0.05
    # PWM mapped with RC3_MIN/MAX (1100..1900), not 1000..2000: the throttles come back to 1e-2
    assert np.abs(ds.aux["throttle"] - flight.throttle[k]).max() < 0.01
    assert any("RC3_MIN/MAX" in w for w in ds.warnings)


def test_battery_arming_and_throttle_side_columns(flight, binlog):
    ds = load_dataset(binlog, airborne=False)
    assert (ds.aux["armed"] == 1.0).all()
    assert np.allclose(ds.aux["voltage"], 16.0 - 0.1 * (ds.t - T0), atol=0.02)  # BAT Volt, interpolated
    k = np.round((ds.t - T0) / 0.004).astype(int)
    assert np.abs(ds.aux["throttle"] - flight.throttle[k]).max() < 1e-3


def test_without_esc_the_motor_commands_go_through_a_thrust_curve(flight, tmp_path):
    from identification.motor_model import apply_thrust_curve, fit_thrust_curve

    path = write_flight(tmp_path / "no_esc.bin", flight, with_esc=False)
    ds = load_dataset(path, airborne=False)
    assert ds.u_from_throttle
    curve = fit_thrust_curve(ds)
    fitted = apply_thrust_curve(ds, curve)
    # the vehicle's rotor speed is linear in throttle (w = 1148 s - 141), so thrust ~ w^2 is nearly
    # quadratic in throttle: the fit must pick a k well above 0, and explain the thrust direction
    assert curve.k >= 0.6 and curve.r2 > 0.9
    k = np.round((ds.t - T0) / 0.004).astype(int)
    ratio = (fitted.u**2).sum(axis=1) / (flight.u[k] ** 2).sum(axis=1)
    assert ratio.std() / ratio.mean() < 0.1  # u^2 proportional to the true thrust within 10%


def test_logs_with_and_without_rotor_speeds_do_not_mix(flight, binlog, tmp_path):
    from identification.dataset import load_datasets

    no_esc = write_flight(tmp_path / "commands_only.bin", flight, with_esc=False)
    with pytest.raises(UserError, match="some logs have rotor speeds") as info:
        load_datasets([binlog, no_esc], airborne=False)
    assert "--motor-curve" in str(info.value)
    both = load_datasets([binlog, no_esc], airborne=False, motor_curve="fang-chen-buaa")
    assert len(both.flights) == 2 and not both.u_from_throttle


def test_a_motor_whose_esc_telemetry_stops_is_not_held_at_its_last_rpm(flight, tmp_path):
    # ArduPilot writes an ESC record only with new telemetry: a motor whose wire broke has no record in the
    # later batches, and carrying its last rpm for the rest of the log would make up rotor speeds
    path = write_flight(tmp_path / "lost.bin", flight, channel_of_motor=CHANNELS, esc_every=5,
                        esc_silent=(CHANNELS[2], 1.5))
    ds = load_dataset(path)
    assert ds.t.max() < T0 + 1.5 + 0.1, ds.t.max()  # 4 of that ESC's 20 ms intervals at most
    assert ds.drop_reasons.get("NaN in states or rotor speeds", 0) > 300
    _, u, _ = truth_rows(flight, ds)
    assert np.abs(ds.u[:, 2] - u[:, 2]).max() < 10.0
