"""The simulated physics seen by a companion: `quadsr sitl` as a separate process, real UDP, real clients."""

from __future__ import annotations

import math

import numpy as np
import pytest

from bridge.lockstep import LockstepClient
from bridge.vehicle import load_vehicle, vehicles_dir

pytestmark = pytest.mark.e2e

VEHICLE = load_vehicle("fang-chen-buaa")
CURVE = VEHICLE.motor_curve
HOVER = VEHICLE.hover_speed
IN_AIR = ("--ground", "none", "--sensors", "ideal")


def f32(x: float) -> float:
    """x rounded to float32, as it travels in a MAVLink float field."""
    return float(np.float32(x))


def test_hover_at_the_computed_speed_holds_altitude(start_sitl):
    sitl = start_sitl(*IN_AIR, "--initial-position", "0,0,-50", "--initial-rotor-speed", "hover")
    throttle = CURVE.throttle_for_speed(HOVER)
    with LockstepClient(sitl.hil, timeout=5.0) as client:
        first = client.connect(10.0)
        for _ in range(2500):  # 10 s
            obs = client.step([throttle] * 4)
    assert first.time_usec == 0 and obs.time_usec == 10_000_000
    drift = obs.truth.position - first.truth.position
    assert abs(drift[2]) < 1e-3, f"altitude drift {drift[2] * 1000:.4f} mm over 10 s"
    assert np.all(np.abs(drift[:2]) < 1e-3)
    assert np.allclose(obs.rotor_speeds, HOVER, rtol=1e-5)
    assert np.all(np.abs(obs.truth.rates) < 1e-6)


def test_motor_time_constant_from_rotor_speeds(start_sitl):
    sitl = start_sitl(*IN_AIR, "--initial-position", "0,0,-100")
    target = CURVE.speed_for_throttle(0.8)
    speeds = []
    with LockstepClient(sitl.hil, timeout=5.0) as client:
        assert np.all(client.connect(10.0).rotor_speeds == 0.0)
        for _ in range(30):
            obs = client.step([0.8] * 4)
            speeds.append(obs.rotor_speeds)
    speeds = np.array(speeds)
    assert np.all(speeds == speeds[:, :1]), "the four motors must respond alike"
    t = 0.004 * np.arange(1, 31)
    tau = -t / np.log(1.0 - speeds[:, 0] / target)
    expected = VEHICLE.motor.time_constant
    assert np.all(np.abs(tau - expected) < 0.002 * expected), tau
    assert speeds[-1, 0] == pytest.approx(target * (1 - math.exp(-0.12 / expected)), rel=1e-4)


# Expected sign of (roll, pitch, yaw) rate when one motor speeds up: the paper's f2, f3, f4 columns.
MOTOR_SIGNS = {1: (-1, 1, 1), 2: (1, -1, 1), 3: (1, 1, -1), 4: (-1, -1, -1)}


def test_each_motor_rolls_pitches_and_yaws_the_right_way(start_sitl):
    sitls = {m: start_sitl(*IN_AIR, "--initial-position", "0,0,-50", "--initial-rotor-speed", "hover")
             for m in MOTOR_SIGNS}
    hover = CURVE.throttle_for_speed(HOVER)
    fast = CURVE.throttle_for_speed(HOVER + 60.0)
    for motor, signs in MOTOR_SIGNS.items():
        throttles = [hover] * 4
        throttles[motor - 1] = fast
        with LockstepClient(sitls[motor].hil, timeout=5.0) as client:
            client.connect(10.0)
            for _ in range(10):
                obs = client.step(throttles)
        rates = obs.truth.rates
        assert tuple(int(np.sign(r)) for r in rates) == signs, f"motor {motor}: rates {rates} rad/s"
        assert min(abs(rates[0]), abs(rates[1])) > 0.05 and abs(rates[2]) > 1e-3


def test_free_fall_follows_gravity_and_quadratic_drag(start_sitl):
    sitl = start_sitl(*IN_AIR, "--initial-position", "0,0,-100")
    m, g, cd = VEHICLE.mass, VEHICLE.gravity, VEHICLE.drag.body_quadratic[2]
    vt = math.sqrt(m * g / cd)  # terminal speed
    with LockstepClient(sitl.hil, timeout=5.0) as client:
        client.connect(10.0)
        first = client.step([0.0] * 4)
        assert first.imu.accel == pytest.approx([0.0, 0.0, 0.0], abs=1e-3)  # free fall: ~no specific force
        for _ in range(249):
            obs = client.step([0.0] * 4)
    t = obs.t
    assert t == 1.0
    v = vt * math.tanh(g * t / vt)
    z = -100.0 + vt * vt / g * math.log(math.cosh(g * t / vt))
    assert obs.truth.velocity[2] == pytest.approx(v, abs=1e-5)
    assert obs.truth.position[2] == pytest.approx(z, abs=1e-4)
    assert obs.imu.accel[2] == pytest.approx(-cd * v * v / m, abs=1e-4)  # drag is all the IMU feels
    assert np.all(obs.truth.position[:2] == 0.0) and np.all(obs.truth.rates == 0.0)


def test_rests_on_the_ground_takes_off_and_lands(start_sitl):
    sitl = start_sitl("--sensors", "ideal")
    zs = []
    with LockstepClient(sitl.hil, timeout=5.0) as client:
        client.connect(10.0)
        for _ in range(50):  # idle: thrust far below weight
            obs = client.step([0.3] * 4)
            zs.append(obs.truth.position[2])
        assert obs.truth.position[2] == 0.0 and np.all(obs.truth.velocity == 0.0)
        assert obs.imu.accel == pytest.approx([0.0, 0.0, -VEHICLE.gravity], abs=1e-5)
        climb = CURVE.throttle_for_speed(HOVER * 1.1)
        for _ in range(250):
            obs = client.step([climb] * 4)
            zs.append(obs.truth.position[2])
        assert obs.truth.position[2] < -0.3 and obs.truth.velocity[2] < -0.5
        for _ in range(400):
            obs = client.step([0.0] * 4)
            zs.append(obs.truth.position[2])
    assert max(zs) <= 0.0, "never below the ground plane"
    assert obs.truth.position[2] == 0.0 and np.all(obs.truth.velocity == 0.0), "landed and resting"
    assert obs.imu.accel == pytest.approx([0.0, 0.0, -VEHICLE.gravity], abs=1e-5)


def test_hil_fields_units_bitmasks_and_order(start_sitl, raw_companion):
    sitl = start_sitl("--seed", "3")  # realistic sensors, resting on the ground
    companion = raw_companion(sitl.hil)
    frames = companion.connect()
    datagrams = []
    for _ in range(150):
        datagrams.append(frames)
        frames = companion.step([0.0] * 4)
    accels, times = [], []
    for frames in datagrams:
        msgs = [m for m, _ in frames]
        types = [m.get_type() for m in msgs]
        sensor = msgs[-1]
        t = sensor.time_usec
        k = t // 4000
        gps_step = k % 25 == 0
        expected = ["HIL_STATE_QUATERNION", "LOCAL_POSITION_NED"] + ["RAW_RPM"] * 4
        expected += ["HIL_GPS"] * gps_step + ["DEBUG_FLOAT_ARRAY", "HIL_SENSOR"]
        assert types == expected, f"step {k}: {types}"
        true_acc = msgs[-2]  # the true accelerations at the step's state: zero while held on the ground
        assert true_acc.name == "TRUE_ACC" and true_acc.time_usec == t and not any(true_acc.data)
        assert all(m.get_srcSystem() == 1 and m.get_srcComponent() == 51 for m in msgs)
        assert msgs[0].time_usec == t and msgs[1].time_boot_ms == t // 1000
        assert [m.index for m in msgs[2:6]] == [0, 1, 2, 3]
        bits = 0x3F | (0x1C0 if k % 4 == 0 else 0) | (0x1A00 if k % 5 == 0 else 0)
        assert sensor.fields_updated == bits, f"step {k}: {sensor.fields_updated:#x}"
        assert sensor.id == 0
        if gps_step:
            gps = msgs[-3]
            assert gps.time_usec == t and gps.fix_type == 3 and gps.satellites_visible == 10
            assert abs(gps.lat - 473977420) < 20 and abs(gps.lon - 85455940) < 30
            assert abs(gps.alt - 488000) < 300  # mm
        hsq = msgs[0]
        assert (hsq.lat, hsq.lon, hsq.alt) == (473977420, 85455940, 488000)
        assert hsq.attitude_quaternion == [1.0, 0.0, 0.0, 0.0]
        assert hsq.zacc == round(-VEHICLE.gravity / 9.80665 * 1000)  # mG, true specific force
        accels.append((sensor.xacc, sensor.yacc, sensor.zacc))
        times.append(t)
        if bits & 0x1C0:
            field = math.hypot(sensor.xmag, sensor.ymag, sensor.zmag)
            assert field == pytest.approx(0.4843, abs=0.1)  # gauss
        if bits & 0x1A00:
            isa_hpa = 1013.25 * (1.0 - 0.0065 * 488.0 / 288.15) ** 5.255877  # ISA at 488 m AMSL
            assert sensor.abs_pressure == pytest.approx(isa_hpa, abs=0.05)  # hPa (noise 1 Pa)
            assert sensor.pressure_alt == pytest.approx(488.0, abs=1.0)  # m
            assert sensor.temperature == pytest.approx(15.0 - 0.0065 * 488, abs=0.05)  # degC
    assert np.all(np.diff(times) == 4000) and times[0] == 0
    mean = np.mean(accels, axis=0)
    assert mean == pytest.approx([0.0, 0.0, -9.8], abs=0.05)  # m/s^2 at rest (noise 0.1, bias 0.03)
    assert np.std(np.array(accels)[:, 2]) == pytest.approx(0.1, rel=0.3)  # the realistic preset is noisy


def test_accel_and_gyro_clamped_as_px4_does(start_sitl, raw_companion, tmp_path):
    light = tmp_path / "light.yaml"
    text = (vehicles_dir() / "fang-chen-buaa.yaml").read_text()
    light.write_text(text.replace("mass: 1.4 ", "mass: 0.1 ", 1))  # 3 g of thrust becomes 45 g
    assert load_vehicle(light).mass == 0.1
    sitl = start_sitl("--vehicle", str(light), *IN_AIR, "--initial-position", "0,0,-100")
    companion = raw_companion(sitl.hil)
    frames = companion.connect()
    accel_limit, gyro_limit = f32(16 * 9.80665), f32(math.radians(2000.0))
    clamped_accel = clamped_gyro = False
    for _ in range(120):
        frames = companion.step([0.0, 1.0, 1.0, 0.0])  # motors 2, 3: roll right, climb
        hsq, sensor = frames[0][0], frames[-1][0]
        assert -accel_limit <= sensor.zacc <= accel_limit and abs(sensor.xgyro) <= gyro_limit
        clamped_accel |= sensor.zacc == -accel_limit
        if hsq.rollspeed > gyro_limit * 1.01:  # the truth is not clamped, the sensor is
            assert sensor.xgyro == gyro_limit
            clamped_gyro = True
    assert clamped_accel and clamped_gyro
