"""Candidate features grown from primitives by operators, with dimensional analysis (SISSO-style rungs).

Each primitive carries a unit as exponents of (m, s) (identification.body_frame). Operators:
- rung 1 (unary, on one primitive): x ("id"), x^2 ("pow"), |x| ("abs", where x takes both signs),
  1/x and 1/x^2 ("inv", where x > 0 throughout), sin x and cos x ("sincos", only for a dimensionless x),
  the norm sqrt(sum x_i^2) of a vector group ("norm", only when every member has the same unit: adding unlike
  units is invalid)
- rung 2: products of two rung-1 features ("mul"; quotients are products with the "inv" features)
- rung 3: products of a beam of the best rung-2 features with the rung-1 features
Invalid combinations (sin of a length, a sum of a velocity and a rate) are never built and are counted in
`FeatureSpace.pruned`. Features are sympy expressions in the primitive names; duplicates (the same
expression, or a constant column) are dropped. A feature's values are computed from its recipe, so the same
space evaluates on any data (training, held-out, validation).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS, PRIMITIVES, Unit

OPERATORS: tuple[str, ...] = ("mul", "pow", "abs", "inv", "norm", "sincos")


def combine_units(op: str, *units: Unit) -> Unit | None:
    """The unit of op(units...) as (m, s) exponents, or None when the combination is dimensionally invalid."""
    if op in ("add", "sub", "norm"):
        return units[0] if all(u == units[0] for u in units) else None
    if op in ("sin", "cos"):
        return (0, 0) if units[0] == (0, 0) else None
    if op == "mul":
        return (sum(u[0] for u in units), sum(u[1] for u in units))
    if op == "abs":
        return units[0]
    raise ValueError(f"unknown operator {op!r}")


def power_unit(unit: Unit, p: int) -> Unit:
    """The unit of x^p."""
    return (unit[0] * p, unit[1] * p)


@dataclass(frozen=True)
class Recipe:
    """How a feature's column is computed: op over primitive columns (unary) or parent features (mul)."""

    op: str  # id, pow2, abs, inv1, inv2, sin, cos, norm, mul
    args: tuple[int, ...]  # primitive indices (unary, norm) or feature indices (mul)


@dataclass
class FeatureSpace:
    """The grown features: expressions (primitive names), units, rungs and recipes, in a fixed order."""

    primitives: tuple[str, ...]
    expressions: list[sympy.Expr] = field(default_factory=list)
    units: list[Unit] = field(default_factory=list)
    rungs: list[int] = field(default_factory=list)
    recipes: list[Recipe] = field(default_factory=list)
    pruned: dict[str, int] = field(default_factory=dict)
    _keys: dict[str, int] = field(default_factory=dict, repr=False)

    def __len__(self) -> int:
        return len(self.expressions)

    def _add(self, expr: sympy.Expr, unit: Unit, rung: int, recipe: Recipe) -> int | None:
        key = sympy.srepr(expr)
        if key in self._keys or expr.is_number:
            return None
        self._keys[key] = len(self.expressions)
        self.expressions.append(expr)
        self.units.append(unit)
        self.rungs.append(rung)
        self.recipes.append(recipe)
        return len(self.expressions) - 1

    def _prune(self, why: str) -> None:
        self.pruned[why] = self.pruned.get(why, 0) + 1

    def columns(
        self, P: np.ndarray, indices: Sequence[int], cache: dict[int, np.ndarray] | None = None
    ) -> np.ndarray:
        """The features' values (N, len(indices)) from the primitive matrix P (N, n_primitives)."""
        cache = {} if cache is None else cache

        def col(i: int) -> np.ndarray:
            if i in cache:
                return cache[i]
            r = self.recipes[i]
            with np.errstate(all="ignore"):
                if r.op == "mul":
                    v = col(r.args[0]) * col(r.args[1])
                else:
                    x = P[:, r.args[0]]
                    if r.op == "id":
                        v = x
                    elif r.op == "pow2":
                        v = x * x
                    elif r.op == "abs":
                        v = np.abs(x)
                    elif r.op == "inv1":
                        v = 1.0 / x
                    elif r.op == "inv2":
                        v = 1.0 / (x * x)
                    elif r.op == "sin":
                        v = np.sin(x)
                    elif r.op == "cos":
                        v = np.cos(x)
                    elif r.op == "norm":
                        v = np.sqrt(np.sum(P[:, list(r.args)] ** 2, axis=1))
                    else:
                        raise ValueError(r.op)
            cache[i] = v
            return v

        out = np.empty((P.shape[0], len(indices)))
        for j, i in enumerate(indices):
            out[:, j] = col(int(i))
        return out


def grow_unary(primitives: Sequence[str], operators: Sequence[str], P: np.ndarray) -> FeatureSpace:
    """Rung 1: each primitive and the unary operators that are valid for its unit and its range in P."""
    unknown = [o for o in operators if o not in OPERATORS]
    if unknown:
        raise ValueError(f"unknown operators {unknown} (known: {', '.join(OPERATORS)})")
    space = FeatureSpace(tuple(primitives))
    sym = [PRIMITIVE_SYMBOLS[n] for n in primitives]
    for k, name in enumerate(primitives):
        x, unit, s = P[:, k], PRIMITIVES[name].unit, sym[k]
        space._add(s, unit, 1, Recipe("id", (k,)))
        if "pow" in operators:
            space._add(s**2, power_unit(unit, 2), 1, Recipe("pow2", (k,)))
        if "abs" in operators and np.any(x < 0) and np.any(x > 0):
            space._add(sympy.Abs(s), unit, 1, Recipe("abs", (k,)))
        if "inv" in operators and np.all(x > 0):
            space._add(1 / s, power_unit(unit, -1), 1, Recipe("inv1", (k,)))
            space._add(1 / s**2, power_unit(unit, -2), 1, Recipe("inv2", (k,)))
        if "sincos" in operators:
            for fn, op in ((sympy.sin, "sin"), (sympy.cos, "cos")):
                u = combine_units(op, unit)
                if u is None:
                    space._prune(f"{op} of a dimensional argument")
                    continue
                space._add(fn(s), u, 1, Recipe(op, (k,)))
    if "norm" in operators:
        groups: dict[str, list[int]] = {}
        for k, name in enumerate(primitives):
            groups.setdefault(PRIMITIVES[name].group, []).append(k)
        for members in groups.values():
            if len(members) < 2:
                continue
            u = combine_units("norm", *[PRIMITIVES[primitives[k]].unit for k in members])
            if u is None:
                space._prune("norm of unlike units")
                continue
            expr = sympy.sqrt(sympy.Add(*[sym[k] ** 2 for k in members]))
            space._add(expr, u, 1, Recipe("norm", tuple(members)))
    return space


def grow_products(space: FeatureSpace, left: Sequence[int], right: Sequence[int], rung: int) -> list[int]:
    """Add the products left_i * right_j (each unordered pair once) as features of `rung`; their indices."""
    added: list[int] = []
    seen: set[tuple[int, int]] = set()
    for a in left:
        for b in right:
            pair = (min(a, b), max(a, b))
            if pair in seen:
                continue
            seen.add(pair)
            unit = combine_units("mul", space.units[a], space.units[b])
            if unit is None:  # never for products; kept for the rule's symmetry
                space._prune("mul")
                continue
            i = space._add(space.expressions[a] * space.expressions[b], unit, rung, Recipe("mul", pair))
            if i is not None:
                added.append(i)
    return added

