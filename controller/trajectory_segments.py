"""Piecewise references users write: holds, steps, ramps and formula segments; waypoints joined by
minimum-jerk or minimum-snap legs. Built from YAML by controller.trajectories (which checks the files);
evaluated here.

Every segment's `values(tau)` gives the 18 numbers of controller.trajectories (position, velocity,
acceleration, jerk, snap NED [m, m/s, ...]; yaw [rad], its rate and acceleration) at tau [s] since the
segment's start.
"""

from __future__ import annotations

import bisect
from dataclasses import dataclass
from typing import Protocol

import numpy as np

from controller.plugin import Reference, reference_from_values
from controller.reference_shaping import PROFILES


class SegmentValues(Protocol):
    """Anything with values(tau) -> the 18 reference numbers at tau [s] since the segment's start."""

    def values(self, t: float) -> list[float]:
        """The 18 numbers at tau [s]."""


@dataclass(frozen=True)
class HoldSegment:
    """Stay at `position` [m, NED] with heading `yaw` [rad]: a hold, or a step when it differs from the
    previous segment's end (the reference jumps; the controller's saturation decides how it is flown)."""

    position: tuple[float, float, float]
    yaw: float

    def values(self, t: float) -> list[float]:
        """The 18 numbers at tau [s]: at rest at the point."""
        return [*self.position] + [0.0] * 12 + [self.yaw, 0.0, 0.0]


@dataclass(frozen=True)
class _Leg:
    """From `start` to `end` [m, NED] and `start_yaw` to `end_yaw` [rad] over `duration` [s]."""

    start: tuple[float, float, float]
    end: tuple[float, float, float]
    start_yaw: float
    end_yaw: float
    duration: float


@dataclass(frozen=True)
class RampSegment(_Leg):
    """A straight line at constant speed from `start` to `end` [m, NED] over `duration` [s], yaw [rad]
    likewise; its velocity jumps at both ends (a ramp, not a smooth move)."""

    def values(self, t: float) -> list[float]:
        """The 18 numbers at tau [s]."""
        r = min(max(t / self.duration, 0.0), 1.0)
        v = [(b - a) / self.duration for a, b in zip(self.start, self.end, strict=True)]
        p = [a + r * (b - a) for a, b in zip(self.start, self.end, strict=True)]
        yaw_rate = (self.end_yaw - self.start_yaw) / self.duration
        return p + v + [0.0] * 9 + [self.start_yaw + r * (self.end_yaw - self.start_yaw), yaw_rate, 0.0]


@dataclass(frozen=True)
class MoveSegment(_Leg):
    """A rest-to-rest move from `start` to `end` [m, NED] over `duration` [s]: `profile` min-jerk (quintic,
    continuous through acceleration when joined) or min-snap (septic, continuous through jerk)."""

    profile: str = "min-snap"

    def values(self, t: float) -> list[float]:
        """The 18 numbers at tau [s]: at rest at both ends."""
        s = PROFILES[self.profile][0](t, self.duration)
        d = [b - a for a, b in zip(self.start, self.end, strict=True)]
        out = [a + s[0] * di for a, di in zip(self.start, d, strict=True)]
        for k in range(1, 5):
            out += [s[k] * di for di in d]
        dyaw = self.end_yaw - self.start_yaw
        return out + [self.start_yaw + s[0] * dyaw, s[1] * dyaw, s[2] * dyaw]


class PiecewiseTrajectory:
    """Segments one after another: segment k runs from starts[k] for durations[k] s; before 0 the first
    segment's start holds, after the last the last segment's end holds (at rest)."""

    def __init__(self, name: str, segments: list[SegmentValues], durations: list[float],
                 duration: float | None = None, description: str = "", kinds: list[str] | None = None):
        if not segments or len(segments) != len(durations):
            raise ValueError("give one duration per segment, at least one segment")
        self.name = name
        self.description = description
        self.segments = list(segments)
        self.durations = [float(d) for d in durations]
        self.kinds = list(kinds) if kinds is not None else ["segment"] * len(segments)
        self.starts = list(np.concatenate([[0.0], np.cumsum(self.durations)[:-1]]))
        self.end_time = float(sum(self.durations))
        self.duration = float(duration) if duration is not None else self.end_time
        last = self.segments[-1].values(self.durations[-1])
        self._end = last[0:3] + [0.0] * 12 + [last[15], 0.0, 0.0]

    def values(self, t: float) -> list[float]:
        """The 18 numbers at t [s]."""
        t = float(t)
        if t >= self.end_time:
            return list(self._end)
        if t < 0.0:
            first = self.segments[0].values(0.0)
            return first[0:3] + [0.0] * 12 + [first[15], 0.0, 0.0]
        k = bisect.bisect_right(self.starts, t) - 1
        return list(self.segments[k].values(t - self.starts[k]))

    def reference(self, t: float) -> Reference:
        """The reference at time t [s]."""
        return reference_from_values(self.values(t))
