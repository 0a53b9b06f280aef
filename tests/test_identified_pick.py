"""The pick keeps to terms the fit rows identify: collinearity.weakest_t and pareto.select's min_t rule."""

from __future__ import annotations

import numpy as np
import pytest
import sympy

from identification.candidate import Candidate
from identification.collinearity import (
    effective_rows,
    offset_t_ratio,
    term_identification,
    term_t_ratios,
    weakest_t,
)
from identification.engine_settings import SelectionSettings
from identification.pareto import select, terms_identified
from identification.weak_noise import Whitener


def _rows(seed: int, n: int = 4000) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    a = rng.standard_normal(n)
    b = rng.standard_normal(n)
    twin = a + 1e-4 * rng.standard_normal(n)  # a near-copy of a (VIF ~1e8)
    y = 2.0 * a + 3.0 * b + 0.01 * rng.standard_normal(n)
    return a, b, twin, y


def test_weakest_t_separates_identified_terms_from_tied_ones():
    a, b, twin, y = _rows(1)
    ones = np.ones_like(a)
    good = weakest_t(np.column_stack([ones, a, b]), y)
    tied = weakest_t(np.column_stack([ones, a, b, twin]), y)
    assert good > 1000  # 2 / (0.01 / sqrt(4000)) ~ 1e4
    assert tied < 5  # a and its twin share one coefficient: neither is told from zero
    exact = weakest_t(np.column_stack([a, b]), 2.0 * a + 3.0 * b)
    assert exact > 1e6  # noise-free data: every term identified


def test_an_autocorrelated_residual_counts_fewer_independent_rows():
    rng = np.random.default_rng(2)
    n = 4000
    a = rng.standard_normal(n)
    white = 0.05 * rng.standard_normal(n)
    slow = np.convolve(white, np.ones(40) / np.sqrt(40), mode="same")  # same spread, correlated over 40 rows
    t_white = weakest_t(a[:, None], 0.01 * a + white)
    t_slow = weakest_t(a[:, None], 0.01 * a + slow)
    assert t_slow < t_white / 3  # lag-1 correlation ~0.975: ~80 times fewer effective rows


def _candidate(size: int, holdout: float, t: float | None) -> Candidate:
    return Candidate(sympy.Symbol(f"c{size}"), size, holdout, "test", holdout_loss=holdout, weakest_t=t)


def test_the_pick_sets_aside_unidentified_candidates_while_one_passes():
    settings = SelectionSettings()
    tied = _candidate(30, 0.010, 0.5)  # the lowest pick loss, built from tied terms
    sound = _candidate(12, 0.015, 40.0)
    unmeasured = _candidate(40, 0.020, None)  # an engine that does not measure t: passes
    assert select([tied, sound, unmeasured], settings) is sound
    assert select([tied], settings) is tied  # nothing passes: the pick falls back to every candidate
    looser = SelectionSettings(min_t=0.1)
    assert select([tied, sound], looser) is tied


def test_the_pick_sets_aside_terms_the_flight_barely_separates():
    # closed loop: a signed rotor combination written as three tied terms fits best but the flight hardly
    # separates them (VIF above max_vif); with too little evidence for that collinearity (t below
    # min_t VIF / max_vif) a candidate of separable terms is picked instead
    settings = SelectionSettings()
    tied = _candidate(30, 0.010, 19.9)
    tied.largest_vif = 400.0  # asks for t >= 5 x 4 = 20
    sound = _candidate(12, 0.013, 1e9)
    sound.largest_vif = 4.0
    assert select([tied, sound], settings) is sound
    tied.weakest_t = 20.1
    assert select([tied, sound], settings) is tied
    assert select([tied, sound], SelectionSettings(max_vif=1000.0)) is tied


def test_noise_free_tied_terms_pinned_down_pass_unless_the_vif_is_capped():
    # noise-free closed loop: the tied terms fit (t ~1e9), pinned down far beyond what their VIF asks; the
    # hard cap (vif_rule "cap", the rule before session 63) sets them aside all the same
    tied = _candidate(30, 0.010, 1e9)
    tied.largest_vif = 101.5
    sound = _candidate(12, 0.013, 1e9)
    sound.largest_vif = 4.0
    assert select([tied, sound], SelectionSettings()) is tied
    assert select([tied, sound], SelectionSettings(vif_rule="cap")) is sound
    assert not terms_identified(None, 101.5, SelectionSettings())  # no t ratio: the cap stands
    assert terms_identified(None, 99.0, SelectionSettings())
    assert not terms_identified(4.9, 1.0, SelectionSettings())


def test_term_identification_reports_the_largest_vif():
    a, b, twin, y = _rows(4)
    t, vif = term_identification(np.column_stack([a, b]), y)
    t_tied, vif_tied = term_identification(np.column_stack([a, b, twin]), y)
    assert vif < 2.0 < 100.0 < vif_tied
    assert t == weakest_t(np.column_stack([a, b]), y)


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_weakest_t_ignores_rows_that_are_not_finite(bad):
    a, b, _, y = _rows(3)
    cols = np.column_stack([a, b])
    cols[5, 0] = bad
    assert weakest_t(cols, y) > 1000


def test_term_t_ratios_name_the_term_below_the_noise():
    """Per-term t ratios, column by column: a term 1000x below the noise has t < 5 while its neighbours are
    pinned down; a constant column gets NaN; the summary (term_identification) is their minimum."""
    rng = np.random.default_rng(3)
    n = 4000
    a, b, c = rng.standard_normal((3, n))
    y = 2.0 * a - 1.0 * b + 1e-4 * c + 0.3 + 0.1 * rng.standard_normal(n)
    cols = np.column_stack([np.ones(n), a, b, c])
    t, vif = term_t_ratios(cols, y)
    assert np.isnan(t[0]) and np.isnan(vif[0])
    assert t[1] > 100 and t[2] > 100 and t[3] < 5
    assert np.allclose(vif[1:], 1.0, atol=0.01)
    assert term_identification(cols, y)[0] == pytest.approx(t[3])


def test_a_term_that_stands_for_an_offset_is_not_identified():
    """A model without a constant: a nearly constant term (|v_b|^2 on a fast flight, 21 % about its mean)
    that holds a sensor's bias fits with a large t on its own, but is measured beside an offset, where its t
    is that of its variation; the same term with a real effect of that variation stays identified."""
    rng = np.random.default_rng(5)
    n = 4000
    t_s = np.arange(n) / 250.0
    speed2 = 341.0 * (1.0 + 0.21 * np.sin(2 * np.pi * t_s / 7.0))  # m^2/s^2
    drag = rng.standard_normal(n)
    noise = 0.02 * rng.standard_normal(n)
    cols = np.column_stack([speed2, drag])
    stated = Whitener(np.full((1, n), 0.02), 0)  # the rows' stated noise: white, 0.02 m/s^2
    bias = -0.015 + 2.0 * drag + noise  # an offset and the drag, nothing of speed2
    t_offset, _ = term_t_ratios(cols, bias, noise=stated)
    t_alone, _ = term_t_ratios(cols, bias, noise=stated, offset=False)
    assert t_alone[0] > 20 and t_offset[0] < 5  # without the offset it carries the bias
    assert t_offset[1] > 1000
    assert term_identification(cols, bias, noise=stated)[0] == pytest.approx(t_offset[0])
    assert term_t_ratios(cols, bias)[0][0] < 5  # the AR(1) standard errors: an offset's already
    real = 2e-4 * speed2 + 2.0 * drag + noise  # varies by 0.014 m/s^2 with speed2: seen beside an offset
    assert term_t_ratios(cols, real, noise=stated)[0][0] > 20
    with_constant = np.column_stack([np.ones(n), cols])  # a constant among the columns: measured as given
    as_given = term_t_ratios(with_constant, bias, offset=False)[0]
    assert np.array_equal(term_t_ratios(with_constant, bias)[0], as_given, equal_nan=True)


def test_the_pick_measures_only_the_candidates_its_answer_depends_on():
    # an engine's candidates defer their t ratio and VIF (Candidate.measure: a pass over the fit rows each);
    # the pick tries them lowest loss first, so it measures a few and picks what measuring all would pick
    rng = np.random.default_rng(5)
    settings = SelectionSettings()
    specs = [(int(rng.integers(3, 40)), float(rng.uniform(0.01, 0.05)), float(rng.choice([0.5, 50.0])))
             for _ in range(200)]
    calls: list[int] = []

    def deferred(k: int, t: float) -> Candidate:
        c = _candidate(specs[k][0], specs[k][1], None)
        c.measure = lambda: (calls.append(k), (t, 2.0))[1]
        return c

    lazy = [deferred(k, t) for k, (_, _, t) in enumerate(specs)]
    eager = [_candidate(size, loss, t) for size, loss, t in specs]
    for c in eager:
        c.largest_vif = 2.0
    picked = select(lazy, settings)
    assert lazy.index(picked) == eager.index(select(eager, settings))
    assert picked.weakest_t >= settings.min_t and picked.measure is None
    assert 0 < len(calls) < 50 and len(set(calls)) == len(calls)  # each measured at most once
    select(lazy, settings)
    assert len(set(calls)) == len(calls)


def test_offset_t_ratio_measures_a_constant_beside_the_terms():
    """A constant offset's t: its size over its standard error on white noise, and small where a term that
    barely varies can stand for it (a hover's rotor speeds for an accelerometer's bias)."""
    rng = np.random.default_rng(3)
    n = 10_000
    x = rng.standard_normal(n)
    y = 0.1 + 2.0 * x + rng.standard_normal(n)  # se of the offset 1/sqrt(n) = 0.01: t ~ 10
    assert 7.0 < offset_t_ratio(x[:, None], y) < 13.0
    near_constant = 5.0 + 1e-3 * rng.standard_normal(n)
    y2 = 0.1 + 2.0 * near_constant + rng.standard_normal(n)
    assert offset_t_ratio(near_constant[:, None], y2) < SelectionSettings().min_t  # se ~50: chance level
    assert offset_t_ratio(x[:, None], 0.1 + 2.0 * x) > 1e9  # exact but for rounding


def test_term_t_ratios_are_the_textbook_ones_on_correlated_columns():
    """The t ratios and VIFs of correlated columns beside an offset are |c_j| / (s sqrt(VIF_j) / sqrt(N_eff))
    with VIF_j the diagonal of the inverse correlation matrix, whichever way term_t_ratios computes them
    (one QR factorisation, or a regression per column for nearly tied ones), and a column tied exactly to the
    others has an infinite VIF and t 0."""
    rng = np.random.default_rng(11)
    n = 3000
    base = rng.standard_normal((n, 4))
    cols = base @ np.array([[1.0, 0.9, 0.0, 0.2], [0.0, 0.4, 0.3, 0.0], [0.0, 0.0, 1.0, 0.9],
                            [0.0, 0.0, 0.0, 0.3]]) + np.array([5.0, -2.0, 0.0, 1.0])
    y = cols @ np.array([0.5, -1.0, 2e-3, 0.7]) + 1.5 + 0.05 * rng.standard_normal(n)
    t, vif = term_t_ratios(cols, y)
    z = (cols - cols.mean(axis=0)) / cols.std(axis=0)
    expected_vif = np.diag(np.linalg.inv(z.T @ z / n))
    coef, *_ = np.linalg.lstsq(np.column_stack([np.ones(n), z]), y, rcond=None)
    resid = y - np.column_stack([np.ones(n), z]) @ coef
    s = np.sqrt(np.mean(resid**2))
    expected_t = np.abs(coef[1:]) / (s * np.sqrt(expected_vif) / np.sqrt(effective_rows(resid)))
    assert vif == pytest.approx(expected_vif, rel=1e-9)
    assert t == pytest.approx(expected_t, rel=1e-9)
    assert t[2] < 5 < t.min(initial=np.inf, where=np.arange(4) != 2)
    tied = np.column_stack([cols, cols[:, 0] - 2.0 * cols[:, 2]])
    t_tied, vif_tied = term_t_ratios(tied, y)
    assert np.isinf(vif_tied).any() and np.min(t_tied) == 0.0
