"""PX4's simulator transport, without PX4: a raw autopilot speaking MAVLink over real TCP and UDP sockets.

`quadsr sitl --hil tcp:...` listens like Gazebo for PX4's `simulator_mavlink -c`; `--hil udpout:...` sends
first as PX4's `-u` mode expects. Before the autopilot's first HIL_ACTUATOR_CONTROLS the vehicle steps freely
at zero throttle from time_usec > 0 (never a stamp twice); then lockstep; any system id is accepted.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import time

from conftest import REPO

from bridge.framing import decode_frame, split_stream
from bridge.link import UdpLink
from bridge.messages import encode_heartbeat, encode_hil_actuator_controls
from bridge.stats import LinkStats
from sitl.status import parse_status

PX4_SYSID = 53  # PX4 instance 52 sends from N+1


class TcpAutopilot:
    """The autopilot's side of PX4's TCP simulator link: a real TCP client, frames split from the stream."""

    def __init__(self, port: int):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=5.0)
        self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.buf = b""
        self.stats = LinkStats()
        self.seq = 0

    def messages(self, timeout: float = 5.0) -> list:
        """The messages of the next read that holds whole frames."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            self.sock.settimeout(max(deadline - time.monotonic(), 0.01))
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                break
            assert data, "the SITL closed the connection"
            frames, used = split_stream(self.buf + data, self.stats)
            self.buf = (self.buf + data)[used:]
            if frames:
                return [decode_frame(*f[1:], f[0]) for f in frames]
        raise AssertionError(f"nothing from the SITL within {timeout} s")

    def sensors(self, count: int, timeout: float = 10.0) -> list:
        """The next `count` HIL_SENSOR messages (nothing sent back)."""
        out: list = []
        deadline = time.monotonic() + timeout
        while len(out) < count:
            out += [m for m in self.messages(deadline - time.monotonic()) if m.get_type() == "HIL_SENSOR"]
        return out

    def send(self, msgs: list, sysid: int = PX4_SYSID) -> None:
        """Frames of msgs from (sysid, 1), written in one send."""
        link = UdpLink(system_id=sysid, component_id=1)
        link.seq = self.seq
        frames = link.pack(msgs)
        self.seq = link.seq
        link.close()
        self.sock.sendall(b"".join(frames))

    def close(self) -> None:
        """Close the connection."""
        self.sock.close()


def test_tcp_free_steps_then_lockstep_with_px4_sysid(start_sitl):
    sitl = start_sitl("--hil", "tcp:127.0.0.1:0", "--no-gcs", "--sensors", "ideal",
                      "--status-interval", "0.5")
    assert sitl.hil.startswith("tcp:")
    ap = TcpAutopilot(sitl.hil_port)
    sitl.wait_for("autopilot connected")
    # Free steps: from 4000 us on, 4000 us apart, each stamp once, HIL_SENSOR from the simulator's ids.
    first = ap.sensors(20)
    times = [m.time_usec for m in first]
    assert times[0] >= 4000
    assert all(b - a == 4000 for a, b in zip(times, times[1:], strict=False)), times
    assert first[0].get_srcSystem() == 1 and first[0].get_srcComponent() == 51
    # The autopilot's first actuator command (from sysid 53, split over two writes) switches to lockstep.
    frame = b"".join(UdpLink(system_id=PX4_SYSID).pack([encode_hil_actuator_controls(times[-1], [0.0] * 4)]))
    ap.sock.sendall(frame[:7])
    ap.sock.sendall(frame[7:])
    sitl.wait_for("first actuator command from the autopilot")
    # Drain what free stepping queued, then answer the newest step: exactly one new step per reply.
    last = ap.sensors(1)[-1].time_usec
    try:
        while True:
            last = max([m.time_usec for m in ap.messages(0.3) if m.get_type() == "HIL_SENSOR"] + [last])
    except AssertionError:
        pass
    for _ in range(50):
        ap.send([encode_hil_actuator_controls(last, [0.3] * 4)])
        got = ap.sensors(1)
        assert [m.time_usec for m in got] == [last + 4000]
        last = got[0].time_usec
    # A second connection cannot take the link over: closed at once, the autopilot keeps stepping.
    intruder = socket.create_connection(("127.0.0.1", sitl.hil_port), timeout=5.0)
    sitl.wait_for("refused a second connection")
    assert intruder.recv(1) == b""
    intruder.close()
    # Hostile bytes on the stream are dropped and counted; the link goes on.
    ap.sock.sendall(b"\x00garbage\xfd\x09\x00\x00\x00" + bytes(20))
    ap.send([encode_heartbeat()])
    for _ in range(5):
        ap.send([encode_hil_actuator_controls(last, [0.3] * 4)])
        last = ap.sensors(1)[0].time_usec
    line = sitl.wait_for(r"steps=.*dropped=[1-9]", timeout=10.0).string
    assert parse_status(line)["cmds"] != "0"
    # The autopilot goes away: a clear line; a new connection gets free steps again, later stamps only.
    ap.close()
    sitl.wait_for("autopilot disconnected")
    ap2 = TcpAutopilot(sitl.hil_port)
    again = ap2.sensors(3, timeout=15.0)
    assert again[0].time_usec > last
    ap2.close()
    assert sitl.stop() == 0


def test_udpout_sends_first_to_the_autopilot(start_sitl):
    px4 = UdpLink(local="udp:127.0.0.1:0", system_id=PX4_SYSID)
    try:
        sitl = start_sitl("--hil", f"udpout:127.0.0.1:{px4.local.port}", "--no-gcs", "--sensors", "ideal")
        assert "sending to the autopilot" in sitl.output
        times = []
        deadline = time.monotonic() + 10.0
        while len(times) < 5 and time.monotonic() < deadline:
            times += [m.time_usec for m in px4.recv(1.0) if m.get_type() == "HIL_SENSOR"]
        assert len(times) >= 5 and times[0] >= 4000 and len(set(times)) == len(times)
        px4.send([encode_hil_actuator_controls(times[-1], [0.0] * 4)])
        sitl.wait_for("first actuator command from the autopilot")
    finally:
        px4.close()


def test_bad_tcp_address_and_busy_port_are_user_errors():
    def run(*flags):
        return subprocess.run([sys.executable, "-m", "quadsr.cli", "sitl", "--no-gcs", *flags], cwd=REPO,
                              capture_output=True, text=True, timeout=60)

    bad = run("--hil", "tcp:127.0.0.1:notaport")
    assert bad.returncode == 2 and "bad TCP address" in bad.stderr and "Traceback" not in bad.stderr
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        taken = run("--hil", f"tcp:127.0.0.1:{busy.getsockname()[1]}")
    assert taken.returncode == 2 and "cannot listen on tcp:" in taken.stderr
