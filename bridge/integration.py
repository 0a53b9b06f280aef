"""The one fixed-step integrator every simulation uses: classical RK4 on a state list of floats.

Plain floats, not numpy: the SITL takes four of these steps per 4 ms exchange, thousands of exchanges per wall
second, and numpy is slower than lists for 17 numbers. Units are whatever the derivative's are (SI here).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

Derivative = Callable[[Sequence[float], Sequence[float]], Sequence[float]]


def rk4_step(f: Derivative, s: Sequence[float], u: Sequence[float], h: float,
             k1: Sequence[float] | None = None) -> list[float]:
    """One RK4 step of ds/dt = f(s, u) over h seconds, u held constant; returns the new state list.

    k1: f(s, u) when the caller already has it (it is then not evaluated again).
    """
    hh = 0.5 * h
    if k1 is None:
        k1 = f(s, u)
    # zip without strict=: all have the state's length by construction, and strict= doubles the cost here
    k2 = f([a + hh * b for a, b in zip(s, k1)], u)  # noqa: B905
    k3 = f([a + hh * b for a, b in zip(s, k2)], u)  # noqa: B905
    k4 = f([a + h * b for a, b in zip(s, k3)], u)  # noqa: B905
    h6 = h / 6.0
    return [a + h6 * (b + 2.0 * (c + d) + e) for a, b, c, d, e in zip(s, k1, k2, k3, k4)]  # noqa: B905
