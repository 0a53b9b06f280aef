"""Test helper: a bench/ script imported as a module, once per test session."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

BENCH = Path(__file__).resolve().parent.parent / "bench"


def bench_module(script: str, name: str) -> ModuleType:
    """bench/<script> as module `name`, registered in sys.modules (a script's dataclasses look their module
    up there) and reused when a test imported it already."""
    if name in sys.modules:
        return sys.modules[name]
    spec = importlib.util.spec_from_file_location(name, BENCH / script)
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
