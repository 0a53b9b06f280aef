"""The backstepping controller's gains and limits: a typed, validated dataclass, loadable from YAML.

Backstepping gains c1..c8 are the paper's (Section IV). The paper does not give the outer PI gains. Ours put
both poles of the x and y error dynamics e'' + k_p e' + k_i e = 0 at s = -3.5 rad/s (k_p = 2w = 7,
k_i = w^2 = 12.25): critically damped, so the paper's Case II step has no overshoot, and 4.6 times slower than
the slowest inner pole (pitch, s^2 + (c3 + c7) s + 1 + c3 c7: about -16 rad/s), so the inner loop may be
treated as instantaneous. w and the error clip were picked by a sweep in the in-process simulator (true model,
motor lag, Case I and II from the ground, w in {2.5, 3, 3.5, 4, 5} rad/s, clip in {1.5, 2, 3} m): w = 3.5 with
a 2 m clip has the smallest error after 4 s (under 1 mm, settled within 5 cm at 2.6 s) with the actual tilt
inside the 35 deg limit; w = 4 settles 0.5 s sooner in Case I but tilts past the limit; w = 5 fights the inner
loop (3 to 15 mm RMS after 5 s instead of 0.01 mm); w <= 3 or a 1.5 m clip settle later (3.0 to 3.9 s).

Model-error observer (the integral action, controller.backstepping.ModelErrorObserver): 10 1/s on x'', y'',
z'' (kept in the body frame) and on the angular accelerations, picked in the in-process simulator on the
SITL's dynamics (Case I and II, the paper-train learned model and the true model, rates 5 to 40) and checked
on the SITL. Noise-free, RMS after 5 s: the learned model goes from 1.24x / 1.77x the true model's to 1.00x /
1.00x, and the true model's own figure improves, the observer also taking in the motor lag: 6.2 -> 2.3 um
(Case I), 2.9 -> 2.8 um (Case II). A thrust coefficient 2 % off costs 2.2 mm / 2.0 mm without the observer,
4.3 um / 2.8 um with it; drag 2 % off 341 um -> 40 um (Case I). Faster rates gain little more without noise
but, with the realistic sensors and the estimated state, put the motors at a limit more often (2 % of the
steps without the observer, 3 % at 10 1/s, 5 % at 20 1/s); the angular observer rings from about 40 1/s
(the motor lag is inside its loop), so 10 leaves a 4x margin. Cost: two model evaluations per step.

What keeps the observer from destabilising the loop (issue 15: with realistic sensors and --state sensors a
take-off at full thrust made it run away to 6.7 m): its estimate is clamped (4 m/s^2, 5 rad/s^2); a step
whose motors saturate or lag the command by more than observer_gate_speed (30 rad/s) is skipped; and its
bandwidth drops when its innovations are noisy, keeping the estimate's noise near observer_noise_accel
(0.08 m/s^2) and observer_noise_angular (0.2 rad/s^2). Noise-free, 10 1/s holds; with the realistic sensors'
estimated state it settles near 1 1/s (RMS after 5 s on a 2 m hold 21.9 mm at 1 1/s adaptive; 63 mm at a
fixed 10 1/s; 16.9 mm without the observer).

A YAML file overrides any subset of the defaults, flat keys:

    c1: 11.52        # ... c8
    k_px: 7.0
    k_ix: 12.25
    max_tilt_deg: 45
    max_feedback_tilt_deg: 35
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from bridge.errors import UserError
from bridge.yaml_file import Section, load_yaml_file

PAPER_C = (11.52, 28.00, 16.63, 6.54, 8.40, 27.50, 15.54, 5.49)
DERIVATIVE_MODES = ("analytic", "filter")


@dataclass(frozen=True)
class BacksteppingGains:
    """Gains [SI] and real-vehicle limits of the PI outer loop and backstepping inner loop."""

    # backstepping gains c1..c8 [1/s]: i = 1..4 for z, phi, theta, psi; c_{i+4} on the velocity error delta_i
    c: tuple[float, ...] = PAPER_C
    # outer PI: x'' = x_d'' + k_px e_x' + k_ix e_x [k_p 1/s, k_i 1/s^2] (same for y)
    k_px: float = 7.0
    k_ix: float = 12.25
    k_py: float = 7.0
    k_iy: float = 12.25
    # model-error observer (controller.backstepping.ModelErrorObserver): bandwidth [1/s] of its estimate of
    # what the model gets wrong in x'', y'', z'' and in the body angular accelerations; 0 turns it off (the
    # paper's law exactly)
    observer_rate: float = 10.0
    observer_angular_rate: float = 10.0
    observer_max_accel: float = 4.0  # m/s^2, clamp of each translational estimate (40 % of g)
    observer_max_angular: float = 5.0  # rad/s^2, clamp of each angular estimate
    # consistency gate [rad/s]: the estimate is held over a step whose commanded rotor speeds saturate or
    # differ from the measured ones by more than this (the model cannot predict a step the motors lag
    # through: a take-off at full thrust made it run away); 0 turns the gate off
    observer_gate_speed: float = 30.0
    # noise-adaptive bandwidth: the estimate's noise std is kept near these [m/s^2, rad/s^2] by lowering the
    # filter gain when the innovations are noisy (an estimated state); noise-free, the rates above hold.
    # 0 turns the adaptation off
    observer_noise_accel: float = 0.08  # d_T, along the thrust axis
    observer_noise_angular: float = 0.2
    # the horizontal NED part d_E (wind): its noise goes straight into the commanded tilt, so it is kept
    # quieter (hold 2 m, realistic sensors, --state sensors, learned model: 21.9 mm RMS after 5 s at 0.08,
    # 18.2 mm at 0.05 on all three translational channels; SE(3) 16.1 mm), d_T's 0.08 keeps the thrust
    # mismatch's rejection under a noisy, delayed state (0.05 there: 2.7 instead of 2.1 cm at 12 ms delay)
    observer_noise_horizontal: float = 0.05
    # optional integral of the position error [1/s^3] (0: off). It winds up in every transient (k_int = 4:
    # 7 mm RMS after 5 s even on the true model); the observer above is the integral action to use
    k_int: float = 0.0
    # --- real-vehicle limits
    # deg, largest commanded tilt: what the reference and the model error (wind) need may use all of it, as
    # the baselines' 45 deg (PX4's MPC_TILTMAX_AIR); at 35 the aggressive circle in 5 m/s of wind sat on the
    # limit (0.21 m RMS after 5 s against SE(3)'s 0.11 m at 45)
    max_tilt_deg: float = 45.0
    # deg, the tilt the position feedback alone may ask (a far error closes at this; the reference's needs
    # and the model error come first, up to max_tilt_deg); the PI gains were chosen with approaches inside it
    max_feedback_tilt_deg: float = 35.0
    max_position_error: float = 2.0  # m, horizontal error fed to the k_i term is clipped to this length
    max_integral_accel: float = 1.0  # m/s^2, anti-windup clamp of the k_int integral's contribution
    integral_zone: float = 0.5  # m, the k_int integral only integrates within this horizontal error
    max_climb_accel: float = 6.0  # m/s^2, largest upward acceleration asked of the outer solve
    max_sink_fraction: float = 0.7  # share of gravity the outer solve may ask as downward acceleration
    ground_clearance: float = 0.05  # m, below this height the vehicle counts as on the ground
    ground_tilt_deg: float = 3.0  # deg, tilt limit while on the ground (no tipping over at take-off)
    # --- phi_d, theta_d derivatives: "analytic" (implicit differentiation of the outer inversion through the
    # reference's jerk and snap and the ideal error dynamics) or "filter" (a 2nd-order command filter)
    derivative_mode: str = "analytic"
    filter_bandwidth: float = 40.0  # rad/s, natural frequency of the command filter (critically damped)
    newton_iterations: int = 8  # cap per control step for numeric inversions

    @property
    def c_gains(self) -> tuple[float, ...]:
        """c1..c8 as a tuple of floats."""
        return tuple(float(v) for v in self.c)

    def replace(self, **changes: Any) -> BacksteppingGains:
        """A validated copy with some fields changed."""
        out = dataclasses.replace(self, **changes)
        validate_gains(out, "gains")
        return out


_FLOAT_FIELDS = {
    f.name for f in dataclasses.fields(BacksteppingGains) if f.type in ("float", float)
}


def validate_gains(g: BacksteppingGains, where: str) -> None:
    """Raise UserError naming `where` and the key when a gain or limit is out of range."""
    if len(g.c) != 8:
        raise UserError(f"{where}: c must have 8 values c1..c8, got {len(g.c)}")
    for i, v in enumerate(g.c, 1):
        if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
            raise UserError(f"{where}: c{i} must be a positive number, got {v!r}",
                            hint="backstepping needs c_i > 0 for W' = -c_i e_i^2 - c_{i+4} delta_i^2 < 0")
    for name in ("k_px", "k_ix", "k_py", "k_iy", "max_position_error", "filter_bandwidth", "max_climb_accel"):
        v = getattr(g, name)
        if not (math.isfinite(v) and v > 0):
            raise UserError(f"{where}: {name} must be a positive number, got {v!r}")
    for name in ("k_int", "max_integral_accel", "integral_zone", "ground_clearance", "ground_tilt_deg",
                 "observer_rate", "observer_angular_rate", "observer_max_accel", "observer_max_angular",
                 "observer_gate_speed", "observer_noise_accel", "observer_noise_angular",
                 "observer_noise_horizontal"):
        v = getattr(g, name)
        if not (math.isfinite(v) and v >= 0):
            raise UserError(f"{where}: {name} must be a number >= 0, got {v!r}")
    for name in ("max_tilt_deg", "max_feedback_tilt_deg"):
        if not 0 < getattr(g, name) < 80:
            raise UserError(f"{where}: {name} must be in (0, 80) deg, got {getattr(g, name)!r}")
    if not 0 < g.max_sink_fraction < 1:
        raise UserError(f"{where}: max_sink_fraction must be in (0, 1), got {g.max_sink_fraction!r}")
    if g.ground_tilt_deg > g.max_tilt_deg:
        raise UserError(f"{where}: ground_tilt_deg must not exceed max_tilt_deg")
    if g.derivative_mode not in DERIVATIVE_MODES:
        raise UserError(f"{where}: derivative_mode must be one of {', '.join(DERIVATIVE_MODES)}, "
                        f"got {g.derivative_mode!r}")
    if not (isinstance(g.newton_iterations, int) and 1 <= g.newton_iterations <= 100):
        raise UserError(f"{where}: newton_iterations must be an integer in [1, 100]")
    # the observer's estimate comes from one step's velocity change: faster than the 250 Hz step, it is noise;
    # the angular one closes a loop through the motor lag and the attitude loop (it rings from ~40 1/s here)
    for name, top in (("observer_rate", 100.0), ("observer_angular_rate", 25.0)):
        if getattr(g, name) > top:
            raise UserError(f"{where}: {name} must be at most {top:g} 1/s, got {getattr(g, name)!r}",
                            hint="it is the bandwidth of the model-error observer (default 10)")
    # PI stability of e'' + k_p e' + k_i e + k_int (integral of e) = 0 (Routh-Hurwitz: k_p k_i > k_int)
    for kp, ki, axis in ((g.k_px, g.k_ix, "x"), (g.k_py, g.k_iy, "y")):
        if g.k_int >= kp * ki:
            raise UserError(f"{where}: k_int must be below k_p{axis} * k_i{axis} = {kp * ki:g} for stability")


def load_gains(path: str | os.PathLike[str] | None) -> BacksteppingGains:
    """Defaults, overridden by the flat keys of a YAML file (None: the defaults); UserError on a bad file."""
    if path is None:
        return BacksteppingGains()
    p = Path(path)
    return gains_from_dict(load_yaml_file(p, f"gains file {p}") or {}, str(p))


def gains_from_dict(data: Any, where: str = "gains") -> BacksteppingGains:
    """Gains from a flat mapping (c1..c8, k_px, ..., limits); UserError naming `where` and the key."""
    sec = Section(where, {} if data is None else data)
    c = [sec.number(f"c{i}", default) for i, default in enumerate(PAPER_C, 1)]
    changes: dict[str, Any] = {}
    for name in (f.name for f in dataclasses.fields(BacksteppingGains) if f.name != "c"):
        if not sec.has(name):
            continue
        if name in _FLOAT_FIELDS:
            changes[name] = sec.number(name)
        elif name == "newton_iterations":
            changes[name] = sec.integer(name)
        else:
            changes[name] = sec.text(name)
    sec.done()
    gains = BacksteppingGains(c=tuple(c), **changes)
    validate_gains(gains, where)
    return gains


def gains_to_dict(g: BacksteppingGains) -> dict[str, Any]:
    """The flat mapping written to YAML (c1..c8 expanded)."""
    out: dict[str, Any] = {f"c{i}": float(v) for i, v in enumerate(g.c, 1)}
    for f in dataclasses.fields(g):
        if f.name != "c":
            out[f.name] = getattr(g, f.name)
    return out


