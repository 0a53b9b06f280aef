"""The wind the SITL flies in, earth NED (m/s): steady vector + Dryden turbulence + 1-cosine gusts, seeded.

Sampled once per 4 ms exchange step and held over it. The turbulence's u axis is the steady wind's horizontal
direction (north when it has none), v to its right, w down. A gust adds A/2 (1 - cos(2 pi (t - t0)/T)) for
t0 <= t <= t0 + T (the 1-cosine shape of discrete-gust certification cases), 0 outside.
"""

from __future__ import annotations

import math

from bridge.airframe import GustConfig, WindConfig

Vec3 = tuple[float, float, float]


def gust_velocity(gust: GustConfig, t: float) -> Vec3:
    """One 1-cosine gust's wind at time t (s), NED m/s."""
    x = t - gust.start
    if x < 0.0 or x > gust.duration:
        return 0.0, 0.0, 0.0
    f = 0.5 * (1.0 - math.cos(2.0 * math.pi * x / gust.duration))
    an, ae, ad = gust.amplitude
    return f * an, f * ae, f * ad


class Wind:
    """The wind field along the flight: sample(t) each exchange step, in order, gives the NED wind (m/s)."""

    def __init__(self, config: WindConfig, dt: float):
        self.config = config
        self.turbulence = None
        self.variance = (0.0, 0.0)  # (horizontal, vertical) turbulence variance, (m/s)^2
        if config.turbulence != "none":
            from sitl.dryden import DrydenTurbulence  # scipy only when turbulence is on

            self.turbulence = DrydenTurbulence(config.turbulence, config.reference_altitude,
                                               config.mean_speed, dt, config.seed)
            su, sv, sw = self.turbulence.sigma
            self.variance = (su * su + sv * sv, sw * sw)
        n, e, _ = config.steady
        heading = math.atan2(e, n)
        self._cos, self._sin = math.cos(heading), math.sin(heading)
        self._first = True

    def sample(self, t: float) -> Vec3:
        """The wind at simulated time t (s), NED m/s; call once per step, in time order."""
        wn, we, wd = self.config.steady
        if self.turbulence is not None:
            u, v, w = self.turbulence.current() if self._first else self.turbulence.step()
            wn += self._cos * u - self._sin * v
            we += self._sin * u + self._cos * v
            wd += w
        self._first = False
        for gust in self.config.gusts:
            gn, ge, gd = gust_velocity(gust, t)
            wn += gn
            we += ge
            wd += gd
        return wn, we, wd
