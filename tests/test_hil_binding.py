"""The HIL link is bound to its companion (issue 16 item 2): a hijack over real UDP does not take the vehicle.

A second local socket sends HEARTBEATs and HIL_ACTUATOR_CONTROLS at full throttle, stamped with the step's
exact time_usec and with far-future ones, before every reply of the flying companion; the companion's own
far-future replies are refused too. Only after the companion has been silent past the failsafe bound may
another sender take over.
"""

from __future__ import annotations

import math

import pytest

from bridge.link import UdpLink
from bridge.messages import RPM_TO_RAD_S, encode_heartbeat, encode_hil_actuator_controls
from bridge.vehicle import load_vehicle
from sitl.status import parse_status

pytestmark = pytest.mark.e2e

CURVE = load_vehicle("fang-chen-buaa").motor_curve
IDLE = 0.3


def _rpm(frames) -> list[float]:
    return [m.frequency * RPM_TO_RAD_S for m, _ in frames if m.get_type() == "RAW_RPM"]


def test_a_second_sender_cannot_take_the_vehicle_until_the_companion_is_silent(start_sitl, raw_companion):
    # a 3 s bound: a loaded machine that stalls the test for a second must not trip the failsafe mid-loop
    sitl = start_sitl("--sensors", "ideal", "--lockstep-timeout", "3", "--status-interval", "0.2")
    companion = raw_companion(sitl.hil)
    hijacker = UdpLink(remote=sitl.hil, system_id=1, component_id=1)
    try:
        frames = companion.connect()
        for k in range(150):  # 30 motor time constants
            t = frames[-1][0].time_usec
            hijacker.send([encode_heartbeat(), encode_hil_actuator_controls(t, [1.0] * 4),
                           encode_hil_actuator_controls(t + 4000 * (k + 1), [1.0] * 4)])
            # the companion's own far-future stamp (no such step was sent), throttles that would be counted
            companion.reply(2**62, [math.nan, math.inf, 2.0, -1.0])
            frames = companion.step([IDLE] * 4, timeout=5.0)
            assert frames[-1][0].time_usec == t + 4000
        assert _rpm(frames) == pytest.approx([CURVE.speed_for_throttle(IDLE)] * 4, rel=1e-6)
        assert not hijacker.recv_frames(0.05), "the SITL answered the hijacker"
        line = sitl.wait_for(r"foreign=\d+", start=len(sitl.lines)).string
        counted = parse_status(line)
        assert int(counted["foreign"]) >= 450 and int(counted["stale"]) >= 150, line
        assert counted["nonfinite"] == counted["clamped"] == "0", line  # a dropped frame's values: unused

        # The companion falls silent: past the failsafe bound another sender may take over.
        start = len(sitl.lines)
        sitl.wait_for("FAILSAFE", timeout=10.0, start=start)
        got = []
        for _ in range(50):
            hijacker.send([encode_heartbeat()])
            got = hijacker.recv_frames(0.2)
            if got:
                break
        assert got and got[-1][0].get_type() == "HIL_SENSOR", "a new companion could not take over"
        t = got[-1][0].time_usec
        hijacker.send([encode_hil_actuator_controls(t, [IDLE] * 4)])
        sitl.wait_for("actuator commands resumed", timeout=10.0, start=start)
        assert sitl.proc.poll() is None
    finally:
        hijacker.close()
