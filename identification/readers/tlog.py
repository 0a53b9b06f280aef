"""Our .tlog (a quadsr HIL flight) -> Dataset.

One row per SITL step (4 ms) that has all its frames: HIL_STATE_QUATERNION (attitude -> ZYX Euler, body
rates), LOCAL_POSITION_NED (float position and velocity, the precise truth), the rotor speeds (RAW_RPM per
rotor, index 0..3 = motors 1..4, as bridge.messages sends them; ESC_STATUS where a dialect has it) and
HIL_SENSOR. Only frames from the SITL's HIL component (the sender of HIL_SENSOR) are used; the time-0
datagram the SITL repeats while waiting is counted once.

Truth targets of a log with the SITL's true accelerations (DEBUG_FLOAT_ARRAY TRUE_ACC, every quadsr SITL log
since session 43): those, at each step's own state: exact, nothing differentiated (one row per step). Older
logs, or logged_accelerations=False, derive them from the states as follows.
Truth targets of a log with rotor speeds and the companion's commands whose commands change at most steps
(a controller, sinusoids): one row per step interval [t_k, t_k+1] at its midpoint, the targets the exact
mean accelerations over the step, the state and rotor speeds those of the midpoint under the held command
(identification.step_targets). Held commands (paper-train): one row per step clear of a command change (the
7-point stencil; POINT_ROWS_ABOVE); no commands or no visible motor lag: kink-aware point derivatives.

Raw sensor targets for the weak form (SensorTargetSettings.step_intervals: identification.weak_form's
RAW_SENSOR_TARGETS) of a log with rotor speeds and commands: one row per step interval too, the gyro's
difference over the step (its exact mean derivative) and the accelerometer's mean over it (its two ends
averaged plus what the curvature of the thrust (the rotors' lag) and of the drag (the body velocity turning
with the body) adds within the step: step_targets.sampled_step_means), the regressors those of
the truth targets' rows (identification.step_targets, the step means of the rates and of R^T v; the targets
not moved to the row state: that shift is fitted to the truth accelerations), and with them each step's
path (aux `step_nodes`: the state at the step's two Gauss nodes), so that load_dataset can make each step two
node rows whose mean is the step's.

Rows where the vehicle rests on the ground plane (z = 0, no motion: the SITL clamps the state there and the
free-flight equations do not hold) are dropped (aux `ground_s`, each row's time from the nearest of them,
lets the flight segmentation drop the lift-off and touch-down as it does in other logs), as are rows
whose differentiation stencil would span a missing step or a resting row. Sensor targets also drop rows
whose window holds a clamped IMU sample (+-16 g, +-2000 deg/s).
"""

from __future__ import annotations

import warnings as pywarnings
from pathlib import Path
from typing import Any

import numpy as np

from bridge.errors import UserError
from bridge.messages import ACCEL_LIMIT, GYRO_LIMIT, RPM_TO_RAD_S, ObservationAssembler
from bridge.rotations import euler_from_quaternions, rotation_matrix
from bridge.tlog import read_tlog
from identification.log_gravity import log_gravity
from identification.readers import RowFilter, make_dataset, rotor_model
from identification.segmentation import SegmentationSettings, seconds_to_nearest
from identification.step_targets import (
    body_state_nodes,
    motor_lag_ratio,
    sample_body_velocity,
    sampled_step_means,
    step_interval_rows,
    step_node_offsets,
)
from identification.table import Dataset
from identification.targets import (
    STANDARD_GRAVITY,
    SensorTargetSettings,
    sensor_targets,
    truth_targets,
)
from identification.weak_noise import STEP_DIFFERENCE, STEP_MEAN

STEP_S = 0.004
# Point truth targets of held commands: a command change (any change) restarts the motor lag, so the
# accelerations' slope jumps there and the lag's fast transient follows (Tm = 5 steps on our vehicles). A row
# is kept only where the 7-point central stencil (6th order) has no change strictly inside its span; the
# others are dropped, not given lower-order stencils. Measured on fang-chen-aero's paper-train flight (60 s),
# true model's residual RMS on dwy: every row with kink-aware stencils 6.4e-2 rad/s^2 (the rows within one
# step of a change 1e-1, and 0.02 of throttle as the threshold of a change hid the smaller ones); rows clear
# of the 5-point span 2.3e-3 (63 % of rows); clear of the 7-point span 2.2e-4 (45 %): given the true
# structure, dwy's wz^2 t ratio 6 -> 76 -> 190+, fz's wx*wz 3 -> 34 -> 64. Step-mean targets
# (identification.step_targets) when fewer than this fraction of rows are clear (a controller, sinusoids:
# every sample a change): their regressors hold the rotor speeds' interval RMS, exact for thrust and
# torques (u^2) but not for terms linear in u (rotor drag, gyroscopic), 2.4e-2 on the same flight's dwy.
POINT_ROWS_ABOVE = 0.25
STENCIL_HALF = 3  # the 7-point central stencil's reach, samples
_STATE_TYPES = {
    "HIL_STATE_QUATERNION",
    "LOCAL_POSITION_NED",
    "RAW_RPM",
    "HIL_GPS",
    "HIL_SENSOR",
    "ESC_STATUS",
    "DEBUG_FLOAT_ARRAY",
}


def _collect(path: Path) -> tuple[list[Any], list[Any], list[str]]:
    """(messages from the SITL's HIL component, the companion's HIL_ACTUATOR_CONTROLS, warnings)."""
    notes: list[str] = []
    with pywarnings.catch_warnings(record=True) as caught:
        pywarnings.simplefilter("always")
        msgs = [m for _, m in read_tlog(path)]
    for w in caught:
        notes.append(str(w.message))
    source = None
    for m in msgs:
        if m.get_type() == "HIL_SENSOR":
            source = (m.get_srcSystem(), m.get_srcComponent())
            break
    if source is None:
        types = sorted({m.get_type() for m in msgs})
        raise UserError(
            f"telemetry log {path} has no HIL_SENSOR message, so no SITL steps "
            f"({len(msgs)} frames of: {', '.join(types[:8]) or 'nothing'})",
            hint="record the flight with `quadsr excite --out FILE.tlog` or `quadsr sitl --log FILE.tlog`",
        )
    sitl = [
        m
        for m in msgs
        if (m.get_srcSystem(), m.get_srcComponent()) == source and m.get_type() in _STATE_TYPES
    ]
    commands = [m for m in msgs if m.get_type() == "HIL_ACTUATOR_CONTROLS"]
    return sitl, commands, notes


def _esc_speeds(msg: Any) -> np.ndarray:
    out = np.full(4, np.nan)
    base = int(getattr(msg, "index", 0))
    for i, rpm in enumerate(msg.rpm):
        if 0 <= base + i < 4:
            out[base + i] = rpm * RPM_TO_RAD_S
    return out


def read_tlog_dataset(
    path: Path,
    targets: str = "truth",
    motor_curve: Any = None,
    rate_hz: float | None = None,
    gravity: float | None = None,
    sensor_settings: SensorTargetSettings | None = None,
    step_intervals: bool = True,
    logged_accelerations: bool = True,
) -> Dataset:
    """Dataset of a quadsr .tlog: truth states, true rotor speeds, targets from truth or sensors.

    Truth targets: the SITL's logged true accelerations at each step where the log has them (False: derived
    from the states even so). Else, when the log has rotor speeds and commands: one row per step interval at
    its midpoint (identification.step_targets; step_intervals=False: per-sample kink-aware derivatives).
    """
    decimation = 1
    if rate_hz is not None:
        factor = (1.0 / STEP_S) / rate_hz
        if abs(factor - round(factor)) > 1e-6 or round(factor) < 1:
            raise UserError(
                f"rate {rate_hz:g} Hz does not divide the tlog's 250 Hz steps",
                hint="use 250, 125, 83.33, 62.5, 50, ... Hz",
            )
        decimation = int(round(factor))
    msgs, commands, notes = _collect(path)
    types = {m.get_type() for m in msgs}
    for needed, what in (
        ("HIL_STATE_QUATERNION", "the true attitude and body rates"),
        ("LOCAL_POSITION_NED", "the true position and velocity"),
    ):
        if needed not in types:
            raise UserError(
                f"telemetry log {path} has no {needed} message ({what})",
                hint="is this a quadsr SITL flight log?",
            )
    have_rpm = bool(types & {"RAW_RPM", "ESC_STATUS"})
    rotor = rotor_model(motor_curve) if not have_rpm else None
    if have_rpm and motor_curve is not None:
        notes.append("motor curve not used: the log has the true rotor speeds")
    if not have_rpm and rotor is None:
        raise UserError(
            f"telemetry log {path} has no rotor speeds (no RAW_RPM or ESC_STATUS message)",
            hint="pass --motor-curve (a vehicle or 'slope,offset') to use the motor commands instead",
        )

    assembler = ObservationAssembler()
    rows: dict[int, dict[str, Any]] = {}
    duplicates = 0
    esc: dict[int, np.ndarray] = {}
    pending_esc = None
    for m in msgs:
        if m.get_type() == "ESC_STATUS":
            pending_esc = _esc_speeds(m)
            continue
        obs = assembler.add(m)
        if obs is None:
            continue
        if obs.time_usec in rows:
            duplicates += 1
            continue
        if pending_esc is not None:
            esc[obs.time_usec] = pending_esc
            pending_esc = None
        rows[obs.time_usec] = {"obs": obs}

    times = np.array(sorted(rows), dtype=np.int64)
    n = len(times)
    t = times * 1e-6
    pos = np.full((n, 3), np.nan)
    vel = np.full((n, 3), np.nan)
    quat = np.full((n, 4), np.nan)
    rates = np.full((n, 3), np.nan)
    u = np.full((n, 4), np.nan)
    acc = np.full((n, 3), np.nan)
    gyro = np.full((n, 3), np.nan)
    true_acc = np.full((n, 6), np.nan)  # the SITL's: NED m/s^2, FRD rad/s^2
    filt = RowFilter(n)
    no_hsq = np.zeros(n, bool)
    no_lpn = np.zeros(n, bool)
    for i, tu in enumerate(times):
        obs = rows[int(tu)]["obs"]
        acc[i] = obs.imu.accel
        gyro[i] = obs.imu.gyro
        if obs.accelerations is not None:
            true_acc[i] = obs.accelerations
        if obs.truth is None:
            no_hsq[i] = True
        else:
            pos[i] = obs.truth.position
            vel[i] = obs.truth.velocity
            quat[i] = obs.truth.quaternion
            rates[i] = obs.truth.rates
            no_lpn[i] = not np.isfinite(obs.truth.position).all()
        if obs.rotor_speeds is not None:
            u[i] = obs.rotor_speeds
        elif int(tu) in esc:
            u[i] = esc[int(tu)]

    if rotor is not None:
        u, settled = _speeds_from_commands(times, commands, rotor)
        filt.drop("motor lag settling after the start", ~settled)
        notes.append(f"rotor speeds from HIL_ACTUATOR_CONTROLS through {rotor.description}")

    filt.drop("step without HIL_STATE_QUATERNION", no_hsq)
    filt.drop("step without LOCAL_POSITION_NED", no_lpn)
    filt.drop("step without rotor speeds", ~np.isfinite(u).all(axis=1))
    resting = (pos[:, 2] >= -1e-3) & (np.abs(vel) <= 1e-3).all(axis=1) & (np.abs(rates) <= 1e-3).all(axis=1)
    filt.drop("resting on the ground", resting)
    rest_times = t[resting]
    ground_s = seconds_to_nearest(t, rest_times)  # s from each sample to the nearest resting one

    euler = euler_from_quaternions(quat)
    usable = ~(no_hsq | no_lpn | resting | ~np.isfinite(u).all(axis=1))
    idx = np.flatnonzero(usable)
    tgt = np.full((n, 6), np.nan)
    extra = {"duplicate time-0 datagram (SITL waiting)": duplicates} if duplicates else {}
    state_times = {int(m.time_usec) for m in msgs if m.get_type() == "HIL_STATE_QUATERNION"}
    no_sensor = len(state_times - set(rows))
    if no_sensor:
        extra["step without HIL_SENSOR"] = no_sensor
    g = STANDARD_GRAVITY if gravity is None else float(gravity)  # m/s^2, what the targets add back
    gravity_estimate = None
    if targets == "truth":  # sensor targets add back the g that body-frame learning removes: any g is right
        # not next to ground contact: the ground's reaction there changes within a step
        airborne = usable & (ground_s > SegmentationSettings().edge_margin_s)
        gravity_estimate = log_gravity(t, vel, euler, acc, airborne)
    logged = np.isfinite(true_acc).all(axis=1)
    use_logged = targets == "truth" and logged_accelerations and bool(logged[usable].any())
    throttles = _held_throttles(times, commands) if commands else None
    kinks = _command_kinks(times, commands)
    crossing = None if kinks is None else _dilate(kinks, STENCIL_HALF - 1)  # a change inside the span
    central = float(np.mean(~crossing[usable])) if crossing is not None and usable.any() else 1.0
    if targets == "truth" and not use_logged and rotor is None and throttles is not None and step_intervals:
        ratio = motor_lag_ratio(u, throttles, usable) if central < POINT_ROWS_ABOVE else None
        if central >= POINT_ROWS_ABOVE:
            notes.append(
                f"truth targets: commands held ({100 * central:.0f}% of rows clear of a command change): "
                "7-point point derivatives (6th order); rows whose stencil would cross a change dropped"
            )
        if ratio is not None:
            t_mid, xi_mid, u_mid, tgt_mid = step_interval_rows(t, pos, vel, quat, rates, u, ratio, g, notes)
            steps = _interval_filter(filt, times, rate_hz, decimation)
            notes.append(
                "truth targets: exact mean accelerations over each 4 ms step, rows at step midpoints "
                f"(motor lag ratio {ratio:.6f} per step, Tm = {-STEP_S / np.log(ratio) * 1000:.2f} ms, "
                "estimated from the log)"
            )
            ground = {"ground_s": seconds_to_nearest(t_mid, rest_times)}
            return _with_gravity(make_dataset(path, "tlog", targets, t_mid, xi_mid, u_mid, tgt_mid, steps,
                                              notes, extra, aux=ground), gravity_estimate)
        elif central < POINT_ROWS_ABOVE:
            notes.append("truth targets: no motor lag seen in the log's speeds; kink-aware point derivatives")
    raw_steps = sensor_settings is not None and sensor_settings.step_intervals
    if targets == "sensors" and raw_steps and rotor is None and throttles is not None and step_intervals:
        ratio = motor_lag_ratio(u, throttles, usable)
        if ratio is not None:
            t_mid, xi_mid, u_mid, _ = step_interval_rows(t, pos, vel, quat, rates, u, ratio, gravity=g,
                                                         row_targets=False)
            steps = _interval_filter(filt, times, rate_hz, decimation)
            clipped = _clamped_imu(acc, gyro)
            steps.drop("IMU sample clamped at an end of the step (+-16 g / +-2000 deg/s)",
                       clipped[:-1] | clipped[1:])
            nodes = step_node_offsets(vel, quat, rates, u, ratio, xi_mid, u_mid)
            r = rotation_matrix(xi_mid[:, 6], xi_mid[:, 7], xi_mid[:, 8])
            z = np.column_stack((u, rates, sample_body_velocity(vel, quat)))
            keep = steps.keep_mask()[0]
            f_b = sampled_step_means(acc, z, body_state_nodes(nodes, xi_mid, u_mid),
                                     np.append(keep, False) | np.insert(keep, 0, False))
            tgt_mid = np.concatenate((np.einsum("nij,nj->ni", r, f_b) + np.array([0.0, 0.0, g]),
                                      np.diff(gyro, axis=0) / np.diff(t)[:, None]), axis=1)
            notes.append(
                f"raw sensor targets (g = {g:g} m/s^2) over each 4 ms step, rows at step midpoints: the "
                "gyro's difference over the step (its exact mean derivative there) and the accelerometer's "
                "mean over it (its ends averaged plus the thrust's and the drag's curvature within the "
                f"step); regressors at the midpoint under the held command (motor lag ratio {ratio:.6f} per "
                "step, estimated from the log)"
            )
            side = {"ground_s": seconds_to_nearest(t_mid, rest_times)}
            if decimation == 1:  # each step's path: its rows become its two Gauss nodes (load_dataset)
                side["step_nodes"] = nodes.reshape(len(t_mid), -1)
            ds = make_dataset(path, "tlog", targets, t_mid, xi_mid, u_mid, tgt_mid, steps, notes, extra,
                              aux=side)
            if decimation == 1:  # consecutive rows share a sample: the targets' noise is correlated
                ds.target_noise = (STEP_MEAN,) * 3 + (STEP_DIFFERENCE,) * 3
            return _with_gravity(ds, gravity_estimate)
    if use_logged:
        tgt = true_acc
        filt.drop("step without the SITL's true accelerations (TRUE_ACC)", ~logged)
        # the SITL reports zeros while it holds the vehicle on the ground plane: no free flight there
        filt.drop("held on the ground plane (true accelerations zero)", (true_acc == 0.0).all(axis=1))
        notes.append("truth targets: the SITL's true accelerations at each step's state (TRUE_ACC), exact")
    elif targets == "truth":
        tgt[idx] = truth_targets(
            t[idx], vel[idx], rates[idx], dt=STEP_S, kinks=None if kinks is None else kinks[idx]
        )
        if crossing is not None and central >= POINT_ROWS_ABOVE:
            filt.drop(f"truth target: a command change within {STENCIL_HALF - 1} steps (the 7-point stencil "
                      "would cross the motor lag's restart)", crossing)
    else:
        st = sensor_targets(
            t[idx], acc[idx], gyro[idx], euler[idx], gravity=g, settings=sensor_settings, dt=STEP_S
        )
        tgt[idx] = st.values
        notes.append(f"sensor targets (g = {g:g} m/s^2): {st.describe(STEP_S)}")
        half = st.max_half_window
        filt.drop("IMU sample clamped in the window (+-16 g / +-2000 deg/s)",
                  _dilate(_clamped_imu(acc, gyro), half))

    if rate_hz is not None:
        filt.drop(f"decimated to {rate_hz:g} Hz", (times // 4000) % decimation != 0)

    state = np.concatenate((pos, vel, euler, rates), axis=1)
    return _with_gravity(make_dataset(path, "tlog", targets, t, state, u, tgt, filt, notes, extra,
                                      aux={"ground_s": ground_s}), gravity_estimate)


def _with_gravity(ds: Dataset, estimate: tuple[float, float] | None) -> Dataset:
    """ds with the gravity its log's accelerations and accelerometer agree on (g, standard error m/s^2)."""
    if estimate is not None:
        ds.gravity_estimates = [(ds.source, *estimate)]
    return ds


def _interval_filter(filt: RowFilter, times: np.ndarray, rate_hz: float | None, decimation: int) -> RowFilter:
    """The filter of the N-1 step intervals between samples at times (us): an interval goes where either end
    went, where it spans a missing step, and where decimation drops its start."""
    steps = RowFilter(len(times) - 1)
    for reason, bad in filt.reasons:
        steps.drop(reason, bad[:-1] | bad[1:])
    steps.drop("step interval over a missing step", np.diff(times) != round(STEP_S * 1e6))
    if rate_hz is not None:
        steps.drop(f"decimated to {rate_hz:g} Hz", (times[:-1] // 4000) % decimation != 0)
    return steps


def _clamped_imu(acc: np.ndarray, gyro: np.ndarray) -> np.ndarray:
    """Samples (N,) where an IMU axis sits at the HIL encoder's clamp (+-16 g, +-2000 deg/s)."""
    return (np.abs(gyro) >= GYRO_LIMIT * (1 - 1e-6)).any(axis=1) | (
        np.abs(acc) >= ACCEL_LIMIT * (1 - 1e-6)
    ).any(axis=1)


def _dilate(mask: np.ndarray, half: int) -> np.ndarray:
    """True within `half` samples of a True sample."""
    if half <= 0 or not mask.any():
        return mask
    kernel = np.ones(2 * half + 1)
    return np.convolve(mask.astype(float), kernel, mode="same") > 0


def _held_throttles(times: np.ndarray, commands: list[Any]) -> np.ndarray:
    """Throttles (N,4) in [0, 1] held from each step (us) to the next: the reply to that step's HIL_SENSOR;
    NaN where the log has no reply for the step."""
    by_time = {int(c.time_usec): np.asarray(c.controls[:4], dtype=float) for c in commands}
    out = np.full((len(times), 4), np.nan)
    for i, tu in enumerate(times):
        if int(tu) in by_time:
            out[i] = by_time[int(tu)]
    return out


def _command_kinks(times: np.ndarray, commands: list[Any]) -> np.ndarray | None:
    """Steps (N,) where a motor command changed: the accelerations' slope jumps there (the motor lag starts
    toward the new speed). None when the log holds no commands."""
    if not commands:
        return None
    cmd = _held_throttles(times, commands)
    jump = np.abs(np.diff(cmd, axis=0)).max(axis=1)
    kinks = np.concatenate(([False], ~(jump <= 0.0)))  # unknown command: assume a kink
    return kinks


def _speeds_from_commands(times: np.ndarray, commands: list[Any], rotor) -> tuple[np.ndarray, np.ndarray]:
    """(rotor speeds (N,4) rad/s, settled (N,)) at step times (us) from the throttles the companion sent."""
    by_time = {int(c.time_usec): c.controls[:4] for c in commands}
    thr = np.zeros((len(times), 4))
    last = np.zeros(4)
    for i, tu in enumerate(times):
        # the command answering step k is held from step k to k+1 (RotorModel.speeds integrates it so)
        last = np.asarray(by_time.get(int(tu), last), dtype=float)
        thr[i] = last
    return rotor.speeds(times * 1e-6, thr)
