"""The discovery engine's candidates carry their terms' means (Candidate.term_means): their self-feedback
slopes (identification.self_feedback) are read from each feature's mean over the moved rows, each computed
once, where evaluating every candidate on both moved arrays was 4 % of a closed-loop target's time; the
slopes are those evaluating the candidates gives. Small seeded synthetic data."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS
from identification.discovery import DiscoveryEngine, _Columns
from identification.effects_physics import Effects, flight_rows
from identification.engine import split_holdout
from identification.self_feedback import mark_self_feedback

wx, wy, wz = (PRIMITIVE_SYMBOLS[n] for n in ("wx", "wy", "wz"))


def test_the_engines_candidates_slopes_from_their_terms_means_are_their_evaluated_slopes():
    xi, u, _ = flight_rows(1500, 3, "fang-chen-buaa", Effects())
    X = np.hstack([xi, u])
    space = DiscoveryEngine().build_space(X)
    P = _Columns(space).primitives(X)
    truth = 2.0 * wx * wy - 1.5 * wx + 0.4 * wx * wz**2  # slope in its own state wx: 2 wy - 1.5 + 0.4 wz^2
    y = sympy.lambdify([PRIMITIVE_SYMBOLS[n] for n in space.primitives], truth)(*P.T)
    Xt, yt, Xh, yh = split_holdout(X, y)
    candidates = DiscoveryEngine().fit(Xt, yt, "dwx", 1, 0, "absolute", None, (Xh, yh))
    fast = [c for c in candidates if c.term_means is not None and c.expression.has(wx)]
    assert len(fast) >= 5  # the engine's candidates holding the own state carry their terms' means
    slow = [dataclasses.replace(c, term_means=None) for c in fast]
    mark_self_feedback(fast, Xt, yt, "dwx")
    mark_self_feedback(slow, Xt, yt, "dwx")
    assert all(abs(c.self_feedback) > 0.01 for c in fast)  # slopes that could differ
    for a, b in zip(fast, slow, strict=True):
        assert a.self_feedback == pytest.approx(b.self_feedback, rel=1e-9, abs=1e-12)
        assert (a.self_feedback_se is None) == (b.self_feedback_se is None)
