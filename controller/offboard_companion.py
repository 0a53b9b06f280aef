"""The companion through an autopilot's offboard interface (PX4 OFFBOARD), as on a real vehicle.

The model-derived backstepping controller runs on the autopilot's own estimate (LOCAL_POSITION_NED,
ATTITUDE_QUATERNION, requested at `rate_hz` of the autopilot's clock) and sends, for every attitude message,
SET_ATTITUDE_TARGET: the outer loop's desired attitude (phi_d, theta_d from the model inversion, the
reference yaw) and the collective f1 = sum of w_i^2 (rad/s)^2 of the inner solve, normalised through PX4's
thrust model fitted to the vehicle's motor curve (bridge.px4_thrust). Sequence: setpoints streamed for
`prestream_s` before the switch (PX4 requires them), OFFBOARD, arm, fly `duration` s of the autopilot's
clock, then AUTO.LOITER (the autopilot holds where the flight ended).

What the autopilot does is watched: a rejected mode switch or arming ends the flight before it starts, a
mode change away from OFFBOARD (PX4's offboard-loss failsafe, or a pilot/GCS) and a disarm end it, and so does
silence for `link_timeout` wall s. Metrics and figures as `quadsr fly`'s, from quadsr's truth log (the SITL's
--log, given as `truth`) over the flight's window of simulated time, else from the autopilot's estimate.
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bridge.offboard import PX4, AutopilotFlavour, OffboardLink
from bridge.offboard_flight import OffboardWatch, await_estimate, start_px4_offboard
from bridge.offboard_flight import result_name as _result_name  # noqa: F401  (guided_companion's)
from bridge.offboard_flight import said as _said  # noqa: F401
from bridge.px4_thrust import fit_thrust_model, normalised_thrust
from bridge.rotations import euler_from_quaternion, quaternion_from_euler
from bridge.tlog import read_tlog
from bridge.vehicle import VehicleConfig
from controller.companion import (
    CRASH_TILT,
    CSV_COLUMNS,
    Companion,
    FlightResult,
    FlightSettings,
    StepLog,
    open_flight_outputs,
)
from controller.plugin import Controller, Trajectory, VehicleState

TRUTH_COLUMNS = ("true_x", "true_y", "true_z", "true_vx", "true_vy", "true_vz", "true_phi", "true_theta",
                 "true_psi")


@dataclass(frozen=True)
class OffboardSettings:
    """How to fly through the autopilot: its address, flight length [s of its clock], rates, timeouts."""

    autopilot: str  # udp:HOST:PORT of its offboard link (PX4 instance N: udp:127.0.0.1:14580+N)
    duration: float = 20.0
    rate_hz: float = 100.0  # attitude and position messages requested, Hz of the autopilot's clock
    prestream_s: float = 1.0  # setpoints streamed before the mode switch, s of the autopilot's clock
    truth: Path | None = None  # quadsr's truth .tlog (the SITL's --log) for metrics
    link_timeout: float = 2.0  # wall s without a message from the autopilot: the flight ends
    connect_timeout: float = 30.0  # wall s for its first HEARTBEAT and estimate
    progress: bool = False


class OffboardCompanion(Companion):
    """One flight of the backstepping controller through an autopilot's OFFBOARD mode (see module doc)."""

    flavour: AutopilotFlavour = PX4  # whose modes and messages (controller.guided_companion: ArduPilot)

    def __init__(self, controller: Controller, trajectory: Trajectory, vehicle: VehicleConfig,
                 settings: OffboardSettings):
        super().__init__(controller, trajectory, vehicle, FlightSettings(duration=settings.duration,
                                                                         progress=False))
        self.offboard = settings
        self.thrust_factor = fit_thrust_model(vehicle)[0]
        self._speeds = np.zeros(4)

    def setpoint(self, t: float, state: VehicleState, trajectory_t: float):
        """(controller command, attitude quaternion, normalised thrust) for the state at t [s]."""
        ref = self.trajectory.reference(trajectory_t)
        cmd = self.controller.update(t, state, ref)
        info = cmd.info
        q = quaternion_from_euler(float(info["phi_d"]), float(info["theta_d"]), float(ref.yaw))
        thrust = normalised_thrust(self.vehicle, self.thrust_factor, float(info["f"][0]))
        return ref, cmd, q, thrust

    def fly(self, out_dir: str | Path) -> FlightResult:
        """Connect, stream, switch to OFFBOARD, arm, fly, hand back (AUTO.LOITER); outputs to out_dir."""
        s = self.offboard
        out, files, tlog, log = open_flight_outputs(out_dir)
        link = OffboardLink(s.autopilot, self.flavour, tlog, connect_timeout=s.connect_timeout)
        completed = crashed = False
        message = ""
        t0_ms = None
        try:
            message = self._start(link)
            if not message:
                try:
                    t0_ms, completed, crashed, message = self._loop(link, log)
                finally:  # also on Ctrl-C: the autopilot holds where the flight ended, no loss failsafe
                    link.set_mode(self.flavour.hold)
        finally:
            link.close()
            tlog.close()
            log.close()
        if t0_ms is not None and s.truth is not None and log.rows:
            self._fill_truth(log, s.truth, t0_ms)
        metrics = self._finish(log, out, files, completed, crashed) if log.rows else None
        return FlightResult(metrics, completed, crashed, message, len(log.rows), out, files,
                            link.link.stats.as_dict(), list(link.state.status_texts))

    # -------------------------------------------------------------------------------------------------
    def _await_estimate(self, link: OffboardLink, not_running: str, no_estimate: Callable[[], str]) -> str:
        """Connect, ask for the attitude and local position at rate_hz and wait for both: '' or why not
        (`not_running` follows the connect timeout's message; `no_estimate()` says why none came)."""
        s = self.offboard
        return await_estimate(link, s.connect_timeout, s.rate_hz, not_running, no_estimate)

    def _start(self, link: OffboardLink) -> str:
        """Connect, request the estimate, pre-stream, OFFBOARD, arm: '' when flying, else why not."""
        s = self.offboard
        return start_px4_offboard(link, s.autopilot, s.rate_hz, s.prestream_s, s.connect_timeout,
                                  s.link_timeout)

    def _loop(self, link: OffboardLink, log: StepLog) -> tuple[int, bool, bool, str]:
        """The flight: one setpoint per new attitude message; (t0 ms, completed, crashed, message)."""
        s = self.offboard
        st = link.state
        t0_ms = st.attitude_ms
        self.controller.reset()
        last_ms = -1
        watch = OffboardWatch(link, s.autopilot, s.link_timeout)
        while True:
            why = watch.poll(0.05) or watch.stalled(last_ms)
            if why:
                return t0_ms, False, False, why
            if st.attitude_ms == last_ms:
                continue
            last_ms = st.attitude_ms
            t = (last_ms - t0_ms) * 1e-3
            if t >= s.duration:
                return t0_ms, True, False, ""
            start = time.perf_counter()
            phi, theta, psi = (float(a) for a in euler_from_quaternion(st.quaternion))
            xi = np.array([*st.position, *st.velocity, phi, theta, psi, *st.rates])
            state = VehicleState(xi, self._speeds, np.array(st.quaternion))
            c0 = time.perf_counter()
            ref, cmd, q, thrust = self.setpoint(t, state, t)
            control = time.perf_counter() - c0
            link.attitude_target(q, thrust)
            self._speeds = np.asarray(cmd.rotor_speeds, dtype=float)
            loop = time.perf_counter() - start
            log.add([t, *ref.position, *ref.velocity, ref.yaw, *xi, *([math.nan] * 9), *self._speeds,
                     *self._speeds, *([thrust] * 4), float(cmd.saturated), control * 1e6, loop * 1e6])
            tilt = math.acos(max(-1.0, min(1.0, math.cos(phi) * math.cos(theta))))
            if tilt > CRASH_TILT:
                return t0_ms, False, True, f"crash at t = {t:.2f} s: tilt {math.degrees(tilt):.0f} deg"

    def _fill_truth(self, log: StepLog, truth: Path, t0_ms: int) -> None:
        """Put quadsr's truth (interpolated at each step's simulated time) in the rows, rewrite steps.csv."""
        pos_t, pos, att_t, att = [], [], [], []
        for _, msg in read_tlog(truth):
            kind = msg.get_type()
            if kind == "LOCAL_POSITION_NED":
                pos_t.append(msg.time_boot_ms)
                pos.append((msg.x, msg.y, msg.z, msg.vx, msg.vy, msg.vz))
            elif kind == "HIL_STATE_QUATERNION":
                att_t.append(msg.time_usec * 1e-3)
                att.append(euler_from_quaternion(msg.attitude_quaternion))
        if len(pos_t) < 2 or len(att_t) < 2:
            return
        times = np.array([row[0] for row in log.rows]) * 1e3 + t0_ms
        pos_a, att_a = np.array(pos), np.unwrap(np.array(att), axis=0)
        first = CSV_COLUMNS.index(TRUTH_COLUMNS[0])
        columns = [np.interp(times, pos_t, pos_a[:, i]) for i in range(6)]
        columns += [np.interp(times, att_t, att_a[:, i]) for i in range(3)]
        for k, row in enumerate(log.rows):
            row[first:first + 9] = [float(c[k]) for c in columns]
        with log.path.open("w", newline="", encoding="utf-8") as fh:
            writer = csv.writer(fh)
            writer.writerow(CSV_COLUMNS)
            writer.writerows([f"{v:.9g}" for v in row] for row in log.rows)

