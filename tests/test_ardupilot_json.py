"""ArduPilot's JSON physics interface: the packet codec, and `quadsr sitl --ardupilot` over real UDP
(a separate process) answering servo packets in lockstep, re-sends, restarts and bad packets."""

from __future__ import annotations

import io
import json
import re
import socket
import subprocess
import sys
import threading
import time

import pytest

from bridge.link import Endpoint
from bridge.tlog import read_tlog
from bridge.vehicle import load_vehicle
from identification.readers.tlog import read_tlog_dataset
from sitl.ardupilot_json import (
    MAGIC_16,
    MAGIC_32,
    BadPacket,
    pack_servo_packet,
    parse_servo_packet,
    sensor_json,
    servo_motors,
    throttles_from_pwm,
)
from sitl.ardupilot_server import TLOG_BATCH_USEC, ArduPilotOptions, ArduPilotServer
from sitl.dynamics import Quadrotor
from tests.conftest import REPO

LISTENING = re.compile(r"listening for ArduPilot on udp:([\d.]+):(\d+)")
HOVER_PWM = 1000 + round(1000 * load_vehicle("fang-chen-buaa").motor_curve.throttle_for_speed(600.0))


def test_servo_packet_round_trip_16_and_32_channels():
    p16 = parse_servo_packet(pack_servo_packet(7, [1100 + i for i in range(16)], frame_rate=1200))
    assert (p16.frame_rate, p16.frame_count, p16.pwm[:3], len(p16.pwm)) == (1200, 7, (1100, 1101, 1102), 16)
    p32 = parse_servo_packet(pack_servo_packet(2**32 - 1, [1500] * 32))
    assert p32.frame_count == 2**32 - 1 and len(p32.pwm) == 32
    # the per-frame path reads the same frame count and motor channels
    assert servo_motors(pack_servo_packet(7, [1100 + i for i in range(16)])) == (7, 1100, 1101, 1102, 1103)
    assert servo_motors(pack_servo_packet(2**32 - 1, [1900, 1800, 1700, 1600] + [0] * 28)) == (
        2**32 - 1, 1900, 1800, 1700, 1600)


@pytest.mark.parametrize(
    ("data", "reason"),
    [
        (b"", "size"),
        (b"\x1a\x48\x00", "size"),
        (pack_servo_packet(1, [1500] * 16)[:-1], "size"),
        (pack_servo_packet(1, [1500] * 16) + b"\x00", "size"),
        (pack_servo_packet(1, [1500] * 32)[:40], "size"),
        ((MAGIC_16 + 1).to_bytes(2, "little") + bytes(38), "magic"),
        (b"GET / HTTP/1.0\r\n\r\n" + bytes(22), "magic"),
    ],
)
def test_bad_packets_are_refused_with_their_reason(data, reason):
    for parse in (parse_servo_packet, servo_motors):
        with pytest.raises(BadPacket) as info:
            parse(data)
        assert info.value.reason == reason
    assert MAGIC_32 != MAGIC_16


def test_pwm_maps_through_the_range_and_clips():
    assert throttles_from_pwm((1000, 1500, 2000, 2500, 1700), 1000, 2000) == (0.0, 0.5, 1.0, 1.0)
    assert throttles_from_pwm((900, 0, 1100, 1900), 1100, 1900) == (0.0, 0.0, 0.0, 1.0)


def test_sensor_json_is_compact_and_complete():
    line = sensor_json(0.001, (0.1, -0.2, 0.3), (0.0, 0.0, -9.8), (1.0, 2.0, -3.0), (0.5, 0.0, -0.1),
                       (1.0, 0.0, 0.0, 0.0))
    assert line.startswith(b"\n") and line.endswith(b"\n") and b" " not in line  # ArduPilot uses sscanf
    obj = json.loads(line)
    assert obj["timestamp"] == 0.001
    assert obj["imu"] == {"gyro": [0.1, -0.2, 0.3], "accel_body": [0.0, 0.0, -9.8]}
    assert obj["position"] == [1.0, 2.0, -3.0] and obj["quaternion"] == [1.0, 0.0, 0.0, 0.0]


class ArduPilotStandIn:
    """Sends servo packets as ArduCopter does (real UDP, ephemeral port) and reads the JSON answers."""

    def __init__(self, port: int):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(5.0)
        self.target = ("127.0.0.1", port)

    def send(self, data: bytes) -> None:
        self.sock.sendto(data, self.target)

    def frame(self, count: int, pwm4: tuple[int, int, int, int]) -> dict:
        self.send(pack_servo_packet(count, [*pwm4] + [0] * 12))
        return json.loads(self.sock.recv(4096))

    def close(self) -> None:
        self.sock.close()


def start_backend(log) -> tuple[subprocess.Popen, int]:
    """`quadsr sitl --ardupilot` on a free port with ideal sensors, logging to log; (process, its port)."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "quadsr.cli", "sitl", "--ardupilot", "udp:127.0.0.1:0", "--log", str(log),
         "--sensors", "ideal", "--status-interval", "0"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=REPO)
    return proc, int(LISTENING.search(proc.stdout.readline()).group(2))


@pytest.mark.e2e
def test_lockstep_resend_restart_and_bad_packets_over_udp(tmp_path):
    log = tmp_path / "truth.tlog"
    proc, port = start_backend(log)
    ap = None
    try:
        ap = ArduPilotStandIn(port)
        # bad packets first: dropped, counted, never answered, never stopping the server
        for bad in (b"junk", (MAGIC_16 + 3).to_bytes(2, "little") + bytes(38),
                    pack_servo_packet(0, [1500] * 16)[:-2]):
            ap.send(bad)
        hover = (HOVER_PWM,) * 4
        replies = [ap.frame(k, hover) for k in range(400)]
        stamps = [r["timestamp"] for r in replies]
        assert stamps[0] == pytest.approx(0.001) and stamps[-1] == pytest.approx(0.4)
        assert all(b - a == pytest.approx(0.001) for a, b in zip(stamps, stamps[1:], strict=False))
        # the same physics in-process gives the same state (1 ms steps, hover PWM through the motor curve),
        # each frame's PWM acting over the step after its answer (pipelined: a 1 ms actuator delay)
        quad = Quadrotor(load_vehicle("fang-chen-buaa"), 1000)
        throttle = (HOVER_PWM - 1000) / 1000
        quad.step((0.0,) * 4)  # the first answer comes before any PWM: the rotors' initial speed, 0, held
        for _ in range(399):
            quad.step((throttle,) * 4)
        assert replies[-1]["position"] == pytest.approx(list(quad.position), abs=1e-9)
        assert quad.position[2] < -0.01  # 600 rad/s is above hover: it climbed
        assert replies[-1]["imu"]["accel_body"][2] == pytest.approx(quad.specific_force_body()[2], abs=1e-8)
        # a re-sent frame gets the same answer, without a step
        assert ap.frame(399, hover) == replies[-1]
        # a skipped frame count steps once and counts the missed ones
        assert ap.frame(402, hover)["timestamp"] == pytest.approx(0.401)
        # frame_count going back: ArduPilot restarted, the vehicle is back on the ground at time 0.001
        again = ap.frame(0, (1000,) * 4)
        assert again["timestamp"] == pytest.approx(0.001) and again["position"][2] == pytest.approx(0.0)
        ap.frame(1, (1000,) * 4)
        # another ArduPilot process (a new source port), whatever its frame_count: a restart too
        other = ArduPilotStandIn(port)
        try:
            assert other.frame(5000, (1000,) * 4)["timestamp"] == pytest.approx(0.001)
        finally:
            other.close()
    finally:
        if ap is not None:
            ap.close()
        proc.terminate()
        out, _ = proc.communicate(timeout=20)
    assert proc.returncode == 0, out
    assert "ArduPilot restarted (frame 0 after 402)" in out
    exit_line = [line for line in out.splitlines() if line.endswith("(exit)")][-1]
    assert "ArduPilot restarted (a new sender 127.0.0.1:" in out
    for counter in ("packets=405", "resent=1", "missed=2", "restarts=2", "bad_magic=1", "bad_size=2",
                    "senders=2"):
        assert counter in exit_line, exit_line
    assert "Traceback" not in out

    # the truth .tlog reads like any quadsr flight: steps on the 4 ms grid with the commands
    ds = read_tlog_dataset(log)
    assert len(ds.t) > 50
    assert ds.u[:, 0].max() == pytest.approx(600.0, rel=0.02)  # true rotor speeds settle at 600 rad/s


@pytest.mark.e2e
def test_a_killed_backend_leaves_a_readable_truth_log(tmp_path):
    """The truth .tlog is written in batches of TLOG_BATCH_USEC of simulated time: SIGKILL loses at most that
    much, and the file reads as any quadsr flight."""
    log = tmp_path / "truth.tlog"
    proc, port = start_backend(log)
    ap = None
    try:
        ap = ArduPilotStandIn(port)
        frames = 450  # 0.45 s of 1 ms steps
        for k in range(frames):
            ap.frame(k, (HOVER_PWM,) * 4)
    finally:
        if ap is not None:
            ap.close()
        proc.kill()
        proc.wait(timeout=20)
    stamps = [m.time_usec * 1e-6 for _, m in read_tlog(log) if m.get_type() == "HIL_SENSOR"]
    assert stamps == pytest.approx([0.004 * k for k in range(len(stamps))])  # whole records, none lost
    assert frames * 1e-3 - TLOG_BATCH_USEC * 1e-6 <= stamps[-1] <= frames * 1e-3, stamps[-1]
    ds = read_tlog_dataset(log)
    assert ds.u[-1, 0] > 100.0  # the rotors were spinning up: commands and states both logged


def test_one_millisecond_steps_track_the_four_millisecond_physics():
    v = load_vehicle("fang-chen-buaa")
    fine, coarse = Quadrotor(v, 1000), Quadrotor(v)
    throttle = (0.75, 0.74, 0.76, 0.75)  # above hover, a little roll, pitch and yaw
    for _ in range(250):
        coarse.step(throttle)
        for _ in range(4):
            fine.step(throttle)
    assert fine.time_usec == coarse.time_usec == 1_000_000
    assert fine.position == pytest.approx(coarse.position, rel=0.01, abs=1e-3)  # RK4, 4 ms vs 1 ms
    assert fine.rates == pytest.approx(coarse.rates, rel=0.01, abs=1e-3)
    assert coarse.position[2] < -0.5  # it climbed
    with pytest.raises(ValueError, match="divide"):
        Quadrotor(v, 1500)


@pytest.mark.parametrize(
    ("flags", "message"),
    [
        (["--ardupilot", "udp:127.0.0.1"], "bad link address"),
        (["--ardupilot", "--mode", "realtime"], "--mode realtime does not apply with --ardupilot"),
        (["--ardupilot", "--offboard", "udp:127.0.0.1:14540"], "--offboard does not apply"),
    ],
)
def test_sitl_ardupilot_refuses_bad_flags(flags, message):
    run = subprocess.run([sys.executable, "-m", "quadsr.cli", "sitl", *flags], capture_output=True, text=True,
                         cwd=REPO, timeout=60)
    assert run.returncode == 2 and message in run.stderr and "Traceback" not in run.stderr, run.stderr


def test_server_says_when_ardupilot_falls_silent():
    out = io.StringIO()
    server = ArduPilotServer(ArduPilotOptions(vehicle=load_vehicle("fang-chen-buaa"),
                                              endpoint=Endpoint("127.0.0.1", 0), status_interval=0,
                                              silence_timeout=0.3), out=out)
    ap = ArduPilotStandIn(server.port)

    def ardupilot_then_silence():
        for k in range(10):
            ap.frame(k, (1500,) * 4)
        deadline = time.monotonic() + 20.0  # a failure bound only: the message comes 0.3 s after the last
        while "silent" not in out.getvalue() and time.monotonic() < deadline:
            time.sleep(0.05)
        server._stop = True

    sender = threading.Thread(target=ardupilot_then_silence, daemon=True)
    sender.start()
    assert server.run() == 0  # in the main thread: it installs its signal handlers
    sender.join(5)
    ap.close()
    text = out.getvalue()
    assert "ArduPilot silent for 0.3 s at t=0.010s (frame 9): stopped or killed?" in text, text
    assert text.count("silent") == 1 and text.rstrip().endswith("(exit)")


def test_a_frames_pwm_drives_the_step_after_its_answer():
    """Pipelined lockstep: the answer to frame k is computed before frame k arrives (so the server computes
    while ArduCopter runs its loop), and frame k's PWM acts from the time of that answer on."""
    def server() -> ArduPilotServer:
        options = ArduPilotOptions(vehicle=load_vehicle("fang-chen-buaa"), endpoint=Endpoint("127.0.0.1", 0),
                                   status_interval=0)
        return ArduPilotServer(options, out=io.StringIO())

    low, high = server(), server()
    sender = ("127.0.0.1", 9)
    try:
        for k in range(50):
            low.handle(pack_servo_packet(k, [HOVER_PWM] * 4 + [0] * 12), sender)
            high.handle(pack_servo_packet(k, [HOVER_PWM] * 4 + [0] * 12), sender)
            low.advance()
            high.advance()
        assert low.quad.time_usec == low.answered_usec + 1000 == 51_000  # computed one step ahead
        a = low.handle(pack_servo_packet(50, [1000] * 4 + [0] * 12), sender)
        b = high.handle(pack_servo_packet(50, [2000] * 4 + [0] * 12), sender)
        assert a == b  # frame 50's answer does not depend on frame 50's PWM
        low.advance()
        high.advance()
        a = json.loads(low.handle(pack_servo_packet(51, [HOVER_PWM] * 4 + [0] * 12), sender))
        b = json.loads(high.handle(pack_servo_packet(51, [HOVER_PWM] * 4 + [0] * 12), sender))
        assert b["imu"]["accel_body"][2] < a["imu"]["accel_body"][2] - 0.1  # but frame 51's does
    finally:
        low.close()
        high.close()


def test_logged_throttles_are_pymavlinks_hil_actuator_controls(tmp_path):
    """The truth .tlog's HIL_ACTUATOR_CONTROLS (packed by the server itself) decode as pymavlink's own, with
    the throttles that drove each step."""
    options = ArduPilotOptions(vehicle=load_vehicle("fang-chen-buaa"), endpoint=Endpoint("127.0.0.1", 0),
                               log=tmp_path / "t.tlog", status_interval=0)
    server = ArduPilotServer(options, out=io.StringIO())
    try:
        for k in range(12):
            server.handle(pack_servo_packet(k, [1250, 1500, 1750, 2000] + [0] * 12), ("127.0.0.1", 9))
            server.advance()
    finally:
        server.close()
    commands = [m for _, m in read_tlog(tmp_path / "t.tlog") if m.get_type() == "HIL_ACTUATOR_CONTROLS"]
    assert [m.time_usec for m in commands] == [0, 4000, 8000, 12000]
    assert commands[0].controls[:4] == [0.0] * 4  # the first step: before any PWM, the initial 0 held
    assert commands[1].controls[:4] == pytest.approx([0.25, 0.5, 0.75, 1.0])
    assert commands[1].controls[4:] == [0.0] * 12 and commands[1].flags == 1 and commands[1].mode == 129
