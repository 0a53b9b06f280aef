"""The control law derived from a model's expressions with sympy at start-up, compiled to fast functions.

Nothing here knows the paper's coefficients: everything comes from the six target expressions
(ax, ay, az NED m/s^2; dwx, dwy, dwz FRD rad/s^2) in the 12 states xi and the rotor speeds u (rad/s).

Motor form. The paper's f = (f1..f4) are combinations of squared rotor speeds; the squared speeds are
q = M^T f / 4 (controller.allocation). Every even power u_i^(2k) in an expression becomes q_i(f)^k. What is
left of u (odd powers, e.g. the rotor gyroscopic term Jm w x (0, 0, -u1-u2+u3+u4), or a learned u1*u2) cannot
be written in f; it is frozen at the measured rotor speeds for the step, as the paper freezes u.

Outer loop (x, y): solve the model's x'' and y'' equations for phi_d, theta_d.
  - "thrust" mode, when x'', y'', z'' depend on the motors only through f1 (true for any physical thrust
    model): solve x'' = a_x, y'' = a_y AND z'' = a_z together for (phi, theta, f1). The thrust is then the
    one that goes with the desired attitude and the desired vertical acceleration instead of the current
    (lagging) one, so when the inner loop reaches phi_d, theta_d the designed x'' and y'' are met exactly.
  - "frozen" mode otherwise (e.g. the paper's learned x'' with u1 and u2*u4 terms): solve x'' = a_x, y'' = a_y
    for (phi, theta) with u frozen at its measured value, as the paper does.
  Closed form when the equations can be solved one unknown at a time (sympy.solve, branch nearest level
  flight, arcsine arguments clipped to [-1, 1]); otherwise Newton steps on the sympy Jacobian, warm-started.
  The derivatives phi_d', phi_d'' (and theta_d's) come from implicit differentiation of F(q, p) = a:
  F_q q' = a' - F_p p' and F_q q'' = a'' - d2F/dt2|_{q''=0}, with sympy-derived F_q, F_p p' and the
  second-order terms (controller.outer_loop supplies a', a'' from the reference's jerk and snap).

Inner loop: s = (z, phi, theta, psi, z', phi', theta', psi') with (phi', theta', psi') = W(phi, theta) w,
gamma_5 = z'', (gamma_6, gamma_7, gamma_8) = W w' + W' w (w' = the model's dwx, dwy, dwz). When the gammas
are affine in f (checked symbolically: all second derivatives in f vanish), gamma = G0 + G1 f is solved by
one 4x4 linear solve; otherwise by Newton steps on d gamma/df.

A model that cannot be inverted (no hover within [0, w_max], z'' or an angular acceleration not depending on
the motors, a singular motor effect, x'' and y'' not depending on roll and pitch) raises UserError.
"""

from __future__ import annotations

import math
import string
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import numpy as np
import sympy
from scipy.optimize import brentq

from bridge.errors import UserError
from controller import native
from identification.model_file import INPUT_NAMES, STATE_NAMES, SYMBOLS, TARGET_NAMES

XI = tuple(SYMBOLS[n] for n in STATE_NAMES)
U = tuple(SYMBOLS[n] for n in INPUT_NAMES)
F = tuple(sympy.Symbol(f"f{i}", real=True) for i in range(1, 5))
_IDX = {n: i for i, n in enumerate(STATE_NAMES)}
PHI, THETA, PSI = SYMBOLS["phi"], SYMBOLS["theta"], SYMBOLS["psi"]
WX, WY, WZ = SYMBOLS["wx"], SYMBOLS["wy"], SYMBOLS["wz"]
TAU = sympy.Symbol("tau_", real=True)
_MAX_CLOSED_FORM_OPS = 400


def squared_speed_expressions(f: tuple[sympy.Expr, ...] = F) -> tuple[sympy.Expr, ...]:
    """q_i = u_i^2 [(rad/s)^2] in terms of f1..f4 (the inverse of the paper's f = M q)."""
    f1, f2, f3, f4 = f
    return (
        (f1 - f2 + f3 + f4) / 4,
        (f1 + f2 - f3 + f4) / 4,
        (f1 + f2 + f3 - f4) / 4,
        (f1 - f2 - f3 - f4) / 4,
    )


def motor_form(expr: sympy.Expr) -> sympy.Expr:
    """Rewrite even powers of the rotor speeds as powers of q_i(f); odd powers stay as u (frozen later)."""
    uset = set(U)
    expr = expr.replace(
        lambda e: e.is_Pow and e.exp.is_Integer and e.exp > 1 and not e.base.is_Symbol
        and bool(e.base.free_symbols & uset),
        lambda e: sympy.expand(e),
    )
    q = dict(zip(U, squared_speed_expressions(), strict=False))
    return expr.replace(
        lambda e: e.is_Pow and e.base in uset and e.exp.is_Integer and int(e.exp) % 2 == 0,
        lambda e: q[e.base] ** (int(e.exp) // 2),
    )


def normalise(expressions: Mapping[str, sympy.Expr]) -> dict[str, sympy.Expr]:
    """The six targets with their symbols replaced by the model file's real symbols (matched by name)."""
    missing = [n for n in TARGET_NAMES if n not in expressions]
    if missing:
        raise UserError(f"the model has no expression for {', '.join(missing)}",
                        hint="the controller needs all six targets ax ay az dwx dwy dwz")
    out = {}
    for name in TARGET_NAMES:
        e = sympy.sympify(expressions[name])
        sub = {}
        for s in e.free_symbols:
            if s.name not in SYMBOLS:
                raise UserError(f"the model's {name} uses an unknown name {s.name!r}")
            sub[s] = SYMBOLS[s.name]
        out[name] = smooth_norms(e.xreplace(sub))
    return out


NORM_FLOOR = 1e-12  # (m/s)^2 or (rad/s)^2 added under every square root: |v| is off by at most 1e-6


def smooth_norms(expr: sympy.Expr) -> sympy.Expr:
    """The expression with sqrt(S) (and S^(-1/2), S^(3/2), ...) replaced by the same power of S + 1e-12.

    A vector norm such as the frame drag's |v_a| = sqrt(u^2 + v^2 + w^2) has an undefined derivative at
    zero (0/0), and the law differentiates the model at hover and on the ground, where v = 0 exactly: a
    NaN there would make the model look uninvertible. With the floor the terms and their derivatives are
    finite everywhere (u |v| has derivative 0 at rest, as it should), and values change by at most 1e-6.
    """
    def is_root(e: sympy.Expr) -> bool:
        return (e.is_Pow and e.exp.is_Rational and e.exp.q == 2 and not e.base.is_number
                and not e.base.is_positive)

    return expr.replace(is_root, lambda e: (e.base + NORM_FLOOR) ** e.exp)


def fast_function(name: str, args: list[sympy.Symbol], exprs: list[sympy.Expr],
              sample: Mapping[sympy.Symbol, float] | None = None) -> Callable[..., list[float]]:
    """The expressions as one fast function of args: native code (controller.native), else math-module Python.

    sample: values of some args inside the expressions' domain (others 0) where the native twin is checked.
    """
    # math module: scalar floats are several times faster than numpy for these small expressions.
    exprs = [e.replace(sympy.DiracDelta, lambda *a: sympy.Integer(0)) for e in exprs]
    python = sympy.lambdify(args, exprs, modules="math", cse=True)
    return native.compile_expressions(name, args, exprs, python, _sample(args, sample))


def _program(unit: native.NativeUnit, cname: str, args: list[sympy.Symbol],
             exprs: list[sympy.Expr]) -> Callable[..., list[float]]:
    """Add the expressions (common subexpressions shared) to a native unit as cname; their Python function."""
    exprs = [e.replace(sympy.DiracDelta, lambda *a: sympy.Integer(0)) for e in exprs]
    steps, reduced = sympy.cse(exprs, symbols=sympy.numbered_symbols("c_", real=True))
    unit.program(cname, args, steps, reduced)
    return sympy.lambdify(args, reduced, modules="math", cse=lambda _e: (steps, list(reduced)))


def _sample(args: list[sympy.Symbol], values: Mapping[sympy.Symbol, float] | None) -> list[float]:
    values = values or {}
    return [float(values.get(a, 0.0)) for a in args]


class _Program:
    """A straight-line program (cse of some expressions) extended with forward-mode derivative passes.

    Differentiating the common-subexpression graph node by node keeps the derivatives as small as the graph:
    expanding d2F/dt2 of the drag terms symbolically takes sympy tens of seconds, this takes well under one.
    """

    def __init__(self, exprs: list[sympy.Expr]):
        self.steps: list[tuple[sympy.Symbol, sympy.Expr]] = []
        self._count = 0
        repl, reduced = sympy.cse(exprs, symbols=sympy.numbered_symbols("x_", real=True))
        self.steps.extend(repl)
        self.values = list(reduced)
        self._nodes = list(repl)

    def _new(self, expr: sympy.Expr, prefix: str) -> sympy.Expr:
        if expr.is_Number or expr.is_Symbol:
            return expr
        self._count += 1
        sym = sympy.Symbol(f"{prefix}{self._count}_", real=True)
        self.steps.append((sym, expr))
        return sym

    def _derive(self, g: sympy.Expr, d1: dict, d2: dict | None) -> tuple[sympy.Expr, sympy.Expr]:
        first, second = sympy.Integer(0), sympy.Integer(0)
        syms = [x for x in g.free_symbols if x in d1 or (d2 is not None and x in d2)]
        grads = {x: sympy.diff(g, x) for x in syms}
        for x in syms:
            if x in d1:
                first += grads[x] * d1[x]
            if d2 is not None and x in d2:
                second += grads[x] * d2[x]
        if d2 is not None:
            for x in syms:
                if x not in d1:
                    continue
                for y in syms:
                    if y in d1:
                        second += sympy.diff(grads[x], y) * d1[x] * d1[y]
        return first, second

    def directional(self, seeds1: dict[sympy.Symbol, sympy.Expr],
                    seeds2: dict[sympy.Symbol, sympy.Expr] | None,
                    prefix: str) -> tuple[list[sympy.Expr], list[sympy.Expr]]:
        """First (and second, if seeds2 is given) derivatives of the values along a path with these seeds."""
        d1 = dict(seeds1)
        d2 = dict(seeds2) if seeds2 is not None else None
        for x, g in self._nodes:
            a, b = self._derive(g, d1, d2)
            a = _no_delta(a)
            if a != 0:
                d1[x] = self._new(a, f"{prefix}a")
            if d2 is not None:
                b = _no_delta(b)
                if b != 0:
                    d2[x] = self._new(b, f"{prefix}b")
        firsts, seconds = [], []
        for v in self.values:
            a, b = self._derive(v, d1, d2)
            firsts.append(_no_delta(a))
            seconds.append(_no_delta(b))
        return firsts, seconds

    def python(self, args: list[sympy.Symbol], outputs: list[sympy.Expr]) -> Callable[..., list[float]]:
        """A math-module function of args returning the outputs, computing every step once."""
        steps = list(self.steps)
        return sympy.lambdify(args, outputs, modules="math", cse=lambda _e: (steps, list(outputs)))

    def add_to(self, unit: native.NativeUnit, cname: str, args: list[sympy.Symbol],
               outputs: list[sympy.Expr]) -> None:
        """The same function as C in a native unit."""
        unit.program(cname, args, list(self.steps), outputs)


def _no_delta(e: sympy.Expr) -> sympy.Expr:
    # d2|x|/dx2 = 2 DiracDelta(x): zero except on a set of measure zero (the drag's kink at v_b = 0)
    return e.replace(sympy.DiracDelta, lambda *a: sympy.Integer(0)) if e.has(sympy.DiracDelta) else e


def solve_small(a: list[list[float]], b: list[float]) -> list[float] | None:
    """x with a x = b for n = 2, 3, 4 (plain floats: numpy's per-call overhead dominates at this size).

    None when a is singular relative to its row scales (|det| <= 1e-12 * product of row max-norms).
    """
    n = len(b)
    if n == 3:
        (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = a
        c0 = a11 * a22 - a12 * a21
        c1 = a12 * a20 - a10 * a22
        c2 = a10 * a21 - a11 * a20
        det = a00 * c0 + a01 * c1 + a02 * c2
        scale = (max(abs(a00), abs(a01), abs(a02)) * max(abs(a10), abs(a11), abs(a12))
                 * max(abs(a20), abs(a21), abs(a22)))
        if not abs(det) > 1e-12 * scale or not math.isfinite(det):
            return None
        b0, b1, b2 = b
        inv = 1.0 / det
        return [
            (c0 * b0 + (a02 * a21 - a01 * a22) * b1 + (a01 * a12 - a02 * a11) * b2) * inv,
            (c1 * b0 + (a00 * a22 - a02 * a20) * b1 + (a02 * a10 - a00 * a12) * b2) * inv,
            (c2 * b0 + (a01 * a20 - a00 * a21) * b1 + (a00 * a11 - a01 * a10) * b2) * inv,
        ]
    if n == 2:
        (a00, a01), (a10, a11) = a
        det = a00 * a11 - a01 * a10
        scale = max(abs(a00), abs(a01)) * max(abs(a10), abs(a11))
        if not abs(det) > 1e-12 * scale or not math.isfinite(det):
            return None
        return [(a11 * b[0] - a01 * b[1]) / det, (a00 * b[1] - a10 * b[0]) / det]
    if n == 4:
        return _solve4(a, b)
    raise ValueError(f"solve_small handles n = 2, 3, 4, not {n}")


def _solve4(a: list[list[float]], b: list[float]) -> list[float] | None:
    """4x4 solve through the 2x2-minor (Laplace) expansion of the inverse: straight-line float code."""
    (a00, a01, a02, a03), (a10, a11, a12, a13), (a20, a21, a22, a23), (a30, a31, a32, a33) = a
    s0 = a00 * a11 - a10 * a01
    s1 = a00 * a12 - a10 * a02
    s2 = a00 * a13 - a10 * a03
    s3 = a01 * a12 - a11 * a02
    s4 = a01 * a13 - a11 * a03
    s5 = a02 * a13 - a12 * a03
    c5 = a22 * a33 - a32 * a23
    c4 = a21 * a33 - a31 * a23
    c3 = a21 * a32 - a31 * a22
    c2 = a20 * a33 - a30 * a23
    c1 = a20 * a32 - a30 * a22
    c0 = a20 * a31 - a30 * a21
    det = s0 * c5 - s1 * c4 + s2 * c3 + s3 * c2 - s4 * c1 + s5 * c0
    scale = (max(abs(a00), abs(a01), abs(a02), abs(a03)) * max(abs(a10), abs(a11), abs(a12), abs(a13))
             * max(abs(a20), abs(a21), abs(a22), abs(a23)) * max(abs(a30), abs(a31), abs(a32), abs(a33)))
    if not abs(det) > 1e-12 * scale or not math.isfinite(det):
        return None
    b0, b1, b2, b3 = b
    inv = 1.0 / det
    x = [
        ((a11 * c5 - a12 * c4 + a13 * c3) * b0 + (-a01 * c5 + a02 * c4 - a03 * c3) * b1
         + (a31 * s5 - a32 * s4 + a33 * s3) * b2 + (-a21 * s5 + a22 * s4 - a23 * s3) * b3) * inv,
        ((-a10 * c5 + a12 * c2 - a13 * c1) * b0 + (a00 * c5 - a02 * c2 + a03 * c1) * b1
         + (-a30 * s5 + a32 * s2 - a33 * s1) * b2 + (a20 * s5 - a22 * s2 + a23 * s1) * b3) * inv,
        ((a10 * c4 - a11 * c2 + a13 * c0) * b0 + (-a00 * c4 + a01 * c2 - a03 * c0) * b1
         + (a30 * s4 - a31 * s2 + a33 * s0) * b2 + (-a20 * s4 + a21 * s2 - a23 * s0) * b3) * inv,
        ((-a10 * c3 + a11 * c1 - a12 * c0) * b0 + (a00 * c3 - a01 * c1 + a02 * c0) * b1
         + (-a30 * s3 + a31 * s1 - a32 * s0) * b2 + (a20 * s3 - a21 * s1 + a22 * s0) * b3) * inv,
    ]
    if not all(math.isfinite(v) for v in x):
        return None
    return x


# ----------------------------------------------------------------------------------------------------------
# Outer loop

# The outer loop's Newton solve and rates as C, in a unit with the generated programs fj (F, dF/dq row-major),
# jac_first (dF/dq, F_p p') and second (d2F/dt2 at q'' = 0). Each mirrors its Python version line by line
# (OuterInversion._newton_python, ._rates_python); build_unit checks that they agree before using them.
_OUTER_C = r"""
#define ON $N
#define OM $M
/* in: a[N], pv[M], guess[N], max_iter, angle_limit; out: q[N], ok, iterations */
static void outer_newton(const double *restrict in, double *restrict out) {
  const double *a = in, *pv = in + ON;
  double q[ON], args[ON + OM], buf[ON + ON * ON], rhs[ON], step[ON];
  for (int i = 0; i < ON; i++) q[i] = in[ON + OM + i];
  const double max_iter = in[2 * ON + OM], lim = in[2 * ON + OM + 1];
  double amax = 0.0;
  for (int i = 0; i < ON; i++) if (fabs(a[i]) > amax) amax = fabs(a[i]);
  const double tol = 1e-9 * (1.0 + amax);
  for (int j = 0; j < OM; j++) args[ON + j] = pv[j];
  int it = 0, ok = 0;
  while (it < max_iter) {
    it++;
    for (int i = 0; i < ON; i++) args[i] = q[i];
    fj(args, buf);
    int small = 1;
    for (int i = 0; i < ON; i++) {
      rhs[i] = -(buf[i] - a[i]);
      if (!(fabs(rhs[i]) < tol)) small = 0;
    }
    if (small) { ok = 1; break; }
    if (!solve_small(ON, buf + ON, rhs, step)) break;
    const double big = fmax(fabs(step[0]), fabs(step[1]));
    const double k = big <= 0.3 ? 1.0 : 0.3 / big;
    for (int i = 0; i < ON; i++) q[i] += k * step[i];
    q[0] = fmin(fmax(q[0], -lim), lim);
    q[1] = fmin(fmax(q[1], -lim), lim);
    if (ON == 3 && q[ON - 1] < 0.0) q[ON - 1] = 0.0;
    if (k == 1.0 && big < 2e-4 && (ON == 2 || fabs(step[ON - 1]) < 2e-4 * (1.0 + fabs(q[ON - 1])))) {
      ok = 1;
      break;
    }
  }
  for (int i = 0; i < ON; i++) out[i] = q[i];
  out[ON] = ok;
  out[ON + 1] = it;
}

/* in: q[N], pv[M], p1[M], p2[M], a1[N], a2[N]; out: ok, q'[N], q''[N] */
static void outer_rates(const double *restrict in, double *restrict out) {
  const double *q = in, *pv = in + ON, *p1 = in + ON + OM, *p2 = in + ON + 2 * OM;
  const double *a1 = in + ON + 3 * OM, *a2 = a1 + ON;
  double args1[ON + 2 * OM], buf1[ON * ON + ON], rhs[ON], d1[ON], d2[ON], args2[2 * ON + 3 * OM], s2[ON];
  for (int i = 0; i < ON; i++) args1[i] = args2[i] = q[i];
  for (int j = 0; j < OM; j++) {
    args1[ON + j] = args2[ON + j] = pv[j];
    args1[ON + OM + j] = args2[2 * ON + OM + j] = p1[j];
    args2[2 * ON + 2 * OM + j] = p2[j];
  }
  out[0] = 0.0;
  jac_first(args1, buf1);
  for (int i = 0; i < ON; i++) rhs[i] = a1[i] - buf1[ON * ON + i];
  if (!solve_small(ON, buf1, rhs, d1)) return;
  for (int i = 0; i < ON; i++) args2[ON + OM + i] = d1[i];
  second(args2, s2);
  for (int i = 0; i < ON; i++) rhs[i] = a2[i] - s2[i];
  if (!solve_small(ON, buf1, rhs, d2)) return;
  out[0] = 1.0;
  for (int i = 0; i < ON; i++) { out[1 + i] = d1[i]; out[1 + ON + i] = d2[i]; }
}
"""


@dataclass
class OuterSolution:
    """phi_d, theta_d [rad] and (thrust mode) the matching f1 [(rad/s)^2]; how they were found."""

    phi: float
    theta: float
    f1: float
    ok: bool
    iterations: int
    method: str


class OuterInversion:
    """Solve the model's x'', y'' (and z'' in thrust mode) for phi_d, theta_d (and f1); derivatives too."""

    def __init__(self, motor_exprs: dict[str, sympy.Expr], raw_exprs: dict[str, sympy.Expr],
                 hover_xi: list[float], hover_u: list[float], hover_f1: float):
        thrust_ok = all(not (motor_exprs[n].free_symbols & set(U)) for n in ("ax", "ay", "az"))
        thrust_ok = thrust_ok and F[0] in motor_exprs["az"].free_symbols
        if thrust_ok:
            self.mode = "thrust"
            self.unknowns: tuple[sympy.Symbol, ...] = (PHI, THETA, F[0])
            eqs = [motor_exprs[n] for n in ("ax", "ay", "az")]
        else:
            self.mode = "frozen"
            self.unknowns = (PHI, THETA)
            eqs = [raw_exprs["ax"], raw_exprs["ay"]]
        self.n = len(self.unknowns)
        self.equations = eqs
        free = set().union(*(e.free_symbols for e in eqs))
        params = sorted(free - set(self.unknowns), key=lambda s: s.name)
        self.params: tuple[sympy.Symbol, ...] = tuple(params)
        # where each parameter comes from at run time: the state, the measured rotor speeds u, or their f
        self._param_src = [_source(s) for s in self.params]
        # the usual case, parameters all states: their indices into xi (the loop then builds no branches)
        self._xi_index = [i for _, i in self._param_src] if all(src == "xi" for src, _ in self._param_src) \
            else None
        n = self.n
        q, p = list(self.unknowns), list(self.params)
        hover = {PHI: 0.0, THETA: 0.0, F[0]: hover_f1, **dict(zip(p, self.param_values(hover_xi, hover_u),
                                                                  strict=True))}
        # F and F_q in one program; F_p p' in a second; the second-order terms (q'' = 0) in a third
        unit = native.NativeUnit()
        prog = _Program(list(eqs))
        cols = [prog.directional({qi: sympy.Integer(1)}, None, f"j{k}")[0] for k, qi in enumerate(q)]
        jac = [cols[c][r] for r in range(n) for c in range(n)]
        self._fj = prog.python(q + p, list(prog.values) + jac)
        prog.add_to(unit, "fj", q + p, list(prog.values) + jac)
        q1 = [sympy.Symbol(f"dq{i}_", real=True) for i in range(n)]
        p1 = [sympy.Symbol(f"dp_{s.name}", real=True) for s in p]
        p2 = [sympy.Symbol(f"ddp_{s.name}", real=True) for s in p]
        prog1 = _Program(list(eqs))
        first, _ = prog1.directional(dict(zip(p, p1, strict=True)), None, "p")
        cols1 = [prog1.directional({qi: sympy.Integer(1)}, None, f"j{k}")[0] for k, qi in enumerate(q)]
        jac1 = [cols1[c][r] for r in range(n) for c in range(n)]
        self._jac_first = prog1.python(q + p + p1, jac1 + first)
        prog1.add_to(unit, "jac_first", q + p + p1, jac1 + first)
        prog2 = _Program(list(eqs))
        seeds1 = {**dict(zip(q, q1, strict=True)), **dict(zip(p, p1, strict=True))}
        _, second = prog2.directional(seeds1, dict(zip(p, p2, strict=True)), "s")
        self._second = prog2.python(q + p + q1 + p1 + p2, second)
        prog2.add_to(unit, "second", q + p + q1 + p1 + p2, second)
        self.param_names = tuple(s.name for s in p)
        self._newton: Callable[..., list[float]] | None = None
        self._rates: Callable[..., list[float]] | None = None
        self._compile_native(unit, [hover[s] for s in q], [hover[s] for s in p])
        self.closed_form = self._try_closed_form(eqs, hover_xi, hover_u, hover_f1)
        self.method = "closed-form" if self.closed_form is not None else "newton"

    def _compile_native(self, unit: native.NativeUnit, q0: list[float], pv0: list[float]) -> None:
        """The Newton solve and the rates, programs and loops, as one native unit (each checked against
        its Python version at points around hover); kept as Python where that cannot be."""
        n, m = self.n, len(self.params)
        unit.code(string.Template(_OUTER_C).substitute(N=n, M=m))
        unit.export("fj", n + m, n + n * n)
        unit.export("outer_newton", 2 * n + m + 2, n + 2)
        unit.export("outer_rates", 3 * n + 3 * m, 1 + 2 * n)
        a0 = [0.0] * n  # F(q0) at hover is (0, 0, 0): ask for a small acceleration instead
        newton_points = [[*(v + 0.3 for v in a0), *pv0, *q0, 8.0, 1.2],
                         [*(v - 0.7 for v in a0), *pv0, *q0, 8.0, 1.2],
                         [*a0, *(v + 0.05 for v in pv0), *q0, 3.0, 1.2]]
        pts = native.points_near([*q0, *pv0, *([0.1] * m), *([0.2] * m), *([0.3] * n), *([0.4] * n)])
        fns = native.build_unit(unit, {
            "fj": ("outer F, dF/dq", self._fj, native.points_near([*q0, *pv0])),
            "outer_newton": ("outer Newton solve", self._newton_flat, newton_points),
            "outer_rates": ("outer q', q''", self._rates_flat, pts),
        })
        self._fj = fns["fj"]
        self._newton = fns["outer_newton"] if fns["outer_newton"] is not self._newton_flat else None
        self._rates = fns["outer_rates"] if fns["outer_rates"] is not self._rates_flat else None

    def _newton_flat(self, *values: float) -> list[float]:
        n, m = self.n, len(self.params)
        a, pv, guess = list(values[:n]), list(values[n:n + m]), list(values[n + m:2 * n + m])
        q, ok, it = self._newton_python(a, pv, guess, values[2 * n + m], values[2 * n + m + 1])
        return [*q, float(ok), float(it)]

    def _rates_flat(self, *values: float) -> list[float]:
        n, m = self.n, len(self.params)
        q, pv = list(values[:n]), list(values[n:n + m])
        p1, p2 = list(values[n + m:n + 2 * m]), list(values[n + 2 * m:n + 3 * m])
        a1, a2 = list(values[n + 3 * m:2 * n + 3 * m]), list(values[2 * n + 3 * m:])
        r = self._rates_python(q, pv, a1, a2, p1, p2)
        return [0.0] + [math.nan] * (2 * n) if r is None else [1.0, *r[0], *r[1]]

    # -- closed form ---------------------------------------------------------------------------------
    def _try_closed_form(self, eqs: list[sympy.Expr], hover_xi: list[float], hover_u: list[float],
                         hover_f1: float) -> Callable[..., list[float]] | None:
        """Solve the equations one unknown at a time if their structure allows; None otherwise."""
        a_syms = [sympy.Symbol(f"a{i}_", real=True) for i in range(self.n)]
        nominal = {s: self._param_value_static(s, hover_xi, hover_u) for s in self.params}
        nominal.update({a: 0.0 for a in a_syms})
        level = {PHI: 0.0, THETA: 0.0, F[0]: hover_f1}  # the branch nearest level hover is chosen
        remaining = list(zip(eqs, a_syms, strict=True))
        unknowns = list(self.unknowns)
        solution: dict[sympy.Symbol, sympy.Expr] = {}
        while remaining:
            pick = None
            for k, (eq, a) in enumerate(remaining):
                e = eq.xreplace(solution) if solution else eq
                present = [u for u in unknowns if u in e.free_symbols]
                if len(present) == 1 and sympy.count_ops(e) < _MAX_CLOSED_FORM_OPS:
                    pick = (k, e, a, present[0])
                    break
            if pick is None:
                return None
            k, e, a, unk = pick
            try:
                sols = sympy.solve(sympy.Eq(e, a), unk, simplify=False, rational=False)
            except (NotImplementedError, ValueError, TypeError):
                return None
            best, best_val = None, math.inf
            keys = list(nominal)
            for sol in sols:
                sol = _guard_inverse_trig(sol)
                try:
                    val = float(sympy.lambdify(keys, sol, modules="math")(*(nominal[s] for s in keys)))
                except (TypeError, ValueError, ZeroDivisionError, OverflowError, NameError):
                    continue
                if not math.isfinite(val):
                    continue
                if abs(val - level[unk]) < best_val:
                    best, best_val = sol, abs(val - level[unk])
            if best is None:
                return None
            # each equation picked had one unknown left, so earlier solutions never contain this one
            solution[unk] = best
            unknowns.remove(unk)
            remaining.pop(k)
        exprs = [solution[u] for u in self.unknowns]
        return fast_function("outer closed form", a_syms + list(self.params), exprs, nominal)

    def _param_value_static(self, s: sympy.Symbol, xi: list[float], u: list[float]) -> float:
        return self.param_values(xi, u)[self.params.index(s)]

    # -- numeric --------------------------------------------------------------------------------------
    def param_values(self, xi: list[float], u: list[float]) -> list[float]:
        """The parameter values (states other than the unknowns; frozen u or its f2..f4), params order."""
        if self._xi_index is not None:
            return [xi[i] for i in self._xi_index]
        out = []
        fm = None
        for src, i in self._param_src:
            if src == "xi":
                out.append(xi[i])
            elif src == "u":
                out.append(u[i])
            else:
                fm = fm or _f_of_speeds(u)
                out.append(fm[i])
        return out

    def residual_jacobian(self, q: list[float], pv: list[float]) -> tuple[list[float], list[list[float]]]:
        """F(q, p) and dF/dq at unknowns q and parameters p."""
        out = self._fj(*q, *pv)
        n = self.n
        if n == 3:
            return out[:3], [out[3:6], out[6:9], out[9:12]]
        return out[:2], [out[2:4], out[4:6]]

    def solve(self, a: list[float], xi: list[float], u: list[float], guess: list[float],
              max_iter: int = 8, angle_limit: float = 1.2) -> OuterSolution:
        """Unknowns q (phi, theta[, f1]) with F(q) = a [m/s^2]; warm-started Newton or the closed form."""
        pv = self.param_values(xi, u)
        n = self.n
        method = "newton"
        q = list(guess[:n])
        if self.closed_form is not None:
            try:
                cf = [float(v) for v in self.closed_form(*a[:n], *pv)]
                if all(math.isfinite(v) for v in cf):
                    q = cf
                    return OuterSolution(q[0], q[1], q[2] if n == 3 else math.nan, True, 0, "closed-form")
            except (ValueError, ZeroDivisionError, OverflowError):
                pass
        if self._newton is not None:
            out = self._newton(*a[:n], *pv, *q, max_iter, angle_limit)
            q = out[:n]
            ok, it = out[n] > 0.5, int(out[n + 1])
        else:
            q, ok, it = self._newton_python(a, pv, q, max_iter, angle_limit)
        return OuterSolution(q[0], q[1], q[2] if n == 3 else math.nan, ok, it, method)

    def _newton_python(self, a: list[float], pv: list[float], q: list[float], max_iter: float,
                       angle_limit: float) -> tuple[list[float], bool, int]:
        """Newton's method on F(q) = a from q: (q, converged, iterations). Mirrored in _OUTER_C."""
        n = self.n
        tol = 1e-9 * (1.0 + max(abs(v) for v in a[:n]))
        it = 0
        ok = False
        while it < max_iter:
            it += 1
            try:
                res, jac = self.residual_jacobian(q, pv)
            except (ValueError, ZeroDivisionError, OverflowError):
                break
            r = [res[i] - a[i] for i in range(n)]
            if max(abs(v) for v in r) < tol:
                ok = True
                break
            step = solve_small(jac, [-v for v in r])
            if step is None:
                break
            # keep Newton's angle steps moderate far from the solution
            big = max(abs(step[0]), abs(step[1]))
            k = 1.0 if big <= 0.3 else 0.3 / big
            q = [q[i] + k * step[i] for i in range(n)]
            q[0] = min(max(q[0], -angle_limit), angle_limit)
            q[1] = min(max(q[1], -angle_limit), angle_limit)
            if n == 3 and q[2] < 0.0:
                q[2] = 0.0
            # a full step this small leaves a residual of order step^2: converged without another evaluation
            # (F'' ~ g per rad^2: a 2e-4 rad step leaves ~2e-7 m/s^2)
            if k == 1.0 and big < 2e-4 and (n == 2 or abs(step[2]) < 2e-4 * (1.0 + abs(q[2]))):
                ok = True
                break
        return q, ok, it

    def rates(self, q: list[float], xi: list[float], u: list[float], a1: list[float], a2: list[float],
              p1: list[float], p2: list[float]) -> tuple[list[float], list[float]] | None:
        """(q', q'') of the unknowns from the desired a', a'' and the parameters' p', p'' (None: singular)."""
        pv = self.param_values(xi, u)
        n = self.n
        if self._rates is not None:
            out = self._rates(*q[:n], *pv, *p1, *p2, *a1[:n], *a2[:n])
            if out[0] < 0.5:
                return None
            return out[1:1 + n], out[1 + n:]
        return self._rates_python(q, pv, a1, a2, p1, p2)

    def _rates_python(self, q: list[float], pv: list[float], a1: list[float], a2: list[float],
                      p1: list[float], p2: list[float]) -> tuple[list[float], list[float]] | None:
        """rates() at parameter values pv. Mirrored in _OUTER_C."""
        n = self.n
        out = self._jac_first(*q, *pv, *p1)
        jac = [out[r * n: (r + 1) * n] for r in range(n)]
        fp = out[n * n:]
        d1 = solve_small(jac, [a1[i] - fp[i] for i in range(n)])
        if d1 is None:
            return None
        s2 = self._second(*q, *pv, *d1, *p1, *p2)
        d2 = solve_small(jac, [a2[i] - s2[i] for i in range(self.n)])
        if d2 is None:
            return None
        return d1, d2


def _source(s: sympy.Symbol) -> tuple[str, int]:
    if s.name in _IDX:
        return "xi", _IDX[s.name]
    if s.name in INPUT_NAMES:
        return "u", INPUT_NAMES.index(s.name)
    return "f", int(s.name[1]) - 1


def _f_of_speeds(u: list[float]) -> list[float]:
    q = [v * v for v in u]
    return [q[0] + q[1] + q[2] + q[3], -q[0] + q[1] + q[2] - q[3], q[0] - q[1] + q[2] - q[3],
            q[0] + q[1] - q[2] - q[3]]


def _guard_inverse_trig(expr: sympy.Expr) -> sympy.Expr:
    """Clip asin/acos arguments to [-1, 1] so the closed form stays real when the request is too large."""
    def clip(arg: sympy.Expr) -> sympy.Expr:
        return sympy.Max(-1, sympy.Min(1, arg))
    expr = expr.replace(sympy.asin, lambda a: sympy.asin(clip(a)))
    return expr.replace(sympy.acos, lambda a: sympy.acos(clip(a)))


# ----------------------------------------------------------------------------------------------------------
# Inner loop

# The affine inner solve as C, with the generated program affine (G0, then G1 row-major): mirrors the
# affine branch of InnerInversion.solve (checked against it by build_unit).
_INNER_C = r"""
/* in: xi[12], u[4], v[4]; out: ok, f[4] */
static void inner_linear(const double *restrict in, double *restrict out) {
  double g[20], rhs[4], f[4] = {0.0, 0.0, 0.0, 0.0};
  affine(in, g);
  for (int i = 0; i < 4; i++) rhs[i] = in[16 + i] - g[i];
  out[0] = solve_small(4, g + 4, rhs, f);
  for (int i = 0; i < 4; i++) out[1 + i] = f[i];
}
"""


def euler_rate_matrix(phi: sympy.Expr, theta: sympy.Expr) -> sympy.Matrix:
    """The paper's R: (phi', theta', psi') = R(phi, theta) (wx, wy, wz)."""
    return sympy.Matrix([
        [1, sympy.sin(phi) * sympy.sin(theta) / sympy.cos(theta),
         sympy.cos(phi) * sympy.sin(theta) / sympy.cos(theta)],
        [0, sympy.cos(phi), -sympy.sin(phi)],
        [0, sympy.sin(phi) / sympy.cos(theta), sympy.cos(phi) / sympy.cos(theta)],
    ])


class InnerInversion:
    """gamma_5..8(s, f) from the model, and the solve gamma(s, f) = v for f = (f1..f4) [(rad/s)^2]."""

    def __init__(self, motor_exprs: dict[str, sympy.Expr], hover_u: list[float] | None = None,
                 hover_f: list[float] | None = None):
        w = sympy.Matrix([WX, WY, WZ])
        r = euler_rate_matrix(PHI, THETA)
        euler_rates = r * w
        r_dot = r.diff(PHI) * euler_rates[0] + r.diff(THETA) * euler_rates[1]
        dw = sympy.Matrix([motor_exprs["dwx"], motor_exprs["dwy"], motor_exprs["dwz"]])
        ang = r * dw + r_dot * w
        self.gammas = [motor_exprs["az"], ang[0], ang[1], ang[2]]
        self.euler_rates = list(euler_rates)
        jac = sympy.Matrix(self.gammas).jacobian(list(F))
        self.jacobian = jac
        self.affine = all(sympy.diff(jac[i, j], fk) == 0 for i in range(4) for j in range(4) for fk in F)
        args = list(XI) + list(U)
        hover = {**dict(zip(U, hover_u or [], strict=False)), **dict(zip(F, hover_f or [], strict=False))}
        unit = native.NativeUnit()
        twins: dict[str, native.Twin] = {}
        if self.affine:
            g0 = [g.xreplace(dict.fromkeys(F, 0)) for g in self.gammas]
            self._affine = _program(unit, "affine", args, g0 + list(jac))
            unit.code(_INNER_C)
            unit.export("inner_linear", 20, 5)
            sample = _sample(args, hover)
            twins["inner_linear"] = ("inner linear solve", self._linear_flat,
                                     native.points_near([*sample, 1.0, 2.0, 3.0, 0.5]))
        self._gamma = _program(unit, "gamma", args + list(F), self.gammas + list(jac))
        unit.export("gamma", 20, 20)
        twins["gamma"] = ("inner gamma, dgamma/df", self._gamma, native.points_near(_sample(args + list(F),
                                                                                              hover)))
        fns = native.build_unit(unit, twins)
        self._gamma = fns["gamma"]
        self._linear = None
        if self.affine and fns["inner_linear"] is not self._linear_flat:
            self._linear = fns["inner_linear"]
        self.method = "linear" if self.affine else "newton"

    def _linear_flat(self, *values: float) -> list[float]:
        """The affine solve in Python, flat in and out as the C inner_linear: (ok, f1..f4)."""
        g0, g1 = self.affine_terms(list(values[:12]), list(values[12:16]))
        f = solve_small(g1, [values[16 + i] - g0[i] for i in range(4)])
        return [0.0] + [math.nan] * 4 if f is None else [1.0, *f]

    @staticmethod
    def euler_angle_rates(xi: list[float]) -> list[float]:
        """(phi', theta', psi') [rad/s] = R(phi, theta) w: euler_rate_matrix written out (for speed)."""
        sf, cf = math.sin(xi[6]), math.cos(xi[6])
        ct = math.cos(xi[7])
        wy, wz = xi[10], xi[11]
        c = (sf * wy + cf * wz) / ct
        return [xi[9] + c * math.sin(xi[7]), cf * wy - sf * wz, c]

    def gamma(self, xi: list[float], u: list[float], f: list[float]) -> list[float]:
        """gamma_5..8 [m/s^2, rad/s^2]: z'' and the Euler angle accelerations under f, odd u terms at u."""
        return list(self._gamma(*xi, *u, *f)[:4])

    def affine_terms(self, xi: list[float], u: list[float]) -> tuple[list[float], list[list[float]]]:
        """G0 (4) and G1 (4x4) with gamma = G0 + G1 f (affine models only)."""
        out = self._affine(*xi, *u)
        return out[:4], [out[4:8], out[8:12], out[12:16], out[16:20]]

    def solve(self, v: list[float], xi: list[float], u: list[float], guess: list[float],
              max_iter: int = 8) -> tuple[list[float], bool]:
        """f with gamma(s, f) = v (the designed values); (f, ok)."""
        if self.affine:
            out = self._linear(*xi, *u, *v) if self._linear is not None else self._linear_flat(*xi, *u, *v)
            return (out[1:], True) if out[0] > 0.5 else (list(guess), False)
        f = list(guess)
        for _ in range(max_iter):
            out = self._gamma(*xi, *u, *f)
            r = [out[i] - v[i] for i in range(4)]
            if max(abs(x) for x in r) < 1e-9 * (1.0 + max(abs(x) for x in v)):
                return f, True
            jac = [out[4:8], out[8:12], out[12:16], out[16:20]]
            step = solve_small(jac, [-x for x in r])
            if step is None:
                return f, False
            f = [f[i] + step[i] for i in range(4)]
        out = self._gamma(*xi, *u, *f)
        return f, max(abs(out[i] - v[i]) for i in range(4)) < 1e-6 * (1.0 + max(abs(x) for x in v))


# ----------------------------------------------------------------------------------------------------------
# The whole law


@dataclass
class DerivedLaw:
    """Everything the controller evaluates in the loop, derived from one model."""

    outer: OuterInversion
    inner: InnerInversion
    gravity: float  # m/s^2, the model's z'' at rest, level, motors off
    hover_speed: float  # rad/s, equal rotor speeds that make z'' = 0 at rest, level
    hover_f: list[float]  # f at hover [(rad/s)^2]
    w_max: float  # rad/s
    notes: list[str] = field(default_factory=list)
    native: dict[str, str] = field(default_factory=dict)  # each loop function: "native" or why Python

    def describe(self) -> str:
        """One line on how the law was derived (for logs and reports)."""
        fast = sum(v == "native" for v in self.native.values())
        why = sorted({v for v in self.native.values() if v != "native"})
        code = f"{fast} of {len(self.native)} loop functions compiled"
        code += f" ({'; '.join(why)})" if why else ""
        return (f"outer: {self.outer.method} in {self.outer.mode} mode "
                f"(unknowns {', '.join(s.name for s in self.outer.unknowns)}); inner: "
                f"{self.inner.method} solve for f1..f4; hover {self.hover_speed:.1f} rad/s; {code}")


_CACHE: dict[tuple, DerivedLaw] = {}


def derive_law(expressions: Mapping[str, sympy.Expr], w_max: float) -> DerivedLaw:
    """Derive (and cache) the control law of a model's six target expressions; UserError if not invertible."""
    exprs = normalise(expressions)
    key = (tuple(sympy.srepr(exprs[n]) for n in TARGET_NAMES), float(w_max), native.enabled())
    if key not in _CACHE:
        _CACHE[key] = _derive(exprs, float(w_max))
    return _CACHE[key]


def _derive(exprs: dict[str, sympy.Expr], w_max: float) -> DerivedLaw:
    motor = {n: motor_form(e) for n, e in exprs.items()}
    for n in ("az", "dwx", "dwy", "dwz"):
        if not (exprs[n].free_symbols & set(U)):
            what = "the collective thrust" if n == "az" else "the motors' torques"
            raise UserError(
                f"the model cannot be inverted: {n} does not depend on the motors (u1..u4), so the "
                f"controller cannot command {what}",
                hint=f"{n} = {exprs[n]}; the law solves az, dwx, dwy, dwz for f1..f4: identify a model whose "
                     "accelerations depend on the squared rotor speeds")
    rest = [0.0] * 12
    az_fn = sympy.lambdify(list(XI) + list(U), exprs["az"], modules="math")

    def az_at(speed: float) -> float:
        try:
            return float(az_fn(*rest, speed, speed, speed, speed))
        except (ValueError, ZeroDivisionError, OverflowError) as exc:
            raise UserError(
                f"the model's z'' cannot be evaluated at rest at the origin (all states 0, so the height "
                f"above ground h = 0; rotor speeds {speed:.1f} rad/s): {exc}",
                hint=f"az = {exprs['az']}; the law is derived about hover at the origin: identify a model "
                     "defined there (without 1/h terms: leave 'inv' out of discovery.operators)") from None

    gravity = az_at(0.0)
    if not (math.isfinite(gravity) and gravity > 0.0):
        raise UserError(f"the model's z'' at rest with the motors off is {gravity:.3g} m/s^2, not gravity "
                        "(positive, NED z down)", hint="check the model's az expression and its frame (NED)")
    top = az_at(w_max)
    if not top < 0.0:
        raise UserError(
            f"the model cannot hover: z'' at rest is {top:.3g} m/s^2 even at w_max = {w_max:.1f} rad/s "
            "(the thrust does not overcome gravity; perhaps z'' does not depend on the motors)",
            hint="the controller needs z'' (az) to depend on the collective thrust f1 = sum of u_i^2")
    hover = brentq(az_at, 0.0, w_max, xtol=1e-10)
    hover_u = [hover] * 4
    hover_f = [4.0 * hover * hover, 0.0, 0.0, 0.0]

    native.status(clear=True)
    inner = InnerInversion(motor, hover_u, hover_f)
    _check_inner(inner, motor, rest, hover_u, hover_f)
    outer = OuterInversion(motor, exprs, rest, hover_u, hover_f[0])
    _check_outer(outer, rest, hover_u, hover_f[0])
    notes = []
    frozen = sorted({s.name for n in TARGET_NAMES for s in motor[n].free_symbols if s in U})
    if frozen:
        notes.append(f"terms odd in {', '.join(frozen)} are evaluated at the measured rotor speeds")
    return DerivedLaw(outer, inner, gravity, hover, hover_f, w_max, notes, native.status())


def _check_inner(inner: InnerInversion, motor: dict[str, sympy.Expr], xi: list[float], u: list[float],
                 f: list[float]) -> None:
    names = ("az", "dwx", "dwy", "dwz")
    deps = {n: sorted(s.name for s in motor[n].free_symbols if s in F) for n in names}
    for n in names:
        if not deps[n]:
            what = "the collective thrust f1" if n == "az" else "any motor combination f1..f4"
            raise UserError(
                f"the model cannot be inverted: {n} does not depend on the motors ({what})",
                hint=f"{n} = {motor[n]}: the controller solves the model's az, dwx, dwy, dwz for f1..f4; "
                     "identify a model whose accelerations depend on the squared rotor speeds")
    jac = np.array(inner._gamma(*xi, *u, *f)[4:], dtype=float).reshape(4, 4)
    scale = np.linalg.norm(jac, axis=1, keepdims=True)
    norm = jac / np.where(scale > 0, scale, 1.0)
    sv = np.linalg.svd(norm, compute_uv=False)
    if not np.all(np.isfinite(sv)) or sv[-1] < 1e-6:
        listing = "; ".join(f"{n} on {', '.join(deps[n])}" for n in names)
        raise UserError(
            "the model cannot be inverted: the motors' effect on (z'', dwx, dwy, dwz) at hover is singular "
            f"(rank {int(np.sum(sv > 1e-6))} of 4), so thrust, roll, pitch and yaw cannot be set "
            "independently "
            f"(depends: {listing})",
            hint="roll needs f2, pitch f3, yaw f4 and z'' f1 (or an invertible mix of them)")


def _check_outer(outer: OuterInversion, xi: list[float], u: list[float], f1: float) -> None:
    q = [0.0, 0.0, f1][: outer.n]
    try:
        _, jac = outer.residual_jacobian(q, outer.param_values(xi, u))
    except (ValueError, ZeroDivisionError):
        jac = [[math.nan] * outer.n] * outer.n
    j2 = np.array(jac, dtype=float)[:2, :2]
    big = max(float(np.max(np.abs(j2))), 1e-30) if np.all(np.isfinite(j2)) else math.nan
    ok = math.isfinite(big) and abs(np.linalg.det(j2)) > 1e-9 * big**2
    if not ok:
        raise UserError(
            "the model cannot be inverted: at hover, x'' and y'' do not depend on roll and pitch "
            f"(d(ax, ay)/d(phi, theta) = {np.array2string(j2, precision=3)}), so the outer loop cannot steer",
            hint="identify ax and ay with the attitude terms (sin/cos of phi, theta, psi times the thrust)")
