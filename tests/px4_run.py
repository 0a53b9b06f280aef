"""Test helpers for real PX4: `quadsr px4` as a child process, and a ground station over PX4's GCS link."""

from __future__ import annotations

import math
import re
import select
import sys
import threading
import time
from pathlib import Path

from pymavlink import mavutil

from quadsr.child_process import OutputProcess

REPO = Path(__file__).resolve().parent.parent
PX4_DIR = REPO.parent / "shared" / "px4"
STARTED = re.compile(r"started PX4 \(pid (\d+)\) and the SITL \(pid (\d+)\)")
INSTANCE = re.compile(r"using PX4 instance (\d+)")
mav = mavutil.mavlink


class QuadsrPx4(OutputProcess):
    """A running `quadsr px4` (PX4 + quadsr's SITL), its output lines, its instance and its children's pids.
    Give `--instance FIRST-LAST`: it takes a free instance and holds it, so parallel runs never share one."""

    def __init__(self, *flags: str):
        super().__init__([sys.executable, "-m", "quadsr.cli", "px4", *flags], cwd=REPO)
        self.instance = int(self.wait_for(INSTANCE, 60.0).group(1))
        m = self.wait_for(STARTED, 60.0)
        self.px4_pid, self.sitl_pid = int(m.group(1)), int(m.group(2))

    def wait_for(self, pattern: str | re.Pattern, timeout: float) -> re.Match:
        """The first output line matching pattern; fails after timeout s wall or when the process ended."""
        m = self.find(pattern, timeout)
        if m is None:
            raise AssertionError(f"quadsr px4 printed no line matching {pattern!r} within {timeout} s "
                                 f"(exit {self.proc.poll()}):\n{self.output}")
        return m

    def stop(self, timeout: float = 30.0) -> int:
        """SIGTERM, wait (SIGKILL after timeout s), the exit code."""
        return super().stop(timeout)


def gone(pid: int) -> bool:
    """True if no live process has this pid (a zombie counts as gone)."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split(")")[-1].split()[0] == "Z"
    except FileNotFoundError:
        return True


class Gcs:
    """A ground station on PX4's GCS link (it answers the first local sender), driven by simulated time.
    Once connected it heartbeats from a thread every 50 ms of wall time, so that PX4 in lockstep at up to
    about 20x real time still hears one a second of its clock (its ground-station-lost check, COM_DL_LOSS_T,
    runs on its clock) while the test reads files or waits."""

    def __init__(self, port: int, sysid: int):
        self.sysid = sysid
        self.conn = mavutil.mavlink_connection(f"udpout:127.0.0.1:{port}", source_system=245,
                                               source_component=190)
        self.sim_ms = 0  # PX4's time_boot_ms (simulated time in lockstep) of the last message seen
        self.position: tuple[float, float, float] | None = None  # NED m, PX4's estimate
        self.armed = False
        self.custom_mode: int | None = None
        self.landed_state = 0
        self._send = threading.Lock()  # the heartbeat thread and commands share the socket
        self._closing = threading.Event()
        self._heart: threading.Thread | None = None

    def recv(self, timeout: float = 1.0):
        """One message from PX4 (None after timeout s wall); keeps sim time, position, armed, landed."""
        msg = self.conn.recv_match(blocking=timeout > 0, timeout=timeout)
        if msg is None or msg.get_srcSystem() != self.sysid:
            return None
        kind = msg.get_type()
        if hasattr(msg, "time_boot_ms"):
            self.sim_ms = max(self.sim_ms, msg.time_boot_ms)
        if kind == "LOCAL_POSITION_NED":
            self.position = (msg.x, msg.y, msg.z)
        elif kind == "HEARTBEAT" and msg.get_srcComponent() == 1:
            self.armed = bool(msg.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED)
            self.custom_mode = msg.custom_mode
        elif kind == "EXTENDED_SYS_STATE":
            self.landed_state = msg.landed_state
        return msg

    def drain(self) -> None:
        """Read every message already queued, so that what follows is PX4's latest news."""
        for _ in range(1_000_000):
            msg = self.conn.recv_match(blocking=False)
            if msg is None and not select.select([self.conn.port], [], [], 0)[0]:
                return

    def connect(self, wall_timeout: float = 30.0) -> None:
        """Heartbeats until PX4 answers with its own."""
        deadline = time.monotonic() + wall_timeout
        while time.monotonic() < deadline:
            self._heartbeat()
            msg = self.recv(0.5)
            if msg is not None and msg.get_type() == "HEARTBEAT":
                self._heart = threading.Thread(target=self._beat, daemon=True)
                self._heart.start()
                return
        raise AssertionError(f"no HEARTBEAT from PX4 (sysid {self.sysid}) within {wall_timeout} s")

    def _heartbeat(self) -> None:
        with self._send:
            self.conn.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)

    def _beat(self) -> None:
        while not self._closing.wait(0.05):
            try:
                self._heartbeat()
            except OSError:  # PX4 gone (a test kills it): keep quiet until closed
                pass

    def command(self, cmd: int, *params: float, wall_timeout: float = 20.0) -> int:
        """COMMAND_LONG to PX4; its COMMAND_ACK result (re-sent every 0.5 s wall until acknowledged)."""
        p = list(params) + [0.0] * (7 - len(params))
        deadline = time.monotonic() + wall_timeout
        while time.monotonic() < deadline:
            with self._send:
                self.conn.mav.command_long_send(self.sysid, 1, cmd, 0, *p)
            until = time.monotonic() + 0.5
            while time.monotonic() < until:
                msg = self.recv(0.1)
                if msg is not None and msg.get_type() == "COMMAND_ACK" and msg.command == cmd:
                    return msg.result
        raise AssertionError(f"no COMMAND_ACK for command {cmd} within {wall_timeout} s")

    def run_until(self, done, sim_s: float, wall_timeout: float = 120.0) -> None:
        """Read messages until done(self) is true; fails after sim_s of simulated time (or the wall bound)."""
        # PX4's clock at the first message read here that carries it: self.sim_ms may be older news (a message
        # without time_boot_ms first, e.g. SERVO_OUTPUT_RAW, would start the count from a stale clock)
        start = None
        deadline = time.monotonic() + wall_timeout
        seen: dict[str, int] = {}
        while not done(self):
            msg = self.recv(0.5)
            if msg is not None:
                seen[msg.get_type()] = seen.get(msg.get_type(), 0) + 1
                if start is None and hasattr(msg, "time_boot_ms"):
                    start = msg.time_boot_ms
            if (start is not None and self.sim_ms - start > sim_s * 1000.0) or time.monotonic() > deadline:
                raise AssertionError(f"not done within {sim_s} s simulated (or {wall_timeout} s wall); "
                                     f"position {self.position}, armed {self.armed}, mode "
                                     f"{self.custom_mode}, from {start} to {self.sim_ms} ms; messages {seen}")

    def arm(self, sim_s: float = 30.0) -> int:
        """Arm; asked again each simulated second while PX4 answers TEMPORARILY_REJECTED (its health checks
        settle for a few seconds after a landing), for at most sim_s. The last ack result."""
        start = self.sim_ms
        while True:
            result = self.command(mav.MAV_CMD_COMPONENT_ARM_DISARM, 1)
            if result != mav.MAV_RESULT_TEMPORARILY_REJECTED or self.sim_ms - start > sim_s * 1000.0:
                return result
            again = self.sim_ms + 1000
            self.run_until(lambda g, again=again: g.sim_ms >= again, sim_s=5.0)

    def takeoff(self) -> int:
        """MAV_CMD_NAV_TAKEOFF to PX4's default altitude (MIS_TAKEOFF_ALT); the ack result."""
        nan = math.nan
        return self.command(mav.MAV_CMD_NAV_TAKEOFF, nan, 0, 0, nan, nan, nan, nan)

    def close(self) -> None:
        """Stop heartbeating and close the socket."""
        self._closing.set()
        if self._heart is not None:
            self._heart.join()
        self.conn.close()
