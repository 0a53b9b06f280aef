"""The user's YAML settings files, read and checked one way: text -> mapping -> typed, validated dataclasses.

Every settings file (vehicle, excitation profile, engine settings, controller gains, estimator settings,
trajectory, campaign, model) is parsed here (`load_yaml_file`) and read key by key through a `Section`, so a
mistake reads the same whichever file it is in and always names the file, the dotted key and what to do:

- "<where>: cannot read it (...)", "<where>: YAML syntax error at line L, column C: <problem>";
- "<where>: key 'a.b' is missing", "<where>: unknown key 'a.b'" (hint: the keys allowed there),
  "<where>: key 'a.b' must be > 0, got -1", "... must be one of x, y, got 'z'",
  "... must be a list of 3 numbers";
- a flat dataclass of settings is read field by field from its type hints (`read_dataclass`).

Numbers: YAML 1.1 reads 1e-4 (no dot) as a string: accepted as Python reads it, and so are 'pi', 'pi/4',
'-2*pi/3' (angles in rad). Each mistake is a `bridge.errors.UserError`, which the CLI prints and exits 2 on.
"""

from __future__ import annotations

import dataclasses
import math
import re
import typing
from pathlib import Path
from typing import Any

import yaml

from bridge.errors import UserError

Vec3 = tuple[float, float, float]
_PI_RE = re.compile(r"^\s*([-+]?\d*\.?\d*)\s*\*?\s*pi\s*(?:/\s*(\d+\.?\d*))?\s*$")


def load_yaml_text(text: str, where: str) -> Any:
    """The parsed document of YAML text (None when empty); UserError naming `where` on a syntax error."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise UserError(f"{where}: YAML syntax error{at}: {problem}", hint="fix the YAML syntax") from None


def load_yaml_file(path: Path, where: str) -> Any:
    """The parsed document of a YAML file (None when empty); UserError naming `where` if unreadable or bad."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{where}: cannot read it ({exc})") from None
    return load_yaml_text(text, where)


def describe_value(value: Any) -> str:
    """A value as a message shows it: its type and repr ('nothing' for None)."""
    return "nothing" if value is None else f"{type(value).__name__} {value!r}"


def _number_text(text: str) -> float | None:
    """A float from '1e-4', 'pi', 'pi/4', '-2*pi/3'; None if it is none of these."""
    m = _PI_RE.match(text)
    if m:
        k = m.group(1)
        factor = -1.0 if k == "-" else (1.0 if k in ("", "+") else float(k))
        return factor * math.pi / (float(m.group(2)) if m.group(2) else 1.0)
    try:
        return float(text)
    except ValueError:
        return None


def float_value(where: str, key: str, value: Any, finite: bool = True) -> float:
    """The number a key holds (finite unless finite=False); UserError naming where and key otherwise."""
    if isinstance(value, str):
        parsed = _number_text(value)
        value = value if parsed is None else parsed
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise UserError(f"{where}: key '{key}' must be a number, got {describe_value(value)}")
    out = float(value)
    if finite and not math.isfinite(out):
        raise UserError(f"{where}: key '{key}' must be finite, got {value}")
    return out


def check_bounds(where: str, key: str, value: float, *, positive: bool = False, nonnegative: bool = False,
                 low: float | None = None, high: float | None = None) -> None:
    """UserError naming where and key unless value is > 0 (positive), >= 0, >= low and <= high as asked."""
    if positive and not value > 0:
        raise UserError(f"{where}: key '{key}' must be > 0, got {value:g}")
    if nonnegative and not value >= 0:
        raise UserError(f"{where}: key '{key}' must be >= 0, got {value:g}")
    if low is not None and not value >= low:
        raise UserError(f"{where}: key '{key}' must be >= {low:g}, got {value:g}")
    if high is not None and not value <= high:
        raise UserError(f"{where}: key '{key}' must be <= {high:g}, got {value:g}")


def vec3_value(where: str, key: str, value: Any) -> Vec3:
    """The 3 finite numbers a key holds (a list); UserError naming where and key otherwise."""
    return numbers_value(where, key, value, 3)  # type: ignore[return-value]


def numbers_value(where: str, key: str, value: Any, n: int) -> tuple[float, ...]:
    """The n finite numbers a key holds (a list); UserError naming where and key otherwise."""
    if not isinstance(value, (list, tuple)) or len(value) != n:
        raise UserError(f"{where}: key '{key}' must be a list of {n} numbers, got {describe_value(value)}")
    return tuple(float_value(where, f"{key}[{i}]", v) for i, v in enumerate(value))


def range_value(where: str, key: str, value: Any, low: float | None = 0.0) -> tuple[float, float]:
    """A [low, high] pair of numbers (each >= `low` unless None); UserError naming where and key otherwise."""
    if not isinstance(value, (list, tuple)) or len(value) != 2:
        raise UserError(f"{where}: key '{key}' must be [low, high], got {describe_value(value)}")
    a, b = numbers_value(where, key, value, 2)
    for i, v in enumerate((a, b)):
        check_bounds(where, f"{key}[{i}]", v, low=low)
    if b < a:
        raise UserError(f"{where}: key '{key}' must be [low, high] with low <= high, got {[a, b]}")
    return a, b


def integer_value(where: str, key: str, value: Any, *, low: int | None = 0, high: int | None = None) -> int:
    """The integer a key holds, within [low, high] (None: unbounded); UserError naming where and key."""
    if isinstance(value, bool) or not isinstance(value, int):
        raise UserError(f"{where}: key '{key}' must be an integer, got {describe_value(value)}")
    if low is not None and value < low:
        raise UserError(f"{where}: key '{key}' must be an integer >= {low}, got {value}")
    if high is not None and value > high:
        raise UserError(f"{where}: key '{key}' must be an integer <= {high}, got {value}")
    return value


class Section:
    """Reads one mapping of a settings file key by key, naming file and dotted key in every mistake.

    `where` names the file ("vehicle file x.yaml"), `prefix` the mapping's dotted key ("" at the top),
    `hint` is what to do after a missing or unknown key (e.g. which file shows every key), `noun` how the
    keys are called in messages ("key"; "gain", "parameter"). `done()` rejects the keys nobody read.
    """

    def __init__(self, where: str, data: Any, prefix: str = "", *, hint: str | None = None,
                 noun: str = "key"):
        self.where = where
        self.prefix = prefix
        self.hint = hint
        self.noun = noun
        if not isinstance(data, dict):
            what = f"key '{prefix}'" if prefix else "the top level"
            raise UserError(f"{where}: {what} must be a mapping, got {describe_value(data)}", hint=hint)
        self.data = data
        self.used: set[str] = set()

    def key(self, name: str) -> str:
        """The dotted key of `name` in this mapping."""
        return f"{self.prefix}.{name}" if self.prefix else str(name)

    def fail(self, name: str, what: str, hint: str | None = None) -> UserError:
        """The UserError "<where>: key '<dotted key>' <what>" (to raise), with this file's hint by default."""
        return UserError(f"{self.where}: {self.noun} '{self.key(name)}' {what}",
                         hint=self.hint if hint is None else hint)

    def child(self, key: str, data: Any) -> Section:
        """A Section over `data` at dotted key `key` (a list item: 'rotors[0]'), same file, hint and noun."""
        return Section(self.where, data, key, hint=self.hint, noun=self.noun)

    def raw(self, name: str, default: Any = ...) -> Any:
        """The value at this key as parsed (marks it read); missing and no default: UserError."""
        self.used.add(name)
        if name not in self.data:
            if default is ...:
                raise self.fail(name, "is missing")
            return default
        return self.data[name]

    def has(self, name: str) -> bool:
        """True when the mapping holds this key (marks it read)."""
        self.used.add(name)
        return name in self.data

    def keys(self) -> list[str]:
        """Every key of this mapping, as given (marks them read: the caller checks each)."""
        self.used.update(self.data)
        return list(self.data)

    def section(self, name: str) -> Section:
        """The sub-mapping at this key (required)."""
        return self.child(self.key(name), self.raw(name))

    def optional_section(self, name: str) -> Section:
        """The sub-mapping at this key, an empty one when the key is absent or empty (null)."""
        value = self.raw(name, None)
        return self.child(self.key(name), {} if value is None else value)

    def sections(self, name: str, what: str, *, min_items: int = 1, default: Any = ...) -> list[Section]:
        """The list of mappings at this key, one Section each ('name[i]'); `what` says what an item is."""
        items = self.raw(name, default)
        if not isinstance(items, list) or len(items) < min_items:
            at_least = f"at least {min_items} " if min_items > 1 else ""
            raise self.fail(name, f"must be a list of {at_least}{what}, got {describe_value(items)}")
        return [self.child(f"{self.key(name)}[{i}]", item) for i, item in enumerate(items)]

    def number(self, name: str, default: Any = ..., *, positive: bool = False, nonnegative: bool = False,
               low: float | None = None, high: float | None = None, finite: bool = True) -> float:
        """A float (finite unless finite=False: NaN, inf allowed), checked against the bounds asked for."""
        value = float_value(self.where, self.key(name), self.raw(name, default), finite)
        check_bounds(self.where, self.key(name), value, positive=positive, nonnegative=nonnegative,
                     low=low, high=high)
        return value

    def integer(self, name: str, default: Any = ..., *, low: int | None = 0, high: int | None = None) -> int:
        """An integer within [low, high] (None: unbounded)."""
        return integer_value(self.where, self.key(name), self.raw(name, default), low=low, high=high)

    def flag(self, name: str, default: Any = ...) -> bool:
        """true or false."""
        value = self.raw(name, default)
        if not isinstance(value, bool):
            raise self.fail(name, f"must be true or false, got {describe_value(value)}")
        return value

    def text(self, name: str, choices: tuple[str, ...] | None = None, default: Any = ...) -> str:
        """A string, one of `choices` when given."""
        value = self.raw(name, default)
        if not isinstance(value, str):
            raise self.fail(name, f"must be a string, got {describe_value(value)}")
        if choices is not None and value not in choices:
            raise self.fail(name, f"must be one of {', '.join(choices)}, got {value!r}")
        return value

    def texts(self, name: str, default: Any = ...) -> tuple[str, ...]:
        """A list of strings (a comma-separated string too)."""
        value = self.raw(name, default)
        if isinstance(value, str):
            value = [v.strip() for v in value.split(",") if v.strip()]
        if not isinstance(value, (list, tuple)) or not all(isinstance(v, str) for v in value):
            raise self.fail(name, f"must be a list of strings, got {describe_value(value)}")
        return tuple(value)

    def numbers(self, name: str, n: int, default: Any = ..., *,
                low: float | None = None) -> tuple[float, ...]:
        """A list of n finite floats, each >= low when given."""
        key = self.key(name)
        out = numbers_value(self.where, key, self.raw(name, default), n)
        for i, v in enumerate(out):
            check_bounds(self.where, f"{key}[{i}]", v, low=low)
        return out

    def range(self, name: str, default: Any = ..., *, low: float | None = 0.0) -> tuple[float, float]:
        """A [low, high] pair with low <= high, each >= `low` (None: unbounded)."""
        return range_value(self.where, self.key(name), self.raw(name, default), low)

    def vec3(self, name: str, default: Any = ..., *, nonnegative: bool = False,
             scalar_ok: bool = False) -> Vec3:
        """Three finite floats (one number for all three when scalar_ok)."""
        value = self.raw(name, default)
        if scalar_ok and not isinstance(value, (list, tuple)):
            v = float_value(self.where, self.key(name), value)
            out: Vec3 = (v, v, v)
        else:
            out = vec3_value(self.where, self.key(name), value)
        for v in out:
            check_bounds(self.where, self.key(name), v, nonnegative=nonnegative)
        return out

    def done(self) -> None:
        """UserError naming the first key nobody read (hint: the keys allowed here)."""
        unknown = [k for k in self.data if k not in self.used]
        if unknown:
            known = ", ".join(sorted(map(str, self.used)))
            raise UserError(f"{self.where}: unknown {self.noun} '{self.key(str(unknown[0]))}'",
                            hint=f"{self.noun}s allowed here: {known}")


def read_dataclass(sec: Section, cls: type, *, positive: bool = False) -> Any:
    """An instance of dataclass `cls` from a Section: each given key read by its field's type, others default.

    float: finite and >= 0 (> 0 with positive), int: >= 0, bool, str, tuple[str, ...] (a list or a
    comma-separated string), a nested dataclass: a sub-mapping read the same way. Unknown keys: UserError.
    """
    hints = typing.get_type_hints(cls)
    values: dict[str, Any] = {}
    for f in dataclasses.fields(cls):
        if not sec.has(f.name):
            continue
        tp = hints[f.name]
        if dataclasses.is_dataclass(tp):
            values[f.name] = read_dataclass(sec.section(f.name), tp, positive=positive)  # type: ignore[arg-type]
        elif typing.get_origin(tp) is tuple:
            values[f.name] = sec.texts(f.name)
        elif tp is bool:
            values[f.name] = sec.flag(f.name)
        elif tp is int:
            values[f.name] = sec.integer(f.name)
        elif tp is float:
            values[f.name] = sec.number(f.name, positive=positive, nonnegative=not positive)
        elif tp is str:
            values[f.name] = sec.text(f.name)
        else:
            raise TypeError(f"read_dataclass: field {cls.__name__}.{f.name} has unsupported type {tp}")
    sec.done()
    return cls(**values)
