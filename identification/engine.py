"""The engine interface, the engine settings, the registry, and the combined default engine.

Every engine fits one target: `fit(X (N,16) = xi then u, y (N,), target, budget, seed, loss, progress,
holdout) -> list[Candidate]`. budget is an iteration count (genetic-programming generations; PySR
iterations), never seconds, so a seed gives the same candidates on any machine; the sparse regression
always runs to completion (its work is fixed by its settings). Candidates from all engines go on one
Pareto front (complexity against error); the final pick is made on held-out data (identification.pareto).

The default engine runs the sparse regression first; where its held-out R^2 is below `gate_r2` (the
library does not explain the target) genetic programming (pyoperon) fits the residual of the sparse
model, and the sums join the sparse candidates on the front.
"""

from __future__ import annotations

import dataclasses
import os
import time
import typing
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np
import sympy
import yaml

from bridge.errors import UserError
from identification.library import DEFAULT_GROUPS, GROUPS
from identification.metrics import LOSSES, loss, r2
from identification.model_file import SYMBOLS, VARIABLE_NAMES, complexity

ENGINE_NAMES: tuple[str, ...] = ("default", "sparse", "operon", "pysr")

Progress = Callable[[float, str], None]  # (fraction done in [0, 1], short status)


@dataclass
class Candidate:
    """One model of one target: expression in the 16 variables, its size and its training loss."""

    expression: sympy.Expr
    complexity: int
    train_loss: float
    engine: str = ""
    holdout_loss: float | None = None
    predict: Callable[[np.ndarray], np.ndarray] | None = field(default=None, repr=False, compare=False)

    def evaluate(self, X: np.ndarray) -> np.ndarray:
        """The candidate's prediction on X (N,16), in the target's unit."""
        if self.predict is None:
            fn = sympy.lambdify([SYMBOLS[n] for n in VARIABLE_NAMES], self.expression, modules="numpy")
            self.predict = lambda X_, fn=fn: np.broadcast_to(
                np.asarray(fn(*[X_[:, i] for i in range(16)]), float), (X_.shape[0],)
            )
        with np.errstate(all="ignore"):
            return np.asarray(self.predict(np.asarray(X, float)), float)


def make_candidate(
    expression: sympy.Expr,
    X: np.ndarray,
    y: np.ndarray,
    loss_kind: str,
    engine: str,
    predict: Callable[[np.ndarray], np.ndarray] | None = None,
) -> Candidate:
    """A Candidate with its complexity and training loss computed."""
    c = Candidate(expression, complexity(expression), float("nan"), engine, predict=predict)
    c.train_loss = loss(y, c.evaluate(X), loss_kind)
    return c


class Engine(Protocol):
    """A symbolic-regression engine behind the common interface."""

    name: str
    timings: dict[str, float]

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
        """Fit one target; return candidates (expressions in the 16 variable names)."""
        ...


# ---------------------------------------------------------------------------------------------------
# Settings (YAML: identify --settings FILE; every key optional)


@dataclass(frozen=True)
class SparseSettings:
    """Sequentially thresholded least squares over the candidate library."""

    groups: tuple[str, ...] = DEFAULT_GROUPS  # library groups (identification.library)
    thresholds: int = 40  # points of the threshold sweep (log-spaced)
    threshold_min: float = 1e-7  # smallest term contribution kept (coef * feature std / target std)
    threshold_max: float = 0.5
    max_iterations: int = 25  # STLSQ iterations per threshold
    backward: bool = True  # also the backward-elimination path (every model size)
    forward_terms: int = 25  # also greedy forward selection up to this many terms (0: off)
    swap_max_terms: int = 8  # forward sets up to this size also try each term's simpler same-group terms
    irls_iterations: int = 10  # absolute-error refit (loss: absolute); each stops at <0.1% gain
    irls_max_terms: int = 24  # larger candidates (overfits, the held-out yardstick) stay least squares


@dataclass(frozen=True)
class OperonSettings:
    """pyoperon's NSGA-II genetic programming (objectives r2 and length: a real Pareto front)."""

    population_size: int = 500  # generations: the identify budget (an iteration count, no time cap)
    max_length: int = 40
    max_depth: int = 10
    optimizer_iterations: int = 10  # constant fitting (0 would turn it off)
    n_threads: int = 2
    allowed_symbols: str = "add,sub,mul,div,sin,cos,constant,variable"
    engineered_inputs: bool = True  # f1..f4, g, the thrust directions and cos(phi)cos(theta) as inputs


@dataclass(frozen=True)
class PysrSettings:
    """PySR (Julia) behind the same interface."""

    populations: int = 8  # iterations: the identify budget
    maxsize: int = 30
    binary_operators: tuple[str, ...] = ("+", "-", "*", "/")
    unary_operators: tuple[str, ...] = ("sin", "cos")
    probe_timeout_s: float = 60.0
    engineered_inputs: bool = True


@dataclass(frozen=True)
class SelectionSettings:
    """The pick on held-out data: the smallest candidate with loss <= best*(1+rel_tol) + abs_tol*std(y)."""

    rel_tol: float = 0.02
    abs_tol: float = 1e-4


@dataclass(frozen=True)
class EngineSettings:
    """All engine settings."""

    sparse: SparseSettings = SparseSettings()
    operon: OperonSettings = OperonSettings()
    pysr: PysrSettings = PysrSettings()
    selection: SelectionSettings = SelectionSettings()
    gate_r2: float = 0.999  # default engine: genetic programming where the sparse held-out R^2 is below this

    def as_dict(self) -> dict[str, Any]:
        """Plain mapping (for the model file)."""
        return _plain(dataclasses.asdict(self))


def _plain(value: Any) -> Any:
    if isinstance(value, dict):
        return {k: _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    return value


def _coerce(where: str, key: str, tp: Any, value: Any) -> Any:
    origin = typing.get_origin(tp)
    if dataclasses.is_dataclass(tp):
        return _section(where, key, tp, value)
    if origin is tuple:
        if isinstance(value, str):
            value = [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            raise UserError(f"{where}: key '{key}' must be a list of strings, got {value!r}")
        return tuple(value)
    if tp is bool:
        if not isinstance(value, bool):
            raise UserError(f"{where}: key '{key}' must be true or false, got {value!r}")
        return value
    if tp is int:
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise UserError(f"{where}: key '{key}' must be an integer >= 0, got {value!r}")
        return value
    if tp is float:
        if (
            isinstance(value, bool)
            or not isinstance(value, (int, float))
            or not np.isfinite(value)
            or value < 0
        ):
            raise UserError(f"{where}: key '{key}' must be a number >= 0, got {value!r}")
        return float(value)
    if tp is str:
        if not isinstance(value, str):
            raise UserError(f"{where}: key '{key}' must be a string, got {value!r}")
        return value
    raise TypeError(tp)


def _section(where: str, prefix: str, cls: type, data: Any) -> Any:
    if not isinstance(data, dict):
        raise UserError(f"{where}: key '{prefix or '(top level)'}' must be a mapping, got {data!r}")
    hints = typing.get_type_hints(cls)
    names = {f.name for f in dataclasses.fields(cls)}
    values = {}
    for key, value in data.items():
        full = f"{prefix}.{key}" if prefix else str(key)
        if key not in names:
            raise UserError(
                f"{where}: unknown key '{full}'", hint=f"keys allowed here: {', '.join(sorted(names))}"
            )
        values[key] = _coerce(where, full, hints[key], value)
    return cls(**values)


def load_engine_settings(path: str | os.PathLike[str] | None) -> EngineSettings:
    """Engine settings from a YAML file (None: the defaults); a bad key or value is a UserError."""
    if path is None:
        return EngineSettings()
    where = f"settings file {path}"
    try:
        data = yaml.safe_load(open(path, encoding="utf-8").read())
    except FileNotFoundError:
        raise UserError(f"{where}: not found") from None
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise UserError(f"{where}: cannot read it: {exc}") from None
    settings = _section(where, "", EngineSettings, data or {})
    bad = [g for g in settings.sparse.groups if g not in GROUPS]
    if bad:
        raise UserError(
            f"{where}: key 'sparse.groups': unknown group {bad[0]!r}", hint=f"known: {', '.join(GROUPS)}"
        )
    return settings


# ---------------------------------------------------------------------------------------------------
# Registry


def make_engine(name: str, settings: EngineSettings | None = None) -> Engine:
    """The engine of that name ('default', 'sparse', 'operon', 'pysr')."""
    settings = settings or EngineSettings()
    if name == "default":
        return DefaultEngine(settings)
    if name == "sparse":
        from identification.sparse import SparseEngine

        return SparseEngine(settings.sparse)
    if name == "operon":
        from identification.operon_engine import OperonEngine

        return OperonEngine(settings.operon)
    if name == "pysr":
        from identification.pysr_engine import PysrEngine

        return PysrEngine(settings.pysr)
    raise UserError(f"unknown engine {name!r}", hint=f"choose one of {', '.join(ENGINE_NAMES)}")


def split_holdout(
    X: np.ndarray, y: np.ndarray, fraction: float = 0.2
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Train on the first rows, hold out the last `fraction` (contiguous in time)."""
    n = len(y)
    cut = int(round(n * (1.0 - fraction)))
    cut = min(max(cut, 1), n - 1) if n > 1 else n
    return X[:cut], y[:cut], X[cut:], y[cut:]


class DefaultEngine:
    """Sparse regression first; pyoperon on the residual where the library does not explain the target."""

    name = "default"

    def __init__(self, settings: EngineSettings | None = None):
        self.settings = settings or EngineSettings()
        self.timings: dict[str, float] = {}
        self.gate_r2: float | None = None  # held-out R^2 of the sparse pick (the gate's input)

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
        """Fit one target: sparse candidates, plus sparse + operon-residual candidates when needed."""
        from identification.operon_engine import OperonEngine
        from identification.pareto import attach_holdout, select
        from identification.sparse import SparseEngine

        if loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}")
        start = time.perf_counter()
        self.timings = {}
        if holdout is None:
            X, y, Xh, yh = split_holdout(X, y)
        else:
            Xh, yh = holdout
        sparse = SparseEngine(self.settings.sparse)
        step = (lambda f, s: progress(0.2 * f, s)) if progress else None
        candidates = sparse.fit(X, y, target, budget, seed, loss, step, (Xh, yh))
        self.timings["sparse"] = time.perf_counter() - start
        attach_holdout(candidates, Xh, yh, loss)
        best = select(candidates, self.settings.selection, scale=float(np.std(yh)) if len(yh) else 1.0)
        self.gate_r2 = r2(yh, best.evaluate(Xh)) if len(yh) else float("nan")
        if not (self.gate_r2 < self.settings.gate_r2):
            if progress:
                progress(1.0, f"sparse R2={self.gate_r2:.6f}")
            return candidates
        op_start = time.perf_counter()
        residual = y - best.evaluate(X)
        operon = OperonEngine(self.settings.operon)
        step = (lambda f, s: progress(0.2 + 0.8 * f, "operon " + s)) if progress else None
        residual_fits = operon.fit(
            X, residual, target, budget, seed, loss, step, (Xh, yh - best.evaluate(Xh))
        )
        for rc in residual_fits:
            expr = best.expression + rc.expression
            candidates.append(
                make_candidate(
                    expr,
                    X,
                    y,
                    loss,
                    "default(sparse+operon)",
                    predict=lambda X_, a=best, b=rc: a.evaluate(X_) + b.evaluate(X_),
                )
            )
        self.timings["operon"] = time.perf_counter() - op_start
        if progress:
            progress(1.0, "done")
        return candidates
