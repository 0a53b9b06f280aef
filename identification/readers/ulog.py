"""PX4 ULog (.ulg, through pyulog) -> Dataset.

Topics (instance 0; times from timestamp_sample where the topic has it, else timestamp):
- vehicle_local_position: x y z, vx vy vz (NED m, m/s), ax ay az (NED m/s^2, the estimator's acceleration);
  rows where its xy/z/v_xy/v_z_valid flags are false are dropped.
- vehicle_attitude: q (w, x, y, z; FRD body -> NED) -> ZYX Euler (interpolated as quaternions).
- vehicle_angular_velocity: xyz (FRD rad/s) and xyz_derivative (FRD rad/s^2). Its sample times are the
  default timeline (50 Hz in the test log); rate_hz gives a uniform one instead.
- rotor speeds: without a motor curve, esc_status esc[i].esc_rpm (rpm -> rad/s; esc[i].actuator_function
  101..104 = motor 1..4; only about 4 Hz in PX4 logs, so interpolated). With a motor curve:
  actuator_outputs through it. PX4 writes actuator_outputs as PWM microseconds on PWM outputs (the test log:
  900 disarmed, 1000 armed idle, ~1450-1550 in hover): a channel n with <PREFIX>_FUNCn = 101..104 is motor
  1..4, throttle = (value - <PREFIX>_MINn) / (<PREFIX>_MAXn - <PREFIX>_MINn), defaults 1000 and 2000 us
  (PX4's) when the log has no such parameters. Values that never exceed 2 are taken as normalized [0, 1].
  Without actuator_outputs, actuator_motors control[0..3] (normalized thrust, motor order) is used; and
  also when it is logged at least 1.5x as often (PX4's system identification logging profile), then turned
  into PX4's output through THR_MDL_FAC's inverse.
- vehicle_land_detected: rows where landed is true are dropped (ground contact is not free flight).
- targets 'truth': the estimator's own accelerations: vehicle_local_position ax ay az and
  vehicle_angular_velocity xyz_derivative. 'sensors': sensor_combined accelerometer (FRD specific force)
  rotated with the attitude plus g, and its gyro differentiated (Savitzky-Golay, identification.targets),
  computed at the sensor rate and then resampled; each sample is placed at the middle of the interval PX4
  integrated it over (timestamp - gyro_integral_dt / 2).
"""

from __future__ import annotations

import contextlib
import io
import re
import struct
from pathlib import Path
from typing import Any

import numpy as np
from scipy.ndimage import maximum_filter1d

from bridge.errors import UserError
from bridge.rotations import euler_from_quaternions
from identification.motor_model import ThrustCurve
from identification.readers import (
    RotorModel,
    RowFilter,
    Stream,
    make_dataset,
    rotor_model,
    uniform_imu,
    uniform_timeline,
)
from identification.table import Dataset
from identification.targets import (
    STANDARD_GRAVITY,
    SensorTargetSettings,
    nominal_step,
    sensor_targets,
    stream_derivative,
)

RPM_TO_RAD_S = 2.0 * np.pi / 60.0
MOTOR_FUNCTIONS = (101, 102, 103, 104)  # PX4 output functions Motor 1..4
ARMING_STATE_ARMED = 2  # vehicle_status.arming_state ARMED (v1.6 era and today)
DEFAULT_RATE_HZ = 50.0  # the timeline of logs without vehicle_angular_velocity


def _open(path: Path) -> tuple[Any, list[str]]:
    """The parsed ULog and warnings (truncation); UserError for an empty or unreadable file."""
    from pyulog import ULog
    from pyulog.core import ULogException

    data = path.read_bytes()
    if not data:
        raise UserError(f"px4 log {path} is empty")
    sink = io.StringIO()
    try:
        with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
            ulog = ULog(str(path))
    except (
        ULogException,
        OSError,
        ValueError,
        struct.error,
        IndexError,
        KeyError,
        UnicodeDecodeError,
    ) as exc:
        raise UserError(
            f"px4 log {path} is corrupt or not a ULog file ({exc})",
            hint="check the file; a ULog starts with the bytes 'ULog'",
        ) from None
    notes = []
    cut = _truncated_bytes(data)
    if cut or getattr(ulog, "file_corruption", False):
        notes.append(
            f"px4 log {path} is truncated or corrupt near its end: using the data it holds"
            + (f" (last message lacks {cut} bytes)" if cut else "")
        )
    if not ulog.data_list:
        raise UserError(
            f"px4 log {path} holds no logged data (truncated in its header?)",
            hint="the file ends before any topic data; use the complete log",
        )
    return ulog, notes


def _truncated_bytes(data: bytes) -> int:
    """How many bytes the last ULog message lacks (0 if the file ends on a message boundary)."""
    i, n = 16, len(data)
    while i + 3 <= n:
        size = data[i] | (data[i + 1] << 8)
        i += 3 + size
    return i - n if i > n else (n - i if i < n else 0)


class _Topics:
    """Access to a ULog's topics by name with clear errors naming the file and what is missing."""

    def __init__(self, ulog: Any, path: Path):
        self.ulog = ulog
        self.path = path
        self.t0 = ulog.start_timestamp
        self.names = sorted({d.name for d in ulog.data_list})

    def has(self, name: str) -> bool:
        return name in self.names

    def get(self, name: str, why: str) -> dict[str, np.ndarray]:
        for d in self.ulog.data_list:
            if d.name == name and d.multi_id == 0:
                if len(d.data["timestamp"]) == 0:
                    break
                return d.data
        raise UserError(
            f"px4 log {self.path} has no topic '{name}'; it is needed for {why}",
            hint=f"topics in this log: {', '.join(self.names)}",
        )

    def times(self, data: dict[str, np.ndarray]) -> np.ndarray:
        ts = data.get("timestamp_sample", data["timestamp"])
        return (ts.astype(np.int64) - np.int64(self.t0)) * 1e-6

    @staticmethod
    def columns(data: dict[str, np.ndarray], names: list[str], topic: str, path: Path) -> np.ndarray:
        missing = [c for c in names if c not in data]
        if missing:
            raise UserError(f"px4 log {path}: topic '{topic}' has no field {missing[0]!r}")
        return np.column_stack([data[c].astype(float) for c in names])


def _esc_rotor_stream(topics: _Topics) -> Stream:
    data = topics.get(
        "esc_status", "the rotor speeds (esc_rpm); or pass a motor curve to use actuator_outputs"
    )
    t = topics.times(data)
    speeds = np.full((len(t), 4), np.nan)
    count = data.get("esc_count", np.full(len(t), 8))
    for i in range(8):
        key = f"esc[{i}].esc_rpm"
        if key not in data:
            continue
        func = data.get(f"esc[{i}].actuator_function")
        for row in range(len(t)):
            if i >= count[row]:
                continue
            f = int(func[row]) if func is not None else 0
            motor = f - 101 if f in MOTOR_FUNCTIONS else (i if f == 0 else -1)
            if 0 <= motor < 4:
                speeds[row, motor] = float(data[key][row]) * RPM_TO_RAD_S
    if not np.isfinite(speeds).any() or np.nanmax(np.abs(speeds)) == 0:
        raise UserError(
            f"px4 log {topics.path}: esc_status reports no rotor speeds (esc_rpm always 0)",
            hint="pass --motor-curve (a vehicle or 'slope,offset') to use actuator_outputs",
        )
    return Stream("esc_status", t, speeds)


def _output_functions(params: dict[str, Any]) -> tuple[dict[int, int], str | None]:
    """Motor index (0..3) per actuator_outputs channel (0-based) and the parameter prefix that said so."""
    found: dict[str, dict[int, int]] = {}
    for key, value in params.items():
        m = re.fullmatch(r"([A-Z0-9_]+)_FUNC(\d+)", key)
        if m and int(value) in MOTOR_FUNCTIONS:
            found.setdefault(m.group(1), {})[int(m.group(2)) - 1] = int(value) - 101
    if not found:
        return {i: i for i in range(4)}, None
    prefix = "PWM_MAIN" if "PWM_MAIN" in found else sorted(found)[0]
    return found[prefix], prefix


def _pwm_range(params: dict[str, Any], prefix: str | None, channel: int) -> tuple[float, float]:
    """(min, max) PWM us of an output channel (0-based): <PREFIX>_MINn/MAXn, else PWM_MIN/PWM_MAX (v1.6
    era), else PX4's defaults 1000 and 2000 us."""
    lo = params.get(f"{prefix}_MIN{channel + 1}") if prefix else None
    hi = params.get(f"{prefix}_MAX{channel + 1}") if prefix else None
    lo = float(lo if lo is not None else params.get("PWM_MIN", 1000.0))
    hi = float(hi if hi is not None else params.get("PWM_MAX", 2000.0))
    return lo, hi


# PX4's Quad-X mixer: throttle of motors 1..4 = thrust + roll*r + pitch*p + yaw*y (actuator_controls_0)
QUAD_X_MIX = np.array([[-1.0, 1.0, 1.0], [1.0, -1.0, 1.0], [1.0, 1.0, -1.0], [-1.0, -1.0, -1.0]])


def _median_interval(topics: _Topics, name: str) -> float:
    """Median sample interval (s) of a topic, inf with fewer than two samples."""
    t = topics.times(topics.get(name, "its rate"))
    return float(np.median(np.diff(t))) if len(t) > 1 else float("inf")


def _px4_output_for_thrust(thrust: np.ndarray, factor: float) -> np.ndarray:
    """PX4's motor output u in [0, 1] for normalised thrust t: the root of t = (1 - f) u + f u^2
    (THR_MDL_FAC f), as PX4's output driver computes it from actuator_motors."""
    t = np.clip(thrust, 0.0, 1.0)
    if factor <= 0.0:
        return t
    b = 1.0 - factor
    return (-b + np.sqrt(b * b + 4.0 * factor * t)) / (2.0 * factor)


def _actuator_throttle_stream(topics: _Topics, notes: list[str]) -> Stream:
    """Motor throttles in [0, 1] (motor order): actuator_outputs, actuator_motors or actuator_controls_0.

    actuator_motors is taken over actuator_outputs when it is logged at least 1.5x as often (PX4's system
    identification logging profile, SDLOG_PROFILE bit 3, logs it at the control rate, actuator_outputs at
    10 Hz); it holds normalised thrust, turned into the output through THR_MDL_FAC when the log has it."""
    params = topics.ulog.initial_parameters
    motors_faster = topics.has("actuator_outputs") and topics.has("actuator_motors") and \
        "THR_MDL_FAC" in params and \
        _median_interval(topics, "actuator_motors") * 1.5 <= _median_interval(topics, "actuator_outputs")
    if topics.has("actuator_outputs") and not motors_faster:
        data = topics.get("actuator_outputs", "the motor commands")
        t = topics.times(data)
        channels, prefix = _output_functions(params)
        thr = np.full((len(t), 4), np.nan)
        raw = {ch: data[f"output[{ch}]"].astype(float) for ch in channels if f"output[{ch}]" in data}
        if len(raw) < 4 or sorted(channels[c] for c in raw) != [0, 1, 2, 3]:
            raise UserError(
                f"px4 log {topics.path}: actuator_outputs does not hold four motor channels",
                hint="check the <PREFIX>_FUNCn parameters (101..104 = motors 1..4)",
            )
        pwm = max(np.nanmax(v) for v in raw.values()) > 2.0
        ranges = set()
        for ch, values in raw.items():
            motor = channels[ch]
            if pwm:
                lo, hi = _pwm_range(params, prefix, ch)
                ranges.add(f"{lo:g}-{hi:g}")
                thr[:, motor] = np.clip((values - lo) / (hi - lo), 0.0, 1.0)
            else:
                thr[:, motor] = np.clip(values, 0.0, 1.0)
        how = f"PWM us {', '.join(sorted(ranges))}, (v - min)/(max - min)" if pwm else "normalized"
        notes.append(f"motor commands from actuator_outputs ({how}; channels by {prefix or 'default'}_FUNCn)")
        return Stream("actuator_outputs", t, thr)
    if topics.has("actuator_motors"):
        data = topics.get("actuator_motors", "the motor commands")
        thr = np.clip(
            _Topics.columns(data, [f"control[{i}]" for i in range(4)], "actuator_motors", topics.path), 0, 1
        )
        if motors_faster:
            factor = float(params["THR_MDL_FAC"])
            thr = _px4_output_for_thrust(thr, factor)
            notes.append(f"motor commands from actuator_motors (normalized thrust through THR_MDL_FAC "
                         f"{factor:g} to the output, motor order; logged more often than actuator_outputs)")
            return Stream("actuator_motors", topics.times(data), thr)
        notes.append("motor commands from actuator_motors (normalized thrust, motor order)")
        return Stream("actuator_motors", topics.times(data), thr)
    data = topics.get(
        "actuator_controls_0", "the motor commands (no actuator_motors or actuator_outputs either)"
    )
    c = _Topics.columns(data, [f"control[{i}]" for i in range(4)], "actuator_controls_0", topics.path)
    thr = np.clip(c[:, 3:4] + c[:, :3] @ QUAD_X_MIX.T, 0.0, 1.0)
    notes.append("motor commands from actuator_controls_0 through PX4's Quad-X mixer (no output topic)")
    return Stream("actuator_controls_0", topics.times(data), thr)


def _esc_is_real(topics: _Topics) -> bool:
    """True when the log has esc_status with non-zero rpm for four motors."""
    if not topics.has("esc_status"):
        return False
    data = topics.get("esc_status", "the rotor speeds")
    rpm = [np.asarray(data.get(f"esc[{i}].esc_rpm", [0]), dtype=float) for i in range(4)]
    return all(np.nanmax(np.abs(r)) > 0 for r in rpm)


def _rate_stream(topics: _Topics, notes: list[str]) -> tuple[Stream, Stream | None]:
    """(body rates FRD rad/s, the log's angular accelerations FRD rad/s^2 or None) from the best topic."""
    path = topics.path
    if topics.has("vehicle_angular_velocity"):
        av = topics.get("vehicle_angular_velocity", "the body rates")
        t = topics.times(av)
        cols = [f"xyz[{i}]" for i in range(3)]
        rates = Stream(
            "vehicle_angular_velocity", t, _Topics.columns(av, cols, "vehicle_angular_velocity", path)
        )
        deriv_cols = [f"xyz_derivative[{i}]" for i in range(3)]
        if all(c in av for c in deriv_cols):
            d = _Topics.columns(av, deriv_cols, "vehicle_angular_velocity", path)
            if np.abs(d).max() > 0:
                return rates, Stream("vehicle_angular_velocity derivative", t, d)
        notes.append(
            "vehicle_angular_velocity has no xyz_derivative: angular accelerations by differentiation"
        )
        return rates, None
    att = topics.get("vehicle_attitude", "the attitude")
    cols = ["rollspeed", "pitchspeed", "yawspeed"]
    if all(k in att for k in cols):
        notes.append(
            "no vehicle_angular_velocity: body rates from vehicle_attitude rollspeed/pitchspeed/yawspeed"
        )
        values = _Topics.columns(att, cols, "vehicle_attitude", path)
        return Stream("vehicle_attitude rates", topics.times(att), values), None
    if topics.has("sensor_combined"):
        sc = topics.get("sensor_combined", "the body rates")
        notes.append("no vehicle_angular_velocity: body rates from sensor_combined.gyro_rad")
        values = _Topics.columns(sc, [f"gyro_rad[{i}]" for i in range(3)], "sensor_combined", path)
        return Stream("sensor_combined gyro", topics.times(sc), values), None
    raise UserError(
        f"px4 log {path} has no body rates: none of vehicle_angular_velocity, vehicle_attitude "
        "rollspeed/pitchspeed/yawspeed, sensor_combined.gyro_rad",
        hint=f"topics in this log: {', '.join(topics.names)}",
    )


def _aux_streams(topics: _Topics) -> dict[str, Stream]:
    """Side columns for segmentation and the motor model: landed, armed, battery voltage, accel_dev."""
    out = {}
    if topics.has("vehicle_land_detected"):
        ld = topics.get("vehicle_land_detected", "ground contact")
        landed = ld["landed"].astype(float)
        out["landed"] = Stream("vehicle_land_detected", topics.times(ld), landed, kind="hold", max_gap=np.inf)
    if topics.has("vehicle_status"):
        vs = topics.get("vehicle_status", "the arming state")
        if "arming_state" in vs:
            armed = (vs["arming_state"] == ARMING_STATE_ARMED).astype(float)
            out["armed"] = Stream("vehicle_status", topics.times(vs), armed, kind="hold", max_gap=np.inf)
    if topics.has("battery_status"):
        bs = topics.get("battery_status", "the battery voltage")
        key = "voltage_filtered_v" if "voltage_filtered_v" in bs else "voltage_v"
        v = bs[key].astype(float)
        if np.nanmax(v) > 0:
            good = v > 0
            out["voltage"] = Stream("battery_status", topics.times(bs)[good], v[good], max_gap=np.inf)
    if topics.has("sensor_combined"):
        sc = topics.get("sensor_combined", "the accelerometer")
        cols = [f"accelerometer_m_s2[{i}]" for i in range(3)]
        if all(c in sc for c in cols):
            f = np.linalg.norm(_Topics.columns(sc, cols, "sensor_combined", topics.path), axis=1)
            dev = np.abs(f - STANDARD_GRAVITY)
            t = (sc["timestamp"].astype(np.int64) - np.int64(topics.t0)) * 1e-6
            width = max(1, int(round(0.02 / max(float(np.median(np.diff(t))), 1e-4))))
            out["accel_dev"] = Stream("sensor_combined accel", t, maximum_filter1d(dev, 2 * width + 1))
    return out


def read_ulog_dataset(
    path: Path,
    targets: str = "truth",
    motor_curve: Any = None,
    rate_hz: float | None = None,
    gravity: float | None = None,
    sensor_settings: SensorTargetSettings | None = None,
) -> Dataset:
    """Dataset of a PX4 ULog: estimator states, rotor speeds (esc rpm or commands), targets, side columns."""
    ulog, notes = _open(path)
    topics = _Topics(ulog, path)
    lp = topics.get("vehicle_local_position", "position and velocity (and the 'truth' linear accelerations)")
    att = topics.get("vehicle_attitude", "the attitude")
    rotor: RotorModel | None = rotor_model(motor_curve)

    t_lp = topics.times(lp)
    pos = _Topics.columns(lp, ["x", "y", "z", "vx", "vy", "vz"], "vehicle_local_position", path)
    s_lp = Stream("vehicle_local_position", t_lp, pos)
    if all(c in lp for c in ("ax", "ay", "az")):
        acc = _Topics.columns(lp, ["ax", "ay", "az"], "vehicle_local_position", path)
        s_acc = Stream("vehicle_local_position acceleration", t_lp, acc)
    else:
        s_acc = Stream(
            "vehicle_local_position velocity derivative",
            s_lp.t,
            stream_derivative(s_lp.t, s_lp.values[:, 3:6]),
        )
        notes.append(
            f"vehicle_local_position has no ax/ay/az: 'truth' accelerations by differentiating its velocity "
            f"({s_lp.rate_hz:.0f} Hz: only the slow part)"
        )
    flags = [f for f in ("xy_valid", "z_valid", "v_xy_valid", "v_z_valid") if f in lp]
    s_valid = Stream(
        "vehicle_local_position validity",
        t_lp,
        np.column_stack([lp[f].astype(float) for f in flags]) if flags else np.ones(len(lp["timestamp"])),
        kind="hold",
        max_gap=np.inf,
    )
    s_att = Stream(
        "vehicle_attitude",
        topics.times(att),
        _Topics.columns(att, [f"q[{i}]" for i in range(4)], "vehicle_attitude", path),
        kind="quaternion",
    )
    s_rate, s_dw = _rate_stream(topics, notes)
    if s_dw is None:
        s_dw = Stream(f"{s_rate.name} derivative", s_rate.t, stream_derivative(s_rate.t, s_rate.values))

    use_esc = rotor is None and _esc_is_real(topics)
    s_thr = None
    try:
        s_thr = _actuator_throttle_stream(topics, [] if use_esc else notes)
    except UserError:
        if not use_esc:
            raise
    if use_esc:
        s_rotor = _esc_rotor_stream(topics)
        notes.append(f"rotor speeds from esc_status rpm at {s_rotor.rate_hz:.1f} Hz, interpolated")
    else:
        s_rotor = s_thr
    if rotor is None and not use_esc:
        notes.append(
            "no rotor speeds in the log (no esc_status rpm): u from the motor commands through a thrust "
            "curve (identification.motor_model; fitted when the model is identified)"
        )

    streams = [s_lp, s_acc, s_att, s_rate, s_dw, s_rotor]
    s_sens = None
    if targets == "sensors":
        s_sens = _sensor_target_stream(
            topics, s_att, gravity, sensor_settings or SensorTargetSettings(), notes
        )
        streams.append(s_sens)

    if rate_hz:
        timeline = uniform_timeline(streams, rate_hz)
    elif topics.has("vehicle_angular_velocity"):
        timeline = s_rate.t
    else:
        timeline = uniform_timeline(streams, DEFAULT_RATE_HZ)
    filt = RowFilter(len(timeline))
    values = {}
    for s in [*streams, s_valid]:
        v, ok = s.resample(timeline)
        values[s.name] = v
        filt.drop(f"gap in {s.name}", ~ok)
    filt.drop("vehicle_local_position not valid", ~(values[s_valid.name] > 0.5).all(axis=1))
    aux = {}
    for name, stream in _aux_streams(topics).items():
        v, ok = stream.resample(timeline)
        aux[name] = np.where(ok, v[:, 0], np.nan)
    if s_thr is not None:
        v, ok = s_thr.resample(timeline)
        aux["throttle"] = np.where(ok[:, None], v, np.nan)

    euler = euler_from_quaternions(values[s_att.name])
    xi = np.concatenate((values[s_lp.name], euler, values[s_rate.name]), axis=1)
    if rotor is not None:
        thr = values[s_rotor.name]
        u, settled = rotor.speeds(timeline, thr)
        filt.drop("motor lag settling after the start or a gap", ~settled & np.isfinite(thr).all(axis=1))
        notes.append(f"motor curve: {rotor.description}")
    elif use_esc:
        u = values[s_rotor.name]
    else:
        u = ThrustCurve().speeds(values[s_rotor.name], None)
    if targets == "truth":
        tgt = np.concatenate((values[s_acc.name], values[s_dw.name]), axis=1)
    else:
        tgt = values[s_sens.name]
    ds = make_dataset(path, "ulog", targets, timeline, xi, u, tgt, filt, notes, aux=aux)  # no flight: says so
    ds.u_from_throttle = rotor is None and not use_esc
    return ds


def _sensor_target_stream(
    topics: _Topics, s_att: Stream, gravity: float | None, settings: SensorTargetSettings, notes: list[str]
) -> Stream:
    """Sensor-derived targets at sensor_combined's times (rotated specific force + g, gyro derivative)."""
    sc = topics.get("sensor_combined", "the 'sensors' targets (accelerometer and gyro)")
    ts = (sc["timestamp"].astype(np.int64) - np.int64(topics.t0)) * 1e-6
    if "gyro_integral_dt" in sc:  # each sample is the mean over the integration interval ending at timestamp
        ts = ts - 0.5e-6 * sc["gyro_integral_dt"].astype(float)
        if np.any(np.diff(ts) <= 0):  # a jittering interval must not reorder the samples
            ts = (sc["timestamp"].astype(np.int64) - np.int64(topics.t0)) * 1e-6
    gyro = _Topics.columns(sc, [f"gyro_rad[{i}]" for i in range(3)], "sensor_combined", topics.path)
    acc = _Topics.columns(sc, [f"accelerometer_m_s2[{i}]" for i in range(3)], "sensor_combined", topics.path)
    ts, imu = uniform_imu(ts, np.hstack([acc, gyro]), notes)
    acc, gyro = imu[:, :3], imu[:, 3:]
    q, ok = s_att.resample(ts)
    euler = euler_from_quaternions(np.where(ok[:, None], q, np.nan))
    g = STANDARD_GRAVITY if gravity is None else float(gravity)
    st = sensor_targets(ts, acc, gyro, euler, gravity=g, settings=settings, dt=nominal_step(ts))
    notes.append(f"sensor targets (g = {g:g} m/s^2): {st.describe(nominal_step(ts))}")
    return Stream("sensor_combined", ts, st.values)
