"""Messaging cost of the HIL link: per-frame encode/parse, and loopback ping-pong round trips per second.

Prints, in one run:
  - encode and parse microseconds per frame: bridge.framing vs pymavlink (pack / parse_buffer / decode);
  - a bare pymavlink HIL_SENSOR -> HIL_ACTUATOR_CONTROLS ping-pong over UDP loopback (two processes):
    the messaging ceiling;
  - the same ping-pong with bridge.link.UdpLink on both sides, and its ratio to the ceiling;
  - a full step datagram (HIL_STATE_QUATERNION, LOCAL_POSITION_NED, 4x RAW_RPM, HIL_SENSOR) answered by a
    bridge.lockstep.LockstepClient, and its ratio to the ceiling.
Each figure is the median of --repeats runs. On a shared machine wall-clock rates swing with the load, so the
CPU microseconds each process spends per round trip are printed too (Linux /proc): they are what the
messaging costs, whatever else runs.

    python bench/link_pingpong.py [--rounds 20000] [--repeats 3]
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
import os
import socket
import statistics
import sys
import time
import timeit
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import numpy as np  # noqa: E402
from pymavlink.dialects.v20 import common as mavlink  # noqa: E402

from bridge import messages as M  # noqa: E402
from bridge.framing import pack_frame, parse_datagram  # noqa: E402
from bridge.link import Endpoint, UdpLink  # noqa: E402
from bridge.stats import LinkStats  # noqa: E402

STEP = 4000


def _sensor(t: int) -> mavlink.MAVLink_hil_sensor_message:
    imu = M.ImuSample(t, np.array((0.01, -0.02, -9.8)), np.array((0.001, 0.002, -0.003)))
    return M.encode_hil_sensor(imu)


def _step_msgs(t: int) -> list:
    state = M.TrueState.from_quaternion(
        t, (1.0, 2.0, -3.0), (0.1, 0.2, -0.3), (1.0, 0.0, 0.0, 0.0), (0, 0, 0)
    )
    return [
        M.encode_hil_state_quaternion(state, 47.397742, 8.545594, 488.0),
        M.encode_local_position_ned(state),
        M.encode_raw_rpm((557.1, 557.2, 557.3, 557.4)),
        _sensor(t),
    ]


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system) a process has used so far (Linux)."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


class _Meter:
    """Wall time and both processes' CPU time over the measured round trips."""

    def __init__(self, child_pid: int):
        self.child_pid = child_pid

    def start(self) -> None:
        self.wall0 = time.perf_counter()
        self.cpu0 = time.process_time()
        self.child0 = _cpu_s(self.child_pid)

    def stop(self, rounds: int) -> tuple[float, float, float]:
        """(round trips/s, our CPU us per round trip, the child's CPU us per round trip)."""
        wall = time.perf_counter() - self.wall0
        ours = time.process_time() - self.cpu0
        child = _cpu_s(self.child_pid) - self.child0
        return rounds / wall, ours / rounds * 1e6, child / rounds * 1e6


# ---- per-frame costs ------------------------------------------------------------------------------------
def frame_costs(n: int = 20000) -> dict[str, float]:
    """Microseconds per frame for encode and parse, ours and pymavlink's."""
    mav = mavlink.MAVLink(None, 1, 51)
    msg = _sensor(123456)
    frame = msg.pack(mav)
    stats = LinkStats()

    def us(fn) -> float:
        return min(timeit.repeat(fn, number=n, repeat=5, timer=time.process_time)) / n * 1e6

    parser = mavlink.MAVLink(None)
    step_dgram = b"".join(pack_frame(m, 0, 1, 51) for m in _flatten(_step_msgs(4000)))
    return {
        "encode HIL_SENSOR, pymavlink pack": us(lambda: msg.pack(mav)),
        "encode HIL_SENSOR, bridge pack_frame": us(lambda: pack_frame(msg, 0, 1, 51)),
        "build+encode HIL_SENSOR from ImuSample (bridge)": us(lambda: pack_frame(_sensor(4000), 0, 1, 51)),
        "parse HIL_SENSOR, pymavlink parse_buffer": us(lambda: parser.parse_buffer(frame)),
        "parse HIL_SENSOR, pymavlink decode": us(lambda: mav.decode(bytearray(frame))),
        "parse HIL_SENSOR, bridge parse_datagram": us(lambda: parse_datagram(frame, stats)),
        "parse 7-frame step datagram, bridge (per datagram)": us(lambda: parse_datagram(step_dgram, stats)),
        "parse 7-frame step datagram, pymavlink parse_buffer": us(lambda: parser.parse_buffer(step_dgram)),
    }


def _flatten(msgs: list) -> list:
    out = []
    for m in msgs:
        out.extend(m if isinstance(m, list) else [m])
    return out


# ---- responders (the companion's seat), run in a child process ------------------------------------------
def _bare_responder(port_q: mp.Queue, rounds: int) -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    port_q.put(sock.getsockname()[1])
    mav = mavlink.MAVLink(None, 1, 1)
    controls = [0.5, 0.5, 0.5, 0.5] + [0.0] * 12
    for _ in range(rounds + 1):
        data, addr = sock.recvfrom(65535)
        for m in mav.parse_buffer(data) or []:
            if m.get_msgId() == mavlink.MAVLINK_MSG_ID_HIL_SENSOR:
                reply = mav.hil_actuator_controls_encode(m.time_usec, controls, M.ARMED_MODE, 1)
                sock.sendto(reply.pack(mav), addr)
                mav.seq = (mav.seq + 1) & 0xFF
    sock.close()


def _link_responder(port_q: mp.Queue, rounds: int) -> None:
    link = UdpLink(Endpoint("127.0.0.1", 0), None, 1, 1)
    port_q.put(link.local.port)
    throttles = (0.5, 0.5, 0.5, 0.5)
    for _ in range(rounds + 1):
        for m in link.recv(5.0):
            if type(m) is M.HilSensor:
                link.send([M.encode_hil_actuator_controls(m.time_usec, throttles)])
    link.close()


def _lockstep_responder(port_q: mp.Queue, rounds: int) -> None:
    from bridge.lockstep import LockstepClient

    host_port = port_q.get()  # the sim side's port
    client = LockstepClient(f"udp:127.0.0.1:{host_port}", timeout=5.0)
    client.connect(5.0)
    for _ in range(rounds):
        client.step((0.5, 0.5, 0.5, 0.5))
    client.close()


# ---- the simulator's seat, in this process --------------------------------------------------------------
def bare_pingpong(rounds: int) -> tuple[float, float, float]:
    """Round trips/s: pymavlink pack + parse_buffer on both sides, raw sockets."""
    q: mp.Queue = mp.Queue()
    child = mp.Process(target=_bare_responder, args=(q, rounds))
    child.start()
    port = q.get(timeout=10)
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    mav = mavlink.MAVLink(None, 1, 51)
    target = ("127.0.0.1", port)
    t = 0
    meter = _Meter(child.pid)
    for i in range(rounds + 1):
        if i == 1:
            meter.start()  # the first round trip includes the child's start-up
        imu = M.ImuSample(t, (0.01, -0.02, -9.8), (0.001, 0.002, -0.003))
        sock.sendto(M.encode_hil_sensor(imu).pack(mav), target)
        mav.seq = (mav.seq + 1) & 0xFF
        while True:
            data, _ = sock.recvfrom(65535)
            msgs = mav.parse_buffer(data) or []
            if any(
                m.get_msgId() == mavlink.MAVLINK_MSG_ID_HIL_ACTUATOR_CONTROLS and m.time_usec == t
                for m in msgs
            ):
                break
        t += STEP
    result = meter.stop(rounds)
    child.join()
    sock.close()
    return result


def link_pingpong(rounds: int) -> tuple[float, float, float]:
    """Round trips/s: bridge.link.UdpLink on both sides, same two messages."""
    q: mp.Queue = mp.Queue()
    child = mp.Process(target=_link_responder, args=(q, rounds))
    child.start()
    port = q.get(timeout=10)
    link = UdpLink(None, Endpoint("127.0.0.1", port), 1, 51)
    t = 0
    meter = _Meter(child.pid)
    hac = M.HilActuatorControls
    for i in range(rounds + 1):
        if i == 1:
            meter.start()
        link.send([M.encode_hil_sensor(M.ImuSample(t, (0.01, -0.02, -9.8), (0.001, 0.002, -0.003)))])
        done = False
        while not done:
            for m in link.recv(5.0):
                if type(m) is hac and m.time_usec == t:
                    done = True
        t += STEP
    result = meter.stop(rounds)
    child.join()
    link.close()
    return result


def lockstep_pingpong(rounds: int) -> tuple[float, float, float]:
    """Steps/s: full step datagrams (7 frames) answered by a LockstepClient."""
    q: mp.Queue = mp.Queue()
    link = UdpLink(Endpoint("127.0.0.1", 0), None, 1, 51)
    child = mp.Process(target=_lockstep_responder, args=(q, rounds))
    child.start()
    q.put(link.local.port)
    t = 0
    hac = M.HilActuatorControls
    while not any(m.get_type() == "HEARTBEAT" for m in link.recv(10.0)):
        pass
    link.send(_step_msgs(t))
    meter = _Meter(child.pid)
    meter.start()
    for _ in range(rounds):
        done = False
        while not done:
            for m in link.recv(5.0):
                if type(m) is hac and m.time_usec == t:
                    done = True
        t += STEP
        link.send(_step_msgs(t))
    result = meter.stop(rounds)
    child.join()
    link.close()
    return result


def main() -> None:
    """Print the figures."""
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rounds", type=int, default=20000)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()

    print("per-frame costs (CPU us, best of 5):")
    for name, value in frame_costs().items():
        print(f"  {name:55s} {value:7.2f}")

    def median(fn) -> tuple[float, float, float]:
        runs = [fn(args.rounds) for _ in range(args.repeats)]
        return tuple(statistics.median(r[k] for r in runs) for k in range(3))

    rows = [
        ("bare pymavlink HIL_SENSOR/HIL_ACTUATOR_CONTROLS (ceiling)", median(bare_pingpong)),
        ("bridge UdpLink, same two messages", median(link_pingpong)),
        ("bridge 7-frame step datagram + LockstepClient", median(lockstep_pingpong)),
    ]
    bare = rows[0][1]
    print(f"loopback ping-pong, two processes, median of {args.repeats} x {args.rounds} round trips:")
    head = f"{'trips/s':>8s} {'ratio':>6s} {'CPU us/trip: sim side':>22s} {'companion':>10s} {'ratio':>6s}"
    print(f"  {'':55s} {head}")
    for name, (rate, cpu_sim, cpu_child) in rows:
        cpu_ratio = (bare[1] + bare[2]) / (cpu_sim + cpu_child)
        cpu = f"{cpu_sim:22.1f} {cpu_child:10.1f} {cpu_ratio:6.2f}"
        print(f"  {name:55s} {rate:8.0f} {rate / bare[0]:6.2f} {cpu}")
    print("  (ratio: relative to the bare ceiling; for CPU, the ceiling's total CPU over this row's)")


if __name__ == "__main__":
    main()
