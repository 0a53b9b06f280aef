"""bridge.messages: every encoder/decoder through real MAVLink bytes, with units and bitmasks checked."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from bridge import messages as M
from bridge.framing import pack_frame, parse_datagram, split_datagram
from bridge.stats import LinkStats


def _wire(*msgs):
    """Messages after a trip through one datagram of real frames (packed by us, decoded from bytes)."""
    flat = []
    for m in msgs:
        flat.extend(m if isinstance(m, list) else [m])
    data = b"".join(pack_frame(m, i, 1, 51) for i, m in enumerate(flat))
    stats = LinkStats()
    out = [m for m, _ in parse_datagram(data, stats)]
    assert stats.dropped == 0 and len(out) == len(flat)
    # pymavlink's own parser must agree on every field
    ref = mavlink.MAVLink(None).parse_buffer(data)
    assert [r.to_dict() for r in ref] == [m.to_dict() for m in out]
    return out


def _state(
    t=8000, pos=(1.0, -2.0, -3.5), vel=(0.25, -0.5, 1.25), q=(1.0, 0.0, 0.0, 0.0), rates=(0.1, -0.2, 0.3)
):
    return M.TrueState.from_quaternion(t, pos, vel, q, rates)


# ---- HIL_SENSOR -------------------------------------------------------------------------------------------
def test_hil_sensor_units_round_trip():
    imu = M.ImuSample(12000, np.array((0.5, -0.25, -9.8)), np.array((1.0, -0.5, 0.25)))
    [msg] = _wire(M.encode_hil_sensor(imu))
    assert msg.get_type() == "HIL_SENSOR" and msg.id == 0
    out = M.decode_hil_sensor(msg)
    assert out.time_usec == 12000
    np.testing.assert_allclose(out.gyro, [1.0, -0.5, 0.25], rtol=1e-7)  # rad/s in, rad/s out
    np.testing.assert_allclose(out.accel, [0.5, -0.25, -9.8], rtol=1e-7)  # m/s^2
    assert out.mag is None and out.abs_pressure is None and out.temperature is None
    assert msg.fields_updated == M.ACCEL_BITS | M.GYRO_BITS == 0x3F


def test_hil_sensor_clamps_like_px4():
    imu = M.ImuSample(0, np.array((200.0, -200.0, 3.0)), np.array((50.0, -50.0, 1.0)))
    [msg] = _wire(M.encode_hil_sensor(imu))
    assert msg.xacc == pytest.approx(16 * 9.80665, rel=1e-6) and msg.yacc == pytest.approx(
        -16 * 9.80665, rel=1e-6
    )
    assert msg.zacc == pytest.approx(3.0)
    assert msg.xgyro == pytest.approx(math.radians(2000), rel=1e-6)
    assert msg.ygyro == pytest.approx(-math.radians(2000), rel=1e-6)
    assert msg.zgyro == pytest.approx(1.0)


def test_hil_sensor_mag_and_baro_bits_only_when_present():
    mag = np.array((0.21, 0.01, 0.43))
    [m_mag] = _wire(M.encode_hil_sensor(M.ImuSample(4000, np.zeros(3), np.zeros(3), mag=mag)))
    assert m_mag.fields_updated == 0x3F | 0x1C0
    [m_baro] = _wire(
        M.encode_hil_sensor(
            M.ImuSample(
                4000, np.zeros(3), np.zeros(3), abs_pressure=1007.5, pressure_alt=55.0, temperature=21.5
            )
        )
    )
    assert m_baro.fields_updated == 0x3F | 0x1A00
    out = M.decode_hil_sensor(m_baro)
    assert out.abs_pressure == pytest.approx(1007.5) and out.pressure_alt == pytest.approx(55.0)
    assert out.temperature == pytest.approx(21.5) and out.mag is None
    np.testing.assert_allclose(M.decode_hil_sensor(m_mag).mag, mag, rtol=1e-6)
    # an explicit fields_updated wins
    [m_fixed] = _wire(
        M.encode_hil_sensor(M.ImuSample(0, np.zeros(3), np.zeros(3), mag=mag, fields_updated=0x3F))
    )
    assert m_fixed.fields_updated == 0x3F and M.decode_hil_sensor(m_fixed).mag is None


def test_encoders_accept_a_leading_mavlink_object():
    mav = mavlink.MAVLink(None, 1, 51)
    imu = M.ImuSample(4000, (0.0, 0.0, -9.8), (0.0, 0.0, 0.0))
    assert M.encode_hil_sensor(mav, imu).to_dict() == M.encode_hil_sensor(imu).to_dict()


# ---- true state ---------------------------------------------------------------------------------------
def test_hil_state_quaternion_int_units_and_float_attitude():
    half = math.radians(30) / 2
    q = (math.cos(half), 0.0, 0.0, math.sin(half))  # yaw 30 deg
    state = _state(q=q)
    accel = (0.0, 0.0, -9.80665)
    [msg] = _wire(M.encode_hil_state_quaternion(state, 47.3977421, 8.5455941, 488.123, accel))
    assert msg.lat == 473977421 and msg.lon == 85455941  # degE7
    assert msg.alt == 488123  # mm
    assert (msg.vx, msg.vy, msg.vz) == (25, -50, 125)  # cm/s
    assert (msg.xacc, msg.yacc, msg.zacc) == (0, 0, -1000)  # mG
    np.testing.assert_allclose(msg.attitude_quaternion, q, rtol=1e-7)
    assert (msg.rollspeed, msg.pitchspeed, msg.yawspeed) == pytest.approx((0.1, -0.2, 0.3))
    assert msg.true_airspeed == round(100 * math.sqrt(0.25**2 + 0.5**2 + 1.25**2))


def test_local_position_ned_and_decoded_true_state():
    state = _state(t=1_234_567)
    hsq, lpn = _wire(
        M.encode_hil_state_quaternion(state, 47.0, 8.0, 500.0), M.encode_local_position_ned(state)
    )
    assert lpn.time_boot_ms == 1234
    truth = M.decode_true_state(hsq, lpn)
    np.testing.assert_allclose(truth.position, [1.0, -2.0, -3.5], rtol=1e-7)
    np.testing.assert_allclose(truth.velocity, [0.25, -0.5, 1.25], rtol=1e-7)
    assert truth.xi.shape == (12,)
    np.testing.assert_allclose(truth.xi[9:], [0.1, -0.2, 0.3], rtol=1e-6)
    # without LOCAL_POSITION_NED: position unknown, velocity from the cm/s ints
    coarse = M.decode_true_state(hsq)
    assert np.isnan(coarse.position).all()
    np.testing.assert_allclose(coarse.velocity, [0.25, -0.5, 1.25])


def test_euler_from_quaternion_zyx():
    phi, theta, psi = 0.1, -0.2, 0.3
    cr, sr = math.cos(phi / 2), math.sin(phi / 2)
    cp, sp = math.cos(theta / 2), math.sin(theta / 2)
    cy, sy = math.cos(psi / 2), math.sin(psi / 2)
    q = (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )
    np.testing.assert_allclose(M.euler_from_quaternion(q), [phi, theta, psi], atol=1e-12)


# ---- rotor speeds -------------------------------------------------------------------------------------
def test_rotor_speeds_as_raw_rpm():
    speeds = [557.1, 0.0, 1006.6, 300.25]
    msgs = _wire(M.encode_raw_rpm(np.array(speeds)))
    assert [m.index for m in msgs] == [0, 1, 2, 3]
    assert msgs[0].frequency == pytest.approx(557.1 * 60 / (2 * math.pi), rel=1e-6)  # rpm
    np.testing.assert_allclose(M.decode_raw_rpm(msgs), speeds, rtol=1e-6)
    assert np.isnan(M.decode_raw_rpm(msgs[:3])[3])
    # the design's encode_esc_status name gives the same four messages
    assert [m.to_dict() for m in M.encode_esc_status(4000, speeds)] == [
        m.to_dict() for m in M.encode_raw_rpm(speeds)
    ]


# ---- GPS ----------------------------------------------------------------------------------------------
def test_hil_gps_units():
    gps = M.GpsSample(100000, 47.3977421, 8.5455941, 488.5, np.array((3.0, 4.0, -0.5)), 3, 12, 0.5, 0.8)
    [msg] = _wire(M.encode_hil_gps(gps))
    assert (msg.lat, msg.lon, msg.alt) == (473977421, 85455941, 488500)
    assert (msg.vn, msg.ve, msg.vd, msg.vel) == (300, 400, -50, 500)  # cm/s
    assert (msg.eph, msg.epv) == (50, 80)  # cm
    assert msg.cog == round(math.degrees(math.atan2(4, 3)) * 100)  # cdeg
    assert (msg.fix_type, msg.satellites_visible) == (3, 12)
    out = M.decode_hil_gps(msg)
    assert out.lat == pytest.approx(47.3977421) and out.alt == pytest.approx(488.5)
    np.testing.assert_allclose(out.vel, [3.0, 4.0, -0.5])
    [still] = _wire(M.encode_hil_gps(M.GpsSample(0, 47.0, 8.0, 0.0, np.zeros(3))))
    assert still.cog == 65535  # unknown course when not moving


# ---- actuator controls --------------------------------------------------------------------------------
def test_hil_actuator_controls_as_px4_sends_them():
    [msg] = _wire(M.encode_hil_actuator_controls(8000, np.array((0.1, 0.2, 0.3, 0.4))))
    assert msg.time_usec == 8000
    assert msg.mode == mavlink.MAV_MODE_FLAG_SAFETY_ARMED | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED == 129
    assert msg.flags == 1
    assert msg.controls[:4] == pytest.approx([0.1, 0.2, 0.3, 0.4]) and msg.controls[4:] == [0.0] * 12
    cmd = M.decode_hil_actuator_controls(msg)
    assert cmd.lockstep and cmd.throttles.shape == (4,)
    [free] = _wire(M.encode_hil_actuator_controls(8000, [0.5] * 4, lockstep=False))
    assert free.flags == 0 and not M.decode_hil_actuator_controls(free).lockstep


# ---- assembling a step ---------------------------------------------------------------------------------
def _step(t, gps=False):
    state = _state(t=t)
    msgs = [
        M.encode_hil_state_quaternion(state, 47.0, 8.0, 500.0),
        M.encode_local_position_ned(state),
        M.encode_raw_rpm([550.0, 560.0, 570.0, 580.0]),
    ]
    if gps:
        msgs.append(M.encode_hil_gps(M.GpsSample(t, 47.0, 8.0, 503.5, np.zeros(3))))
    msgs.append(M.encode_hil_sensor(M.ImuSample(t, (0.0, 0.0, -9.8), (0.1, 0.2, 0.3))))
    return msgs


def test_observation_assembler_yields_one_observation_per_hil_sensor():
    asm = M.ObservationAssembler()
    status = mavlink.MAVLink_statustext_message(4, b"hello")
    frames = _wire(*_step(4000), status, *_step(8000, gps=True))
    obs = asm.feed(frames)
    assert [o.time_usec for o in obs] == [4000, 8000]
    first, second = obs
    assert first.t == pytest.approx(0.004)
    np.testing.assert_allclose(first.truth.xi[:3], [1.0, -2.0, -3.5], rtol=1e-7)
    np.testing.assert_allclose(first.rotor_speeds, [550.0, 560.0, 570.0, 580.0], rtol=1e-6)
    np.testing.assert_allclose(first.imu.gyro, [0.1, 0.2, 0.3], rtol=1e-6)
    assert first.gps is None and second.gps is not None and second.gps.alt == pytest.approx(503.5)
    assert [m.get_type() for m in second.extras] == ["STATUSTEXT"]


def test_observation_wind_is_the_wind_cov_of_its_own_step_from_frames_and_from_messages():
    wind = mavlink.MAVLink_wind_cov_message(8000, 5.0, -1.5, 0.25, 1.0, 0.5, 500.0, 0.0, 0.0)
    stale = mavlink.MAVLink_wind_cov_message(4000, 9.0, 9.0, 9.0, 1.0, 0.5, 500.0, 0.0, 0.0)
    msgs = _wire(*_step(4000), *_step(8000)[:-1], wind, _step(8000)[-1],
                 *_step(12000)[:-1], stale, _step(12000)[-1])
    data = b"".join(pack_frame(m, i, 1, 51) for i, m in enumerate(msgs))
    checked = split_datagram(data, LinkStats())
    for obs in (M.ObservationAssembler().feed(msgs), M.ObservationAssembler().feed_frames(checked)):
        assert [o.time_usec for o in obs] == [4000, 8000, 12000]
        assert obs[0].wind is None and obs[2].wind is None  # no WIND_COV, or one of another step
        np.testing.assert_allclose(obs[1].wind, [5.0, -1.5, 0.25])
        assert all(not o.extras for o in obs)  # WIND_COV is part of the step, not an extra


def test_true_accelerations_belong_to_their_step_and_other_arrays_are_extras():
    """TRUE_ACC (DEBUG_FLOAT_ARRAY) of a step gives Observation.accelerations (NED m/s^2, FRD rad/s^2) from
    messages and from raw frames alike; one of another step is not taken, and a foreign array (another
    name) is an extra, not accelerations."""
    acc = M.encode_true_accelerations(8000, (0.5, -0.25, 9.75), (1.5, -2.0, 0.125))
    stale = M.encode_true_accelerations(4000, (7.0, 7.0, 7.0), (7.0, 7.0, 7.0))
    foreign = mavlink.MAVLink_debug_float_array_message(12000, b"OTHER", 0, [3.0] * 58)
    msgs = _wire(*_step(4000), *_step(8000)[:-1], acc, _step(8000)[-1],
                 *_step(12000)[:-1], stale, foreign, _step(12000)[-1])
    data = b"".join(pack_frame(m, i, 1, 51) for i, m in enumerate(msgs))
    checked = split_datagram(data, LinkStats())
    for obs in (M.ObservationAssembler().feed(msgs), M.ObservationAssembler().feed_frames(checked)):
        assert [o.time_usec for o in obs] == [4000, 8000, 12000]
        assert obs[0].accelerations is None and obs[2].accelerations is None
        np.testing.assert_array_equal(obs[1].accelerations, [0.5, -0.25, 9.75, 1.5, -2.0, 0.125])
        assert not obs[1].extras
        assert [(m.get_type(), m.name) for m in obs[2].extras] == [("DEBUG_FLOAT_ARRAY", "OTHER")]


def test_observation_assembler_does_not_mix_steps():
    asm = M.ObservationAssembler()
    old = _wire(*_step(4000))
    new_sensor = _wire(M.encode_hil_sensor(M.ImuSample(8000, (0.0, 0.0, -9.8), (0.0, 0.0, 0.0))))
    assert asm.feed(old[:-1]) == []  # step 4000 without its HIL_SENSOR
    [obs] = asm.feed(new_sensor)
    assert obs.time_usec == 8000 and obs.truth is None  # the 4000 truth is not passed off as 8000's


# ---- fast paths of the lockstep hot loop -------------------------------------------------------------
def _sanitize_reference(controls):
    """The throttle rule written plainly: NaN/inf -> 0 (counted), others clipped to [0, 1] (counted)."""
    out, nonfinite, clamped = [], 0, 0
    for value in list(controls)[:4]:
        v = float(value)
        if not math.isfinite(v):
            nonfinite, v = nonfinite + 1, 0.0
        elif not 0.0 <= v <= 1.0:
            clamped, v = clamped + 1, min(max(v, 0.0), 1.0)
        out.append(v)
    out += [0.0] * (4 - len(out))
    return tuple(out), nonfinite, clamped


def test_sanitize_throttles_fast_path_keeps_the_rule():
    """In-range float throttles take a shortcut; every input (NaN, inf, out of range, ints, numpy scalars,
    -0.0, short or long lists) must give the plain rule's values, types and counts."""
    rng = np.random.default_rng(13)
    specials = [math.nan, math.inf, -math.inf, -0.0, 0.0, 1.0, 1.0000001, -1e-300, 2, 0, np.float64(0.5),
                np.float32(0.25), True]
    for k in range(3000):
        n = 4 if k % 10 else int(rng.integers(0, 7))
        values = [float(rng.uniform(-0.2, 1.2)) if rng.random() < 0.8
                  else specials[int(rng.integers(len(specials)))] for _ in range(n)]
        got = M.sanitize_throttles(values)
        want = _sanitize_reference(values)
        assert got[1:] == want[1:], values
        assert [(type(v), repr(v)) for v in got[0]] == [(type(v), repr(v)) for v in want[0]], values


def test_unpack_frame_in_place_equals_padded_payload():
    """unpack_frame reads a full-length payload in place and pads a truncated one: both give the values of
    the payload pymavlink would decode (signed frames too)."""
    from bridge.framing import spec_for, unpack_frame
    from bridge.signing import Signing

    rng = np.random.default_rng(4)
    signing = Signing(bytes(range(32)))
    for k in range(200):
        values = (int(rng.integers(0, 2**40)), float(rng.normal()), float(rng.normal()) * (k % 3 != 0),
                  0.0 if k % 2 else float(rng.normal()))
        last = float(rng.normal()) if k % 2 else 0.0  # non-zero: a full payload, read in place
        msg = M.WindCov(values[0], values[1], values[2], values[3], 0.0, 0.0, 0.0, 0.0, last)
        frame = pack_frame(msg, k & 0xFF, 1, 51, signing if k % 4 < 2 else None)
        [(spec, raw, header_len, signature_len)] = split_datagram(frame, LinkStats())
        full = len(raw) - header_len - 2 - signature_len == spec.size
        assert full == bool(last)
        assert spec is spec_for(M.WindCov)
        decoded = mavlink.MAVLink(None).decode(bytearray(raw))
        assert unpack_frame(raw, header_len, signature_len, spec) == tuple(
            getattr(decoded, n) for n in M.WindCov.ordered_fieldnames)
