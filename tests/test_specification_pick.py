"""Of equally good structures, one the weak rows do not show misspecified
(identification.specification_pick): Hausman's test tells a term from its tie with a slowly varying factor,
which the t rule cannot; of the equally good candidates the test does not reject, the pick moves to the one
with the fewest terms, the simplest the rows do not fit clearly worse than the best, each term measured by
the better t ratio of the weak rows' own fit and the generalised one."""

from __future__ import annotations

import dataclasses

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS
from identification.candidate import Candidate
from identification.engine_settings import SelectionSettings
from identification.pareto import terms_identified
from identification.refit import structure_test
from identification.specification_pick import specification_line, specification_pick
from identification.weak_form import WeakSettings, weak_rows
from identification.weak_noise import STEP_DIFFERENCE, RefitTest, weak_whitener

DT = 0.004
WZ = PRIMITIVE_SYMBOLS["wz"]
U1 = PRIMITIVE_SYMBOLS["u1"]
ROTOR_SUM = sum(PRIMITIVE_SYMBOLS[f"u{i}"] for i in range(1, 5))


def tied_flight(seed: int, seconds: float = 60.0):
    """A rate wz' = a wz + c wz (u1 + .. + u4) (rad/s^2) read by a gyro with white noise 0.01 rad/s, on a
    flight that alternates 5 s blocks: the rotor sum 30 % above 2000 rad/s with the rate driven at 0.2 Hz,
    and 30 % below at 2 Hz (as motor steps change the rotor sum and the rates' content together):
    (the parts structure_test takes: X (N,16) at each step's start, the gyro's difference over each step
    less the known drive (rad/s^2), the weak operator; their whitener)."""
    rng = np.random.default_rng(seed)
    n = int(seconds / DT)
    t = np.arange(n) * DT
    high = (t // 5.0) % 2 == 0
    total = 2000.0 * (1.0 + 0.3 * np.convolve(np.where(high, 1.0, -1.0), np.ones(125) / 125, mode="same"))
    f = np.where(high, 0.2, 2.0)  # Hz: the drive's frequency in each block, 10-20 rad/s of rate
    drive = 40 * np.pi * f * np.sin(2 * np.pi * np.cumsum(f) * DT + rng.uniform(0, 2 * np.pi))  # rad/s^2
    w = np.zeros(n + 1)
    for k in range(n):
        w[k + 1] = w[k] + DT * (drive[k] - 2.0 * w[k] - 2.5e-6 * total[k] * w[k])
    gyro = w + 0.01 * rng.standard_normal(n + 1)
    X = np.zeros((n, 16))
    X[:, 11] = w[:-1]  # wz at each step's start, where the (Euler) step reads it
    X[:, 12:16] = total[:, None] / 4.0
    target = np.diff(gyro) / DT - drive
    op = weak_rows(t, None, WeakSettings())
    return [(X, target, op)], [weak_whitener(op, t, None, STEP_DIFFERENCE)]


def test_the_test_tells_a_term_from_its_tie_with_a_slow_factor():
    """wz alone stands for a wz + c wz (u1 + .. + u4) at the mean rotor sum (the t rule's tie); the rows
    reject it, and not the true structure, on several noise draws."""
    for seed in range(3):
        parts, whiteners = tied_flight(seed)
        tied = structure_test([WZ], parts, whiteners)
        true = structure_test([WZ, WZ * ROTOR_SUM], parts, whiteners)
        assert tied is not None and true is not None
        assert not tied.generalised, tied.p_value
        assert true.generalised, true.p_value


def candidate(expr: sympy.Expr, complexity: int, loss: float, t: float = 10.0) -> Candidate:
    """A measured candidate (its weakest t ratio given) with a held-out loss."""
    return Candidate(expr, complexity, loss, "test", holdout_loss=loss, weakest_t=t, largest_vif=1.0)


def verdict(p: float, rss: float = 1.0, t: float = 10.0, terms: int = 1) -> RefitTest:
    """A specification test's result with p-value p, the generalised fit's whitened residual rss and every
    term's t ratio t in it (the fields specification_pick reads)."""
    z = np.ones(terms)
    return RefitTest(1.0, terms, p, z, z, z, z / t, rss=rss, s2=1.0)


def test_the_pick_moves_to_the_simplest_equally_good_structure_not_rejected():
    """Rejected pick: the simplest candidate within tolerance that the rule passes, at most one term larger,
    whose test passes; a better-scoring but unidentified or much larger one is not taken."""
    settings = SelectionSettings()
    chosen = candidate(-0.003 * WZ, 5, 1.000)
    tie = candidate(-2e-6 * WZ * ROTOR_SUM, 9, 0.999)
    unidentified = candidate(-2e-6 * WZ * ROTOR_SUM + 1e-3 * U1, 7, 0.995, t=1.0)
    big = candidate(WZ + U1 + U1**2 + WZ * U1, 8, 0.990)
    far = candidate(-2e-6 * WZ * U1, 6, 1.5)  # outside the tolerance
    passes = {frozenset([WZ * ROTOR_SUM]), frozenset([WZ * ROTOR_SUM, U1]),
              frozenset([WZ, U1, U1**2, WZ * U1]), frozenset([WZ * U1])}

    def test(shapes):
        return verdict(0.5 if frozenset(shapes) in passes else 1e-6)

    picked, record = specification_pick(chosen, [chosen, tie, unidentified, big, far], settings, 1.0, test)
    assert picked.expression == tie.expression  # a copy, its t ratio the generalised fit's
    assert record["picked"]["p_value"] == 0.5 and record["rejected"]["p_value"] == 1e-6
    assert "picked an equally good one" in specification_line("dwx", record)

    # a pick the test does not reject stays, untouched
    same, none = specification_pick(chosen, [chosen, tie], settings, 1.0, lambda shapes: verdict(0.3))
    assert same is chosen and none is None
    # no test (no stated noise): the pick stays
    assert specification_pick(chosen, [chosen, tie], settings, 1.0, lambda shapes: None) == (chosen, None)
    # rejected, and no equally good candidate passes: the pick stays and the record says so
    stays, record = specification_pick(chosen, [chosen, tie], settings, 1.0, lambda shapes: verdict(1e-4))
    assert stays is chosen and "picked" not in record and record["tried"] == 1
    assert "may lack a term" in specification_line("dwx", record)


def test_the_screen_gives_the_exact_tests_p_value_for_any_subset():
    """The search's screen (Gram matrices of the pool's weak columns) gives Hausman's test of any subset as
    the test on the rows gives it."""
    from identification.refit import pool_screen

    parts, whiteners = tied_flight(1, seconds=30.0)
    pool = [WZ, WZ * ROTOR_SUM, WZ**2, WZ**3, sympy.Integer(1)]
    screen = pool_screen(pool, parts, whiteners)
    assert screen is not None and screen.terms == pool
    for subset in ([0], [1], [0, 1], [0, 2, 4], [1, 3], [0, 1, 2, 3, 4]):
        exact = structure_test([pool[i] for i in subset], parts, whiteners)
        p, _ = screen.p_value(subset)
        assert exact is not None
        assert np.isclose(p, exact.p_value, rtol=1e-5, atol=1e-300), (subset, p, exact.p_value)


def test_of_the_structures_that_pass_the_fewest_terms_then_the_best_generalised_fit():
    """A constant beside the rejected pick passes the test as a weak term the rows hold does (a constant is a
    node simpler): of the structures that pass, the fewest terms, and of those the simplest whose generalised
    fit is not clearly worse than the best (chi^2 within CLEARLY_BETTER_CHI2); a term only the generalised
    fit pins down (its t ratio in the weak rows' own fit below min_t) is identified by it."""
    settings = SelectionSettings()
    one = sympy.Integer(1)
    chosen = candidate(-0.003 * WZ, 5, 1.000)
    constant = candidate(-0.003 * WZ + 2e-4 * one, 7, 1.000)
    damping = candidate(-0.003 * WZ - 0.005 * U1, 8, 1.000, t=3.0)  # the weak rows' own fit: t 3
    larger = candidate(-0.003 * WZ - 0.005 * U1 + WZ**2, 9, 0.999)
    fits = {frozenset([WZ, one]): 900.0, frozenset([WZ, U1]): 100.0, frozenset([WZ, U1, WZ**2]): 90.0}

    def test(shapes, t=20.0):
        key = frozenset(shapes)
        return verdict(0.2, fits[key], t, len(shapes)) if key in fits else verdict(1e-5, 1e4, t, len(shapes))

    picked, record = specification_pick(chosen, [chosen, constant, damping, larger], settings, 1.0, test)
    assert set(term_shapes_of(picked)) == {WZ, U1}, picked.expression
    assert picked.weakest_t == 20.0 and record["tried"] == 2  # larger: two terms more than the pick
    # a twin of the damping, more complex, that the rows do not support clearly better (chi^2 lower by less
    # than CLEARLY_BETTER_CHI2): the simpler; supported clearly better: the twin
    twin = candidate(-0.003 * WZ - 0.005 * U1**2, 10, 1.000)
    for twin_rss, expected in ((95.0, {WZ, U1}), (90.0, {WZ, U1**2})):
        fits[frozenset([WZ, U1**2])] = twin_rss
        picked, _ = specification_pick(chosen, [chosen, constant, damping, twin], settings, 1.0, test)
        assert set(term_shapes_of(picked)) == expected, (twin_rss, picked.expression)
    # the generalised fit does not pin the term down either: the constant
    picked, _ = specification_pick(chosen, [chosen, constant, damping, larger], settings, 1.0,
                                   lambda shapes: test(shapes, 3.0 if U1 in shapes else 20.0))
    assert set(term_shapes_of(picked)) == {WZ, one}, picked.expression


def term_shapes_of(c: Candidate) -> list[sympy.Expr]:
    """A candidate's additive terms, coefficients dropped."""
    from identification.collinearity import term_shapes

    return term_shapes(c.expression)


def damped_flight(seed: int, seconds: float = 60.0, damping: float = 0.005):
    """A rate wx' = -damping wx + drive (rad/s^2), the drive known, read by a gyro with white noise 0.01 rad/s
    (the parts structure_test takes, as tied_flight's)."""
    rng = np.random.default_rng(seed)
    n = int(seconds / DT)
    t = np.arange(n) * DT
    # rates of a few hundredths of a rad/s wandering slowly, as a hover's: the damping's share of the target
    # is small, and mostly at the low frequencies
    phase = rng.uniform(0, 2 * np.pi)
    slow, fast = 2 * np.pi * 0.02, 2 * np.pi * 0.3
    rate = 0.05 * np.sin(slow * t + phase) + 0.05 * np.sin(fast * t)  # rad/s, the rate the drive gives
    drive = 0.05 * slow * np.cos(slow * t + phase) + 0.05 * fast * np.cos(fast * t) + damping * rate
    w = np.zeros(n + 1)
    w[0] = rate[0]
    for k in range(n):
        w[k + 1] = w[k] + DT * (drive[k] - damping * w[k])
    gyro = w + 0.01 * rng.standard_normal(n + 1)
    X = np.zeros((n, 16))
    X[:, 9] = w[:-1]
    op = weak_rows(t, None, WeakSettings())
    return [(X, np.diff(gyro) / DT - drive, op)], [weak_whitener(op, t, None, STEP_DIFFERENCE)]


def test_a_weak_damping_is_identified_by_the_generalised_fit_not_the_weak_rows_own():
    """A rate damping of -0.005 /s (a rigid body's, small against the moments) on a hover's slowly wandering
    rates: the weak rows' own fit leaves its t ratio below min_t, the generalised fit (the low frequencies,
    where the gyro's differenced noise is small) pins it down, as the specification pick now asks of a
    structure the test passes (generalised_t)."""
    from identification.collinearity import term_t_ratios
    from identification.specification_pick import generalised_t

    wx = PRIMITIVE_SYMBOLS["wx"]
    settings = SelectionSettings()
    for seed in range(3):
        parts, whiteners = damped_flight(seed)
        (X, y, op), w = parts[0], whiteners[0]
        plain_t, _ = term_t_ratios(np.asarray(op @ X[:, 9:10]), op @ y, None, w, offset=False)
        result = structure_test([wx], parts, whiteners)
        assert result is not None
        damping = candidate(float(result.plain[0]) * wx, 3, 1.0, t=float(plain_t[0]))
        assert plain_t[0] < settings.min_t and not terms_identified(damping.weakest_t, 1.0, settings)
        measured = generalised_t(damping, result, [wx])
        assert measured.weakest_t >= 3 * settings.min_t
        assert terms_identified(measured.weakest_t, 1.0, settings)
        assert abs(result.gls[0] + 0.005) < 3 * result.se_gls[0]  # and it is the damping
        assert damping.weakest_t == plain_t[0]  # the candidate itself untouched


def test_the_search_adds_the_term_the_test_asks_for_when_no_candidate_passes():
    """No equally good candidate passes: the specification search walks from the pick over the pool to a
    structure the test does not reject, and takes it only when the pick's rule does (every term identified);
    the model file's record says what it searched."""
    from identification.refit import pool_screen
    from identification.specification_search import SearchSpace

    parts, whiteners = tied_flight(2)
    pool = [WZ, WZ**2, WZ**3, sympy.Integer(1), WZ * ROTOR_SUM]
    settings = SelectionSettings()
    chosen = candidate(-0.003 * WZ, 5, 1.0)
    test = lambda shapes: structure_test(shapes, parts, whiteners)  # noqa: E731
    made = []

    def space(t_ratio: float) -> SearchSpace:
        def make(shapes):
            made.append(frozenset(shapes))
            return candidate(sympy.Add(*shapes), 3 * len(shapes), 1.0, t=t_ratio)
        return SearchSpace(lambda start: pool_screen(pool, parts, whiteners, keep=start), make, 2)

    picked, record = specification_pick(chosen, [chosen], settings, 1.0, test, space(10.0))
    assert set(term for term in picked.expression.args) == {WZ, WZ * ROTOR_SUM}
    assert record["searched"]["pool"] == len(pool) and record["picked"]["p_value"] >= 0.01
    assert "specification search" in specification_line("dwz", record)
    # the same structure, but its terms not identified (by either fit, as the pick's rule asks of a structure
    # the test passes: generalised_t): the pick stays
    made.clear()

    def unidentified(shapes):
        result = test(shapes)
        return None if result is None else dataclasses.replace(result, se_plain=np.abs(result.plain),
                                                                se_gls=np.abs(result.gls))

    stays, record = specification_pick(chosen, [chosen], settings, 1.0, unidentified, space(1.0))
    assert stays is chosen and "picked" not in record and made
    assert "nor the specification search" in specification_line("dwz", record)
    # and where its walk went: first the term the test asks for, which the rule did not take
    walked = record["searched"]["walked_to"]
    assert walked["added"][0] == str(WZ * ROTOR_SUM) and len(walked["added"]) == 2
    assert f"its walk, the best fit at each step, added {WZ * ROTOR_SUM}" in specification_line("dwz", record)
    # a pool without the term: nothing passes, and the record says where the walk ended and its p
    lacking = SearchSpace(lambda start: pool_screen(pool[:4], parts, whiteners, keep=start),
                          lambda shapes: None, 2)
    stays, record = specification_pick(chosen, [chosen], settings, 1.0, test, lacking)
    walked = record["searched"]["walked_to"]
    assert stays is chosen and record["searched"]["checked"] == 0
    assert walked["p_value"] < 0.01 and len(walked["added"]) == 2
    assert str(WZ * ROTOR_SUM) not in walked["added"]
    assert "its walk, the best fit at each step, added " in specification_line("dwz", record)


def test_the_search_starts_from_the_picks_terms_when_the_pool_holds_their_equals():
    """A term of the pick whose column equals an earlier pool term's on these rows (wz u2 and wz u1 when the
    four rotors turn alike) stays in the search's pool in that term's place, so the search still walks from
    the pick: here to the term the test asks for (wz beside wz u2, the true structure on these rows)."""
    from identification.refit import pool_screen
    from identification.specification_search import SearchSpace

    parts, whiteners = tied_flight(2)
    u2 = PRIMITIVE_SYMBOLS["u2"]
    pool = [WZ * U1, WZ**2, WZ, WZ * u2]
    screens = []

    def screen(start):
        screens.append(pool_screen(pool, parts, whiteners, keep=start))
        return screens[-1]

    def make(shapes):
        return candidate(sympy.Add(*shapes), 3 * len(shapes), 1.0)

    test = lambda shapes: structure_test(shapes, parts, whiteners)  # noqa: E731
    chosen = candidate(-7e-4 * WZ * u2, 5, 1.0)
    picked, record = specification_pick(chosen, [chosen], SelectionSettings(), 1.0, test,
                                        SearchSpace(screen, make, 2))
    assert set(picked.expression.args) == {WZ, WZ * u2}, picked.expression
    assert screens[0].terms == [WZ**2, WZ, WZ * u2]  # wz u1 gave way to the pick's equal term
    assert record["searched"]["checked"] >= 1
    # without the start, the first of two equal columns stays
    assert pool_screen(pool, parts, whiteners).terms == [WZ * U1, WZ**2, WZ]


def test_the_search_pool_holds_each_products_factors():
    """A flight's candidates may hold a term only beside a factor that barely varies (wy (u1 + .. + u4) for
    wy): the search's pool adds each product less one factor, once, after the terms themselves."""
    from identification.specification_search import with_factors

    wx, wy = PRIMITIVE_SYMBOLS["wx"], PRIMITIVE_SYMBOLS["wy"]
    pool = with_factors([WZ**2 * sympy.Abs(wx), wy * ROTOR_SUM, WZ, sympy.Integer(1), WZ**2])
    assert pool[:5] == [WZ**2 * sympy.Abs(wx), wy * ROTOR_SUM, WZ, sympy.Integer(1), WZ**2]
    assert set(pool[5:]) == {sympy.Abs(wx), wy, ROTOR_SUM} and len(pool) == 8


def test_the_search_reduces_a_passing_structure_to_what_the_rule_takes():
    """General to specific: a structure the test passes but whose terms the rule does not take (the true
    term beside the pick's stand-ins, which share its column) loses one term at a time, the one whose
    removal fits least worse, while the test still passes and it fits at least as well as the pick; the
    search takes the first the rule takes. Here the pick holds two stand-ins beside wz, so no single move
    reaches the true structure, and every structure on the way passes the test."""
    from identification.refit import pool_screen
    from identification.specification_search import SearchSpace, reduced

    parts, whiteners = tied_flight(2)
    pool = [WZ, WZ**2, WZ**3, sympy.Integer(1), WZ * ROTOR_SUM]
    stand_ins = {WZ**2, WZ**3}
    test = lambda shapes: structure_test(shapes, parts, whiteners)  # noqa: E731

    def make(shapes):  # the rule: a stand-in beside the true term leaves neither identified
        return candidate(sympy.Add(*shapes), 3 * len(shapes), 1.0, t=1.0 if stand_ins & set(shapes) else 10.0)

    def space() -> SearchSpace:
        return SearchSpace(lambda start: pool_screen(pool, parts, whiteners, keep=start), make, 2)

    chosen = candidate(-0.003 * WZ + 1e-5 * WZ**2 + 1e-6 * WZ**3, 9, 1.0)
    picked, record = specification_pick(chosen, [chosen], SelectionSettings(), 1.0, test, space())
    assert set(picked.expression.args) == {WZ, WZ * ROTOR_SUM}, picked.expression
    assert record["rejected"]["p_value"] < 0.01 <= record["picked"]["p_value"]
    # each reduction passes the test and fits at least as well as where it started
    screen = pool_screen(pool, parts, whiteners)
    full = [0, 1, 2, 4]
    start_p, start_fit = screen.p_value([0, 1, 2])
    steps = list(reduced(full, screen, start_fit))
    assert start_p < 0.01 and steps and [len(s) for s in steps] == list(range(3, 3 - len(steps), -1))
    for s in steps:
        p, rss = screen.p_value(s)
        assert p >= 0.01 and rss <= start_fit
    assert {pool[i] for i in steps[1]} == {WZ, WZ * ROTOR_SUM}
    # nothing fits as well as the start: no reduction
    assert list(reduced(full, screen, 0.0)) == []
