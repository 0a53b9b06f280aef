"""The outer loop: the paper's PI law with feedforward for the desired horizontal acceleration (NED, m/s^2).

    a_x = x_d'' + k_px e_x' + k_ix e_x - d_x (+ k_int * integral of e_x)        e_x = x_d - x, likewise y

With a_x reached exactly (the model inversion in controller.derivation does that when the inner loop tracks
phi_d, theta_d), the error obeys e'' + k_p e' + k_i e = 0 (the paper's Section III-A). The paper's "integral"
term k_i e_x = k_i * integral(e_x') is the position error itself.

d_x is the model-error observer's estimate of what the model gets wrong in x'' (ModelErrorObserver, run by
the backstepping controller): asking the model for a_x - d_x makes the vehicle do a_x, so the error dynamics
above hold for the vehicle, not only for the model. It is the integral action: a constant model error is
removed exactly, without the integral of e_x (k_int) that winds up in every transient.

What the paper leaves out and a real vehicle needs:
  - the position error fed to k_i is clipped to `max_position_error` (horizontal length): the integral term's
    anti-windup, so that Case I's reference starting 3.7 m away asks for a bounded acceleration and the
    vehicle closes the gap at about k_i * e_max / k_p instead of overshooting a saturated PD;
  - the optional extra integral (k_int) integrates only within `integral_zone`, never on the ground, never
    while the command is limited (conditional integration), and its contribution is clamped;
  - the horizontal acceleration is limited so that the tilt stays below max_tilt (tan(tilt) * (g - a_z)),
    and below ground_tilt while the vehicle is still on the ground; at the limit the feedforward (the
    reference's acceleration and the model error, e.g. a wind's drag) keeps priority and only the feedback
    is shortened, along its own direction (saturate_feedback), so a large error closes at the best feasible
    rate instead of settling on a lagging orbit. The feedback alone is also held within max_feedback_tilt
    (35 deg, below max_tilt's 45): a far error is closed as the PI gains were chosen for, and the rest of
    the tilt is kept for what the reference and the wind need. There is no integrator
    to wind up (the error clip bounds the k_i term; the model-error observer does not integrate e).

Derivatives a' and a'' for the attitude feedforward come from the reference's jerk and snap plus the ideal
closed-loop error dynamics (e'' = -(k_p e' + k_i e + k_int I)), so they need no numerical differentiation.
When a limit is active they fall back to the reference's jerk and snap alone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from controller.gains import BacksteppingGains


@dataclass
class OuterCommand:
    """NED acceleration [m/s^2] asked of the model (x, y: the PI law; z passed in) and its two derivatives."""

    accel: list[float]
    accel_rate: list[float]
    accel_rate2: list[float]
    limited: bool  # the tilt/acceleration limit or the error clip was active
    integral: tuple[float, float]  # the k_int integrator state [m s]


def saturate_feedback(ffx: float, ffy: float, fbx: float, fby: float, a_max: float,
                      fb_max: float = math.inf) -> tuple[float, float]:
    """ff + k fb [m/s^2] with |k fb| <= min(a_max - |ff|, fb_max) (k in [0, 1]); ff scaled to a_max alone if
    beyond it.

    The feedforward (what the reference needs) keeps priority; the feedback keeps its direction and gets the
    margin a_max - |ff| that is free in every direction, so the error obeys e'' = -sat(k_p e' + k_i e), a
    radially symmetric saturated linear feedback of a double integrator, which converges from any error.
    Scaling the sum instead (or giving the feedback all that is left along its direction) makes the bound
    depend on the direction: on the aggressive circle that left the vehicle on a lagging orbit, 4 m behind.
    """
    ff2 = ffx * ffx + ffy * ffy
    if not ff2 < a_max * a_max:  # the reference alone is beyond the limit (or NaN): keep its direction
        n = math.sqrt(ff2)
        return (ffx * a_max / n, ffy * a_max / n) if n > 0.0 else (0.0, 0.0)
    fb = math.sqrt(fbx * fbx + fby * fby)
    margin = a_max - math.sqrt(ff2)
    if fb_max < margin:
        margin = fb_max
    k = 1.0 if fb <= margin else margin / fb
    return ffx + k * fbx, ffy + k * fby


class OuterLoop:
    """PI with feedforward for x and y: error clip, conditional-integration anti-windup, tilt limit."""

    def __init__(self, gains: BacksteppingGains, gravity: float):
        self.gains = gains
        self.gravity = gravity  # m/s^2, from the model (its z'' at rest with motors off)
        self._kp = (gains.k_px, gains.k_py)
        self._ki = (gains.k_ix, gains.k_iy)
        self._tan_tilt = math.tan(math.radians(gains.max_tilt_deg))
        self._tan_feedback = math.tan(math.radians(min(gains.max_feedback_tilt_deg, gains.max_tilt_deg)))
        self._tan_ground = math.tan(math.radians(gains.ground_tilt_deg))
        self._vertical = self.vertical_limits()
        self.reset()

    def reset(self) -> None:
        """Zero the integrator and forget the last limit state."""
        self._integral = [0.0, 0.0]
        self._was_limited = False

    def vertical_limits(self) -> tuple[float, float]:
        """(most upward, most downward) vertical acceleration [m/s^2, NED] the outer solve may ask for."""
        g = self.gains
        return -g.max_climb_accel, g.max_sink_fraction * self.gravity

    def update(self, dt: float, position: list[float], velocity: list[float], ref_pos: list[float],
               ref_vel: list[float], ref_acc: list[float], ref_jerk: list[float], ref_snap: list[float],
               az: tuple[float, float, float], on_ground: bool,
               model_error: tuple[float, float] = (0.0, 0.0),
               model_error_rate: tuple[float, float] = (0.0, 0.0)) -> OuterCommand:
        """The desired acceleration for the position/velocity NED [m, m/s] and the reference at this step.

        az = (a_z, a_z', a_z''): the vertical acceleration the inner loop's z design asks for, and its
        derivatives [m/s^2, m/s^3, m/s^4]; clipped here to the vertical limits for the attitude solve.
        model_error = (d_x, d_y) [m/s^2]: the vehicle's x'', y'' minus the model's, taken off the request;
        model_error_rate: its time derivative [m/s^3], taken off the request's (for the attitude feedforward).
        """
        return OuterCommand(*self.update_flat(
            dt, position[0], position[1], velocity[0], velocity[1], ref_pos, ref_vel, ref_acc, ref_jerk,
            ref_snap, az[0], az[1], az[2], on_ground, model_error[0], model_error[1], model_error_rate[0],
            model_error_rate[1]))

    def update_flat(self, dt: float, x: float, y: float, vx: float, vy: float, ref_pos: list[float],
                    ref_vel: list[float], ref_acc: list[float], ref_jerk: list[float], ref_snap: list[float],
                    az: float, az1: float, az2: float, on_ground: bool, dx: float, dy: float, dx1: float,
                    dy1: float) -> tuple[list[float], list[float], list[float], bool, tuple[float, float]]:
        """update() on plain floats (the controller's hot path): the OuterCommand's fields as a tuple.

        x, y [m], vx, vy [m/s]: position and velocity NED; az, az1, az2: a_z and its two derivatives;
        dx, dy [m/s^2]: the model error and dx1, dy1 [m/s^3] its rate.
        """
        g = self.gains
        ex, ey = ref_pos[0] - x, ref_pos[1] - y
        evx, evy = ref_vel[0] - vx, ref_vel[1] - vy
        dist = math.hypot(ex, ey)
        e_max = g.max_position_error
        clipped = dist > e_max
        k = e_max / dist if clipped else 1.0
        ecx, ecy = ex * k, ey * k

        # conditional integration (anti-windup): near the reference, airborne, last command not limited
        k_int = g.k_int
        if k_int > 0.0 and not on_ground and dist < g.integral_zone and not self._was_limited and dt > 0:
            cap = g.max_integral_accel / k_int
            integ = self._integral
            integ[0] = min(max(integ[0] + ex * dt, -cap), cap)
            integ[1] = min(max(integ[1] + ey * dt, -cap), cap)
        if on_ground:
            self._integral = [0.0, 0.0]
        ix, iy = self._integral

        kpx, kpy = self._kp
        kix, kiy = self._ki
        ffx, ffy = ref_acc[0] - dx, ref_acc[1] - dy  # feedforward: the reference's and the model's error
        fbx = kpx * evx + kix * ecx + k_int * ix  # feedback
        fby = kpy * evy + kiy * ecy + k_int * iy
        ax, ay = ffx + fbx, ffy + fby
        up, down = self._vertical
        a_z = up if up > az else az  # min(max(az, up), down), NaN passing as it would there
        if down < a_z:
            a_z = down
        room = self.gravity - a_z
        a_max = (self._tan_ground if on_ground else self._tan_tilt) * room
        fb_max = (self._tan_ground if on_ground else self._tan_feedback) * room
        tilt_limited = math.hypot(ax, ay) > a_max or math.hypot(fbx, fby) > fb_max
        if tilt_limited:
            ax, ay = saturate_feedback(ffx, ffy, fbx, fby, a_max, fb_max)
        limited = clipped or tilt_limited or a_z != az
        self._was_limited = limited or clipped

        if clipped or tilt_limited or on_ground:
            rx, ry = ref_jerk[0], ref_jerk[1]
            r2x, r2y = ref_snap[0], ref_snap[1]
        else:
            e2x = -(kpx * evx + kix * ex + k_int * ix)
            e2y = -(kpy * evy + kiy * ey + k_int * iy)
            e3x = -(kpx * e2x + kix * evx + k_int * ex)
            e3y = -(kpy * e2y + kiy * evy + k_int * ey)
            rx = ref_jerk[0] + kpx * e2x + kix * evx + k_int * ex - dx1
            ry = ref_jerk[1] + kpy * e2y + kiy * evy + k_int * ey - dy1
            r2x = ref_snap[0] + kpx * e3x + kix * e2x + k_int * evx
            r2y = ref_snap[1] + kpy * e3y + kiy * e2y + k_int * evy
        if a_z != az:
            az1, az2 = 0.0, 0.0
        return [ax, ay, a_z], [rx, ry, az1], [r2x, r2y, az2], limited, (ix, iy)
