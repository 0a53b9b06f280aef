"""A campaign's tasks: every grid combination times every Monte-Carlo draw, each with a stable id and seed.

The id and the seed of a task are hashes of the campaign seed and the task's parameters (canonical JSON), so
they do not depend on scheduling, on the order of the grid, or on how many workers run. Draw k of the
`random:` parameters comes from a generator seeded with (campaign seed, k): every grid point flies the same
draws (common random numbers), so controllers are compared on the same vehicles and winds.
"""

from __future__ import annotations

import hashlib
import itertools
import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from quadsr.campaign.spec import CampaignSpec, Distribution

SIGNIFICANT = 12  # digits a drawn number keeps: the canonical form must not depend on float printing


@dataclass(frozen=True)
class Task:
    """One flight (or learn-then-fly) of the campaign: its parameters, sample index, id and seed."""

    task_id: str
    seed: int
    sample: int
    params: dict[str, Any]


def _round(value: Any) -> Any:
    if isinstance(value, float):
        return float(f"{value:.{SIGNIFICANT}g}") if math.isfinite(value) else value
    if isinstance(value, tuple):
        return tuple(_round(v) for v in value)
    return value


def canonical(params: dict[str, Any]) -> str:
    """The parameters as canonical JSON (sorted keys, rounded numbers): what ids and seeds hash."""
    rounded = {k: _round(v) for k, v in sorted(params.items())}
    return json.dumps(rounded, sort_keys=True, separators=(",", ":"))


def _digest(*parts: Any) -> bytes:
    return hashlib.sha256("\x1f".join(str(p) for p in parts).encode()).digest()


def task_seed(campaign_seed: int, params: dict[str, Any]) -> int:
    """A task's seed (0 .. 2^31-1) from the campaign seed and its parameters only."""
    return int.from_bytes(_digest("seed", campaign_seed, canonical(params))[:4], "big") & 0x7FFFFFFF


def task_id(campaign_seed: int, params: dict[str, Any]) -> str:
    """A task's id (16 hex digits) from the campaign seed and its parameters only."""
    return _digest("task", campaign_seed, canonical(params)).hex()[:16]


def draw(dist: Distribution, rng: np.random.Generator, nominal: Any) -> Any:
    """One value of a distribution (scale multiplies the vehicle file's nominal value or list)."""
    if dist.kind == "choice":
        return dist.args[int(rng.integers(len(dist.args)))]
    a, b = dist.args
    if dist.kind == "uniform":
        return float(rng.uniform(a, b))
    if dist.kind == "normal":
        return float(rng.normal(a, b))
    if dist.kind == "log_uniform":
        return float(math.exp(rng.uniform(math.log(a), math.log(b))))
    scale = float(rng.uniform(a, b))  # scale
    if isinstance(nominal, (list, tuple)):
        return tuple(float(v) * scale for v in nominal)
    return float(nominal) * scale


def sample_draws(spec: CampaignSpec, nominal: dict[str, Any]) -> list[dict[str, Any]]:
    """The `samples` draws of the random parameters (names drawn in sorted order from rng(seed, k))."""
    draws = []
    for k in range(spec.samples):
        rng = np.random.default_rng([spec.seed, k])
        draws.append({name: _round(draw(spec.random[name], rng, nominal.get(name)))
                      for name in sorted(spec.random)})
    return draws


def expand(spec: CampaignSpec, nominal: dict[str, Any]) -> list[Task]:
    """Every task of the campaign, in a stable order (grid order, then sample index)."""
    defaults = spec.defaults()
    names = list(spec.grid)
    draws = sample_draws(spec, nominal)
    tasks = []
    seen: set[str] = set()
    for combo in itertools.product(*(spec.grid[n] for n in names)):
        for k, drawn in enumerate(draws):
            params = {**defaults, **spec.fixed, **dict(zip(names, combo, strict=True)), **drawn}
            if spec.samples > 1:
                params["sample"] = k  # two equal draws stay two tasks
            tid = task_id(spec.seed, params)
            if tid in seen:
                continue
            seen.add(tid)
            tasks.append(Task(tid, task_seed(spec.seed, params), k, params))
    return tasks
