"""The model file (model.yaml): the learned or true equations of motion, their provenance and metrics.

Expressions are strings in the 12 state and 4 input names only (docs/design.md). They are parsed with
a small AST walker (no eval), so a model file cannot run code.
"""

from __future__ import annotations

import ast
import datetime as _dt
import functools
import hashlib
import math
import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import sympy
import yaml
from sympy.printing.str import StrPrinter

from bridge.errors import UserError
from bridge.yaml_file import Section, load_yaml_file

FORMAT = "quadsr-model/2"  # written; /2 adds the learned body-frame expressions (section `body`)
FORMATS_READ: tuple[str, ...] = ("quadsr-model/1", "quadsr-model/2")
KINDS = ("learned", "true-model")

STATE_NAMES: tuple[str, ...] = ("x", "y", "z", "vx", "vy", "vz", "phi", "theta", "psi", "wx", "wy", "wz")
INPUT_NAMES: tuple[str, ...] = ("u1", "u2", "u3", "u4")
TARGET_NAMES: tuple[str, ...] = ("ax", "ay", "az", "dwx", "dwy", "dwz")
VARIABLE_NAMES: tuple[str, ...] = STATE_NAMES + INPUT_NAMES

STATE_VARIABLES: tuple[dict[str, str], ...] = (
    {"name": "x", "unit": "m", "frame": "NED", "description": "north position"},
    {"name": "y", "unit": "m", "frame": "NED", "description": "east position"},
    {"name": "z", "unit": "m", "frame": "NED", "description": "down position (z < 0 is above ground)"},
    {"name": "vx", "unit": "m/s", "frame": "NED", "description": "north velocity"},
    {"name": "vy", "unit": "m/s", "frame": "NED", "description": "east velocity"},
    {"name": "vz", "unit": "m/s", "frame": "NED", "description": "down velocity"},
    {"name": "phi", "unit": "rad", "frame": "ZYX Euler", "description": "roll"},
    {"name": "theta", "unit": "rad", "frame": "ZYX Euler", "description": "pitch"},
    {"name": "psi", "unit": "rad", "frame": "ZYX Euler", "description": "yaw"},
    {"name": "wx", "unit": "rad/s", "frame": "FRD", "description": "body roll rate"},
    {"name": "wy", "unit": "rad/s", "frame": "FRD", "description": "body pitch rate"},
    {"name": "wz", "unit": "rad/s", "frame": "FRD", "description": "body yaw rate"},
)
INPUT_VARIABLES: tuple[dict[str, str], ...] = (
    {"name": "u1", "unit": "rad/s", "description": "rotor 1 speed (front-right, CCW)"},
    {"name": "u2", "unit": "rad/s", "description": "rotor 2 speed (rear-left, CCW)"},
    {"name": "u3", "unit": "rad/s", "description": "rotor 3 speed (front-left, CW)"},
    {"name": "u4", "unit": "rad/s", "description": "rotor 4 speed (rear-right, CW)"},
)
TARGET_INFO: dict[str, dict[str, str]] = {
    "ax": {"description": "x'' (north acceleration)", "unit": "m/s^2", "frame": "NED"},
    "ay": {"description": "y'' (east acceleration)", "unit": "m/s^2", "frame": "NED"},
    "az": {"description": "z'' (down acceleration)", "unit": "m/s^2", "frame": "NED"},
    "dwx": {"description": "wx' (body roll acceleration)", "unit": "rad/s^2", "frame": "FRD"},
    "dwy": {"description": "wy' (body pitch acceleration)", "unit": "rad/s^2", "frame": "FRD"},
    "dwz": {"description": "wz' (body yaw acceleration)", "unit": "rad/s^2", "frame": "FRD"},
}

BODY_TARGET_INFO: dict[str, dict[str, str]] = {
    "fx": {"description": "specific force forward, (R^T (a - g e_z))_x", "unit": "m/s^2", "frame": "FRD"},
    "fy": {"description": "specific force right, (R^T (a - g e_z))_y", "unit": "m/s^2", "frame": "FRD"},
    "fz": {"description": "specific force down, (R^T (a - g e_z))_z", "unit": "m/s^2", "frame": "FRD"},
    **{n: TARGET_INFO[n] for n in ("dwx", "dwy", "dwz")},
}

# real=True lets sympy simplify Abs, sqrt etc.; other packages must use these symbols (Model.symbols).
SYMBOLS: dict[str, sympy.Symbol] = {name: sympy.Symbol(name, real=True) for name in VARIABLE_NAMES}

_FUNCTIONS: dict[str, Callable[..., sympy.Expr]] = {
    "sin": sympy.sin,
    "cos": sympy.cos,
    "tan": sympy.tan,
    "Abs": sympy.Abs,
    "abs": sympy.Abs,
    "sqrt": sympy.sqrt,
    "exp": sympy.exp,
    "log": sympy.log,
}
_CONSTANTS: dict[str, sympy.Expr] = {"pi": sympy.pi}


class ExpressionError(ValueError):
    """An expression string that is not a formula in the model's variables and building blocks."""


def _node_to_sympy(node: ast.AST, names: Mapping[str, sympy.Expr] = SYMBOLS) -> sympy.Expr:
    def walk(child: ast.AST) -> sympy.Expr:
        return _node_to_sympy(child, names)

    if isinstance(node, ast.Expression):
        return walk(node.body)
    if isinstance(node, ast.Constant):
        if isinstance(node.value, bool) or not isinstance(node.value, (int, float)):
            raise ExpressionError(f"constant {node.value!r} is not a number")
        if isinstance(node.value, int):
            return sympy.Integer(node.value)
        if not math.isfinite(node.value):
            raise ExpressionError(f"constant {node.value!r} is not finite")
        return sympy.Float(node.value)
    if isinstance(node, ast.Name):
        if node.id in names:
            return names[node.id]
        if node.id in _CONSTANTS:
            return _CONSTANTS[node.id]
        raise ExpressionError(f"unknown name {node.id!r} (allowed: {', '.join(names)}, pi)")
    if isinstance(node, ast.UnaryOp):
        operand = walk(node.operand)
        if isinstance(node.op, ast.USub):
            return -operand
        if isinstance(node.op, ast.UAdd):
            return operand
        raise ExpressionError(f"operator {type(node.op).__name__} is not allowed")
    if isinstance(node, ast.BinOp):
        left, right = walk(node.left), walk(node.right)
        if isinstance(node.op, ast.Add):
            return left + right
        if isinstance(node.op, ast.Sub):
            return left - right
        if isinstance(node.op, ast.Mult):
            return left * right
        if isinstance(node.op, ast.Div):
            return left / right
        if isinstance(node.op, ast.Pow):
            return left**right
        raise ExpressionError(f"operator {type(node.op).__name__} is not allowed")
    if isinstance(node, ast.Call):
        if not isinstance(node.func, ast.Name) or node.func.id not in _FUNCTIONS:
            name = node.func.id if isinstance(node.func, ast.Name) else ast.unparse(node.func)
            raise ExpressionError(f"function {name!r} is not allowed (allowed: {', '.join(_FUNCTIONS)})")
        if node.keywords or len(node.args) != 1:
            raise ExpressionError(f"function {node.func.id!r} takes exactly one argument")
        return _FUNCTIONS[node.func.id](walk(node.args[0]))
    raise ExpressionError(f"'{ast.unparse(node)}' is not allowed in an expression")


def parse_expression(text: str, names: Mapping[str, sympy.Expr] | None = None) -> sympy.Expr:
    """Parse a formula in the 16 variable names (or the given names) into sympy, without eval."""
    if not isinstance(text, str) or not text.strip():
        raise ExpressionError("expected a non-empty formula string")
    try:
        tree = ast.parse(text.strip().replace("^", "**"), mode="eval")
    except SyntaxError as exc:
        raise ExpressionError(f"not a formula: {exc.msg}") from None
    return _node_to_sympy(tree, SYMBOLS if names is None else names)


# the strings of compound nodes printed so far (_ExactFloatPrinter): a node's string does not depend on where
# it stands (its parent adds any parentheses), and the candidates a target's front lists share their terms
# (a hub law's is thousands of characters): seed 71's heavy closed loop's wy' front, 77 models, printed in
# 0.11 s with them against 0.42 s
_PRINTED: dict[sympy.Basic, str] = {}
_PRINTED_MAX = 20000


class _ExactFloatPrinter(StrPrinter):
    """sympy's str printer, but floats printed as Python's shortest exact repr (lossless round trip)."""

    def _print(self, expr: Any, **kwargs: Any) -> str:
        if kwargs or not isinstance(expr, sympy.Basic) or not expr.args:
            return super()._print(expr, **kwargs)
        text = _PRINTED.get(expr)
        if text is None:
            text = super()._print(expr)
            if len(_PRINTED) >= _PRINTED_MAX:
                _PRINTED.clear()
            _PRINTED[expr] = text
        return text

    def _print_Float(self, expr: sympy.Float) -> str:
        return repr(float(expr))


def expression_to_string(expr: sympy.Expr) -> str:
    """The sympy-parsable string written to the model file (floats exact to the last bit)."""
    return _ExactFloatPrinter({"order": "none"}).doprint(expr)


def check_expression(expr: sympy.Expr) -> None:
    """Raise ExpressionError if expr uses a symbol that is not a state or input."""
    bad = sorted(str(s) for s in expr.free_symbols if s not in SYMBOLS.values())
    if bad:
        raise ExpressionError(f"unknown names {bad} (allowed: {', '.join(VARIABLE_NAMES)})")


@functools.lru_cache(maxsize=8192)  # the pick sizes thousands of moves over one pool of terms
def complexity(expr: sympy.Expr) -> int:
    """The size of an expression: the number of nodes in its sympy tree, an integer power counted as one
    unary operator (its exponent is no node of its own) and an absolute value as two, as a square root
    (Pow(x, 1/2): x and its exponent): a kink costs what a fractional power does; a signed square x |x|
    (drag's v |v|, smooth: no kink) costs what x^2 does; a sign costs nothing (u1 - u2 is as large as
    u1 + u2: the mixer's patterns are alike in size)."""
    nodes = list(sympy.preorder_traversal(expr))
    if any(isinstance(node, sympy.Abs) for node in nodes):  # sized with each signed square as a square
        nodes = list(sympy.preorder_traversal(expr.replace(_holds_signed_square, _as_square)))
    signs = sum((2 if len(node.args) == 2 else 1) for node in nodes
                if node.is_Mul and any(a is sympy.S.NegativeOne for a in node.args))
    return (len(nodes) - sum(1 for node in nodes if node.is_Pow and node.exp.is_Integer)
            + sum(1 for node in nodes if isinstance(node, sympy.Abs)) - signs)


def _holds_signed_square(e: sympy.Expr) -> bool:
    """Whether e is a product holding some x and |x| (a signed square, complexity)."""
    return bool(e.is_Mul) and any(isinstance(a, sympy.Abs) and a.args[0] in e.args for a in e.args)


def _as_square(e: sympy.Expr) -> sympy.Expr:
    """The product e with each pair x, |x| of its factors as x^2 (unevaluated: only its size is read)."""
    out = list(e.args)
    for a in e.args:
        if isinstance(a, sympy.Abs) and a in out and a.args[0] in out:
            out.remove(a)
            out.remove(a.args[0])
            out.append(sympy.Pow(a.args[0], 2, evaluate=False))
    return sympy.Mul(*out, evaluate=False)


@functools.lru_cache(maxsize=4096)
def degree(expr: sympy.Expr) -> float:
    """The summed polynomial degree of an expression's additive terms (a factor's degree times its power's
    size, |x| as x, sqrt(x^2 + y^2) 1, 1/h^2 2, any other function 1, a number 0): the pick's tie-break
    between equally complex models (identification.pareto)."""
    return float(sum(_term_degree(t) for t in sympy.Add.make_args(sympy.sympify(expr))))


def _term_degree(e: sympy.Expr) -> float:
    """One term's degree (degree)."""
    if e.is_Number:
        return 0.0
    if e.is_Symbol:
        return 1.0
    if e.is_Mul:
        return sum(_term_degree(a) for a in e.args)
    if e.is_Add:
        return max(_term_degree(a) for a in e.args)
    if e.is_Pow:
        return abs(float(e.exp)) * _term_degree(e.base) if e.exp.is_Number else 1.0
    if isinstance(e, sympy.Abs):
        return _term_degree(e.args[0])
    return 1.0


def file_sha256(path: str | os.PathLike[str]) -> str:
    """The SHA-256 of a file's bytes, hex."""
    digest = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            digest.update(chunk)
    return digest.hexdigest()


def display_path(path: str | os.PathLike[str]) -> str:
    """A path as recorded in a model file: relative to the working directory when under it."""
    p = Path(path).resolve()
    try:
        return str(p.relative_to(Path.cwd().resolve()))
    except ValueError:
        return str(p)


@dataclass
class ParetoPoint:
    """One candidate of a target's Pareto front (complexity against error)."""

    complexity: int
    loss: float
    expression: str
    holdout_loss: float | None = None
    engine: str | None = None


@dataclass
class TargetModel:
    """One target's chosen expression with its front, metrics and how it was found."""

    name: str
    expression: sympy.Expr
    pareto: list[ParetoPoint] = field(default_factory=list)
    metrics: dict[str, dict[str, float]] = field(default_factory=dict)
    engine: str | None = None
    wall_time_s: float | None = None

    @property
    def description(self) -> str:
        """What the target is (for tables and plots)."""
        return _info(self.name)["description"]

    @property
    def unit(self) -> str:
        """The target's SI unit."""
        return _info(self.name)["unit"]

    @property
    def frame(self) -> str:
        """The target's frame: NED for linear, FRD for angular accelerations and body-frame targets."""
        return _info(self.name)["frame"]


def _info(name: str) -> dict[str, str]:
    return TARGET_INFO[name] if name in TARGET_INFO else BODY_TARGET_INFO[name]


@dataclass
class BodyModel:
    """What a body-frame learner found: fx fy fz dwx dwy dwz in primitive names, and those primitives.

    The six NED/FRD targets of the Model are composed from it exactly (a = R f_b + g e_z).
    """

    targets: dict[str, TargetModel]
    primitives: dict[str, dict[str, Any]]  # name -> {expression (16 variables), unit, frame, description}
    gravity: float  # m/s^2, along +z (down) in NED

    def symbols(self) -> dict[str, sympy.Symbol]:
        """Primitive name -> Symbol (the state and input symbols where the name is one of the 16)."""
        return {n: SYMBOLS[n] if n in SYMBOLS else sympy.Symbol(n, real=True) for n in self.primitives}


class Model:
    """Equations of motion: per target a sympy expression in the 12 states and 4 rotor speeds."""

    state_names: tuple[str, ...] = STATE_NAMES
    input_names: tuple[str, ...] = INPUT_NAMES

    def __init__(
        self,
        targets: Mapping[str, TargetModel | sympy.Expr],
        kind: str = "learned",
        vehicle: dict[str, Any] | None = None,
        flights: list[dict[str, Any]] | None = None,
        engine: dict[str, Any] | None = None,
        created: str | None = None,
        source: str | None = None,
        extra: dict[str, Any] | None = None,
        body: BodyModel | None = None,
    ):
        if kind not in KINDS:
            raise ValueError(f"kind must be one of {KINDS}, not {kind!r}")
        self.targets: dict[str, TargetModel] = {}
        for name in TARGET_NAMES:
            if name not in targets:
                continue
            entry = targets[name]
            if not isinstance(entry, TargetModel):
                entry = TargetModel(name=name, expression=sympy.sympify(entry))
            check_expression(entry.expression)
            self.targets[name] = entry
        unknown = set(targets) - set(TARGET_NAMES)
        if unknown:
            raise ValueError(f"unknown targets {sorted(unknown)} (known: {TARGET_NAMES})")
        self.kind = kind
        self.vehicle = vehicle
        self.flights = list(flights or [])
        self.engine = dict(engine or {})
        self.created = created or _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
        self.source = source
        self.extra = dict(extra or {})
        self.body = body  # the learned body-frame expressions (format /2), None for NED-learned models
        self._scalar_fn: Callable[..., Any] | None = None
        self._vector_fns: dict[str, Callable[..., Any]] | None = None

    @property
    def target_names(self) -> tuple[str, ...]:
        """The targets this model has an expression for, in the canonical order."""
        return tuple(self.targets)

    @property
    def expressions(self) -> dict[str, sympy.Expr]:
        """Target name -> sympy expression (ax, ay, az NED m/s^2; dwx, dwy, dwz FRD rad/s^2)."""
        return {name: t.expression for name, t in self.targets.items()}

    @property
    def symbols(self) -> dict[str, sympy.Symbol]:
        """Variable name -> sympy Symbol (real), the 12 states then the 4 inputs."""
        return dict(SYMBOLS)

    @property
    def state_symbols(self) -> tuple[sympy.Symbol, ...]:
        """The 12 state symbols in xi order."""
        return tuple(SYMBOLS[n] for n in STATE_NAMES)

    @property
    def input_symbols(self) -> tuple[sympy.Symbol, ...]:
        """The 4 rotor-speed symbols u1..u4."""
        return tuple(SYMBOLS[n] for n in INPUT_NAMES)

    def _require_all(self) -> None:
        missing = [n for n in TARGET_NAMES if n not in self.targets]
        if missing:
            where = f" {self.source}" if self.source else ""
            raise UserError(
                f"model{where} has no expression for {', '.join(missing)}",
                hint="identify all six targets (quadsr identify without --targets)",
            )

    def _build(self) -> None:
        """The per-target numpy functions (rows of states); the scalar one is built on first use
        (_scalar): identify composes and scores its model on arrays only (seed 71's heavy closed loop:
        0.34 of 0.87 s building both)."""
        args = [SYMBOLS[n] for n in VARIABLE_NAMES]
        self._vector_fns = {
            n: sympy.lambdify(args, self.targets[n].expression, modules="numpy", cse=True)
            for n in self.target_names
        }

    def _scalar(self) -> Callable[..., Any]:
        """The targets as one function of 16 floats (math module: a controller's single state)."""
        if self._scalar_fn is None:
            args = [SYMBOLS[n] for n in VARIABLE_NAMES]
            exprs = [self.targets[n].expression for n in self.target_names]
            self._scalar_fn = sympy.lambdify(args, exprs, modules="math", cse=True)
        return self._scalar_fn

    def accelerations(self, xi: Any, u: Any) -> np.ndarray:
        """The six targets at state xi (12,) and rotor speeds u (4,) -> (6,); or (N,12),(N,4) -> (N,6)."""
        self._require_all()
        return self.evaluate(xi, u)

    def evaluate(self, xi: Any, u: Any) -> np.ndarray:
        """The targets this model has (target_names order), like accelerations() but for any subset."""
        if self._vector_fns is None:
            self._build()
        xi_a = np.asarray(xi, dtype=float)
        u_a = np.asarray(u, dtype=float)
        if xi_a.shape[-1:] != (12,) or u_a.shape[-1:] != (4,):
            raise ValueError(f"expected xi (...,12) and u (...,4), got {xi_a.shape} and {u_a.shape}")
        if xi_a.ndim == 1 and u_a.ndim == 1:
            try:
                return np.array(self._scalar()(*xi_a.tolist(), *u_a.tolist()), dtype=float)
            except (ValueError, ZeroDivisionError, OverflowError):
                pass  # math domain error: fall through to numpy's nan/inf semantics
        xi2 = np.atleast_2d(xi_a)
        u2 = np.atleast_2d(u_a)
        n = max(xi2.shape[0], u2.shape[0])
        cols = [xi2[:, i] for i in range(12)] + [u2[:, i] for i in range(4)]
        out = np.empty((n, len(self.targets)))
        with np.errstate(all="ignore"):
            for j, name in enumerate(self.target_names):
                out[:, j] = np.broadcast_to(self._vector_fns[name](*cols), (n,))
        if xi_a.ndim == 1 and u_a.ndim == 1:
            return out[0]
        return out

    @property
    def kinematics(self) -> dict[str, sympy.Expr]:
        """The known (not learned) Euler-angle rates phi', theta', psi' (rad/s) as sympy expressions."""
        from identification.kinematics import euler_rate_expressions

        return euler_rate_expressions(SYMBOLS)

    def state_derivative(self, xi: Any, u: Any) -> np.ndarray:
        """xi' (12,) or (N,12): velocity NED, accelerations, Euler rates (known), body angular accel."""
        from identification.kinematics import euler_rates

        xi_a = np.asarray(xi, dtype=float)
        acc = self.accelerations(xi_a, u)
        out = np.empty(np.broadcast_shapes(xi_a.shape, acc.shape[:-1] + (12,)))
        out[..., 0:3] = xi_a[..., 3:6]
        out[..., 3:6] = acc[..., 0:3]
        out[..., 6:9] = euler_rates(xi_a[..., 6], xi_a[..., 7], xi_a[..., 9:12])
        out[..., 9:12] = acc[..., 3:6]
        return out

    def functions(self) -> dict[str, Callable[..., Any]]:
        """Target -> numpy function of the 16 variables (x..wz, u1..u4) as separate arguments."""
        if self._vector_fns is None:
            self._build()
        assert self._vector_fns is not None
        return dict(self._vector_fns)


# ---------------------------------------------------------------------------------------------------
# writing


def _plain(value: Any) -> Any:
    """Numpy scalars and tuples to YAML-safe builtins."""
    if isinstance(value, dict):
        return {str(k): _plain(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_plain(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return _plain(value.tolist())
    if isinstance(value, float) and not math.isfinite(value):
        return None if math.isnan(value) else value
    return value


def _target_entry(t: TargetModel) -> dict[str, Any]:
    entry: dict[str, Any] = dict(_info(t.name))
    entry["expression"] = expression_to_string(t.expression)
    entry["complexity"] = complexity(t.expression)
    if t.engine is not None:
        entry["engine"] = t.engine
    if t.wall_time_s is not None:
        entry["wall_time_s"] = round(float(t.wall_time_s), 3)
    entry["pareto"] = []
    for p in t.pareto:
        point: dict[str, Any] = {"complexity": int(p.complexity), "loss": float(p.loss)}
        if p.holdout_loss is not None:
            point["holdout_loss"] = float(p.holdout_loss)
        if p.engine is not None:
            point["engine"] = p.engine
        point["expression"] = p.expression
        entry["pareto"].append(point)
    if t.metrics:
        entry["metrics"] = _plain(t.metrics)
    return entry


def model_to_dict(model: Model) -> dict[str, Any]:
    """The model as the YAML mapping of docs/design.md."""
    targets = {name: _target_entry(t) for name, t in model.targets.items()}
    body: dict[str, Any] | None = None
    if model.body is not None:
        body = {
            "gravity": float(model.body.gravity),
            "primitives": _plain(model.body.primitives),
            "targets": {name: _target_entry(t) for name, t in model.body.targets.items()},
        }
    data: dict[str, Any] = {
        "format": FORMAT,
        "kind": model.kind,
        "created": model.created,
        "vehicle": _plain(model.vehicle),
        "flights": _plain(model.flights),
        "variables": {
            "states": [dict(v) for v in STATE_VARIABLES],
            "inputs": [dict(v) for v in INPUT_VARIABLES],
        },
        "targets": targets,
    }
    if body is not None:
        data["body"] = body
    data["engine"] = _plain(model.engine)
    data.update(_plain(model.extra))
    return data


def save_model(model: Model, path: str | os.PathLike[str]) -> Path:
    """Write the model as YAML (atomically: a killed run never leaves half a file)."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    text = yaml.safe_dump(model_to_dict(model), sort_keys=False, width=100000, allow_unicode=True)
    tmp = out.with_name(out.name + ".tmp")
    with open(tmp, "w", encoding="utf-8") as fh:
        fh.write(text)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, out)
    return out


# ---------------------------------------------------------------------------------------------------
# reading


MODEL_HINT = "regenerate it with `quadsr identify` or `quadsr model-from-vehicle`, or fix that key"


def _expression(sec: Section, name: str, names: Mapping[str, sympy.Expr] | None = None) -> sympy.Expr:
    """The checked formula at this key (`names`: the symbols it may use; None: the state and input names)."""
    try:
        expr = parse_expression(sec.raw(name), names)
        if names is None:
            check_expression(expr)
    except ExpressionError as exc:
        raise sec.fail(name, f"is not a usable formula: {exc}") from None
    return expr


def _optional_number(sec: Section, name: str) -> float | None:
    """A number (NaN allowed: a metric that could not be computed) or None when absent or null."""
    return None if sec.raw(name, None) is None else sec.number(name, finite=False)


def _read_variables(top: Section) -> None:
    if not top.has("variables"):
        return  # optional: the names are fixed by the format
    variables = top.section("variables")
    for key, expected in (("states", STATE_NAMES), ("inputs", INPUT_NAMES)):
        items = variables.sections(key, "{name, unit, ...}", min_items=0)
        names = [item.raw("name", None) for item in items]
        if tuple(names) != expected:
            raise variables.fail(key, f"must hold the names {list(expected)} in this order, got {names}")


def _read_target(entry: Section, name: str, names: Mapping[str, sympy.Expr] | None = None) -> TargetModel:
    expr = _expression(entry, "expression", names)
    pareto: list[ParetoPoint] = []
    points = [] if entry.raw("pareto", None) is None else entry.sections(
        "pareto", "{complexity, loss, expression}", min_items=0)
    for point in points:
        _expression(point, "expression", names)
        pareto.append(
            ParetoPoint(
                complexity=point.integer("complexity"),
                loss=point.number("loss", finite=False),
                expression=str(point.raw("expression")),
                holdout_loss=_optional_number(point, "holdout_loss"),
                engine=point.raw("engine", None),
            )
        )
    metrics: dict[str, dict[str, float]] = {}
    raw_metrics = entry.optional_section("metrics")
    for split in raw_metrics.keys():
        values = raw_metrics.section(split)
        metrics[str(split)] = {str(m): _optional_number(values, m) for m in values.keys()}  # type: ignore
    return TargetModel(
        name=name,
        expression=expr,
        pareto=pareto,
        metrics=metrics,
        engine=entry.raw("engine", None),
        wall_time_s=_optional_number(entry, "wall_time_s"),
    )


def load_model(path: str | os.PathLike[str]) -> Model:
    """Read a model.yaml; a missing, unreadable or malformed file is a UserError naming file and key."""
    p = Path(path)
    if not p.exists():
        raise UserError(f"model file {p} does not exist",
                        hint="write one with `quadsr identify` or `quadsr model-from-vehicle`")
    where = f"model file {p}"
    data = load_yaml_file(p, where)
    if data is None:
        raise UserError(f"{where}: the file is empty", hint=MODEL_HINT)
    top = Section(where, data, hint=MODEL_HINT)
    if not top.has("format"):
        raise top.fail("format", f"is missing (expected {FORMAT!r})")
    if top.raw("format") not in FORMATS_READ:
        raise top.fail("format", f"is {top.raw('format')!r}, which this quadsr cannot read "
                                 f"(it reads {', '.join(FORMATS_READ)})")
    kind = top.text("kind", KINDS, default="learned")
    _read_variables(top)
    raw_targets = top.section("targets")
    if not raw_targets.data:
        raise top.fail("targets", "holds no targets")
    targets = {name: _read_target(raw_targets.section(name), name)
               for name in TARGET_NAMES if raw_targets.has(name)}
    raw_targets.done()
    vehicle = top.section("vehicle").data if top.raw("vehicle", None) is not None else None
    flights = [] if not top.raw("flights", None) else [
        f.data for f in top.sections("flights", "{file, sha256, format}", min_items=0)]
    engine = top.optional_section("engine").data
    created = top.raw("created", None)
    body = _read_body(top.section("body")) if top.raw("body", None) is not None else None
    known = {"format", "kind", "created", "vehicle", "flights", "variables", "targets", "engine", "body"}
    extra = {k: v for k, v in data.items() if k not in known}
    return Model(
        targets,
        kind=kind,
        vehicle=vehicle,
        flights=flights,
        engine=engine,
        created=str(created) if created is not None else None,
        source=str(p),
        extra=extra,
        body=body,
    )


def _read_body(body: Section) -> BodyModel:
    """The `body` section (format /2): gravity, primitive definitions, body-frame targets in their names."""
    gravity = body.number("gravity")
    prims = body.section("primitives")
    primitives: dict[str, dict[str, Any]] = {}
    for name in prims.keys():
        info = prims.section(name)
        if not str(name).isidentifier():
            raise prims.fail(name, "is not a name")
        _expression(info, "expression")
        primitives[str(name)] = dict(info.data)
    model = BodyModel({}, primitives, gravity)
    names = {**SYMBOLS, **model.symbols()}
    raw_targets = body.section("targets")
    for name in raw_targets.keys():
        if name not in BODY_TARGET_INFO:
            raise raw_targets.fail(name, "is not a body target", hint=f"known: {', '.join(BODY_TARGET_INFO)}")
        model.targets[name] = _read_target(raw_targets.section(name), name, names)
    return model
