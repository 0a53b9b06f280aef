"""Test helper: a synthetic flight whose targets come from the true model."""

from __future__ import annotations

import numpy as np

from identification.dataset import Dataset
from identification.true_model import random_states, true_model


def synthetic_dataset(n: int, seed: int, noise: float = 0.0) -> Dataset:
    """Random states and rotor speeds, targets from the true model (+ noise x each target's std), 250 Hz."""
    xi, u = random_states(n, seed)
    y = true_model("fang-chen-buaa").accelerations(xi, u)
    if noise:
        y = y + noise * y.std(axis=0) * np.random.default_rng(seed + 1).standard_normal(y.shape)
    return Dataset(t=np.arange(n) * 0.004, xi=xi, u=u, targets=y, source="synthetic", format="synthetic",
                   target_source="truth")
