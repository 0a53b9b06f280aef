"""Straight-line sympy programs compiled to native code at start-up (C99, the system C compiler, ctypes).

Why: the controller evaluates a handful of derived programs every 4 ms step (the model, its Jacobians, the
implicit derivatives of the outer inversion). As math-module Python (sympy.lambdify) each costs 10-40 us a
call, most of a step; compiled, each costs about 2 us (arguments written into one double buffer, results read
from another). The compiled code is the same program: same common subexpressions, same order, IEEE doubles
(no -ffast-math), so results agree with the Python functions to rounding; every compiled function is checked
against its Python twin at sample points before it is used.

Optional by design: without a C compiler (a slim container), when compiling fails, or with QUADSR_NATIVE=0,
the callers keep their Python functions and `status()` says why. One difference the callers allow for: where
math-module Python raises ValueError/ZeroDivisionError (outside an expression's domain), C returns NaN or
inf; every caller checks its results for finiteness.

Shared libraries are cached by the hash of their source in $QUADSR_CACHE_DIR (default
$XDG_CACHE_HOME/quadsr/native, else ~/.cache/quadsr/native), so a law is compiled once per machine.
"""

from __future__ import annotations

import ctypes
import hashlib
import math
import os
import random
import shutil
import subprocess
import tempfile
import threading
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

import sympy
from sympy.printing.c import C99CodePrinter

CFLAGS = ("-O2", "-fPIC", "-shared", "-fno-math-errno", "-std=c99")
COMPILE_TIMEOUT_S = 120.0
_CHECK_POINTS = 3
_SEED = 20261122

_status: dict[str, str] = {}  # function name -> "native" or why it is Python
_loaded: dict[str, ctypes.CDLL] = {}  # keep the libraries alive


def enabled() -> bool:
    """Whether native compilation is allowed (QUADSR_NATIVE unset or not 0/off/no/false)."""
    return os.environ.get("QUADSR_NATIVE", "1").strip().lower() not in ("0", "off", "no", "false")


def compiler() -> str | None:
    """The C compiler to use ($CC, else cc, gcc or clang on PATH), or None."""
    cc = os.environ.get("CC")
    if cc:
        return shutil.which(cc.split()[0]) and cc
    for name in ("cc", "gcc", "clang"):
        if shutil.which(name):
            return name
    return None


def cache_dir() -> Path:
    """Where compiled libraries are kept."""
    env = os.environ.get("QUADSR_CACHE_DIR")
    if env:
        return Path(env) / "native"
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "quadsr" / "native"


def status(clear: bool = False) -> dict[str, str]:
    """Each function built since the last clear: "native", or why it runs as Python (clear: start afresh)."""
    if clear:
        _status.clear()
    return dict(_status)


class _Printer(C99CodePrinter):
    def __init__(self) -> None:
        super().__init__({"strict": True})

    def _print_Pow(self, expr: sympy.Pow) -> str:  # small integer powers as products (pow() is a call)
        if expr.exp.is_Integer and 2 <= int(expr.exp) <= 4 and not expr.base.is_Number:
            b = f"({self._print(expr.base)})"
            return "(" + "*".join([b] * int(expr.exp)) + ")"
        return super()._print_Pow(expr)


SOLVE_C = r"""
/* x with a x = b (a row-major n x n, n <= 4), Gaussian elimination with partial pivoting. Returns 0, like
   controller.derivation.solve_small returns None, when |det| <= 1e-12 * (product of row max-norms), when
   anything is not finite, or when the solution is not finite. */
static int solve_small(int n, const double *a, const double *b, double *x) {
  double m[4][5];
  double scale = 1.0, det = 1.0;
  for (int i = 0; i < n; i++) {
    double rmax = 0.0;
    for (int j = 0; j < n; j++) {
      m[i][j] = a[i * n + j];
      if (fabs(m[i][j]) > rmax) rmax = fabs(m[i][j]);
    }
    m[i][n] = b[i];
    scale *= rmax;
  }
  for (int c = 0; c < n; c++) {
    int p = c;
    for (int r = c + 1; r < n; r++) if (fabs(m[r][c]) > fabs(m[p][c])) p = r;
    if (p != c) {
      for (int j = 0; j <= n; j++) { double t = m[c][j]; m[c][j] = m[p][j]; m[p][j] = t; }
      det = -det;
    }
    double piv = m[c][c];
    det *= piv;
    if (!(piv != 0.0)) return 0;
    for (int r = c + 1; r < n; r++) {
      double f = m[r][c] / piv;
      for (int j = c; j <= n; j++) m[r][j] -= f * m[c][j];
    }
  }
  if (!(fabs(det) > 1e-12 * scale) || !isfinite(det)) return 0;
  for (int i = n - 1; i >= 0; i--) {
    double s = m[i][n];
    for (int j = i + 1; j < n; j++) s -= m[i][j] * x[j];
    x[i] = s / m[i][i];
    if (!isfinite(x[i])) return 0;
  }
  return 1;
}
"""


def c_function(cname: str, args: Sequence[sympy.Symbol], steps: Sequence[tuple[sympy.Symbol, sympy.Expr]],
               outputs: Sequence[sympy.Expr], static: bool = True) -> str:
    """C99 source of `void cname(const double *in, double *out)`: the steps in order, then the outputs."""
    rename: dict[sympy.Symbol, sympy.Symbol] = {}
    lines = [f"{'static ' if static else ''}void {cname}(const double *restrict in, double *restrict out) {{"]
    for i, a in enumerate(args):
        rename[a] = sympy.Symbol(f"a{i}", real=True)
        lines.append(f"  const double a{i} = in[{i}];")
    printer = _Printer()
    for k, (sym, expr) in enumerate(steps):
        code = printer.doprint(expr.xreplace(rename))
        rename[sym] = sympy.Symbol(f"t{k}", real=True)
        lines.append(f"  const double t{k} = {code};")
    for i, expr in enumerate(outputs):
        lines.append(f"  out[{i}] = {printer.doprint(sympy.sympify(expr).xreplace(rename))};")
    lines.append("}")
    return "\n".join(lines) + "\n"


class NativeUnit:
    """One C translation unit: generated programs, hand-written glue calling them, exported entry points.

    Every function, generated or glue, has the signature `void f(const double *in, double *out)`; an
    export names one with its input and output lengths. `build()` compiles the unit once (cached) and
    returns the exports as Python callables `f(*inputs) -> list of outputs`.
    """

    def __init__(self) -> None:
        self._parts = ["#include <math.h>", SOLVE_C]
        self._exports: dict[str, tuple[int, int]] = {}
        self.problem: str | None = None  # why the unit cannot be built (checked by build_unit)

    def program(self, cname: str, args: Sequence[sympy.Symbol],
                steps: Sequence[tuple[sympy.Symbol, sympy.Expr]], outputs: Sequence[sympy.Expr]) -> None:
        """Add a generated program (if an expression cannot be printed as C, the unit records why)."""
        try:
            self._parts.append(c_function(cname, args, steps, outputs))
        except Exception as exc:  # noqa: BLE001 - any printer failure (an unsupported function) means Python
            self.problem = self.problem or f"{cname} not printable as C ({type(exc).__name__}: {exc})"

    def code(self, text: str) -> None:
        """Add hand-written C (glue functions)."""
        self._parts.append(text)

    def export(self, cname: str, n_in: int, n_out: int) -> None:
        """Make cname callable from Python with n_in inputs and n_out outputs."""
        self._exports[cname] = (n_in, n_out)

    def source(self) -> str:
        """The unit's C source, with one non-static trampoline per export."""
        tramp = [f"void export_{c}(const double *restrict in, double *restrict out) {{ {c}(in, out); }}"
                 for c in self._exports]
        return "\n".join(self._parts + tramp) + "\n"

    def build(self) -> dict[str, Callable[..., list[float]]]:
        """Compile (or load from the cache) and return {cname: callable}; raises RuntimeError/OSError."""
        lib = ctypes.CDLL(str(_build(self.source())))
        _loaded[lib._name] = lib
        return {c: _wrap(getattr(lib, f"export_{c}"), n_in, n_out)
                for c, (n_in, n_out) in self._exports.items()}


def _build(source: str) -> Path:
    """The shared library of source, from the cache or compiled now (atomic: safe across processes)."""
    cc = compiler()
    if cc is None:
        if os.environ.get("CC"):
            raise RuntimeError(f"CC={os.environ['CC']} is not on PATH")
        raise RuntimeError("no C compiler (cc, gcc or clang) on PATH")
    key = hashlib.sha256((cc + " ".join(CFLAGS) + source).encode()).hexdigest()[:24]
    directory = cache_dir()
    try:
        directory.mkdir(parents=True, exist_ok=True)
        probe = directory / f".write-test-{os.getpid()}"
        probe.touch()
        probe.unlink()
    except OSError:
        directory = Path(tempfile.gettempdir()) / f"quadsr-native-{os.getuid()}"
        directory.mkdir(parents=True, exist_ok=True)
    lib = directory / f"{key}.so"
    if lib.exists():
        return lib
    with tempfile.TemporaryDirectory(dir=directory) as tmp:
        src = Path(tmp) / "fn.c"
        src.write_text(source)
        out = Path(tmp) / "fn.so"
        proc = subprocess.run([*cc.split(), *CFLAGS, "-o", str(out), str(src), "-lm"], capture_output=True,
                              text=True, timeout=COMPILE_TIMEOUT_S)
        if proc.returncode != 0:
            first = (proc.stderr.strip().splitlines() or ["?"])[0]
            raise RuntimeError(f"{cc} failed: {first}")
        os.replace(out, lib)
    return lib


def _wrap(fn: Any, n_in: int, n_out: int) -> Callable[..., list[float]]:
    fn.restype = None
    fn.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
    inb = (ctypes.c_double * max(n_in, 1))()
    outb = (ctypes.c_double * max(n_out, 1))()
    pin, pout = ctypes.addressof(inb), ctypes.addressof(outb)
    lock = threading.Lock()  # the buffers are shared: two controllers on one law may run in two threads

    def call(*values: float) -> list[float]:
        with lock:
            inb[:n_in] = values
            fn(pin, pout)
            return outb[:n_out]

    call.buffers = (inb, outb)  # type: ignore[attr-defined]  # kept alive with the function
    return call


def _agrees(native: Callable[..., list[float]], python: Callable[..., list[float]],
            points: Sequence[Sequence[float]]) -> str | None:
    """None when native and Python agree at the points (where Python is defined); else what differed."""
    checked = 0
    for p in points:
        try:
            ref = [float(v) for v in python(*p)]
        except (ValueError, ZeroDivisionError, OverflowError, TypeError):
            continue
        got = native(*p)
        for i, (a, b) in enumerate(zip(ref, got, strict=True)):
            if math.isfinite(a) and not abs(a - b) <= 1e-9 * (1.0 + abs(a)):
                return f"output {i} differs at a check point ({b!r} native, {a!r} python)"
        checked += 1
    return None if checked else "no check point inside the expressions' domain"


def points_near(sample: Sequence[float], count: int = 3) -> list[list[float]]:
    """The sample and `count` seeded random points around it (each value moved by up to 30% of 1 + |v|)."""
    rng = random.Random(_SEED)
    base = [float(v) for v in sample]
    return [base] + [[v + rng.uniform(-0.3, 0.3) * (1.0 + abs(v)) for v in base] for _ in range(count)]


Twin = tuple[str, Callable[..., list[float]], Sequence[Sequence[float]]]


def build_unit(unit: NativeUnit, twins: Mapping[str, Twin]) -> dict[str, Callable[..., list[float]]]:
    """Each export of the unit as native code, or its Python twin when that cannot be (status() says why).

    twins: export name -> (label for status(), the Python function computing the same, points to check at).
    """
    def python_all(why: str) -> dict[str, Callable[..., list[float]]]:
        for label, _, _ in twins.values():
            _status[label] = why
        return {c: fn for c, (_, fn, _) in twins.items()}

    if not enabled():
        return python_all("QUADSR_NATIVE=0")
    if unit.problem is not None:
        return python_all(unit.problem)
    try:
        built = unit.build()
    except (RuntimeError, OSError, subprocess.SubprocessError) as exc:
        return python_all(str(exc))
    out = {}
    for cname, (label, python, points) in twins.items():
        problem = _agrees(built[cname], python, points)
        _status[label] = "native" if problem is None else f"native check failed: {problem}"
        out[cname] = built[cname] if problem is None else python
    return out


def compile_program(name: str, args: Sequence[sympy.Symbol],
                    steps: Sequence[tuple[sympy.Symbol, sympy.Expr]], outputs: Sequence[sympy.Expr],
                    python: Callable[..., list[float]], sample: Sequence[float] | None = None,
                    ) -> Callable[..., list[float]]:
    """A native twin of `python` (same args, a list of the outputs), or `python` itself if that fails.

    `sample`: a point inside the expressions' domain (e.g. hover) to check the twin at, besides
    seeded random points near it.
    """
    unit = NativeUnit()
    unit.program("fn", args, steps, outputs)
    unit.export("fn", len(args), len(outputs))
    points = points_near(sample if sample is not None else [0.0] * len(args))
    return build_unit(unit, {"fn": (name, python, points)})["fn"]


def compile_expressions(name: str, args: Sequence[sympy.Symbol], exprs: Sequence[sympy.Expr],
                        python: Callable[..., list[float]], sample: Sequence[float] | None = None,
                        ) -> Callable[..., list[float]]:
    """compile_program of expressions after common-subexpression elimination."""
    steps, reduced = sympy.cse(list(exprs), symbols=sympy.numbered_symbols("c_", real=True))
    return compile_program(name, args, steps, reduced, python, sample)
