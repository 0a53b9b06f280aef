"""A companion's flight through PX4 OFFBOARD: the start-up sequence and the watch on what PX4 does meanwhile.

Shared by every client that flies through PX4's offboard link (controller.offboard_companion: the
model-derived controller; identification.offboard_excite: an excitation on body-rate setpoints), so both
start and stop the same way. Start: PX4's HEARTBEAT, its estimate requested (ATTITUDE_QUATERNION and
LOCAL_POSITION_NED at rate_hz of PX4's clock), level setpoints at zero thrust streamed for prestream_s of its
clock (PX4 switches to OFFBOARD only with a live setpoint stream), OFFBOARD, arm. Watch: the flight ends when
PX4 leaves OFFBOARD (its offboard-loss failsafe, a pilot or GCS), disarms, goes silent for link_timeout wall
s, or when this process sent no setpoint for longer than PX4's offboard-loss timeout of its clock.
"""

from __future__ import annotations

import time
from collections.abc import Callable

from bridge.messages import mavlink
from bridge.offboard import PX4, OffboardLink
from bridge.rotations import euler_from_quaternion, quaternion_from_euler

OFFBOARD_LOSS_MS = 1000  # PX4's COM_OF_LOSS_T default (1 s): setpoints older than this trip its failsafe


def result_name(result: int | None) -> str:
    """A COMMAND_ACK result as its MAV_RESULT name ('no acknowledgement' for None)."""
    if result is None:
        return "no acknowledgement"
    entry = mavlink.enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else str(result)


def said(link: OffboardLink) -> str:
    """'; PX4 said: ...' with the autopilot's newest three distinct STATUSTEXTs, or '' if it said none."""
    texts = list(dict.fromkeys(link.state.status_texts))[-3:]
    return (f"; {link.flavour.name} said: " + " | ".join(texts)) if texts else ""


def await_estimate(link: OffboardLink, connect_timeout: float, rate_hz: float, not_running: str,
                   no_estimate: Callable[[], str]) -> str:
    """Connect, ask for the attitude and local position at rate_hz and wait for both: '' or why not
    (`not_running` follows the connect timeout's message; `no_estimate()` says why none came; wall s)."""
    try:
        link.connect(connect_timeout)
    except TimeoutError as exc:
        return f"{exc}: {not_running}"
    for msg_id in (mavlink.MAVLINK_MSG_ID_ATTITUDE_QUATERNION, mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED):
        link.request_rate(msg_id, rate_hz)
    deadline = time.monotonic() + connect_timeout
    while link.state.position is None or link.state.quaternion is None:
        if time.monotonic() > deadline:
            return no_estimate()
        link.poll(0.1)
    return ""


def start_px4_offboard(link: OffboardLink, address: str, rate_hz: float, prestream_s: float,
                       connect_timeout: float, link_timeout: float) -> str:
    """Connect, request the estimate at rate_hz, pre-stream for prestream_s (PX4's clock), OFFBOARD, arm:
    '' when PX4 is armed in OFFBOARD, else why not (timeouts in wall s)."""
    why = await_estimate(
        link, connect_timeout, rate_hz, "is PX4 running (quadsr px4)? its offboard port is 14580+N",
        lambda: f"PX4 at {address} sent no position and attitude within {connect_timeout:g} s")
    if why:
        return why
    st = link.state
    yaw = float(euler_from_quaternion(st.quaternion)[2])
    level = quaternion_from_euler(0.0, 0.0, yaw)
    start_ms = st.time_boot_ms
    while st.time_boot_ms - start_ms < prestream_s * 1000.0:
        link.attitude_target(level, 0.0)
        if link.silent(0.05, link_timeout):
            return f"PX4 went silent for {link_timeout:g} s while setpoints were streamed"
    result = link.set_mode(PX4.offboard)
    if result != mavlink.MAV_RESULT_ACCEPTED:
        return f"PX4 rejected the switch to OFFBOARD ({result_name(result)}){said(link)}"
    result = link.arm()
    if result != mavlink.MAV_RESULT_ACCEPTED:
        link.set_mode(PX4.hold)
        return f"PX4 refused to arm ({result_name(result)}){said(link)}"
    return ""


class OffboardWatch:
    """Why an offboard flight must end now ('' while it may go on), from the autopilot's reports."""

    def __init__(self, link: OffboardLink, address: str, link_timeout: float):
        self.link = link
        self.address = address
        self.link_timeout = link_timeout  # wall s
        self.in_offboard = False  # the autopilot has reported its offboard mode since the flight began

    def poll(self, timeout: float = 0.05) -> str:
        """Read the link (up to timeout wall s) and check it: '' or why the flight ends."""
        link, st = self.link, self.link.state
        f = link.flavour
        if link.silent(timeout, self.link_timeout):
            return f"link lost: nothing from {f.name} at {self.address} for {self.link_timeout:g} s"
        if link.in_mode(f.offboard):
            self.in_offboard = True
        elif self.in_offboard:
            return (f"{f.name} left {f.offboard.name} (custom mode {st.custom_mode:#x}): its offboard-loss "
                    f"failsafe or a pilot/GCS switch{said(link)}")
        if not st.armed and self.in_offboard:
            return f"{f.name} disarmed{said(link)}"
        return ""

    def stalled(self, last_setpoint_ms: int) -> str:
        """'' unless the last setpoint (at last_setpoint_ms of the autopilot's clock, -1: none yet) is older
        than PX4's offboard-loss timeout: then why the flight ends."""
        gap = self.link.state.time_boot_ms - last_setpoint_ms
        if last_setpoint_ms < 0 or gap <= OFFBOARD_LOSS_MS:
            return ""
        return (f"no setpoint for {gap * 1e-3:.1f} s of PX4's clock (this process stalled): past PX4's "
                f"offboard-loss timeout (COM_OF_LOSS_T, {OFFBOARD_LOSS_MS / 1000:g} s), its failsafe took "
                f"over{said(self.link)}")
