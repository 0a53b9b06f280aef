"""Paired comparison of two models' losses on the same rows: is one better beyond the rows' noise?"""

from __future__ import annotations

import numpy as np

EXACT = 1e-9  # residuals below this fraction of the targets' spread are float rounding, not evidence


def paired_loss_t(y: np.ndarray, a: np.ndarray, b: np.ndarray, loss: str, blocks: int) -> float:
    """t ratio of the pick-row loss of predictions a against b (both (N,), targets y): the rows' loss
    differences (|y - a| - |y - b| for the absolute loss, squared errors for the squared loss) averaged, over
    the standard error of that mean from `blocks` contiguous blocks' means (batch means: the rows' own
    autocorrelation, and the weak rows' window overlap, stay inside a block). Negative: a is better. 0 when
    the two predict the same or both fit every row to rounding (residuals within EXACT of the targets'
    spread); +-inf when the differences do not vary between blocks; NaN when not finite."""
    ra, rb = y - np.asarray(a, float), y - np.asarray(b, float)
    d = np.abs(ra) - np.abs(rb) if loss == "absolute" else ra * ra - rb * rb
    if not np.all(np.isfinite(d)):
        return float("nan")
    spread = float(np.std(y) or np.max(np.abs(y))) if len(y) else 0.0
    if len(y) and max(np.max(np.abs(ra)), np.max(np.abs(rb))) <= EXACT * spread:
        return 0.0  # both exact to rounding: "better" is the arithmetic's last bits (machine-dependent)
    mean = float(np.mean(d)) if len(d) else 0.0
    k = int(min(max(blocks, 2), len(d)))
    if k < 2 or mean == 0.0:
        return 0.0
    means = np.asarray([float(np.mean(part)) for part in np.array_split(d, k)])
    se = float(np.std(means, ddof=1)) / np.sqrt(k)
    if not se > 0.0:
        return float(np.sign(mean)) * float("inf")
    return mean / se
