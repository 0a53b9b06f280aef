"""Generalised least squares on weak-form rows: their noise covariance from the raw targets' (WENDy).

A raw sensor target is a short linear filter of the sensor's white noise: on our .tlog's step rows the
gyro's difference over the step ((n_k+1 - n_k) / dt: stencil (-1, 1)) and the accelerometer's mean over it
((n_k + n_k+1) / 2: stencil (1/2, 1/2)); neighbouring rows share a sample, so their noise is correlated.
Weak rows V y_raw then carry noise V B e (e white, B the stencil along each contiguous run) with covariance
sigma^2 V B B^T V^T, known up to sigma^2 (Bortz, Messenger and Dukic 2023, "Direct estimation of parameters
in ODE models using WENDy"). Least squares that ignores it weighs every weak row alike; for a differenced
gyro that noise is blue (it grows with frequency) and the ordinary fit throws away the low frequencies
where the small terms live. Measured on a 40 s closed-loop flight of the paper's vehicle with realistic
sensors, the true structure fitted to the weak rows of the gyro's differences: the rate dampings' standard
error 30-31 % (wx', wy') and 3.7 % (wz') of their value by ordinary least squares (a Monte Carlo over 30
noise draws: 28, 33, 3.9 %), 16.5, 9.7 and 1.2 % by generalised least squares on the same rows.

The covariance is banded (windows share samples only up to weak_form.overlap_lag rows apart): a banded
Cholesky factor L whitens the rows (L^-1 V A, L^-1 V y), after which the rows are independent with one
variance and ordinary least squares on them is the generalised one; its coefficient covariance
s^2 (A_w^T A_w)^-1 (s the whitened residual's RMS, the sensor noise sigma) is the coefficients' standard
error under the stated noise, which the weak rows' own residual cannot give (their t ratios were 2.4x too
large for those dampings and 3x too small for wz''s).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import linalg, sparse, stats

from identification.targets import contiguous_runs, nominal_step

if TYPE_CHECKING:
    from identification.dataset import Dataset

# the raw targets' noise as a filter of the sensor's white noise, weights on consecutive samples
STEP_DIFFERENCE = (-1.0, 1.0)  # gyro difference over a step interval (its mean derivative there)
STEP_MEAN = (0.5, 0.5)  # accelerometer mean over a step interval (its ends averaged)
WHITE = (1.0,)  # one sample per row


@dataclass(frozen=True)
class Whitener:
    """L^-1 for weak rows' noise covariance L L^T (banded lower Cholesky factor, scipy's lower form)."""

    factor: np.ndarray  # (bandwidth + 1, M): factor[i, j] = L[i + j, j]
    bandwidth: int

    @property
    def rows(self) -> int:
        """The number of weak rows it whitens."""
        return int(self.factor.shape[1])

    def lower(self) -> sparse.csr_matrix:
        """L as a sparse (M, M) lower-triangular matrix."""
        m = self.rows
        diags = [self.factor[i, : m - i] for i in range(self.bandwidth + 1)]
        return sparse.diags(diags, [-i for i in range(self.bandwidth + 1)], shape=(m, m), format="csr")

    def apply(self, a: np.ndarray) -> np.ndarray:
        """L^-1 a for weak rows a (M,) or (M, k), in the rows' unit per unit of noise."""
        return linalg.solve_banded((self.bandwidth, 0), self.factor, np.asarray(a, dtype=float),
                                   check_finite=False)


def stacked_whitener(parts: list[Whitener | None]) -> Whitener | None:
    """The whitener of several roles' weak rows one after the other (their noises independent: a
    block-diagonal covariance); None when any part has none."""
    if not parts or any(w is None for w in parts):
        return None
    band = max(w.bandwidth for w in parts)
    factor = np.zeros((band + 1, sum(w.rows for w in parts)))
    at = 0
    for w in parts:
        m = w.rows
        for i in range(w.bandwidth + 1):  # L[i + j, j] of this block only (no entry past its last row)
            factor[i, at: at + m - i] = w.factor[i, : m - i]
        at += m
    return Whitener(factor, band)


def raw_noise_operator(t: np.ndarray, flight: np.ndarray | None, stencil: tuple[float, ...]
                       ) -> sparse.csr_matrix:
    """B (N, P): raw rows' noise = B e with e white (P,), each contiguous run of a flight's rows (t s) on
    its own samples, row k of a run the stencil's weights on samples k .. k + len(stencil) - 1. Rows that
    share a time within a flight are one sample's nodes (weak_form.node_groups): they share its noise."""
    t = np.asarray(t, dtype=float)
    n = len(t)
    flights = np.zeros(n, dtype=int) if flight is None else np.asarray(flight)
    key = np.column_stack((flights, t))
    if n > 1 and len(np.unique(key, axis=0)) < n:
        distinct, sample = np.unique(key, axis=0, return_inverse=True)
        first = raw_noise_operator(distinct[:, 1], distinct[:, 0].astype(int), stencil)
        pick = sparse.csr_matrix((np.ones(n), (np.arange(n), sample.ravel())), shape=(n, len(distinct)))
        return (pick @ first).tocsr()
    w = np.asarray(stencil, dtype=float)
    rows, cols, vals = [], [], []
    p = 0
    for f in np.unique(flights):
        idx = np.flatnonzero(flights == f)
        dt = nominal_step(t[idx])
        for run in contiguous_runs(t[idx], dt) if np.isfinite(dt) else [slice(0, len(idx))]:
            r = idx[run]
            for j, wj in enumerate(w):
                rows.append(r)
                cols.append(p + np.arange(len(r)) + j)
                vals.append(np.full(len(r), wj))
            p += len(r) + len(w) - 1
    if not rows:
        return sparse.csr_matrix((n, 0))
    return sparse.csr_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))),
                             shape=(n, p))


def weak_whitener(operator: sparse.spmatrix, t: np.ndarray, flight: np.ndarray | None,
                  stencil: tuple[float, ...]) -> Whitener | None:
    """The whitener of weak rows operator @ y_raw (operator (M, N) over raw rows at t (s), flight) whose raw
    noise follows stencil (raw_noise_operator); None without rows or when the covariance is singular."""
    v = sparse.csr_matrix(operator)
    m = v.shape[0]
    if m == 0:
        return None
    s = v @ raw_noise_operator(t, flight, stencil)
    cov = (s @ s.T).tocoo()
    lower = cov.row >= cov.col
    band = int(np.max(cov.row[lower] - cov.col[lower])) if lower.any() else 0
    ab = np.zeros((band + 1, m))
    ab[cov.row[lower] - cov.col[lower], cov.col[lower]] = cov.data[lower]
    if not np.all(ab[0] > 0):
        return None
    ab[0] *= 1.0 + 1e-12  # rounding's margin: the covariance is positive definite by construction
    try:
        factor = linalg.cholesky_banded(ab, lower=True, check_finite=False)
    except linalg.LinAlgError:
        return None
    return Whitener(factor, band)


SPECIFICATION_LEVEL = 0.01  # the Hausman test's level: below it the generalised fit is not trusted


@dataclass(frozen=True)
class RefitTest:
    """Hausman's test of the generalised against the weak rows' own least squares, and both fits' errors.

    Under the stated noise and a right model both fits are unbiased and the generalised one has the smaller
    covariance, so their difference has covariance V_plain - V_gls; a difference far beyond it (p below
    SPECIFICATION_LEVEL) means the rows hold something systematic the two weigh differently (a term the
    model lacks or ties to another, a regressor off its step mean: the generalised fit, weighing the low
    frequencies, takes it in): then the weak rows' own fit stays. Standard errors in the terms' own units."""

    statistic: float
    dof: int
    p_value: float
    plain: np.ndarray  # the weak rows' least-squares coefficients
    gls: np.ndarray  # the generalised ones
    se_plain: np.ndarray  # the first's, from its sandwich covariance under the stated noise
    se_gls: np.ndarray
    rss: float = float("nan")  # the generalised fit's whitened residual sum of squares (its chi^2 times s2)
    s2: float = float("nan")  # and its variance per whitened row (the noise's level, estimated)

    @property
    def generalised(self) -> bool:
        """Whether the generalised fit passes (p at or above SPECIFICATION_LEVEL)."""
        return self.p_value >= SPECIFICATION_LEVEL

    def as_dict(self) -> dict:
        """Plain mapping for the model file."""
        return {"method": "generalised least squares" if self.generalised else "weak-row least squares",
                "hausman_statistic": round(float(self.statistic), 4), "dof": int(self.dof),
                "p_value": float(f"{self.p_value:.4g}"), "level": SPECIFICATION_LEVEL}


def stated_whitener(rows: Dataset, mask: np.ndarray, operator: sparse.spmatrix | None,
                    target: int) -> Whitener | None:
    """The whitener of a role's weak rows (its rows under mask) for target index target, when its log
    states that target's raw noise (Dataset.target_noise); None otherwise."""
    if operator is None or rows.target_noise is None or rows.target_noise[target] is None or not mask.any():
        return None
    return weak_whitener(operator, rows.t[mask], rows.flight[mask], rows.target_noise[target])


def specification_test(parts: list[tuple[np.ndarray, np.ndarray, Whitener]]) -> RefitTest | None:
    """RefitTest over parts (weak columns (M_i, k), weak target (M_i,), the rows' whitener); None when the
    columns do not determine every coefficient."""
    a = np.vstack([p[0] for p in parts])
    y = np.concatenate([p[1] for p in parts])
    scale = column_scale(a)
    k = a.shape[1]
    aw = np.vstack([w.apply(ai) for ai, _, w in parts]) / scale
    yw = np.concatenate([w.apply(yi) for _, yi, w in parts])
    if np.linalg.matrix_rank(a / scale) < k or len(y) <= k:
        return None
    b_plain = np.linalg.lstsq(a / scale, y, rcond=None)[0]
    b_gls = np.linalg.lstsq(aw, yw, rcond=None)[0]
    resid = yw - aw @ b_gls
    s2 = float(resid @ resid / (len(yw) - k))
    v_gls = s2 * np.linalg.pinv(aw.T @ aw)
    v_plain = estimate_covariance(np.linalg.pinv(a / scale), [w for _, _, w in parts], s2)
    stat, dof, p = hausman_statistic(b_plain - b_gls, v_plain, v_gls)
    se = (np.sqrt(np.maximum(np.diag(v), 0.0)) / scale for v in (v_plain, v_gls))
    return RefitTest(stat, dof, p, b_plain / scale, b_gls / scale, *se, rss=float(resid @ resid), s2=s2)


def hausman_statistic(d: np.ndarray, v_plain: np.ndarray, v_gls: np.ndarray) -> tuple[float, int, float]:
    """(statistic, dof, p) of Hausman's test of the difference d (k,) of two fits' coefficients whose
    covariances are v_plain and v_gls (k, k): d's quadratic form on the positive part of their difference
    (eigenvalues above 1e-9 of the largest), chi-squared with that many degrees of freedom (p 1 with none)."""
    lam, vec = np.linalg.eigh(v_plain - v_gls)
    keep = lam > 1e-9 * max(float(lam.max(initial=0.0)), 1e-300)
    proj = vec[:, keep].T @ d
    stat = float(np.sum(proj * proj / lam[keep]))
    dof = int(keep.sum())
    return stat, dof, (float(stats.chi2.sf(stat, dof)) if dof else 1.0)


def estimate_covariance(weights: np.ndarray, whiteners: list[Whitener], s2: float) -> np.ndarray:
    """Covariance (k, k) of the estimates weights @ y (weights (k, M): linear weights on the weak rows of
    every part, in the order of whiteners) when each part's rows carry noise s2 L L^T (L its whitener's
    factor) and the parts' noises are independent; in the estimates' units squared."""
    k = weights.shape[0]
    out = np.zeros((k, k))
    start = 0
    for w in whiteners:
        stop = start + w.rows
        q = (w.lower().T @ weights[:, start:stop].T).T  # the weights on the rows' white noise
        out += s2 * q @ q.T
        start = stop
    return out


def column_scale(a: np.ndarray) -> np.ndarray:
    """Each column's RMS (1 for a zero column): least squares well scaled whatever the terms' units."""
    scale = np.sqrt(np.mean(a * a, axis=0))
    scale[~(scale > 0)] = 1.0
    return scale


def uncertain_terms(target: str, errors: dict[str, tuple[float, float]], limit: float) -> list[str]:
    """Terminal lines naming a target's terms whose standard error (errors: term -> (coefficient, standard
    error)) is above limit times the coefficient's size: the flight does not pin them down."""
    loose = [(term, k, e) for term, (k, e) in errors.items() if not abs(e) <= limit * abs(k)]
    if not loose:
        return []
    parts = [f"{term} = {k:.4g} +- {e:.2g} ({abs(e / k):.0%})" if k else f"{term} = 0 +- {e:.2g}"
             for term, k, e in loose]
    return [f"warning: {target}: {len(loose)} coefficient(s) with a standard error above {limit:.0%} of "
            "their value under the sensors' noise (1 sigma): " + "; ".join(parts),
            "  to pin them down: a longer flight (the error shrinks as 1/sqrt of its length), or open-loop "
            "motor steps, which a rate loop does not tie to the rates"]
