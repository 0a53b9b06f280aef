"""Huber weights of a fit's rows: least squares that follows the absolute loss where target errors are rare.

A flight's truth targets are exact between its command kinks and off by up to 50x the typical residual at
them (paper-train's held commands: the RMS of the true model's residual 50x its robust scale); sensor
targets have outliers of their own. The engines fit and pick by the absolute error (loss 'absolute'), but
their sparse paths, screening and least-squares solves weigh each row by its squared residual, so those
few rows choose the terms: a term that fits the kinks beats the true one (on `fang-chen-aero`, the true
structure of fz was 30 % better on the pick rows than the engine's). Huber's M-estimator (Huber 1964)
weighs row i by w_i = min(1, k s / |r_i|), r_i its residual under the current model and s the residual's
robust standard deviation (1.4826 x its median absolute deviation), k = 1.345 (95 % of least squares'
efficiency for normal errors): rows within k s count fully, the rest as in the absolute loss.
"""

from __future__ import annotations

import numpy as np

HUBER_K = 1.345  # Huber's tuning constant: 95 % efficiency at the normal distribution


def robust_sigma(resid: np.ndarray) -> float:
    """The residual's (N,) robust standard deviation: 1.4826 x its median absolute deviation (the standard
    deviation for normal errors; a few large rows do not move it); 0 for no rows."""
    r = np.asarray(resid, dtype=float)
    if r.size == 0:
        return 0.0
    return 1.4826 * float(np.median(np.abs(r - np.median(r))))


def huber_weights(resid: np.ndarray, k: float = HUBER_K) -> np.ndarray | None:
    """Row weights (N,) in (0, 1] from a model's residual (N,) (module docstring); None when the residual's
    robust spread is 0 (an exact fit: every row counts fully)."""
    r = np.asarray(resid, dtype=float)
    r = r - float(np.median(r))
    s = robust_sigma(r)
    if not np.isfinite(s) or s <= 0.0:
        return None
    a = np.abs(r)
    with np.errstate(divide="ignore"):
        return np.where(a > k * s, k * s / np.where(a > 0, a, 1.0), 1.0)
