"""The engine interface's types: Candidate (one model of one target), the Progress callback, Engine.

Every engine fits one target: `fit(X (N,16) = xi then u, y (N,), target, budget, seed, loss, progress,
holdout) -> list[Candidate]`. A candidate's expression is in the 16 variable names, or, for an engine that
learns in the body frame (`frame = "body"`), in the body-frame primitive names of identification.body_frame.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
import sympy

from identification.metrics import loss
from identification.model_file import SYMBOLS, VARIABLE_NAMES, complexity

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
    # how well the rows its coefficients are measured on identify its terms (the fit rows; the fit and pick
    # rows under cross-validation, SelectionSettings.identify_on_pick_rows): the weakest term's t ratio;
    # None: not measured (an engine whose candidates are not linear in their terms)
    weakest_t: float | None = None
    largest_vif: float | None = None  # the largest variance inflation factor of its terms on those rows
    # mean d(target)/d(own state) on the fit rows (1/s) and its standard error (identification.self_feedback);
    # None: not measured; the error only for a positive slope
    self_feedback: float | None = None
    self_feedback_se: float | None = None
    # () -> (weakest_t, largest_vif), run once when the pick first asks (measured()): most of an engine's
    # candidates are never near the pick, and each measure is a pass over the fit rows
    measure: Callable[[], tuple[float, float]] | None = field(default=None, repr=False, compare=False)
    # per additive term (its shape as a string): (coefficient, its standard error) in the target's unit per
    # the term's, under the rows' stated noise (the generalised refit, identification.weak_noise); None:
    # not measured
    standard_errors: dict[str, tuple[float, float]] | None = field(default=None, compare=False)
    refit_test: dict | None = field(default=None, compare=False)  # which refit, and why (weak_noise)
    # (term shapes, coefficients in the target's unit per each term's) when the candidate is that sum, as
    # fitted (refit.terms_candidate): its slopes are read from the terms' own (self_feedback.slope)
    linear: tuple[tuple[sympy.Expr, ...], np.ndarray] | None = field(default=None, repr=False, compare=False)
    # (X (N,16) -> each of its terms' mean over X's rows (k,) in its unit, NaN where not finite; their
    # coefficients (k,)) when the candidate is a constant plus that sum of terms as its engine evaluates
    # them: its slope is read from its terms' means (self_feedback.slope), each mean computed once per rows
    term_means: tuple[Callable[[np.ndarray], np.ndarray], np.ndarray] | None = field(
        default=None, repr=False, compare=False)
    # () -> train_loss, run once when first read (trained()): the polish fits thousands of moves, each picked
    # on its held-out loss, and their training losses are read only for the few on the reported front
    train: Callable[[], float] | None = field(default=None, repr=False, compare=False)
    # () -> expression, built when first read (Candidate.expression): the polish fits thousands of moves
    # and reads a few of their expressions (the pick's, its ties', the reported front's)
    build: Callable[[], sympy.Expr] | None = field(default=None, repr=False, compare=False)

    def measured(self) -> Candidate:
        """The candidate with weakest_t and largest_vif set (its deferred measure run, once)."""
        if self.measure is not None:
            self.weakest_t, self.largest_vif = self.measure()
            self.measure = None
        return self

    def trained(self) -> Candidate:
        """The candidate with train_loss set (its deferred training loss computed, once)."""
        if self.train is not None:
            self.train_loss = self.train()
            self.train = None
        return self

    def evaluate(self, X: np.ndarray) -> np.ndarray:
        """The candidate's prediction on X (N,16), in the target's unit."""
        if self.predict is None:
            fn = sympy.lambdify([SYMBOLS[n] for n in VARIABLE_NAMES], self.expression, modules="numpy")
            self.predict = lambda X_, fn=fn: np.broadcast_to(
                np.asarray(fn(*[X_[:, i] for i in range(16)]), float), (X_.shape[0],)
            )
        with np.errstate(all="ignore"):
            return np.asarray(self.predict(np.asarray(X, float)), float)


def _expression(self: Candidate) -> sympy.Expr:
    if self.build is not None:
        self._expression, self.build = self.build(), None
    return self._expression


def _set_expression(self: Candidate, value: sympy.Expr) -> None:
    self._expression, self.build = value, None


# the expression field read through its builder (Candidate.build) when the candidate has one; the dataclass's
# __init__, __eq__ and __repr__ go through the property as through the field
Candidate.expression = property(_expression, _set_expression)  # type: ignore[assignment]


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
        """Fit one target within `budget` generations/iterations; return candidates."""
        ...
