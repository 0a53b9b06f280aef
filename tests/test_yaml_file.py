"""bridge.yaml_file: the one reader of settings files (one parse, one error style, typed dataclasses)."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from bridge.errors import UserError
from bridge.yaml_file import Section, load_yaml_file, read_dataclass

REPO = Path(__file__).resolve().parent.parent


@dataclass(frozen=True)
class _Inner:
    rate: float = 1.0
    on: bool = True


@dataclass(frozen=True)
class _Outer:
    count: int = 3
    names: tuple[str, ...] = ("a",)
    label: str = "x"
    inner: _Inner = field(default_factory=_Inner)


def test_section_names_file_and_dotted_key_in_every_mistake():
    top = Section("demo file d.yaml", {"m": {"k": -1, "v": [1, 2], "s": "pi/4", "extra": 0}},
                  hint="see the example")
    m = top.section("m")
    with pytest.raises(UserError, match=r"^demo file d\.yaml: key 'm\.k' must be > 0, got -1"):
        m.number("k", positive=True)
    with pytest.raises(UserError, match=r"key 'm\.v' must be a list of 3 numbers"):
        m.vec3("v")
    assert math.isclose(m.number("s"), math.pi / 4)  # angles in rad as 'pi/4'
    with pytest.raises(UserError, match=r"key 'm\.gone' is missing") as err:
        m.number("gone")
    assert err.value.hint == "see the example"  # the file's hint, after a missing key
    with pytest.raises(UserError, match=r"unknown key 'm\.extra'") as err:
        m.done()
    assert "k, s, v" in err.value.hint and "gone" in err.value.hint
    with pytest.raises(UserError, match=r"key 'm\.v' must be \[low, high\] with low <= high"):
        Section("f", {"v": [3, 1]}, "m").range("v")


def test_read_dataclass_reads_each_field_by_its_type_and_refuses_the_rest():
    got = read_dataclass(Section("f", {"count": 5, "names": "b, c", "inner": {"rate": "1e-3"}}), _Outer)
    assert got == _Outer(count=5, names=("b", "c"), inner=_Inner(rate=1e-3))
    for data, words in (({"count": 1.5}, "key 'count' must be an integer"),
                        ({"inner": {"rate": -1}}, "key 'inner.rate' must be >= 0"),
                        ({"inner": {"on": "yes"}}, "key 'inner.on' must be true or false"),
                        ({"inner": {"rat": 1}}, "unknown key 'inner.rat'"),
                        ({"names": [1]}, "key 'names' must be a list of strings")):
        with pytest.raises(UserError) as err:
            read_dataclass(Section("f", data), _Outer)
        assert words in str(err.value), str(err.value)
    with pytest.raises(UserError, match="unknown gain 'cnt'"):
        read_dataclass(Section("g", {"cnt": 1}, noun="gain"), _Outer)
    with pytest.raises(UserError, match=r"key 'inner\.rate' must be > 0"):
        read_dataclass(Section("f", {"inner": {"rate": 0}}), _Outer, positive=True)


def test_load_yaml_file_names_the_line_of_a_syntax_error(tmp_path):
    bad = tmp_path / "bad.yaml"
    bad.write_text("a: [1, 2\n")
    with pytest.raises(UserError, match=r"^my file: YAML syntax error at line \d+, column \d+"):
        load_yaml_file(bad, "my file")
    with pytest.raises(UserError, match="my file: cannot read it"):
        load_yaml_file(tmp_path, "my file")


def test_no_other_module_parses_yaml_itself():
    """Every settings file goes through bridge.yaml_file: no yaml.safe_load / yaml.load elsewhere."""
    parse = re.compile(r"\byaml\.(safe_load|load|full_load|unsafe_load)\(")
    offenders = []
    for path in REPO.rglob("*.py"):
        rel = path.relative_to(REPO)
        # build/, dist/: copies a non-editable `pip install .` leaves behind (ignored by git)
        if (rel.parts[0] in ("tests", ".git", "build", "dist") or rel == Path("bridge/yaml_file.py")
                or "venv" in rel.parts[0]):
            continue
        if parse.search(path.read_text(encoding="utf-8")):
            offenders.append(str(rel))
    assert offenders == [], f"parse YAML with bridge.yaml_file.load_yaml_file instead: {offenders}"
