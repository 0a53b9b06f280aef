"""Motor model for logs without rotor speeds: from motor commands to an equivalent rotor speed.

Thrust of one rotor, relative to full thrust, in PX4's THR_MDL_FAC form: T/Tmax = (1 - k) s + k s^2, with s
the throttle in [0, 1] (k = 0 linear, k = 1 quadratic in throttle). With battery voltage V logged, the
throttle is compensated as s = throttle * V / V_ref (a DC motor's speed scales with the voltage it gets;
V_ref = the median voltage of the rows fitted). The equivalent rotor speed (rad/s) is
u = w_ref * sqrt(T/Tmax) (w_ref = 1000 rad/s by convention), so that u^2 is proportional to thrust and the
identified model's f1 = sum u_i^2 terms are thrust terms whatever the curve.

fit_thrust_curve picks k (0, 0.1, ..., 1) and whether to use the voltage, jointly with the thrust-direction
model a_NED - (0, 0, g) = -c * (sum u_i^2) * R(phi, theta, psi)[:, 2] (least squares for c): the curve
whose model explains the three accelerations best (R^2 over the stacked axes) on the rows given.
A user who knows the curve passes --motor-curve instead (identification.readers.rotor_model).
choose_motor_model also uses it on logs that do have rotor speeds, when the commands explain the thrust
direction clearly better (rpm logged at a few Hz and interpolated, a simulator's rpm that does not make
thrust quadratic in it).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from bridge.rotations import rotation_matrix
from identification.table import Dataset
from identification.targets import STANDARD_GRAVITY

W_REF = 1000.0  # rad/s: equivalent rotor speed at full thrust
K_GRID = tuple(round(0.1 * i, 1) for i in range(11))


@dataclass(frozen=True)
class ThrustCurve:
    """T/Tmax = (1 - k) s + k s^2 of throttle s (voltage-compensated when voltage_ref is set, V)."""

    k: float = 0.5
    voltage_ref: float | None = None
    w_ref: float = W_REF
    r2: float | None = None  # of the thrust-direction model on the fitted rows

    def speeds(self, throttle: np.ndarray, voltage: np.ndarray | None) -> np.ndarray:
        """Equivalent rotor speeds (N,4) rad/s of throttles (N,4) in [0, 1] and battery voltage (N,) V."""
        s = np.clip(np.asarray(throttle, dtype=float), 0.0, None)
        if self.voltage_ref is not None and voltage is not None:
            s = s * (np.asarray(voltage, dtype=float)[:, None] / self.voltage_ref)
        rel = np.clip((1.0 - self.k) * s + self.k * s * s, 0.0, None)
        return self.w_ref * np.sqrt(rel)

    def describe(self) -> str:
        """One line: the curve, the voltage compensation, the fit."""
        volt = f", throttle x V/{self.voltage_ref:.2f} V" if self.voltage_ref else ", no voltage compensation"
        fit = f"; thrust-direction R^2 {self.r2:.3f}" if self.r2 is not None else ""
        curve = f"T/Tmax = {1 - self.k:.1f} s + {self.k:.1f} s^2 (THR_MDL_FAC {self.k:.1f})"
        return f"thrust curve {curve}{volt}{fit}"

    def as_dict(self) -> dict:
        """The curve as plain data for the model file."""
        return {
            "form": "T/Tmax = (1-k)*s + k*s^2, u = w_ref*sqrt(T/Tmax), s = throttle*V/voltage_ref",
            "k": self.k,
            "voltage_ref_v": self.voltage_ref,
            "w_ref_rad_s": self.w_ref,
            "thrust_direction_r2": self.r2,
        }


def thrust_direction_r2(ds: Dataset, u: np.ndarray, gravity: float = STANDARD_GRAVITY) -> tuple[float, float]:
    """(R^2 over ax, ay, az stacked, c in m/s^2 per (rad/s)^2) of a_NED - g e3 = -c sum(u^2) R e3."""
    r = rotation_matrix(*ds.xi[:, 6:9].T)
    f1 = (u**2).sum(axis=1)
    x = (-f1[:, None] * r[:, :, 2]).reshape(-1)
    y = (ds.targets[:, :3] - np.array([0.0, 0.0, gravity])).reshape(-1)
    ok = np.isfinite(x) & np.isfinite(y)
    if ok.sum() < 3 or not np.any(x[ok]):
        return float("nan"), float("nan")
    c = float(x[ok] @ y[ok] / (x[ok] @ x[ok]))
    res = y[ok] - c * x[ok]
    ref = ds.targets[:, :3].reshape(-1)[ok]  # R^2 of the accelerations themselves (g is a constant)
    return 1.0 - float(res @ res) / float(((ref - ref.mean()) ** 2).sum()), c


def fit_thrust_curve(ds: Dataset) -> ThrustCurve:
    """The curve (k on K_GRID, with or without voltage) whose thrust-direction model fits ds's rows best."""
    thr = ds.aux.get("throttle")
    if thr is None:
        raise ValueError("fit_thrust_curve needs the aux column 'throttle'")
    volt = ds.aux.get("voltage")
    options: list[float | None] = [None]
    if volt is not None and np.isfinite(volt).all() and len(volt):
        options.append(float(np.median(volt)))
    best = None
    for vref in options:
        for k in K_GRID:
            curve = ThrustCurve(k, vref)
            r2, _ = thrust_direction_r2(ds, curve.speeds(thr, volt))
            if np.isfinite(r2) and (best is None or r2 > best.r2 + 1e-9):
                best = replace(curve, r2=r2)
    return best or ThrustCurve()


SWITCH_MARGIN = 0.01  # R^2 by which the commands' thrust curve must beat measured rotor speeds


def choose_motor_model(train: Dataset) -> tuple[ThrustCurve | None, str]:
    """The thrust curve to remake u with (None: keep the measured rotor speeds), and a line saying why.

    Logs without rotor speeds: the fitted curve. Logs with both rotor speeds and motor commands: the curve
    only when its thrust-direction model beats the measured speeds' by SWITCH_MARGIN in R^2 (e.g. rpm
    reported at 4 Hz, or a simulator whose rpm does not make thrust quadratic in it)."""
    if "throttle" not in train.aux or not np.isfinite(train.aux["throttle"]).all():
        return None, ""
    curve = fit_thrust_curve(train)
    if train.u_from_throttle:
        return curve, f"motor model (fitted on the training rows): {curve.describe()}"
    measured, _ = thrust_direction_r2(train, train.u)
    if curve.r2 is not None and curve.r2 > measured + SWITCH_MARGIN:
        return curve, (
            f"motor model: the motor commands through a {curve.describe()} explain the thrust direction "
            f"better than the logged rotor speeds (R^2 {measured:.3f}): using the commands"
        )
    return None, (
        f"rotor speeds as logged: their thrust-direction R^2 {measured:.3f} is not beaten by the motor "
        f"commands' best thrust curve ({curve.r2:.3f})"
    )


def apply_thrust_curve(ds: Dataset, curve: ThrustCurve) -> Dataset:
    """ds with u remade from its throttle (and voltage) through the curve; a note says which."""
    out = ds.select(slice(None))
    out.u = curve.speeds(ds.aux["throttle"], ds.aux.get("voltage"))
    out.u_from_throttle = True
    out.warnings.append(f"motor model: {curve.describe()}")
    return out


def curve_from_dict(data: dict | None, where: str) -> ThrustCurve:
    """The ThrustCurve a model file recorded (engine.motor_model); UserError when it has none."""
    from bridge.errors import UserError

    if not isinstance(data, dict) or "k" not in data:
        raise UserError(
            f"{where}: the log has no rotor speeds and the model records no motor model (engine.motor_model)",
            hint="pass --motor-curve, or validate a model identified from motor commands",
        )
    try:
        vref = data.get("voltage_ref_v")
        return ThrustCurve(
            float(data["k"]), None if vref is None else float(vref), float(data.get("w_ref_rad_s", W_REF))
        )
    except (TypeError, ValueError):
        raise UserError(f"{where}: engine.motor_model is malformed ({data!r})") from None
