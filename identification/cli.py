"""Subcommands of the identification package: excite, identify, validate, model-from-vehicle."""

from __future__ import annotations

import argparse
import importlib

_MODULES = ("identification.cli_excite", "identification.cli_models")


def register(sub: argparse._SubParsersAction) -> None:
    """Add the identification subcommands that exist to the quadsr parser."""
    for name in _MODULES:
        try:
            module = importlib.import_module(name)
        except ModuleNotFoundError as exc:
            if exc.name == name:
                continue
            raise
        module.register(sub)
