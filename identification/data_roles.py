"""Which rows fit a model, which pick it, which validate it: blocks separated by gaps, with provenance.

Honest selection: the engine fits on `fit` rows only; the pick among its candidates (identification.pareto)
uses `pick` rows only; the reported validation uses `validate` rows only, never seen by either. Each role
comes from whole flights (`quadsr identify --pick-log/--validate-log`) or, inside each flight given for
fitting, from time blocks in this order:

    fit | gap | pick | gap | validate

A target at time t is computed from samples up to half a differentiator window away (identification.targets),
and the states are correlated over a few motor time constants, so blocks touching each other would share
information; a gap of at least the longest filter/differentiator window (DEFAULT_GAP_S: the longest
Savitzky-Golay window any reader may choose, 0.4 s) keeps them apart. Rows inside a gap are used by nobody.

Each block is recorded for the model file: the flight's file and sha256, the first and last time of its
rows (s, the log's own clock) and its row count.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from bridge.errors import UserError
from identification.dataset import Dataset
from identification.targets import SensorTargetSettings

DEFAULT_GAP_S = SensorTargetSettings().max_window_s  # s: no differentiator window is longer
ROLES = ("fit", "pick", "validate")
MIN_ROWS = 20  # fewer rows in a role is an error


@dataclass(frozen=True)
class Block:
    """Rows of one flight given one role: file, sha256, first and last row time (s), row count."""

    role: str
    file: str
    sha256: str
    t_start: float
    t_end: float
    rows: int

    def as_dict(self) -> dict:
        """Plain mapping for the model file."""
        return {
            "file": self.file,
            "sha256": self.sha256,
            "t_start_s": round(self.t_start, 6),
            "t_end_s": round(self.t_end, 6),
            "rows": self.rows,
        }


@dataclass
class DataRoles:
    """The three row sets and the blocks they came from; gap_s the time left out between blocks."""

    fit: Dataset
    pick: Dataset
    validate: Dataset
    blocks: list[Block]
    gap_s: float
    unused_rows: int

    def as_dict(self) -> dict:
        """The model file's `data` section: per role its blocks, plus the gap and the rows used by none."""
        out: dict = {"gap_s": self.gap_s, "unused_rows_in_gaps": self.unused_rows}
        for role in ROLES:
            out[role] = [b.as_dict() for b in self.blocks if b.role == role]
        return out


def _blocks(role: str, data: Dataset) -> list[Block]:
    out = []
    for i, f in enumerate(data.flights):
        t = data.t[data.flight == i]
        if len(t):
            out.append(Block(role, f.file, f.sha256, float(t.min()), float(t.max()), int(len(t))))
    return out


def time_block_masks(
    t: np.ndarray, fractions: tuple[float, ...], gap_s: float
) -> list[np.ndarray]:
    """Boolean masks over times t (s) for consecutive blocks of the given fractions of the usable time,
    each separated from the next by gap_s (s) that no block holds. Fractions sum to 1."""
    t = np.asarray(t, dtype=float)
    if len(t) == 0:
        return [np.zeros(0, dtype=bool) for _ in fractions]
    t0, t1 = float(t.min()), float(t.max())
    usable = (t1 - t0) - gap_s * (len(fractions) - 1)
    masks = []
    start = t0
    for k, frac in enumerate(fractions):
        end = start + frac * max(usable, 0.0)
        last = k == len(fractions) - 1
        masks.append((t >= start) & ((t <= t1) if last else (t < end)))
        start = end + gap_s
    return masks


def assign_roles(
    data: Dataset,
    *,
    pick: Dataset | None = None,
    validate: Dataset | None = None,
    pick_fraction: float = 0.2,
    validate_fraction: float = 0.2,
    gap_s: float = DEFAULT_GAP_S,
) -> DataRoles:
    """Split `data` into fit / pick / validate (module docstring); pick or validate flights replace the
    in-flight blocks of that role. UserError when a role gets fewer than MIN_ROWS rows."""
    if not (gap_s >= 0 and np.isfinite(gap_s)):
        raise UserError(f"the gap between fit, pick and validation blocks must be >= 0 s, got {gap_s}")
    fractions = {"fit": 1.0}
    for role, given, frac in (("pick", pick, pick_fraction), ("validate", validate, validate_fraction)):
        if given is None:
            if not (0.0 < frac < 1.0):
                raise UserError(f"the {role} fraction must be between 0 and 1, got {frac}")
            fractions[role] = frac
            fractions["fit"] -= frac
    if fractions["fit"] <= 0.0:
        raise UserError(
            f"pick ({pick_fraction}) and validation ({validate_fraction}) fractions leave nothing to fit on",
            hint="their sum must be below 1",
        )
    roles = [r for r in ROLES if r in fractions]
    masks = {r: np.zeros(len(data), dtype=bool) for r in roles}
    for i in range(len(data.flights)):
        rows = np.flatnonzero(data.flight == i)
        blocks = time_block_masks(data.t[rows], tuple(fractions[r] for r in roles), gap_s)
        for r, m in zip(roles, blocks, strict=True):
            masks[r][rows[m]] = True
    sets = {r: data.select(masks[r]) for r in roles}
    if pick is not None:
        sets["pick"] = pick
    if validate is not None:
        sets["validate"] = validate
    for role in ROLES:
        n = len(sets[role])
        if n < MIN_ROWS:
            where = "its own log(s)" if role not in fractions else f"{fractions[role]:.0%} of each flight"
            raise UserError(
                f"only {n} rows to {role} on ({where}, {gap_s:g} s gaps between blocks)",
                hint="fly longer, give more logs, or pass --pick-log/--validate-log flights",
            )
    fit_files = {f.sha256 for f in sets["fit"].flights if f.rows and f.sha256}
    for role, given in (("pick", pick), ("validate", validate)):
        shared = [f.file for f in (given.flights if given is not None else []) if f.sha256 in fit_files]
        if shared:
            raise UserError(
                f"{shared[0]} is given both to fit and to {role}",
                hint=f"a {role} log must be a different flight from the logs the model is fitted on",
            )
    blocks = [b for role in ROLES for b in _blocks(role, sets[role])]
    used = sum(int(m.sum()) for m in masks.values())
    return DataRoles(sets["fit"], sets["pick"], sets["validate"], blocks, gap_s, len(data) - used)
