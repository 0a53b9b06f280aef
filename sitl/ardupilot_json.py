"""ArduPilot's JSON external-physics protocol (libraries/SITL/SIM_JSON.cpp): its servo packet and our reply.

ArduPilot sends one binary servo packet per physics step by UDP, little-endian:
    uint16 magic (18458: pwm[16]; 29569: pwm[32] with SERVO_32_ENABLE=1), uint16 frame_rate (Hz),
    uint32 frame_count, uint16 pwm[16 or 32] (us)
and waits for one JSON object between newlines, compact (ArduPilot reads it with strstr/sscanf):
    timestamp (s, sim time), imu.gyro (rad/s, FRD), imu.accel_body (specific force m/s^2, FRD),
    position (m, NED from home), velocity (m/s, NED), quaternion (w, x, y, z, body FRD -> earth NED).
"""

from __future__ import annotations

import struct
from typing import NamedTuple

from bridge.messages import ACCEL_LIMIT, GYRO_LIMIT

MAGIC_16 = 18458
MAGIC_32 = 29569
_HEAD = struct.Struct("<HHI")
_PACKETS = {MAGIC_16: struct.Struct("<HHI16H"), MAGIC_32: struct.Struct("<HHI32H")}
_SIZES = {MAGIC_16: _PACKETS[MAGIC_16].size, MAGIC_32: _PACKETS[MAGIC_32].size}
_MOTORS = struct.Struct("<HxxI4H")  # magic, frame_count and the first four PWM values (us)


class ServoPacket(NamedTuple):
    """One servo packet: ArduPilot's physics rate (Hz), its frame counter and the PWM outputs (us)."""

    frame_rate: int
    frame_count: int
    pwm: tuple[int, ...]


class BadPacket(ValueError):
    """A datagram that is not a servo packet; `reason` is the counter it belongs to (magic or size)."""

    def __init__(self, reason: str, detail: str):
        super().__init__(detail)
        self.reason = reason


def _magic_of(data: bytes) -> int:
    """The magic of a datagram that has a servo packet's magic and size; BadPacket('magic'|'size') if not."""
    n = len(data)
    if n < _HEAD.size:
        raise BadPacket("size", f"{n} bytes, shorter than a servo packet header")
    magic = data[0] | data[1] << 8
    size = _SIZES.get(magic)
    if size is None:
        raise BadPacket("magic", f"magic {magic}, expected {MAGIC_16} or {MAGIC_32}")
    if n != size:
        raise BadPacket("size", f"{n} bytes with magic {magic}, expected {size}")
    return magic


def parse_servo_packet(data: bytes) -> ServoPacket:
    """The servo packet in a datagram; BadPacket('magic'|'size') when it is not one."""
    values = _PACKETS[_magic_of(data)].unpack(data)
    return ServoPacket(values[1], values[2], values[3:])


def servo_motors(data: bytes) -> tuple[int, int, int, int, int]:
    """(frame_count, PWM of motors 1..4 in us) of a servo packet, checked as parse_servo_packet checks it;
    the JSON backend's per-frame path (one struct call, no tuple of all 16 or 32 channels)."""
    _magic_of(data)
    _, count, p1, p2, p3, p4 = _MOTORS.unpack_from(data)
    return count, p1, p2, p3, p4


def pack_servo_packet(frame_count: int, pwm: list[int] | tuple[int, ...], frame_rate: int = 1200) -> bytes:
    """A servo packet as ArduPilot sends it (pwm of 16 or 32 channels, us); for tests and tools."""
    magic = MAGIC_16 if len(pwm) == 16 else MAGIC_32
    if len(pwm) not in (16, 32):
        raise ValueError(f"a servo packet holds 16 or 32 PWM values, got {len(pwm)}")
    return _PACKETS[magic].pack(magic, frame_rate, frame_count, *pwm)


def throttles_from_pwm(
    pwm: tuple[int, ...], pwm_min: float, pwm_max: float
) -> tuple[float, float, float, float]:
    """Motor throttles in [0, 1] of the first four channels (us) over the range [pwm_min, pwm_max] (us)."""
    span = pwm_max - pwm_min
    out = []
    for p in pwm[:4]:
        s = (p - pwm_min) / span
        out.append(0.0 if s < 0.0 else (1.0 if s > 1.0 else s))
    return out[0], out[1], out[2], out[3]


_V3 = "[%.10g,%.10g,%.10g]"
_SENSOR_LINE = (
    '\n{"timestamp":%.6f,"imu":{"gyro":' + _V3 + ',"accel_body":' + _V3 + '},"position":' + _V3
    + ',"velocity":' + _V3 + ',"quaternion":[%.10g,%.10g,%.10g,%.10g]}\n'
)


def sensor_json(
    timestamp: float,
    gyro: tuple[float, float, float],
    accel: tuple[float, float, float],
    position: tuple[float, float, float],
    velocity: tuple[float, float, float],
    quaternion: tuple[float, float, float, float],
) -> bytes:
    """The reply line: timestamp (s, to the us), gyro FRD (rad/s), specific force FRD (m/s^2), NED position
    (m) and velocity (m/s), attitude quaternion (w, x, y, z); 10 significant digits, compact, between
    newlines (one % format: this runs once per 1 ms physics step)."""
    a, w = ACCEL_LIMIT, GYRO_LIMIT  # the IMU's full scale, as on the PX4 path (a touchdown reads past it)
    accel = tuple(a if v > a else (-a if v < -a else v) for v in accel)
    gyro = tuple(w if v > w else (-w if v < -w else v) for v in gyro)
    return (_SENSOR_LINE % (timestamp, *gyro, *accel, *position, *velocity, *quaternion)).encode("ascii")
