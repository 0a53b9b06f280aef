"""Structures the specification test screens fast: Hausman's test of any subset of a pool of terms.

specification_pick chooses among the structures the cross-validated polish happened to visit; when none of
them passes Hausman's test (weak_noise.specification_test) the model may lack a term the flight holds, or
hold a stand-in for one. Measured on realistic-sensor fang-chen-aero (seed 31, the training flight's weak
rows), dwy as picked: p 5.6e-34; with wy added 6e-30, with wz^2 added 1e-40, with both 0.012 (the true
structure 0.44): the test asks for two terms at once, which no tie and no one-term move gives.

So the search walks from the pick over the pool (every candidate's terms and the polish's extra ones, and each
product among them less one factor: with_factors), one move at a time (add a term, or put one in another's
place), to the structure whose generalised fit leaves the least whitened residual (forward stepwise
generalised least squares, the test its stopping rule), for at most SelectionSettings.specification_search
steps. HausmanScreen scores every move from the pool's Gram matrices, in microseconds each. At each step the
simplest structures the screen passes (then the best fitting) are checked by the exact test and then, as a
candidate scored like the polish's moves, by the pick's own rule and tolerance (every term identified, the
cross-validated loss within tolerance of the best): a term the test asks for but the flight does not pin down
is never added. Walking to the structure the test rejects least instead took seed 31's dwy to wy (u1^2 + .. +
u4^2), a stand-in that fits worse than wy, and on to wz^4: five extras in all (136 / 2 / 5); a move that fits
worse than where it starts is never offered (a structure that fits nothing, a constant in place of every term,
passes the test: both fits agree on nothing).

A walk only grows its structure, so the true term beside the pick's stand-ins for it (vb |v| beside vb,
vb ub^2 and vb wb^2, its expansion) passes the test but is not identified, and the rule declines it. So a
passing structure the rule declines is reduced, general to specific: one term fewer at a time, each time the
one whose removal fits least worse, while the test still passes and it fits at least as well as the start
(reduced), and each reduction is offered to the rule in turn. Measured on seed 41's realistic aero (fy):
the pick's stand-ins gave way to vb |v| (p 0.49), 135 / 1 / 10 -> 136 / 0 / 7.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from typing import TypeVar

import numpy as np
import sympy

from identification.weak_noise import SPECIFICATION_LEVEL, Whitener, column_scale, hausman_statistic

TRIES_PER_STEP = 4  # the simplest passing structures of a step checked by the exact test and the rule
MAX_CONDITION = 1e10  # a subset's Gram matrix beyond this condition number does not determine its terms
T = TypeVar("T")


@dataclass(frozen=True)
class SearchSpace:
    """What the search walks over: its screen of a pool holding the start's terms (built when first asked
    for, given the start; None: no search), how a structure becomes a candidate scored like the pick's
    (None: it cannot), and at most how many steps."""

    screen: Callable[[Sequence[sympy.Expr]], HausmanScreen | None]
    make: Callable[[list[sympy.Expr]], object | None]
    steps: int


@dataclass
class HausmanScreen:
    """Gram matrices of a pool's weak columns (scaled to unit RMS) from which Hausman's test of any subset
    follows without touching the rows: the plain fit's (plain, plain_y), the generalised fit's (white,
    white_y, white_yy) and the plain fit's noise (noise: A^T L L^T A, L the whiteners' factors)."""

    terms: list[sympy.Expr]
    plain: np.ndarray
    plain_y: np.ndarray
    white: np.ndarray
    white_y: np.ndarray
    white_yy: float
    noise: np.ndarray
    rows: int

    @classmethod
    def build(cls, terms: Sequence[sympy.Expr], parts: Sequence[tuple[np.ndarray, np.ndarray, Whitener]]
              ) -> HausmanScreen:
        """The screen of terms from parts (weak columns (M_i, P) of the terms, weak target (M_i,), the rows'
        whitener), as weak_noise.specification_test takes them."""
        scale = column_scale(np.vstack([a for a, _, _ in parts]))
        p = len(terms)
        plain, white, noise = np.zeros((p, p)), np.zeros((p, p)), np.zeros((p, p))
        plain_y, white_y, white_yy, rows = np.zeros(p), np.zeros(p), 0.0, 0
        for a, y, w in parts:
            a = a / scale
            aw, yw = w.apply(a), w.apply(y)
            la = w.lower().T @ a
            plain += a.T @ a
            plain_y += a.T @ y
            white += aw.T @ aw
            white_y += aw.T @ yw
            white_yy += float(yw @ yw)
            noise += la.T @ la
            rows += len(y)
        return cls(list(terms), plain, plain_y, white, white_y, white_yy, noise, rows)

    def p_value(self, subset: Sequence[int]) -> tuple[float, float]:
        """(p, rss): Hausman's test's p-value of the terms at subset and the generalised fit's whitened
        residual sum of squares; (0, inf) when the subset does not determine its coefficients."""
        s = np.asarray(subset)
        k = len(s)
        g, gw = self.plain[np.ix_(s, s)], self.white[np.ix_(s, s)]
        if not np.linalg.cond(g) < MAX_CONDITION:
            return 0.0, float("inf")
        try:
            gi, gwi = np.linalg.inv(g), np.linalg.inv(gw)
        except np.linalg.LinAlgError:
            return 0.0, float("inf")
        b_plain, b_gls = gi @ self.plain_y[s], gwi @ self.white_y[s]
        rss = float(self.white_yy - 2.0 * b_gls @ self.white_y[s] + b_gls @ gw @ b_gls)
        if self.rows <= k or not rss > 0.0:
            return 0.0, float("inf")
        s2 = rss / (self.rows - k)
        _, _, p = hausman_statistic(b_plain - b_gls, s2 * (gi @ self.noise[np.ix_(s, s)] @ gi), s2 * gwi)
        return p, rss


def with_factors(shapes: Sequence[sympy.Expr]) -> list[sympy.Expr]:
    """shapes and, of each product among them, the product less one of its factors (wz^2 |wx| -> wz^2 and
    |wx|; wy (u1 + .. + u4) -> wy and u1 + .. + u4), once each, in order: a flight's candidates may hold a
    term only as its product with a factor that barely varies, and the search needs the term itself."""
    out = dict.fromkeys(shapes)
    for s in shapes:
        factors = sympy.Mul.make_args(s)
        if len(factors) < 2:
            continue
        for i in range(len(factors)):
            rest = sympy.Mul(*factors[:i], *factors[i + 1:])
            if not rest.is_number:
                out.setdefault(rest)
    return list(out)


@dataclass(frozen=True)
class Walk:
    """Where a search's walk went: the structure it ended at (the best fitting of its last step; when
    accept took one, the structure that step started from), that structure's p-value on the screen, and how
    many structures accept was asked about."""

    terms: list[sympy.Expr]
    p_value: float
    asked: int


def search(start: Sequence[sympy.Expr], screen: HausmanScreen, steps: int,
           accept: Callable[[list[sympy.Expr]], T | None],
           size: Callable[[list[sympy.Expr]], int] = len) -> tuple[T | None, Walk]:
    """(what accept returns for the first structure it takes, walking from start over the screen's pool:
    module docstring, or None; where the walk went). accept: the exact test, the pick's rule and its
    tolerance on a structure's terms (None: not taken); size: a structure's complexity (the passing
    structures of a step are offered simplest first, then best fitting)."""
    index = {t: i for i, t in enumerate(screen.terms)}
    current = [index[t] for t in start if t in index]
    if len(current) != len(start):
        return None, Walk(list(start), 0.0, 0)
    asked, seen, offered = 0, {frozenset(current)}, set()
    p_now, fit = screen.p_value(current)
    start_fit = fit

    def walk() -> Walk:
        return Walk([screen.terms[i] for i in current], p_now, asked)

    def offer(m: list[int]) -> T | None:
        nonlocal asked
        if frozenset(m) in offered:
            return None
        offered.add(frozenset(m))
        asked += 1
        return accept([screen.terms[i] for i in m])

    for _ in range(steps):
        moves = []
        have = set(current)
        for j in range(len(screen.terms)):
            if j in have:
                continue
            moves.append([*current, j])
            moves += [[*current[:i], j, *current[i + 1:]] for i in range(len(current))]
        scored = []
        for m in moves:
            if frozenset(m) in seen:
                continue
            seen.add(frozenset(m))
            p, rss = screen.p_value(m)
            if rss <= fit:  # a swap that fits worse than where it starts would only pass by fitting less
                scored.append((p, rss, m))
        if not scored:
            return None, walk()
        passing = sorted((prm for prm in scored if prm[0] >= SPECIFICATION_LEVEL),
                         key=lambda prm: (size([screen.terms[i] for i in prm[2]]), prm[1]))
        for *_, m in passing[:TRIES_PER_STEP]:
            for s in itertools.chain([m], reduced(m, screen, start_fit)):  # reduced only when m is declined
                taken = offer(s)
                if taken is not None:
                    return taken, walk()
        p_now, fit, current = min(scored, key=lambda prm: prm[1])
    return None, walk()


def reduced(m: Sequence[int], screen: HausmanScreen, fit: float) -> Iterator[list[int]]:
    """From a structure the test passes (pool indices m), one term fewer at a time: each time the term whose
    removal leaves the least whitened residual, while the test still passes and the residual stays at most
    fit (the search's start's); the structures largest first (general to specific), each computed when the
    one before is declined."""
    current = list(m)
    while len(current) > 1:
        best = None
        for i in range(len(current)):
            sub = current[:i] + current[i + 1:]
            p, rss = screen.p_value(sub)
            if p >= SPECIFICATION_LEVEL and rss <= fit and (best is None or rss < best[0]):
                best = (rss, sub)
        if best is None:
            return
        current = best[1]
        yield current
