"""Excitation profiles: their settings (identification/profiles/<name>.yaml, validated) and their signals.

A profile makes a signal generator for one flight: `generator.command(obs) -> rotor speeds (4,) rad/s`
(PX4 order), called once per SITL step with that step's Observation; the flight client turns the speeds
into throttles through the vehicle's motor curve.

Kinds:
- random-steps (paper-train): each motor holds random speeds drawn uniformly in the current group's range,
  each for a random time; groups follow one another. Open loop from altitude, no ground. For symbolic
  regression to separate all six targets the data must spread over the attitudes (every roll, pitch and
  yaw, so sin/cos terms are not collinear: the tumbling does that), the body rates (the gyroscopic
  products wy*wz, wx*wz, wx*wy), the velocities (drag: the fall reaches about 20 m/s) and the four rotor
  speeds independently (f1..f4 not collinear). A rate guard keeps body rates under the gyro's +-2000 deg/s
  clamp: while a rate exceeds it, new draws come from the half of the range that brakes that axis (still
  random, no feedback gain); set rate_guard: null for the paper's pure open loop.
- sinusoids (paper-validate): u_i = offset_i + amplitude_i sin(frequency t + phase_i).
- closed-loop: the hover stabiliser (identification.hover_stabilizer) takes off, climbs, settles, then
  follows a Lissajous path with a turning heading while PRBS or chirp excitation is added to every
  motor; the excitation fades near the box walls and the tilt limit, so the vehicle stays where a real
  one would survive. Optional, for a model with height and rate laws (issue 12): a `schedule` of segments
  flown in turn, each a hover height (low ones near the ground as well as cruise ones: a law in 1/h needs
  rows spread over the heights where it acts) reached by a smooth climb or descent, and a yaw rate (both
  signs, several magnitudes: wz apart from the height and from wz^2); the height and yaw-rate lists cycle
  independently. And a `collective` excitation, one PRBS (or chirp) level added to all four motors, so
  the rotor sum varies (the rate dampings w apart from the rotor drag's w*(u1+..+u4)); it fades over
  backoff.distance near the box's floor and ceiling, the per-motor excitation over backoff.height.
  Flown through an autopilot's offboard link (identification.offboard_excite) the same reference, signal
  and fading drive body-rate setpoints instead: the stabiliser's outer loops give rates and thrust, the
  signal's channels 1-3 add body_rate_amplitude (rad/s) to the roll, pitch, yaw rates and channel 4 adds
  thrust_amplitude (a fraction) to the collective thrust; the autopilot's rate loop turns them into motor
  commands.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from bridge.errors import UserError
from bridge.vehicle import VehicleConfig
from bridge.yaml_file import Section, describe_value, load_yaml_file, numbers_value, range_value
from identification.hover_stabilizer import HoverStabilizer, Reference, StabilizerGains

PROFILE_KINDS = ("random-steps", "sinusoids", "closed-loop")
STEP_S = 0.004
# Sign of each motor's contribution to roll, pitch, yaw torque (PX4 Quad-X; docs/design.md f2, f3, f4).
TORQUE_SIGNS = np.array([[-1, 1, 1], [1, -1, 1], [1, 1, -1], [-1, -1, -1]], dtype=float)


def profiles_dir() -> Path:
    """The folder of the bundled profiles."""
    return Path(__file__).resolve().parent / "profiles"


def list_profiles() -> list[str]:
    """Names of the bundled profiles."""
    return sorted(p.stem for p in profiles_dir().glob("*.yaml"))


# --------------------------------------------------------------------------------------------------------
# Settings


@dataclass(frozen=True)
class RandomStepsProfile:
    """Random held motor speeds in successive ranges (rad/s), open loop from altitude."""

    name: str
    description: str
    groups: tuple[tuple[float, float], ...]  # rad/s (low, high) per group
    group_duration: float  # s
    hold: tuple[float, float]  # s, min and max hold time of one random speed
    rate_guard: float | None  # rad/s
    start: str = "altitude"
    kind: str = "random-steps"

    @property
    def duration(self) -> float:
        """Default flight duration, s."""
        return self.group_duration * len(self.groups)


@dataclass(frozen=True)
class SinusoidsProfile:
    """u_i = offset_i + amplitude_i sin(frequency t + phase_i) (rad/s, rad/s, rad/s, rad), open loop."""

    name: str
    description: str
    duration: float
    offset: tuple[float, float, float, float]
    amplitude: tuple[float, float, float, float]
    frequency: float
    phase: tuple[float, float, float, float]
    start: str = "altitude"
    kind: str = "sinusoids"


@dataclass(frozen=True)
class ClosedLoopSchedule:
    """Segments flown in turn once the excitation begins: the hover point's height and the heading's turn
    rate of segment k are altitudes[k % len] and yaw_rates[k % len] (the lists cycle independently)."""

    segment: float  # s per segment, the move to its height included
    altitudes: tuple[float, ...]  # m above the start point
    yaw_rates: tuple[float, ...]  # rad/s, FRD about the body's down axis (positive: heading turns clockwise)
    move_speed: float  # m/s, the largest vertical speed of the smooth (half-cosine) move between two heights
    yaw_acceleration: float = 1.0  # rad/s^2: the yaw rate ramps from one segment's to the next's
    swing_fraction: float = 0.5  # the vertical swing: at most this share of the height above the box floor

    def move_time(self, dh: float) -> float:
        """Time (s) of the half-cosine move over dh (m) whose largest speed is move_speed."""
        return math.pi * abs(dh) / (2.0 * self.move_speed)

    def yaw_ramp_time(self, dr: float) -> float:
        """Time (s) of the yaw rate's ramp over dr (rad/s) at yaw_acceleration."""
        return abs(dr) / self.yaw_acceleration


@dataclass(frozen=True)
class ClosedLoopProfile:
    """Stabilised flight with excitation on every motor inside a box and under a tilt limit."""

    name: str
    description: str
    duration: float  # s, whole flight
    takeoff_altitude: float  # m above the start point
    climb_rate: float  # m/s
    settle: float  # s
    box_half_width: float  # m, north and east of the start point
    box_altitude: tuple[float, float]  # m above the start point
    tilt_limit: float  # deg
    signal: str  # prbs | chirp
    amplitude: float  # rad/s
    prbs_hold: tuple[float, float]  # s
    chirp: tuple[float, float]  # Hz
    backoff_distance: float  # m
    backoff_tilt: float  # deg
    reference_amplitude: tuple[float, float, float]  # m N E D
    reference_period: tuple[float, float, float]  # s
    yaw_rate: float  # rad/s
    gains: StabilizerGains = field(default_factory=StabilizerGains)
    body_rate_amplitude: float = 1.0  # rad/s added to the body-rate setpoints, through an autopilot
    thrust_amplitude: float = 0.15  # fraction of the collective thrust added, through an autopilot
    collective: float = 0.0  # rad/s added to (or taken from) all four motors together, its own signal
    collective_hold: tuple[float, float] = (0.1, 0.4)  # s, prbs: the collective level's hold range
    backoff_height: float | None = None  # m, the per-motor fade near the box floor/ceiling (None: distance)
    backoff_lookahead: float = 0.0  # s: the floor/ceiling margin is taken where the climb rate would be then
    schedule: ClosedLoopSchedule | None = None
    start: str = "ground"
    kind: str = "closed-loop"

    @property
    def excitation_start(self) -> float:
        """Time (s) when the climb and settling are over and the excitation begins."""
        return self.takeoff_altitude / self.climb_rate + self.settle


Profile = RandomStepsProfile | SinusoidsProfile | ClosedLoopProfile


def resolve_profile_path(name_or_path: str | Path) -> Path:
    """A profile file: an existing path, else a bundled name (identification/profiles/<name>.yaml)."""
    text = str(name_or_path)
    p = Path(text)
    if p.is_file():
        return p
    bundled = profiles_dir() / f"{text}.yaml"
    if "/" not in text and bundled.is_file():
        return bundled
    raise UserError(
        f"excitation profile {text!r}: not found",
        hint=f"use a bundled profile ({', '.join(list_profiles())}) or a path to a profile YAML file",
    )


def load_profile(name_or_path: str | Path) -> Profile:
    """Load and validate a profile (bundled name or YAML path); each mistake is a UserError naming the key."""
    path = resolve_profile_path(name_or_path)
    where = f"excitation profile {path}"
    data = load_yaml_file(path, where)
    r = Section(where, data, hint=f"see the bundled profiles in {profiles_dir()} for every key with its unit")
    kind = r.text("kind", PROFILE_KINDS)
    name = str(r.raw("name", path.stem))
    description = str(r.raw("description", ""))
    if kind == "random-steps":
        groups_raw = r.raw("groups")
        if not isinstance(groups_raw, list) or not groups_raw:
            raise r.fail("groups", "must be a non-empty list of [low, high] speed ranges in rad/s")
        groups = []
        for i, g in enumerate(groups_raw):
            groups.append(range_value(where, f"groups[{i}]", g))
        guard = r.raw("rate_guard", None)
        profile: Profile = RandomStepsProfile(
            name=name,
            description=description,
            groups=tuple(groups),
            group_duration=r.number("group_duration", positive=True),
            hold=r.range("hold"),
            rate_guard=None if guard is None else r.number("rate_guard", positive=True),
        )
        if profile.hold[0] <= 0:
            raise r.fail("hold", "must be > 0 s")
    elif kind == "sinusoids":
        profile = SinusoidsProfile(
            name=name,
            description=description,
            duration=r.number("duration", positive=True),
            offset=r.numbers("offset", 4),
            amplitude=r.numbers("amplitude", 4),  # type: ignore[arg-type]
            frequency=r.number("frequency"),
            phase=r.numbers("phase", 4),  # type: ignore[arg-type]
        )
    else:
        to, box = r.optional_section("takeoff"), r.optional_section("box")
        ref, ex, st = (r.optional_section(k) for k in ("reference", "excitation", "stabilizer"))
        backoff = ex.optional_section("backoff")
        d = StabilizerGains()
        gains = StabilizerGains(
            position_gain=st.numbers("position_gain", 3, d.position_gain, low=0.0),  # type: ignore[arg-type]
            velocity_gain=st.numbers("velocity_gain", 3, d.velocity_gain, low=0.0),  # type: ignore[arg-type]
            attitude_gain=st.numbers("attitude_gain", 3, d.attitude_gain, low=0.0),  # type: ignore[arg-type]
            rate_gain=st.numbers("rate_gain", 3, d.rate_gain, low=0.0),  # type: ignore[arg-type]
            max_tilt=st.number("max_tilt", d.max_tilt, positive=True, high=60.0),
            max_speed=st.numbers("max_speed", 3, d.max_speed, low=0.0),  # type: ignore[arg-type]
        )
        schedule = _read_schedule(r) if r.has("schedule") else None
        if schedule is not None and ref.has("yaw_rate"):
            raise ref.fail("yaw_rate", "is not used with a schedule (its yaw_rates turn the heading)",
                           hint="remove reference.yaw_rate or the schedule")
        profile = ClosedLoopProfile(
            name=name,
            description=description,
            duration=r.number("duration", positive=True),
            takeoff_altitude=to.number("altitude", positive=True),
            climb_rate=to.number("climb_rate", positive=True),
            settle=to.number("settle", 1.0, nonnegative=True),
            box_half_width=box.number("half_width", positive=True),
            box_altitude=box.range("altitude"),
            tilt_limit=r.number("tilt_limit", positive=True, high=80.0),
            signal=ex.text("signal", ("prbs", "chirp")),
            amplitude=ex.number("amplitude", nonnegative=True),
            prbs_hold=ex.range("hold", (0.02, 0.15)),
            chirp=ex.range("chirp", (0.5, 8.0)),
            backoff_distance=backoff.number("distance", 1.0, positive=True),
            backoff_tilt=backoff.number("tilt", 10.0, positive=True),
            reference_amplitude=ref.numbers("amplitude", 3, (1.0, 1.0, 0.8), low=0.0),  # type: ignore[arg-type]
            reference_period=ref.numbers("period", 3, (8.0, 5.3, 6.1), low=0.1),  # type: ignore[arg-type]
            yaw_rate=ref.number("yaw_rate", 1.0),
            gains=gains,
            body_rate_amplitude=ex.number("body_rate_amplitude", 1.0, low=0.0),
            thrust_amplitude=ex.number("thrust_amplitude", 0.15, low=0.0, high=0.9),
            collective=ex.number("collective", 0.0, nonnegative=True),
            collective_hold=ex.range("collective_hold", (0.1, 0.4)),
            backoff_height=backoff.number("height", positive=True) if backoff.has("height") else None,
            backoff_lookahead=backoff.number("lookahead", 0.0, nonnegative=True, high=5.0),
            schedule=schedule,
        )
        for sub_reader in (to, box, ex, backoff, ref, st):
            sub_reader.done()
        _check_closed_loop(r, profile)
    r.done()
    return profile


MAX_SCHEDULE_YAW_RATE = 4.0  # rad/s: the stabiliser's yaw loop (gain 4 1/s) lags a faster turn by > 1 rad


def _listed_numbers(sec: Section, name: str) -> tuple[float, ...]:
    """A non-empty list of finite numbers at this key (any length)."""
    value = sec.raw(name)
    if not isinstance(value, (list, tuple)) or not value:
        raise sec.fail(name, f"must be a non-empty list of numbers, got {describe_value(value)}")
    return numbers_value(sec.where, sec.key(name), value, len(value))


def _read_schedule(r: Section) -> ClosedLoopSchedule:
    sc = r.section("schedule")
    altitudes = _listed_numbers(sc, "altitudes")
    yaw_rates = _listed_numbers(sc, "yaw_rates")
    for i, w in enumerate(yaw_rates):
        if abs(w) > MAX_SCHEDULE_YAW_RATE:
            raise sc.fail(f"yaw_rates[{i}]", f"must be within +-{MAX_SCHEDULE_YAW_RATE:g} rad/s, got {w:g}")
    out = ClosedLoopSchedule(
        segment=sc.number("segment", positive=True),
        altitudes=altitudes,
        yaw_rates=yaw_rates,
        move_speed=sc.number("move_speed", positive=True),
        yaw_acceleration=sc.number("yaw_acceleration", 1.0, positive=True),
        swing_fraction=sc.number("swing_fraction", 0.5, positive=True, high=0.9),
    )
    sc.done()
    return out


def _check_closed_loop(r: Section, p: ClosedLoopProfile) -> None:
    lo, hi = p.box_altitude
    if not lo < p.takeoff_altitude < hi:
        raise r.fail("takeoff.altitude", f"must lie inside box.altitude {list(p.box_altitude)}")
    if p.gains.max_tilt >= p.tilt_limit:
        raise r.fail("stabilizer.max_tilt", f"must be below tilt_limit ({p.tilt_limit:g} deg)")
    a = p.reference_amplitude
    if a[0] >= p.box_half_width or a[1] >= p.box_half_width:
        raise r.fail("reference.amplitude", f"must stay inside box.half_width ({p.box_half_width:g} m)")
    if p.takeoff_altitude - a[2] <= lo or p.takeoff_altitude + a[2] >= hi:
        raise r.fail("reference.amplitude", "the vertical swing must stay inside box.altitude")
    sc = p.schedule
    if sc is None:
        return
    for i, h in enumerate(sc.altitudes):
        if not lo < h or h + vertical_swing(p, h) >= hi:
            raise r.fail(f"schedule.altitudes[{i}]",
                         f"must lie inside box.altitude {list(p.box_altitude)} with its vertical swing, "
                         f"got {h:g}")
    heights = (p.takeoff_altitude, *sc.altitudes, sc.altitudes[0])  # the first move, each next, the wrap
    longest = max(sc.move_time(b - a_) for a_, b in zip(heights[:-1], heights[1:], strict=True))
    if longest > 0.5 * sc.segment:
        raise r.fail("schedule.move_speed",
                     f"too slow: the longest move between two heights takes {longest:.2f} s, more than half "
                     f"of schedule.segment ({sc.segment:g} s)",
                     hint="raise schedule.move_speed or schedule.segment, or bring the heights closer")
    rates = (0.0, *sc.yaw_rates, sc.yaw_rates[0])  # from the settled heading, each next, the wrap
    longest = max(sc.yaw_ramp_time(b - a_) for a_, b in zip(rates[:-1], rates[1:], strict=True))
    if longest > 0.5 * sc.segment:
        raise r.fail("schedule.yaw_acceleration",
                     f"too low: the largest change of yaw rate takes {longest:.2f} s, more than half of "
                     f"schedule.segment ({sc.segment:g} s)",
                     hint="raise schedule.yaw_acceleration or schedule.segment, or bring the yaw rates "
                          "closer")


def vertical_swing(p: ClosedLoopProfile, height: float) -> float:
    """The Lissajous' vertical amplitude (m) around a hover point `height` m above the start point: the
    reference's, but with a schedule at most swing_fraction of the height above the box floor (a low hover
    near the ground swings a few cm, a cruise one the full amplitude)."""
    a = p.reference_amplitude[2]
    if p.schedule is None:
        return a
    return max(0.0, min(a, p.schedule.swing_fraction * (height - p.box_altitude[0])))


# --------------------------------------------------------------------------------------------------------
# Signal generators


class RandomSteps:
    """paper-train: random held speeds per motor (rad/s) in successive groups' ranges."""

    def __init__(self, profile: RandomStepsProfile, seed: int, duration: float):
        self.p = profile
        self.rng = np.random.default_rng(seed)
        self.group_duration = duration / len(profile.groups)
        self.speeds = np.zeros(4)
        self.next_switch = np.zeros(4)
        self.group = -1
        self.guard_draws = 0

    def command(self, t: float, xi: np.ndarray) -> np.ndarray:
        """Rotor speeds (4,) rad/s at time t (s) since the flight start, given the true state xi."""
        group = min(int(t / self.group_duration), len(self.p.groups) - 1)
        if group != self.group:
            self.group = group
            self.next_switch[:] = t  # a new group redraws every motor at once
        lo, hi = self.p.groups[group]
        due = np.flatnonzero(self.next_switch <= t + 1e-9)
        if due.size:
            brake = self._brake_preference(xi)
            for i in due:
                a, b = lo, hi
                if brake[i] > 0:
                    a = 0.5 * (lo + hi)
                elif brake[i] < 0:
                    b = 0.5 * (lo + hi)
                self.speeds[i] = self.rng.uniform(a, b)
                self.next_switch[i] = t + self.rng.uniform(*self.p.hold)
        return self.speeds.copy()

    def _brake_preference(self, xi: np.ndarray) -> np.ndarray:
        """Per motor: +1 if speeding it up brakes the body rates over the guard, -1 if slowing it does, 0."""
        if self.p.rate_guard is None:
            return np.zeros(4)
        w = np.asarray(xi[9:12], dtype=float)
        over = np.abs(w) > self.p.rate_guard
        if not over.any():
            return np.zeros(4)
        self.guard_draws += 1
        score = -(TORQUE_SIGNS[:, over] * np.sign(w[over])).sum(axis=1)
        return np.sign(score)


class Sinusoids:
    """paper-validate: u_i = offset_i + amplitude_i sin(frequency t + phase_i), rad/s."""

    def __init__(self, profile: SinusoidsProfile):
        self.offset = np.asarray(profile.offset)
        self.amplitude = np.asarray(profile.amplitude)
        self.frequency = profile.frequency
        self.phase = np.asarray(profile.phase)

    def command(self, t: float, xi: np.ndarray) -> np.ndarray:
        """Rotor speeds (4,) rad/s at time t (s) since the flight start (the state is not used)."""
        return np.maximum(self.offset + self.amplitude * np.sin(self.frequency * t + self.phase), 0.0)


class ClosedLoopExcitation:
    """closed-loop: take-off and hover stabilised, then excitation added to each motor, fading near limits."""

    def __init__(
        self,
        profile: ClosedLoopProfile,
        vehicle: VehicleConfig,
        seed: int,
        duration: float,
        start_xi: np.ndarray,
    ):
        self.p = profile
        self.rng = np.random.default_rng(seed)
        # the collective level's own generator: a seed's per-motor sequence is the same with or without it
        self.collective_rng = np.random.default_rng([seed, 1])
        self.duration = duration
        self.stabilizer = HoverStabilizer(vehicle, profile.gains)
        self.origin = np.asarray(start_xi[:3], dtype=float)
        self.yaw0 = float(start_xi[8])
        self.levels = self.rng.choice((-1.0, 1.0), size=4)
        self.next_switch = np.zeros(4)
        self.collective_level = float(self.collective_rng.choice((-1.0, 1.0)))
        self.collective_switch = 0.0
        self.chirp_offsets = np.arange(4) * 0.25 * max(duration - profile.excitation_start, 1e-3)
        self.scale = 0.0  # the excitation scale of the last step (0..1), for the summary
        self.collective_scale = 0.0
        self.min_scale = 1.0
        self._turned = [0.0]  # heading turned (rad) by the start of each schedule segment

    def segment(self, te: float) -> tuple[int, float]:
        """The schedule's segment index and the time (s) into it at te s since the excitation began."""
        sc = self.p.schedule
        assert sc is not None
        k = int(te // sc.segment)
        return k, te - k * sc.segment

    def height(self, te: float) -> tuple[float, float]:
        """The hover point's height above the start point (m) and its rate (m/s, up) at te s since the
        excitation began: the take-off altitude, or the schedule's with a half-cosine move between two."""
        sc = self.p.schedule
        if sc is None or te < 0:
            return self.p.takeoff_altitude, 0.0
        k, tau = self.segment(te)
        n = len(sc.altitudes)
        target = sc.altitudes[k % n]
        before = self.p.takeoff_altitude if k == 0 else sc.altitudes[(k - 1) % n]
        move = sc.move_time(target - before)
        if tau >= move:
            return target, 0.0
        x = math.pi * tau / move
        return before + (target - before) * 0.5 * (1.0 - math.cos(x)), \
            (target - before) * 0.5 * math.pi / move * math.sin(x)

    def _segment_yaw(self, k: int, tau: float) -> tuple[float, float]:
        """(yaw rate rad/s, heading turned since the segment began rad) tau s into segment k: the rate ramps
        at yaw_acceleration from the previous segment's (0 before the first) to this one's, then holds."""
        sc = self.p.schedule
        assert sc is not None
        n = len(sc.yaw_rates)
        r0 = 0.0 if k == 0 else sc.yaw_rates[(k - 1) % n]
        r1 = sc.yaw_rates[k % n]
        ramp = sc.yaw_ramp_time(r1 - r0)
        if tau < ramp:
            a = math.copysign(sc.yaw_acceleration, r1 - r0)
            return r0 + a * tau, r0 * tau + 0.5 * a * tau * tau
        return r1, r0 * ramp + 0.5 * (r1 - r0) * ramp + r1 * (tau - ramp)

    def yaw_rate(self, te: float) -> float:
        """The commanded heading's turn rate (rad/s) at te s since the excitation began."""
        if self.p.schedule is None:
            return self.p.yaw_rate
        return self._segment_yaw(*self.segment(max(te, 0.0)))[0]

    def heading(self, te: float) -> float:
        """The commanded heading (rad) at te s since the excitation began: the yaw rates integrated."""
        sc = self.p.schedule
        if sc is None:
            turned = self.p.yaw_rate * te
        else:
            k, tau = self.segment(max(te, 0.0))
            while len(self._turned) <= k:  # the heading turned by the end of each whole segment, cached
                j = len(self._turned) - 1
                self._turned.append(self._turned[-1] + self._segment_yaw(j, sc.segment)[1])
            turned = self._turned[k] + self._segment_yaw(k, tau)[1]
        return math.remainder(self.yaw0 + turned, 2.0 * math.pi)

    def reference(self, t: float) -> Reference:
        """The reference at time t (s): climb to the hover point, then the Lissajous path with turning yaw
        around the (scheduled) hover height."""
        p = self.p
        o = self.origin
        climb_end = p.takeoff_altitude / p.climb_rate
        if t < climb_end:
            return Reference((o[0], o[1], o[2] - p.climb_rate * t), (0.0, 0.0, -p.climb_rate), self.yaw0)
        te = t - p.excitation_start
        if te < 0:
            return Reference((o[0], o[1], o[2] - p.takeoff_altitude), yaw=self.yaw0)
        h, h_rate = self.height(te)
        swing = vertical_swing(p, h)
        pos, vel = [], []
        for i, (a, per) in enumerate(zip(p.reference_amplitude, p.reference_period, strict=True)):
            om = 2.0 * math.pi / per
            a = swing if i == 2 else a
            centre = o[i] - (h if i == 2 else 0.0)
            pos.append(centre + a * math.sin(om * te))
            vel.append(a * om * math.cos(om * te) - (h_rate if i == 2 else 0.0))
        return Reference(tuple(pos), tuple(vel), self.heading(te))  # type: ignore[arg-type]

    def margins(self, xi: np.ndarray) -> tuple[float, float, float]:
        """(margin to the box walls m, to its floor or ceiling m, to the tilt limit deg)."""
        p = self.p
        rel = np.asarray(xi[:3], dtype=float) - self.origin
        margin_xy = p.box_half_width - max(abs(rel[0]), abs(rel[1]))
        alt = -rel[2]
        climb = -float(xi[5]) * p.backoff_lookahead  # m the vertical speed covers in the lookahead
        margin_alt = min(alt + min(climb, 0.0) - p.box_altitude[0], p.box_altitude[1] - alt - max(climb, 0.0))
        tilt = math.degrees(math.acos(max(-1.0, min(1.0, math.cos(xi[6]) * math.cos(xi[7])))))
        return margin_xy, margin_alt, p.tilt_limit - tilt

    def limit_scale(self, xi: np.ndarray) -> float:
        """Excitation scale 0..1: 1 well inside the box and tilt limit, falling to 0 at them (over
        backoff.height, else backoff.distance, at the box's floor and ceiling)."""
        p = self.p
        margin_xy, margin_alt, margin_tilt = self.margins(xi)
        height = p.backoff_distance if p.backoff_height is None else p.backoff_height
        s = min(margin_xy / p.backoff_distance, margin_alt / height, margin_tilt / p.backoff_tilt)
        return min(max(s, 0.0), 1.0)

    def collective_limit_scale(self, xi: np.ndarray) -> float:
        """The collective excitation's scale 0..1: as limit_scale, but over backoff.distance at the floor and
        ceiling too (the collective moves the vehicle up and down; per-motor PRBS mostly turns it)."""
        _, margin_alt, _ = self.margins(xi)
        return min(self.limit_scale(xi), min(max(margin_alt / self.p.backoff_distance, 0.0), 1.0))

    def signal(self, t: float) -> np.ndarray:
        """The raw excitation (4,) in [-1, 1] at time t (s) since the excitation began."""
        if self.p.signal == "prbs":
            due = self.next_switch <= t + 1e-9
            for i in np.flatnonzero(due):
                self.levels[i] = -self.levels[i] if self.rng.random() < 0.5 else self.levels[i]
                self.next_switch[i] = t + self.rng.uniform(*self.p.prbs_hold)
            return self.levels.copy()
        return self._chirp(t + self.chirp_offsets)

    def collective_signal(self, t: float) -> float:
        """The raw collective excitation in [-1, 1] at time t (s) since the excitation began."""
        if self.p.signal == "prbs":
            if self.collective_switch <= t + 1e-9:
                if self.collective_rng.random() < 0.5:
                    self.collective_level = -self.collective_level
                self.collective_switch = t + self.collective_rng.uniform(*self.p.collective_hold)
            return self.collective_level
        span = max(self.duration - self.p.excitation_start, 1e-3)
        return float(self._chirp(np.array([t + 0.125 * span]))[0])  # between motors 1 and 2's phases

    def _chirp(self, t: np.ndarray) -> np.ndarray:
        f0, f1 = self.p.chirp
        span = max(self.duration - self.p.excitation_start, 1e-3)
        tau = t % span
        return np.sin(2.0 * math.pi * (f0 * tau + 0.5 * (f1 - f0) / span * tau * tau))

    def command(self, t: float, xi: np.ndarray) -> np.ndarray:
        """Rotor speeds (4,) rad/s: the stabiliser's, plus the scaled excitation once it has begun."""
        speeds = self.stabilizer.command(xi, self.reference(t))
        te = t - self.p.excitation_start
        if te < 0:
            self.scale = self.collective_scale = 0.0
            return speeds
        self.scale = self.limit_scale(xi)
        self.min_scale = min(self.min_scale, self.scale)
        out = speeds + self.scale * self.p.amplitude * self.signal(te)
        if self.p.collective > 0:
            self.collective_scale = self.collective_limit_scale(xi)
            out = out + self.collective_scale * self.p.collective * self.collective_signal(te)
        return np.maximum(out, 0.0)

    def rates_and_thrust(self, t: float, xi: np.ndarray) -> tuple[np.ndarray, float]:
        """Setpoints for an autopilot's rate loop at t (s) since the flight start: body rates FRD (3,) rad/s
        and collective thrust (N), the stabiliser's outer loops plus the scaled excitation once begun."""
        rates, thrust = self.stabilizer.rates_and_thrust(xi, self.reference(t))
        te = t - self.p.excitation_start
        if te < 0:
            self.scale = 0.0
            return np.asarray(rates, dtype=float), thrust
        self.scale = self.limit_scale(xi)
        self.min_scale = min(self.min_scale, self.scale)
        sig = self.signal(te)
        rates_out = np.asarray(rates, dtype=float) + self.scale * self.p.body_rate_amplitude * sig[:3]
        return rates_out, thrust * (1.0 + self.scale * self.p.thrust_amplitude * float(sig[3]))


def make_generator(
    profile: Profile, vehicle: VehicleConfig, seed: int, duration: float, start_xi: np.ndarray
) -> RandomSteps | Sinusoids | ClosedLoopExcitation:
    """The signal generator of a profile for one flight of `duration` s starting in state start_xi."""
    if isinstance(profile, RandomStepsProfile):
        return RandomSteps(profile, seed, duration)
    if isinstance(profile, SinusoidsProfile):
        return Sinusoids(profile)
    return ClosedLoopExcitation(profile, vehicle, seed, duration, start_xi)
