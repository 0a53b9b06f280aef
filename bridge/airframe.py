"""The vehicle file's airframe sections: rotor geometry, aerodynamic effects and wind, as typed, checked data.

Frames and units: rotor positions and the centre-of-gravity offset in body FRD (m), wind in earth NED (m/s),
rotor speeds in rad/s. Every section is optional; absent, an effect is off (coefficient 0) and the geometry is
the Quad-X built from `arm_length`, `thrust_coefficient` and `moment_coefficient` (PX4 motor order).
The formulas these numbers feed are in sitl/ (one module per effect) and identification/true_model.py.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bridge.errors import UserError
from bridge.yaml_file import Section, Vec3

ROTOR_DIRECTIONS = ("ccw", "cw")  # seen from above
TURBULENCE_PRESETS = ("none", "light", "moderate", "severe")
KNOT = 0.514444  # m/s
FOOT = 0.3048  # m
# MIL-F-8785C low-altitude turbulence: wind speed at 20 ft (W20) for each intensity (15, 30, 45 kt).
W20_KNOTS = {"light": 15.0, "moderate": 30.0, "severe": 45.0}
DRYDEN_ALTITUDE_RANGE = (10.0 * FOOT, 1000.0 * FOOT)  # m: where the low-altitude model holds
ALLOCATION_MIN_RECIPROCAL_CONDITION = 1e-6


@dataclass(frozen=True)
class RotorConfig:
    """One rotor: hub position (FRD m, from the frame's centre), spin seen from above, its coefficients."""

    position: Vec3  # m, body FRD
    direction: str  # ccw | cw (seen from above)
    thrust_coefficient: float  # N/(rad/s)^2: thrust Ct*w^2 along -z body
    moment_coefficient: float  # N m/(rad/s)^2: drag torque Cm*w^2, +z body for ccw, -z for cw

    @property
    def spin_z(self) -> float:
        """z component (FRD) of the rotor's spin direction: -1 for ccw seen from above, +1 for cw."""
        return -1.0 if self.direction == "ccw" else 1.0


@dataclass(frozen=True)
class RotorDragConfig:
    """Rotor drag (blade flapping, induced drag): F_i = -w_i diag(k_d, k_d, k_z) v_i, v_i hub airspeed FRD."""

    k_d: float  # N/((rad/s)(m/s)) = kg/rad, in the rotor plane
    k_z: float  # kg/rad, along the rotor axis


@dataclass(frozen=True)
class GroundEffectConfig:
    """Cheeseman-Bennett: T/T_inf = 1/(1 - (R/(4 h))^2), h the rotor's height (m), capped at h_min."""

    rotor_radius: float  # R, m
    min_height: float  # m: below it the law is held at its h_min value (it diverges at h = R/4)


@dataclass(frozen=True)
class AeroConfig:
    """The aerodynamic effects beyond the paper's model; each off when None or zero."""

    rotor_drag: RotorDragConfig | None = None
    translational_lift: float = 0.0  # k_h, N/(m/s)^2: T_i += k_h (v_ix^2 + v_iy^2)
    frame_drag: Vec3 = (0.0, 0.0, 0.0)  # C, kg/m per body axis FRD: F = -|v_a| C v_a
    ground_effect: GroundEffectConfig | None = None

    @property
    def active(self) -> bool:
        """True when any effect is on."""
        return (self.rotor_drag is not None or self.translational_lift != 0.0 or any(self.frame_drag)
                or self.ground_effect is not None)


@dataclass(frozen=True)
class GustConfig:
    """A 1-cosine gust: w(t) = A/2 (1 - cos(2 pi (t - start)/duration)) for start <= t <= start + duration."""

    start: float  # s of simulated time
    duration: float  # s
    amplitude: Vec3  # m/s, NED peak


@dataclass(frozen=True)
class WindConfig:
    """Wind in earth NED: steady vector + Dryden turbulence (MIL-F-8785C, low altitude) + 1-cosine gusts."""

    steady: Vec3 = (0.0, 0.0, 0.0)  # m/s NED
    turbulence: str = "none"  # none | light | moderate | severe
    reference_altitude: float = 10.0  # m above ground: the Dryden scales and intensities are taken there
    gusts: tuple[GustConfig, ...] = ()
    seed: int = 0

    @property
    def active(self) -> bool:
        """True when there is any wind at all."""
        return any(self.steady) or self.turbulence != "none" or bool(self.gusts)

    @property
    def mean_speed(self) -> float:
        """|steady wind|, m/s: the speed at which the frozen turbulence field is carried past the vehicle."""
        return math.sqrt(sum(v * v for v in self.steady))


def quad_x_rotors(arm_length: float, ct: float, cm: float) -> tuple[RotorConfig, ...]:
    """Quad-X of arm d (m) in PX4 order: 1 front-right, 2 rear-left (ccw), 3 front-left, 4 rear-right (cw)."""
    a = arm_length * math.sqrt(0.5)
    signs = ((1, 1, "ccw"), (-1, -1, "ccw"), (1, -1, "cw"), (-1, 1, "cw"))
    return tuple(RotorConfig((sx * a, sy * a, 0.0), d, ct, cm) for sx, sy, d in signs)


def allocation_matrix(rotors: tuple[RotorConfig, ...], cg: Vec3) -> np.ndarray:
    """4xN: thrust (N), roll, pitch, yaw torque (N m, FRD about the CG) per squared rotor speed (rad/s)^2."""
    cols = []
    for r in rotors:
        x, y = r.position[0] - cg[0], r.position[1] - cg[1]
        ct = r.thrust_coefficient
        cols.append((ct, -y * ct, x * ct, -r.spin_z * r.moment_coefficient))
    return np.array(cols, dtype=float).T


def check_allocation(where: str, key: str, rotors: tuple[RotorConfig, ...], cg: Vec3) -> None:
    """UserError unless the rotors can produce thrust, roll, pitch and yaw torque independently."""
    a = allocation_matrix(rotors, cg)
    # Scale rows to unit size so that N and N m compare; a rank-deficient matrix has a tiny singular value.
    norms = np.linalg.norm(a, axis=1)
    if np.any(norms == 0):
        axis = ("thrust", "roll torque", "pitch torque", "yaw torque")[int(np.argmin(norms))]
        raise UserError(f"{where}: key '{key}': degenerate rotor geometry, the rotors give no {axis}",
                        hint="place rotors on both sides of the centre of gravity, with both spin directions")
    sv = np.linalg.svd(a / norms[:, None], compute_uv=False)
    if sv[-1] < ALLOCATION_MIN_RECIPROCAL_CONDITION * sv[0]:
        values = ", ".join(f"{v:.3g}" for v in sv)
        raise UserError(f"{where}: key '{key}': degenerate rotor geometry: thrust, roll, pitch and yaw "
                        f"cannot be set independently (allocation matrix singular values {values})",
                        hint="e.g. two rotors at the same place or all rotors on one line; use the Quad-X "
                             "default (omit 'rotors') or fix the positions and directions")


def parse_rotors(sec: Section, arm_length: float, ct: float,
                 cm: float) -> tuple[tuple[RotorConfig, ...], Vec3]:
    """The `rotors` list (default Quad-X) and `center_of_gravity` (FRD m, default 0) of a vehicle file."""
    cg = sec.vec3("center_of_gravity", default=(0.0, 0.0, 0.0))
    if not sec.has("rotors"):
        rotors = quad_x_rotors(arm_length, ct, cm)
    else:
        items = sec.raw("rotors")
        if not isinstance(items, list) or len(items) != 4:
            raise UserError(f"{sec.where}: key 'rotors' must be a list of 4 rotors in PX4 motor order",
                            hint="each: {position: [x, y, z], direction: ccw|cw} and optionally "
                                 "thrust_coefficient, moment_coefficient (default the top-level ones)")
        out = []
        for i, item in enumerate(items):
            r = sec.child(f"rotors[{i}]", item)
            out.append(RotorConfig(
                position=r.vec3("position"),
                direction=r.text("direction", ROTOR_DIRECTIONS),
                thrust_coefficient=r.number("thrust_coefficient", positive=True, default=ct),
                moment_coefficient=r.number("moment_coefficient", positive=True, default=cm),
            ))
            r.done()
        rotors = tuple(out)
    check_allocation(sec.where, "rotors" if sec.has("rotors") else "center_of_gravity", rotors, cg)
    return rotors, cg


def parse_aero(sec: Section) -> AeroConfig:
    """The `aerodynamics` section (every effect optional; an unknown effect key is an error)."""
    rotor_drag = None
    if sec.has("rotor_drag"):
        s = sec.section("rotor_drag")
        rotor_drag = RotorDragConfig(k_d=s.number("k_d", nonnegative=True),
                                     k_z=s.number("k_z", nonnegative=True))
        s.done()
    lift = 0.0
    if sec.has("translational_lift"):
        s = sec.section("translational_lift")
        lift = s.number("k_h", nonnegative=True)
        s.done()
    frame = sec.vec3("frame_drag", nonnegative=True, scalar_ok=True, default=(0.0, 0.0, 0.0))
    ground = None
    if sec.has("ground_effect"):
        s = sec.section("ground_effect")
        radius = s.number("rotor_radius", positive=True)
        min_height = s.number("min_height", default=radius / 2.0)
        if not min_height > radius / 4.0:
            raise UserError(f"{sec.where}: key '{s.key('min_height')}' must be > rotor_radius/4 = "
                            f"{radius / 4:g} m (the law diverges there), got {min_height:g}")
        ground = GroundEffectConfig(rotor_radius=radius, min_height=min_height)
        s.done()
    sec.done()
    return AeroConfig(rotor_drag=rotor_drag, translational_lift=lift, frame_drag=frame, ground_effect=ground)


def wind_config(where: str, steady: Vec3 = (0.0, 0.0, 0.0), turbulence: str = "none",
                reference_altitude: float = 10.0, gusts: tuple[GustConfig, ...] = (), seed: int = 0,
                key: str = "wind") -> WindConfig:
    """A checked WindConfig (the file's `wind` section or the CLI's flags); `key` names it in errors."""
    if turbulence not in TURBULENCE_PRESETS:
        raise UserError(f"{where}: key '{key}.turbulence' must be one of {', '.join(TURBULENCE_PRESETS)}, "
                        f"got {turbulence!r}")
    cfg = WindConfig(steady=steady, turbulence=turbulence, reference_altitude=reference_altitude,
                     gusts=gusts, seed=seed)
    if turbulence != "none" and cfg.mean_speed < 0.1:
        raise UserError(f"{where}: key '{key}.turbulence' is {turbulence} but the steady wind speed is "
                        f"{cfg.mean_speed:g} m/s: Dryden turbulence needs a wind speed (its time scale)",
                        hint=f"give '{key}.steady' as [N, E, D] m/s with a speed of at least 0.1 m/s "
                             "(e.g. quadsr sitl --wind 5,0,0)")
    lo, hi = DRYDEN_ALTITUDE_RANGE
    if not lo <= reference_altitude <= hi:
        raise UserError(f"{where}: key '{key}.reference_altitude' must be within [{lo:.3g}, {hi:.4g}] m (the "
                        f"low-altitude Dryden model's 10-1000 ft), got {reference_altitude:g}")
    for i, g in enumerate(gusts):
        if not (g.duration > 0 and g.start >= 0):
            raise UserError(f"{where}: key '{key}.gusts[{i}]' needs start >= 0 s and duration > 0 s, "
                            f"got start {g.start:g}, duration {g.duration:g}")
    return cfg


def parse_wind(sec: Section) -> WindConfig:
    """The `wind` section: steady [N, E, D] m/s, turbulence preset, reference_altitude m, gusts, seed."""
    steady = sec.vec3("steady", default=(0.0, 0.0, 0.0))
    turbulence = sec.text("turbulence", TURBULENCE_PRESETS, default="none")
    altitude = sec.number("reference_altitude", positive=True, default=10.0)
    seed = sec.integer("seed", default=0)
    gusts = []
    for g in sec.sections("gusts", "{start: s, duration: s, amplitude: [N, E, D] m/s}", min_items=0,
                          default=[]):
        gusts.append(GustConfig(start=g.number("start", nonnegative=True),
                                duration=g.number("duration", positive=True), amplitude=g.vec3("amplitude")))
        g.done()
    sec.done()
    return wind_config(sec.where, steady, turbulence, altitude, tuple(gusts), seed, key=sec.prefix or "wind")


def dryden_parameters(preset: str, altitude: float) -> tuple[Vec3, Vec3]:
    """(sigma_u, sigma_v, sigma_w) m/s, (L_u, L_v, L_w) m: MIL-F-8785C low-altitude turbulence at h (m)."""
    h = min(max(altitude, DRYDEN_ALTITUDE_RANGE[0]), DRYDEN_ALTITUDE_RANGE[1]) / FOOT  # ft
    sigma_w = 0.1 * W20_KNOTS[preset] * KNOT
    base = 0.177 + 0.000823 * h
    sigma_uv = sigma_w / base**0.4
    length_uv = h / base**1.2 * FOOT
    return (sigma_uv, sigma_uv, sigma_w), (length_uv, length_uv, h * FOOT)
