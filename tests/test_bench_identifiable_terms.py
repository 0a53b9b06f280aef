"""bench/discovery.py's identifiability of the true terms on a training flight: given the true structure, a
term the flight's noise hides (the paper vehicle's rate damping, 0.5 % of a rate's effect) is listed as not
identifiable, the rotor torques beside it are not, and on noise-free rows nothing is listed."""

from __future__ import annotations

import numpy as np
from bench_module import bench_module

discovery = bench_module("discovery.py", "bench_discovery")


def test_a_term_below_the_noise_is_not_identifiable_and_the_torques_are():
    case = discovery.Case("paper vehicle")
    train = discovery.synthetic(case, 2000, seed=4)
    body = discovery.body_expressions(discovery.VEHICLE, case.effects)
    gravity = 9.8
    assert discovery.unidentifiable_terms(body, train, gravity, weak=False) == {n: [] for n in body}
    rng = np.random.default_rng(5)
    noisy = train.targets.copy()
    noisy[:, 3:] += 1.0 * rng.standard_normal((len(noisy), 3))  # rad/s^2 on dwx dwy dwz
    train.targets[:] = noisy
    hidden = discovery.unidentifiable_terms(body, train, gravity, weak=False)
    assert "wx" in hidden["dwx"] and "wy" in hidden["dwy"]
    assert not any(t.startswith("u") for t in hidden["dwx"] + hidden["dwy"] + hidden["dwz"])
    assert hidden["fx"] == [] and hidden["fz"] == []


def test_a_height_law_left_out_of_the_true_structure_hides_the_other_terms():
    """A flight near the ground with a ground effect: the law (no monomial on a SITL vehicle, so scored apart)
    is part of the true structure; left out, its share of the targets is residual and the other terms' t
    ratios fall with it, so a flight rich in low hovers would be scored as identifying less."""
    case = discovery.Case("ground effect", discovery.Effects(ground_effect=0.08), height=(0.3, 3.0))
    train = discovery.synthetic(case, 2000, seed=4)
    full = discovery.body_expressions(discovery.VEHICLE, case.effects)
    far = discovery.body_expressions(discovery.VEHICLE, discovery.Effects())
    law = {n: full[n] - far[n] for n in full}
    assert law["fz"] != 0
    gravity = 9.8
    given_law = discovery.unidentifiable_terms(far, train, gravity, weak=False, height_law=law)
    assert given_law == {n: [] for n in far}  # noise-free rows, the whole true structure: every term pinned
    without = discovery.unidentifiable_terms(far, train, gravity, weak=False)
    assert any(without.values()), without  # the law in the residual: some true term's t below min_t


def test_the_fit_and_pick_rows_leave_out_identifys_validation_block():
    """fit_and_pick_rows are the rows identify fits and picks on without a validation flight: the training
    flight minus its validation block (the last fifth) and the gaps beside the blocks, so fewer rows, and a
    term at the edge of the noise can be identifiable on the whole flight and not on them."""
    case = discovery.Case("paper vehicle")
    train = discovery.synthetic(case, 2000, seed=4)
    own = discovery.fit_and_pick_rows(train)
    assert 0.7 * len(train) < len(own) < 0.8 * len(train)
    assert own.t.max() < train.t.min() + 0.8 * (train.t.max() - train.t.min())
    assert set(np.round(own.t, 9)) <= set(np.round(train.t, 9))
    body = discovery.body_expressions(discovery.VEHICLE, case.effects)
    rng = np.random.default_rng(6)
    train.targets[:, 3:] += 0.11 * rng.standard_normal((len(train), 3))  # rad/s^2: roll damping's t near 5
    whole = discovery.unidentifiable_terms(body, train, 9.8, weak=False)
    fewer = discovery.unidentifiable_terms(body, discovery.fit_and_pick_rows(train), 9.8, weak=False)
    assert "wx" not in whole["dwx"] and "wx" in fewer["dwx"]  # t 5.5+ on the flight, under 4.8 on 3/4 of it
    assert all(set(whole[n]) <= set(fewer[n]) for n in body)


def test_a_true_constant_is_asked_its_t_as_the_other_terms():
    """A sensor's bias is a constant of the reference (bench/discovery.py sensor_reference); one below the
    noise is listed as not identifiable, as any term, one well above it is not."""
    case = discovery.Case("paper vehicle")
    body = discovery.body_expressions(discovery.VEHICLE, case.effects)
    wz = discovery.PRIMITIVE_SYMBOLS["wz"]
    rng = np.random.default_rng(7)
    listed = {}
    for offset in (1e-4, 0.5):  # rad/s^2 on wz' = -0.2 wz + offset, beside 1 rad/s^2 of noise, 2000 rows
        train = discovery.synthetic(case, 2000, seed=4)
        train.targets[:, 5] = -0.2 * train.xi[:, 11] + offset + 1.0 * rng.standard_normal(len(train))
        reference = {**body, "dwz": -0.2 * wz + offset}
        listed[offset] = discovery.unidentifiable_terms(reference, train, 9.8, weak=False)["dwz"]
    assert listed[1e-4] == ["1"] and listed[0.5] == []
