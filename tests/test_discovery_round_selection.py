"""The engine's pick between its rounds (the model whose residual the next round screens against) follows the
selection settings the user gave, as the final pick does, without the identification rules (t ratio, VIF).
Until session 75 the rounds picked with the defaults whatever the settings file said, so a `selection.abs_tol`
set in a file and the same value made the default gave different models. Small seeded synthetic data."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import sympy

import identification.discovery as discovery
from identification.body_frame import PRIMITIVE_SYMBOLS
from identification.discovery import DiscoveryEngine, _Columns
from identification.effects_physics import Effects, flight_rows
from identification.engine import split_holdout
from identification.engine_settings import SelectionSettings, load_engine_settings

wx, wy, wz = (PRIMITIVE_SYMBOLS[n] for n in ("wx", "wy", "wz"))


def _rows() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Fit and holdout rows of y = 2 wx wy + 0.5 wz^2 - 1.5 wy (rad/s^2) over a seeded synthetic flight."""
    xi, u, _ = flight_rows(1500, 0, "fang-chen-buaa", Effects())
    X = np.hstack([xi, u])
    space = DiscoveryEngine().build_space(X)
    P = _Columns(space).primitives(X)
    truth = 2.0 * wx * wy + 0.5 * wz**2 - 1.5 * wy
    y = sympy.lambdify([PRIMITIVE_SYMBOLS[n] for n in space.primitives], truth)(*P.T)
    return split_holdout(X, y)


def _picks(monkeypatch: pytest.MonkeyPatch, engine: DiscoveryEngine) -> list[SelectionSettings]:
    """The selection settings of every pick the engine's fit makes (a spy on discovery.select)."""
    seen: list[SelectionSettings] = []
    real = discovery.select

    def spy(candidates: list, settings: SelectionSettings, *args: object, **kwargs: object) -> object:
        seen.append(settings)
        return real(candidates, settings, *args, **kwargs)

    monkeypatch.setattr(discovery, "select", spy)
    Xt, yt, Xh, yh = _rows()
    engine.fit(Xt, yt, "dwx", 1, 0, "absolute", None, (Xh, yh))
    return seen


def test_the_rounds_pick_with_the_tolerances_of_the_settings_file(
        monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """selection.abs_tol and rel_tol from a settings file reach every pick of the fit; the rounds' picks
    drop the identification rules (min_t 0, no VIF cap) and keep the rest."""
    path = tmp_path / "engine.yaml"
    path.write_text("selection:\n  abs_tol: 1.0e-3\n  rel_tol: 0.05\n  max_self_feedback_t: 2.0\n")
    selection = load_engine_settings(path).selection
    seen = _picks(monkeypatch, DiscoveryEngine(selection=selection))
    rounds = [s for s in seen if s.min_t == 0.0]
    assert rounds, "the fit made no pick between rounds"
    assert all(s.abs_tol == 1e-3 and s.rel_tol == 0.05 for s in seen), seen
    assert all(math.isinf(s.max_vif) and s.max_self_feedback_t == 2.0 for s in rounds), rounds


def test_the_default_rounds_pick_is_the_default_pick_without_its_identification_rules(
        monkeypatch: pytest.MonkeyPatch) -> None:
    """With no settings the rounds pick as before (the defaults' tolerances, no t ratio or VIF rule)."""
    seen = _picks(monkeypatch, DiscoveryEngine())
    rounds = [s for s in seen if s.min_t == 0.0]
    default = SelectionSettings()
    assert rounds
    assert all(s.abs_tol == default.abs_tol and s.rel_tol == default.rel_tol and math.isinf(s.max_vif)
               for s in rounds), rounds
