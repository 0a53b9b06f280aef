"""Discovery rules for terms a flight barely separates (small seeded synthetic data, issue 12).

- projected screening: a true term nearly collinear with a picked one (wz*(u1+..+u4) beside wz when the rotor
  sum varies by a few %) is screened by what it adds to the model, so it comes in;
- a positive primitive that barely varies (the height within +-0.5 %) gives no features: h*vb^2 cannot be
  told from vb^2, and the simpler one wins;
- the gravity left by a removed g other than the data's is a lone term along R^T e_z of fx, fy, fz only
  (the primitives gbx gby gbz, opt-in: not in the defaults), and it cancels exactly in the composed x'', y'',
  z''; `quadsr identify --gravity G` gives the data's g instead.
"""

from __future__ import annotations

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS, PRIMITIVES, compose_ned, primitive_matrix
from identification.discovery import DiscoveryEngine, _projected_scores, _screen_scores, _standardized
from identification.engine import split_holdout
from identification.engine_settings import DiscoverySettings, SelectionSettings
from identification.feature_space import grow_unary, lone_features
from identification.model_file import Model
from identification.pareto import attach_holdout, select
from identification.true_model import random_states
from identification.validate import expression_terms

P = PRIMITIVE_SYMBOLS
WITH_GRAVITY = (*DiscoverySettings().primitives, "gbx", "gby", "gbz")  # the lone gravity terms, opt-in


def _rows(n: int, seed: int, hover: float = 600.0, spread: float = 0.03, height=(5.0, 50.0)):
    """Random states, the rotor speeds near hover (relative spread `spread`), the height in `height` (m)."""
    xi, u = random_states(n, seed)
    rng = np.random.default_rng(seed + 1)
    u[:] = hover * (1.0 + rng.uniform(-spread, spread, (n, 4)))
    xi[:, 2] = -rng.uniform(height[0], height[1], n)
    return np.hstack([xi, u])


def _values(expr: sympy.Expr, X: np.ndarray) -> np.ndarray:
    names = tuple(PRIMITIVES)
    fn = sympy.lambdify([P[n] for n in names], expr, modules="numpy")
    return np.broadcast_to(np.asarray(fn(*primitive_matrix(X, names).T), float), (len(X),))


def _pick(X: np.ndarray, y: np.ndarray, target: str, settings: DiscoverySettings | None = None):
    Xt, yt, Xh, yh = split_holdout(X, y)
    engine = DiscoveryEngine(settings or DiscoverySettings(rounds=6))
    cands = engine.fit(Xt, yt, target, 0, 0, "absolute", None, (Xh, yh))
    attach_holdout(cands, Xh, yh, "absolute")
    return select(cands, SelectionSettings(), float(np.std(yh))), engine


def _assert_terms(found: sympy.Expr, truth: sympy.Expr, rel: float = 1e-6) -> None:
    got, ref = expression_terms(found), expression_terms(truth)
    assert set(got) == set(ref), f"missing {set(ref) - set(got)}, extra {set(got) - set(ref)}"
    for term, c in ref.items():
        assert abs(got[term] - c) <= rel * abs(c), (term, got[term], c)


def test_projected_screening_ranks_a_term_by_what_it_adds_to_the_model():
    rng = np.random.default_rng(0)
    n = 2000
    wz, s = rng.normal(size=n), 1.0 + 0.05 * rng.uniform(-1, 1, n)  # s: a rotor sum varying by 5 %
    junk = rng.normal(size=(n, 30))
    F = np.column_stack([wz, wz * s, junk])
    y = -0.5 * wz * s
    r = y - wz * np.dot(wz, y) / np.dot(wz, wz)  # the residual of the model "c wz"
    plain = _screen_scores(_standardized(F), r)
    projected = _projected_scores(_standardized(F), r, wz[:, None])
    assert np.argmax(projected) == 1 and projected[1] > 0.99  # what wz*s adds explains the residual
    assert plain[1] < 0.2 and np.argmax(plain[1:]) != 0  # plainly it ranks by its part along wz: low
    assert projected[0] == -np.inf  # the model's own column adds nothing


def test_finds_the_rotor_sum_product_beside_a_near_constant_rotor_sum():
    # dwz: a large yaw torque and rotor-drag moment, and a small c wz (u1+u2+u3+u4) with the rotor sum
    # varying by 3 %: once wz is picked for it, plain screening ranks the product by its part along wz
    # (nothing left) and picks c' wz for good (measured: -0.048 wz); projected screening brings it in
    X = _rows(3000, 1)
    truth = (2.0e-3 * P["ub"] * (P["u1"] - P["u2"] - P["u3"] + P["u4"])
             + 1.9e-5 * (P["u1"] ** 2 + P["u2"] ** 2 - P["u3"] ** 2 - P["u4"] ** 2)
             - 2.0e-5 * P["wz"] * (P["u1"] + P["u2"] + P["u3"] + P["u4"]))
    best, _ = _pick(X, _values(truth, X), "dwz", DiscoverySettings(rounds=6, screen=10))
    _assert_terms(best.expression, sympy.expand(truth))


def test_a_height_that_barely_varies_gives_no_features_and_the_simpler_term_wins():
    truth = -0.027 * P["vb"] ** 2 - 1.1e-5 * (P["u1"] ** 2 + P["u2"] ** 2 + P["u3"] ** 2 + P["u4"] ** 2)
    X = _rows(3000, 2, height=(9.95, 10.05))  # 10 m +- 0.5 %
    names = ("vb", "u1", "h")
    space = grow_unary(names, ("pow", "inv"), primitive_matrix(X, names), min_spread=0.01)
    assert not any(P["h"] in e.free_symbols for e in space.expressions)
    assert any(k.startswith("h: barely varies") for k in space.pruned)
    best, engine = _pick(X, _values(truth, X), "fz")
    _assert_terms(best.expression, sympy.expand(truth))
    assert any(k.startswith("h: barely varies") for k in engine.stats["pruned"])
    assert any(n.startswith("h: barely varies") for n in engine.notes)  # identify prints and records it
    # a height that varies (5-50 m) keeps its features
    X = _rows(500, 3)
    space = grow_unary(names, ("pow", "inv"), primitive_matrix(X, names), min_spread=0.01)
    assert {"h", "1/h"} <= {str(e) for e in space.expressions}


def test_gravity_left_by_another_g_is_learned_as_a_lone_term_and_cancels_in_the_composition():
    X = _rows(3000, 4)
    dg = 9.81 - 9.80665  # RotorPy's g against the standard one removed
    truth = -1.1e-5 * (P["u1"] ** 2 + P["u2"] ** 2 + P["u3"] ** 2 + P["u4"] ** 2) - 0.03 * P["ub"] ** 2
    settings = DiscoverySettings(rounds=6, primitives=WITH_GRAVITY)
    best, engine = _pick(X, _values(truth + dg * P["gbz"], X), "fz", settings)
    _assert_terms(best.expression, sympy.expand(truth + dg * P["gbz"]))
    # each lone term belongs to its own force target only: never offered to another target, never multiplied
    space = engine.build_space(X)
    assert sorted(lone_features(space).values()) == ["fx", "fy", "fz"]
    assert not any(len(e.free_symbols & {P["gbx"], P["gby"], P["gbz"]}) and not e.is_Symbol
                   for e in space.expressions)
    best_dwx, _ = _pick(X, _values(truth * 0.1 + 0.004 * P["gbx"], X), "dwx", settings)
    assert not best_dwx.expression.free_symbols & {P["gbx"], P["gby"], P["gbz"]}
    # R f_b + g e_z with f_b = dg R^T e_z: exactly (0, 0, g + dg) whatever the attitude
    composed = Model(compose_ned({"fx": dg * P["gbx"], "fy": dg * P["gby"], "fz": dg * P["gbz"]}, 9.80665))
    acc = np.atleast_2d(composed.evaluate(X[:50, :12], X[:50, 12:]))
    assert np.allclose(acc[:, 0], 0.0, atol=1e-12) and np.allclose(acc[:, 1], 0.0, atol=1e-12)
    assert np.allclose(acc[:, 2], 9.81, atol=1e-12)


def test_a_genetic_programming_product_comes_back_as_its_terms_refit_and_pruned():
    # ub*wx*wz is a product of three primitives: no rung-2 feature holds it, the GP on the sparse model's
    # residual finds it; its terms then join the picked model's features in one more sparse fit, so the pick
    # is the exact sum of the true terms with least-squares coefficients, not "model + opaque GP tree"
    truth = -2e-4 * P["ub"] * (P["u1"] + P["u2"] + P["u3"] + P["u4"]) + 0.05 * P["ub"] * P["wx"] * P["wz"]
    X = _rows(2000, 5, spread=0.5)
    Xt, yt, Xh, yh = split_holdout(X, _values(truth, X))
    engine = DiscoveryEngine(DiscoverySettings(rounds=3, operon_population=100))
    cands = engine.fit(Xt, yt, "fx", 20, 0, "absolute", None, (Xh, yh))
    attach_holdout(cands, Xh, yh, "absolute")
    best = select(cands, SelectionSettings(), float(np.std(yh)))
    assert best.engine.endswith("(+operon)")
    _assert_terms(best.expression, sympy.expand(truth))
    gp = [c for c in cands if c.engine.endswith("(+operon)")]
    assert gp and all(c.weakest_t is not None for c in gp)  # linear in their terms: t ratios measured
    assert all(abs(float(t.as_coeff_Mul()[0])) > 0 for t in sympy.Add.make_args(best.expression))


def test_genetic_programming_runs_beside_a_picked_lone_gravity_term():
    # noisy fz whose pick holds gbz: the GP (which does not see the lone terms) still measures its candidates'
    # terms, the picked gbz among them, over every primitive (a NameError on gbz before)
    X = _rows(1500, 6)
    truth = -1.1e-5 * (P["u1"] ** 2 + P["u2"] ** 2 + P["u3"] ** 2 + P["u4"] ** 2) + 0.05 * P["gbz"]
    y = _values(truth, X)
    y = y + np.random.default_rng(6).normal(0.0, 1e-3 * np.std(y), len(y))
    Xt, yt, Xh, yh = split_holdout(X, y)
    engine = DiscoveryEngine(DiscoverySettings(rounds=2, operon_population=60, primitives=WITH_GRAVITY))
    cands = engine.fit(Xt, yt, "fz", 3, 0, "absolute", None, (Xh, yh))
    assert engine.stats["operon_generations"] == 3
    attach_holdout(cands, Xh, yh, "absolute")
    best = select(cands, SelectionSettings(), float(np.std(yh)))
    assert P["gbz"] in best.expression.free_symbols
    assert any(c.engine.endswith("(+operon)") and c.weakest_t is not None for c in cands)


def test_identify_gravity_option_bad_value_or_with_a_vehicle_is_a_clear_error(tmp_path):
    import subprocess
    import sys
    from pathlib import Path

    repo = Path(__file__).resolve().parent.parent
    for extra, message in ((["--gravity", "0"], "not a gravity"),
                           (["--gravity", "9.81", "--vehicle", "fang-chen-buaa"], "both give the gravity")):
        proc = subprocess.run([sys.executable, "-m", "quadsr.cli", "identify", str(tmp_path / "none.csv"),
                               "-o", str(tmp_path / "m.yaml"), *extra], cwd=repo, capture_output=True,
                              text=True, check=False)
        assert proc.returncode == 2, proc.stderr
        assert message in proc.stderr and "Traceback" not in proc.stderr
