"""Failsafe of `quadsr sitl`: a silent companion gets motors off and a STATUSTEXT, then it can resume."""

from __future__ import annotations

import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from bridge.lockstep import LockstepClient
from bridge.messages import RPM_TO_RAD_S
from bridge.vehicle import load_vehicle
from sitl.status import parse_status

pytestmark = pytest.mark.e2e

SPIN = 0.7
SPIN_SPEED = load_vehicle("fang-chen-buaa").motor_curve.speed_for_throttle(SPIN)


def texts(frames) -> list[tuple[int, str]]:
    return [(m.severity, m.text) for m, _ in frames if m.get_type() == "STATUSTEXT"]


def rotor_speeds(frames) -> np.ndarray:
    return np.array([m.frequency * RPM_TO_RAD_S for m, _ in frames if m.get_type() == "RAW_RPM"])


def drain(companion, frames, quiet: float):
    """Read step datagrams until none comes for `quiet` s; return the last one's frames (and all texts)."""
    seen = []
    while True:
        try:
            frames = companion.step_datagram(quiet)
        except AssertionError:
            return frames, seen
        seen.extend(texts(frames))


def test_lockstep_failsafe_stops_motors_keeps_stepping_and_resumes(start_sitl, raw_companion):
    sitl = start_sitl("--lockstep-timeout", "0.6", "--sensors", "ideal", "--status-interval", "0.2")
    companion = raw_companion(sitl.hil)
    frames = companion.connect()
    for _ in range(50):
        frames = companion.step([SPIN] * 4)
    assert np.allclose(rotor_speeds(frames), SPIN_SPEED, rtol=1e-3)
    for _ in range(3):  # slow but within the wait bound (with room for a loaded machine): no failsafe
        time.sleep(0.15)
        frames = companion.step([SPIN] * 4)
        assert not texts(frames)
    t_silent = frames[-1][0].time_usec
    wall_silent = time.monotonic()
    again = companion.step_datagram(1.0)  # silent: the unanswered step is re-sent after 0.1 s (lost reply?)
    assert again[-1][0].time_usec == t_silent and 0.08 < time.monotonic() - wall_silent  # (late under load)
    first = companion.step_datagram(1.0, after=t_silent)  # the first failsafe step, after the 0.6 s bound
    assert 0.58 < time.monotonic() - wall_silent  # not before the bound (later on a loaded machine)
    assert first[-1][0].time_usec == t_silent + 4000
    assert texts(first) == [(mavlink.MAV_SEVERITY_WARNING, "quadsr failsafe: no reply for 0.6 s, motors off")]
    time.sleep(0.5)  # ... and it keeps stepping at wall-clock pace with the motors off
    frames, _ = drain(companion, first, quiet=0.002)  # what is queued (steps come every 4 ms)
    stepped = (frames[-1][0].time_usec - first[-1][0].time_usec) * 1e-6
    assert 0.2 < stepped < time.monotonic() - wall_silent - 0.58  # wall-clock pace at most (load slows it)
    assert np.all(rotor_speeds(frames) < 1.0)  # 25 motor time constants
    sitl.wait_for(r"phase=failsafe .*failsafe=ON")
    companion.reply(frames[-1][0].time_usec, [SPIN] * 4)  # an answer resumes lockstep
    frames, seen = drain(companion, frames, quiet=0.05)
    for _ in range(60):
        previous = frames[-1][0].time_usec
        frames = companion.step([SPIN] * 4)
        assert frames[-1][0].time_usec == previous + 4000
        seen.extend(texts(frames))
    assert (mavlink.MAV_SEVERITY_INFO, "quadsr failsafe: actuator commands resumed") in seen
    assert np.allclose(rotor_speeds(frames), SPIN_SPEED, rtol=1e-3)
    with pytest.raises(AssertionError):
        companion.step_datagram(0.25, after=frames[-1][0].time_usec)  # lockstep again: no step unanswered
    status = parse_status(sitl.wait_for(r"failsafes=", start=len(sitl.lines)).string)
    assert int(status["resent"]) >= 3 and int(status["cmds"]) >= 114


def test_a_lockstep_client_recovers_from_a_failsafe(start_sitl):
    sitl = start_sitl("--lockstep-timeout", "0.2", "--sensors", "ideal")
    with LockstepClient(sitl.hil, timeout=2.0) as client:
        client.connect(10.0)
        for _ in range(50):
            client.step([SPIN] * 4)
        time.sleep(0.4)
        for _ in range(300):
            obs = client.step([SPIN] * 4)
        assert client.status_texts[0] == "quadsr failsafe: no reply for 0.2 s, motors off"
        assert any("resumed" in t for t in client.status_texts)
        for _ in range(100):
            previous = obs.time_usec
            obs = client.step([SPIN] * 4)
            assert obs.time_usec == previous + 4000
        time.sleep(0.05)  # lockstep pace, not wall-clock pace: a pause inside the 0.2 s bound costs no step
        previous = obs.time_usec
        obs = client.step([SPIN] * 4)
        assert obs.time_usec == previous + 4000
    assert np.allclose(obs.rotor_speeds, SPIN_SPEED, rtol=1e-3)


def test_a_new_companion_in_failsafe_gets_lockstep_from_the_step_it_answers(start_sitl):
    # The failsafe steps at wall pace; a companion that connects must not lose steps to it while its first
    # reply is on the way (a slow or loaded companion): its hello stops the pacing, its reply is applied to
    # the very step it answers, and every later step follows its commands.
    sitl = start_sitl("--lockstep-timeout", "0.2", "--sensors", "ideal")
    with LockstepClient(sitl.hil, timeout=2.0) as first:
        first.connect(10.0)
        for _ in range(10):
            first.step([SPIN] * 4)
    sitl.wait_for(r"phase=failsafe")
    with LockstepClient(sitl.hil, timeout=2.0) as late:
        start = late.connect(10.0)
        time.sleep(0.15)  # slow to answer, within the 0.2 s bound: no step may pass meanwhile
        obs = late.step([SPIN] * 4)
        assert obs.time_usec == start.time_usec + 4000
        for _ in range(40):
            previous = obs.time_usec
            obs = late.step([SPIN] * 4)
            assert obs.time_usec == previous + 4000
        assert any("resumed" in t for t in late.status_texts)
    assert np.allclose(obs.rotor_speeds, SPIN_SPEED, rtol=1e-3)


def test_realtime_failsafe_after_0_2_s_of_simulated_silence(start_sitl, raw_companion):
    sitl = start_sitl("--mode", "realtime", "--sensors", "ideal")
    companion = raw_companion(sitl.hil)
    frames = companion.connect()
    t_end = time.monotonic() + 0.3
    while time.monotonic() < t_end:  # the SITL paces; the companion answers every step
        companion.reply(frames[-1][0].time_usec, [SPIN] * 4)
        frames = companion.step_datagram()
    # the last reply answers the newest step (what a loaded companion fell behind on is read first), so the
    # silence starts at a known step: the SITL applies that reply at this step's time or a few steps later
    frames, _ = drain(companion, frames, quiet=0.002)
    companion.reply(frames[-1][0].time_usec, [SPIN] * 4)
    last_reply = frames[-1][0].time_usec
    assert np.allclose(rotor_speeds(frames), SPIN_SPEED, rtol=1e-3)
    warned_at = None
    t_end = time.monotonic() + 0.6
    while time.monotonic() < t_end:  # silent: steps keep coming at 250 Hz
        previous = frames[-1][0].time_usec
        frames = companion.step_datagram()
        assert frames[-1][0].time_usec == previous + 4000
        for severity, text in texts(frames):
            assert severity == mavlink.MAV_SEVERITY_WARNING and warned_at is None
            assert text == "quadsr failsafe: no command for 0.2 s, motors off"
            warned_at = frames[-1][0].time_usec
    assert warned_at is not None
    assert 200_000 <= warned_at - last_reply <= 240_000  # 0.2 s after the reply's arrival (<= 10 steps late)
    assert np.all(rotor_speeds(frames) < 1.0)
    resumed = False
    for _ in range(50):
        companion.reply(frames[-1][0].time_usec, [SPIN] * 4)
        frames = companion.step_datagram()
        resumed |= any(s == mavlink.MAV_SEVERITY_INFO and "resumed" in t for s, t in texts(frames))
    assert resumed
    assert np.all(rotor_speeds(frames) > 0.9 * SPIN_SPEED)
    assert "FAILSAFE" in sitl.output
