"""Genetic-programming symbolic regression with pyoperon (C++, from PyPI, no Julia).

The paper's building blocks (add, sub, mul, div, sin, cos, constant) over the 16 variables plus engineered
inputs (f1..f4, g, the thrust direction); NSGA-II on (r2, length) gives a real Pareto front. Constant
fitting (Levenberg-Marquardt) is on; the run length is a generation budget with no time cap, so a seed
gives the same front on any machine and thread count.
"""

from __future__ import annotations

import time
import warnings

import numpy as np

from bridge.errors import UserError
from identification.candidate import Candidate, Progress, make_candidate
from identification.engine_settings import OperonSettings
from identification.library import input_matrix
from identification.metrics import LOSSES
from identification.model_file import SYMBOLS, ExpressionError, parse_expression

# Decimal places of the infix formatter (fixed-point): 25 keeps ~17 significant digits down to 1e-8.
_PRECISION = 25


class OperonEngine:
    """pyoperon's SymbolicRegressor behind the common engine interface."""

    name = "operon"

    def __init__(self, settings: OperonSettings | None = None):
        self.settings = settings or OperonSettings()
        self.timings: dict[str, float] = {}
        self.stats: dict[str, object] = {}

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
        """Evolve one target for `budget` generations; each front member a candidate in the 16 variables."""
        if loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}")
        try:
            from pyoperon.sklearn import SymbolicRegressor
        except ImportError as exc:
            raise UserError(
                f"the operon engine needs pyoperon ({exc})",
                hint="pip install pyoperon (a C++ wheel, no Julia)",
            ) from None
        s = self.settings
        start = time.perf_counter()
        X = np.asarray(X, dtype=float)
        y = np.asarray(y, dtype=float)
        inputs, names, extra = input_matrix(X, s.engineered_inputs)
        if progress:
            progress(0.0, f"{int(budget)} generations")
        reg = SymbolicRegressor(
            allowed_symbols=s.allowed_symbols,
            objectives=["r2", "length"],
            optimizer_iterations=s.optimizer_iterations,
            population_size=s.population_size,
            generations=int(budget),
            max_length=s.max_length,
            max_depth=s.max_depth,
            n_threads=s.n_threads,
            random_state=int(seed),
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            reg.fit(inputs, y)
        self.stats = dict(reg.stats_)
        mapping = {**SYMBOLS, **extra}
        candidates: list[Candidate] = []
        seen: set[str] = set()
        for point in reg.pareto_front_:
            text = reg.get_model_string(point["tree"], _PRECISION, names).replace("^", "**")
            try:
                expr = parse_expression(text, mapping)
            except (ExpressionError, RecursionError):
                continue
            key = str(expr)
            if key in seen:
                continue
            seen.add(key)
            candidates.append(make_candidate(expr, X, y, loss, self.name))
        self.timings = {"operon": time.perf_counter() - start}
        if progress:
            progress(1.0, f"{len(candidates)} candidates")
        return candidates
