"""Discovery rules for terms a flight barely separates (small seeded synthetic data, issue 12).

- projected screening: a true term nearly collinear with a picked one (wz*(u1+..+u4) beside wz when the rotor
  sum varies by a few %) is screened by what it adds to the model, so it comes in;
- a positive primitive that barely varies (the height within +-0.5 %) gives no features: h*vb^2 cannot be
  told from vb^2, and the simpler one wins;
- data flown with another g than the one removed: `quadsr identify --gravity G` gives the data's g (a bad
  value, or one beside --vehicle, is a clear error).
"""

from __future__ import annotations

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS, PRIMITIVES, primitive_matrix
from identification.discovery import DiscoveryEngine, _projected_scores, _screen_scores, _standardized
from identification.engine import split_holdout
from identification.engine_settings import DiscoverySettings, SelectionSettings
from identification.feature_space import grow_unary
from identification.pareto import attach_holdout, select
from identification.true_model import random_states
from identification.validate import expression_terms

P = PRIMITIVE_SYMBOLS


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


def _gp_product_pick(operon_rows: int):
    truth = -2e-4 * P["ub"] * (P["u1"] + P["u2"] + P["u3"] + P["u4"]) + 0.05 * P["ub"] * P["wx"] * P["wz"]
    X = _rows(2000, 5, spread=0.5)
    Xt, yt, Xh, yh = split_holdout(X, _values(truth, X))
    engine = DiscoveryEngine(DiscoverySettings(rounds=3, operon_population=100, operon_rows=operon_rows))
    cands = engine.fit(Xt, yt, "fx", 20, 0, "absolute", None, (Xh, yh))
    attach_holdout(cands, Xh, yh, "absolute")
    return truth, cands, select(cands, SelectionSettings(), float(np.std(yh)))


def test_the_gp_reads_a_strided_subset_of_the_fit_rows_and_its_terms_are_refit_on_all():
    # operon_rows: the GP proposes the product from 400 of the 1,600 fit rows; its terms, refit by least
    # squares on every fit row, give the exact coefficients
    truth, _, best = _gp_product_pick(400)
    assert best.engine.endswith("(+operon)")
    _assert_terms(best.expression, sympy.expand(truth))


def test_a_genetic_programming_product_comes_back_as_its_terms_refit_and_pruned():
    # ub*wx*wz is a product of three primitives: no rung-2 feature holds it, the GP on the sparse model's
    # residual finds it; its terms then join the picked model's features in one more sparse fit, so the pick
    # is the exact sum of the true terms with least-squares coefficients, not "model + opaque GP tree"
    truth, cands, best = _gp_product_pick(0)
    assert best.engine.endswith("(+operon)")
    _assert_terms(best.expression, sympy.expand(truth))
    gp = [c for c in cands if c.engine.endswith("(+operon)")]
    assert gp and all(c.measured().weakest_t is not None for c in gp)  # linear in their terms: t measured
    assert all(abs(float(t.as_coeff_Mul()[0])) > 0 for t in sympy.Add.make_args(best.expression))


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
