"""A companion that was stalled (descheduled, or stopped) while the autopilot kept sending does not take the
stall for a lost link: the silence is confirmed by a read after the clock is taken. Real UDP sockets."""

from __future__ import annotations

import time

from bridge.link import UdpLink
from bridge.messages import mavlink
from bridge.offboard import OffboardLink


def _pair() -> tuple[UdpLink, OffboardLink]:
    """An 'autopilot' (system 1) listening on an ephemeral port and a companion's link to it, introduced."""
    autopilot = UdpLink(local="udp:127.0.0.1:0", system_id=1, component_id=1)
    companion = OffboardLink(f"udp:127.0.0.1:{autopilot.local.port}")
    companion.poll(0.0)  # its first heartbeat tells the autopilot where the companion is
    deadline = time.monotonic() + 5.0
    while not autopilot.recv(0.1) and time.monotonic() < deadline:
        companion.poll(0.0)
    heartbeat(autopilot)
    deadline = time.monotonic() + 5.0
    while companion.state.system_id is None and time.monotonic() < deadline:
        companion.poll(0.1)
    assert companion.state.system_id == 1
    return autopilot, companion


def heartbeat(autopilot: UdpLink) -> None:
    """The autopilot's HEARTBEAT (armed PX4 quadrotor) to its last peer."""
    autopilot.send(mavlink.MAVLink_heartbeat_message(
        mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, mavlink.MAV_MODE_FLAG_SAFETY_ARMED, 0,
        mavlink.MAV_STATE_ACTIVE, 3))


def test_a_stall_with_messages_queued_is_not_a_lost_link():
    autopilot, companion = _pair()
    read = companion.poll
    calls = []

    def stalled_poll(timeout: float = 0.0) -> list:
        if calls:
            return read(timeout)
        # the read found nothing; then this process stalled for 10 s while the autopilot went on sending
        calls.append(timeout)
        companion.state.last_heard = time.monotonic() - 10.0
        heartbeat(autopilot)
        time.sleep(0.05)
        return []

    companion.poll = stalled_poll
    try:
        assert not companion.silent(0.05, 2.0)
        assert time.monotonic() - companion.state.last_heard < 1.0  # the queued message was read
    finally:
        autopilot.close()
        companion.link.close()


def test_silence_past_the_limit_is_a_lost_link():
    autopilot, companion = _pair()
    try:
        assert not companion.silent(0.05, 0.2)  # heard just now
        time.sleep(0.3)
        assert companion.silent(0.05, 0.2)  # nothing for 0.35 s, nothing queued
        heartbeat(autopilot)
        time.sleep(0.05)
        assert not companion.silent(0.05, 0.2)
    finally:
        autopilot.close()
        companion.link.close()
