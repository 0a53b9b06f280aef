"""The paper's controller as a plug-in: PI outer loop (x, y) and backstepping inner loop (z, phi, theta, psi).

Inner loop (Section III-B): with s = (z, phi, theta, psi, z', phi', theta', psi'), e_i = s_id - s_i and
delta_i = s_id' + c_i e_i - s_{i+4}, the law solves

    gamma_{i+4}(s, f) = e_i + s_id'' + c_i (s_id' - s_{i+4}) + c_{i+4} delta_i        i = 1..4

for f = (f1..f4), which gives W_i' = -c_i e_i^2 - c_{i+4} delta_i^2 for W_i = (e_i^2 + delta_i^2)/2.
s_1d = z_d, s_4d = psi_d come from the reference; s_2d = phi_d, s_3d = theta_d from the outer loop, with
their first and second derivatives from implicit differentiation of the outer inversion (derivative_mode
"analytic", the default) or from a second-order command filter ("filter"). The gammas and their solve are
derived from the model (controller.derivation); the speeds come from f through controller.allocation.

Integral action: a ModelErrorObserver estimates, from each step's measured velocity and body-rate changes,
what the model gets wrong (d, NED m/s^2 and FRD rad/s^2); the outer loop asks for a_x - d_x, a_y - d_y, the z
design for gamma_5 - d_z and the attitude designs for gamma_{6..8} - R(phi, theta) d_w. With an exact model
and motors without lag, d stays at the trapezoid rule's error over a step and this is the paper's law.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import sympy

from controller import native
from controller.allocation import allocate_floats
from controller.derivation import XI, DerivedLaw, U, derive_law, fast_function, normalise
from controller.gains import BacksteppingGains, validate_gains
from controller.outer_loop import OuterLoop
from controller.plugin import Command, Reference, VehicleState, as_floats
from identification.model_file import TARGET_NAMES

NOMINAL_DT = 0.004  # s, the HIL exchange step (250 Hz)
NOISE_MEMORY = 1.0  # s, time constant of the model-error observer's innovation-noise estimate
MIN_NOISE_SAMPLES = 10  # innovations seen before the noise-adaptive observer updates its estimate


class ModelErrorObserver:
    """What the model gets wrong as the vehicle flies, low-passed: the controller's integral action.

    Over each control step, the vehicle's velocity change (NED) and body-rate change (FRD) are compared with
    what the model predicts for that step (its x'', y'', z'' and dwx, dwy, dwz by the trapezoid rule over the
    step's two ends, at the measured states and the rotor speeds commanded for the step). The difference
    d = measured - modelled goes through a first-order low-pass at `rate` (translational [1/s]) and
    `angular_rate` (FRD [rad/s^2], [1/s]); the controller asks the model for (design) - d, so the vehicle
    does what the design asks.

    Why this and not an integral of the tracking error: d does not see the tracking transient. With an exact
    model (and motors without lag) d stays at the trapezoid rule's error over a step (under 1e-3 m/s^2 in a
    take-off) from any initial condition, so the paper's error dynamics are untouched, while a constant
    model error is removed exactly, as an integral action would.

    Which frame: the translational estimate is kept in two parts, d = d_T b3 + (d_Ex, d_Ey, 0), b3 = R e3
    the body z axis (NED): each measured difference m is split as m = (m_z / b3_z) b3 + the horizontal rest
    (a bijection while the tilt is below 90 deg). d_T [m/s^2] turns with the vehicle: the largest model
    error, the thrust coefficient's (or the mass's), is a force along the thrust axis, and its estimate then
    needs no time to follow the attitude (its NED rate, d_T R (w x e3), goes into the attitude feedforward).
    d_E (NED, horizontal [m/s^2]) stays put when the vehicle turns: a steady wind's drag is a horizontal
    earth-fixed force, and kept in the body frame it was turned away with every change of heading (a
    1 m/s^2 NED push on the figure-eight with yaw: 5.9 mm RMS after 5 s in the body frame, 0.04 mm in this
    split: tests/test_backstepping.py). Both kinds are split exactly at any attitude; the filter moves the
    sum by its gain times the innovation.

    With the commanded (not the measured) rotor speeds, d also takes in what the motors do not deliver at
    once (their lag, a throttle-curve error). Anti-windup: d is the model's error, not an integral of the
    tracking error, so limits and saturation cannot wind it up; d_T and each of d_E's components are clamped
    to +-max_accel, the angular ones to +-max_angular, and all are reset while the vehicle is on the ground
    (the ground pushes back).
    """

    def __init__(self, expressions: Mapping[str, sympy.Expr], rate: float, angular_rate: float,
                 max_accel: float, max_angular: float, hover_speed: float = 0.0, noise_accel: float = 0.0,
                 noise_angular: float = 0.0, noise_horizontal: float | None = None):
        names = TARGET_NAMES if angular_rate > 0.0 else TARGET_NAMES[:3]
        self._accel = None
        self.code = "off"  # its model function: "compiled", "python (why)", or off
        if rate > 0.0 or angular_rate > 0.0:
            norm = normalise(expressions)
            self._accel = fast_function("model (observer)", list(XI) + list(U), [norm[n] for n in names],
                                        dict.fromkeys(U, hover_speed))
            state = native.status().get("model (observer)", "python")
            self.code = "compiled" if state == "native" else f"python ({state})"
        # channels: d_Ex, d_Ey (NED), d_T (along b3), then angular (FRD, when the angular observer is on)
        self._rates = ((rate,) * 3 + (angular_rate,) * 3)[: len(names)]
        self._limits = ((max_accel,) * 3 + (max_angular,) * 3)[: len(names)]
        # noise-adaptive gain: d's noise is about sigma sqrt(k / 2) for a white innovation of std sigma and
        # a filter gain k, so k is capped at 2 (target / sigma)^2 (target: d's noise std; 0: no cap)
        horizontal = noise_accel if noise_horizontal is None else noise_horizontal  # d_Ex, d_Ey
        self._targets = ((horizontal, horizontal, noise_accel) + (noise_angular,) * 3)[: len(names)]
        self._noise_var = [0.0] * 6  # sigma^2 per channel, from the first differences of the measurements
        self._noise_count = [0] * 6  # measurements differenced so far, per channel
        self._last_meas: list[float | None] = [None] * 6
        self.gains_used = [0.0] * 6  # the filter gain per step last used, per channel (for logs and tests)
        self._dt = -1.0
        # (index, gain 1 - e^(-rate dt) > 0, limit, noise cap 2 target^2) at _dt
        self._filters: list[tuple[int, float, float, float]] = []
        self._var_gain = 0.0
        self.reset()

    def reset(self) -> None:
        """Forget the estimate and the last step (the noise level learnt is kept: see forget_noise)."""
        # d_Ex, d_Ey (NED horizontal) [m/s^2], d_T (along the body z axis b3, FRD: + down the body)
        # [m/s^2], then angular FRD [rad/s^2]
        self.value = [0.0] * 6
        self._start: tuple[tuple[float, ...], list[float], list[float]] | None = None
        self._last_meas = [None] * 6

    def forget_noise(self) -> None:
        """Forget the noise level learnt (before a new flight)."""
        self._noise_var = [0.0] * 6
        self._noise_count = [0] * 6

    def start_step(self, xi: list[float], u: list[float], consistent: bool = True) -> None:
        """A step starts at state xi (airborne) with the rotor speeds u [rad/s] just commanded for it;
        `consistent` False (the consistency gate: motors saturated, or the command far from the measured
        rotor speeds, so the model cannot say what the vehicle will do this step) holds the estimate."""
        if self._accel is None or not consistent:
            self._start = None
            return
        try:
            a = self._accel(*xi, *u)
        except (ValueError, ZeroDivisionError, OverflowError):  # outside the model's domain: skip the step
            self._start = None
            return
        self._start = ((xi[3], xi[4], xi[5], xi[9], xi[10], xi[11]), a, u)

    def end_step(self, dt: float, xi: list[float]) -> tuple[list[float], list[float]]:
        """The step of dt [s] ended at state xi: update d; return (d at xi: translational NED [m/s^2], then
        angular FRD [rad/s^2]; the NED part's rate d_T R (w x e3) [m/s^3])."""
        start = self._start
        self._start = None
        d = self.value
        a = None
        if start is not None and dt > 0.0:
            pv, pa, u = start
            try:
                a = self._accel(*xi, *u)
            except (ValueError, ZeroDivisionError, OverflowError):
                pass
        if a is None and not any(d):  # off, just off the ground, or nothing to update an estimate of 0 with
            return [0.0] * 6, [0.0, 0.0, 0.0]
        # bridge.rotations.rotation_from_euler written out: this runs every control step
        sf, cf = math.sin(xi[6]), math.cos(xi[6])
        st, ct = math.sin(xi[7]), math.cos(xi[7])
        sp, cp = math.sin(xi[8]), math.cos(xi[8])
        r00, r01, r02 = ct * cp, sf * st * cp - cf * sp, cf * st * cp + sf * sp
        r10, r11, r12 = ct * sp, sf * st * sp + cf * cp, cf * st * sp - sf * cp
        r20, r21, r22 = -st, sf * ct, cf * ct  # (r02, r12, r22) = b3, the body z axis in NED
        if a is not None and r22 > 0.05:  # upside down (or within 3 deg of on edge): no split; hold
            if dt != self._dt:
                self._dt = dt
                gains = [1.0 - math.exp(-k * dt) for k in self._rates]
                self._filters = [(i, k, self._limits[i], 2.0 * self._targets[i] ** 2)
                                 for i, k in enumerate(gains) if k > 0.0]
                self._var_gain = 1.0 - math.exp(-dt / NOISE_MEMORY)
            inv = 1.0 / dt
            mx = (xi[3] - pv[0]) * inv - 0.5 * (a[0] + pa[0])
            my = (xi[4] - pv[1]) * inv - 0.5 * (a[1] + pa[1])
            mt = ((xi[5] - pv[2]) * inv - 0.5 * (a[2] + pa[2])) / r22  # m = mt b3 + (horizontal rest)
            meas = [mx - mt * r02, my - mt * r12, mt]
            if len(a) == 6:
                meas += [(xi[9] - pv[3]) * inv - 0.5 * (a[3] + pa[3]),
                         (xi[10] - pv[4]) * inv - 0.5 * (a[4] + pa[4]),
                         (xi[11] - pv[5]) * inv - 0.5 * (a[5] + pa[5])]
            var, last, av = self._noise_var, self._last_meas, self._var_gain
            for i, k, lim, cap in self._filters:
                m = meas[i]
                if m != m:  # NaN: the model has no value here; keep the estimate
                    continue
                prev = last[i]
                last[i] = m
                if prev is not None:  # white noise doubles its variance in a first difference
                    dm = m - prev
                    n = self._noise_count[i] = self._noise_count[i] + 1
                    w = 1.0 / n if n * av < 1.0 else av  # the sample mean until the memory is full
                    var[i] += w * (0.5 * dm * dm - var[i])
                if cap > 0.0:
                    if self._noise_count[i] < MIN_NOISE_SAMPLES:
                        continue  # no noise level yet: hold the estimate
                    if k * var[i] > cap:
                        k = cap / var[i]
                self.gains_used[i] = k
                x = d[i] + k * (m - d[i])
                if x > lim:
                    x = lim
                elif x < -lim:
                    x = -lim
                d[i] = x
            if not any(d):
                return [0.0] * 6, [0.0, 0.0, 0.0]
        ex, ey, dt_ = d[0], d[1], d[2]
        wx, wy = xi[9], xi[10]
        # d = (d_Ex, d_Ey, 0) + d_T b3; its rate d_T R (w x e3), w x e3 = (wy, -wx, 0)
        return ([ex + dt_ * r02, ey + dt_ * r12, dt_ * r22, d[3], d[4], d[5]],
                [dt_ * (r00 * wy - r01 * wx), dt_ * (r10 * wy - r11 * wx), dt_ * (r20 * wy - r21 * wx)])


def _wrap(angle: float) -> float:
    return (angle + math.pi) % (2.0 * math.pi) - math.pi


def designed_gamma(c_i: float, c_i4: float, sd: float, sd1: float, sd2: float, s: float, s4: float) -> float:
    """The paper's designed value of gamma_{i+4}: e_i + s_id'' + c_i (s_id' - s_{i+4}) + c_{i+4} delta_i."""
    e = sd - s
    return e + sd2 + c_i * (sd1 - s4) + c_i4 * (sd1 + c_i * e - s4)


class BacksteppingController:
    """Fang and Chen's PI + backstepping tracking controller, derived at start-up from a model's expressions.

    `model` is an identification Model (or any object with `.expressions`) or a dict of the six target
    expressions; `vehicle` supplies w_max (its motor curve). A model that cannot be inverted raises UserError.
    """

    name = "backstepping"

    def __init__(self, model: Any, vehicle: Any = None, gains: BacksteppingGains | None = None, *,
                 w_max: float | None = None):
        exprs: Mapping[str, sympy.Expr] = model.expressions if hasattr(model, "expressions") else model
        source = getattr(model, "source", None)
        # what the flight's figures and tables say this controller flew on
        self.model_label = f"{getattr(model, 'kind', 'given')} model" + \
            (f" {Path(source).name}" if source else "")
        if w_max is None:
            if vehicle is None:
                raise ValueError("give the vehicle (for its motor curve) or w_max")
            w_max = float(vehicle.motor_curve.max_speed)
        self.w_max = float(w_max)
        self.gains = gains if gains is not None else BacksteppingGains()
        validate_gains(self.gains, "gains")
        self.law: DerivedLaw = derive_law(exprs, self.w_max)
        self.outer_loop = OuterLoop(self.gains, self.law.gravity)
        self._vertical = self.outer_loop.vertical_limits()
        g = self.gains
        self._observer_gate = g.observer_gate_speed if g.observer_gate_speed > 0.0 else math.inf
        self.observer = ModelErrorObserver(exprs, g.observer_rate, g.observer_angular_rate,
                                           g.observer_max_accel, g.observer_max_angular, self.law.hover_speed,
                                           g.observer_noise_accel, g.observer_noise_angular,
                                           g.observer_noise_horizontal)
        c = self.gains.c_gains
        self._c = c
        self._kz = (1.0 + c[0] * c[4], c[0] + c[4])  # z error dynamics e'' + kz1 e' + kz0 e = 0
        self._tilt = math.radians(self.gains.max_tilt_deg)
        self._tilt_ground = math.radians(self.gains.ground_tilt_deg)
        # worked out once, not every step (gains are frozen)
        self._angle_limit = self._tilt + 0.2  # rad, the outer Newton's angle clamp
        self._analytic = g.derivative_mode == "analytic"
        self._frozen = self.law.outer.mode == "frozen"
        # each outer-inversion parameter's (p', p'') as an index into the pairs update() builds:
        # 0-2 position (v, a), 3-5 velocity (a, a'), 6 yaw (psi', psi''), 7 fixed (0, 0)
        index = []
        for name in self.law.outer.param_names:
            if name in ("x", "y", "z"):
                index.append("xyz".index(name))
            elif name in ("vx", "vy", "vz"):
                index.append(3 + ("vx", "vy", "vz").index(name))
            else:
                index.append(6 if name == "psi" else 7)
        self._param_rate_index = index
        self.reset()

    def describe(self) -> str:
        """How the law was derived (one line)."""
        return f"{self.law.describe()}; model-error observer: {self.observer.code}"

    def reset(self) -> None:
        """Clear the integrator, the command filter and the warm starts."""
        self.outer_loop.reset()
        self.observer.reset()
        self.observer.forget_noise()
        law = self.law
        self._q = [0.0, 0.0, law.hover_f[0]][: law.outer.n]
        self._qd = [0.0] * law.outer.n
        self._qdd = [0.0] * law.outer.n
        self._f = list(law.hover_f)
        self._t_prev: float | None = None
        self._filt: list[float] | None = None  # phi_f, phi_f', theta_f, theta_f'

    # ------------------------------------------------------------------------------------------------------
    def update(self, t: float, state: VehicleState, reference: Reference) -> Command:
        """Motor speeds [rad/s, PX4 order] in [0, w_max] for the state (NED/FRD) and reference at t [s]."""
        law, g = self.law, self.gains
        c0, c1, c2, c3, c4, c5, c6, c7 = self._c
        xi = as_floats(state.xi)
        u_meas = as_floats(state.rotor_speeds)
        if self._t_prev is None:
            dt = NOMINAL_DT
        else:
            dt = t - self._t_prev
            if 0.0 > dt:  # max(dt, 0.0), keeping a NaN as max() does
                dt = 0.0
        self._t_prev = t
        z, vz = xi[2], xi[5]
        phi, theta, psi = xi[6], xi[7], xi[8]
        wx, wy, wz = xi[9], xi[10], xi[11]
        rp = as_floats(reference.position)
        rv = as_floats(reference.velocity)
        ra = as_floats(reference.acceleration)
        rj = as_floats(reference.jerk)
        rs = as_floats(reference.snap)
        on_ground = z > -g.ground_clearance
        # (phi', theta', psi') = R(phi, theta) w, as InnerInversion.euler_angle_rates (its trig reused below)
        sf, cf = math.sin(phi), math.cos(phi)
        st, ct = math.sin(theta), math.cos(theta)
        dpsi = (sf * wy + cf * wz) / ct
        dphi, dtheta = wx + dpsi * st, cf * wy - sf * wz
        observer = self.observer
        if on_ground:
            observer.reset()
        d, d_rate = observer.end_step(dt, xi)
        d0, d1, d2, d3, d4, d5 = d

        # z and psi channels (their designed second derivatives also feed the outer solve)
        zd, zd1, zd2 = rp[2], rv[2], ra[2]
        v5 = designed_gamma(c0, c4, zd, zd1, zd2, z, vz)
        e1, de1 = zd - z, zd1 - vz
        k0, k1 = self._kz
        dde1 = -(k0 * e1 + k1 * de1)
        v5_1 = rj[2] + k0 * de1 + k1 * dde1
        v5_2 = rs[2] + k0 * dde1 + k1 * -(k0 * de1 + k1 * dde1)
        # the z design's vertical acceleration is kept within the outer loop's vertical limits: a large
        # height error then climbs at the limit and leaves the motors room for the attitude (thrust and
        # attitude before position), instead of asking for full or zero thrust
        up, down = self._vertical
        if v5 < up or v5 > down:
            v5 = up if v5 < up else down
            v5_1 = v5_2 = 0.0
        v5 -= d2
        e4 = _wrap(float(reference.yaw) - psi)
        v8 = designed_gamma(c3, c7, psi + e4, float(reference.yaw_rate),
                            float(reference.yaw_acceleration), psi, dpsi)

        # outer loop: desired acceleration, then the model inversion for phi_d, theta_d
        # the model is asked for the design minus its error d, so the design's derivatives lose d's rate
        accel, accel1, accel2, limited, integral = self.outer_loop.update_flat(
            dt, xi[0], xi[1], xi[3], xi[4], rp, rv, ra, rj, rs, v5, v5_1 - d_rate[2], v5_2, on_ground,
            d0, d1, d_rate[0], d_rate[1])
        outer = law.outer
        u_outer = u_meas
        if self._frozen and (u_meas[0] * u_meas[0] + u_meas[1] * u_meas[1] + u_meas[2] * u_meas[2]
                             + u_meas[3] * u_meas[3]) < 0.5 * law.hover_f[0]:
            u_outer = [law.hover_speed] * 4  # spinning up on the ground: freeze at hover, not at ~0
        # warm start: last solution moved along its own derivatives (one Newton step then usually suffices)
        q, qd, qdd = self._q, self._qd, self._qdd
        guess = [q[i] + (qd[i] + 0.5 * qdd[i] * dt) * dt for i in range(outer.n)]
        sol = outer.solve(accel, xi, u_outer, guess, max_iter=g.newton_iterations,
                          angle_limit=self._angle_limit)
        phid, thetad = sol.phi, sol.theta
        outer_ok = sol.ok and math.isfinite(phid) and math.isfinite(thetad)
        if outer_ok:
            q = [phid, thetad, sol.f1] if outer.n == 3 else [phid, thetad]
        else:
            q = list(self._q)
            phid, thetad = q[0], q[1]
        self._q = q
        tilt_limit = self._tilt_ground if on_ground else self._tilt
        cos_tilt = math.cos(phid) * math.cos(thetad)
        tilt = math.acos(cos_tilt if cos_tilt < 1.0 else 1.0)
        tilt_clamped = tilt > tilt_limit
        if tilt_clamped:
            # scale both angles so the tilt acos(cos phi cos theta) is the limit (converges in a few steps)
            k = 1.0
            for _ in range(6):
                k *= tilt_limit / tilt
                tilt = math.acos(min(1.0, math.cos(phid * k) * math.cos(thetad * k)))
                if tilt <= tilt_limit:
                    break
            phid, thetad = phid * k, thetad * k

        # phi_d', phi_d'', theta_d', theta_d''
        if self._analytic:
            rates = None
            if outer_ok and not tilt_clamped:
                # the velocity parameters move with the vehicle's acceleration: the request plus what the
                # model misses (d), not the model's request alone
                a0, a1, a2 = accel[0] + d0, accel[1] + d1, accel[2] + d2
                first = (xi[3], xi[4], vz, a0, a1, a2, dpsi, 0.0)  # see _param_rate_index
                second = (a0, a1, a2, accel1[0], accel1[1], accel1[2], v8, 0.0)
                index = self._param_rate_index
                rates = outer.rates(q, xi, u_outer, accel1, accel2, [first[i] for i in index],
                                    [second[i] for i in index])
            if rates is None:
                rates = [0.0] * outer.n, [0.0] * outer.n
            qd, qdd = self._qd, self._qdd = rates
            dphid, dthetad, ddphid, ddthetad = qd[0], qd[1], qdd[0], qdd[1]
        else:
            dphid, ddphid, dthetad, ddthetad = self._filter(phid, thetad, dt)

        v6 = designed_gamma(c1, c5, phid, dphid, ddphid, phi, dphi)
        v7 = designed_gamma(c2, c6, thetad, dthetad, ddthetad, theta, dtheta)
        if d3 or d4 or d5:
            # R(phi, theta) d_w: d_w in Euler angles (as the Euler rates above)
            ew = (sf * d4 + cf * d5) / ct
            v6, v7, v8 = v6 - (d3 + ew * st), v7 - (cf * d4 - sf * d5), v8 - ew
        gamma_d = [v5, v6, v7, v8]
        f, inner_ok = law.inner.solve(gamma_d, xi, u_meas, self._f, max_iter=g.newton_iterations)
        if not inner_ok or not all(map(math.isfinite, f)):
            f = list(self._f)
        self._f = list(f)
        _, speeds, stage = allocate_floats(f, self.w_max)
        if not on_ground:
            gate = self._observer_gate
            consistent = stage == "none" and abs(speeds[0] - u_meas[0]) <= gate \
                and abs(speeds[1] - u_meas[1]) <= gate and abs(speeds[2] - u_meas[2]) <= gate \
                and abs(speeds[3] - u_meas[3]) <= gate
            observer.start_step(xi, speeds, consistent)
        return Command(
            rotor_speeds=np.array(speeds),
            saturated=stage != "none",
            info={
                "phi_d": phid, "theta_d": thetad, "f1_d": q[2] if len(q) == 3 else math.nan,
                "dphi_d": dphid, "dtheta_d": dthetad,
                "ddphi_d": ddphid, "ddtheta_d": ddthetad, "f": f, "accel_d": accel,
                "gamma_d": gamma_d, "outer_ok": outer_ok, "inner_ok": inner_ok,
                "limited": limited or tilt_clamped, "on_ground": on_ground,
                "outer_iterations": sol.iterations, "integral": integral, "model_error": tuple(d),
                "observer_gains": tuple(observer.gains_used),
                "allocation": stage,
            },
        )

    def _filter(self, phid: float, thetad: float, dt: float) -> tuple[float, float, float, float]:
        """Critically damped 2nd-order command filter on phi_d, theta_d -> (phi', phi'', theta', theta'')."""
        w = self.gains.filter_bandwidth
        ww, w2 = w * w, 2.0 * w
        filt = self._filt
        if filt is None:
            filt = self._filt = [phid, 0.0, thetad, 0.0]
        # semi-implicit Euler in substeps small against 1/w
        n = max(1, int(math.ceil(dt * w / 0.1)))
        h = dt / n
        out = []
        for k, target in ((0, phid), (2, thetad)):
            x, v = filt[k], filt[k + 1]
            for _ in range(n):
                v += h * (ww * (target - x) - w2 * v)
                x += h * v
            filt[k], filt[k + 1] = x, v
            out += [v, ww * (target - x) - w2 * v]
        return out[0], out[1], out[2], out[3]
