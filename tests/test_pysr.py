"""PySR behind the engine interface: a clear, quick error without Julia; a real fit where it all exists."""

from __future__ import annotations

import os
import subprocess
import sys
import time

import numpy as np
import pytest

from bridge.errors import UserError
from identification.engine import PysrSettings, make_engine, split_holdout
from identification.metrics import r2
from identification.pysr_engine import probe_pysr
from identification.true_model import random_states, true_model


def test_without_julia_the_cli_says_what_to_install_quickly(tmp_path):
    # a Julia-less environment even where one is installed: no julia on PATH, an empty juliapkg project
    env = dict(os.environ)
    env.update(
        PYTHON_JULIAPKG_OFFLINE="yes",
        PYTHON_JULIAPKG_EXE=str(tmp_path / "no-julia-here"),
        PYTHON_JULIAPKG_PROJECT=str(tmp_path / "juliaenv"),
        JULIA_DEPOT_PATH=str(tmp_path / "depot"),
        HOME=str(tmp_path),
        PATH=os.path.dirname(sys.executable),
    )
    start = time.perf_counter()
    done = subprocess.run(
        [
            sys.executable,
            "-m",
            "quadsr.cli",
            "identify",
            str(tmp_path / "never-read.tlog"),
            "--engine",
            "pysr",
            "-o",
            str(tmp_path / "m.yaml"),
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        stdin=subprocess.DEVNULL,
    )
    elapsed = time.perf_counter() - start
    assert done.returncode == 2, done.stderr
    assert "pysr engine cannot run" in done.stderr
    assert "pip install quadsr[pysr]" in done.stderr and "Julia" in done.stderr
    assert "Traceback" not in done.stderr
    assert "never-read.tlog" not in done.stderr  # it fails before reading any log
    assert elapsed < 60
    assert not (tmp_path / "m.yaml").exists()


def test_pysr_engine_fits_or_raises_the_clear_error():
    xi, u = random_states(400, seed=31)
    X = np.hstack([xi, u])
    y = true_model("fang-chen-buaa").accelerations(xi, u)[:, 5]
    engine = make_engine("pysr")
    if probe_pysr() is not None:
        start = time.perf_counter()
        with pytest.raises(UserError) as info:
            engine.fit(X, y, "dwz", 30, 0)
        assert "pip install quadsr[pysr]" in str(info.value) and time.perf_counter() - start < 60
        return
    # PySR and Julia are here: a short real fit, the same twice with the same seed
    Xt, yt, Xh, yh = split_holdout(X, y)
    runs = []
    for _ in range(2):
        engine = make_engine("pysr")
        engine.settings = PysrSettings(populations=4, maxsize=20)
        cands = engine.fit(Xt, yt, "dwz", 5, 7, "squared")
        assert cands
        assert max(r2(yh, c.evaluate(Xh)) for c in cands) > 0.9
        runs.append([str(c.expression) for c in cands])
    assert runs[0] == runs[1]
