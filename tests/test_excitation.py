"""Excitation profiles: settings validation, the signals, and the hover stabiliser flown on the SITL's own
dynamics (in process, no network) to show the closed-loop flight stays inside its box and tilt limit."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from bridge.errors import UserError
from identification.excitation import (
    ClosedLoopExcitation,
    RandomSteps,
    Sinusoids,
    list_profiles,
    load_profile,
    make_generator,
    profiles_dir,
)
from identification.hover_stabilizer import HoverStabilizer, Reference


def test_bundled_profiles_load():
    assert {"paper-train", "paper-validate", "closed-loop"} <= set(list_profiles())
    train = load_profile("paper-train")
    assert train.groups == ((0, 300), (0, 700), (0, 800), (0, 1000)) and train.duration == 32.0
    val = load_profile("paper-validate")
    assert val.phase == pytest.approx((0.0, math.pi / 4, math.pi / 3, math.pi / 6))
    assert load_profile(profiles_dir() / "closed-loop.yaml").tilt_limit == 30.0


def _write(tmp_path, data, name="p.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def test_profile_mistakes_name_the_file_and_key(tmp_path):
    base = yaml.safe_load((profiles_dir() / "closed-loop.yaml").read_text())
    bad = dict(base, excitation=dict(base["excitation"], amplitud=3))
    with pytest.raises(UserError, match=r"p\.yaml: unknown key 'excitation\.amplitud'"):
        load_profile(_write(tmp_path, bad))
    bad = dict(base, tilt_limit="steep")
    with pytest.raises(UserError, match=r"key 'tilt_limit' must be a number"):
        load_profile(_write(tmp_path, bad))
    bad = dict(base, stabilizer=dict(base["stabilizer"], max_tilt=35.0))
    with pytest.raises(UserError, match=r"stabilizer\.max_tilt' must be below tilt_limit"):
        load_profile(_write(tmp_path, bad))
    bad = dict(base, reference=dict(base["reference"], amplitude=[3.5, 1, 0.5]))
    with pytest.raises(UserError, match=r"reference\.amplitude' must stay inside box\.half_width"):
        load_profile(_write(tmp_path, bad))
    train = yaml.safe_load((profiles_dir() / "paper-train.yaml").read_text())
    with pytest.raises(UserError, match=r"key 'groups\[1\]' must be \[low, high\]"):
        load_profile(_write(tmp_path, dict(train, groups=[[0, 300], [700, 0]])))
    with pytest.raises(UserError, match="key 'hold' is missing"):
        load_profile(_write(tmp_path, {k: v for k, v in train.items() if k != "hold"}))
    with pytest.raises(UserError, match="key 'kind' must be one of"):
        load_profile(_write(tmp_path, dict(train, kind="wobble")))
    with pytest.raises(UserError, match="'nope' : not found|'nope': not found"):
        load_profile("nope")


def test_paper_validate_is_the_papers_formula():
    gen = Sinusoids(load_profile("paper-validate"))
    for t in (0.0, 0.123, 7.7):
        expected = [300 + 300 * math.sin(10 * t + p) for p in (0, math.pi / 4, math.pi / 3, math.pi / 6)]
        assert gen.command(t, np.zeros(12)) == pytest.approx(expected)


def test_paper_train_groups_ranges_and_holds():
    prof = load_profile("paper-train")
    gen = RandomSteps(prof, seed=4, duration=8.0)  # 2 s per group
    t = np.arange(2000) * 0.004
    u = np.array([gen.command(tk, np.zeros(12)) for tk in t])
    for g, (lo, hi) in enumerate(prof.groups):
        seg = u[(t >= 2.0 * g) & (t < 2.0 * (g + 1))]
        assert seg.min() >= lo and seg.max() <= hi
        assert seg.max() > lo + 0.8 * (hi - lo)  # the range is used
    for i in range(4):
        changes = np.flatnonzero(np.diff(u[:, i]) != 0) + 1
        holds = np.diff(changes) * 0.004
        within_group = holds[np.floor(t[changes[1:]] / 2.0) == np.floor(t[changes[:-1]] / 2.0)]
        assert within_group.min() >= 0.02 - 1e-9 and within_group.max() <= 0.2 + 0.004
    # seeded: the same seed repeats the flight, another differs
    again = RandomSteps(prof, seed=4, duration=8.0)
    assert np.array_equal(u[:50], [again.command(tk, np.zeros(12)) for tk in t[:50]])
    other = RandomSteps(prof, seed=5, duration=8.0)
    assert not np.array_equal(u[:50], [other.command(tk, np.zeros(12)) for tk in t[:50]])


def test_rate_guard_draws_from_the_braking_half():
    prof = load_profile("paper-train")
    gen = RandomSteps(prof, seed=1, duration=32.0)
    spinning = np.zeros(12)
    spinning[9] = 30.0  # rolling right faster than the guard (25 rad/s)
    draws = []
    for k in range(400):
        gen.next_switch[:] = 0.0  # force a new draw for every motor
        draws.append(gen.command(28.0 + k * 1e-3, spinning))  # group 0-1000 rad/s
    draws = np.array(draws)
    # negative roll torque brakes: motors 1 and 4 (roll sign -1) speed up, 2 and 3 slow down
    assert draws[:, [0, 3]].min() >= 500.0 and draws[:, [1, 2]].max() <= 500.0
    assert gen.guard_draws == 400


def test_stabilizer_allocation_and_hover(vehicle):
    stab = HoverStabilizer(vehicle)
    w = stab.allocate(vehicle.mass * vehicle.gravity, np.zeros(3))
    assert w == pytest.approx([vehicle.hover_speed] * 4, rel=1e-9)
    # a pure roll torque: motors 2 and 3 (left side) faster than 1 and 4
    w = stab.allocate(vehicle.mass * vehicle.gravity, np.array([0.05, 0.0, 0.0]))
    assert w[1] > w[0] and w[2] > w[3] and w[1] == pytest.approx(w[2])
    # level at the reference: hover speeds
    xi = np.zeros(12)
    xi[2] = -3.0
    assert stab.command(xi, Reference((0.0, 0.0, -3.0))) == pytest.approx([vehicle.hover_speed] * 4, rel=1e-6)


def _fly_in_process(vehicle, profile, duration, seed=0):
    from sitl.dynamics import Quadrotor

    quad = Quadrotor(vehicle)
    curve = vehicle.motor_curve

    def state():
        return np.array((*quad.position, *quad.velocity, *quad.euler, *quad.rates))

    gen = make_generator(profile, vehicle, seed, duration, state())
    xs, us, scales = [], [], []
    for k in range(int(round(duration / 0.004))):
        x = state()
        xs.append(x)
        u = gen.command(k * 0.004, x)
        us.append(u)
        scales.append(getattr(gen, "scale", 1.0))
        quad.step([curve.throttle_for_speed(float(w)) for w in u])
    return gen, np.array(xs), np.array(us), np.array(scales)


def test_closed_loop_takes_off_and_stays_inside_its_limits(vehicle):
    prof = load_profile("closed-loop")
    gen, xs, us, scales = _fly_in_process(vehicle, prof, duration=20.0)
    assert isinstance(gen, ClosedLoopExcitation)
    t = np.arange(len(xs)) * 0.004
    exciting = t >= prof.excitation_start
    alt = -xs[:, 2]
    assert alt[0] == 0.0 and alt[(t > 2.0) & ~exciting].min() > 1.5  # took off from the ground
    tilt = np.degrees(np.arccos(np.cos(xs[:, 6]) * np.cos(xs[:, 7])))
    assert tilt.max() < prof.tilt_limit
    assert np.abs(xs[exciting, :2]).max() < prof.box_half_width
    lo, hi = prof.box_altitude
    assert lo < alt[exciting].min() and alt[exciting].max() < hi
    # the excitation is really there (PRBS of +-100 rad/s on each motor) and the heading turns all round
    assert scales[exciting].mean() > 0.8
    assert np.ptp(xs[exciting, 8]) > 5.0
    assert (np.std(np.diff(us[exciting], axis=0), axis=0) > 5.0).all()


def test_excitation_backs_off_near_the_limits(vehicle):
    prof = load_profile("closed-loop")
    start = np.zeros(12)
    gen = ClosedLoopExcitation(prof, vehicle, 0, 30.0, start)
    xi = np.zeros(12)
    xi[2] = -3.5
    assert gen.limit_scale(xi) == 1.0
    xi[0] = prof.box_half_width - 0.5 * prof.backoff_distance  # half way into the margin
    assert gen.limit_scale(xi) == pytest.approx(0.5)
    xi[0] = prof.box_half_width + 0.1
    assert gen.limit_scale(xi) == 0.0
    xi[0] = 0.0
    xi[6] = math.radians(prof.tilt_limit - 0.25 * prof.backoff_tilt)
    assert gen.limit_scale(xi) == pytest.approx(0.25, abs=1e-6)
    xi[6] = 0.0
    # near the floor the per-motor excitation fades over backoff.height, the collective over backoff.distance
    xi[2] = -(prof.box_altitude[0] + 0.5 * prof.backoff_height)
    assert gen.limit_scale(xi) == pytest.approx(0.5)
    assert gen.collective_limit_scale(xi) == pytest.approx(0.5 * prof.backoff_height / prof.backoff_distance)
    xi[2] = -(prof.box_altitude[0] + 0.2)  # 0.2 m above the floor of the box, at rest: full per-motor
    assert gen.limit_scale(xi) == 1.0
    xi[5] = 0.2 / prof.backoff_lookahead  # descending: in the lookahead the floor is 0.2 m nearer
    assert gen.limit_scale(xi) == 0.0 and gen.collective_limit_scale(xi) == 0.0
    xi[5] = -1.0  # climbing away from the floor: as at rest
    assert gen.limit_scale(xi) == 1.0


def _schedule_profile(tmp_path, **schedule):
    base = yaml.safe_load((profiles_dir() / "closed-loop.yaml").read_text())
    return load_profile(_write(tmp_path, dict(base, schedule=dict(base["schedule"], **schedule))))


def test_schedule_mistakes_name_the_key(tmp_path):
    base = yaml.safe_load((profiles_dir() / "closed-loop.yaml").read_text())
    with pytest.raises(UserError, match=r"schedule\.altitudes\[1\]' must lie inside box\.altitude"):
        _schedule_profile(tmp_path, altitudes=[2.0, 0.1])  # below the box floor (0.15 m)
    with pytest.raises(UserError, match=r"schedule\.altitudes\[0\]' must lie inside box\.altitude"):
        _schedule_profile(tmp_path, altitudes=[5.5])  # its 0.8 m swing reaches the 6 m ceiling
    with pytest.raises(UserError, match=r"schedule\.altitudes' must be a non-empty list of numbers"):
        _schedule_profile(tmp_path, altitudes=[])
    with pytest.raises(UserError, match=r"schedule\.yaw_rates\[1\]' must be a number"):
        _schedule_profile(tmp_path, yaw_rates=[1.0, "fast"])
    with pytest.raises(UserError, match=r"schedule\.yaw_rates\[0\]' must be within \+-4 rad/s"):
        _schedule_profile(tmp_path, yaw_rates=[-5.0, 1.0])
    with pytest.raises(UserError, match=r"schedule\.move_speed' too slow: the longest move"):
        _schedule_profile(tmp_path, move_speed=0.3)  # 2.0 -> 0.3 m at 0.3 m/s: 8.9 s of a 7 s segment
    with pytest.raises(UserError, match=r"schedule\.yaw_acceleration' too low"):
        _schedule_profile(tmp_path, yaw_acceleration=0.5)  # -1.5 -> 1.5 rad/s: 6 s of a 7 s segment
    with pytest.raises(UserError, match=r"schedule\.segment' must be > 0"):
        _schedule_profile(tmp_path, segment=0)
    with pytest.raises(UserError, match=r"unknown key 'schedule\.heights'"):
        _schedule_profile(tmp_path, heights=[1.0])
    bad = dict(base, reference=dict(base["reference"], yaw_rate=1.0))
    with pytest.raises(UserError, match=r"reference\.yaw_rate' is not used with a schedule"):
        load_profile(_write(tmp_path, bad))
    bad = dict(base, excitation=dict(base["excitation"], collective=-5.0))
    with pytest.raises(UserError, match=r"excitation\.collective' must be >= 0"):
        load_profile(_write(tmp_path, bad))
    backoff = dict(base["excitation"]["backoff"], height=0)
    bad = dict(base, excitation=dict(base["excitation"], backoff=backoff))
    with pytest.raises(UserError, match=r"excitation\.backoff\.height' must be > 0"):
        load_profile(_write(tmp_path, bad))


def test_profiles_without_a_schedule_keep_their_reference(vehicle):
    prof = load_profile("px4-offboard")
    assert prof.schedule is None and prof.collective == 0.0 and prof.backoff_height is None
    gen = ClosedLoopExcitation(prof, vehicle, 0, prof.duration, np.zeros(12))
    te = 3.0
    ref = gen.reference(prof.excitation_start + te)
    assert ref.position[2] == pytest.approx(-prof.takeoff_altitude
                                            + prof.reference_amplitude[2] * math.sin(2 * math.pi / 6.1 * te))
    assert ref.yaw == pytest.approx(math.remainder(prof.yaw_rate * te, 2 * math.pi))


def test_schedule_reference_visits_every_height_and_turns_both_ways(vehicle):
    prof = load_profile("closed-loop")
    sc = prof.schedule
    gen = ClosedLoopExcitation(prof, vehicle, 0, 60.0, np.zeros(12))
    t = np.arange(prof.excitation_start, prof.excitation_start + len(sc.altitudes) * sc.segment, 0.004)
    refs = [gen.reference(tk) for tk in t]
    te = t - prof.excitation_start
    centre = np.array([gen.height(x)[0] for x in te])
    rate = np.array([gen.yaw_rate(x) for x in te])
    yaw = np.unwrap([r.yaw for r in refs])
    # each segment ends at its height, held; low hovers near the ground and cruise heights both
    for k, h in enumerate(sc.altitudes):
        end = (te > (k + 0.6) * sc.segment) & (te < (k + 1) * sc.segment)
        assert np.allclose(centre[end], h)
    assert min(sc.altitudes) <= 0.3 and max(sc.altitudes) >= 1.5
    # the moves are smooth: no jump in the hover height, its speed at most move_speed
    assert np.abs(np.diff(centre)).max() <= sc.move_speed * 0.004 + 1e-9
    # the vertical swing stays above the box floor, a low hover swings little
    z = -np.array([r.position[2] for r in refs])
    assert z.min() > prof.box_altitude[0] and np.ptp(z[centre == min(sc.altitudes)]) < 0.2
    # the heading turns both ways at several rates, continuously (ramped yaw rate, no heading jump)
    held = rate[np.abs(np.diff(rate, prepend=rate[0])) < 1e-9]  # the rates held after each ramp
    assert rate.max() >= 1.0 and rate.min() <= -1.0 and len(set(np.round(held, 6))) >= 5
    assert np.abs(np.diff(rate)).max() <= sc.yaw_acceleration * 0.004 + 1e-9
    assert np.allclose(np.diff(yaw) / 0.004, 0.5 * (rate[1:] + rate[:-1]), atol=1e-6)
    # the yaw rate is not the height's: both signs at low and at cruise heights over the two lists' cycle
    te_all = np.arange(0.0, 35 * sc.segment, 0.1)
    c = np.array([gen.height(x)[0] for x in te_all])
    r = np.array([gen.yaw_rate(x) for x in te_all])
    assert abs(np.corrcoef(c, r)[0, 1]) < 0.1


def test_default_closed_loop_flight_varies_height_rotor_sum_and_yaw_rate():
    """The default profile flown on the SITL's dynamics (every aerodynamic effect and the ground): inside its
    limits, half of it below 1 m, the rotor sum varied well beyond the per-motor PRBS's, yaw rates of both
    signs, and per-motor PRBS left as it was (the collective has its own random sequence)."""
    from bridge.vehicle import load_vehicle

    aero = load_vehicle("fang-chen-aero")
    prof = load_profile("closed-loop")
    gen, xs, us, scales = _fly_in_process(aero, prof, duration=40.0, seed=1)
    t = np.arange(len(xs)) * 0.004
    exciting = t >= prof.excitation_start
    alt = -xs[exciting, 2]
    tilt = np.degrees(np.arccos(np.cos(xs[:, 6]) * np.cos(xs[:, 7])))
    assert alt.min() > prof.box_altitude[0] and alt.max() < prof.box_altitude[1]
    assert tilt.max() < prof.tilt_limit and np.abs(xs[exciting, :2]).max() < prof.box_half_width
    assert np.mean(alt < 1.0) > 0.4 and np.mean(alt < 0.5) > 0.15 and alt.min() < 0.35
    assert np.median(alt) < 1.2 and alt.max() > 1.8
    rotor_sum = us[exciting].sum(axis=1)
    assert rotor_sum.std() / rotor_sum.mean() > 0.15  # 0.09 with the per-motor PRBS alone
    wz = xs[exciting, 11]
    assert np.mean(wz > 0.5) > 0.2 and np.mean(wz < -0.5) > 0.2
    assert abs(np.corrcoef(wz, alt)[0, 1]) < 0.3
    # a rate damping w stands apart from the rotor drag's w*u_j: its VIF beside them
    wx = xs[exciting, 9]
    A = np.column_stack([wx[:, None] * us[exciting], np.ones(len(wx))])
    resid = wx - A @ np.linalg.lstsq(A, wx, rcond=None)[0]
    assert np.var(wx) / np.var(resid) < 60  # ~110 with the per-motor PRBS alone
    assert scales[exciting].mean() > 0.8  # the per-motor PRBS is rarely faded
    # the collective's own generator: the per-motor levels are the same sequence as without it
    from dataclasses import replace

    plain = ClosedLoopExcitation(replace(prof, collective=0.0), aero, 1, 40.0, np.zeros(12))
    with_c = ClosedLoopExcitation(prof, aero, 1, 40.0, np.zeros(12))
    for k in range(500):
        a, b = plain.signal(k * 0.004), with_c.signal(k * 0.004)
        with_c.collective_signal(k * 0.004)
        assert np.array_equal(a, b)
