"""Equations in one display normal form with rounded coefficients, grouped by physical meaning.

Expanded, rotor-speed sums regrouped into f1..f4 and Omega_r (docs/design.md: f1 = sum u_i^2 (thrust),
f2, f3, f4 the roll, pitch, yaw combinations, Omega_r = -u1 - u2 + u3 + u4), body-axis drag regrouped into
v_b,i |v_b,i| (v_b = R^T v), coefficients rounded to SIGNIFICANT digits and factored out where they agree
at that precision; signs go to the coefficients (no `*(-1)*`). An expression that is not a polynomial in
those building blocks is shown as sympy prints it, its numbers rounded. LaTeX for the paper's report
(quadsr.report), plain text grouped as thrust, control, coupling, drag, gravity/bias for people
(equation_text, the model report).
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Sequence

import sympy

from identification.kinematics import rotation_matrix_sym
from identification.model_file import SYMBOLS

# --------------------------------------------------------------------------------------------------------
# Display normal form


_AXES = "xyz"
_S = SYMBOLS
_R = rotation_matrix_sym(_S["phi"], _S["theta"], _S["psi"])
_VB = [sympy.expand(c) for c in _R.T * sympy.Matrix([_S["vx"], _S["vy"], _S["vz"]])]
_V = [sympy.Symbol(f"v_b{a}") for a in _AXES]  # body velocity component, display only
_A = [sympy.Symbol(f"v_b{a}_abs") for a in _AXES]  # its absolute value, display only
_TRIG = [f(_S[n]) for n in ("phi", "theta", "psi") for f in (sympy.sin, sympy.cos)]
_TV = [_S["vx"], _S["vy"], _S["vz"], *_TRIG]  # what the drag quotient and rotation factors are made of
_U = [_S[f"u{i}"] for i in range(1, 5)]
_OTHER = [_S[n] for n in ("wx", "wy", "wz", "x", "y", "z", "phi", "theta", "psi")]
# motor combinations (docs/design.md): name -> (power of u_i, sign per rotor)
_COMBINATIONS = {
    "f1": (2, (1, 1, 1, 1)),
    "f2": (2, (-1, 1, 1, -1)),
    "f3": (2, (1, -1, 1, -1)),
    "f4": (2, (1, 1, -1, -1)),
    "Omega_r": (1, (-1, -1, 1, 1)),
}
_F = {name: sympy.Symbol(name) for name in _COMBINATIONS}
LATEX_NAMES: dict[sympy.Symbol, str] = {
    **{_V[i]: f"v_{{b,{a}}}" for i, a in enumerate(_AXES)},
    **{_A[i]: rf"\lvert v_{{b,{a}}} \rvert" for i, a in enumerate(_AXES)},
    **{_F[f"f{i}"]: f"f_{i}" for i in range(1, 5)},
    _F["Omega_r"]: r"\Omega_r",
    **{_S[f"v{a}"]: f"v_{a}" for a in _AXES},
    **{_S[f"w{a}"]: rf"\omega_{a}" for a in _AXES},
    **{_S[f"u{i}"]: f"u_{i}" for i in range(1, 5)},
}
TARGET_LATEX = {
    "ax": r"\ddot x",
    "ay": r"\ddot y",
    "az": r"\ddot z",
    "dwx": r"\dot\omega_x",
    "dwy": r"\dot\omega_y",
    "dwz": r"\dot\omega_z",
}
SIGNIFICANT = 4


def _rounded(value: float) -> float:
    return float(f"{value:.{SIGNIFICANT}g}")


def _abs_to_symbol(node: sympy.Expr) -> sympy.Expr:
    arg = node.args[0]
    for i, vb in enumerate(_VB):
        if sympy.expand(arg - vb) == 0 or sympy.expand(arg + vb) == 0:
            return _A[i]
    return node


def _monomial(gens: Sequence[sympy.Expr], exponents: Sequence[int], which: Sequence[int]) -> sympy.Expr:
    return sympy.Mul(*[gens[k] ** exponents[k] for k in which if exponents[k]])


def _has_root_or_quotient(node: sympy.Expr) -> bool:
    """Whether a power of a variable's expression other than a non-negative integer one (a root, a quotient)
    sits outside every function's argument: then the expression is shown as sympy prints it. A model's
    expressions are sums of features times the rotation's entries, so no expansion cancels such a power;
    one that would (x (y + 1/x)) is shown as printed too."""
    if isinstance(node, sympy.Function):
        return False
    if isinstance(node, sympy.Pow) and node.base.free_symbols:
        exp = node.exp
        if not (exp.is_Integer and exp >= 0):
            return True
    return any(_has_root_or_quotient(a) for a in node.args)


@functools.lru_cache(maxsize=128)
def display_terms(expr: sympy.Expr) -> tuple[tuple[float, sympy.Expr], ...] | None:
    """The expression as (coefficient, factor) terms in the display normal form; None if it has none."""
    if _has_root_or_quotient(expr):
        # the expansion below would end in Poly's PolynomialError: closed-loop aero's hub-law model took 46 s
        # to get there (sympy.expand of the composed NED accelerations)
        return None
    e = sympy.expand(expr).replace(lambda n: isinstance(n, sympy.Abs), _abs_to_symbol)
    gens: list[sympy.Expr] = [*_A, *_U, *_TV, *_OTHER]
    gens += sorted(
        (a for a in e.atoms(sympy.Function, sympy.Symbol) if a not in gens), key=sympy.default_sort_key
    )
    try:
        poly = sympy.Poly(e, *gens)
    except sympy.PolynomialError:
        return None
    iu = [gens.index(u) for u in _U]
    itv = [gens.index(g) for g in _TV]
    iother = [k for k in range(len(gens)) if k not in iu and k not in itv]
    by_rest: dict[tuple[int, ...], dict[tuple[int, ...], float]] = {}
    for monom, coef in poly.terms():
        rest = tuple(0 if k in iu else p for k, p in enumerate(monom))
        by_rest.setdefault(rest, {})[tuple(monom[k] for k in iu)] = float(coef)
    # 1. rotor speeds: four u_i^p terms with one coefficient and a combination's signs -> that combination
    items: list[tuple[float, sympy.Expr, sympy.Expr]] = []  # (coefficient, key factor, trig/velocity part)
    for rest, by_u in by_rest.items():
        key, tv = _monomial(gens, rest, iother), _monomial(gens, rest, itv)
        for name, (power, signs) in _COMBINATIONS.items():
            ks = [tuple(power if j == i else 0 for j in range(4)) for i in range(4)]
            if all(k in by_u for k in ks):
                members = [by_u[k] * s for k, s in zip(ks, signs, strict=True)]
                if len({_rounded(c) for c in members}) == 1:
                    items.append((sum(members) / 4, _F[name] * key, tv))
                    for k in ks:
                        del by_u[k]
        for um, c in by_u.items():
            items.append((c, sympy.Mul(*[u**p for u, p in zip(_U, um, strict=True)]) * key, tv))
    # 2. per key factor, the trig/velocity polynomial; with |v_b,i| in the key, divided by v_b,i if it can be
    groups: dict[sympy.Expr, sympy.Expr] = {}
    for c, key, tv in items:
        groups[key] = groups.get(key, sympy.Integer(0)) + sympy.Float(c) * tv
    out: list[tuple[float, sympy.Expr]] = []
    for key, q in groups.items():
        extra: sympy.Expr = sympy.Integer(1)
        for i in range(3):
            if key.has(_A[i]):
                quotient, remainder = sympy.div(q, _VB[i], *_TV)
                scale = max(abs(float(c)) for c in sympy.Poly(q, *_TV).coeffs())
                rest = sympy.Poly(remainder, *_TV)
                if rest.is_zero or max(abs(float(c)) for c in rest.coeffs()) <= 1e-9 * scale:
                    q, extra = quotient, _V[i]
                break
        terms = [(m, float(c)) for m, c in sympy.Poly(q, *_TV).terms() if float(c) != 0.0]
        if not terms:
            continue
        parts = [(sympy.Mul(*[g**p for g, p in zip(_TV, m, strict=True)]), c) for m, c in terms]
        if len({_rounded(abs(c)) for _, c in parts}) == 1:
            first = parts[0][1]
            norm = sympy.Add(*[(1 if c * first > 0 else -1) * mono for mono, c in parts])
            out.append((math.copysign(sum(abs(c) for _, c in parts) / len(parts), first), norm * extra * key))
        else:
            out += [(c, mono * extra * key) for mono, c in parts]

    def order(term: tuple[float, sympy.Expr]) -> int:
        f = term[1]
        if f.has(*_F.values()):
            return 0
        if f.has(*_A):
            return 1
        return 3 if f == 1 else 2

    return tuple(sorted(out, key=order))


def latex_number(value: float) -> str:
    """A number to 4 significant digits in LaTeX (scientific as a \\cdot 10^{b} outside 1e-3..1e4)."""
    if value == 0 or not math.isfinite(value):
        return str(value)
    mantissa, exponent = f"{value:.{SIGNIFICANT - 1}e}".split("e")
    if -3 <= int(exponent) < 4:
        return f"{value:.{SIGNIFICANT}g}"
    return rf"{float(mantissa):.{SIGNIFICANT}g} \cdot 10^{{{int(exponent)}}}"


@functools.lru_cache(maxsize=128)
def equation_latex(expr: sympy.Expr) -> str:
    """The right-hand side in LaTeX, in the display normal form with rounded coefficients."""
    terms = display_terms(expr)
    if terms is None:
        floats = expr.atoms(sympy.Float)
        rounded = expr.xreplace({f: sympy.Float(_rounded(float(f)), SIGNIFICANT) for f in floats})
        return sympy.latex(rounded, symbol_names=LATEX_NAMES, fold_func_brackets=True)
    if not terms:
        return "0"
    parts = []
    for c, factor in terms:
        body = latex_number(abs(c))
        if factor != 1:
            body += " " + sympy.latex(factor, symbol_names=LATEX_NAMES, fold_func_brackets=True)
        parts.append(("- " if c < 0 else "+ ") + body)
    text = " ".join(parts)
    return text[2:] if text.startswith("+ ") else text


def display_comparison(
    learned: sympy.Expr, reference: sympy.Expr
) -> list[tuple[str, float | None, float | None]]:
    """Terms of two expressions in the display normal form: (LaTeX factor, reference coef, learned coef)."""
    got, ref = display_terms(learned), display_terms(reference)
    if got is None or ref is None:
        return []
    got_by = {f: c for c, f in got}
    rows = [(f, c, got_by.pop(f, None)) for c, f in ref] + [(f, None, c) for f, c in got_by.items()]
    return [
        ("1" if f == 1 else sympy.latex(f, symbol_names=LATEX_NAMES, fold_func_brackets=True), r, g)
        for f, r, g in rows
    ]


# --------------------------------------------------------------------------------------------------------
# Plain text, grouped by physical meaning

GROUPS = ("thrust", "control", "coupling", "drag", "gravity/bias", "other")
_LINEAR = ("ax", "ay", "az")
_RATES = [_S["wx"], _S["wy"], _S["wz"]]
_VELOCITIES = [_S["vx"], _S["vy"], _S["vz"], *_V, *_A]


def _degree(f: sympy.Expr, x: sympy.Symbol) -> int:
    """The degree of f in x; 1 where f is no polynomial in x (|x|, 1/x, sin x: x appears once)."""
    try:
        return int(sympy.degree(f, x))
    except sympy.PolynomialError:
        return 1


def term_group(target: str, factor: sympy.Expr) -> str:
    """The physical meaning of one display term of a target: thrust, control, coupling, drag, gravity/bias
    or other (f1 and lone u_i on x'', y'', z'' are thrust; f2..f4 and u_i on wx', wy', wz' control;
    Omega_r and products of body rates coupling; velocities and lone body rates drag/damping)."""
    if factor == 1:
        return "gravity/bias"
    f = factor
    has_u = f.has(*_U) or f.has(_F["f1"], _F["f2"], _F["f3"], _F["f4"])
    if f.has(_F["Omega_r"]):
        return "coupling"
    if has_u:
        if target in _LINEAR:
            return "thrust"
        return "thrust" if f.has(_F["f1"]) and not f.has(_F["f2"], _F["f3"], _F["f4"]) else "control"
    rate_power = sum(_degree(f, r) for r in _RATES if f.has(r))
    if rate_power >= 2 and sum(1 for r in _RATES if f.has(r)) >= 2:
        return "coupling"
    if f.has(*_VELOCITIES) or rate_power == 1:
        return "drag"
    return "other"


def number_text(value: float, digits: int) -> str:
    """|value| to `digits` significant digits (scientific outside 1e-3..1e4)."""
    v = abs(value)
    if v == 0 or not math.isfinite(v):
        return str(v)
    exponent = int(math.floor(math.log10(v)))
    if -3 <= exponent < 4:
        return f"{float(f'{v:.{digits}g}'):g}"
    return f"{v:.{digits - 1}e}"


def _factor_text(factor: sympy.Expr, digits: int) -> str:
    floats = factor.atoms(sympy.Float)
    factor = factor.xreplace({f: sympy.Float(float(f"{float(f):.{digits}g}"), digits) for f in floats})
    text = re.sub(r"v_b([xyz])_abs", r"|vb\1|", sympy.sstr(factor)).replace("v_b", "vb")
    return text.replace("**", "^")


def equation_text(target: str, expr: sympy.Expr, digits: int = 3) -> list[tuple[str, str]]:
    """(group, text) lines of an expression in the display normal form, coefficients to `digits`
    significant digits, grouped as GROUPS; one ('other', text) line when it has no such form."""
    terms = display_terms(expr)
    if terms is None:
        floats = expr.atoms(sympy.Float)
        rounded = expr.xreplace({f: sympy.Float(float(f"{float(f):.{digits}g}"), digits) for f in floats})
        return [("other", sympy.sstr(rounded).replace("**", "^"))]
    by_group: dict[str, list[str]] = {}
    for c, factor in terms:
        body = number_text(c, digits) + ("" if factor == 1 else " " + _factor_text(factor, digits))
        by_group.setdefault(term_group(target, factor), []).append(("- " if c < 0 else "+ ") + body)
    return [(g, " ".join(by_group[g])) for g in GROUPS if g in by_group]


DISPLAY_LEGEND = (
    "f1 = u1^2+u2^2+u3^2+u4^2 (thrust), f2 = -u1^2+u2^2+u3^2-u4^2 (roll), f3 = u1^2-u2^2+u3^2-u4^2 (pitch), "
    "f4 = u1^2+u2^2-u3^2-u4^2 (yaw), Omega_r = -u1-u2+u3+u4; vbx, vby, vbz the body-axis velocity "
    "(m/s, R^T v), |vbx| its absolute value"
)
