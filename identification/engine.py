"""The engine registry: an engine by name, and the held-out split every engine shares.

The interface types are in identification.candidate, the settings in identification.engine_settings; the
engines import those, never this module, so there is no import cycle. Engines:
- default / discovery: features grown from body-frame primitives, screened, sparsified, genetic programming on
  the residual (identification.discovery); learns in the body frame, NED accelerations composed exactly
- sparse: STLSQ over the hand-written physics library (identification.sparse), NED targets
- operon: pyoperon genetic programming alone, NED targets
- pysr: PySR (Julia), NED targets

Every engine fits one target: `fit(X, y, target, budget, seed, loss, progress, holdout) -> list[Candidate]`.
budget is an iteration count (genetic-programming generations; PySR iterations), never seconds, so a seed
gives the same candidates on any machine; the sparse regressions always run to completion (their work is
fixed by their settings).
"""

from __future__ import annotations

import numpy as np

from bridge.errors import UserError
from identification.candidate import Candidate, Engine, Progress, make_candidate
from identification.engine_settings import (
    DiscoverySettings,
    EngineSettings,
    OperonSettings,
    PysrSettings,
    SelectionSettings,
    SparseSettings,
    load_engine_settings,
)

__all__ = [
    "ENGINE_HELP",
    "ENGINE_NAMES",
    "Candidate",
    "DiscoverySettings",
    "Engine",
    "EngineSettings",
    "OperonSettings",
    "Progress",
    "PysrSettings",
    "SelectionSettings",
    "SparseSettings",
    "load_engine_settings",
    "make_candidate",
    "make_engine",
    "split_holdout",
]

ENGINE_NAMES: tuple[str, ...] = ("default", "discovery", "sparse", "operon", "pysr")
# what each engine is, in one line (quadsr identify --engine's help), beside the names it describes
ENGINE_HELP = ("default (= discovery): body-frame features grown from primitives, screened and sparsified, "
               "pyoperon on the residual; sparse: STLSQ over a library of the paper's terms "
               "(NED, no discovery); operon: pyoperon alone; pysr: PySR (needs Julia)")


def make_engine(name: str, settings: EngineSettings | None = None) -> Engine:
    """The engine of that name ('default' is 'discovery'; 'sparse', 'operon', 'pysr')."""
    settings = settings or EngineSettings()
    if name in ("default", "discovery"):
        from identification.discovery import DiscoveryEngine

        return DiscoveryEngine(settings.discovery, settings.sparse, name=name, selection=settings.selection)
    if name == "sparse":
        from identification.sparse import SparseEngine

        return SparseEngine(settings.sparse)
    if name == "operon":
        from identification.operon_engine import OperonEngine

        return OperonEngine(settings.operon)
    if name == "pysr":
        from identification.pysr_engine import PysrEngine

        return PysrEngine(settings.pysr)
    raise UserError(f"unknown engine {name!r}", hint=f"choose one of {', '.join(ENGINE_NAMES)}")


def split_holdout(
    X: np.ndarray, y: np.ndarray, fraction: float = 0.2
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Train on the first rows, hold out the last `fraction` (contiguous in time)."""
    n = len(y)
    cut = int(round(n * (1.0 - fraction)))
    cut = min(max(cut, 1), n - 1) if n > 1 else n
    return X[:cut], y[:cut], X[cut:], y[cut:]
