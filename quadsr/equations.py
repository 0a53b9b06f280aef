"""The paper's, learned and true equations in one display normal form (LaTeX via sympy), for report.md.

Expanded, rotor-speed sums regrouped into f1..f4 and Omega_r, body-axis drag regrouped into v_b,i |v_b,i|
(v_b = R^T v), coefficients rounded to 4 significant digits and factored out where they agree at that
precision. An expression that is not a polynomial in those building blocks is shown as sympy prints it.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import sympy

from identification.kinematics import euler_rate_matrix_sym, rotation_matrix_sym
from identification.model_file import SYMBOLS, parse_expression
from identification.paper_model import PAPER_KINEMATICS

SIGN_NOTES = """\
- Frames: the paper's earth frame has gravity along +Z_e and thrust along -Z_b, as our NED earth and FRD body
  frames, so x'', y'', z'' and wx', wy', wz' compare directly.
- Motor combinations: the paper's (u2^2+u3^2-u1^2-u4^2), (u1^2+u3^2-u2^2-u4^2), (u1^2+u2^2-u3^2-u4^2) are our
  f2, f3, f4 with the rotors in PX4 Quad-X order, so the torque terms keep their signs.
- Gyroscopic products: the paper has +0.697 wy wz, -0.708 wx wz, +0.0219 wx wy. Euler's equations with
  the paper's own inertias (Table II) give (Jyy-Jzz)/Jxx = -0.697, (Jzz-Jxx)/Jyy = +0.708,
  (Jxx-Jyy)/Jzz = -0.0219: all three of the paper's signs are flipped (w x Jw added instead of subtracted).
  The learned model finds Euler's signs.
- Our vehicle also has the rotor gyroscopic torque (Jm, from the BUAA simulator code: the Omega_r terms) and a
  small body-rate damping (the wx, wy, wz terms); the paper's equations have neither.
- Translation: the paper's zeta_4 and zeta_5 are fits near hover (u1 and u2 u4 standing in for f1, theta for
  sin(theta), sin(phi + psi) for the rotation), its zeta_6 has 9.44 for g = 9.8 and a drag -0.000289 vz^2
  that is right only when falling; the SITL (and the learned model) has the exact rotation of the thrust and
  quadratic drag along each body axis (v_b = R^T v)."""

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
    "f1": (2, (1, 1, 1, 1)), "f2": (2, (-1, 1, 1, -1)), "f3": (2, (1, -1, 1, -1)), "f4": (2, (1, 1, -1, -1)),
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
TARGET_LATEX = {"ax": r"\ddot x", "ay": r"\ddot y", "az": r"\ddot z", "dwx": r"\dot\omega_x",
                "dwy": r"\dot\omega_y", "dwz": r"\dot\omega_z"}
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


@functools.lru_cache(maxsize=128)
def display_terms(expr: sympy.Expr) -> tuple[tuple[float, sympy.Expr], ...] | None:
    """The expression as (coefficient, factor) terms in the display normal form; None if it has none."""
    e = sympy.expand(expr).replace(lambda n: isinstance(n, sympy.Abs), _abs_to_symbol)
    gens: list[sympy.Expr] = [*_A, *_U, *_TV, *_OTHER]
    gens += sorted((a for a in e.atoms(sympy.Function, sympy.Symbol) if a not in gens),
                   key=sympy.default_sort_key)
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


@functools.lru_cache(maxsize=1)
def kinematics_match_paper() -> bool:
    """True when our known Euler-angle rates equal the paper's zeta_7..9 identically."""
    ours = euler_rate_matrix_sym(_S["phi"], _S["theta"]) * sympy.Matrix([_S["wx"], _S["wy"], _S["wz"]])
    theirs = [parse_expression(PAPER_KINEMATICS[k]) for k in ("dphi", "dtheta", "dpsi")]
    return all(sympy.simplify(a - b) == 0 for a, b in zip(ours, theirs, strict=True))



def display_comparison(learned: sympy.Expr, reference: sympy.Expr) -> list[tuple[str, float | None,
                                                                              float | None]]:
    """Terms of two expressions in the display normal form: (LaTeX factor, reference coef, learned coef)."""
    got, ref = display_terms(learned), display_terms(reference)
    if got is None or ref is None:
        return []
    got_by = {f: c for c, f in got}
    rows = [(f, c, got_by.pop(f, None)) for c, f in ref] + [(f, None, c) for f, c in got_by.items()]
    return [("1" if f == 1 else sympy.latex(f, symbol_names=LATEX_NAMES, fold_func_brackets=True), r, g)
            for f, r, g in rows]

