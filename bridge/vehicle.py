"""The vehicle file: a quadrotor's physical, motor, sensor and simulation settings as typed, validated data.

Shared by every process: the SITL simulates it, the clients use its motor curve, the true model is written
from it. Units SI, earth frame NED, body frame FRD (see docs/design.md).
"""

from __future__ import annotations

import dataclasses
import hashlib
import importlib.util
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bridge.errors import UserError
from bridge.yaml_file import describe_value, float_value, load_yaml_file

Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]

EXCHANGE_STEP = 0.004  # s, the HIL exchange step (250 Hz); the physics step must divide it
SENSOR_PRESETS = ("realistic", "ideal")
GROUND_MODELS = ("plane", "none")


@dataclass(frozen=True)
class MotorCurve:
    """Throttle sigma in [0, 1] <-> steady rotor speed w = Cr*sigma + wb (rad/s), clipped to [0, w_max]."""

    curve_slope: float  # Cr, rad/s per unit throttle
    curve_offset: float  # wb, rad/s

    @property
    def max_speed(self) -> float:
        """Steady rotor speed at full throttle, rad/s (Cr + wb)."""
        return self.curve_slope + self.curve_offset

    def speed_for_throttle(self, sigma: float) -> float:
        """Steady rotor speed (rad/s) for throttle sigma (clipped to [0, 1] first)."""
        s = min(max(sigma, 0.0), 1.0)
        return min(max(self.curve_slope * s + self.curve_offset, 0.0), self.max_speed)

    def throttle_for_speed(self, w: float) -> float:
        """Throttle in [0, 1] giving steady speed w (rad/s); w is clipped to [0, w_max] first.

        w <= 0 maps to -wb/Cr (0.123 for the default vehicle): the largest throttle that still gives 0 rad/s,
        so the inverse is continuous over [0, w_max] and speed_for_throttle(throttle_for_speed(w)) == w.
        """
        wc = min(max(w, 0.0), self.max_speed)
        return min(max((wc - self.curve_offset) / self.curve_slope, 0.0), 1.0)

    @staticmethod
    def hover_speed(mass: float, gravity: float, thrust_coefficient: float) -> float:
        """Rotor speed (rad/s) at which four equal rotors carry the weight: sqrt(m g / (4 Ct))."""
        return math.sqrt(mass * gravity / (4.0 * thrust_coefficient))


@dataclass(frozen=True)
class MotorConfig:
    """Motor dynamics: first-order lag toward the curve's steady speed."""

    time_constant: float  # Tm, s
    curve_slope: float  # Cr, rad/s
    curve_offset: float  # wb, rad/s
    rotor_inertia: float  # Jm, kg m^2 (rotor + motor bell about the shaft, for the gyroscopic torque)


@dataclass(frozen=True)
class DragConfig:
    """Aerodynamic damping: body-frame quadratic drag and linear angular damping."""

    body_quadratic: Vec3  # Cd per body axis FRD, N/(m/s)^2: F_b,i = -Cd_i * v_b,i * |v_b,i|
    angular_damping: Vec3  # D per body axis FRD, N m s/rad: tau_i = -D_i * w_i


@dataclass(frozen=True)
class InitialConfig:
    """Where the vehicle starts: position NED (m) and yaw (rad), level and at rest."""

    position: Vec3
    yaw: float


@dataclass(frozen=True)
class SimulationConfig:
    """Integration settings."""

    physics_step: float  # s, RK4 substep; must divide the 4 ms exchange step
    seed: int  # seed of the sensor noise (CLI --seed overrides it)

    @property
    def substeps(self) -> int:
        """Number of physics substeps per 4 ms exchange step."""
        return int(round(EXCHANGE_STEP / self.physics_step))


@dataclass(frozen=True)
class ImuNoiseConfig:
    """White noise std and constant bias of a 3-axis sensor, per body axis FRD (unit of the sensor)."""

    noise: Vec3
    bias: Vec3


@dataclass(frozen=True)
class MagConfig:
    """Magnetometer: noise std and bias (gauss, FRD) and the earth field at home (gauss, NED)."""

    noise: Vec3
    bias: Vec3
    earth_field: Vec3


@dataclass(frozen=True)
class BaroConfig:
    """Barometer: white noise std and constant offset of the absolute pressure, Pa (as PX4's baro sim)."""

    noise: float  # Pa
    bias: float  # Pa


@dataclass(frozen=True)
class GpsConfig:
    """GPS: white noise std and constant bias of position (m, NED) and velocity (m/s, NED)."""

    horizontal_noise: float  # m, std of north and east
    vertical_noise: float  # m, std of down
    velocity_noise: float  # m/s, std per NED axis
    bias: Vec3  # m, NED
    eph: float  # m, reported horizontal accuracy
    epv: float  # m, reported vertical accuracy
    satellites: int


@dataclass(frozen=True)
class SensorsConfig:
    """Sensor noise and bias; preset 'ideal' zeroes every noise and bias (see effective())."""

    preset: str  # realistic | ideal
    accel: ImuNoiseConfig  # m/s^2
    gyro: ImuNoiseConfig  # rad/s
    mag: MagConfig
    baro: BaroConfig
    gps: GpsConfig

    def effective(self) -> SensorsConfig:
        """The settings the sensor model uses: these for 'realistic', all noise and bias 0 for 'ideal'."""
        if self.preset != "ideal":
            return self
        z3 = (0.0, 0.0, 0.0)
        return dataclasses.replace(
            self,
            accel=ImuNoiseConfig(z3, z3),
            gyro=ImuNoiseConfig(z3, z3),
            mag=dataclasses.replace(self.mag, noise=z3, bias=z3),
            baro=BaroConfig(0.0, 0.0),
            gps=dataclasses.replace(self.gps, horizontal_noise=0.0, vertical_noise=0.0, velocity_noise=0.0,
                                    bias=z3),
        )


@dataclass(frozen=True)
class HomeConfig:
    """Geodetic origin of the NED frame: latitude and longitude (deg, WGS84), altitude (m AMSL)."""

    lat: float
    lon: float
    alt: float


@dataclass(frozen=True)
class VehicleConfig:
    """A quadrotor as loaded from a vehicle file (all SI, NED/FRD)."""

    name: str
    mass: float  # kg
    gravity: float  # m/s^2
    inertia: Mat3  # kg m^2, body FRD
    arm_length: float  # m, centre to rotor axis
    thrust_coefficient: float  # Ct, N/(rad/s)^2
    moment_coefficient: float  # Cm, N m/(rad/s)^2
    motor: MotorConfig
    drag: DragConfig
    ground: str  # plane | none
    initial: InitialConfig
    simulation: SimulationConfig
    sensors: SensorsConfig
    home: HomeConfig
    source_path: Path | None = None

    @property
    def motor_curve(self) -> MotorCurve:
        """The throttle <-> steady rotor speed curve."""
        return MotorCurve(self.motor.curve_slope, self.motor.curve_offset)

    @property
    def hover_speed(self) -> float:
        """Rotor speed (rad/s) at which four equal rotors carry the weight."""
        return MotorCurve.hover_speed(self.mass, self.gravity, self.thrust_coefficient)

    @property
    def mixer_gain(self) -> float:
        """k = (sqrt(2)/2) d Ct: roll/pitch torque per (rad/s)^2 for Quad-X, N m/(rad/s)^2."""
        return math.sqrt(2.0) / 2.0 * self.arm_length * self.thrust_coefficient

    def with_overrides(
        self,
        ground: str | None = None,
        initial_position: tuple[float, float, float] | None = None,
        sensors: str | None = None,
        seed: int | None = None,
        initial_yaw: float | None = None,
    ) -> VehicleConfig:
        """A copy with CLI-style overrides applied (validated like the file)."""
        where = f"override of vehicle {self.name}"
        cfg = self
        if ground is not None:
            if ground not in GROUND_MODELS:
                raise UserError(f"{where}: ground must be one of {', '.join(GROUND_MODELS)}, got {ground!r}")
            cfg = dataclasses.replace(cfg, ground=ground)
        if initial_position is not None or initial_yaw is not None:
            pos = cfg.initial.position if initial_position is None else _vec3_value(where, "initial.position",
                                                                                      initial_position)
            yaw = cfg.initial.yaw if initial_yaw is None else float_value(where, "initial.yaw", initial_yaw)
            cfg = dataclasses.replace(cfg, initial=InitialConfig(pos, yaw))
        if sensors is not None:
            if sensors not in SENSOR_PRESETS:
                raise UserError(f"{where}: sensors must be one of {', '.join(SENSOR_PRESETS)}, "
                                f"got {sensors!r}")
            cfg = dataclasses.replace(cfg, sensors=dataclasses.replace(cfg.sensors, preset=sensors))
        if seed is not None:
            if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
                raise UserError(f"{where}: seed must be an integer >= 0, got {seed!r}")
            cfg = dataclasses.replace(cfg, simulation=dataclasses.replace(cfg.simulation, seed=seed))
        _check_initial(where, cfg)
        return cfg


# ----------------------------------------------------------------------------------------------------------
# Locating and loading


def vehicles_dir() -> Path:
    """The folder of the bundled vehicle files (sitl/vehicles), found without importing sitl."""
    spec = importlib.util.find_spec("sitl")
    if spec is not None and spec.submodule_search_locations:
        for location in spec.submodule_search_locations:
            candidate = Path(location) / "vehicles"
            if candidate.is_dir():
                return candidate
    return Path(__file__).resolve().parent.parent / "sitl" / "vehicles"


def list_vehicles() -> list[str]:
    """Names of the bundled vehicle files (without .yaml), sorted."""
    folder = vehicles_dir()
    return sorted(p.stem for p in folder.glob("*.yaml")) if folder.is_dir() else []


def resolve_vehicle_path(path_or_name: str | Path) -> Path:
    """A vehicle file path: an existing path as given, else a bundled name (sitl/vehicles/<name>.yaml)."""
    text = str(path_or_name)
    path = Path(text)
    if path.is_file():
        return path
    if path.is_dir():
        raise UserError(f"vehicle file {text}: is a directory, not a file",
                        hint="give the vehicle YAML file inside it, e.g. --vehicle "
                        f"{path / 'my-quad.yaml'}, or a bundled name ({', '.join(list_vehicles())})")
    looks_like_name = "/" not in text and "\\" not in text and not text.endswith((".yaml", ".yml"))
    if looks_like_name:
        bundled = vehicles_dir() / f"{text}.yaml"
        if bundled.is_file():
            return bundled
    known = ", ".join(list_vehicles()) or "none found"
    raise UserError(
        f"vehicle file {text}: not found",
        hint=f"give a path to a vehicle YAML file or a bundled name ({known})",
    )


def vehicle_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a vehicle file's bytes (a bare name is resolved first)."""
    return hashlib.sha256(resolve_vehicle_path(path).read_bytes()).hexdigest()


def load_vehicle(path_or_name: str | Path) -> VehicleConfig:
    """Load and validate a vehicle file (path or bundled name); each mistake is a UserError naming the key."""
    path = resolve_vehicle_path(path_or_name)
    where = f"vehicle file {path}"
    data = load_yaml_file(path, where)
    return _parse(where, data, path)


# ----------------------------------------------------------------------------------------------------------
# Validation


class _Section:
    """Reads one mapping of the file, tracking the dotted key path and rejecting unknown keys."""

    def __init__(self, where: str, data: Any, prefix: str):
        self.where = where
        self.prefix = prefix
        if not isinstance(data, dict):
            what = f"key '{prefix}'" if prefix else "the top level"
            raise UserError(f"{where}: {what} must be a mapping, got {describe_value(data)}")
        self.data = data
        self.used: set[str] = set()

    def key(self, name: str) -> str:
        return f"{self.prefix}.{name}" if self.prefix else name

    def raw(self, name: str, default: Any = ...) -> Any:
        self.used.add(name)
        if name not in self.data:
            if default is ...:
                raise UserError(f"{self.where}: missing key '{self.key(name)}'",
                                hint="see sitl/vehicles/fang-chen-buaa.yaml for every key with its unit")
            return default
        return self.data[name]

    def section(self, name: str) -> _Section:
        return _Section(self.where, self.raw(name), self.key(name))

    def number(self, name: str, *, positive: bool = False, nonnegative: bool = False,
               default: Any = ...) -> float:
        value = float_value(self.where, self.key(name), self.raw(name, default))
        _check_sign(self.where, self.key(name), value, positive, nonnegative)
        return value

    def integer(self, name: str, *, nonnegative: bool = True, default: Any = ...) -> int:
        value = self.raw(name, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise UserError(f"{self.where}: key '{self.key(name)}' must be an integer, "
                            f"got {describe_value(value)}")
        if nonnegative and value < 0:
            raise UserError(f"{self.where}: key '{self.key(name)}' must be >= 0, got {value}")
        return value

    def text(self, name: str, choices: tuple[str, ...] | None = None, default: Any = ...) -> str:
        value = self.raw(name, default)
        if not isinstance(value, str):
            raise UserError(f"{self.where}: key '{self.key(name)}' must be a string, "
                            f"got {describe_value(value)}")
        if choices is not None and value not in choices:
            raise UserError(f"{self.where}: key '{self.key(name)}' must be one of {', '.join(choices)}, "
                            f"got {value!r}")
        return value

    def vec3(self, name: str, *, nonnegative: bool = False, scalar_ok: bool = False,
             default: Any = ...) -> Vec3:
        value = self.raw(name, default)
        if scalar_ok and not isinstance(value, (list, tuple)):
            v = float_value(self.where, self.key(name), value)
            out = (v, v, v)
        else:
            out = _vec3_value(self.where, self.key(name), value)
        for v in out:
            _check_sign(self.where, self.key(name), v, False, nonnegative)
        return out

    def done(self) -> None:
        unknown = [k for k in self.data if k not in self.used]
        if unknown:
            known = ", ".join(sorted(self.used))
            raise UserError(f"{self.where}: unknown key '{self.key(str(unknown[0]))}'",
                            hint=f"keys allowed here: {known}")


def _vec3_value(where: str, key: str, value: Any) -> Vec3:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise UserError(f"{where}: key '{key}' must be a list of 3 numbers, got {describe_value(value)}")
    return tuple(float_value(where, f"{key}[{i}]", v) for i, v in enumerate(value))  # type: ignore[return-value]


def _check_sign(where: str, key: str, value: float, positive: bool, nonnegative: bool) -> None:
    if positive and not value > 0:
        raise UserError(f"{where}: key '{key}' must be > 0, got {value:g}")
    if nonnegative and not value >= 0:
        raise UserError(f"{where}: key '{key}' must be >= 0, got {value:g}")


def _inertia(sec: _Section) -> Mat3:
    key = sec.key("inertia")
    value = sec.raw("inertia")
    is_seq = isinstance(value, (list, tuple)) and len(value) == 3
    if is_seq and all(not isinstance(v, (list, tuple)) for v in value):
        d = _vec3_value(sec.where, key, value)  # the diagonal only
        mat = ((d[0], 0.0, 0.0), (0.0, d[1], 0.0), (0.0, 0.0, d[2]))
    elif is_seq:
        mat = tuple(_vec3_value(sec.where, f"{key}[{i}]", row) for i, row in enumerate(value))  # type: ignore
    else:
        raise UserError(f"{sec.where}: key '{key}' must be 3 diagonal values or a 3x3 matrix (kg m^2), "
                        f"got {describe_value(value)}")
    for i in range(3):
        for j in range(i + 1, 3):
            a, b = mat[i][j], mat[j][i]
            if abs(a - b) > 1e-12 * max(1.0, abs(a), abs(b)):
                raise UserError(f"{sec.where}: key '{key}' must be symmetric, but [{i}][{j}] = {a:g} and "
                                f"[{j}][{i}] = {b:g}")
    # Sylvester's criterion: every leading principal minor > 0.
    m1 = mat[0][0]
    m2 = mat[0][0] * mat[1][1] - mat[0][1] * mat[1][0]
    m3 = _det3(mat)
    if not (m1 > 0 and m2 > 0 and m3 > 0):
        raise UserError(f"{sec.where}: key '{key}' must be positive definite (kg m^2), "
                        f"got {[list(row) for row in mat]}",
                        hint="principal moments must be positive; check signs and units")
    return mat  # type: ignore[return-value]


def _det3(m: Mat3) -> float:
    return (m[0][0] * (m[1][1] * m[2][2] - m[1][2] * m[2][1])
            - m[0][1] * (m[1][0] * m[2][2] - m[1][2] * m[2][0])
            + m[0][2] * (m[1][0] * m[2][1] - m[1][1] * m[2][0]))


def _check_initial(where: str, cfg: VehicleConfig) -> None:
    if cfg.ground == "plane" and cfg.initial.position[2] > 0:
        raise UserError(f"{where}: key 'initial.position' has z = {cfg.initial.position[2]:g} m, below the "
                        "ground plane (NED: z > 0 is underground)",
                        hint="use z <= 0 (e.g. -10 for 10 m up), or ground: none")


def _parse(where: str, data: Any, path: Path) -> VehicleConfig:
    if data is None:
        raise UserError(f"{where}: the file is empty")
    top = _Section(where, data, "")
    name = top.text("name")
    mass = top.number("mass", positive=True)
    gravity = top.number("gravity", nonnegative=True)
    inertia = _inertia(top)
    arm = top.number("arm_length", positive=True)
    ct = top.number("thrust_coefficient", positive=True)
    cm = top.number("moment_coefficient", positive=True)

    ms = top.section("motor")
    motor = MotorConfig(
        time_constant=ms.number("time_constant", positive=True),
        curve_slope=ms.number("curve_slope", positive=True),
        curve_offset=ms.number("curve_offset"),
        rotor_inertia=ms.number("rotor_inertia", nonnegative=True),
    )
    ms.done()
    if motor.curve_slope + motor.curve_offset <= 0:
        raise UserError(f"{where}: keys 'motor.curve_slope' + 'motor.curve_offset' (the full-throttle speed) "
                        f"must be > 0, got {motor.curve_slope + motor.curve_offset:g} rad/s")

    ds = top.section("drag")
    drag = DragConfig(
        body_quadratic=ds.vec3("body_quadratic", nonnegative=True, scalar_ok=True),
        angular_damping=ds.vec3("angular_damping", nonnegative=True, scalar_ok=True),
    )
    ds.done()

    ground = top.text("ground", GROUND_MODELS)

    ins = top.section("initial")
    initial = InitialConfig(position=ins.vec3("position"), yaw=ins.number("yaw"))
    ins.done()

    ss = top.section("simulation")
    step = ss.number("physics_step", positive=True)
    seed = ss.integer("seed", default=0)
    ss.done()
    n = EXCHANGE_STEP / step
    if abs(n - round(n)) > 1e-9 * n or round(n) < 1:
        raise UserError(f"{where}: key 'simulation.physics_step' must divide the 0.004 s exchange step "
                        f"(0.004, 0.002, 0.001, ...), got {step:g}")
    simulation = SimulationConfig(physics_step=EXCHANGE_STEP / round(n), seed=seed)

    sensors = _parse_sensors(top.section("sensors"))

    hs = top.section("home")
    home = HomeConfig(lat=hs.number("lat"), lon=hs.number("lon"), alt=hs.number("alt"))
    hs.done()
    if not -90.0 < home.lat < 90.0:
        raise UserError(f"{where}: key 'home.lat' must be strictly between -90 and 90 deg, got {home.lat:g}")
    if not -180.0 <= home.lon <= 180.0:
        raise UserError(f"{where}: key 'home.lon' must be within [-180, 180] deg, got {home.lon:g}")
    top.done()

    cfg = VehicleConfig(
        name=name, mass=mass, gravity=gravity, inertia=inertia, arm_length=arm, thrust_coefficient=ct,
        moment_coefficient=cm, motor=motor, drag=drag, ground=ground, initial=initial, simulation=simulation,
        sensors=sensors, home=home, source_path=path,
    )
    _check_initial(where, cfg)
    return cfg


def _parse_sensors(sec: _Section) -> SensorsConfig:
    preset = sec.text("preset", SENSOR_PRESETS)

    def imu(name: str) -> ImuNoiseConfig:
        s = sec.section(name)
        out = ImuNoiseConfig(noise=s.vec3("noise", nonnegative=True, scalar_ok=True), bias=s.vec3("bias"))
        s.done()
        return out

    accel = imu("accel")
    gyro = imu("gyro")
    s = sec.section("mag")
    mag = MagConfig(noise=s.vec3("noise", nonnegative=True, scalar_ok=True), bias=s.vec3("bias"),
                    earth_field=s.vec3("earth_field"))
    s.done()
    s = sec.section("baro")
    baro = BaroConfig(noise=s.number("noise", nonnegative=True), bias=s.number("bias"))
    s.done()
    s = sec.section("gps")
    gps = GpsConfig(
        horizontal_noise=s.number("horizontal_noise", nonnegative=True),
        vertical_noise=s.number("vertical_noise", nonnegative=True),
        velocity_noise=s.number("velocity_noise", nonnegative=True),
        bias=s.vec3("bias"),
        eph=s.number("eph", positive=True),
        epv=s.number("epv", positive=True),
        satellites=s.integer("satellites"),
    )
    s.done()
    sec.done()
    return SensorsConfig(preset=preset, accel=accel, gyro=gyro, mag=mag, baro=baro, gps=gps)
