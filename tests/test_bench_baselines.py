"""bench/discovery.py's baselines: PySINDy on the generic degree-2 library (153 columns), fitted with BLAS on
one thread as the bench runs it, finds every term of a known sparse polynomial with its coefficient and
reproduces validation rows; the settings written above the table state the library and pyoperon's budget."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from bench_module import bench_module

from identification.model_file import SYMBOLS, TARGET_NAMES
from identification.table import Dataset
from identification.validate import expression_terms

discovery = bench_module("discovery.py", "bench_discovery")

# per target: {monomial of the 16 variables: coefficient}, a sparse degree-2 polynomial
TRUTH = {
    "ax": {"vx*u1": 2.0, "wz": -0.5},
    "ay": {"vy*u2": -1.5, "1": 0.3},
    "az": {"u1**2": 4e-2, "vz": 0.7},
    "dwx": {"wy*wz": -0.8},
    "dwy": {"wx*wz": 0.6, "u3": 1e-2},
    "dwz": {"u1*u2": -3e-3, "wz": -0.2},
}


def _polynomial_rows(n: int, seed: int) -> Dataset:
    """n rows of random states and rotor speeds with TRUTH's targets, noise-free."""
    rng = np.random.default_rng(seed)
    xi = rng.uniform(-2.0, 2.0, (n, 12))
    u = rng.uniform(300.0, 700.0, (n, 4))
    X = np.hstack([xi, u])
    names = ("x", "y", "z", "vx", "vy", "vz", "phi", "theta", "psi", "wx", "wy", "wz", "u1", "u2", "u3", "u4")
    env = {k: X[:, i] for i, k in enumerate(names)}
    y = np.column_stack([sum(c * (1.0 if m == "1" else eval(m, {}, env)) for m, c in TRUTH[t].items())
                         for t in TARGET_NAMES])
    return Dataset(t=np.arange(n) * 0.004, xi=xi, u=u, targets=y, source="test", format="synthetic",
                   target_source="truth")


def test_pysindy_poly2_recovers_a_sparse_polynomial_with_one_blas_thread():
    features = discovery.polynomial_features(2)
    assert len(features) == 153  # 1 + 16 + 16*17/2
    train = _polynomial_rows(1500, seed=3)
    with discovery.single_threaded_blas():
        model = discovery._pysindy(features, train)
    val = _polynomial_rows(500, seed=4)
    pred = np.atleast_2d(model.evaluate(val.xi, val.u))
    for j, name in enumerate(TARGET_NAMES):
        learned = expression_terms(model.targets[name].expression)
        truth = {(1 if m == "1" else eval(m, {}, SYMBOLS)): c for m, c in TRUTH[name].items()}
        for term, c in truth.items():  # every true term, its coefficient
            assert float(learned.get(term, 0.0)) == pytest.approx(c, rel=1e-6), (name, term)
        # noise-free rows: the smallest threshold fits best on the held-out rows, so round-off terms may
        # stay in, but they add nothing: the validation rows are reproduced
        assert np.max(np.abs(pred[:, j] - val.targets[:, j])) < 1e-6 * np.std(val.targets[:, j]), name


def test_the_settings_state_the_libraries_and_pyoperons_budget():
    lines = discovery.baseline_settings(["discovery", "pysindy-poly2", "operon"], 20, seed=7)
    assert len(lines) == 2  # ours is no baseline
    assert "153 columns" in lines[0]
    assert "20 generations per target" in lines[1] and "10,000 individuals" in lines[1]
    assert "seed 7" in lines[1]


def test_the_validation_flight_option_gives_the_whole_training_flight_to_fit_and_pick():
    # the bench's default: ours validates on the case's other flight (as `quadsr identify --validate-log`),
    # so no block of the training flight is set aside; --own-validation-block: identify's fit | pick |
    # validate blocks of the training flight
    case = next(c for c in discovery.CASES if c.name == "paper vehicle")
    train, val = discovery.synthetic(case, 1500, 0), discovery.synthetic(case, 600, 1000)
    gravity = 9.81
    given = discovery.fit("sparse", train, 0, gravity, 1, 1, validate=val)
    blocks = discovery.fit("sparse", train, 0, gravity, 1, 1)
    rows_given = given.engine["rows"]
    rows_blocks = blocks.engine["rows"]
    assert rows_given["validate"] == len(val)
    assert rows_given["fit"] + rows_given["pick"] > rows_blocks["fit"] + rows_blocks["pick"] + 250
    assert rows_blocks["validate"] < len(train) // 4


@pytest.mark.parametrize("engine, says", [
    ("discovery-weak", "`discovery` gives both rows"),
    ("pysr", "unknown engine 'pysr' (known: discovery, sparse"),
])
def test_an_engine_the_bench_does_not_run_is_refused_before_any_flight(tmp_path, engine, says):
    root = Path(__file__).resolve().parents[1]
    out = tmp_path / "out"
    run = subprocess.run([sys.executable, str(root / "bench" / "discovery.py"), "--engines", engine,
                          "--out", str(out), "--cases", "sitl paper flights"], capture_output=True, text=True,
                         timeout=120, cwd=root, env={**os.environ, "PYTHONPATH": str(root)})
    assert run.returncode == 1
    assert says in run.stderr
    assert "Traceback" not in run.stderr
    assert not any(out.glob("*.tlog"))  # nothing flown
