"""What the companion flies instead of the raw reference: a take-off phase and a time-scaling governor.

Both wrap a trajectory (anything with `reference(t)`) and are controller-agnostic: every controller flown by
the companion (backstepping, pid, se3) gets them.

Take-off phase (`TakeoffTrajectory`): when the vehicle starts more than `min_gap` below the reference's first
point (a hover, a circle or a mission that begins in the air), it first flies a minimum-snap (septic,
rest-to-rest: velocity, acceleration and jerk zero at both ends) straight line from where it stands to that
point, with its duration chosen so that the line's peak speed 2.19 D/T and peak acceleration 7.51 D/T^2
stay within `speed` [m/s] and `acceleration` [m/s^2]; the user's trajectory then starts `duration` seconds
later. The reference never asks for more than
the controller can give, so nothing saturates and nothing overshoots. References that start on the ground
(the paper's Cases I and II) are passed through unchanged.

Governor (`TimeScalingGovernor`): the reference is followed in its own time tau, advanced at a rate
s = dtau/dt in (0, 1]. s is the largest value for which the scaled reference stays within the vehicle's
limits over a look-ahead window, s^2 |a_h(tau)| <= max_horizontal_accel, s |v(tau)| <= max_speed,
s^2 |a_z(tau)| <= max_vertical_accel, and changes by at most `rate` [1/s] per second. What the controllers
receive is the time-scaled reference: p(tau), v = s v(tau), a = s^2 a(tau) + s' v(tau), jerk s^3 j(tau) +
3 s s' a(tau) + s'' v(tau), snap s^4 snap(tau) (yaw likewise). A spin-up from rest follows a minimum-snap
S-curve from s = 0 to 1 (peak s' = rate), so the reference stays smooth. A feasible reference has s = 1
throughout: it is flown as written. An infeasible one is flown slower, on the same path, instead of being
chased into a flip.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from controller.plugin import Reference, Trajectory

MIN_JERK_PEAK_SPEED = 1.875  # peak speed of the rest-to-rest quintic over distance D and time T, in D/T
MIN_JERK_PEAK_ACCEL = 10.0 / math.sqrt(3.0)  # peak acceleration, in D/T^2 (5.774)
MIN_SNAP_PEAK_SPEED = 35.0 / 16.0  # the rest-to-rest septic's (2.1875 D/T)
MIN_SNAP_PEAK_ACCEL = 7.513188  # its peak acceleration in D/T^2 (numerically, at r = 0.2764)


@dataclass(frozen=True)
class TakeoffSettings:
    """Take-off phase limits: speed [m/s], acceleration [m/s^2], shortest phase [s], height gap [m]."""

    speed: float = 1.0
    acceleration: float = 1.5
    min_duration: float = 2.0
    min_gap: float = 0.2  # m: a first reference point less than this above the start needs no take-off


@dataclass(frozen=True)
class GovernorSettings:
    """The vehicle's limits the governor keeps a reference within (SI) and how fast it may re-scale time."""

    max_horizontal_accel: float = 6.0  # m/s^2 (35 deg of tilt gives 6.9; some is kept for feedback)
    max_vertical_accel: float = 4.0  # m/s^2, up or down
    max_speed: float = 15.0  # m/s
    rate: float = 0.5  # 1/s, largest |s'|
    lookahead: float = 1.5  # s of reference time checked ahead of tau
    samples: int = 7  # points in the look-ahead window
    spin_up_speed: float = 2.0  # m/s: a reference starting faster than this is spun up from s = 0


def min_jerk(t: float, duration: float) -> tuple[float, float, float, float, float]:
    """The rest-to-rest quintic 10 r^3 - 15 r^4 + 6 r^5 (r = t/T) and its 4 time derivatives, from 0 to 1."""
    if t <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0
    if t >= duration:
        return 1.0, 0.0, 0.0, 0.0, 0.0
    r = t / duration
    k = 1.0 / duration
    return (r**3 * (10.0 - 15.0 * r + 6.0 * r * r),
            k * 30.0 * r * r * (1.0 - r) ** 2,
            k * k * 60.0 * r * (1.0 - r) * (1.0 - 2.0 * r),
            k**3 * 60.0 * (1.0 - 6.0 * r + 6.0 * r * r),
            k**4 * 360.0 * (2.0 * r - 1.0))


def min_snap(t: float, duration: float) -> tuple[float, float, float, float, float]:
    """The rest-to-rest septic 35 r^4 - 84 r^5 + 70 r^6 - 20 r^7 (r = t/T) and its 4 time derivatives: 0 to 1
    with velocity, acceleration and jerk zero at both ends (continuous through jerk when joined)."""
    if t <= 0.0:
        return 0.0, 0.0, 0.0, 0.0, 0.0
    if t >= duration:
        return 1.0, 0.0, 0.0, 0.0, 0.0
    r = t / duration
    k = 1.0 / duration
    r2, r3 = r * r, r * r * r
    return (r2 * r2 * (35.0 - 84.0 * r + 70.0 * r2 - 20.0 * r3),
            k * 140.0 * r3 * (1.0 - r) ** 3,
            k * k * 420.0 * r2 * (1.0 - r) ** 2 * (1.0 - 2.0 * r),
            k**3 * 840.0 * r * (1.0 - r) * (1.0 - 5.0 * r + 5.0 * r2),
            k**4 * 840.0 * (1.0 - 12.0 * r + 30.0 * r2 - 20.0 * r3))


PROFILES = {"min-jerk": (min_jerk, MIN_JERK_PEAK_SPEED, MIN_JERK_PEAK_ACCEL),
            "min-snap": (min_snap, MIN_SNAP_PEAK_SPEED, MIN_SNAP_PEAK_ACCEL)}


def min_jerk_duration(distance: float, speed: float, acceleration: float, shortest: float = 0.0,
                      profile: str = "min-jerk") -> float:
    """Shortest time [s] for a rest-to-rest profile (min-jerk quintic or min-snap septic) over distance [m]
    within speed [m/s] and acceleration [m/s^2]."""
    _, peak_v, peak_a = PROFILES[profile]
    return max(shortest, peak_v * distance / speed, math.sqrt(peak_a * distance / acceleration))


class TakeoffTrajectory:
    """A trajectory preceded by a minimum-snap take-off from `start` [m, NED] to its first point."""

    def __init__(self, trajectory: Trajectory, start: np.ndarray | list[float], start_yaw: float = 0.0,
                 settings: TakeoffSettings | None = None):
        self.inner = trajectory
        self.settings = s = settings or TakeoffSettings()
        self.name = getattr(trajectory, "name", "")
        first = trajectory.reference(0.0)
        self.start = np.asarray(start, dtype=float).copy()
        self.target = np.asarray(first.position, dtype=float).copy()
        self.start_yaw = float(start_yaw)
        self.target_yaw = float(first.yaw)
        gap = self.start[2] - self.target[2]  # m, how far the first point is above the start (NED z down)
        self.active = gap > s.min_gap
        distance = float(np.linalg.norm(self.target - self.start))
        self.duration = min_jerk_duration(distance, s.speed, s.acceleration, s.min_duration, "min-snap") \
            if self.active else 0.0

    def reference(self, t: float) -> Reference:
        """The take-off line before `duration` [s], then the trajectory shifted by it."""
        if t >= self.duration:
            return self.inner.reference(t - self.duration)
        p, v, a, j, sn = min_snap(t, self.duration)
        d = self.target - self.start
        dyaw = self.target_yaw - self.start_yaw
        return Reference(position=self.start + p * d, velocity=v * d, acceleration=a * d, jerk=j * d,
                         snap=sn * d, yaw=self.start_yaw + p * dyaw, yaw_rate=v * dyaw,
                         yaw_acceleration=a * dyaw)


class HeightFloor:
    """A trajectory kept at least `min_height` [m] above z = 0 (NED, z down, the ground at the start): where
    it is lower, its height is min_height and its vertical velocity, acceleration, jerk and snap are 0 (the
    horizontal path and yaw unchanged). For an autopilot that flies attitude targets only in the air
    (ArduCopter GUIDED), since the paper's Cases I and II start on the ground."""

    def __init__(self, trajectory: Trajectory, min_height: float):
        self.inner = trajectory
        self.min_height = float(min_height)
        self.name = getattr(trajectory, "name", "")

    def reference(self, t: float) -> Reference:
        """The trajectory's reference at t [s], raised to min_height where it is lower."""
        ref = self.inner.reference(t)
        if float(ref.position[2]) <= -self.min_height:
            return ref
        flat = np.array([1.0, 1.0, 0.0])  # the vertical components held at 0
        return Reference(position=np.array([ref.position[0], ref.position[1], -self.min_height]),
                         velocity=flat * ref.velocity, acceleration=flat * ref.acceleration,
                         jerk=flat * ref.jerk, snap=flat * ref.snap, yaw=ref.yaw, yaw_rate=ref.yaw_rate,
                         yaw_acceleration=ref.yaw_acceleration)

    def raised_until(self, duration: float, step: float = 0.01) -> float:
        """The last time [s] in [0, duration] at which the reference is raised (0: never), on a step grid."""
        last = 0.0
        for k in range(int(duration / step) + 1):
            if float(self.inner.reference(k * step).position[2]) > -self.min_height:
                last = k * step
        return last


class TimeScalingGovernor:
    """Follows a trajectory in its own time tau at rate s in (0, 1] that keeps it within the limits (see
    the module doc). Stateful: call `reference(t)` with increasing t [s]; `reset()` before a new flight."""

    def __init__(self, trajectory: Trajectory, settings: GovernorSettings | None = None,
                 start_scale: float = 1.0):
        self.inner = trajectory
        self.settings = settings or GovernorSettings()
        self.name = getattr(trajectory, "name", "")
        self.start_scale = float(start_scale)  # s at t = 0 (0: spun up from rest at `rate`)
        self.reset()

    def reset(self) -> None:
        """Back to tau = 0 and the starting s."""
        self.tau = 0.0
        self.scale = self.start_scale
        self.scale_rate = 0.0
        self.scale_accel = 0.0
        self._limited = 1.0  # the rate-limited s the limits allow
        # a spin-up from s = 0 follows a minimum-snap S-curve to 1 with peak s' = rate (smooth reference)
        self._spin_up = MIN_SNAP_PEAK_SPEED / self.settings.rate if self.start_scale < 1.0 else 0.0
        self.min_feasible = 1.0  # the smallest s the limits allowed so far (1: the reference was feasible)
        self._t: float | None = None

    def feasible_scale(self, tau: float) -> float:
        """The largest s in (0, 1] keeping the reference within the limits over [tau, tau + lookahead]."""
        g = self.settings
        s = 1.0
        for k in range(g.samples):
            ref = self.inner.reference(tau + g.lookahead * k / max(g.samples - 1, 1))
            v, a = ref.velocity, ref.acceleration
            speed = math.sqrt(v[0] * v[0] + v[1] * v[1] + v[2] * v[2])
            ah = math.hypot(a[0], a[1])
            if speed > g.max_speed:
                s = min(s, g.max_speed / speed)
            if ah > g.max_horizontal_accel:
                s = min(s, math.sqrt(g.max_horizontal_accel / ah))
            if abs(a[2]) > g.max_vertical_accel:
                s = min(s, math.sqrt(g.max_vertical_accel / abs(a[2])))
        return s

    def reference(self, t: float) -> Reference:
        """The time-scaled reference at wall (flight) time t [s]."""
        g = self.settings
        if self._t is None or t > self._t:
            dt = 0.0 if self._t is None else t - self._t
            target = self.feasible_scale(self.tau)
            self.min_feasible = min(self.min_feasible, target)
            lim = self._limited
            if self._t is None:
                lim, rate = target, 0.0
            else:  # towards the target at |s'| <= rate, but never above it (the limits come first)
                step = max(-g.rate * dt, min(g.rate * dt, target - lim))
                step = target - lim if target < lim + step else step
                rate = step / dt
                lim += step
            self._limited = lim
            up = min_snap(t, self._spin_up) if self._spin_up > 0.0 else (1.0, 0.0, 0.0, 0.0, 0.0)
            previous = self.scale
            if up[0] < lim:
                self.scale, self.scale_rate, self.scale_accel = up[0], up[1], up[2]
            else:
                self.scale, self.scale_rate, self.scale_accel = lim, rate, 0.0
            self.tau += 0.5 * (previous + self.scale) * dt
        self._t = t
        ref = self.inner.reference(self.tau)
        s, sd, sdd = self.scale, self.scale_rate, self.scale_accel
        v, a = np.asarray(ref.velocity, float), np.asarray(ref.acceleration, float)
        return Reference(position=ref.position, velocity=s * v, acceleration=s * s * a + sd * v,
                         jerk=s**3 * np.asarray(ref.jerk, float) + 3.0 * s * sd * a + sdd * v,
                         snap=s**4 * np.asarray(ref.snap, float), yaw=ref.yaw, yaw_rate=s * ref.yaw_rate,
                         yaw_acceleration=s * s * ref.yaw_acceleration + sd * ref.yaw_rate)


def shaped_reference(trajectory: Trajectory, start: np.ndarray | list[float], start_yaw: float = 0.0,
                     takeoff: TakeoffSettings | None = None,
                     governor: GovernorSettings | None = None) -> Any:
    """The trajectory as the companion flies it: governed (if settings are given), behind a take-off phase
    (if settings are given and the first point is in the air). After a take-off the vehicle is at rest on
    the first point, so the governor spins the reference up from s = 0 (a circle starting at 4.8 m/s is
    not a velocity step); so it does for a reference starting faster than spin_up_speed."""
    first = trajectory.reference(0.0)
    climb = takeoff is not None and float(start[2]) - float(first.position[2]) > takeoff.min_gap
    inner: Any = trajectory
    if governor is not None:
        fast_start = float(np.linalg.norm(first.velocity)) > governor.spin_up_speed
        inner = TimeScalingGovernor(trajectory, governor, start_scale=0.0 if climb or fast_start else 1.0)
    return TakeoffTrajectory(inner, start, start_yaw, takeoff) if climb else inner


def describe_shaping(flown: Any) -> list[str]:
    """Lines saying what the take-off phase and the governor did in a flight (nothing if they did nothing)."""
    lines = []
    governor = flown
    if isinstance(flown, TakeoffTrajectory):
        start = ", ".join(f"{v:.2f}" for v in flown.start)
        target = ", ".join(f"{v:.2f}" for v in flown.target)
        lines.append(f"take-off phase: {flown.duration:.2f} s from ({start}) to the first point ({target}) "
                     "m NED")
        governor = flown.inner
    if isinstance(governor, TimeScalingGovernor) and governor.min_feasible < 0.999:
        lines.append(f"governor: the reference was beyond the limits and was flown at down to "
                     f"{governor.min_feasible:.2f} of its speed (reference time {governor.tau:.2f} s at the "
                     "end)")
    return lines
