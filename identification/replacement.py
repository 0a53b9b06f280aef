"""Replacement screening: for each term of a model, the feature that would serve better in its place.

Sure independence screening ranks features by their correlation with the residual, so it only finds what
the model lacks. A term already in the model that stands for a near-collinear, truer one is never
challenged: rung-1 features are always in the pool, so `wy` enters first where the physics is
wy (u1 + u2 + u3 + u4) (the rotor sum nearly constant), and the screening then fits what is left,
wy (sum - its mean), with wrong terms (on `fang-chen-aero`'s fz: wy, wy u_i^2; the true structure was 30 %
better on the pick rows). This is the replacement step of stepwise regression (Miller 2002, sequential
replacement): for each term j of the model, among the features most correlated with it, the one that
lowers the (row-weighted) residual sum of squares most when it takes j's place, kept when it does better
than j itself. The engine adds those to its pool; the sparse paths and the pick on held-out rows decide.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from scipy.linalg import solve_triangular


def replacements(
    F: np.ndarray,
    Z: np.ndarray,
    y: np.ndarray,
    terms: Sequence[int],
    exclude: Sequence[int],
    weights: np.ndarray | None = None,
    nearest: int = 40,
    correlations: dict[int, np.ndarray] | None = None,
) -> list[int]:
    """Column indices of F (N,M) that fit y (N,) better than a term of the model in its place (module
    docstring; F column-major gathers its columns fastest, the same values). terms: the model's columns of F
    (its constant implied); exclude: columns not to propose (the pool); Z: F standardised
    (identification.discovery._standardized, NaN where unusable); weights (N,): row weights of the sums of
    squares; nearest: how many of the features most correlated with a term are tried; correlations: a term's
    |correlation| with every column of Z, kept by the caller for as long as Z is the same (the rounds' picks
    share most terms, and each is a pass over all of Z).
    """
    terms = [int(j) for j in terms]
    if not terms:
        return []
    sw = np.ones(len(y)) if weights is None else np.sqrt(np.asarray(weights, dtype=float))
    blocked = np.zeros(F.shape[1], dtype=bool)
    blocked[np.asarray(list(exclude), dtype=int)] = True
    blocked[terms] = True
    out: list[int] = []
    yw = y * sw
    weighted = np.hstack([np.ones((len(y), 1)), F[:, terms]]) * sw[:, None]  # the model's columns, once
    # one factorisation of the whole model for every term: the span of the model less term j is the
    # model's span less one direction u_j = Q g_j (g_j = R^-T e_j, normalised: in the span, orthogonal to
    # every other column), so a column's part outside the model less j is its part outside the model plus
    # its u_j part, and the residual likewise (where a QR of the model less j per term was most of the time)
    q, r = np.linalg.qr(weighted, mode="reduced")
    diag = np.abs(np.diag(r))
    if not (np.all(np.isfinite(r)) and diag.min() > 1e-10 * diag.max()):
        return _replacements_term_by_term(F, Z, terms, blocked, weighted, yw, sw, nearest, correlations)
    g = solve_triangular(r, np.eye(len(diag)), trans="T")  # column i: R^-T e_i
    g /= np.linalg.norm(g, axis=0)
    qy = q.T @ yw
    r_all = yw - q @ qy  # the residual of the whole model
    for at, j in enumerate(terms):
        near = _nearest(Z, j, blocked, nearest, correlations)
        if not near:
            continue
        raw = F[:, [j, *near]]
        cols = raw * sw[:, None]
        qc = q.T @ cols
        b = g[:, at + 1] @ qc  # its u_j part
        # its part outside the whole model: what its norm leaves beside its part in the model
        den = np.sum(cols * cols, axis=0) - np.sum(qc * qc, axis=0) + b * b
        num = r_all @ cols + float(g[:, at + 1] @ qy) * b
        _take_better(raw, num, den, near, out)
    return out


def _take_better(raw: np.ndarray, num: np.ndarray, den: np.ndarray, near: list[int], out: list[int]) -> None:
    """Append to out the feature of near that lowers the residual sum of squares most in the term's place,
    when it does better than the term: raw (N, 1 + len(near)) the term's and near's columns, num and den each
    column's inner product with the residual of the model less the term and its squared norm outside it."""
    with np.errstate(all="ignore"):
        gain = np.where(den > 1e-12 * np.maximum(np.sum(raw**2, axis=0), 1e-300), num**2 / den, 0.0)
    k = int(np.argmax(gain[1:]))
    if gain[1 + k] > gain[0] and near[k] not in out:
        out.append(near[k])


def _nearest(Z: np.ndarray, j: int, blocked: np.ndarray, nearest: int,
             correlations: dict[int, np.ndarray] | None) -> list[int]:
    """The columns of Z most correlated with column j (at most `nearest`, none blocked, a correlation
    above 0); none when column j is not finite."""
    zj = Z[:, j]
    if not np.all(np.isfinite(zj)):
        return []
    corr = None if correlations is None else correlations.get(j)
    if corr is None:
        with np.errstate(all="ignore"):
            corr = np.abs(np.nan_to_num(Z.T @ zj, nan=0.0)) / len(zj)
        if correlations is not None:
            correlations[j] = corr
    corr = corr.copy()
    corr[blocked] = -1.0
    return [int(k) for k in np.argsort(-corr, kind="stable")[:nearest] if corr[k] > 0.0]


def _replacements_term_by_term(F: np.ndarray, Z: np.ndarray, terms: list[int], blocked: np.ndarray,
                               weighted: np.ndarray, yw: np.ndarray, sw: np.ndarray, nearest: int,
                               correlations: dict[int, np.ndarray] | None) -> list[int]:
    """replacements with the model less each term factorised anew (a model whose columns are (nearly)
    dependent, where the whole model's factor cannot be inverted)."""
    out: list[int] = []
    for at, j in enumerate(terms):
        near = _nearest(Z, j, blocked, nearest, correlations)
        if not near:
            continue
        q = np.linalg.qr(np.delete(weighted, at + 1, axis=1), mode="reduced")[0]
        r = yw - q @ (q.T @ yw)
        raw = F[:, [j, *near]]
        cols = raw * sw[:, None]
        cols = cols - q @ (q.T @ cols)
        _take_better(raw, r @ cols, np.sum(cols * cols, axis=0), near, out)
    return out
