"""`quadsr sitl` end to end: CLI errors, connecting, determinism, the tlog, real time, the ground link."""

from __future__ import annotations

import math
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from bridge.framing import parse_datagram
from bridge.lockstep import LockstepClient
from bridge.stats import LinkStats
from bridge.tlog import read_tlog
from bridge.vehicle import load_vehicle
from tests.test_hil_frames import pymavlink_frames

pytestmark = pytest.mark.e2e

REPO = Path(__file__).resolve().parent.parent


def run_cli(*args: str, timeout: float = 60.0) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "quadsr.cli", "sitl", *args], capture_output=True, text=True,
                          timeout=timeout, cwd=REPO)


@pytest.mark.parametrize(
    ("args", "says"),
    [
        (["--vehicle", "no-such-vehicle"], "no-such-vehicle"),
        (["--hil", "tcp:localhost"], "tcp:localhost"),
        (["--initial-position", "1,2"], "--initial-position"),
        (["--signing-key", "/nonexistent/key.bin"], "/nonexistent/key.bin"),
        (["--lockstep-timeout", "-1"], "--lockstep-timeout"),
        (["--initial-rotor-speed", "fast"], "--initial-rotor-speed"),
        (["--mode", "turbo"], "--mode"),
    ],
)
def test_user_mistakes_exit_2_with_a_clear_message(args, says):
    result = run_cli("--no-gcs", "--hil", "udp:127.0.0.1:0", *args, timeout=30)
    assert result.returncode == 2, result.stdout + result.stderr
    assert says in result.stderr and "Traceback" not in result.stderr


def test_port_in_use_is_a_clear_error(udp_port):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", udp_port))
        result = run_cli("--hil", f"udp:127.0.0.1:{udp_port}", "--no-gcs")
    assert result.returncode == 2
    assert str(udp_port) in result.stderr and "Traceback" not in result.stderr


def test_waits_on_the_ground_until_a_companion_speaks(start_sitl, raw_companion):
    sitl = start_sitl("--status-interval", "0.2")
    sitl.wait_for(r"steps=0 .*phase=waiting")
    time.sleep(0.4)
    assert "phase=waiting" in sitl.status_lines()[-1] and " steps=0 " in sitl.status_lines()[-1]
    companion = raw_companion(sitl.hil)
    companion.hello()
    # no reply yet: the time-0 datagram is re-sent (every 0.1 s), never a later step
    times = [companion.step_datagram()[-1][0].time_usec for _ in range(4)]
    assert set(times) == {0}
    assert companion.step([0.0] * 4)[-1][0].time_usec == 4000


def test_sigint_and_sigterm_exit_0_with_a_readable_tlog(start_sitl, tmp_path):
    for signum in (signal.SIGINT, signal.SIGTERM):
        log = tmp_path / f"{signum}.tlog"
        sitl = start_sitl("--log", str(log))
        with LockstepClient(sitl.hil, timeout=5.0) as client:
            client.connect(10.0)
            for _ in range(100):
                client.step([0.2] * 4)
            sitl.signal(signum)
            assert sitl.proc.wait(10) == 0
        assert "(exit)" in sitl.output and "Traceback" not in sitl.output
        kinds = [m.get_type() for _, m in read_tlog(log)]
        assert kinds.count("HIL_ACTUATOR_CONTROLS") == 100 and kinds.count("HIL_SENSOR") >= 101


def test_tlog_is_read_by_mavlogdump_after_sigkill(start_sitl, tmp_path):
    log = tmp_path / "killed.tlog"
    sitl = start_sitl("--log", str(log))
    with LockstepClient(sitl.hil, timeout=5.0) as client:
        client.connect(10.0)
        for _ in range(200):
            client.step([0.5] * 4)
        sitl.proc.kill()
        sitl.proc.wait(10)
    mavlogdump = Path(sys.executable).parent / "mavlogdump.py"
    result = subprocess.run([sys.executable, str(mavlogdump), "--types", "HIL_SENSOR,HIL_ACTUATOR_CONTROLS",
                             str(log)], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert sum("HIL_ACTUATOR_CONTROLS" in line for line in lines) == 200
    # The kill may land between sending step 200 and logging it: the log holds at least up to step 199.
    assert sum("HIL_SENSOR" in line for line in lines) >= 200
    sensors = [m.time_usec for _, m in read_tlog(log) if m.get_type() == "HIL_SENSOR"]
    assert sorted(set(sensors))[:200] == list(range(0, 200 * 4000, 4000))


def fly(sitl, raw_companion, commands: np.ndarray) -> list[list[bytes]]:
    """Fly a command sequence with a raw companion; the payloads of every frame of every step's datagram."""
    companion = raw_companion(sitl.hil)
    frames = companion.connect()
    payloads = []
    for throttles in commands:
        payloads.append([f[10:-2] for _, f in frames])
        frames = companion.step(throttles)
    payloads.append([f[10:-2] for _, f in frames])
    return payloads


def test_lockstep_same_seed_same_commands_bit_identical_telemetry(start_sitl, raw_companion):
    rng = np.random.default_rng(11)
    hover = load_vehicle("fang-chen-buaa").motor_curve.throttle_for_speed(557.1)
    commands = np.clip(hover + 0.08 + 0.05 * rng.standard_normal((400, 4)), 0.0, 1.0)
    a, b, c = (start_sitl("--seed", seed) for seed in ("7", "7", "8"))
    first, second, other = (fly(s, raw_companion, commands) for s in (a, b, c))
    assert len(first) == 401 and sum(len(p) for p in first) > 400 * 7
    assert first == second
    assert first != other  # a different seed gives different sensor noise
    assert [p[:6] for p in first] == [p[:6] for p in other]  # ... but the same truth


def test_realtime_mode_steps_at_the_wall_clock_pace(start_sitl):
    sitl = start_sitl("--mode", "realtime")
    with LockstepClient(sitl.hil, timeout=5.0) as client:
        client.connect(10.0)
        client.step([0.0] * 4)
        t0, sim0 = time.monotonic(), client.observation.time_usec
        while time.monotonic() - t0 < 1.0:
            client.step([0.0] * 4)
        wall, sim = time.monotonic() - t0, (client.observation.time_usec - sim0) * 1e-6
    # paced by the wall clock: never ahead of it by more than the catch-up a lagging SITL may burst
    # (sitl.server.MAX_LAG_S, 0.1 s); behind it only as far as a loaded machine starves the SITL
    assert 0.5 * wall < sim <= wall + 0.1 + 0.008
    assert "FAILSAFE" not in sitl.output


@pytest.mark.parametrize("name,wind", [("fang-chen-buaa", None), ("fang-chen-aero", (5.0, -2.0, 0.5))])
def test_fast_hil_frames_equal_the_bridge_encoders(name, wind):
    """sitl.hil packs frames itself for speed: they must be pymavlink's bytes and decode to what
    bridge.messages would send (GPS and mag/baro steps, wind, states that saturate the ints, seq wrapping)."""
    from bridge.airframe import wind_config
    from bridge.link import UdpLink
    from sitl.dynamics import Quadrotor
    from sitl.hil import HilEncoder, reference_messages
    from sitl.sensors import SensorModel

    flow = None if wind is None else wind_config("test", wind, "light")  # with wind: WIND_COV in each step
    vehicle = load_vehicle(name).with_overrides(ground="none", initial_position=(10, -20, -30.0), wind=flow)
    quad = Quadrotor(vehicle)
    sensors = SensorModel(vehicle.sensors, vehicle.home, 5)
    rng = np.random.default_rng(2)
    with UdpLink(system_id=1, component_id=51) as link:
        link.seq = 230  # the sequence number wraps inside the run
        encoder = HilEncoder(vehicle.home, link)
        stats = LinkStats()
        for k in range(60):
            if k % 20 == 0:
                quad.reset(position=rng.normal(0, 50, 3), yaw=rng.uniform(-3, 3), roll=rng.uniform(-1, 1),
                           pitch=rng.uniform(-1, 1), velocity=rng.normal(0, 400, 3),
                           rates=rng.normal(0, 30, 3), rotor_speeds=rng.uniform(0, 1000, 4))
                sensors.reset()
            quad.step(rng.uniform(0, 1, 4))
            frame = sensors.sample(quad)
            seq = link.seq
            ours = encoder.step_frames(quad, frame)
            fast = [m for m, _ in parse_datagram(b"".join(ours), stats)]
            # byte for byte what pymavlink's own packer makes of the same messages and sequence numbers
            assert ours == pymavlink_frames(reference_messages(quad, frame, vehicle.home), seq, 1, 51)
            reference = link.pack(reference_messages(quad, frame, vehicle.home))
            slow = [m for m, _ in parse_datagram(b"".join(reference), stats)]
            assert [m.to_dict() for m in fast] == [m.to_dict() for m in slow]
            assert any(m.get_type() == "WIND_COV" for m in fast) == (wind is not None)
        assert stats.dropped == 0


class GroundStation:
    """A bare pymavlink GCS on a UDP port, receiving in a thread (the SITL sends first)."""

    def __init__(self, port: int):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.sock.settimeout(0.1)
        self.mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        self.mav.robust_parsing = True
        self.got: list = []
        self.sitl_addr = None
        self.running = True
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self) -> None:
        parser = mavlink.MAVLink(None)
        parser.robust_parsing = True
        while self.running:
            try:
                data, self.sitl_addr = self.sock.recvfrom(65535)
            except (TimeoutError, OSError):
                continue
            self.got.extend(parser.parse_buffer(data) or [])

    def of(self, kind: str, since: int = 0) -> list:
        return [m for m in self.got[since:] if m.get_type() == kind]

    def command(self, cmd: int, *params: float) -> None:
        msg = mavlink.MAVLink_command_long_message(1, 1, cmd, 0, *(list(params) + [0.0] * 7)[:7])
        self.sock.sendto(msg.pack(self.mav), self.sitl_addr)

    def close(self) -> None:
        self.running = False
        self.thread.join(2.0)
        self.sock.close()


def test_ground_link_acts_like_a_px4_vehicle(start_sitl, udp_port):
    gcs = GroundStation(udp_port)
    try:
        sitl = start_sitl("--gcs", f"udp:127.0.0.1:{udp_port}", "--sensors", "ideal")
        deadline = time.monotonic() + 20.0  # no companion yet: streams at wall-clock pace, 1 Hz heartbeat
        while len(gcs.of("HEARTBEAT")) < 2 and time.monotonic() < deadline:
            time.sleep(0.05)
        hb = gcs.of("HEARTBEAT")[0]
        assert (hb.type, hb.autopilot) == (mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4)
        assert not hb.base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        assert hb.get_srcSystem() == 1 and hb.get_srcComponent() == 1
        # ATTITUDE at 50 Hz of the wall clock it stamps (time_boot_ms): never faster; a slot a loaded machine
        # made late is skipped, not sent twice (measured here under load: 33 in the first 1.1 s), so the
        # count over wall time is no test; the exact rates are checked below in simulated time
        wait_t = np.diff([m.time_boot_ms for m in gcs.of("ATTITUDE")])
        assert len(wait_t) >= 10 and wait_t.min() >= 19, wait_t
        for kind in ("ATTITUDE_QUATERNION", "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT", "SYS_STATUS",
                     "HOME_POSITION"):
            assert gcs.of(kind), kind
        home = gcs.of("HOME_POSITION")[0]
        assert (home.latitude, home.longitude, home.altitude) == (473977420, 85455940, 488000)
        gcs.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAVLINK_MSG_ID_ATTITUDE, 100_000)
        gcs.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        gcs.command(mavlink.MAV_CMD_NAV_TAKEOFF)
        time.sleep(0.2)
        acks = {a.command: a.result for a in gcs.of("COMMAND_ACK")}
        assert acks == {
            mavlink.MAV_CMD_SET_MESSAGE_INTERVAL: mavlink.MAV_RESULT_ACCEPTED,
            mavlink.MAV_CMD_REQUEST_MESSAGE: mavlink.MAV_RESULT_ACCEPTED,
            mavlink.MAV_CMD_NAV_TAKEOFF: mavlink.MAV_RESULT_UNSUPPORTED,
        }
        assert gcs.of("AUTOPILOT_VERSION")[0].capabilities & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        start = len(gcs.got)
        throttle = load_vehicle("fang-chen-buaa").motor_curve.throttle_for_speed(600.0)
        with LockstepClient(sitl.hil, timeout=5.0) as client:  # 10 s of simulated time
            client.connect(10.0)
            for _ in range(2500):
                obs = client.step([throttle] * 4)
            time.sleep(0.3)
        # Rates in simulated time: LOCAL_POSITION_NED 50 Hz, ATTITUDE now 10 Hz, HEARTBEAT 1 Hz (armed).
        lpn_t = np.array([m.time_boot_ms for m in gcs.of("LOCAL_POSITION_NED", start)])
        att_t = np.array([m.time_boot_ms for m in gcs.of("ATTITUDE", start)])
        assert len(lpn_t) >= 500 and np.all(np.diff(lpn_t)[-490:] == 20)
        assert len(att_t) >= 100 and np.all(np.diff(att_t)[-95:] == 100)
        beats = gcs.of("HEARTBEAT", start)
        assert 9 <= len(beats) <= 12 and beats[-1].base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED
        last = gcs.of("LOCAL_POSITION_NED", start)[-1]
        assert last.z == pytest.approx(obs.truth.position[2], abs=0.1) and last.z < -1.0
        glob = gcs.of("GLOBAL_POSITION_INT", start)[-1]
        assert glob.relative_alt == pytest.approx(-last.z * 1000, abs=100)
        assert math.isclose(glob.alt, 488000 + glob.relative_alt, abs_tol=2)
    finally:
        gcs.close()
