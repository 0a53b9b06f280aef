"""Reference trajectories: the paper's Case I and Case II and user trajectories from YAML.

A trajectory gives the desired position NED [m] with its derivatives up to snap, and yaw [rad] with two
derivatives, at time t [s]. Two kinds, both checked when loaded (a mistake: UserError naming file and key):

    name: case1                      # expressions in t (s), sympy-parsed without eval; smooth functions only
    description: ...
    duration: 20                     # s, default flight length
    expressions: {x: "3*sin(0.5*t + pi/3)", y: "3*sin(0.5*t - 2*pi/3)", z: "-0.2*t", yaw: "0"}

    name: hop                        # waypoints joined by a C4 quintic spline (continuous up to snap),
    duration: 12                     # at rest (zero velocity and acceleration) at the first and last one
    waypoints:
      - {t: 0, position: [0, 0, 0], yaw: 0}
      - {t: 4, position: [0, 0, -2]}          # yaw omitted: held from the previous waypoint
    max_speed: 5                     # m/s, optional (default 15); the reference must stay below it
    max_acceleration: 4              # m/s^2, optional (default 6); waypoints too close in time are refused

Derivatives are analytic: sympy derivatives lambdified into one numeric function for expressions, the
polynomial pieces' derivatives for waypoints. Before t = 0 and after the last waypoint the reference holds.
"""

from __future__ import annotations

import ast
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import sympy
from scipy.interpolate import make_interp_spline

from bridge.errors import UserError
from bridge.yaml_file import Section, load_yaml_file
from controller.plugin import Reference, reference_from_values
from controller.reference_shaping import min_jerk_duration
from controller.trajectory_segments import HoldSegment, MoveSegment, PiecewiseTrajectory, RampSegment

TRAJECTORY_DIR = Path(__file__).resolve().parent / "trajectories"
BUILTIN = ("case1", "case2")
T = sympy.Symbol("t", real=True)
_FUNCTIONS = {
    "sin": sympy.sin, "cos": sympy.cos, "tan": sympy.tan, "exp": sympy.exp, "sqrt": sympy.sqrt,
    "log": sympy.log, "atan": sympy.atan, "sinh": sympy.sinh, "cosh": sympy.cosh, "tanh": sympy.tanh,
}
_CONSTANTS = {"pi": sympy.pi, "e": sympy.E}
_AXES = ("x", "y", "z", "yaw")
_KINDS = ("expressions", "waypoints", "segments")
INTERPOLATIONS = ("quintic", "min-jerk", "min-snap")
SEGMENT_KINDS = ("hold", "step", "ramp", "move", "expressions")
# the share of max_speed / max_acceleration that min-jerk / min-snap legs without times are planned to
TIME_ALLOCATION_MARGIN = 0.8
_CHECK_SAMPLES = 2001
# A reference needing more than this is refused unless the file raises the limit (35 deg tilt ~ 6.9 m/s^2).
DEFAULT_LIMITS = {"max_speed": 15.0, "max_acceleration": 6.0}


class _Bad(ValueError):
    pass


def parse_time_expression(text: Any) -> sympy.Expr:
    """A smooth formula in t [s]: numbers, + - * / **, sin cos tan exp sqrt log atan sinh cosh tanh, pi, e."""
    if isinstance(text, bool) or not isinstance(text, (str, int, float)):
        raise _Bad(f"expected a formula in t, got {text!r}")
    src = str(text).strip().replace("^", "**")
    if not src:
        raise _Bad("expected a formula in t, got an empty string")
    try:
        tree = ast.parse(src, mode="eval")
    except SyntaxError as exc:
        raise _Bad(f"not a formula: {exc.msg} in {src!r}") from None
    return _node(tree.body)


def _node(node: ast.AST) -> sympy.Expr:
    if isinstance(node, ast.Constant) and isinstance(node.value, (int, float)) \
            and not isinstance(node.value, bool):
        if not math.isfinite(node.value):
            raise _Bad(f"constant {node.value!r} is not finite")
        return sympy.Integer(node.value) if isinstance(node.value, int) else sympy.Float(node.value)
    if isinstance(node, ast.Name):
        if node.id == "t":
            return T
        if node.id in _CONSTANTS:
            return _CONSTANTS[node.id]
        raise _Bad(f"unknown name {node.id!r} (allowed: t, pi, e)")
    if isinstance(node, ast.UnaryOp) and isinstance(node.op, (ast.USub, ast.UAdd)):
        v = _node(node.operand)
        return -v if isinstance(node.op, ast.USub) else v
    if isinstance(node, ast.BinOp):
        a, b = _node(node.left), _node(node.right)
        ops = {ast.Add: lambda: a + b, ast.Sub: lambda: a - b, ast.Mult: lambda: a * b,
               ast.Div: lambda: a / b, ast.Pow: lambda: a**b}
        for op, fn in ops.items():
            if isinstance(node.op, op):
                return fn()
        raise _Bad(f"operator {type(node.op).__name__} is not allowed")
    if isinstance(node, ast.Call) and isinstance(node.func, ast.Name):
        if node.func.id not in _FUNCTIONS:
            raise _Bad(f"function {node.func.id!r} is not allowed "
                       f"(smooth functions only: {', '.join(_FUNCTIONS)})")
        if node.keywords or len(node.args) != 1:
            raise _Bad(f"function {node.func.id!r} takes one argument")
        return _FUNCTIONS[node.func.id](_node(node.args[0]))
    raise _Bad(f"'{ast.unparse(node)}' is not allowed in a trajectory formula")


class ExpressionTrajectory:
    """x, y, z [m, NED] and yaw [rad] as formulas in t [s]; sympy derivatives, one lambdified call."""

    def __init__(self, name: str, expressions: dict[str, sympy.Expr], duration: float = 20.0,
                 description: str = ""):
        self.name = name
        self.description = description
        self.duration = float(duration)
        self.expressions = {k: sympy.sympify(expressions.get(k, 0)) for k in _AXES}
        rows: list[sympy.Expr] = []
        for order in range(5):
            rows += [sympy.diff(self.expressions[k], T, order) for k in ("x", "y", "z")]
        rows += [sympy.diff(self.expressions["yaw"], T, order) for order in range(3)]
        self._rows = rows
        self._fn = sympy.lambdify([T], rows, modules="math", cse=True)

    def values(self, t: float) -> list[float]:
        """18 numbers at t [s]: position, velocity, acceleration, jerk, snap (NED); yaw, rate, accel."""
        if t < 0:
            v = list(self._fn(0.0))
            return v[0:3] + [0.0] * 12 + [v[15], 0.0, 0.0]
        return list(self._fn(float(t)))

    def reference(self, t: float) -> Reference:
        """The reference at time t [s] (held at its t = 0 value, at rest, before 0)."""
        return reference_from_values(self.values(t))


class WaypointTrajectory:
    """Waypoints [s, m NED, rad] joined by clamped C4 quintic splines; holds at rest outside the waypoints."""

    def __init__(self, name: str, times: np.ndarray, positions: np.ndarray, yaws: np.ndarray,
                 duration: float | None = None, description: str = ""):
        self.name = name
        self.description = description
        self.times = np.asarray(times, dtype=float)
        pts = np.column_stack([np.asarray(positions, float), np.asarray(yaws, float)])
        self.duration = float(duration) if duration is not None else float(self.times[-1])
        zero = np.zeros(4)
        rest = [(1, zero), (2, zero)]  # at rest at both ends: zero velocity and acceleration
        spline = make_interp_spline(self.times, pts, k=5, bc_type=(rest, rest))
        derivs = [spline.derivative(j) if j else spline for j in range(6)]
        left, mid = self.times[:-1], 0.5 * (self.times[:-1] + self.times[1:])
        # piece k: p(t) = sum_j D^j(t_k) (t - t_k)^j / j!; the 5th derivative is constant on each piece
        coef = np.empty((6, len(left), 4))
        for j in range(6):
            coef[j] = derivs[j](mid if j == 5 else left) / math.factorial(j)
        # dcoef[d, j] multiplies (t - t_k)^j in the d-th derivative
        self._dcoef = np.zeros((5, 6, len(left), 4))
        for d in range(5):
            for j in range(d, 6):
                self._dcoef[d, j - d] = coef[j] * math.factorial(j) / math.factorial(j - d)
        self._end = [float(v) for v in pts[-1]]
        self._start = [float(v) for v in pts[0]]

    def values(self, t: float) -> list[float]:
        """The 18 numbers (as ExpressionTrajectory.values) at t [s]."""
        t = float(t)
        if t <= self.times[0] or t >= self.times[-1]:
            p = self._start if t <= self.times[0] else self._end
            return p[0:3] + [0.0] * 12 + [p[3], 0.0, 0.0]
        k = int(np.searchsorted(self.times, t, side="right")) - 1
        dt = t - self.times[k]
        pw = np.array([1.0, dt, dt * dt, dt**3, dt**4, dt**5])
        v = np.einsum("dja,j->da", self._dcoef[:, :, k, :], pw)  # (5 derivatives, 4 axes)
        return list(v[:, :3].ravel()) + [float(v[0, 3]), float(v[1, 3]), float(v[2, 3])]

    def reference(self, t: float) -> Reference:
        """The reference at time t [s]."""
        return reference_from_values(self.values(t))


UserTrajectory = ExpressionTrajectory | WaypointTrajectory | PiecewiseTrajectory


def case1() -> ExpressionTrajectory:
    """The paper's Case I: x_d = 3 sin(0.5t + pi/3), y_d = 3 sin(0.5t - 2pi/3), z_d = -0.2t, psi_d = 0."""
    return load_trajectory("case1")


def case2() -> ExpressionTrajectory:
    """The paper's Case II: x_d = 2, y_d = 4, z_d = -0.3t, psi_d = 0 (vertical take-off at a fixed spot)."""
    return load_trajectory("case2")


def load_trajectory(name_or_path: str | os.PathLike[str]) -> UserTrajectory:
    """A built-in trajectory by name (case1, case2) or a YAML file; UserError naming file and key if bad."""
    text = str(name_or_path)
    path = TRAJECTORY_DIR / f"{text}.yaml" if text in BUILTIN else Path(text)
    if not path.is_file():
        raise UserError(f"trajectory {text!r} not found",
                        hint=f"use one of {', '.join(BUILTIN)} or a path to a trajectory YAML file")
    data = load_yaml_file(path, f"trajectory file {path}")
    return trajectory_from_dict(data, str(path))


def trajectory_from_dict(data: Any, where: str) -> UserTrajectory:
    """Build and check a trajectory from its YAML mapping; `where` names the file in errors."""
    if not isinstance(data, dict):
        raise UserError(f"{where}: expected a mapping with 'expressions', 'waypoints' or 'segments'")
    sec = Section(where, data)
    given = [k for k in _KINDS if sec.has(k)]
    if len(given) != 1:
        raise UserError(f"{where}: give exactly one of 'expressions', 'waypoints' or 'segments'")
    kind = given[0]
    name = str(sec.raw("name", Path(where).stem))
    description = str(sec.raw("description", ""))
    duration = sec.number("duration", positive=True) if sec.raw("duration", None) is not None else None
    limits = {k: sec.number(k, v, positive=True) for k, v in DEFAULT_LIMITS.items()}
    has_interpolation = sec.has("interpolation")
    sec.done()
    traj: Any
    if kind == "expressions":
        traj = _expression_trajectory(sec.section("expressions"), name, description,
                                      duration if duration is not None else 20.0)
    elif kind == "segments":
        traj = _segment_trajectory(sec, name, description, duration)
    else:
        interp = sec.raw("interpolation", "quintic")
        if interp not in INTERPOLATIONS:
            raise UserError(f"{where}: key 'interpolation' must be 'quintic' (C4 quintic spline through the "
                            f"waypoints), 'min-jerk' or 'min-snap' (a rest-to-rest minimum-jerk or -snap leg "
                            f"between each two), got {interp!r}")
        traj = _waypoint_trajectory(sec, name, description, duration, interp, limits)
    if has_interpolation and kind != "waypoints":
        raise UserError(f"{where}: key 'interpolation' only applies to 'waypoints'")
    _check_samples(traj, where, limits, kind)
    return traj


def _expression_trajectory(sec: Section, name: str, description: str,
                           duration: float) -> ExpressionTrajectory:
    """x, y, z (NED, m) and optional yaw (rad) as formulas in t, from the mapping `sec`."""
    exprs: dict[str, sympy.Expr] = {}
    for key in _AXES:
        if sec.has(key):
            try:
                exprs[key] = parse_time_expression(sec.raw(key))
            except _Bad as exc:
                raise UserError(f"{sec.where}: key '{sec.key(key)}': {exc}") from None
    sec.done()
    for key in ("x", "y", "z"):
        if key not in exprs:
            raise sec.fail(key, "is missing",
                           hint="give x, y and z (NED, m) as formulas in t; yaw (rad) defaults to 0")
    return ExpressionTrajectory(name, exprs, duration=duration, description=description)


def _point(sec: Section, name: str) -> list[float]:
    """[x, y, z] in m (NED) at this key."""
    pos = sec.raw(name)
    if (not isinstance(pos, list) or len(pos) != 3
            or not all(isinstance(p, (int, float)) and not isinstance(p, bool) and math.isfinite(p)
                       for p in pos)):
        raise sec.fail(name, f"must be [x, y, z] in m (NED), got {pos!r}")
    return [float(p) for p in pos]


def _waypoint_trajectory(top: Section, name: str, description: str, duration: float | None,
                         interpolation: str = "quintic",
                         limits: dict[str, float] | None = None) -> WaypointTrajectory | PiecewiseTrajectory:
    times: list[float | None] = []
    positions, yaws = [], []
    yaw = 0.0
    for wp in top.sections("waypoints", "waypoints (each t, position and optional yaw)", min_items=2):
        t = wp.raw("t", None)
        if t is None and interpolation != "quintic":
            times.append(None)
        else:
            if t is None:
                raise wp.fail("t", "is missing (a time >= 0 in s)",
                              hint="with interpolation min-jerk or min-snap the times may be left out "
                                   "(every waypoint's): they are allocated from max_speed and "
                                   "max_acceleration")
            t = wp.number("t", nonnegative=True)
            last = next((v for v in reversed(times) if v is not None), None)
            if last is not None and t <= last:
                raise wp.fail("t", f"= {t:g} is not after the previous waypoint's t = {last:g}",
                              hint="waypoint times must strictly increase")
            times.append(float(t))
        positions.append(_point(wp, "position"))
        if wp.has("yaw"):
            yaw = wp.number("yaw")
        yaws.append(yaw)
        wp.done()
    if interpolation == "quintic":
        return WaypointTrajectory(name, np.array(times, dtype=float), np.array(positions), np.array(yaws),
                                  duration=duration, description=description)
    if any(v is None for v in times) and not all(v is None for v in times):
        raise top.fail("waypoints", "must give t for every waypoint or for none",
                       hint="without times, each leg's time is allocated from max_speed and "
                            "max_acceleration")
    lim = limits or DEFAULT_LIMITS
    legs, durations = [], []
    for k in range(len(positions) - 1):
        a, b = positions[k], positions[k + 1]
        if times[0] is None:
            dist = float(np.linalg.norm(np.subtract(b, a)))
            leg = min_jerk_duration(dist, TIME_ALLOCATION_MARGIN * lim["max_speed"],
                                    TIME_ALLOCATION_MARGIN * lim["max_acceleration"], shortest=0.5,
                                    profile=interpolation)
        else:
            leg = float(times[k + 1]) - float(times[k])  # type: ignore[arg-type]
        legs.append(MoveSegment(tuple(a), tuple(b), yaws[k], yaws[k + 1], leg, interpolation))  # type: ignore
        durations.append(leg)
    if times[0] not in (None, 0.0):
        legs.insert(0, HoldSegment(tuple(positions[0]), yaws[0]))  # type: ignore[arg-type]
        durations.insert(0, float(times[0]))  # type: ignore[arg-type]
    return PiecewiseTrajectory(name, legs, durations, duration=duration, description=description,
                               kinds=["move"] * len(legs))


def _segment_trajectory(top: Section, name: str, description: str,
                        duration: float | None) -> PiecewiseTrajectory:
    """Segments: hold (at position, default the previous end), step (jump to position and hold), ramp
    (constant speed to position), move (minimum-snap to position), expressions (x, y, z, yaw in t since the
    segment's start); each with a duration [s] and an optional yaw [rad]."""
    segments: list[Any] = []
    durations, kinds = [], []
    end: list[float] | None = None
    yaw = 0.0
    for i, seg in enumerate(top.sections("segments", f"segments (each a mapping with kind "
                                                     f"({', '.join(SEGMENT_KINDS)}) and duration)")):
        kind = seg.text("kind", SEGMENT_KINDS)
        if not seg.has("duration"):
            raise seg.fail("duration", "is missing", hint="the segment's length in s")
        dur = seg.number("duration", positive=True)
        if kind == "expressions":
            built = _expression_trajectory(seg, f"{name}[{i}]", "", dur)
            segments.append(built)
            last = built.values(dur)
            end, yaw = last[0:3], last[15]
        else:
            start_yaw = yaw
            if seg.has("yaw"):
                yaw = seg.number("yaw")
            if seg.has("position"):
                target = _point(seg, "position")
            elif kind == "hold" and end is not None:
                target = list(end)
            else:
                raise seg.fail("position", "is missing",
                               hint="a hold without position stays at the previous segment's end; the "
                                    f"first segment and every {kind} need [x, y, z] in m (NED)")
            seg.done()
            if kind in ("hold", "step") or end is None:
                segments.append(HoldSegment(tuple(target), yaw))  # type: ignore[arg-type]
            elif kind == "ramp":
                segments.append(RampSegment(tuple(end), tuple(target), start_yaw, yaw, dur))  # type: ignore
            else:
                segments.append(MoveSegment(tuple(end), tuple(target), start_yaw, yaw, dur))  # type: ignore
            end = target
        durations.append(dur)
        kinds.append(str(kind))
    return PiecewiseTrajectory(name, segments, durations, duration=duration, description=description,
                               kinds=kinds)


def _check_samples(traj: UserTrajectory, where: str, limits: dict[str, float],
                   key: str) -> None:
    """Evaluate the reference densely over [0, duration]: finite first, then within the speed/accel limits."""
    names = ("position", "velocity", "acceleration", "jerk", "snap")
    times = np.linspace(0.0, traj.duration, _CHECK_SAMPLES)
    rows = []
    for t in times:
        try:
            v = np.asarray(traj.values(float(t)), dtype=float)
        except (ValueError, ZeroDivisionError, OverflowError) as exc:
            raise UserError(f"{where}: key '{key}' cannot be evaluated at t = {t:.3f} s: {exc}") from None
        bad = ~np.isfinite(v) | (np.abs(v) > 1e6)
        if bad.any():
            idx = int(np.argmax(bad))
            what = names[idx // 3] if idx < 15 else ("yaw", "yaw rate", "yaw acceleration")[idx - 15]
            raise UserError(f"{where}: key '{key}': the {what} is not finite (or exceeds 1e6) "
                            f"at t = {t:.3f} s",
                            hint="the reference must be smooth (continuous up to snap) over [0, duration]")
        rows.append(v)
    arr = np.array(rows)
    hint = ("space the waypoints further apart in time" if key == "waypoints"
            else "slow the trajectory down, or raise the limit in the file")
    for name, cols in (("max_speed", slice(3, 6)), ("max_acceleration", slice(6, 9))):
        mag = np.linalg.norm(arr[:, cols], axis=1)
        k = int(np.argmax(mag))
        if mag[k] > limits[name]:
            what, unit = ("speed", "m/s") if name == "max_speed" else ("acceleration", "m/s^2")
            raise UserError(f"{where}: key '{key}': {what} {mag[k]:.2f} {unit} at t = {times[k]:.2f} s "
                            f"exceeds {name} {limits[name]:g} {unit}", hint=hint)


@dataclass(frozen=True)
class TrajectoryInfo:
    """What a CLI prints about a trajectory."""

    name: str
    kind: str
    duration: float
    description: str


def describe(traj: UserTrajectory) -> TrajectoryInfo:
    """Name, kind (expressions | waypoints | segments), default duration [s] and description."""
    kind = "expressions" if isinstance(traj, ExpressionTrajectory) else \
        "waypoints" if isinstance(traj, WaypointTrajectory) or set(getattr(traj, "kinds", [])) == {"move"} \
        else "segments"
    return TrajectoryInfo(traj.name, kind, traj.duration, traj.description)
