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
    assert alt[0] == 0.0 and alt[t > 3.0].min() > 1.0  # took off from the ground
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
    xi[2] = -(prof.box_altitude[0] + 0.2)  # 0.2 m above the floor of the box
    assert gen.limit_scale(xi) == pytest.approx(0.2)
