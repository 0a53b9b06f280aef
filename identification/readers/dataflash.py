"""ArduPilot DataFlash (.bin, through pymavlink's DFReader) -> Dataset, from ArduCopter 3.2 to today.

Messages (times from TimeUS, us since boot; TimeMS, ms, in logs before Copter 3.3):
- ATT: Roll, Pitch, Yaw in degrees (Yaw 0..360) -> ZYX Euler rad, wrapped to [-pi, pi). Its times are the
  default timeline (rate_hz gives a uniform one instead).
- RATE: R, P, Y body rates in deg/s -> FRD rad/s (ArduPilot's body frame is also x forward, y right, z
  down). Without RATE (old logs), the gyro of IMU instance 0 is used.
- XKF1 (EKF3 core C = 0; NKF1 for EKF2 logs; EKF1 for Copter <= 3.4): PN PE PD (m) and VN VE VD (m/s),
  NED from the EKF origin. Without any, POS (Lat, Lng in deg, Alt in m AMSL) made local NED (flat earth
  from the first fix), with the velocity by Savitzky-Golay differentiation, and a warning.
- IMU (instance 0): GyrX..Z (rad/s) and AccX..Z (specific force, m/s^2), FRD.
- rotor speeds: ESC RPM (rpm -> rad/s) per Instance when the ESCs report a non-zero rpm. Otherwise RCOU
  (C1..C14, or Chan1..Chan8 in old logs) PWM (us) -> throttle (PWM - min) / (max - min) with ArduCopter's
  range: MOT_PWM_MIN/MAX, or RC3_MIN/MAX when those are 0, or 1000/2000 us -> a --motor-curve when given,
  else the thrust curve of identification.motor_model (fitted at identification).
  Motor order: ArduPilot's Quad-X numbers its motors like PX4 (AP_MotorsMatrix: motor 1 at 45 deg =
  front-right CCW, 2 at -135 deg = rear-left CCW, 3 at -45 deg = front-left CW, 4 at 135 deg = rear-right
  CW; only the motor-test letters A-D go round clockwise: A = 1, B = 4, C = 2, D = 3). What differs per
  airframe is which output channel drives which motor: SERVOn_FUNCTION = 33..36 means channel n drives
  motor 1..4. We map RCOU channel n and ESC instance n-1 through those parameters (identity when the log
  has none) into u1..u4 in PX4 order.
- side columns (identification.table): throttle (RCOU), voltage (BAT Volt, instance 0), armed (EV 10/11),
  accel_dev (IMU) for the flight segmentation and the motor model.
- targets 'truth': the log's state differentiated (EKF velocity, RATE rates) by Savitzky-Golay with each
  column's window chosen as for sensor targets (identification.targets.choose_savgol); a 25 Hz XKF1
  follows only the slower accelerations. 'sensors': IMU specific force rotated with ATT plus g, IMU gyro
  differentiated (identification.targets), at the IMU rate, then resampled.
"""

from __future__ import annotations

import contextlib
import io
import math
import struct
from pathlib import Path
from typing import Any

import numpy as np

from bridge.errors import UserError
from bridge.geodesy import flat_earth_ned
from identification.motor_model import ThrustCurve
from identification.readers import (
    GAP_FACTOR,
    RowFilter,
    Stream,
    make_dataset,
    rotor_model,
    uniform_imu,
    uniform_timeline,
)
from identification.readers.ardupilot_mixer import INPUTS, fit_mixer, loop_rate_outputs
from identification.table import Dataset
from identification.targets import (
    STANDARD_GRAVITY,
    SensorTargetSettings,
    nominal_step,
    sensor_targets,
    stream_derivative,
)

RPM_TO_RAD_S = 2.0 * math.pi / 60.0
MOTOR_FUNCTIONS = (33, 34, 35, 36)  # SERVOn_FUNCTION of Motor1..Motor4
WANTED = ("ATT", "ANG", "RATE", "IMU", "XKF1", "NKF1", "EKF1", "POS", "ESC", "RCOU", "BAT", "EV", "ARM")
EV_ARMED, EV_DISARMED = 10, 11  # EV Id of ArduCopter's ARMED and DISARMED events


def _walk(data: bytes) -> tuple[int, int]:
    """(bytes the last record lacks, bytes of garbage skipped) by walking the records with their FMTs."""
    lengths = {0x80: 89}
    i, n, garbage = 0, len(data), 0
    while i + 3 <= n:
        if data[i] != 0xA3 or data[i + 1] != 0x95 or data[i + 2] not in lengths:
            garbage += 1
            i += 1
            continue
        mtype = data[i + 2]
        size = lengths[mtype]
        if i + size > n:
            return i + size - n, garbage
        if mtype == 0x80:
            lengths[data[i + 3]] = data[i + 4]
        i += size
    return 0, garbage + (n - i)


def _read(path: Path) -> tuple[dict[str, list[Any]], dict[str, float], list[str]]:
    """Messages of the wanted types, the parameters, and warnings (truncation, skipped garbage)."""
    from pymavlink import DFReader

    data = path.read_bytes()
    notes = []
    cut, garbage = _walk(data)
    if cut:
        notes.append(
            f"dataflash log {path} is truncated (its last record lacks {cut} bytes): using what it holds"
        )
    if garbage:
        notes.append(f"dataflash log {path}: skipped {garbage} bytes that were not records (corrupt?)")
    sink = io.StringIO()
    msgs: dict[str, list[Any]] = {k: [] for k in WANTED}
    try:
        with contextlib.redirect_stdout(sink), contextlib.redirect_stderr(sink):
            reader = DFReader.DFReader_binary(str(path), zero_time_base=True)
            while True:
                m = reader.recv_match(type=list(WANTED))
                if m is None:
                    break
                msgs[m.get_type()].append(m)
            params = dict(reader.params)
            reader.close()
    except (struct.error, ValueError, KeyError, IndexError, OSError, Exception) as exc:
        raise UserError(
            f"dataflash log {path} is corrupt: {type(exc).__name__}: {exc}",
            hint="is it an ArduPilot .bin log? it must start with FMT records",
        ) from None
    return msgs, params, notes


def _need(msgs: dict[str, list[Any]], name: str, path: Path, why: str) -> list[Any]:
    if not msgs.get(name):
        have = ", ".join(k for k, v in msgs.items() if v) or "none of " + ", ".join(WANTED)
        raise UserError(
            f"dataflash log {path} has no {name} messages; they are needed for {why}",
            hint=f"messages found: {have}",
        )
    return msgs[name]


def _field(msgs: list[Any], name: str, path: Path) -> np.ndarray:
    try:
        return np.array([getattr(m, name) for m in msgs], dtype=float)
    except AttributeError:
        raise UserError(f"dataflash log {path}: {msgs[0].get_type()} has no field {name}") from None


def _times(msgs: list[Any], path: Path) -> np.ndarray:
    """Record times (s since boot): TimeUS (us), or TimeMS (ms) in logs before ArduCopter 3.3."""
    if hasattr(msgs[0], "TimeUS"):
        return _field(msgs, "TimeUS", path) * 1e-6
    if hasattr(msgs[0], "TimeMS"):
        return _field(msgs, "TimeMS", path) * 1e-3
    raise UserError(f"dataflash log {path}: {msgs[0].get_type()} has no time field (TimeUS or TimeMS)")


def _motor_of_channel(params: dict[str, float]) -> dict[int, int]:
    """Motor index 0..3 of each output channel (1-based) from SERVOn_FUNCTION; channels 1..4 by default."""
    found = {}
    for key, value in params.items():
        if key.startswith("SERVO") and key.endswith("_FUNCTION") and int(value) in MOTOR_FUNCTIONS:
            try:
                ch = int(key[5:-9])
            except ValueError:
                continue
            found[ch] = int(value) - 33
    if sorted(found.values()) == [0, 1, 2, 3]:
        return found
    return {1: 0, 2: 1, 3: 2, 4: 3}


def _esc_stream(msgs: list[Any], channels: dict[int, int], path: Path) -> Stream:
    t = _times(msgs, path)
    inst = _field(msgs, "Instance", path).astype(int)
    rpm = _field(msgs, "RPM", path)
    # One ESC record per instance: group them per time stamp into rows of 4 motors (the batch of one loop).
    times = np.unique(t)
    speeds = np.full((len(times), 4), np.nan)
    row = np.searchsorted(times, t)
    for r, i, v in zip(row, inst, rpm, strict=True):
        motor = channels.get(int(i) + 1)
        if motor is not None:
            speeds[r, motor] = v * RPM_TO_RAD_S
    # carry the last value of a motor whose record came in another batch, for as long as that motor's
    # records keep coming (GAP_FACTOR of its own median interval): an ESC whose telemetry stops must not
    # hold its last rpm for the rest of the log
    for j in range(4):
        col = speeds[:, j]
        have = np.isfinite(col)
        if have.sum() < 2:
            continue
        idx = np.where(have, np.arange(len(col)), 0)
        np.maximum.accumulate(idx, out=idx)
        max_age = GAP_FACTOR * float(np.median(np.diff(times[have])))
        fresh = have[idx] & (times - times[idx] <= max_age)
        speeds[:, j] = np.where(fresh, col[idx], np.nan)
    return Stream("ESC", times, speeds)


def pwm_range(params: dict[str, float]) -> tuple[float, float, str]:
    """(min, max) motor PWM (us) as ArduCopter uses it, and where it came from: MOT_PWM_MIN/MAX, or the
    throttle channel's RC3_MIN/MAX when those are 0 (unset), or 1000/2000 us when the log has neither."""
    lo, hi = params.get("MOT_PWM_MIN") or 0.0, params.get("MOT_PWM_MAX") or 0.0
    if lo > 0 and hi > lo:
        return float(lo), float(hi), "MOT_PWM_MIN/MAX"
    lo, hi = params.get("RC3_MIN") or 0.0, params.get("RC3_MAX") or 0.0
    if lo > 0 and hi > lo:
        return float(lo), float(hi), "RC3_MIN/MAX (MOT_PWM_MIN/MAX = 0)"
    return 1000.0, 2000.0, "1000-2000 us (no MOT_PWM_MIN/MAX or RC3_MIN/MAX in the log)"


def _rcou_stream(
    msgs: list[Any], channels: dict[int, int], params: dict[str, float], path: Path, notes: list[str]
) -> Stream:
    """Motor throttles in [0, 1] (motor order) from RCOU PWM: C1..C14, or Chan1..Chan8 in old logs."""
    lo, hi, source = pwm_range(params)
    t = _times(msgs, path)
    thr = np.full((len(t), 4), np.nan)
    prefix = "C" if hasattr(msgs[0], "C1") else "Chan"
    for ch, motor in channels.items():
        thr[:, motor] = np.clip((_field(msgs, f"{prefix}{ch}", path) - lo) / (hi - lo), 0.0, 1.0)
    notes.append(f"motor commands from RCOU PWM {lo:g}-{hi:g} us ({source})")
    return Stream("RCOU", t, thr)


def _attitude_stream(att: list[Any], ang: list[Any], path: Path, notes: list[str]) -> Stream:
    """Roll, pitch, yaw (rad) from ANG when it is faster than ATT (ArduCopter 4.6+ logs ATT at 10 Hz and, with
    LOG_BITMASK's ATTITUDE_FAST, ANG at the loop rate), else from ATT."""
    cols = ("Roll", "Pitch", "Yaw")
    euler = np.radians(np.column_stack([_field(att, c, path) for c in cols]))
    s_att = Stream("ATT", _times(att, path), euler, kind="angle")
    if len(ang) > 1 and all(hasattr(ang[0], c) for c in cols):
        s_ang = Stream("ANG", _times(ang, path),
                       np.radians(np.column_stack([_field(ang, c, path) for c in cols])), kind="angle")
        if s_ang.rate_hz > 1.5 * s_att.rate_hz:
            notes.append(f"attitude from ANG at {s_ang.rate_hz:.0f} Hz (ATT is at {s_att.rate_hz:.0f} Hz)")
            return s_ang
    return s_att


def _loop_rate_motors(s_thr: Stream, rate: list[Any], params: dict[str, float], path: Path,
                      notes: list[str]) -> Stream:
    """The motor commands at RATE's rate, rebuilt from its mixer inputs through a mixer fitted on the log's
    RCOU (identification.readers.ardupilot_mixer), when RCOU is much slower and the fit holds; else s_thr."""
    if len(rate) < 2 or not all(hasattr(rate[0], c) for c in INPUTS):
        return s_thr
    rate_t = _times(rate, path)
    s_rate = Stream("RATE", rate_t, np.zeros(len(rate_t)))
    if not s_rate.rate_hz > 2.0 * s_thr.rate_hz:
        return s_thr
    inputs = np.column_stack([_field(rate, c, path) for c in INPUTS])
    fit = fit_mixer(rate_t, inputs, s_thr.t, s_thr.values, params)
    if not fit.usable:
        notes.append(f"motor commands from RCOU at {s_thr.rate_hz:.0f} Hz: not rebuilt at RATE's "
                     f"{s_rate.rate_hz:.0f} Hz ({fit.reason})")
        return s_thr
    now, _ = s_thr.resample(rate_t)
    notes.append(f"motor commands at {s_rate.rate_hz:.0f} Hz from RATE's mixer inputs (AOut, ROut, POut, "
                 f"YOut) through a mixer fitted on RCOU at {s_thr.rate_hz:.0f} Hz ({fit.samples} samples; "
                 "R^2 per motor " + ", ".join(f"{r:.4f}" for r in fit.r2) + ")")
    return Stream("RATE mixer", rate_t, loop_rate_outputs(fit, rate_t, inputs, now, params))


def _aux_streams(msgs: dict[str, list[Any]], imu: list[Any], path: Path) -> dict[str, Stream]:
    """Side columns for segmentation and the motor model: armed (EV, ARM), voltage (BAT), accel_dev (IMU).

    The arming state before the first arming event is the opposite of that event: ArduCopter starts a log at
    arming (LOG_DISARMED 0), so a log whose first event is a disarm was armed from its start.
    """
    out = {}
    events = [(float(t), 1.0 if m.Id == EV_ARMED else 0.0)
              for m, t in zip(msgs["EV"], _times(msgs["EV"], path) if msgs["EV"] else [], strict=True)
              if getattr(m, "Id", None) in (EV_ARMED, EV_DISARMED)]
    arm = [m for m in msgs["ARM"] if hasattr(m, "ArmState")]  # ArduPilot 4.1 and newer
    if arm:
        times = _times(arm, path)
        events += [(float(t), 1.0 if m.ArmState else 0.0) for m, t in zip(arm, times, strict=True)]
    if events:
        events.sort()
        t = np.array([e[0] for e in events])
        armed = np.array([e[1] for e in events])
        out["armed"] = Stream(
            "EV", np.concatenate(([0.0], t)), np.concatenate(([1.0 - armed[0]], armed)), "hold", np.inf
        )
    bat = [m for m in msgs["BAT"] if getattr(m, "Inst", getattr(m, "Instance", 0)) == 0]
    if bat and hasattr(bat[0], "Volt"):
        v = _field(bat, "Volt", path)
        good = v > 0
        if good.any():
            out["voltage"] = Stream("BAT", _times(bat, path)[good], v[good], max_gap=np.inf)
    if imu:
        f = np.linalg.norm(np.column_stack([_field(imu, c, path) for c in ("AccX", "AccY", "AccZ")]), axis=1)
        out["accel_dev"] = Stream(
            "IMU accel", _times(imu, path), np.abs(f - STANDARD_GRAVITY), max_gap=np.inf
        )
    return out


def _position_streams(msgs: dict[str, list[Any]], path: Path, notes: list[str]) -> Stream:
    """Position NED (m) and velocity NED (m/s) as one stream, from XKF1 core 0 or else POS."""
    ekf = msgs["XKF1"] or msgs["NKF1"] or msgs["EKF1"]
    if ekf:
        core = _field(ekf, "C", path) if hasattr(ekf[0], "C") else np.zeros(len(ekf))
        first = [m for m, c in zip(ekf, core, strict=True) if c == core.min()]
        cols = ("PN", "PE", "PD", "VN", "VE", "VD")
        return Stream(
            ekf[0].get_type(), _times(first, path), np.column_stack([_field(first, c, path) for c in cols])
        )
    pos = _need(msgs, "POS", path, "the position and velocity (no XKF1, NKF1 or EKF1 either)")
    t = _times(pos, path)
    lat, lon, alt = (_field(pos, c, path) for c in ("Lat", "Lng", "Alt"))
    p = flat_earth_ned(lat, lon, alt)
    v = stream_derivative(t, p)
    notes.append(
        "no XKF1/NKF1/EKF1: position from POS (flat earth from the first fix), velocity by differentiating it"
    )
    return Stream("POS", t, np.column_stack((p, v)))


def read_dataflash_dataset(
    path: Path,
    targets: str = "truth",
    motor_curve: Any = None,
    rate_hz: float | None = None,
    gravity: float | None = None,
    sensor_settings: SensorTargetSettings | None = None,
) -> Dataset:
    """Dataset of an ArduPilot DataFlash log: EKF states, rotor speeds (ESC or RCOU via a curve), targets."""
    msgs, params, notes = _read(path)
    att = _need(msgs, "ATT", path, "the attitude")
    rotor = rotor_model(motor_curve)
    channels = _motor_of_channel(params)

    s_att = _attitude_stream(att, msgs["ANG"], path, notes)
    imu = [m for m in msgs["IMU"] if getattr(m, "I", 0) == 0]
    if msgs["RATE"]:
        rate = msgs["RATE"]
        s_rate = Stream(
            "RATE",
            _times(rate, path),
            np.radians(np.column_stack([_field(rate, c, path) for c in ("R", "P", "Y")])),
        )
    else:
        if not imu:
            _need(msgs, "RATE", path, "the body rates (no IMU either)")
        s_rate = Stream(
            "IMU gyro",
            _times(imu, path),
            np.column_stack([_field(imu, c, path) for c in ("GyrX", "GyrY", "GyrZ")]),
        )
        notes.append("no RATE: body rates from the IMU gyro")
    s_pos = _position_streams(msgs, path, notes)
    esc = msgs["ESC"] if any(getattr(m, "RPM", 0) for m in msgs["ESC"]) else []
    use_esc = rotor is None and bool(esc)
    s_thr = (
        _rcou_stream(msgs["RCOU"], channels, params, path, [] if use_esc else notes) if msgs["RCOU"] else None
    )
    if s_thr is not None and not use_esc:
        s_thr = _loop_rate_motors(s_thr, msgs["RATE"], params, path, notes)
    if use_esc:
        s_rotor = _esc_stream(esc, channels, path)
    else:
        if s_thr is None:
            _need(msgs, "ESC", path, "the rotor speeds (RPM); without them the motor commands (RCOU)")
        s_rotor = s_thr
        if rotor is not None:
            notes.append(f"rotor speeds from RCOU PWM through {rotor.description}")
        else:
            notes.append(
                "no ESC rpm: u from the RCOU motor commands through a thrust curve (identification."
                "motor_model; fitted when the model is identified), or pass --motor-curve"
            )

    settings = sensor_settings or SensorTargetSettings()
    if targets == "truth":
        d_v = stream_derivative(s_pos.t, s_pos.values[:, 3:6])
        d_w = stream_derivative(s_rate.t, s_rate.values)
        s_tgt = Stream(f"{s_pos.name} velocity derivative", s_pos.t, d_v)
        s_dw = Stream(f"{s_rate.name} derivative", s_rate.t, d_w)
    else:
        if not imu:
            _need(msgs, "IMU", path, "the 'sensors' targets")
        cols = ("AccX", "AccY", "AccZ", "GyrX", "GyrY", "GyrZ")
        raw = np.column_stack([_field(imu, c, path) for c in cols])
        ti, imu_values = uniform_imu(_times(imu, path), raw, notes)
        acc, gyro = imu_values[:, :3], imu_values[:, 3:]
        euler, ok = s_att.resample(ti)
        euler[~ok] = np.nan
        g = STANDARD_GRAVITY if gravity is None else float(gravity)
        st = sensor_targets(ti, acc, gyro, euler, gravity=g, settings=settings, dt=nominal_step(ti))
        notes.append(f"sensor targets (g = {g:g} m/s^2): {st.describe(nominal_step(ti))}")
        s_tgt = Stream("IMU", ti, st.values[:, :3])
        s_dw = Stream("IMU gyro derivative", ti, st.values[:, 3:])

    streams = [s_att, s_rate, s_pos, s_rotor, s_tgt, s_dw]
    timeline = uniform_timeline(streams, rate_hz) if rate_hz else s_att.t
    filt = RowFilter(len(timeline))
    vals = {}
    for s in streams:
        v, ok = s.resample(timeline)
        vals[s.name] = v
        filt.drop(f"gap in {s.name}", ~ok)
    xi = np.concatenate((vals[s_pos.name], vals[s_att.name], vals[s_rate.name]), axis=1)
    if rotor is not None:
        thr = vals[s_rotor.name]
        u, settled = rotor.speeds(timeline, thr)
        filt.drop("motor lag settling after the start or a gap", ~settled & np.isfinite(thr).all(axis=1))
    elif use_esc:
        u = vals[s_rotor.name]
    else:
        u = ThrustCurve().speeds(vals[s_rotor.name], None)
    aux = {}
    for name, stream in _aux_streams(msgs, imu, path).items():
        v, ok = stream.resample(timeline)
        aux[name] = np.where(ok, v[:, 0], np.nan)
    if s_thr is not None:
        v, ok = s_thr.resample(timeline)
        aux["throttle"] = np.where(ok[:, None], v, np.nan)
    tgt = np.concatenate((vals[s_tgt.name], vals[s_dw.name]), axis=1)
    ds = make_dataset(path, "dataflash", targets, timeline, xi, u, tgt, filt, notes, aux=aux)
    ds.u_from_throttle = rotor is None and not use_esc
    return ds
