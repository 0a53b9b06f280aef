"""One mapping of a user's YAML settings file, read key by key into checked values.

`Section(where, data, prefix)` names each mistake by file (`where`) and dotted key path; `done()` rejects the
keys nobody read. Used by the vehicle file's readers (bridge.vehicle, bridge.airframe).
"""

from __future__ import annotations

from typing import Any

from bridge.errors import UserError
from bridge.yaml_file import describe_value, float_value

Vec3 = tuple[float, float, float]


class Section:
    """Reads one mapping of a settings file, tracking the dotted key path and rejecting unknown keys."""

    def __init__(self, where: str, data: Any, prefix: str):
        self.where = where
        self.prefix = prefix
        if not isinstance(data, dict):
            what = f"key '{prefix}'" if prefix else "the top level"
            raise UserError(f"{where}: {what} must be a mapping, got {describe_value(data)}")
        self.data = data
        self.used: set[str] = set()

    def key(self, name: str) -> str:
        return f"{self.prefix}.{name}" if self.prefix else name

    def raw(self, name: str, default: Any = ...) -> Any:
        self.used.add(name)
        if name not in self.data:
            if default is ...:
                raise UserError(f"{self.where}: missing key '{self.key(name)}'",
                                hint="see sitl/vehicles/fang-chen-buaa.yaml for every key with its unit")
            return default
        return self.data[name]

    def has(self, name: str) -> bool:
        """True when the mapping holds this key (marks it read)."""
        self.used.add(name)
        return name in self.data

    def section(self, name: str) -> Section:
        return Section(self.where, self.raw(name), self.key(name))

    def optional_section(self, name: str) -> Section:
        """The sub-mapping at this key, an empty one when the key is absent."""
        return Section(self.where, self.raw(name, {}), self.key(name))

    def number(self, name: str, *, positive: bool = False, nonnegative: bool = False,
               default: Any = ...) -> float:
        value = float_value(self.where, self.key(name), self.raw(name, default))
        check_sign(self.where, self.key(name), value, positive, nonnegative)
        return value

    def integer(self, name: str, *, nonnegative: bool = True, default: Any = ...) -> int:
        value = self.raw(name, default)
        if isinstance(value, bool) or not isinstance(value, int):
            raise UserError(f"{self.where}: key '{self.key(name)}' must be an integer, "
                            f"got {describe_value(value)}")
        if nonnegative and value < 0:
            raise UserError(f"{self.where}: key '{self.key(name)}' must be >= 0, got {value}")
        return value

    def text(self, name: str, choices: tuple[str, ...] | None = None, default: Any = ...) -> str:
        value = self.raw(name, default)
        if not isinstance(value, str):
            raise UserError(f"{self.where}: key '{self.key(name)}' must be a string, "
                            f"got {describe_value(value)}")
        if choices is not None and value not in choices:
            raise UserError(f"{self.where}: key '{self.key(name)}' must be one of {', '.join(choices)}, "
                            f"got {value!r}")
        return value

    def vec3(self, name: str, *, nonnegative: bool = False, scalar_ok: bool = False,
             default: Any = ...) -> Vec3:
        value = self.raw(name, default)
        if scalar_ok and not isinstance(value, (list, tuple)):
            v = float_value(self.where, self.key(name), value)
            out = (v, v, v)
        else:
            out = vec3_value(self.where, self.key(name), value)
        for v in out:
            check_sign(self.where, self.key(name), v, False, nonnegative)
        return out

    def done(self) -> None:
        unknown = [k for k in self.data if k not in self.used]
        if unknown:
            known = ", ".join(sorted(self.used))
            raise UserError(f"{self.where}: unknown key '{self.key(str(unknown[0]))}'",
                            hint=f"keys allowed here: {known}")


def vec3_value(where: str, key: str, value: Any) -> Vec3:
    if not isinstance(value, (list, tuple)) or len(value) != 3:
        raise UserError(f"{where}: key '{key}' must be a list of 3 numbers, got {describe_value(value)}")
    return tuple(float_value(where, f"{key}[{i}]", v) for i, v in enumerate(value))  # type: ignore[return-value]


def check_sign(where: str, key: str, value: float, positive: bool, nonnegative: bool) -> None:
    if positive and not value > 0:
        raise UserError(f"{where}: key '{key}' must be > 0, got {value:g}")
    if nonnegative and not value >= 0:
        raise UserError(f"{where}: key '{key}' must be >= 0, got {value:g}")
