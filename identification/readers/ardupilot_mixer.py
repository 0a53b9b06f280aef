"""ArduCopter's motor outputs at its loop rate, rebuilt from the mixer inputs it logs in RATE.

ArduCopter logs RCOU (the PWM it outputs) only in its 10 Hz logging task, whatever LOG_BITMASK says, but with
ATTITUDE_FAST it logs RATE at the loop rate (400 Hz), and RATE carries the mixer's inputs: AOut (throttle),
ROut, POut, YOut (roll, pitch, yaw demands, -1..1). For a multicopter below saturation the mixer
(AP_MotorsMatrix::output_armed_stabilizing) makes each motor's thrust demand a linear function of those four,
and AP_Motors turns thrust t into the actuator a (a fraction of MOT_PWM_MIN..MAX) through MOT_THST_EXPO e and
MOT_SPIN_MIN/MAX:
    x = (a - spin_min) / (spin_max - spin_min),   t = (1 - e) x + e x^2.
So the 10 Hz RCOU samples, linearised to t and paired with the RATE record of the same loop, fit the four
linear maps t_i = c_i0 + c_i . (AOut, ROut, POut, YOut) (least squares, unsaturated samples only); the maps
applied to every RATE record give the outputs at 400 Hz, through the same curve back to a. The fit's R^2 per
motor on the RCOU samples says whether it holds; below MIN_FIT_R2 (or with too few samples) it is not used.
Where the motors are not spinning (RCOU at or below MOT_SPIN_MIN: disarmed, spooling) RCOU is kept.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

DEFAULTS = {"MOT_SPIN_MIN": 0.15, "MOT_SPIN_MAX": 0.95, "MOT_THST_EXPO": 0.65}  # ArduCopter's defaults
INPUTS = ("AOut", "ROut", "POut", "YOut")
MIN_FIT_R2 = 0.99  # the loop-rate outputs are used only if every motor's fit explains RCOU this well
MIN_SAMPLES = 20  # RCOU samples in the unsaturated range needed for the fit
SAME_LOOP_S = 0.003  # a RATE record this close before an RCOU record is from the same loop (2.5 ms at 400 Hz)
EDGE = 0.005  # fraction of the PWM range kept clear of spin_min and spin_max for the fit (saturation)


@dataclass
class MixerFit:
    """The fitted maps (4 motors x [1, AOut, ROut, POut, YOut]), R^2 per motor, samples used, or why not."""

    coefficients: np.ndarray | None
    r2: tuple[float, ...]
    samples: int
    reason: str = ""

    @property
    def usable(self) -> bool:
        """True when every motor's map explains its RCOU samples with R^2 >= MIN_FIT_R2."""
        return self.coefficients is not None and not self.reason


def _curve(params: dict[str, float]) -> tuple[float, float, float]:
    """(spin_min, spin_max, expo) from the log's parameters (ArduCopter's defaults where absent)."""
    lo = float(params.get("MOT_SPIN_MIN", DEFAULTS["MOT_SPIN_MIN"]))
    hi = float(params.get("MOT_SPIN_MAX", DEFAULTS["MOT_SPIN_MAX"]))
    expo = min(max(float(params.get("MOT_THST_EXPO", DEFAULTS["MOT_THST_EXPO"])), -1.0), 1.0)
    return lo, hi, expo


def thrust_of_actuator(a: np.ndarray, params: dict[str, float]) -> np.ndarray:
    """ArduCopter's thrust demand (0..1) of actuator outputs a (fraction of the PWM range)."""
    lo, hi, e = _curve(params)
    x = (np.asarray(a, dtype=float) - lo) / (hi - lo)
    return (1.0 - e) * x + e * x * x


def actuator_of_thrust(t: np.ndarray, params: dict[str, float]) -> np.ndarray:
    """Actuator outputs (fraction of the PWM range) of thrust demands t, as AP_Motors' thrust_to_actuator."""
    lo, hi, e = _curve(params)
    t = np.clip(np.asarray(t, dtype=float), 0.0, 1.0)
    x = t if abs(e) < 1e-9 else ((e - 1.0) + np.sqrt((1.0 - e) ** 2 + 4.0 * e * t)) / (2.0 * e)
    return lo + (hi - lo) * np.clip(x, 0.0, 1.0)


def fit_mixer(rate_t: np.ndarray, inputs: np.ndarray, rcou_t: np.ndarray, rcou: np.ndarray,
              params: dict[str, float]) -> MixerFit:
    """Fit thrust_i = c_i0 + c_i . inputs (RATE's AOut, ROut, POut, YOut) on the RCOU samples (s; actuator
    fractions, motor order) that are unsaturated and have a RATE record of the same loop."""
    lo, hi, _ = _curve(params)
    idx = np.searchsorted(rate_t, rcou_t, side="right") - 1
    ok = idx >= 0
    idx = np.clip(idx, 0, len(rate_t) - 1)
    ok &= (rcou_t - rate_t[idx]) <= SAME_LOOP_S
    ok &= np.all((rcou > lo + EDGE) & (rcou < hi - EDGE), axis=1) & np.all(np.isfinite(inputs[idx]), axis=1)
    n = int(ok.sum())
    if n < MIN_SAMPLES:
        return MixerFit(None, (), n, f"{n} unsaturated RCOU samples with a RATE record of the same loop "
                                     f"(need {MIN_SAMPLES})")
    design = np.column_stack((np.ones(n), inputs[idx[ok]]))
    thrust = thrust_of_actuator(rcou[ok], params)
    coef, *_ = np.linalg.lstsq(design, thrust, rcond=None)
    resid = thrust - design @ coef
    var = np.var(thrust, axis=0)
    r2 = tuple(float(1.0 - np.mean(resid[:, j] ** 2) / var[j]) if var[j] > 0 else math.nan for j in range(4))
    worst = min((r for r in r2 if math.isfinite(r)), default=math.nan)
    reason = "" if worst >= MIN_FIT_R2 else f"the fit explains RCOU only to R^2 {worst:.4f} (< {MIN_FIT_R2})"
    return MixerFit(coef.T, r2, n, reason)


def loop_rate_outputs(fit: MixerFit, rate_t: np.ndarray, inputs: np.ndarray, rcou_now: np.ndarray,
                      params: dict[str, float]) -> np.ndarray:
    """Actuator outputs (N,4; fraction of the PWM range, motor order) at RATE's times from its mixer inputs;
    where RCOU (rcou_now: RCOU resampled at those times) shows a motor not spinning, RCOU's value."""
    assert fit.coefficients is not None
    thrust = np.column_stack((np.ones(len(rate_t)), inputs)) @ fit.coefficients.T
    out = actuator_of_thrust(thrust, params)
    lo, _, _ = _curve(params)
    idle = ~(rcou_now > lo + EDGE)  # also NaN (outside RCOU's span): not rebuilt
    return np.where(idle, rcou_now, out)
