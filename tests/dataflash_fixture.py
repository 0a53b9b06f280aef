"""Writer of small synthetic ArduPilot DataFlash (.bin) logs for tests.

No real ArduPilot log is available here, so tests fly the SITL's own dynamics (sitl.dynamics.Quadrotor) under
the hover stabiliser with some excitation and write what ArduCopter 4.x would log, in the real binary
format: FMT records (the first describing FMT itself), then PARM, IMU, ATT, RATE, ESC, RCOU, XKF1 and POS
records with ArduPilot's own message formats, units and multipliers (ATT/RATE in degrees, XKF1 angles in
centidegrees, IMU in SI, RCOU in PWM microseconds, ESC in rpm), so that pymavlink's DFReader parses them.
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

HEAD = b"\xa3\x95"
FMT_TYPE = 0x80

# struct codes of the DataFlash format characters (as pymavlink's DFReader.FORMAT_TO_STRUCT)
_STRUCT = {
    "b": "b",
    "B": "B",
    "h": "h",
    "H": "H",
    "i": "i",
    "I": "I",
    "f": "f",
    "d": "d",
    "n": "4s",
    "N": "16s",
    "Z": "64s",
    "c": "h",
    "C": "H",
    "e": "i",
    "E": "I",
    "L": "i",
    "M": "B",
    "q": "q",
    "Q": "Q",
}
_SCALE = {"c": 100.0, "C": 100.0, "e": 100.0, "E": 100.0, "L": 1e7}

# ArduCopter 4.x definitions (name, format, columns)
MESSAGES = {
    "PARM": ("QNff", "TimeUS,Name,Value,Default"),
    "MSG": ("QZ", "TimeUS,Message"),
    "IMU": ("QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz"),
    "ATT": ("QffffffB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,AEKF"),
    "RATE": ("Qfffffffffffff", "TimeUS,RDes,R,ROut,PDes,P,POut,YDes,Y,YOut,ADes,A,AOut,AOutSlew"),
    "ESC": ("QBffffcfcf", "TimeUS,Instance,RPM,RawRPM,Volt,Curr,Temp,CTot,MotTemp,Err"),
    "RCOU": ("QHHHHHHHHHHHHHH", "TimeUS," + ",".join(f"C{i}" for i in range(1, 15))),
    "XKF1": ("QBccCfffffffccce", "TimeUS,C,Roll,Pitch,Yaw,VN,VE,VD,dPD,PN,PE,PD,GX,GY,GZ,OH"),
    "POS": ("QLLfff", "TimeUS,Lat,Lng,Alt,RelHomeAlt,RelOriginAlt"),
    "BAT": ("QBfffffcf", "TimeUS,Inst,Volt,VoltR,Curr,CurrTot,EnrgTot,Temp,Res"),
    "EV": ("QB", "TimeUS,Id"),
}

# ArduCopter 3.2-era definitions (TimeMS in ms, EKF1, RCOU Chan1..Chan8, no RATE or ESC)
OLD_MESSAGES = {
    "PARM": ("Nf", "Name,Value"),
    "MSG": ("Z", "Message"),
    "IMU": ("Iffffff", "TimeMS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ"),
    "ATT": ("IccccCCCC", "TimeMS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw"),
    "RCOU": ("Ihhhhhhhh", "TimeMS," + ",".join(f"Chan{i}" for i in range(1, 9))),
    "EKF1": ("IccCffffffccc", "TimeMS,Roll,Pitch,Yaw,VN,VE,VD,PN,PE,PD,GX,GY,GZ"),
    "POS": ("ILLff", "TimeMS,Lat,Lng,Alt,RelAlt"),
}


class DataFlashWriter:
    """Writes DataFlash records: define(name) emits the FMT record, write(name, **fields) a message."""

    def __init__(self, path: str | Path, messages: dict[str, tuple[str, str]] | None = None):
        self.path = Path(path)
        self.messages = messages or MESSAGES
        self._fh = self.path.open("wb")
        self._types: dict[str, tuple[int, str, list[str]]] = {}
        self._next_type = 0x81
        self._record(
            FMT_TYPE, "BB4s16s64s", FMT_TYPE, 89, b"FMT", b"BBnNZ", b"Type,Length,Name,Format,Columns"
        )

    def _record(self, mtype: int, struct_fmt: str, *values) -> None:
        self._fh.write(HEAD + bytes([mtype]) + struct.pack("<" + struct_fmt, *values))

    def define(self, name: str, fmt: str | None = None, columns: str | None = None) -> None:
        """Emit the FMT record of a message (ArduCopter's definition of self.messages unless given)."""
        fmt = fmt or self.messages[name][0]
        columns = columns or self.messages[name][1]
        mtype = self._next_type
        self._next_type += 1
        length = 3 + struct.calcsize("<" + "".join(_STRUCT[c] for c in fmt))
        self._record(FMT_TYPE, "BB4s16s64s", mtype, length, name.encode(), fmt.encode(), columns.encode())
        self._types[name] = (mtype, fmt, columns.split(","))

    def write(self, name: str, **fields: float | int | str) -> None:
        """Write one message; missing fields are 0; scaled types (c, C, e, E, L) take the physical value."""
        if name not in self._types:
            self.define(name)
        mtype, fmt, cols = self._types[name]
        values = []
        for c, col in zip(fmt, cols, strict=True):
            v = fields.get(col, 0)
            if c in "nNZ":
                values.append(str(v).encode())
            elif c in _SCALE:
                values.append(int(round(float(v) * _SCALE[c])))
            elif c in "fd":
                values.append(float(v))
            else:
                values.append(int(v))
        self._record(mtype, "".join(_STRUCT[c] for c in fmt), *values)

    def close(self) -> None:
        """Flush and close the file."""
        self._fh.close()


@dataclass
class SyntheticFlight:
    """Truth of the synthetic flight at IMU rate: time (s), xi (N,12), rotor speeds (N,4) PX4 order,
    accelerations (N,6) from the dynamics, and the throttles (N,4) commanded."""

    t: np.ndarray
    xi: np.ndarray
    u: np.ndarray
    accel: np.ndarray
    throttle: np.ndarray
    params: dict[str, float] = field(default_factory=dict)


def fly_synthetic(duration: float = 6.0, seed: int = 0) -> SyntheticFlight:
    """Fly the default vehicle (ground none, from 50 m) stabilised, with random excitation; 250 Hz truth."""
    from bridge.vehicle import load_vehicle
    from identification.hover_stabilizer import HoverStabilizer, Reference
    from sitl.dynamics import Quadrotor

    veh = load_vehicle("fang-chen-buaa").with_overrides(ground="none", initial_position=(0.0, 0.0, -50.0))
    quad = Quadrotor(veh)
    quad.reset(position=(0.0, 0.0, -50.0), rotor_speeds=(veh.hover_speed,) * 4)
    stab = HoverStabilizer(veh)
    curve = veh.motor_curve
    rng = np.random.default_rng(seed)
    n = int(round(duration / 0.004))
    t = np.arange(n) * 0.004
    xi, u, acc, thr = (np.empty((n, k)) for k in (12, 4, 6, 4))
    # smooth excitation per motor (a sum of sines): a 25 Hz EKF log can still follow the accelerations
    freq = rng.uniform(0.8, 3.0, (4, 3))
    phase = rng.uniform(0.0, 2.0 * math.pi, (4, 3))
    for k in range(n):
        xi[k] = (*quad.position, *quad.velocity, *quad.euler, *quad.rates)
        u[k] = quad.rotor_speeds
        extra = 30.0 * np.sin(2.0 * math.pi * freq * t[k] + phase).sum(axis=1)
        ref = Reference(
            (math.sin(0.5 * t[k]), 0.5 * math.sin(0.7 * t[k]), -50.0), yaw=0.4 * math.sin(0.3 * t[k])
        )
        speeds = stab.command(xi[k], ref) + extra
        thr[k] = [curve.throttle_for_speed(float(w)) for w in speeds]
        acc[k, :3] = quad.acceleration_earth()
        acc[k, 3:] = quad.angular_acceleration()
        # the specific force goes in the IMU record: keep it with the accelerations for the writer
        quad.step(thr[k])
    return SyntheticFlight(t, xi, u, acc, thr)


def specific_force(xi: np.ndarray, accel_ned: np.ndarray, g: float) -> np.ndarray:
    """Specific force FRD (N,3) m/s^2 = R^T (a - g e3) for states xi (N,12) and NED accelerations (N,3)."""
    from bridge.rotations import rotation_matrix

    r = rotation_matrix(xi[:, 6], xi[:, 7], xi[:, 8])
    a = accel_ned.copy()
    a[:, 2] -= g
    return np.einsum("nji,nj->ni", r, a)


def ekf_fields(x: np.ndarray) -> dict[str, float]:
    """The EKF record's attitude (deg, yaw 0..360), velocity NED (m/s) and position NED (m) of a state."""
    return {
        "Roll": math.degrees(x[6]),
        "Pitch": math.degrees(x[7]),
        "Yaw": math.degrees(x[8]) % 360.0,
        "VN": x[3],
        "VE": x[4],
        "VD": x[5],
        "PN": x[0],
        "PE": x[1],
        "PD": x[2],
    }


def write_flight(
    path: str | Path,
    flight: SyntheticFlight,
    *,
    channel_of_motor: tuple[int, int, int, int] = (1, 2, 3, 4),
    g: float = 9.8,
    xkf_every: int = 10,
    att_every: int = 1,
    esc_every: int = 25,
    with_esc: bool = True,
    with_rcou: bool = True,
    with_xkf1: bool = True,
    with_pos: bool = True,
    with_att: bool = True,
    time0_us: int = 5_000_000,
    esc_silent: tuple[int, float] | None = None,
) -> Path:
    """Write a synthetic flight as an ArduCopter DataFlash log.

    channel_of_motor: the output channel (1-based) of motors 1..4 (PX4/ArduPilot Quad-X numbering); written
    as SERVOn_FUNCTION = 33..36 parameters, and ESC instances follow the channels (instance = channel - 1).
    esc_silent: (channel, s of flight time): that channel's ESC telemetry stops then (a lost wire).
    """
    w = DataFlashWriter(path)
    for name in MESSAGES:
        w.define(name)
    w.write("MSG", TimeUS=time0_us - 1000, Message="ArduCopter V4.5.7 (synthetic)")
    params = {"MOT_PWM_MIN": 1000.0, "MOT_PWM_MAX": 2000.0, "FRAME_CLASS": 1.0, "FRAME_TYPE": 1.0}
    for motor, ch in enumerate(channel_of_motor):
        params[f"SERVO{ch}_FUNCTION"] = 33.0 + motor
    for name, value in params.items():
        w.write("PARM", TimeUS=time0_us - 500, Name=name, Value=value, Default=value)
    f = specific_force(flight.xi, flight.accel[:, :3], g)
    w.write("EV", TimeUS=time0_us - 200, Id=10)  # ARMED
    lat0, lon0, alt0 = -35.363261, 149.165230, 584.0
    motor_of_channel = {ch: m for m, ch in enumerate(channel_of_motor)}
    for k, tk in enumerate(flight.t):
        tu = time0_us + int(round(tk * 1e6))
        x = flight.xi[k]
        w.write(
            "IMU",
            TimeUS=tu,
            I=0,
            GyrX=x[9],
            GyrY=x[10],
            GyrZ=x[11],
            AccX=f[k, 0],
            AccY=f[k, 1],
            AccZ=f[k, 2],
            GH=1,
            AH=1,
            GHz=250,
            AHz=250,
        )
        if with_att and k % att_every == 0:
            yaw_deg = math.degrees(x[8]) % 360.0
            w.write("ATT", TimeUS=tu, Roll=math.degrees(x[6]), Pitch=math.degrees(x[7]), Yaw=yaw_deg, AEKF=3)
            w.write("RATE", TimeUS=tu, R=math.degrees(x[9]), P=math.degrees(x[10]), Y=math.degrees(x[11]))
        if with_rcou:
            pwm = {
                f"C{ch}": int(round(1000 + 1000 * flight.throttle[k, m]))
                for m, ch in enumerate(channel_of_motor)
            }
            w.write("RCOU", TimeUS=tu, **pwm)
        if with_esc and k % esc_every == 0:
            for ch in sorted(motor_of_channel):
                if esc_silent is not None and ch == esc_silent[0] and tk >= esc_silent[1]:
                    continue
                rpm = flight.u[k, motor_of_channel[ch]] * 60.0 / (2.0 * math.pi)
                w.write("ESC", TimeUS=tu, Instance=ch - 1, RPM=rpm, RawRPM=rpm, Volt=16.0, Curr=5.0, Temp=30)
        if k % 25 == 0:
            w.write("BAT", TimeUS=tu, Inst=0, Volt=16.0 - 0.1 * tk, VoltR=16.0, Curr=5.0)
        if k % xkf_every == 0:
            if with_xkf1:
                w.write("XKF1", TimeUS=tu, C=0, **ekf_fields(x))
                w.write(
                    "XKF1", TimeUS=tu, C=1, VN=99.0, VE=99.0, VD=99.0, PN=99.0, PE=99.0, PD=99.0
                )  # core 1
            if with_pos:
                lat = lat0 + math.degrees(x[0] / 6378137.0)
                lon = lon0 + math.degrees(x[1] / (6378137.0 * math.cos(math.radians(lat0))))
                w.write(
                    "POS", TimeUS=tu, Lat=lat, Lng=lon, Alt=alt0 - x[2], RelHomeAlt=-x[2], RelOriginAlt=-x[2]
                )
    w.close()
    return Path(path)


def write_old_flight(
    path: str | Path, flight: SyntheticFlight, *, g: float = 9.8, rc3: tuple[int, int] = (1100, 1900)
) -> Path:
    """Write a synthetic flight as an ArduCopter 3.2-era DataFlash log: TimeMS, IMU/ATT/RCOU at 50 Hz,
    EKF1 at 25 Hz, ATT in centidegrees, RCOU Chan1..4 in the RC3_MIN..RC3_MAX range with MOT_PWM_MIN/MAX = 0
    (ArduCopter then uses the throttle channel's range), no RATE, ESC or SERVOn_FUNCTION."""
    w = DataFlashWriter(path, OLD_MESSAGES)
    for name in OLD_MESSAGES:
        w.define(name)
    w.write("MSG", Message="ArduCopter V3.2.1 (synthetic)")
    params = {"MOT_PWM_MIN": 0.0, "MOT_PWM_MAX": 0.0, "RC3_MIN": float(rc3[0]), "RC3_MAX": float(rc3[1])}
    for name, value in params.items():
        w.write("PARM", Name=name, Value=value)
    f = specific_force(flight.xi, flight.accel[:, :3], g)
    for k, tk in enumerate(flight.t):
        tm = 5000 + int(round(tk * 1e3))
        x = flight.xi[k]
        if k % 5 == 0:  # 50 Hz: TimeMS resolves 1 ms, so every 4 ms sample would repeat times
            w.write(
                "IMU", TimeMS=tm, GyrX=x[9], GyrY=x[10], GyrZ=x[11], AccX=f[k, 0], AccY=f[k, 1], AccZ=f[k, 2]
            )
            w.write(
                "ATT",
                TimeMS=tm,
                Roll=math.degrees(x[6]),
                Pitch=math.degrees(x[7]),
                Yaw=math.degrees(x[8]) % 360.0,
            )
            pwm = {
                f"Chan{m + 1}": int(round(rc3[0] + (rc3[1] - rc3[0]) * flight.throttle[k, m]))
                for m in range(4)
            }
            w.write("RCOU", TimeMS=tm, **pwm)
        if k % 10 == 0:
            w.write("EKF1", TimeMS=tm, **ekf_fields(x))
    w.close()
    return Path(path)
