"""Fit metrics of the paper's Table I: RMSE, MAE (both in the target's unit) and R^2."""

from __future__ import annotations

from typing import Any

import numpy as np

LOSSES = ("absolute", "squared")


def rmse(y: np.ndarray, y_hat: np.ndarray) -> float:
    """Root mean squared error, in the target's unit."""
    d = np.asarray(y, float) - np.asarray(y_hat, float)
    return float(np.sqrt(np.mean(d * d))) if d.size else float("nan")


def mae(y: np.ndarray, y_hat: np.ndarray) -> float:
    """Mean absolute error, in the target's unit (the paper's fitness, divided by n)."""
    d = np.asarray(y, float) - np.asarray(y_hat, float)
    return float(np.mean(np.abs(d))) if d.size else float("nan")


def r2(y: np.ndarray, y_hat: np.ndarray) -> float:
    """Coefficient of determination 1 - SS_res/SS_tot (1 for a perfect fit; nan for a constant target)."""
    y = np.asarray(y, float)
    d = y - np.asarray(y_hat, float)
    ss_tot = float(np.sum((y - y.mean()) ** 2)) if y.size else 0.0
    if ss_tot == 0.0:
        return float("nan")
    return 1.0 - float(np.sum(d * d)) / ss_tot


def loss(y: np.ndarray, y_hat: np.ndarray, kind: str = "absolute") -> float:
    """The fitting loss: 'absolute' = MAE (the paper's), 'squared' = RMSE; non-finite predictions -> inf."""
    if kind not in LOSSES:
        raise ValueError(f"loss must be one of {LOSSES}, got {kind!r}")
    y_hat = np.asarray(y_hat, float)
    if not np.all(np.isfinite(y_hat)):
        return float("inf")
    return mae(y, y_hat) if kind == "absolute" else rmse(y, y_hat)


def table_metrics(y: np.ndarray, y_hat: np.ndarray) -> dict[str, float]:
    """{rmse, mae, r2} of one target."""
    return {"rmse": rmse(y, y_hat), "mae": mae(y, y_hat), "r2": r2(y, y_hat)}


def weak_metrics(y: np.ndarray, y_hat: np.ndarray, operator: Any = None) -> dict[str, float]:
    """table_metrics of y_hat against y (N,), after a weak-form matrix V (M, N) on both when one is given
    (rows where either is not finite are left out)."""
    if operator is not None:
        y, y_hat = operator @ np.asarray(y, float), operator @ np.asarray(y_hat, float)
    ok = np.isfinite(y) & np.isfinite(y_hat)
    return table_metrics(np.asarray(y)[ok], np.asarray(y_hat)[ok])
