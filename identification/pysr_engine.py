"""PySR (Julia) behind the common engine interface; optional: `pip install quadsr[pysr]` plus Julia.

`import pysr` starts a Julia download that fails without a network, or hangs where traffic is silently
dropped. So availability is probed first in a subprocess with a timeout (and PYTHON_JULIAPKG_OFFLINE=yes
unless the user set it), and pysr is imported only after the probe passed. A run repeats only with
deterministic=True and parallelism='serial', which is what this engine uses.
"""

from __future__ import annotations

import importlib.util
import os
import subprocess
import sys
import time

import numpy as np

from bridge.errors import UserError
from bridge.shutdown import die_with_parent
from identification.candidate import Candidate, Progress, make_candidate
from identification.engine_settings import PysrSettings
from identification.library import input_matrix
from identification.metrics import LOSSES
from identification.model_file import SYMBOLS, ExpressionError, parse_expression

INSTALL_HINT = (
    "install the extra with `pip install quadsr[pysr]` and Julia 1.10 or 1.11 (juliaup or your package "
    "manager), then run `python -c 'import pysr'` once with a network so juliapkg installs its Julia "
    "packages; or use --engine default (no Julia needed)"
)
_PROBE_CODE = "import pysr, juliacall; print(pysr.__version__)"
_probe_cache: dict[tuple[str, float], str | None] = {}


def _offline_env() -> dict[str, str]:
    env = dict(os.environ)
    env.setdefault("PYTHON_JULIAPKG_OFFLINE", "yes")
    return env


def probe_pysr(timeout_s: float = 60.0) -> str | None:
    """None when PySR and its Julia work here; else the reason why not (fast when pysr is not installed)."""
    key = (sys.executable, timeout_s)
    if key in _probe_cache:
        return _probe_cache[key]
    reason: str | None
    if importlib.util.find_spec("pysr") is None:
        reason = "PySR is not installed"
    elif importlib.util.find_spec("juliacall") is None:
        reason = "juliacall (PySR's bridge to Julia) is not installed"
    else:
        try:
            done = subprocess.run(
                [sys.executable, "-c", _PROBE_CODE],
                env=_offline_env(),
                capture_output=True,
                text=True,
                timeout=timeout_s,
                stdin=subprocess.DEVNULL,
                preexec_fn=die_with_parent,
            )
        except subprocess.TimeoutExpired:
            reason = f"importing pysr did not finish within {timeout_s:g} s (a Julia download hanging?)"
        else:
            if done.returncode == 0:
                reason = None
            else:
                lines = [ln for ln in (done.stderr or "").strip().splitlines() if ln.strip()]
                last = lines[-1] if lines else f"exit code {done.returncode}"
                reason = f"importing pysr failed: {last[:300]}"
    _probe_cache[key] = reason
    return reason


def require_pysr(timeout_s: float = 60.0) -> None:
    """Raise a UserError saying what to install when PySR or Julia is missing."""
    reason = probe_pysr(timeout_s)
    if reason is not None:
        raise UserError(f"the pysr engine cannot run: {reason}", hint=INSTALL_HINT)


class PysrEngine:
    """PySRRegressor with the paper's operators, deterministic and serial."""

    name = "pysr"

    def __init__(self, settings: PysrSettings | None = None):
        self.settings = settings or PysrSettings()
        self.timings: dict[str, float] = {}

    def fit(
        self,
        X: np.ndarray,
        y: np.ndarray,
        target: str,
        budget: int,
        seed: int,
        loss: str = "absolute",
        progress: Progress | None = None,
        holdout: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> list[Candidate]:
        """Fit one target with PySR, `budget` iterations (no time cap); a candidate per hall-of-fame row."""
        if loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}")
        s = self.settings
        require_pysr(s.probe_timeout_s)
        os.environ.setdefault(
            "PYTHON_JULIAPKG_OFFLINE", "yes"
        )  # the probe passed offline: never download here
        from pysr import PySRRegressor

        start = time.perf_counter()
        X = np.asarray(X, dtype=float)
        y = np.asarray(y, dtype=float)
        inputs, names, extra = input_matrix(X, s.engineered_inputs)
        # neutral names: PySR reserves some (sympy's S, N, E, ...); mapped back when parsing
        aliases = [f"v{i}" for i in range(len(names))]
        mapping = {**SYMBOLS, **extra}
        alias_map = {a: mapping[n] for a, n in zip(aliases, names, strict=True)}
        if progress:
            progress(0.0, f"{int(budget)} iterations")
        reg = PySRRegressor(
            niterations=int(budget),
            populations=s.populations,
            maxsize=s.maxsize,
            binary_operators=list(s.binary_operators),
            unary_operators=list(s.unary_operators),
            elementwise_loss="L1DistLoss()" if loss == "absolute" else "L2DistLoss()",
            random_state=int(seed),
            deterministic=True,
            parallelism="serial",
            progress=False,
            verbosity=0,
            temp_equation_file=True,
            delete_tempfiles=True,
        )
        reg.fit(inputs, y, variable_names=aliases)
        candidates: list[Candidate] = []
        table = reg.equations_
        for _, row in table.iterrows():
            texts = []
            if "sympy_format" in row:
                texts.append(str(row["sympy_format"]))
            texts.append(str(row["equation"]))
            for text in texts:
                try:
                    expr = parse_expression(text, alias_map)
                except (ExpressionError, RecursionError):
                    continue
                candidates.append(make_candidate(expr, X, y, loss, self.name))
                break
        self.timings = {"pysr": time.perf_counter() - start}
        if progress:
            progress(1.0, f"{len(candidates)} candidates")
        return candidates
