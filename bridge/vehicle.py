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

from bridge.airframe import (
    AeroConfig,
    RotorConfig,
    WindConfig,
    parse_aero,
    parse_rotors,
    parse_wind,
    quad_x_rotors,
)
from bridge.errors import UserError
from bridge.yaml_file import Section, describe_value, float_value, load_yaml_file, vec3_value

Vec3 = tuple[float, float, float]
Mat3 = tuple[Vec3, Vec3, Vec3]

EXCHANGE_STEP = 0.004  # s, the HIL exchange step (250 Hz); the physics step must divide it
SENSOR_PRESETS = ("realistic", "ideal")
GROUND_MODELS = ("plane", "none")
VEHICLE_HINT = "see sitl/vehicles/fang-chen-buaa.yaml for every key with its unit"


THRUST_MODELS = ("linear", "px4", "polynomial")


def px4_thrust(factor: float, u: float) -> float:
    """PX4's normalised thrust (1-f) u + f u^2 at output u in [0, 1] (f = THR_MDL_FAC)."""
    return (1.0 - factor) * u + factor * u * u


@dataclass(frozen=True)
class MotorCurve:
    """Throttle sigma in [0, 1] <-> steady rotor speed w (rad/s), one of three curves:

    linear (the paper's): w = Cr*sigma + wb clipped to [0, w_max], w_max = Cr + wb;
    px4 (PX4's THR_MDL_FAC = f: thrust, so w^2, is (1-f) s + f s^2 of full): w = w_max sqrt((1-f) s + f s^2);
    polynomial: w = c0 + c1 s + c2 s^2 + ... (increasing on [0, 1]) clipped to [0, w_max], w_max = p(1).
    """

    curve_slope: float = 0.0  # Cr, rad/s per unit throttle (linear)
    curve_offset: float = 0.0  # wb, rad/s (linear)
    kind: str = "linear"  # linear | px4 | polynomial
    full_speed: float = 0.0  # rad/s at full throttle (px4)
    thr_mdl_fac: float = 0.0  # PX4's THR_MDL_FAC in [0, 1] (px4)
    coefficients: tuple[float, ...] = ()  # c0, c1, ... rad/s (polynomial)

    @property
    def max_speed(self) -> float:
        """Steady rotor speed at full throttle, rad/s."""
        if self.kind == "px4":
            return self.full_speed
        if self.kind == "polynomial":
            return sum(self.coefficients)
        return self.curve_slope + self.curve_offset

    def _raw_speed(self, s: float) -> float:
        """The curve's formula at throttle s in [0, 1], before clipping (rad/s)."""
        if self.kind == "px4":
            return self.full_speed * math.sqrt(max(px4_thrust(self.thr_mdl_fac, s), 0.0))
        if self.kind == "polynomial":
            out = 0.0
            for c in reversed(self.coefficients):
                out = out * s + c
            return out
        return self.curve_slope * s + self.curve_offset

    def speed_for_throttle(self, sigma: float) -> float:
        """Steady rotor speed (rad/s) for throttle sigma (clipped to [0, 1] first)."""
        s = min(max(sigma, 0.0), 1.0)
        return min(max(self._raw_speed(s), 0.0), self.max_speed)

    def throttle_for_speed(self, w: float) -> float:
        """Throttle in [0, 1] giving steady speed w (rad/s); w is clipped to [0, w_max] first.

        w <= 0 maps to the largest throttle that still gives 0 rad/s (-wb/Cr = 0.123 for the default vehicle),
        so the inverse is continuous over [0, w_max] and speed_for_throttle(throttle_for_speed(w)) == w.
        """
        wc = min(max(w, 0.0), self.max_speed)
        if self.kind == "linear":
            return min(max((wc - self.curve_offset) / self.curve_slope, 0.0), 1.0)
        if self.kind == "px4":
            r, f = (wc / self.full_speed) ** 2, self.thr_mdl_fac
            s = r if f == 0.0 else (-(1.0 - f) + math.sqrt((1.0 - f) ** 2 + 4.0 * f * r)) / (2.0 * f)
            return min(max(s, 0.0), 1.0)
        lo, hi = 0.0, 1.0  # polynomial: increasing on [0, 1], bisection (52 halvings reach float precision)
        for _ in range(52):
            mid = 0.5 * (lo + hi)
            if self._raw_speed(mid) <= wc:
                lo = mid
            else:
                hi = mid
        return lo

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
    curve: MotorCurve | None = None  # the throttle curve when not the linear one of curve_slope/curve_offset
    speed_noise: float = 0.0  # rad/s, std of white noise on each commanded rotor speed (0: off)
    pwm_min: float = 1000.0  # us, the ESC pulse of throttle 0 (an autopilot's PWM output, e.g. ArduPilot's)
    pwm_max: float = 2000.0  # us, the ESC pulse of throttle 1


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

    rotors: tuple[RotorConfig, ...] = ()  # PX4 motor order; () means the Quad-X from arm_length
    center_of_gravity: Vec3 = (0.0, 0.0, 0.0)  # m, FRD, from the centre the rotor positions are measured from
    aero: AeroConfig = AeroConfig()
    wind: WindConfig = WindConfig()

    @property
    def motor_curve(self) -> MotorCurve:
        """The throttle <-> steady rotor speed curve."""
        if self.motor.curve is not None:
            return self.motor.curve
        return MotorCurve(self.motor.curve_slope, self.motor.curve_offset)

    @property
    def rotor_set(self) -> tuple[RotorConfig, ...]:
        """The four rotors in PX4 order (the Quad-X from arm_length unless the file lists them)."""
        return self.rotors or quad_x_rotors(self.arm_length, self.thrust_coefficient, self.moment_coefficient)

    @property
    def rotor_arms(self) -> tuple[Vec3, ...]:
        """Each rotor hub's position relative to the centre of gravity, m, body FRD."""
        cx, cy, cz = self.center_of_gravity
        return tuple((r.position[0] - cx, r.position[1] - cy, r.position[2] - cz) for r in self.rotor_set)

    @property
    def paper_physics(self) -> bool:
        """True for the paper's model: Quad-X from arm_length, CG at the centre, no effect, wind or noise."""
        return (not self.rotors and not any(self.center_of_gravity) and not self.aero.active
                and not self.wind.active and self.motor.speed_noise == 0.0)

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
        wind: WindConfig | None = None,
    ) -> VehicleConfig:
        """A copy with CLI-style overrides applied (validated like the file)."""
        where = f"override of vehicle {self.name}"
        cfg = self
        if ground is not None:
            if ground not in GROUND_MODELS:
                raise UserError(f"{where}: ground must be one of {', '.join(GROUND_MODELS)}, got {ground!r}")
            cfg = dataclasses.replace(cfg, ground=ground)
        if initial_position is not None or initial_yaw is not None:
            pos = cfg.initial.position if initial_position is None else vec3_value(where, "initial.position",
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
        if wind is not None:
            cfg = dataclasses.replace(cfg, wind=wind)
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


def _inertia(sec: Section) -> Mat3:
    key = sec.key("inertia")
    value = sec.raw("inertia")
    is_seq = isinstance(value, (list, tuple)) and len(value) == 3
    if is_seq and all(not isinstance(v, (list, tuple)) for v in value):
        d = vec3_value(sec.where, key, value)  # the diagonal only
        mat = ((d[0], 0.0, 0.0), (0.0, d[1], 0.0), (0.0, 0.0, d[2]))
    elif is_seq:
        mat = tuple(vec3_value(sec.where, f"{key}[{i}]", row) for i, row in enumerate(value))  # type: ignore
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
    top = Section(where, data, hint=VEHICLE_HINT)
    name = top.text("name")
    mass = top.number("mass", positive=True)
    gravity = top.number("gravity", nonnegative=True)
    inertia = _inertia(top)
    arm = top.number("arm_length", positive=True)
    ct = top.number("thrust_coefficient", positive=True)
    cm = top.number("moment_coefficient", positive=True)

    motor = _parse_motor(top.section("motor"))

    rotors, cg = parse_rotors(top, arm, ct, cm)
    aero = parse_aero(top.optional_section("aerodynamics"))
    wind = parse_wind(top.optional_section("wind"))

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
        sensors=sensors, home=home, source_path=path, rotors=rotors if top.has("rotors") else (),
        center_of_gravity=cg, aero=aero, wind=wind,
    )
    _check_initial(where, cfg)
    return cfg


def _parse_motor(ms: Section) -> MotorConfig:
    kind = ms.text("thrust_model", THRUST_MODELS, default="linear")
    where = ms.where
    slope = offset = 0.0
    curve = None
    if kind == "linear":
        slope = ms.number("curve_slope", positive=True)
        offset = ms.number("curve_offset")
        if slope + offset <= 0:
            raise UserError(f"{where}: keys 'motor.curve_slope' + 'motor.curve_offset' (the full-throttle "
                            f"speed) must be > 0, got {slope + offset:g} rad/s")
    elif kind == "px4":
        full = ms.number("max_speed", positive=True)
        fac = ms.number("thr_mdl_fac", nonnegative=True)
        if fac > 1.0:
            raise UserError(f"{where}: key 'motor.thr_mdl_fac' must be within [0, 1] (PX4's THR_MDL_FAC), "
                            f"got {fac:g}")
        curve = MotorCurve(kind="px4", full_speed=full, thr_mdl_fac=fac)
    else:
        coeffs = ms.raw("coefficients")
        if not isinstance(coeffs, list) or not 1 <= len(coeffs) <= 8:
            raise UserError(f"{where}: key 'motor.coefficients' must be a list of 1 to 8 numbers c0, c1, ... "
                            "(rad/s): w = c0 + c1*sigma + c2*sigma^2 + ...")
        values = tuple(float_value(where, f"motor.coefficients[{i}]", c) for i, c in enumerate(coeffs))
        curve = MotorCurve(kind="polynomial", coefficients=values)
        grid = [curve._raw_speed(i / 200.0) for i in range(201)]
        if curve.max_speed <= 0 or any(b < a for a, b in zip(grid, grid[1:])):  # noqa: B905
            raise UserError(f"{where}: key 'motor.coefficients' must give a speed that rises with throttle "
                            "on [0, 1] and is > 0 at full throttle",
                            hint="check the signs of the coefficients")
    motor = MotorConfig(
        time_constant=ms.number("time_constant", positive=True),
        curve_slope=slope,
        curve_offset=offset,
        rotor_inertia=ms.number("rotor_inertia", nonnegative=True),
        curve=curve,
        speed_noise=ms.number("speed_noise", nonnegative=True, default=0.0),
        pwm_min=ms.number("pwm_min", positive=True, default=1000.0),
        pwm_max=ms.number("pwm_max", positive=True, default=2000.0),
    )
    ms.done()
    if not motor.pwm_min < motor.pwm_max <= 65535:
        raise UserError(f"{where}: keys 'motor.pwm_min' < 'motor.pwm_max' <= 65535 us are required, got "
                        f"{motor.pwm_min:g} and {motor.pwm_max:g}",
                        hint="the usual ESC range is 1000 to 2000 us")
    return motor


def _parse_sensors(sec: Section) -> SensorsConfig:
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
