"""The one fixed-step integrator every simulation uses: classical RK4 on a state list of floats.

Plain floats, not numpy: the SITL takes four of these steps per 4 ms exchange, thousands of exchanges per wall
second, and numpy is slower than lists for 17 numbers. Units are whatever the derivative's are (SI here).

For each state length the step is generated once as straight-line code (every state element its own local
variable, no zip or comprehension): about twice as fast as comprehensions over zip() for the SITL's 17
floats, with the same operations in the same order, so the results are bit-identical.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

Derivative = Callable[[Sequence[float], Sequence[float]], Sequence[float]]
Stepper = Callable[..., list[float]]
_STEPPERS: dict[tuple[int, int], Stepper] = {}


def rk4_step(f: Derivative, s: Sequence[float], u: Sequence[float], h: float,
             k1: Sequence[float] | None = None,
             known: tuple[Sequence[float], Sequence[float]] | None = None) -> list[float]:
    """One RK4 step of ds/dt = f(s, u) over h seconds, u held constant; returns the new state list.

    k1: f(s, u) when the caller already has it (it is then not evaluated again).
    known: (values at h/2, values at h) of the state's last m elements when their path over the step is
    known in closed form (a first-order lag toward a held command: c + (s - c) exp(-t/T)). The stages and
    the result take those values instead of RK4's estimates of them, so the other elements are integrated
    along the exact path: classical RK4 on a lag of T = 5 h misses its stage values by 0.5 % of the step's
    change, which the rest of the state feels as a force error in every transient.
    """
    m = 0 if known is None else len(known[0])
    stepper = _STEPPERS.get((len(s), m))
    if stepper is None:
        stepper = _STEPPERS[(len(s), m)] = _unrolled_rk4(len(s), m)
    if m:
        return stepper(f, s, u, h, k1, known[0], known[1])
    return stepper(f, s, u, h, k1)


def lag_path(
    values: Sequence[float], targets: Sequence[float], half_decay: float
) -> tuple[list[float], list[float]]:
    """rk4_step's `known` for first-order lags toward held targets: (values at h/2, values at h) of
    c + (x - c) exp(-t/T), half_decay = exp(-h/(2T)). (The SITL's step writes it out for its four rotors.)"""
    mid = [c + (x - c) * half_decay for x, c in zip(values, targets, strict=True)]
    end = [c + (x - c) * half_decay * half_decay for x, c in zip(values, targets, strict=True)]
    return mid, end


def _unrolled_rk4(n: int, m: int = 0) -> Stepper:
    """The RK4 step for states of n floats, the last m known (rk4_step), as straight-line code (see the
    module docstring)."""
    idx = range(n)

    def names(p: str) -> str:
        return ", ".join(f"{p}{i}" for i in idx) + ("," if n == 1 else "")

    def stage(p: str, step: str, tail: str) -> str:
        return "[" + ", ".join(f"s{i} + {step} * {p}{i}" if i < n - m else f"{tail}[{i - n + m}]"
                               for i in idx) + "]"

    final = "[" + ", ".join(f"s{i} + h6 * (a{i} + 2.0 * (b{i} + c{i}) + d{i})" if i < n - m
                            else f"te[{i - n + m}]" for i in idx) + "]"
    source = (
        f"def rk4(f, s, u, h, k1{', tm, te' if m else ''}):\n"
        "    hh = 0.5 * h\n"
        "    if k1 is None:\n"
        "        k1 = f(s, u)\n"
        f"    {names('s')} = s\n"
        f"    {names('a')} = k1\n"
        f"    {names('b')} = f({stage('a', 'hh', 'tm')}, u)\n"
        f"    {names('c')} = f({stage('b', 'hh', 'tm')}, u)\n"
        f"    {names('d')} = f({stage('c', 'h', 'te')}, u)\n"
        "    h6 = h / 6.0\n"
        f"    return {final}\n"
    )
    namespace: dict = {}
    exec(source, namespace)  # noqa: S102 - generated from the state length only
    return namespace["rk4"]
