"""The user's YAML settings files (vehicle, profile, gains, trajectory, model): read once, one error style.

Every file kind reads its text and parses it here, so a mistake reads the same whichever file it is in:
"<where>: cannot read it (...)" or "<where>: YAML syntax error at line L, column C: <problem>"; and a number
a key holds is checked here (YAML 1.1 reads 1e-4, without a dot, as a string: accepted as Python reads it).
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import yaml

from bridge.errors import UserError


def load_yaml_file(path: Path, where: str) -> Any:
    """The parsed document of a YAML file (None when empty); UserError naming `where` if unreadable or bad."""
    try:
        text = path.read_text(encoding="utf-8")
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"{where}: cannot read it ({exc})") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        at = f" at line {mark.line + 1}, column {mark.column + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or str(exc)
        raise UserError(f"{where}: YAML syntax error{at}: {problem}", hint="fix the YAML syntax") from None


def describe_value(value: Any) -> str:
    """A value as a message shows it: its type and repr ('nothing' for None)."""
    return "nothing" if value is None else f"{type(value).__name__} {value!r}"


def float_value(where: str, key: str, value: Any) -> float:
    """The finite number a key holds; UserError naming where and key otherwise."""
    if isinstance(value, str):
        try:
            value = float(value)
        except ValueError:
            pass
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise UserError(f"{where}: key '{key}' must be a number, got {describe_value(value)}")
    out = float(value)
    if not math.isfinite(out):
        raise UserError(f"{where}: key '{key}' must be finite, got {value}")
    return out
