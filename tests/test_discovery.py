"""The discovery engine finds effects its library never held, from primitives (small seeded synthetic data).

Each effect is written down in identification.effects_physics; none is a ready-made column: the engine only
gets the body-frame primitives (ub vb wb wx wy wz u1..u4 h) and its operators.
"""

from __future__ import annotations

import numpy as np
import pytest
import sympy

from identification.body_frame import BODY_TARGET_NAMES, body_targets
from identification.discovery import DiscoveryEngine
from identification.effects_physics import Effects, body_expressions, flight_rows
from identification.engine import split_holdout
from identification.engine_settings import DiscoverySettings, SelectionSettings
from identification.metrics import r2
from identification.pareto import attach_holdout, select
from identification.validate import expression_terms

VEHICLE = "fang-chen-buaa"
GRAVITY = 9.8  # the vehicle's


def _fit(
    effects: Effects, target: str, seed: int = 0, n: int = 1500, settings: DiscoverySettings | None = None,
    budget: int = 2,
):
    xi, u, ned = flight_rows(n, seed, VEHICLE, effects)
    y = body_targets(xi, ned, GRAVITY)[:, BODY_TARGET_NAMES.index(target)]
    Xt, yt, Xh, yh = split_holdout(np.hstack([xi, u]), y)
    engine = DiscoveryEngine(settings)
    cands = engine.fit(Xt, yt, target, budget, seed, "absolute", None, (Xh, yh))
    attach_holdout(cands, Xh, yh, "absolute")
    best = select(cands, SelectionSettings(), float(np.std(yh)))
    return best, engine, cands, (Xh, yh)


def _assert_same_terms(found: sympy.Expr, truth: sympy.Expr, rel: float = 1e-3) -> None:
    got, ref = expression_terms(found), expression_terms(truth)
    assert set(got) == set(ref), f"missing {set(ref) - set(got)}, extra {set(got) - set(ref)}"
    for term, c in ref.items():
        assert abs(got[term] - c) <= rel * abs(c), (term, got[term], c)


@pytest.mark.parametrize(
    ("effect", "effects", "target", "must_have"),
    [
        ("rotor drag sum(u_i) ub", Effects(rotor_drag=2e-4), "fx", ["u1*ub", "u4*ub"]),
        ("frame drag |v| v", Effects(frame_drag=0.02), "fy", ["vb*sqrt(ub**2 + vb**2 + wb**2)"]),
        ("ground effect u_i^2 / h^2", Effects(ground_effect=0.08), "fz", ["u1**2/h**2", "u3**2/h**2"]),
        ("linear thrust", Effects(linear_thrust=4e-3, quadratic_thrust=False), "fz", ["u1", "u2"]),
        ("weak rotor 3 (thrust)", Effects(rotor_scale=(1.0, 1.0, 0.92, 1.0)), "fz", ["u3**2"]),
        ("weak rotor 3 (roll torque)", Effects(rotor_scale=(1.0, 1.0, 0.92, 1.0)), "dwx", ["u3**2"]),
        ("inertia couplings, gyroscopic terms", Effects(), "dwx", ["wy*wz", "u1*wy"]),
        ("inertia couplings", Effects(), "dwy", ["wx*wz", "u2*wx"]),
        ("inertia couplings", Effects(), "dwz", ["wx*wy"]),
    ],
)
def test_finds_the_effect_from_primitives(effect, effects, target, must_have):
    best, engine, _, (Xh, yh) = _fit(effects, target)
    truth = body_expressions(VEHICLE, effects)[target]
    _assert_same_terms(best.expression, truth)  # every true term, no other, coefficients within 0.1%
    names = {str(k) for k in expression_terms(best.expression)}
    assert set(must_have) <= names, effect
    assert r2(yh, best.evaluate(Xh)) > 0.999999


def test_weak_rotor_coefficient_differs_from_the_others():
    best, *_ = _fit(Effects(rotor_scale=(1.0, 1.0, 0.92, 1.0)), "fz")
    c = {str(k): v for k, v in expression_terms(best.expression).items()}
    assert c["u3**2"] / c["u1**2"] == pytest.approx(0.92, rel=1e-3)
    assert c["u2**2"] / c["u1**2"] == pytest.approx(1.0, rel=1e-3)


def test_units_pruning_never_builds_sin_of_a_length_or_unlike_sums():
    from identification.body_frame import PRIMITIVES, primitive_matrix
    from identification.feature_space import combine_units, grow_unary

    prims = ("ub", "vb", "wb", "h", "phi", "theta")
    xi, u, _ = flight_rows(200, 1, VEHICLE)
    P = primitive_matrix(np.hstack([xi, u]), prims)
    space = grow_unary(prims, ("pow", "abs", "inv", "norm", "sincos"), P)
    built = {str(e) for e in space.expressions}
    assert {"sin(phi)", "cos(theta)", "1/h", "sqrt(ub**2 + vb**2 + wb**2)"} <= built
    assert not any(s.startswith(("sin(h", "cos(h", "sin(ub", "cos(wb")) for s in built)
    assert space.pruned["sin of a dimensional argument"] == 4  # ub, vb, wb, h
    assert space.pruned["cos of a dimensional argument"] == 4
    # adding unlike units is invalid (a velocity and a length; a rate and a velocity); like units are fine
    assert combine_units("add", PRIMITIVES["ub"].unit, PRIMITIVES["h"].unit) is None
    assert combine_units("norm", PRIMITIVES["wx"].unit, PRIMITIVES["ub"].unit) is None
    assert combine_units("add", PRIMITIVES["u1"].unit, PRIMITIVES["wz"].unit) == (0, -1)
    assert combine_units("sin", PRIMITIVES["phi"].unit) == (0, 0)
    # products carry their units: rotor drag sum(u) ub is (1/s)(m/s) = m/s^2, an acceleration's unit
    assert combine_units("mul", PRIMITIVES["u1"].unit, PRIMITIVES["ub"].unit) == (1, -2)


def test_abs_only_for_a_quantity_that_takes_both_signs():
    from identification.feature_space import grow_unary

    rng = np.random.default_rng(3)
    both = rng.uniform(-1.0, 1.0, 500)
    one_sided = rng.uniform(0.0, 1.2, 500)
    one_sided[::50] = -1e-3  # a yaw rate that keeps its sign but for a few samples near zero
    P = np.column_stack([both, one_sided])
    space = grow_unary(("wx", "wz"), ("abs",), P)
    built = {str(e) for e in space.expressions}
    assert "Abs(wx)" in built and "Abs(wz)" not in built  # |wz| = wz on all but 10 rows: not separable
    assert space.pruned["abs of a quantity that keeps its sign in the data"] == 1
    # a real excursion to the other side (here 30 % of the larger side) keeps |x|
    P[::50, 1] = -0.36
    assert "Abs(wz)" in {str(e) for e in grow_unary(("wx", "wz"), ("abs",), P).expressions}


def test_genetic_programming_always_runs_and_the_same_seed_gives_the_same_model():
    settings = DiscoverySettings(rounds=2, operon_population=60)
    runs = []
    for _ in range(2):
        best, engine, cands, _ = _fit(Effects(rotor_drag=2e-4), "fx", seed=3, n=800, settings=settings,
                                      budget=4)
        assert "operon" in engine.timings  # no threshold gates it off, even on an exact sparse fit
        assert engine.stats["operon_generations"] == 4
        assert engine.stats["operon_front"] >= 1  # (here the residual is ~0: its front adds nothing new)
        runs.append([str(c.expression) for c in cands] + [str(best.expression)])
    assert runs[0] == runs[1]


def test_unknown_primitive_or_operator_is_a_user_error():
    from bridge.errors import UserError

    with pytest.raises(UserError, match="unknown primitive 'airspeed'"):
        DiscoveryEngine(DiscoverySettings(primitives=("ub", "airspeed")))
    with pytest.raises(UserError, match="unknown operator 'exp'"):
        DiscoveryEngine(DiscoverySettings(operators=("mul", "exp")))


def test_rounds_stop_once_the_pick_stops_improving_and_more_rounds_change_nothing_exact():
    # exact data: a round or two reach the true dwz; a pick exact to rounding ends the search at once (no
    # round can be better), whatever the patience: counts, not time, long before the `rounds` cap
    truth = body_expressions(VEHICLE, Effects())["dwz"]
    picks, rounds = [], []
    for patience in (1, 8):
        settings = DiscoverySettings(rounds=8, patience=patience, screen=20)
        best, engine, _, _ = _fit(Effects(), "dwz", seed=4, n=800, settings=settings, budget=0)
        _assert_same_terms(best.expression, truth)
        picks.append(str(best.expression))
        rounds.append(engine.stats["rounds"])
    assert rounds[0] <= 3 and rounds[1] == rounds[0]
    assert picks[0] == picks[1]


def test_patience_rounds_without_a_better_pick_end_the_search_on_noisy_data():
    # with noise no pick is exact: `patience` rounds in a row without a better held-out pick end the search,
    # and a larger patience runs more rounds (here for nothing: the same model)
    xi, u, ned = flight_rows(800, 4, VEHICLE, Effects())
    y = body_targets(xi, ned, GRAVITY)[:, BODY_TARGET_NAMES.index("dwz")]
    y = y + np.random.default_rng(4).normal(0.0, 0.01 * np.std(y), len(y))
    Xt, yt, Xh, yh = split_holdout(np.hstack([xi, u]), y)
    rounds, picks = [], []
    for patience in (1, 8):
        engine = DiscoveryEngine(DiscoverySettings(rounds=8, patience=patience, screen=20))
        cands = engine.fit(Xt, yt, "dwz", 0, 4, "absolute", None, (Xh, yh))
        picks.append(str(select(cands, SelectionSettings(), float(np.std(yh))).expression))
        rounds.append(engine.stats["rounds"])
    assert rounds[0] <= 3 and rounds[1] > rounds[0]
    assert picks[0] == picks[1]


def test_the_sparse_paths_grow_while_the_pick_reaches_their_end():
    # rotor drag, a weak rotor 3 and frame drag: dwz holds more features than a path of max_terms = 2
    # reaches; the paths stopped there give a wrong model, grown (max_terms_limit) the true one
    effects = Effects(rotor_drag=2e-4, rotor_scale=(1.0, 1.0, 0.92, 1.0), frame_drag=0.02)
    truth = body_expressions(VEHICLE, effects)["dwz"]
    capped, engine, _, _ = _fit(effects, "dwz", settings=DiscoverySettings(max_terms=2, max_terms_limit=2),
                                budget=0)
    assert "path_terms" not in engine.stats
    assert set(expression_terms(capped.expression)) != set(expression_terms(truth))
    grown, engine, _, _ = _fit(effects, "dwz", settings=DiscoverySettings(max_terms=2, max_terms_limit=12),
                               budget=0)
    assert 2 < engine.stats["path_terms"] <= 12
    _assert_same_terms(grown.expression, truth)


@pytest.mark.parametrize("rounds", [1, 2])
def test_the_rounds_never_exceed_their_budget(rounds):
    # noisy targets and a patience longer than the budget: only the budget stops the rounds (a count, so the
    # same on any machine); the hub law's extra rounds are not taken on a flight far from the ground
    xi, u, ned = flight_rows(1500, 3, "fang-chen-buaa", Effects(rotor_drag=0.02))
    y = body_targets(xi, ned, 9.8)[:, BODY_TARGET_NAMES.index("dwx")]
    y = y + np.random.default_rng(4).normal(0.0, 0.05 * np.std(y), len(y))
    Xt, yt, Xh, yh = split_holdout(np.hstack([xi, u]), y)
    engine = DiscoveryEngine(DiscoverySettings(rounds=rounds, patience=10, screen=5))
    engine.fit(Xt, yt, "dwx", 0, 0, "absolute", None, (Xh, yh))
    assert engine.stats["rounds"] == rounds, engine.stats
