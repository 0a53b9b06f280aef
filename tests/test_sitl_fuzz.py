"""Bad input never stops `quadsr sitl`: 100,000+ bad datagrams, then it still steps correctly, all counted."""

from __future__ import annotations

import math
import socket
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from bridge.framing import pack_frame
from bridge.messages import RPM_TO_RAD_S, encode_hil_actuator_controls
from bridge.vehicle import load_vehicle
from sitl.status import parse_status

pytestmark = pytest.mark.e2e

CURVE = load_vehicle("fang-chen-buaa").motor_curve
KINDS = ("random", "truncated", "bad_crc", "unknown_id", "bad_throttle", "other_system", "other_message",
         "mutated")


def bad_datagrams(rng: np.random.Generator, n: int, step_datagram: bytes) -> list[tuple[str, bytes]]:
    """n bad datagrams of every kind (each one counted once by the SITL when it arrives)."""
    actuator = pack_frame(encode_hil_actuator_controls(0, [0.5] * 4), 0, 1, 1)
    out = []
    for i in range(n):
        kind = KINDS[i % len(KINDS)]
        if kind == "random":
            data = rng.bytes(int(rng.integers(1, 300)))
        elif kind == "truncated":
            data = actuator[: int(rng.integers(1, len(actuator)))]
        elif kind == "bad_crc":
            b = bytearray(actuator)
            b[int(rng.integers(10, len(b)))] ^= int(rng.integers(1, 256))
            data = bytes(b)
        elif kind == "unknown_id":
            payload = rng.bytes(int(rng.integers(1, 60)))
            msg_id = int(rng.integers(60000, 1 << 24))
            header = [0xFD, len(payload), 0, 0, 0, 1, 1, msg_id & 0xFF, (msg_id >> 8) & 0xFF, msg_id >> 16]
            data = bytes(header) + payload + rng.bytes(2)
        elif kind == "bad_throttle":  # stale (time 0) and NaN / inf / out of range
            bad = [math.nan, math.inf, -math.inf, 7.5, -3.0, 1e30]
            controls = [bad[int(j)] for j in rng.integers(0, len(bad), 4)]
            data = pack_frame(encode_hil_actuator_controls(0, controls), i & 0xFF, 1, 1)
        elif kind == "other_system":  # a far-future time: it would be a valid reply from the right system
            system = int(rng.integers(2, 256))
            data = pack_frame(encode_hil_actuator_controls(2**62, [1.0] * 4), i & 0xFF, system, 1)
        elif kind == "other_message":
            data = pack_frame(mavlink.MAVLink_system_time_message(i, i), i & 0xFF, 1, 1)
        else:  # a real step datagram with one byte flipped inside its first frame
            b = bytearray(step_datagram)
            b[int(rng.integers(1, 40))] ^= int(rng.integers(1, 256))
            data = bytes(b)
        out.append((kind, data))
    return out


def test_100k_bad_datagrams_are_counted_and_the_sitl_still_steps(start_sitl, raw_companion):
    sitl = start_sitl("--sensors", "ideal", "--status-interval", "0.5")
    companion = raw_companion(sitl.hil)
    fuzzer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    target = ("127.0.0.1", sitl.hil_port)
    frames = companion.connect()
    step_bytes = b"".join(f for _, f in frames)
    frames = companion.step([0.0] * 4)  # stepping: the SITL is bound to the companion
    rng = np.random.default_rng(2024)
    pool = bad_datagrams(rng, 4000, step_bytes)
    idle = 0.3
    idle_speed = CURVE.speed_for_throttle(idle)
    burst, sent = 100, 0
    by_kind = dict.fromkeys(KINDS, 0)
    t0 = time.monotonic()
    while sent < 100_000:
        start = int(rng.integers(0, len(pool) - burst))
        for kind, data in pool[start:start + burst]:  # a burst while the SITL waits for its answer
            fuzzer.sendto(data, target)
            by_kind[kind] += 1
        sent += burst
        previous = frames[-1][0].time_usec
        frames = companion.step([idle] * 4, timeout=5.0)
        assert frames[-1][0].time_usec == previous + 4000
        rpm = [m.frequency * RPM_TO_RAD_S for m, _ in frames if m.get_type() == "RAW_RPM"]
        if previous > 0.4e6:  # 20 motor time constants after the start
            assert rpm == pytest.approx([idle_speed] * 4, rel=1e-5), "fuzz frames must not reach the motors"
    fuzz_seconds = time.monotonic() - t0
    steps_during_fuzz = frames[-1][0].time_usec // 4000

    # The companion's own bad throttles: NaN/inf -> 0, out of [0, 1] -> clamped, each counted.
    for _ in range(100):  # 20 motor time constants
        frames = companion.step([math.nan, math.inf, 2.0, -1.0])
    rpm = [m.frequency * RPM_TO_RAD_S for m, _ in frames if m.get_type() == "RAW_RPM"]
    assert max(rpm[0], rpm[1], rpm[3]) < 1e-3 and rpm[2] == pytest.approx(CURVE.max_speed, rel=1e-6)

    # Afterwards it steps as before: exact time progression, sensible physics (a climb at 1.2x hover).
    climb = CURVE.throttle_for_speed(1.2 * load_vehicle("fang-chen-buaa").hover_speed)
    zs = []
    for _ in range(250):
        previous = frames[-1][0].time_usec
        frames = companion.step([climb] * 4)
        assert frames[-1][0].time_usec == previous + 4000
        zs.append(frames[1][0].z)
    assert np.all(np.isfinite(zs)) and zs[-1] < -0.5 and np.all(np.diff(zs[100:]) < 0)

    line = sitl.wait_for(r"cmds=(\d+)", start=len(sitl.lines), timeout=5.0).string
    status = parse_status(line)
    counted = {k: int(v) for k, v in status.items() if v.isdigit()}
    assert counted["cmds"] >= steps_during_fuzz + 350
    assert counted["nonfinite"] >= 200 and counted["clamped"] >= 200  # the companion's own
    for reason in ("garbage", "truncated", "bad_crc", "unknown_id", "wrong_system"):
        assert counted.get(reason, 0) > 1000, (reason, line)
    # Each bad datagram is one drop, except those whose frames are all valid (the fuzzer's time-0 commands,
    # SYSTEM_TIME): the SITL is bound to its companion, so each valid frame of the fuzzer's socket is foreign,
    # as are the 7 intact frames after the corrupted first frame of a mutated step datagram.
    expected = sent - by_kind["other_message"] - by_kind["bad_throttle"]
    assert expected <= counted["dropped"] <= expected * 1.002, line
    assert counted["foreign"] >= by_kind["bad_throttle"] + by_kind["other_message"] + 6 * by_kind["mutated"]
    assert fuzz_seconds < 40
    assert sitl.proc.poll() is None
    fuzzer.close()
