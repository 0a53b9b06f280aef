"""bridge.integration.rk4_step (generated straight-line code per state length) against the textbook form."""

from __future__ import annotations

import math
import random

import pytest

from bridge.integration import rk4_step


def textbook_rk4(f, s, u, h):
    """Classical RK4 written out with comprehensions (the form rk4_step had before it was unrolled)."""
    k1 = f(s, u)
    k2 = f([a + 0.5 * h * b for a, b in zip(s, k1, strict=True)], u)
    k3 = f([a + 0.5 * h * b for a, b in zip(s, k2, strict=True)], u)
    k4 = f([a + h * b for a, b in zip(s, k3, strict=True)], u)
    h6 = h / 6.0
    return [a + h6 * (b + 2.0 * (c + d) + e) for a, b, c, d, e in zip(s, k1, k2, k3, k4, strict=True)]


@pytest.mark.parametrize("n", [1, 3, 17])
def test_rk4_step_is_bit_identical_to_the_textbook_form(n):
    rng = random.Random(n)

    def f(s, u):  # nonlinear, couples every element
        total = sum(s)
        return tuple(math.sin(x) * u[0] - 0.3 * x * x + 0.01 * total + u[1] * i for i, x in enumerate(s))

    for _ in range(50):
        s = [rng.uniform(-3, 3) for _ in range(n)]
        u = (rng.uniform(-2, 2), rng.uniform(-1, 1))
        h = rng.uniform(1e-4, 0.05)
        ours = rk4_step(f, s, u, h)
        assert ours == textbook_rk4(f, s, u, h)  # exact: same operations in the same order
        assert rk4_step(f, s, u, h, list(f(s, u))) == ours  # a given first slope is used as is


def test_rk4_step_integrates_exponential_decay():
    """ds/dt = -s over 1 s in 100 steps: RK4's error is far below 1e-9."""
    s = [1.0, 2.0]
    for _ in range(100):
        s = rk4_step(lambda x, u: (-x[0], -x[1]), s, (), 0.01)
    assert s == pytest.approx([math.exp(-1.0), 2.0 * math.exp(-1.0)], abs=1e-9)


def test_known_elements_follow_their_closed_form_and_drive_the_rest():
    """x' = y, y' = (c - y)/T (a lag toward a held c): with y's closed form given, y ends exact and x is RK4
    along the exact y (Simpson on an exponential), far closer than classical RK4 with one step of T/5."""
    tau, c, h = 0.02, 300.0, 0.004
    f = lambda s, u: (s[1], (u[0] - s[1]) / tau)  # noqa: E731
    s0 = [0.0, 500.0]
    exact_y = c + (s0[1] - c) * math.exp(-h / tau)
    exact_x = c * h + (s0[1] - c) * tau * (1.0 - math.exp(-h / tau))
    known = ([c + (s0[1] - c) * math.exp(-0.5 * h / tau)], [exact_y])
    ours = rk4_step(f, s0, [c], h, known=known)
    classical = rk4_step(f, s0, [c], h)
    assert ours[1] == exact_y
    assert abs(ours[0] - exact_x) < abs(classical[0] - exact_x) / 20.0
    assert abs(classical[0] - exact_x) > 1e-7  # classical RK4 is measurably off here
    # the first slope may be given with the known path, as without it
    assert rk4_step(f, s0, [c], h, list(f(s0, [c])), known) == ours
