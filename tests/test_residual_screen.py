"""The polish screens the pick's cross-validated residual over the fit and pick rows
(SelectionSettings.cv_polish_residual, DiscoveryEngine.residual_features): a term only the pick rows excite,
which the engine (screening on the fit rows alone) cannot find, is still found."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS
from identification.collinearity import term_shapes
from identification.dataset import Dataset
from identification.discovery import DiscoveryEngine
from identification.engine import EngineSettings
from identification.identify import identify
from identification.true_model import random_states, true_model

S = PRIMITIVE_SYMBOLS


def _flight(n: int, seed: int, yaw_rate: float) -> Dataset:
    """Random states and rotor speeds of the paper vehicle with the yaw rate (rad/s FRD) a slow sine of this
    amplitude, targets from the true model with 1 % noise, 250 Hz."""
    xi, u = random_states(n, seed)
    t = np.arange(n) * 0.004
    xi[:, 11] = yaw_rate * np.sin(2 * np.pi * 0.3 * t + seed)
    y = true_model("fang-chen-buaa").accelerations(xi, u)
    y = y + 0.01 * y.std(axis=0) * np.random.default_rng(seed + 1).standard_normal(y.shape)
    return Dataset(t=t, xi=xi, u=u, targets=y, source=f"synthetic-{seed}", format="synthetic",
                   target_source="truth")


def test_a_coupling_only_the_pick_flight_excites_is_found():
    """The training flight barely yaws (2 mrad/s), the pick flight yaws at 2 rad/s: the roll equation's
    Euler coupling wy*wz is in none of the engine's candidates (fitted on the training flight), and only the
    residual screen brings it in; without it the model misses it (its validation R^2 0.997 shows it)."""
    train, pick, validate = _flight(3000, 1, 0.002), _flight(1000, 2, 2.0), _flight(1000, 3, 2.0)
    found = {}
    for screen in (5, 0):
        settings = EngineSettings()
        settings = replace(settings, selection=replace(settings.selection, cv_polish_residual=screen))
        model = identify(train, pick=pick, validate=validate, targets=("dwx",), budget=10, seed=0,
                         progress=False, settings=settings)
        target = model.body.targets["dwx"]
        found[screen] = (term_shapes(target.expression), target.metrics["validation"]["r2"])
    assert S["wy"] * S["wz"] in found[5][0]
    assert S["wy"] * S["wz"] not in found[0][0]
    assert found[5][1] > 0.999 > found[0][1]  # 1 % noise: R^2 0.9999 at best


def test_residual_features_rank_the_feature_the_residual_holds():
    """Over the fit rows and rows the engine never fitted, the feature the residual is made of ranks first;
    the terms passed to skip are never proposed, nor the height features (the hub law stands for them),
    even for a residual made of one."""
    rng = np.random.default_rng(4)
    xi, u = random_states(3000, 6)
    X = np.hstack([xi, u])
    engine = DiscoveryEngine()
    y = 0.3 * X[:, 9] + 0.01 * rng.standard_normal(len(X))  # wx: something to fit
    engine.fit(X[:2000], y[:2000], "dwx", 2, 0, "squared", None, (X[2000:2500], y[2000:2500]))
    parts = [(X[:2000], None), (X[2000:], None)]
    residual = 0.5 * X[:, 10] * X[:, 11] + 0.01 * rng.standard_normal(len(X))  # wy*wz
    top = engine.residual_features(parts, residual, 3)
    assert top[0] == S["wy"] * S["wz"]
    assert S["wy"] * S["wz"] not in engine.residual_features(parts, residual, 3, skip=[S["wy"] * S["wz"]])
    assert isinstance(top[0], sympy.Expr) and len(top) == 3
    space = engine._final[0]
    heights = {e for e, h in zip(space.expressions, space.height_features(), strict=False) if h}
    assert S["h"] ** 2 in heights
    of_height = 0.5 * X[:, 2] ** 2 + 0.01 * rng.standard_normal(len(X))  # h^2 (h = -z, m)
    assert not set(engine.residual_features(parts, of_height, 10)) & heights
