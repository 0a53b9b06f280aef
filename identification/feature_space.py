"""Candidate features grown from primitives by operators, with dimensional analysis (SISSO-style rungs).

Each primitive carries a unit as exponents of (m, s) (identification.body_frame). Operators:
- rung 1 (unary, on one primitive): x ("id"), x^2 ("pow"), |x| ("abs", where x takes both signs in the
  data: the smaller side reaches at least `abs_sign_share` of the larger; a yaw rate that keeps its sign
  but for a few near-zero samples makes |x| equal to +-x on all but those rows, so no flight of that kind
  tells a law in |x| from one in x, and the simpler x stands),
  1/x, 1/x^2, ... 1/x^K ("inv", for a quantity physically bounded away from zero, the height,
  and bounded away from zero in the data too: its smallest value at least 1/inverse_span of its median, so
  that no handful of rows (a lift-off at h -> 0) makes 1/x^k many orders of magnitude above its typical
  value and owns the least squares; a series in 1/h times the thrust approximates a ground-effect law);
  K = inverse_powers, or near_inverse_powers for a flight that reaches near the ground on its own scale
  (`reaches_near`: its lowest height at most near_spread standard deviations of its heights), where a
  height law changes most; a flight far from the ground gets no higher powers to crowd its screening,
  the ground-plane gradient g_j/x^(k+1), k = 1..K ("tilt", near the ground only, for each primitive marked
  ground_normal, gx and gy: the gravity direction in the body frame, i.e. the ground plane's normal): a body
  point r (a rotor hub) is at height h - r.g, so a law 1/h^k at the hubs is, to first order,
  1/h^k + k (r.g)/h^(k+1); the unknown offsets r are the coefficients (a tilted vehicle's lower rotors
  nearer the ground: the restoring moment of ground effect),
  sin x and cos x ("sincos", only for a dimensionless x),
  the norm sqrt(sum x_i^2) of a vector group ("norm", only when every member has the same unit: adding unlike
  units is invalid); the signed sums sum_i s_i x_i and sum_i s_i x_i^2 (s_i = +-1) over a group of like
  scalars with like units ("add": the rotors' f1..f4 and momentum-like combinations; built first, so
  that where a pool is reduced to independent columns a combination stands for its members)
- rung 2: products of two rung-1 features ("mul"; quotients are products with the "inv" features)
- rung 3: products of a beam of the best rung-2 features with the rung-1 features
Invalid combinations (sin of a length, a sum of a velocity and a rate) are never built and are counted in
`FeatureSpace.pruned`; so are the features of a positive primitive (the height) that barely varies on the
data (relative spread below `min_spread`): a product with it could not be told from its other factor alone,
and the simpler term must win. Features are sympy expressions in the primitive names; duplicates (the same
expression, or a constant column) are dropped. A feature's values are computed from its recipe, so the same
space evaluates on any data (training, held-out, validation).
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np
import sympy

from identification.body_frame import PRIMITIVE_SYMBOLS, PRIMITIVES, Unit
from identification.hub_law import HUB_PRIMITIVES, HubLaw

OPERATORS: tuple[str, ...] = ("mul", "pow", "abs", "inv", "tilt", "norm", "sincos", "add")


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

    op: str  # id, pow2, abs, inv, tilt, sin, cos, norm, sum1, sum2, mul, hub
    # primitive indices (unary, norm, sums; tilt: (normal, height); hub: HUB_PRIMITIVES') or feature indices
    args: tuple[int, ...]
    # the signed sums' signs, one per argument; inv, tilt: (the power of 1/x,); hub: (its index in `laws`,)
    signs: tuple[int, ...] = ()


@dataclass
class FeatureSpace:
    """The grown features: expressions (primitive names), units, rungs and recipes, in a fixed order."""

    primitives: tuple[str, ...]
    expressions: list[sympy.Expr] = field(default_factory=list)
    units: list[Unit] = field(default_factory=list)
    rungs: list[int] = field(default_factory=list)
    recipes: list[Recipe] = field(default_factory=list)
    pruned: dict[str, int] = field(default_factory=dict)
    laws: list[HubLaw] = field(default_factory=list)  # hub laws (identification.hub_law): "hub" recipes
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

    def add_law(self, law: HubLaw, unit: Unit) -> int | None:
        """A fitted hub law as one feature (rung 0: never grown into products); its index, or None when
        the space already holds the same expression or a primitive it reads is not in the space."""
        if any(n not in self.primitives for n in HUB_PRIMITIVES):
            return None
        self.laws.append(law)
        args = tuple(self.primitives.index(n) for n in HUB_PRIMITIVES)
        return self._add(law.expression(), unit, 0, Recipe("hub", args, (len(self.laws) - 1,)))

    def copy(self) -> FeatureSpace:
        """A copy whose lists can grow without changing this one."""
        return FeatureSpace(self.primitives, list(self.expressions), list(self.units), list(self.rungs),
                            list(self.recipes), dict(self.pruned), list(self.laws), dict(self._keys))

    def height_features(self) -> np.ndarray:
        """Per feature (bool): whether it reads the height (a positive primitive: its powers, inverse powers,
        ground-plane gradients, a hub law, or a product holding one of them)."""
        out = np.zeros(len(self), bool)
        for i, r in enumerate(self.recipes):
            if r.op in ("tilt", "hub"):
                out[i] = True
            elif r.op == "mul":
                out[i] = out[r.args[0]] or out[r.args[1]]
            elif r.op in ("id", "pow2", "inv", "abs"):
                out[i] = PRIMITIVES[self.primitives[r.args[0]]].positive
        return out

    def _prune(self, why: str) -> None:
        self.pruned[why] = self.pruned.get(why, 0) + 1

    def columns(
        self, P: np.ndarray, indices: Sequence[int], cache: dict[int, np.ndarray] | None = None,
        out: np.ndarray | None = None,
    ) -> np.ndarray:
        """The features' values (N, len(indices)) from the primitive matrix P (N, n_primitives), written into
        `out` (N, len(indices)) when given."""
        cache = {} if cache is None else cache

        def col(i: int) -> np.ndarray:
            if i in cache:
                return cache[i]
            r = self.recipes[i]
            with np.errstate(all="ignore"):
                if r.op == "mul":
                    v = col(r.args[0]) * col(r.args[1])
                elif r.op == "hub":
                    v = self.laws[r.signs[0]].values(P[:, list(r.args)])
                else:
                    x = P[:, r.args[0]]
                    if r.op == "id":
                        v = x
                    elif r.op == "pow2":
                        v = x * x
                    elif r.op == "abs":
                        v = np.abs(x)
                    elif r.op == "inv":
                        v = x ** -float(r.signs[0])
                    elif r.op == "tilt":
                        v = x * P[:, r.args[1]] ** -float(r.signs[0])
                    elif r.op == "sin":
                        v = np.sin(x)
                    elif r.op == "cos":
                        v = np.cos(x)
                    elif r.op == "norm":
                        v = np.sqrt(np.sum(P[:, list(r.args)] ** 2, axis=1))
                    elif r.op in ("sum1", "sum2"):
                        power = 1 if r.op == "sum1" else 2
                        v = P[:, list(r.args)] ** power @ np.asarray(r.signs, float)
                    else:
                        raise ValueError(r.op)
            cache[i] = v
            return v

        out = np.empty((P.shape[0], len(indices))) if out is None else out
        for j, i in enumerate(indices):
            out[:, j] = col(int(i))
        return out


def reaches_near(x: np.ndarray, near_spread: float) -> bool:
    """True when a positive quantity's data come near zero on their own scale (scale-free): its smallest value
    is at most near_spread standard deviations of its values (a flight whose lowest height, m, is within
    its own vertical extent of the ground)."""
    return bool(x.min() <= near_spread * x.std())


def sign_patterns(n: int) -> list[tuple[int, ...]]:
    """The 2^(n-1) sign patterns of n summed members with the first one positive (the mixer's patterns for
    four rotors: the sum first, then u1 + u2 + u3 - u4, ... in itertools.product order)."""
    return [(1, *rest) for rest in itertools.product((1, -1), repeat=n - 1)]


def grow_unary(
    primitives: Sequence[str],
    operators: Sequence[str],
    P: np.ndarray,
    inverse_span: float = 10.0,
    inverse_powers: int = 2,
    near_inverse_powers: int | None = None,
    near_spread: float = 1.0,
    abs_sign_share: float = 0.05,
    min_spread: float = 0.0,
) -> FeatureSpace:
    """Rung 1: each primitive and the unary operators that are valid for its unit and its range in P
    (inverse_span: 1/x only where min(x) >= median(x) / inverse_span; near_inverse_powers (None: as
    inverse_powers) and the ground-plane gradients where the data reach near zero; abs_sign_share: |x| only
    where min(-min(x), max(x)) >= abs_sign_share * max|x|; min_spread: no feature at all of a positive
    primitive whose relative spread std(x)/mean(x) in P is below it; module docstring)."""
    unknown = [o for o in operators if o not in OPERATORS]
    if unknown:
        raise ValueError(f"unknown operators {unknown} (known: {', '.join(OPERATORS)})")
    space = FeatureSpace(tuple(primitives))
    sym = [PRIMITIVE_SYMBOLS[n] for n in primitives]
    groups: dict[str, list[int]] = {}
    for k, name in enumerate(primitives):
        groups.setdefault(PRIMITIVES[name].group, []).append(k)
    if "add" in operators:
        for members in groups.values():
            if len(members) < 2 or not all(PRIMITIVES[primitives[k]].summable for k in members):
                continue
            u = combine_units("add", *[PRIMITIVES[primitives[k]].unit for k in members])
            if u is None:
                space._prune("sum of unlike units")
                continue
            patterns = sign_patterns(len(members))
            patterns.sort(key=lambda s_: (min(s_) < 0, abs(sum(s_))))  # the sum, then the balanced ones
            for power, op in ((2, "sum2"), (1, "sum1")):
                for signs in patterns:
                    expr = sympy.Add(*[s_ * sym[k] ** power for s_, k in zip(signs, members, strict=True)])
                    space._add(expr, power_unit(u, power), 1, Recipe(op, tuple(members), signs))
    normals = [k for k, name in enumerate(primitives) if PRIMITIVES[name].ground_normal]
    for k, name in enumerate(primitives):
        x, unit, s = P[:, k], PRIMITIVES[name].unit, sym[k]
        if PRIMITIVES[name].ground_normal:
            continue  # only in the ground-plane gradients, below
        if PRIMITIVES[name].positive and barely_varies(x, min_spread):
            space._prune(f"{name}: barely varies on these rows (relative spread below {min_spread:g})")
            continue
        space._add(s, unit, 1, Recipe("id", (k,)))
        if "pow" in operators:
            space._add(s**2, power_unit(unit, 2), 1, Recipe("pow2", (k,)))
        if "abs" in operators and np.any(x < 0) and np.any(x > 0):
            low, high = -float(x.min()), float(x.max())
            if min(low, high) >= abs_sign_share * max(low, high):
                space._add(sympy.Abs(s), unit, 1, Recipe("abs", (k,)))
            else:
                space._prune("abs of a quantity that keeps its sign in the data")
        if "inv" in operators and PRIMITIVES[name].positive and np.all(x > 0):
            if x.min() * inverse_span >= np.median(x):
                near = reaches_near(x, near_spread)
                powers = max(inverse_powers, near_inverse_powers or 0) if near else inverse_powers
                for p in range(1, powers + 1):
                    space._add(1 / s**p, power_unit(unit, -p), 1, Recipe("inv", (k,), (p,)))
                for j in normals if near and "tilt" in operators else ():
                    for p in range(2, powers + 2):  # the gradient of 1/x^(p-1)
                        space._add(sym[j] / s**p, power_unit(unit, -p), 1, Recipe("tilt", (j, k), (p,)))
                if normals and not near:
                    space._prune("ground-plane gradient of a flight far from the ground")
            else:
                space._prune("inverse of a quantity that comes near zero in the data")
        if "sincos" in operators:
            for fn, op in ((sympy.sin, "sin"), (sympy.cos, "cos")):
                u = combine_units(op, unit)
                if u is None:
                    space._prune(f"{op} of a dimensional argument")
                    continue
                space._add(fn(s), u, 1, Recipe(op, (k,)))
    for members in groups.values():
        if len(members) < 2 or "norm" not in operators or set(members) & set(normals):
            continue
        u = combine_units("norm", *[PRIMITIVES[primitives[k]].unit for k in members])
        if u is None:
            space._prune("norm of unlike units")
            continue
        expr = sympy.sqrt(sympy.Add(*[sym[k] ** 2 for k in members]))
        space._add(expr, u, 1, Recipe("norm", tuple(members)))
    return space


def barely_varies(x: np.ndarray, min_spread: float) -> bool:
    """True when a positive quantity's relative spread std(x)/mean(x) is below min_spread: any term it
    multiplies (h vb^2 at 10 +- 0.05 m) cannot be told from the term alone (vb^2), nor h from a constant."""
    mean = float(np.mean(x)) if len(x) else 0.0
    return bool(mean > 0 and float(np.std(x)) < min_spread * mean)


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

