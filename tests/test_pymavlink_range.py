"""bridge/framing.py uses pymavlink internals: the installed pymavlink is in the pinned range and agrees."""

from __future__ import annotations

import re
from importlib.metadata import version
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def _version(text: str) -> tuple[int, ...]:
    return tuple(int(p) for p in text.split("."))


def test_installed_pymavlink_is_in_the_pinned_range_and_passes_the_self_check():
    from bridge.framing import self_check

    pin = re.search(r'"pymavlink>=([\d.]+),<([\d.]+)"', (REPO / "pyproject.toml").read_text()).groups()
    installed = _version(version("pymavlink"))
    assert _version(pin[0]) <= installed < _version(pin[1]), (installed, pin)
    assert self_check() == []


def test_self_check_sees_a_frame_that_differs(monkeypatch):
    """The check can fail: a packer that drops the last payload byte is caught for every message with one."""
    import bridge.framing as framing

    real = framing.pack_frame
    monkeypatch.setattr(framing, "pack_frame", lambda *a, **k: real(*a, **k)[:-3] + real(*a, **k)[-2:])
    problems = framing.self_check()
    assert len(problems) > 100 and all("differs" in p for p in problems)
