"""Physical plausibility checks of a model, printed with it: can an engineer trust these equations?

At the hover point (level, at rest, at the median position of the rows (NED m: a model with a height
term, such as ground effect, is judged where the log flew, not at the origin), every rotor at the log's
hover speed u_h: the median rotor speed of the rows, or the vehicle's hover speed when a vehicle file is
given):
- gravity: z'' with the rotors stopped is +g (NED, down) within 15%.
- hover: with a vehicle file, z'' at its hover speed is near 0 (within 15% of g) and the mass that the
  model's thrust implies (Ct * sum u_h^2 / thrust acceleration, kg) matches the file's. Without one, the
  log's median rotor speed is no hover speed unless the log hovered (an open-loop excitation from altitude
  falls at a fifth of the weight), so the model's own hover speed is solved for (all rotors equal, z'' = 0)
  and must exist and lie within a factor HOVER_SPAN of the rotor speeds the log flew (p5..p95): else its
  thrust balances gravity only by extrapolation, or not at.
- control signs: more thrust (sum u_i^2) accelerates up (z'' < 0), the roll, pitch and yaw combinations
  f2, f3, f4 (docs/design.md) give positive wx', wy', wz'; a target that does not respond is flagged too
  (saying so when the identification found the flight does not excite it: checks.not_excited).
- self-feedback: d(wx')/d(wx), d(wy')/d(wy), d(wz')/d(wz) and d(x'')/d(vx), d(y'')/d(vy), d(z'')/d(vz),
  averaged over the data's rows, must not be positive beyond max_self_feedback (1/s): a positive one is
  anti-damping (the state feeds its own growth), which no rigid body with rotors and drag has.
Every check works on whatever expressions the engine found (numerically, by finite differences).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from identification.table import STATE_NAMES
from identification.targets import STANDARD_GRAVITY

# motor combinations of docs/design.md: the rotor signs of f1..f4
COMBINATION_SIGNS = {
    "f1": np.array([1.0, 1.0, 1.0, 1.0]),
    "f2": np.array([-1.0, 1.0, 1.0, -1.0]),
    "f3": np.array([1.0, -1.0, 1.0, -1.0]),
    "f4": np.array([1.0, 1.0, -1.0, -1.0]),
}
# target -> (combination, expected sign of its response, what it is)
CONTROL = {
    "az": ("f1", -1.0, "more thrust accelerates up (z'' < 0, NED)"),
    "dwx": ("f2", 1.0, "the roll combination f2 rolls right (wx' > 0)"),
    "dwy": ("f3", 1.0, "the pitch combination f3 pitches up (wy' > 0)"),
    "dwz": ("f4", 1.0, "the yaw combination f4 yaws right (wz' > 0)"),
}
SELF = {"ax": 3, "ay": 4, "az": 5, "dwx": 9, "dwy": 10, "dwz": 11}  # target -> its own state in xi
HOVER_SPAN = 1.5  # the model's hover speed may lie this factor outside the log's p5..p95 rotor speeds


@dataclass(frozen=True)
class Check:
    """One plausibility check: its name, whether it passed, and a line saying what was measured."""

    name: str
    ok: bool
    text: str

    def line(self) -> str:
        """'ok' or 'FLAG' then the text."""
        return f"{'ok  ' if self.ok else 'FLAG'} {self.name}: {self.text}"


def _eval(model, target: str, xi: np.ndarray, u: np.ndarray) -> np.ndarray:
    j = model.target_names.index(target)
    return np.asarray(model.predict(np.atleast_2d(xi), np.atleast_2d(u))[:, j], dtype=float)


def model_hover_speed(model, level: np.ndarray, top: float) -> float | None:
    """The rotor speed (rad/s, all four equal) at which the model's z'' is 0 at the state `level` (level,
    at rest), the lowest in (0, top]; None when no speed there balances gravity."""
    speeds = np.linspace(0.0, top, 401)
    az = _eval(model, "az", np.tile(level, (len(speeds), 1)), np.repeat(speeds[:, None], 4, axis=1))
    below = np.flatnonzero(np.isfinite(az) & (az <= 0.0))
    if not np.isfinite(az[0]) or az[0] <= 0.0 or below.size == 0:
        return None
    lo, hi = float(speeds[below[0] - 1]), float(speeds[below[0]])
    for _ in range(50):  # bisection: z'' > 0 at lo, <= 0 at hi
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if float(_eval(model, "az", level, np.full(4, mid))[0]) > 0.0 else (lo, mid)
    return 0.5 * (lo + hi)


def _hover_check(model, level: np.ndarray, u: np.ndarray) -> Check:
    """The model's own hover speed against the rotor speeds the log flew (module docstring)."""
    finite = u[np.all(np.isfinite(u), axis=1)]  # (N,4) rad/s
    if finite.size == 0:
        return Check("hover thrust", False, "the log has no finite rotor speeds to judge the hover by")
    p5, p95 = (float(v) for v in np.percentile(finite, [5, 95]))
    top = max(4.0 * float(np.max(finite)), 1.0)
    u_star = model_hover_speed(model, level, top)
    if u_star is None:
        return Check("hover thrust", False, f"no rotor speed up to {top:.4g} rad/s makes z'' 0 at rest, "
                     "level: the model's thrust never balances gravity")
    ok = p5 / HOVER_SPAN <= u_star <= p95 * HOVER_SPAN
    where = "within" if ok else "outside"
    return Check("hover thrust", ok, f"the model hovers at {u_star:.4g} rad/s per rotor, {where} "
                 f"{HOVER_SPAN:g}x the log's rotor speeds ({p5:.4g}..{p95:.4g} rad/s, p5..p95)")


def plausibility_checks(
    model,
    xi: np.ndarray,
    u: np.ndarray,
    vehicle=None,
    gravity: float = STANDARD_GRAVITY,
    max_self_feedback: float = 0.5,
) -> list[Check]:
    """The checks of a fitted model (anything with predict(xi, u) and target_names, e.g. QuadrotorModel)
    on data rows xi (N,12), u (N,4) rad/s; vehicle: a bridge.vehicle.VehicleConfig or None."""
    checks: list[Check] = []
    names = tuple(model.target_names)
    u_h = float(vehicle.hover_speed) if vehicle is not None else float(np.median(u))
    level = np.zeros(12)
    if len(xi):
        level[0:3] = np.nanmedian(np.asarray(xi, dtype=float)[:, 0:3], axis=0)  # m NED, where the log flew
    if "az" in names:
        g_model = float(_eval(model, "az", level, np.zeros(4))[0])
        ok = abs(g_model - gravity) <= 0.15 * gravity
        checks.append(
            Check(
                "gravity", ok, f"z'' with the rotors stopped {g_model:+.3g} m/s^2 (expected +{gravity:.3g})"
            )
        )
        if vehicle is not None:
            hover = float(_eval(model, "az", level, np.full(4, u_h))[0])
            ok = abs(hover) <= 0.15 * gravity
            text = (
                f"z'' at the hover speed {u_h:.4g} rad/s is {hover:+.3g} m/s^2 "
                f"(expected 0 within {0.15 * gravity:.2g})"
            )
            thrust_acc = g_model - hover  # m/s^2 of thrust at u_h
            if thrust_acc > 0:
                mass = vehicle.thrust_coefficient * 4 * u_h**2 / thrust_acc
                ok = ok and abs(mass - vehicle.mass) <= 0.2 * vehicle.mass
                text += f"; implied mass {mass:.3g} kg (vehicle file {vehicle.mass:.3g} kg)"
            checks.append(Check("hover thrust", ok, text))
        else:
            checks.append(_hover_check(model, level, np.asarray(u, dtype=float)))
    delta = max(1.0, 0.02 * u_h)
    unexcited = _not_excited(model)
    for target, (combo, sign, what) in CONTROL.items():
        if target not in names:
            continue
        s = COMBINATION_SIGNS[combo]
        up = _eval(model, target, level, u_h + delta * s)[0]
        down = _eval(model, target, level, u_h - delta * s)[0]
        slope = float(up - down) / (2 * delta)  # target unit per rad/s of the combination's command
        scale = max(abs(float(_eval(model, target, level, np.full(4, u_h))[0])), 1e-3)
        if abs(slope) * u_h * 0.1 < 1e-6 * scale or slope == 0:
            why = " (not excited by the flight: its minimal model has no control term)" if (
                target in unexcited) else ""
            checks.append(
                Check(f"control {target}", False, f"{target} does not respond to {combo}: {what}{why}")
            )
        else:
            ok = np.sign(slope) == sign
            checks.append(
                Check(f"control {target}", ok, f"d{target}/d({combo} command) {slope:+.3g}: {what}")
            )
    rows = np.arange(len(xi))
    if len(rows) > 400:
        rows = np.linspace(0, len(xi) - 1, 400).astype(int)
    for target, k in SELF.items():
        if target not in names:
            continue
        x = np.asarray(xi, dtype=float)[rows]
        step = max(1e-3, 0.05 * float(np.std(x[:, k]) or 1.0))
        hi, lo = x.copy(), x.copy()
        hi[:, k] += step
        lo[:, k] -= step
        ur = np.asarray(u, dtype=float)[rows]
        d = (_eval(model, target, hi, ur) - _eval(model, target, lo, ur)) / (2 * step)
        mean = float(np.nanmean(d))
        name = STATE_NAMES[k]
        ok = mean <= max_self_feedback
        label = "anti-damping" if not ok else "damping" if mean < 0 else "no feedback"
        checks.append(
            Check(f"self-feedback {target}", ok, f"d{target}/d{name} {mean:+.3g} 1/s on average ({label})")
        )
    return checks


def _not_excited(model) -> set[str]:
    """The targets the model's identification flagged not excited (checks.not_excited; fz stands for az)."""
    learned = getattr(model, "model_", model)
    flagged = set((getattr(learned, "extra", None) or {}).get("checks", {}).get("not_excited", {}) or {})
    return flagged | ({"az"} if "fz" in flagged else set())


def checks_text(checks: list[Check]) -> str:
    """The checks as lines, flags first counted."""
    flags = sum(not c.ok for c in checks)
    head = f"plausibility: {flags} flag(s) in {len(checks)} checks"
    return "\n".join([head, *(f"  {c.line()}" for c in checks)])
