"""The picked structure's coefficients refit on the fit and pick rows together (SelectionSettings.refit).

The pick compares candidates fitted on the fit rows by their loss on the pick rows; that is how a
structure (which terms) is chosen on data its fits never saw. Once it is chosen, the pick rows hold
information about its coefficients that a fit on the fit rows alone throws away (a fifth of the flight
beside three fifths). Refitting the chosen terms on both, as the candidates were fitted (least squares,
then the absolute-error refit for loss 'absolute'), is the usual select-then-refit; the validation rows
stay untouched, so validation still reports on data used for neither fitting nor picking, and the model
file's `data.roles_used` says which rows fitted the coefficients.

The refit scales each additive term of the chosen expression (its numeric factor; a term's inner
constants, such as a hub law's fitted height scale, are kept as the pick chose them).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import sympy
from scipy import sparse

from identification.body_frame import expression_columns
from identification.candidate import Candidate
from identification.collinearity import term_shapes
from identification.library import Feature
from identification.metrics import loss as loss_fn
from identification.sparse import LeastSquaresProblem, sparse_expression
from identification.specification_search import HausmanScreen
from identification.weak_noise import RefitTest, Whitener, specification_test

Rows = tuple[np.ndarray, np.ndarray, "sparse.spmatrix | None"]  # X (N,16), y (N,), weak operator or None


def refit_rows(chosen: Candidate, parts: Sequence[Rows], loss: str, irls_iterations: int,
               irls_max_terms: int, whiteners: Sequence[Whitener | None] | None = None) -> Candidate | None:
    """The chosen candidate with each additive term's coefficient refit on every part's rows together
    (parts: (X (N,16), y (N,) in the target's unit, the weak operator of those rows or None)); None when
    a term is not finite on those rows, the expression has no terms, or the refit is not finite.
    whiteners: per part, its weak rows' whitener (identification.weak_noise): when every part with rows
    has one, generalised least squares if Hausman's test does not reject it against the weak rows' own fit
    (weak_noise.specification_test), else that fit; either way each term's standard error under the
    stated noise (Candidate.standard_errors; least squares' errors, also where loss 'absolute' then refits
    the coefficients for the least absolute error) and the test (Candidate.refit_test). Without: as before."""
    shapes = term_shapes(chosen.expression)
    if not shapes:
        return None
    columns = _part_columns(shapes, parts)
    if columns is None:
        return None
    used, plain_a, plain_b = columns
    whiten = _whitened(parts, used, whiteners)
    test = specification_test([(a, b, whiteners[i]) for a, b, i in zip(plain_a, plain_b, used, strict=True)]
                              ) if whiten else None
    if test is not None and test.generalised:
        a = np.vstack([whiteners[i].apply(ai) for ai, i in zip(plain_a, used, strict=True)])
        b = np.concatenate([whiteners[i].apply(bi) for bi, i in zip(plain_b, used, strict=True)])
    else:
        a, b = np.vstack(plain_a), np.concatenate(plain_b)
    problem = LeastSquaresProblem(a, b)
    active = problem.usable.copy()
    coef = problem.solve(active)
    if loss == "absolute" and int(active.sum()) <= irls_max_terms:
        coef = problem.l1_refit(active, coef, irls_iterations)
    if not np.all(np.isfinite(coef)):
        return None
    c = terms_candidate(shapes, coef, chosen.engine)
    if test is not None:
        se = test.se_gls if test.generalised else test.se_plain
        c.standard_errors = {str(sh): (float(k), float(e)) for sh, k, e in zip(shapes, coef, se, strict=True)}
        c.refit_test = test.as_dict()
    a, b = np.vstack(plain_a), np.concatenate(plain_b)  # the loss on the rows as the candidates saw them
    c.complexity, c.train_loss = chosen.complexity, loss_fn(b, a @ coef, loss)
    c.holdout_loss = chosen.holdout_loss  # the structure's pick loss, as fitted on the fit rows alone
    c.weakest_t, c.largest_vif = chosen.weakest_t, chosen.largest_vif
    c.self_feedback, c.self_feedback_se = chosen.self_feedback, chosen.self_feedback_se
    return c


def terms_candidate(shapes: Sequence[sympy.Expr], coef: np.ndarray, engine: str,
                    ordered: bool = False, lazy: bool = False) -> Candidate:
    """The candidate sum of coef_k x shapes_k (terms in the primitive names or the 16 variables), its
    prediction from the terms' columns; complexity 0 and losses NaN for the caller to set. ordered: the
    sum's terms in sympy's order (sparse_expression); lazy: its expression built when first read."""
    shapes = list(shapes)

    def build() -> sympy.Expr:
        return sparse_expression([Feature(f"t{k}", s, engine) for k, s in enumerate(shapes)], coef, ordered)

    def predict(X_: np.ndarray, shapes: list[sympy.Expr] = shapes, coef: np.ndarray = coef) -> np.ndarray:
        return expression_columns(shapes, X_) @ coef

    return Candidate(None if lazy else build(), 0, float("nan"), engine, predict=predict,
                     linear=(tuple(shapes), coef), build=build if lazy else None)


def structure_test(shapes: Sequence[sympy.Expr], parts: Sequence[Rows],
                   whiteners: Sequence[Whitener | None] | None) -> RefitTest | None:
    """Hausman's test (weak_noise.specification_test) of the model of these terms on every part's weak
    rows together (parts as refit_rows'); None when a part has no weak operator or whitener, a term is not
    finite there, or the columns do not determine every coefficient."""
    columns = _part_columns(list(shapes), parts) if shapes else None
    if columns is None:
        return None
    used, plain_a, plain_b = columns
    if not _whitened(parts, used, whiteners):
        return None
    return specification_test([(a, b, whiteners[i]) for a, b, i in zip(plain_a, plain_b, used, strict=True)])


def pool_screen(shapes: Sequence[sympy.Expr], parts: Sequence[Rows],
                whiteners: Sequence[Whitener | None] | None, keep: Sequence[sympy.Expr] = ()
                ) -> HausmanScreen | None:
    """The specification search's screen (specification_search.HausmanScreen) of the terms shapes on every
    part's weak rows (parts as refit_rows'), less the terms not finite on some part's rows and all but one
    of terms whose columns are equal: the one in keep (the search's start, which must stay in its pool),
    else the first; None when the rows have no weak operator or whitener."""
    used = [i for i, (X, _, _) in enumerate(parts) if len(X)]
    if not shapes or not _whitened(parts, used, whiteners):
        return None
    columns = []
    for i in used:
        X, _, op = parts[i]
        columns.append(np.asarray(op @ expression_columns(list(shapes), X)))
    finite = np.all([np.isfinite(c).all(axis=0) for c in columns], axis=0)
    distinct: dict[bytes, int] = {}
    first = set(keep)
    for j in sorted(np.flatnonzero(finite), key=lambda j: shapes[j] not in first):  # keep's terms first
        distinct.setdefault(np.concatenate([c[:, j] for c in columns]).tobytes(), int(j))
    pool = sorted(distinct.values())
    return HausmanScreen.build([shapes[j] for j in pool], [
        (c[:, pool], np.asarray(parts[i][2] @ parts[i][1], float), whiteners[i])
        for c, i in zip(columns, used, strict=True)])


def _part_columns(shapes: list[sympy.Expr], parts: Sequence[Rows]
                  ) -> tuple[list[int], list[np.ndarray], list[np.ndarray]] | None:
    """(the parts with rows, each one's term columns and target on its weak rows, or its rows without
    an operator); None when a term is not finite on some part's rows or no part has rows."""
    used = [i for i, (X, _, _) in enumerate(parts) if len(X)]
    plain_a, plain_b = [], []
    for i in used:
        X, y, op = parts[i]
        cols = expression_columns(shapes, X)
        if not np.all(np.isfinite(cols)):
            return None
        if op is not None:
            cols, y = np.asarray(op @ cols), np.asarray(op @ y)
        plain_a.append(cols)
        plain_b.append(np.asarray(y, float))
    return (used, plain_a, plain_b) if plain_a else None


def _whitened(parts: Sequence[Rows], used: list[int], whiteners: Sequence[Whitener | None] | None) -> bool:
    """Whether every part with rows has weak rows and their whitener."""
    return whiteners is not None and bool(used) and all(
        parts[i][2] is not None and whiteners[i] is not None for i in used)
