"""`quadsr fly --autopilot` when the autopilot refuses the switch to OFFBOARD.

Real PX4 accepts the switch whenever setpoints stream (which the companion ensures), so the refusal comes from
a stand-in autopilot here: a real UDP MAVLink peer in a thread that reports PX4's heartbeat and estimate and
answers DO_SET_MODE with MAV_RESULT_DENIED and a STATUSTEXT, as PX4 does when it refuses.
"""

from __future__ import annotations

import subprocess
import sys
import threading
import time

from conftest import REPO

from bridge.link import UdpLink
from bridge.messages import mavlink
from bridge.vehicle import load_vehicle
from identification.true_model import write_true_model


def refusing_autopilot(link: UdpLink, stop: threading.Event, seen: list[int]) -> None:
    """Heartbeat, estimate at 100 Hz of its clock (run 10x faster than real time), DO_SET_MODE denied."""
    boot_ms = 1000
    next_heartbeat = 0
    while not stop.is_set():
        boot_ms += 10
        msgs = [mavlink.MAVLink_attitude_quaternion_message(boot_ms, 1, 0, 0, 0, 0, 0, 0),
                mavlink.MAVLink_local_position_ned_message(boot_ms, 0, 0, 0, 0, 0, 0)]
        if boot_ms >= next_heartbeat:
            next_heartbeat = boot_ms + 1000
            msgs.append(mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4,
                mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, (4 << 16) | (3 << 24),  # AUTO.LOITER
                mavlink.MAV_STATE_STANDBY, 3))
        if link.peer is not None:
            link.send(msgs)
        for msg in link.recv(0.001):
            if msg.get_type() != "COMMAND_LONG":
                continue
            seen.append(msg.command)
            denied = msg.command == mavlink.MAV_CMD_DO_SET_MODE
            reply = [mavlink.MAVLink_command_ack_message(
                msg.command, mavlink.MAV_RESULT_DENIED if denied else mavlink.MAV_RESULT_ACCEPTED)]
            if denied:
                reply.insert(0, mavlink.MAVLink_statustext_message(
                    mavlink.MAV_SEVERITY_CRITICAL, b"Switching to Offboard is currently not available"))
            link.send(reply)
        time.sleep(0.001)


def test_refused_offboard_switch_is_a_clear_message_and_exit_4(tmp_path):
    model = tmp_path / "true.yaml"
    write_true_model(load_vehicle("fang-chen-buaa"), model)
    link = UdpLink(local="udp:127.0.0.1:0", system_id=9, component_id=1)
    stop = threading.Event()
    seen: list[int] = []
    worker = threading.Thread(target=refusing_autopilot, args=(link, stop, seen), daemon=True)
    worker.start()
    try:
        done = subprocess.run(
            [sys.executable, "-m", "quadsr.cli", "fly", "--model", str(model), "--trajectory", "case2",
             "--autopilot", f"udp:127.0.0.1:{link.local.port}", "--out", str(tmp_path / "out"),
             "--no-progress"],
            cwd=REPO, capture_output=True, text=True, timeout=120)
    finally:
        stop.set()
        worker.join(5.0)
        link.close()
    assert done.returncode == 4, done.stdout + done.stderr
    assert "PX4 rejected the switch to OFFBOARD (MAV_RESULT_DENIED)" in done.stdout
    assert "Switching to Offboard is currently not available" in done.stdout
    assert "Traceback" not in done.stdout + done.stderr
    assert mavlink.MAV_CMD_COMPONENT_ARM_DISARM not in seen  # never armed after the refusal
