"""The control law derived from model expressions: motor form, outer inversion and its derivatives, inner
solve, and models that cannot be inverted."""

from __future__ import annotations

import copy
import math
import time

import numpy as np
import pytest
import sympy

from bridge.errors import UserError
from bridge.vehicle import load_vehicle
from controller.derivation import F, derive_law, motor_form, solve_small
from identification.model_file import SYMBOLS as S
from identification.paper_model import paper_model as paper_learned_model
from identification.true_model import true_model_expressions

W_MAX = 1006.6


@pytest.fixture(scope="module")
def true_exprs(vehicle):
    return true_model_expressions(vehicle)


@pytest.fixture(scope="module")
def true_law(true_exprs):
    return derive_law(true_exprs, W_MAX)


def paper_model() -> dict[str, sympy.Expr]:
    """The paper's learned equations (Section II-B), zeta_4..zeta_12 in our symbols."""
    return dict(paper_learned_model().expressions)


def test_motor_form_writes_even_powers_in_f_and_keeps_odd_ones():
    u1, u2, u3, u4 = (S[n] for n in ("u1", "u2", "u3", "u4"))
    f1, f2, f3, f4 = F
    assert sympy.simplify(motor_form(u1**2 + u2**2 + u3**2 + u4**2) - f1) == 0
    assert sympy.simplify(motor_form(-(u1**2) + u2**2 + u3**2 - u4**2) - f2) == 0
    assert sympy.simplify(motor_form(u1**2 - u2**2 + u3**2 - u4**2) - f3) == 0
    assert sympy.simplify(motor_form(u1**2 + u2**2 - u3**2 - u4**2) - f4) == 0
    mixed = motor_form((u1 + u2) ** 2)  # expanded: q1 + q2 in f, and the cross term frozen in u
    assert mixed.has(u1) and mixed.has(u2) and mixed.has(f1)
    assert motor_form(u1 * u2) == u1 * u2


def test_true_model_modes(true_law):
    assert true_law.outer.mode == "thrust" and true_law.outer.method == "newton"
    assert [s.name for s in true_law.outer.unknowns] == ["phi", "theta", "f1"]
    assert true_law.inner.affine and true_law.inner.method == "linear"
    assert math.isclose(true_law.gravity, 9.8) and math.isclose(true_law.hover_speed, 557.142, rel_tol=1e-5)


def test_paper_model_is_solved_in_closed_form_like_the_paper():
    law = derive_law(paper_model(), W_MAX)
    assert law.outer.mode == "frozen" and law.outer.method == "closed-form"
    xi, u = [0.0] * 12, [560.0, 555.0, 565.0, 550.0]
    xi[8] = 0.2  # psi
    sol = law.outer.solve([0.7, -0.4], xi, u, [0.0, 0.0])
    assert sol.method == "closed-form"
    # the paper's formulas (its eq. for xi_7d and xi_8d)
    k = 7.87e-6 * u[0] ** 2 + 7.78e-6 * (u[1] ** 2 + u[2] ** 2 + u[3] ** 2)
    phi = math.asin((-0.4 + 0.0441) / k) - 0.2
    theta = (0.7 + 0.00768 * u[0] * math.sin(phi) * math.sin(0.2) + 1.63e-5 * u[1] * u[3] * math.sin(phi)
             * math.sin(0.2)) / (-0.00665 * u[0] * math.cos(phi) * math.cos(0.2)
                                 - 1.63e-5 * u[1] * u[3] * math.cos(phi) * math.cos(0.2))
    assert math.isclose(sol.phi, phi, rel_tol=1e-12) and math.isclose(sol.theta, theta, rel_tol=1e-12)
    # the general path (Newton on the sympy Jacobian) finds the same solution
    newton = copy.copy(law.outer)
    newton.closed_form = None
    sol2 = newton.solve([0.7, -0.4], xi, u, [0.0, 0.0], max_iter=20)
    sol2 = newton.solve([0.7, -0.4], xi, u, [sol2.phi, sol2.theta], max_iter=20)
    assert sol2.ok and sol2.method == "newton"
    assert math.isclose(sol2.phi, phi, rel_tol=1e-9) and math.isclose(sol2.theta, theta, rel_tol=1e-9)


def test_arcsine_domain_is_guarded():
    law = derive_law(paper_model(), W_MAX)
    sol = law.outer.solve([0.0, 500.0], [0.0] * 12, [557.0] * 4, [0.0, 0.0])
    assert math.isfinite(sol.phi) and math.isclose(sol.phi, math.pi / 2)


def test_newton_solution_satisfies_the_true_model(true_law, true_exprs):
    xi = [0.3, -0.2, -2.0, 1.2, -0.7, 0.3, 0.05, -0.1, 0.4, 0.1, -0.2, 0.05]
    a = [1.5, -2.0, -1.0]
    sol = true_law.outer.solve(a, xi, [557.0] * 4, [0.0, 0.0, true_law.hover_f[0]], max_iter=20)
    assert sol.ok
    fn = sympy.lambdify([S[n] for n in ("x", "y", "z", "vx", "vy", "vz", "phi", "theta", "psi", "wx", "wy",
                                        "wz", "u1", "u2", "u3", "u4")],
                        [true_exprs[n] for n in ("ax", "ay", "az")])
    xs = list(xi)
    xs[6], xs[7] = sol.phi, sol.theta
    u = math.sqrt(sol.f1 / 4)
    assert np.allclose(fn(*xs, u, u, u, u), a, atol=1e-6)


def _solve_tight(outer, a, xi, u, guess):
    sol = outer.solve(a, xi, u, guess, max_iter=30)
    sol = outer.solve(a, xi, u, [sol.phi, sol.theta, sol.f1][: outer.n], max_iter=30)
    assert sol.ok
    return np.array([sol.phi, sol.theta, sol.f1][: outer.n])


@pytest.mark.parametrize("which", ["true", "paper"])
def test_implicit_derivatives_match_finite_differences(true_law, which):
    law = true_law if which == "true" else derive_law(paper_model(), W_MAX)
    outer = law.outer
    n = outer.n
    a0, a1, a2 = np.array([0.8, -0.5, -0.6]), np.array([0.4, 0.3, -0.2]), np.array([-0.3, 0.5, 0.1])
    xi0 = np.array([0.0, 0.0, -2.0, 1.0, -0.5, 0.2, 0.0, 0.0, 0.3, 0.0, 0.0, 0.0])
    xi1 = np.zeros(12)
    xi2 = np.zeros(12)
    xi1[3:6], xi2[3:6] = [0.5, -0.2, 0.1], [0.1, 0.3, -0.2]  # velocities move
    xi1[8], xi2[8] = 0.2, -0.1  # and yaw
    u = [560.0, 555.0, 565.0, 550.0]
    guess = [0.0, 0.0, law.hover_f[0]][:n]

    def at(t):
        xi = (xi0 + xi1 * t + 0.5 * xi2 * t * t).tolist()
        a = (a0 + a1 * t + 0.5 * a2 * t * t).tolist()
        return _solve_tight(outer, a, xi, u, guess)

    h = 1e-3
    qm, q0, qp = at(-h), at(0.0), at(h)
    fd1 = (qp - qm) / (2 * h)
    fd2 = (qp - 2 * q0 + qm) / h**2
    p1 = [xi1[3 + "xyz".index(s[1])] if s.startswith("v") else (xi1[8] if s == "psi" else 0.0)
          for s in outer.param_names]
    p2 = [xi2[3 + "xyz".index(s[1])] if s.startswith("v") else (xi2[8] if s == "psi" else 0.0)
          for s in outer.param_names]
    d1, d2 = outer.rates(q0.tolist(), xi0.tolist(), u, a1[:n].tolist(), a2[:n].tolist(), p1, p2)
    scale = np.array([1.0, 1.0, 1e5][:n])
    assert np.allclose(np.array(d1) / scale, fd1 / scale, rtol=1e-5, atol=1e-7)
    assert np.allclose(np.array(d2) / scale, fd2 / scale, rtol=1e-3, atol=1e-5)


def test_inner_affine_solve_meets_the_designed_values(true_law):
    xi = [0.0, 0.0, -1.0, 0.5, 0.2, -0.1, 0.1, -0.2, 0.3, 0.4, -0.3, 0.2]
    u = [560.0, 540.0, 570.0, 550.0]
    v = [-0.5, 3.0, -2.0, 0.5]
    f, ok = true_law.inner.solve(v, xi, u, true_law.hover_f)
    assert ok
    assert np.allclose(true_law.inner.gamma(xi, u, f), v, atol=1e-9)


def test_non_affine_model_uses_newton(true_exprs):
    u1, u2, u3, u4 = (S[n] for n in ("u1", "u2", "u3", "u4"))
    exprs = dict(true_exprs)
    # a thrust that is not linear in f1: z'' gains a small -c f1^2 term, roll a cubic in f2
    exprs["az"] = exprs["az"] - 2e-15 * (u1**2 + u2**2 + u3**2 + u4**2) ** 2
    exprs["dwx"] = exprs["dwx"] + 1e-16 * (-(u1**2) + u2**2 + u3**2 - u4**2) ** 3
    law = derive_law(exprs, W_MAX)
    assert not law.inner.affine and law.inner.method == "newton"
    xi = [0.0, 0.0, -1.0, 0.0, 0.0, 0.0, 0.1, -0.05, 0.0, 0.2, 0.1, 0.0]
    v = [-1.0, 2.0, 1.0, 0.3]
    f, ok = law.inner.solve(v, xi, [557.0] * 4, law.hover_f)
    assert ok and np.allclose(law.inner.gamma(xi, [557.0] * 4, f), v, atol=1e-8)


def _refused(exprs, words):
    with pytest.raises(UserError) as err:
        derive_law(exprs, W_MAX)
    text = str(err.value)
    for w in words:
        assert w in text, text
    return text


def test_thrust_not_depending_on_the_motors_is_refused(true_exprs):
    exprs = dict(true_exprs)
    exprs["az"] = 9.8 - 0.03 * S["vz"]
    _refused(exprs, ["cannot be inverted", "az does not depend on the motors"])


def test_thrust_undefined_at_the_origin_is_a_clear_error(true_exprs):
    # a learned 1/h term (h = -z): the law is derived about hover at the origin, where it divides by zero
    exprs = dict(true_exprs)
    exprs["az"] = exprs["az"] + 0.005 * S["u4"] ** 2 / S["z"]
    _refused(exprs, ["cannot be evaluated at rest at the origin", "division by zero"])


def test_roll_without_f2_is_refused(true_exprs):
    exprs = dict(true_exprs)
    exprs["dwx"] = -0.697 * S["wy"] * S["wz"]
    _refused(exprs, ["dwx does not depend on the motors"])
    # roll driven by the pitch combination f3: dwx and dwy cannot be set independently
    u1, u2, u3, u4 = (S[n] for n in ("u1", "u2", "u3", "u4"))
    exprs["dwx"] = 8.3e-5 * (u1**2 - u2**2 + u3**2 - u4**2)
    _refused(exprs, ["singular", "rank 3"])


def test_no_attitude_in_horizontal_acceleration_is_refused(true_exprs):
    exprs = dict(true_exprs)
    exprs["ax"] = -0.04 * S["vx"]
    exprs["ay"] = -0.04 * S["vy"]
    _refused(exprs, ["x'' and y'' do not depend on roll and pitch"])


def test_missing_target_and_too_weak_motors_are_refused(true_exprs):
    exprs = {k: v for k, v in true_exprs.items() if k != "dwz"}
    _refused(exprs, ["no expression for dwz"])
    with pytest.raises(UserError, match="cannot hover"):
        derive_law(true_exprs, 300.0)


def test_derivation_is_fast_and_cached(true_exprs):
    exprs = {k: v * (1 + 1e-9) for k, v in true_exprs.items()}  # a new model: no cache hit
    t0 = time.process_time()  # CPU time of this process: other processes' load does not count
    derive_law(exprs, W_MAX)
    first = time.process_time() - t0
    t0 = time.process_time()
    derive_law(exprs, W_MAX)
    assert time.process_time() - t0 < 0.2 * first
    assert first < 15.0  # about 0.5 s on an idle core


def test_solve_small_against_numpy():
    rng = np.random.default_rng(3)
    for n in (2, 3, 4):
        for _ in range(100):
            a = rng.normal(size=(n, n)) * np.logspace(-6, 2, n)[:, None]
            b = rng.normal(size=n)
            assert np.allclose(solve_small(a.tolist(), b.tolist()), np.linalg.solve(a, b), rtol=1e-8)
        assert solve_small(np.ones((n, n)).tolist(), list(range(n))) is None


def test_written_out_euler_rates_equal_the_papers_matrix():
    """InnerInversion.euler_angle_rates (plain floats, in the loop) is R(phi, theta) w (euler_rate_matrix)."""
    from controller.derivation import InnerInversion, euler_rate_matrix

    rng = np.random.default_rng(4)
    for phi, theta, wx, wy, wz in rng.uniform(-1.2, 1.2, (50, 5)):
        r = np.array(euler_rate_matrix(sympy.Float(phi), sympy.Float(theta)).evalf(), dtype=float)
        xi = [0.0] * 6 + [phi, theta, 0.3, wx, wy, wz]
        assert InnerInversion.euler_angle_rates(xi) == pytest.approx(r @ [wx, wy, wz], rel=1e-12, abs=1e-12)


def test_a_model_with_vector_norms_is_inverted_at_rest():
    """fang-chen-aero's true model has the frame drag -|v_a| C v_a: its derivative at v = 0 is 0/0 unless the
    norm is smoothed; the law must still be derived (on the ground and at hover v = 0 exactly)."""
    import sympy

    from controller.derivation import NORM_FLOOR, smooth_norms
    from controller.registry import make_controller
    from identification.true_model import true_model

    u, v, w = sympy.symbols("u v w", real=True)
    drag = -u * sympy.sqrt(u**2 + v**2 + w**2)
    smooth = smooth_norms(drag)
    import numpy as np

    at_rest = (np.float64(0.0),) * 3  # numeric evaluation, as the law's functions do
    with np.errstate(all="ignore"):
        assert np.isnan(sympy.lambdify((u, v, w), sympy.diff(drag, u), "numpy")(*at_rest))
    assert abs(sympy.lambdify((u, v, w), sympy.diff(smooth, u), "numpy")(*at_rest)) <= 1e-6  # ~0, finite
    assert abs(float((smooth - drag).subs({u: 3.0, v: 4.0, w: 0.0}))) < 3.0 * NORM_FLOOR
    vehicle = load_vehicle("fang-chen-aero")
    controller = make_controller("backstepping", true_model(vehicle), vehicle)
    assert "hover" in controller.describe()
