"""Native (C) twins of the controller's loop functions: same results as the Python ones, a clean fallback
when they cannot be built, and the whole controller giving the same commands either way."""

from __future__ import annotations

import math

import numpy as np
import pytest
import sympy

from controller import derivation, native
from controller.backstepping import BacksteppingController
from controller.plugin import VehicleState
from controller.simulate import ModelPlant, simulate
from controller.trajectories import load_trajectory
from identification.paper_model import paper_model
from identification.true_model import true_model

X, Y = sympy.symbols("x y", real=True)
# every construct the derived programs use: trig and inverse trig with a clipped argument, |.|, sign,
# small and fractional powers, rationals, exp/log, a piecewise
EXPRS = [
    sympy.sin(X) * sympy.cos(Y) + sympy.Rational(1, 3) * X**2 - Y**3 / 7,
    sympy.asin(sympy.Max(-1, sympy.Min(1, X * Y))) + sympy.atan2(Y, X),
    sympy.Abs(X) * X + sympy.sign(Y) * sympy.sqrt(sympy.Abs(Y)) + X**4,
    sympy.exp(-X**2) * sympy.log(1 + Y**2) + sympy.Piecewise((X, X > 0), (0, True)),
]


@pytest.fixture()
def cache(tmp_path, monkeypatch):
    monkeypatch.setenv("QUADSR_CACHE_DIR", str(tmp_path))
    monkeypatch.delenv("CC", raising=False)
    monkeypatch.delenv("QUADSR_NATIVE", raising=False)
    return tmp_path / "native"


def _python(exprs=EXPRS):
    return sympy.lambdify([X, Y], exprs, modules="math", cse=True)


def test_compiled_expressions_match_python_or_say_why_not(cache):
    python = _python()
    fn = native.compile_expressions("test exprs", [X, Y], EXPRS, python, [0.3, -0.2])
    state = native.status()["test exprs"]
    if native.compiler() is None:  # a machine without a C compiler keeps Python and says so
        assert fn is python and "no C compiler" in state
        return
    assert state == "native" and fn is not python
    rng = np.random.default_rng(5)
    for x, y in rng.uniform(-2.0, 2.0, (200, 2)):
        expected = python(float(x), float(y))
        got = fn(float(x), float(y))
        assert got == pytest.approx(expected, rel=1e-12, abs=1e-12)
    assert len(list(cache.glob("*.so"))) == 1


def test_outside_the_domain_python_raises_and_c_gives_nan(cache):
    expr = [sympy.sqrt(X) + Y]
    fn = native.compile_expressions("sqrt", [X, Y], expr, _python(expr), [1.0, 0.0])
    if native.status()["sqrt"] == "native":
        assert math.isnan(fn(-1.0, 0.0)[0])
    else:
        with pytest.raises(ValueError):
            fn(-1.0, 0.0)


def test_native_off_by_environment(cache, monkeypatch):
    monkeypatch.setenv("QUADSR_NATIVE", "0")
    python = _python()
    assert native.compile_expressions("off", [X, Y], EXPRS, python) is python
    assert native.status()["off"] == "QUADSR_NATIVE=0"
    assert not cache.exists()


def test_missing_compiler_falls_back_with_the_reason(cache, monkeypatch):
    monkeypatch.setenv("CC", "no-such-compiler-quadsr")
    python = _python()
    assert native.compile_expressions("no cc", [X, Y], EXPRS, python) is python
    assert "no-such-compiler-quadsr" in native.status()["no cc"]


def test_compiler_error_falls_back_with_its_message(cache, monkeypatch):
    if native.compiler() is None:
        pytest.fail("this machine has no C compiler; the fallback is tested above")
    monkeypatch.setenv("CC", "cc -DBROKEN -include /nonexistent/quadsr-header.h")
    python = _python()
    assert native.compile_expressions("broken", [X, Y], EXPRS, python) is python
    assert "failed" in native.status()["broken"]


def test_unprintable_function_stays_python(cache):
    expr = [sympy.besselj(0, X) + Y]
    python = sympy.lambdify([X, Y], expr, modules="scipy")
    assert native.compile_expressions("bessel", [X, Y], expr, python, [1.0, 1.0]) is python
    assert "not printable as C" in native.status()["bessel"]


def test_a_twin_that_disagrees_is_not_used(cache):
    if native.compiler() is None:
        pytest.fail("this machine has no C compiler; the fallback is tested above")
    unit = native.NativeUnit()
    unit.program("f", [X, Y], [], [X + Y])
    unit.export("f", 2, 1)
    wrong = sympy.lambdify([X, Y], [X - Y], modules="math")
    fns = native.build_unit(unit, {"f": ("disagrees", wrong, [[1.0, 2.0]])})
    assert fns["f"] is wrong
    assert native.status()["disagrees"].startswith("native check failed: output 0 differs")


def test_the_cache_is_reused_without_compiling(cache, monkeypatch):
    if native.compiler() is None:
        pytest.fail("this machine has no C compiler; the fallback is tested above")
    python = _python()
    native.compile_expressions("first", [X, Y], EXPRS, python, [0.3, -0.2])
    libs = list(cache.glob("*.so"))

    def no_compiler(*_a, **_k):
        raise AssertionError("compiled again")

    monkeypatch.setattr(native.subprocess, "run", no_compiler)
    fn = native.compile_expressions("second", [X, Y], EXPRS, python, [0.3, -0.2])
    assert native.status()["second"] == "native" and fn is not python
    assert list(cache.glob("*.so")) == libs


def test_solve_small_in_c_matches_python(cache):
    if native.compiler() is None:
        pytest.fail("this machine has no C compiler; the fallback is tested above")
    unit = native.NativeUnit()
    unit.code("""static void solve4(const double *restrict in, double *restrict out) {
  out[0] = solve_small(4, in, in + 16, out + 1);
}""")
    unit.export("solve4", 20, 5)
    fn = unit.build()["solve4"]
    rng = np.random.default_rng(2)
    for _ in range(100):
        a = rng.normal(size=(4, 4)) * rng.choice([1e-3, 1.0, 1e5], size=(4, 1))
        b = rng.normal(size=4)
        out = fn(*a.ravel(), *b)
        expected = derivation.solve_small(a.tolist(), b.tolist())
        assert out[0] == 1.0 and expected is not None
        assert out[1:] == pytest.approx(expected, rel=1e-9, abs=1e-12)
    singular = [[1.0, 2.0, 3.0, 4.0], [2.0, 4.0, 6.0, 8.0], [0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0]]
    assert fn(*sum(singular, []), 1.0, 1.0, 1.0, 1.0)[0] == 0.0
    assert derivation.solve_small(singular, [1.0] * 4) is None
    assert fn(*([math.nan] * 16), 1.0, 1.0, 1.0, 1.0)[0] == 0.0


def _commands(model, vehicle, case: str, monkeypatch, native_on: bool) -> tuple[list, BacksteppingController]:
    monkeypatch.setenv("QUADSR_NATIVE", "1" if native_on else "0")
    ctl = BacksteppingController(model, vehicle)
    plant = ModelPlant(model, motor_time_constant=vehicle.motor.time_constant)
    states = []
    update = ctl.update

    def record(t, state, ref):
        states.append((t, VehicleState(np.array(state.xi), np.array(state.rotor_speeds)), ref))
        return update(t, state, ref)

    ctl.update = record
    simulate(ctl, load_trajectory(case), plant, 6.0)
    ctl.update = update
    return states, ctl


@pytest.mark.parametrize("which", ["true", "paper"])
def test_controller_gives_the_same_commands_native_or_python(which, vehicle, cache, monkeypatch):
    """Every loop function native vs all Python: the same motor speeds at the states of a Case I flight
    (take-off, the 3.7 m approach with its limits, tracking), replayed through both controllers."""
    model = true_model(vehicle) if which == "true" else paper_model()
    states, fast = _commands(model, vehicle, "case1", monkeypatch, True)
    _, slow = _commands(model, vehicle, "case1", monkeypatch, False)
    assert "0 of" in slow.describe() and "QUADSR_NATIVE=0" in slow.describe()
    assert slow.describe().endswith("model-error observer: python (QUADSR_NATIVE=0)")
    if native.compiler() is not None:
        n = len(fast.law.native)
        assert f"{n} of {n} loop functions compiled" in fast.describe(), fast.describe()
        assert fast.describe().endswith("model-error observer: compiled")
        assert fast.law.outer is not slow.law.outer
    fast.reset()
    slow.reset()
    worst = 0.0
    for t, state, ref in states:
        a = fast.update(t, state, ref).rotor_speeds
        b = slow.update(t, state, ref).rotor_speeds
        worst = max(worst, float(np.max(np.abs(a - b))))
    # rounding differs (Gaussian elimination vs cofactors, C vs Python libm), so Newton may stop one
    # iteration apart; the warm starts and the observer carry that along: 1e-3 rad/s is 2e-6 of hover
    assert worst < 1e-3, f"largest difference {worst:.3g} rad/s"


def test_a_compiled_function_is_safe_to_call_from_several_threads(cache):
    """Its argument and result buffers are shared by every caller of the function."""
    from concurrent.futures import ThreadPoolExecutor

    python = _python()
    fn = native.compile_expressions("threads", [X, Y], EXPRS, python, [0.3, -0.2])
    points = np.random.default_rng(9).uniform(-2.0, 2.0, (4000, 2)).tolist()

    def run(chunk):
        return [(fn(x, y), python(x, y)) for x, y in chunk]

    with ThreadPoolExecutor(4) as pool:
        results = [r for part in pool.map(run, [points[i::4] for i in range(4)]) for r in part]
    assert all(got == pytest.approx(ref, rel=1e-12, abs=1e-12) for got, ref in results)
