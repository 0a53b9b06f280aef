"""The companion through ArduCopter's GUIDED mode: the same flight loop as the PX4 OFFBOARD path
(controller.offboard_companion), with ArduPilot's start sequence and thrust scale.

Start (ArduPilot's rules): its HEARTBEAT; ATTITUDE_QUATERNION and LOCAL_POSITION_NED requested at rate_hz
(LOCAL_POSITION_NED exists only once its EKF has an origin: GUIDED needs that position estimate); GUID_OPTIONS
bit 3 set, so that SET_ATTITUDE_TARGET.thrust is a thrust demand, not a climb rate; MOT_THST_HOVER read;
GUIDED (re-asked while refused, e.g. before the EKF is ready); arm (re-asked while its pre-arm checks refuse);
MAV_CMD_NAV_TAKEOFF to the trajectory's start height (at least TAKEOFF_MIN_M) and a wait until there (bounded
in ArduPilot's simulated time): GUIDED flies attitude targets only once airborne. Then ArduPilot's own
position controller (SET_POSITION_TARGET_LOCAL_NED) flies to the trajectory's first point and the companion
waits until it is there and at rest, so the trajectory starts where the vehicle is. Then attitude + thrust
targets from the model-derived controller for `duration` s of ArduPilot's clock, then LOITER.

Height floor: the trajectory is flown at least MIN_HEIGHT_M above the EKF origin (where the vehicle took
off; controller.reference_shaping.HeightFloor), since GUIDED flies attitude targets only in the air and the
paper's Cases I and II start on the ground (Case I climbs through 0.5 m at 2.5 s, Case II at 1.7 s). Flown
raw, Case I's first point on the ground 3.7 m away made the controller dive from the take-off height into
the ground at about 1 m/s: the SITL's ground stops the vehicle within a step, which its IMU does not feel,
so ArduPilot's EKF went on integrating the old velocity, rejected GPS and declared its failsafe ("GPS
Glitch or Compass error", LAND).

Thrust: with GUID_OPTIONS bit 3 ArduCopter takes the thrust field as its throttle demand on its linearised
thrust scale (its mixer inverts MOT_THST_EXPO), so a demand proportional to the collective f1 = sum w_i^2
((rad/s)^2) is f1 / f1_hover * MOT_THST_HOVER, f1_hover = 4 w_hover^2 of the vehicle. ArduCopter boosts that
demand by 1/(cos roll cos pitch) (angle boost), which the controller's f1 already includes: it is sent
multiplied by cos roll cos pitch of ArduPilot's attitude estimate.

Metrics as the PX4 path's: from quadsr's truth log (the SITL's --log) when given, else from ArduPilot's
estimate (LOCAL_POSITION_NED, NED m from its EKF origin, which is where the SITL's vehicle starts).
ArduPilot's time_boot_ms runs on the JSON backend's simulated time (ArduPilot advances its clock by the
differences of the SITL's timestamps, from its first), so truth rows are taken at the same time_boot_ms
(measured: the best alignment of truth and estimate is within 40 ms of it).
"""

from __future__ import annotations

import math

from bridge.messages import mavlink
from bridge.offboard import ARDUPILOT, OffboardLink
from bridge.vehicle import VehicleConfig
from controller.offboard_companion import OffboardCompanion, OffboardSettings, _result_name, _said
from controller.plugin import Controller, Trajectory, VehicleState
from controller.reference_shaping import HeightFloor

GUIDED_THRUST_AS_THRUST = 8  # GUID_OPTIONS bit 3: SET_ATTITUDE_TARGET thrust is thrust, not climb rate
TAKEOFF_MIN_M = 1.0  # m above the EKF origin
TAKEOFF_TOLERANCE_M = 0.15
TAKEOFF_SIM_S = 30.0  # s of ArduPilot's clock for the take-off
RETRY_SIM_MS = 1000  # ms of ArduPilot's clock between re-asks of a refused mode switch or arming
MIN_HEIGHT_M = 0.5  # m above the EKF origin: the lowest the trajectory is flown (see the module doc)
AT_REST_M_S = 0.1  # m/s: the vehicle is at the first point when within TAKEOFF_TOLERANCE_M and this slow


class GuidedCompanion(OffboardCompanion):
    """One flight of the backstepping controller through ArduCopter's GUIDED mode (see module doc)."""

    flavour = ARDUPILOT

    hover_demand: float | None = None  # ArduCopter's MOT_THST_HOVER, read at the start

    def __init__(self, controller: Controller, trajectory: Trajectory, vehicle: VehicleConfig,
                 settings: OffboardSettings):
        floor = HeightFloor(trajectory, MIN_HEIGHT_M)
        super().__init__(controller, floor, vehicle, settings)
        raised = floor.raised_until(settings.duration)
        self.notes = [] if not raised else [
            f"the reference is flown at least {MIN_HEIGHT_M:g} m above the EKF origin (GUIDED flies attitude "
            f"targets only in the air): raised until t = {raised:.2f} s"]

    def setpoint(self, t: float, state: VehicleState, trajectory_t: float):
        """(controller command, attitude quaternion, ArduCopter thrust demand in [0, 1]) at t [s]."""
        ref, cmd, q, _ = super().setpoint(t, state, trajectory_t)
        f1 = float(cmd.info["f"][0])
        tilt = math.cos(float(state.xi[6])) * math.cos(float(state.xi[7]))
        demand = f1 / (4.0 * self.vehicle.hover_speed ** 2) * self.hover_demand * max(tilt, 0.1)
        return ref, cmd, q, demand

    def _start(self, link: OffboardLink) -> str:
        """Connect, estimate, GUID_OPTIONS, GUIDED, arm, take off: '' when flying, else why not."""
        s = self.offboard
        name = f"ArduPilot at {s.autopilot}"
        why = self._await_estimate(
            link, "is ArduPilot running (quadsr ardupilot)? its MAVLink port is tcp:HOST:5760+10*N",
            lambda: (f"{name} sent no local position within {s.connect_timeout:g} s: its EKF has no "
                     f"origin yet (GUIDED needs a position estimate; wait for GPS){_said(link)}"))
        if why:
            return why
        st = link.state
        options = link.get_param("GUID_OPTIONS")
        if options is None:
            return f"{name} did not answer a read of GUID_OPTIONS (is it ArduCopter?)"
        options = int(options) | GUIDED_THRUST_AS_THRUST  # the user's other bits kept (the value is saved)
        if not link.set_param("GUID_OPTIONS", options):
            return f"{name} did not take GUID_OPTIONS = {options} (bit 3: thrust as thrust)"
        self.hover_demand = link.get_param("MOT_THST_HOVER")
        if self.hover_demand is None or not 0.0 < self.hover_demand < 1.0:
            return f"{name} gave no usable MOT_THST_HOVER ({self.hover_demand})"
        why = self._until_accepted(link, lambda: link.set_mode(ARDUPILOT.offboard), "switch to GUIDED")
        if why:
            return why
        why = self._until_accepted(link, link.arm, "arm in GUIDED")
        if why:
            link.set_mode(ARDUPILOT.hold)
            return why
        height = max(TAKEOFF_MIN_M, -float(self.trajectory.reference(0.0).position[2]))
        result = link.command(mavlink.MAV_CMD_NAV_TAKEOFF, (0, 0, 0, 0, 0, 0, height))
        if result != mavlink.MAV_RESULT_ACCEPTED:
            return f"{name} refused the take-off to {height:g} m ({_result_name(result)}){_said(link)}"
        start_ms = st.time_boot_ms
        while abs(-st.position[2] - height) > TAKEOFF_TOLERANCE_M:
            if st.time_boot_ms - start_ms > TAKEOFF_SIM_S * 1000:
                return f"{name} did not reach {height:g} m within {TAKEOFF_SIM_S:g} s{_said(link)}"
            if link.silent(0.1, s.link_timeout):
                return f"{name} went silent for {s.link_timeout:g} s during the take-off"
        return self._to_first_point(link, name)

    def _to_first_point(self, link: OffboardLink, name: str) -> str:
        """Fly to the trajectory's first point with ArduPilot's position controller and wait until the
        vehicle is there at rest (bounded in its clock): '' when there, else why not."""
        s = self.offboard
        st = link.state
        first = self.trajectory.reference(0.0)
        target = [float(v) for v in first.position]
        start_ms = resend_ms = st.time_boot_ms
        link.position_target(target, float(first.yaw))
        while True:
            here = [p - q for p, q in zip(st.position, target, strict=True)]
            if math.hypot(*here) < TAKEOFF_TOLERANCE_M and math.hypot(*st.velocity) < AT_REST_M_S:
                return ""
            if st.time_boot_ms - start_ms > TAKEOFF_SIM_S * 1000:
                point = ", ".join(f"{v:.2f}" for v in target)
                return f"{name} did not reach the first point ({point}) m NED within {TAKEOFF_SIM_S:g} s" \
                    f"{_said(link)}"
            if st.time_boot_ms - resend_ms > RETRY_SIM_MS:
                resend_ms = st.time_boot_ms
                link.position_target(target, float(first.yaw))
            if link.silent(0.1, s.link_timeout):
                return f"{name} went silent for {s.link_timeout:g} s on the way to the first point"

    def _until_accepted(self, link: OffboardLink, ask, what: str) -> str:
        """Ask until ArduPilot accepts (re-asked every RETRY_SIM_MS of its clock while it refuses, for up to
        connect_timeout s of it): '' when accepted, else a message with its last result and STATUSTEXTs."""
        st = link.state
        start_ms = st.time_boot_ms
        while True:
            result = ask()
            if result == mavlink.MAV_RESULT_ACCEPTED:
                return ""
            if st.time_boot_ms - start_ms > self.offboard.connect_timeout * 1000:
                return (f"ArduPilot refused to {what} ({_result_name(result)}) for "
                        f"{self.offboard.connect_timeout:g} s of its clock{_said(link)}")
            retry = st.time_boot_ms + RETRY_SIM_MS
            while st.time_boot_ms < retry:
                if link.silent(0.1, self.offboard.link_timeout):
                    return f"ArduPilot went silent while asked to {what}"

