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

Where the blocks go. By default the tail of each flight validates (the flight's future: the hardest
honest test) and the piece before it picks. But a short flight's tail can be a steady glide in which a
target barely varies (the 10 s PX4 take-off log ends in a steady descent: z'' spread 0.03 m/s^2), and R^2
there measures noise, not the model. So each role's spread is checked, per target, against the flight's:
the spread ratio is the standard deviation of the target (winsorised at the flight's 1st and 99th
percentiles, so one spike does not count as variation) in the role's rows over that in all the flight's
rows. When the default layout's pick or validate block spreads some target less than MIN_SPREAD_RATIO,
the pick and validate blocks (same lengths) are moved to the positions on a grid that maximise the
smallest ratio over all roles (the fit rows included, so that they keep variation to learn from) and
targets, if that reaches MIN_SPREAD_RATIO (else the tail stays, with a note: a flight whose
targets vary only in a short part, such as a take-off transient, has no good place to validate); the fit
rows are then the rest of the flight, which may come in two or three pieces, each still gap_s away from
the held-out blocks. The placement looks only at the targets, never at a model, so it cannot favour one;
the model file records it per flight (`data.layout`).

Each block is recorded for the model file: the flight's file and sha256, the first and last time of its
rows (s, the log's own clock) and its row count; a role holding several pieces of one flight has one block
per piece.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import numpy as np

from bridge.errors import UserError
from identification.dataset import Dataset
from identification.targets import SensorTargetSettings

DEFAULT_GAP_S = SensorTargetSettings().max_window_s  # s: no differentiator window is longer
ROLES = ("fit", "pick", "validate")
MIN_ROWS = 20  # fewer rows in a role is an error
MIN_SPREAD_RATIO = 0.5  # the tail layout stays when its held-out blocks spread each target at least this
GRID_POSITIONS = 60  # candidate start times per moved block


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


@dataclass(frozen=True)
class Layout:
    """How one flight's blocks were placed: kind 'tail' (fit | pick | validate in time) or 'spread' (moved
    where the targets vary); the smallest spread ratio over the targets of the layout used (over all roles
    when moved, else the tail's held-out blocks) and of the tail layout's held-out blocks; a line saying
    so."""

    file: str
    kind: str
    min_spread_ratio: float
    tail_min_spread_ratio: float
    note: str

    def as_dict(self) -> dict:
        """Plain mapping for the model file."""
        return {
            "file": self.file,
            "placement": self.kind,
            "min_spread_ratio": round(self.min_spread_ratio, 4),
            "tail_min_spread_ratio": round(self.tail_min_spread_ratio, 4),
        }


@dataclass
class DataRoles:
    """The three row sets and the blocks they came from; gap_s the time left out between blocks; layouts:
    per flight cut into blocks, how they were placed."""

    fit: Dataset
    pick: Dataset
    validate: Dataset
    blocks: list[Block]
    gap_s: float
    unused_rows: int
    layouts: list[Layout] = field(default_factory=list)

    def as_dict(self) -> dict:
        """The model file's `data` section: per role its blocks, the gap, the rows used by none and how each
        flight's blocks were placed."""
        out: dict = {"gap_s": self.gap_s, "unused_rows_in_gaps": self.unused_rows}
        for role in ROLES:
            out[role] = [b.as_dict() for b in self.blocks if b.role == role]
        out["layout"] = [lay.as_dict() for lay in self.layouts]
        return out

    def notes(self) -> list[str]:
        """A line per flight whose held-out blocks were moved from the tail, or whose tail barely varies
        anyway (to print)."""
        return [lay.note for lay in self.layouts if lay.note]


def _runs(role: str, data: Dataset, mask: np.ndarray) -> list[Block]:
    """A Block per run of consecutive rows (in time) of each flight that the mask holds."""
    out = []
    for i, f in enumerate(data.flights):
        rows = np.flatnonzero(data.flight == i)
        rows = rows[np.argsort(data.t[rows], kind="stable")]
        held = mask[rows]
        edges = np.flatnonzero(np.diff(np.concatenate(([0], held.astype(np.int8), [0]))))
        for a, b in zip(edges[::2], edges[1::2], strict=True):
            t = data.t[rows[a:b]]
            out.append(Block(role, f.file, f.sha256, float(t[0]), float(t[-1]), int(b - a)))
    return out


def _whole(role: str, data: Dataset) -> list[Block]:
    """A Block per flight of a dataset given whole to a role."""
    return _runs(role, data, np.ones(len(data), dtype=bool))


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


def _standardised(y: np.ndarray) -> np.ndarray:
    """Targets (N,k) winsorised at their 1st and 99th percentiles, centred and scaled to unit spread
    (non-finite values and constant columns give 0)."""
    y = np.asarray(y, dtype=float)
    out = np.zeros_like(y)
    for j in range(y.shape[1]):
        col = y[:, j]
        ok = np.isfinite(col)
        if ok.sum() < 2:
            continue
        lo, hi = np.percentile(col[ok], (1.0, 99.0))
        c = np.clip(np.where(ok, col, np.median(col[ok])), lo, hi)
        sd = float(c.std())
        if sd > 0:
            out[:, j] = (c - c.mean()) / sd
    return out


class _Spread:
    """Spread ratios of row sets of one flight from prefix sums (rows sorted by time t, s)."""

    def __init__(self, t: np.ndarray, y: np.ndarray):
        self.t = t
        z = _standardised(y)
        self.live = np.flatnonzero(z.std(axis=0) > 0)  # targets that vary at all in this flight
        z = z[:, self.live]
        self.s1 = np.vstack((np.zeros(z.shape[1]), np.cumsum(z, axis=0)))
        self.s2 = np.vstack((np.zeros(z.shape[1]), np.cumsum(z * z, axis=0)))

    def _index(self, a: float, b: float) -> tuple[int, int]:
        """Row range [i, j) of the times in [a, b] (s)."""
        return int(np.searchsorted(self.t, a, "left")), int(np.searchsorted(self.t, b, "right"))

    def ratio(self, n: int, s1: np.ndarray, s2: np.ndarray) -> float:
        """Smallest standard-deviation ratio over the targets of a set of n rows with sums s1, s2."""
        if not len(self.live):
            return 1.0
        if n < 2:
            return 0.0
        var = s2 / n - (s1 / n) ** 2
        return float(np.sqrt(max(float(var.min()), 0.0)))

    def layout_ratio(self, held: list[tuple[float, float]], gap: float) -> float:
        """Smallest ratio over the held-out blocks [a, b] (s) and the fit rows (more than gap from each)."""
        removed = sorted((a - gap, b + gap) for a, b in held)
        merged: list[list[float]] = []
        for a, b in removed:
            if merged and a <= merged[-1][1]:
                merged[-1][1] = max(merged[-1][1], b)
            else:
                merged.append([a, b])
        n_fit, f1, f2 = len(self.t), self.s1[-1].copy(), self.s2[-1].copy()
        for a, b in merged:  # fit: rows at least gap away (strictly) from every held-out block
            i, j = self._index(a, b)
            n_fit -= j - i
            f1 -= self.s1[j] - self.s1[i]
            f2 -= self.s2[j] - self.s2[i]
        worst = self.ratio(n_fit, f1, f2)
        for a, b in held:
            i, j = self._index(a, b)
            worst = min(worst, self.ratio(j - i, self.s1[j] - self.s1[i], self.s2[j] - self.s2[i]))
        return worst


def _spread_layout(
    spread: _Spread, held_fractions: dict[str, float], usable: float, gap: float
) -> tuple[dict[str, tuple[float, float]], float]:
    """The held-out blocks' (start, end) times (s) that maximise the smallest spread ratio (module
    docstring), searched on a grid; ties go to the latest validate, then pick, position."""
    t0, t1 = float(spread.t[0]), float(spread.t[-1])
    durations = {r: f * usable for r, f in held_fractions.items()}
    grids = {r: np.linspace(t1 - d, t0, GRID_POSITIONS) for r, d in durations.items()}  # latest first
    names = [r for r in ("validate", "pick") if r in durations]
    best: tuple[float, dict[str, tuple[float, float]]] = (-np.inf, {})
    first = names[0]
    for a in grids[first]:
        blocks = {first: (float(a), float(a + durations[first]))}
        if len(names) == 1:
            score = spread.layout_ratio(list(blocks.values()), gap)
            if score > best[0]:
                best = (score, dict(blocks))
            continue
        second = names[1]
        for b in grids[second]:
            end = b + durations[second]
            if not (end + gap <= a or b >= a + durations[first] + gap):
                continue
            both = {**blocks, second: (float(b), float(end))}
            score = spread.layout_ratio(list(both.values()), gap)
            if score > best[0]:
                best = (score, both)
    return best[1], best[0]


def interleaved_masks(
    t: np.ndarray, fractions: dict[str, float], gap: float, blocks: int
) -> dict[str, np.ndarray]:
    """Role masks over times t (s) with the pick rows in `blocks` equal blocks spread over the flight, each
    in the middle of its share of the time before the validation block (if any, at the tail), gap (s) on
    both sides of every held-out block: fit | gap | pick | gap | fit | ... | gap | validate."""
    t = np.asarray(t, dtype=float)
    t0, t1 = float(t.min()), float(t.max())
    has_validate = "validate" in fractions
    usable = max((t1 - t0) - gap * (2 * blocks + (1 if has_validate else 0)), 0.0)
    pick_len = fractions["pick"] * usable / blocks
    end = t1 - fractions["validate"] * usable - gap if has_validate else t1
    masks = {"validate": t > end + gap * (1 - 1e-9)} if has_validate else {}
    region = (end - t0) / blocks
    pick = np.zeros(len(t), dtype=bool)
    near = np.zeros(len(t), dtype=bool)
    for k in range(blocks):
        mid = t0 + (k + 0.5) * region
        a, b = mid - 0.5 * pick_len, mid + 0.5 * pick_len
        pick |= (t >= a) & (t <= b)
        near |= (t >= a - gap) & (t <= b + gap)
    masks["pick"] = pick
    masks["fit"] = ~near & (t <= end)
    return masks


def _flight_masks(
    t: np.ndarray, y: np.ndarray, fractions: dict[str, float], gap: float, file: str, pick_blocks: int = 1
) -> tuple[dict[str, np.ndarray], Layout | None]:
    """Role masks over one flight's rows (sorted by time t, s; targets y) and how they were placed."""
    roles = [r for r in ROLES if r in fractions]
    tail = dict(zip(roles, time_block_masks(t, tuple(fractions[r] for r in roles), gap), strict=True))
    held = {r: fractions[r] for r in roles if r != "fit"}
    if not held or len(t) < 2:
        return tail, None
    spread = _Spread(t, y)
    if pick_blocks > 1 and "pick" in held:
        masks = interleaved_masks(t, fractions, gap, pick_blocks)
        ratio = min(_mask_ratio(spread, masks[r]) for r in held)
        if ratio >= MIN_SPREAD_RATIO:
            return masks, Layout(file, "interleaved", ratio, ratio, "")
        masks, layout = _one_pick_block(t, tail, held, gap, file, spread)
        return masks, dataclasses.replace(layout, note=(
            f"note: {file}: {pick_blocks} pick blocks spread over the flight would hold a target that barely "
            f"varies (smallest spread {ratio:.2f} < {MIN_SPREAD_RATIO:g}): one pick block ({layout.kind} "
            "layout) instead" + (f"; {layout.note[len('note: '):]}" if layout.note else "")))
    return _one_pick_block(t, tail, held, gap, file, spread)


def _one_pick_block(
    t: np.ndarray, tail: dict[str, np.ndarray], held: dict[str, float], gap: float, file: str, spread: _Spread
) -> tuple[dict[str, np.ndarray], Layout]:
    """The tail layout's masks, or the held-out blocks moved where every target varies (module docstring),
    and how they were placed; held: the held-out roles' fractions, spread: the flight's spread sums."""
    tail_ratio = min(_mask_ratio(spread, tail[r]) for r in held)  # the held-out blocks of the tail layout
    if tail_ratio >= MIN_SPREAD_RATIO:
        return tail, Layout(file, "tail", tail_ratio, tail_ratio, "")
    usable = float(t[-1] - t[0]) - gap * len(held)  # the fit block and each held-out one, a gap between
    blocks, ratio = _spread_layout(spread, held, usable, gap)
    if not blocks or ratio < MIN_SPREAD_RATIO:
        note = (
            f"note: {file}: a target barely varies at the end of the flight (smallest spread of a target "
            f"in a held-out block, against the whole flight's: {tail_ratio:.2f} < {MIN_SPREAD_RATIO:g}) and "
            f"no placement of the held-out blocks does well enough (best {max(ratio, tail_ratio):.2f}): kept "
            "the tail; the validation R^2 of a target that barely varies there says little"
        )
        return tail, Layout(file, "tail", tail_ratio, tail_ratio, note)
    masks = {r: (t >= a) & (t <= b) for r, (a, b) in blocks.items()}
    near = np.zeros(len(t), dtype=bool)
    for a, b in blocks.values():
        near |= (t >= a - gap) & (t <= b + gap)
    masks["fit"] = ~near
    where = ", ".join(f"{r} {a:.2f}-{b:.2f} s" for r, (a, b) in sorted(blocks.items()))
    note = (
        f"note: {file}: a target barely varies at the end of the flight (smallest spread of a target in a "
        f"held-out block, against the whole flight's: {tail_ratio:.2f} < {MIN_SPREAD_RATIO:g}), so the "
        f"held-out blocks go where every target varies: {where}, fit on the rest {gap:g} s apart "
        f"(smallest spread {ratio:.2f})"
    )
    return masks, Layout(file, "spread", ratio, tail_ratio, note)


def _mask_ratio(spread: _Spread, mask: np.ndarray) -> float:
    """Smallest spread ratio over the targets of the rows a mask holds."""
    z1 = np.diff(spread.s1, axis=0)[mask]
    z2 = np.diff(spread.s2, axis=0)[mask]
    return spread.ratio(int(mask.sum()), z1.sum(axis=0), z2.sum(axis=0))


def assign_roles(
    data: Dataset,
    *,
    pick: Dataset | None = None,
    validate: Dataset | None = None,
    pick_fraction: float = 0.2,
    validate_fraction: float = 0.2,
    gap_s: float = DEFAULT_GAP_S,
    pick_blocks: int = 1,
) -> DataRoles:
    """Split `data` into fit / pick / validate (module docstring); pick or validate flights replace the
    in-flight blocks of that role; pick_blocks > 1 spreads the pick rows over each flight in that many
    blocks (interleaved_masks). UserError when a role gets fewer than MIN_ROWS rows."""
    if not (gap_s >= 0 and np.isfinite(gap_s)):
        raise UserError(f"the gap between fit, pick and validation blocks must be >= 0 s, got {gap_s}")
    if isinstance(pick_blocks, bool) or int(pick_blocks) != pick_blocks or pick_blocks < 1:
        raise UserError(f"the number of pick blocks must be a whole number >= 1, got {pick_blocks}",
                        hint="1: one pick block before the validation block (the default)")
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
    layouts = []
    for i, f in enumerate(data.flights):
        rows = np.flatnonzero(data.flight == i)
        rows = rows[np.argsort(data.t[rows], kind="stable")]
        flight_masks, layout = _flight_masks(data.t[rows], data.targets[rows], fractions, gap_s, f.file,
                                             int(pick_blocks))
        for r, m in flight_masks.items():
            masks[r][rows[m]] = True
        if layout is not None:
            layouts.append(layout)
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
    blocks = [
        b
        for role in ROLES
        for b in (_runs(role, data, masks[role]) if role in fractions else _whole(role, sets[role]))
    ]
    used = sum(int(m.sum()) for m in masks.values())
    return DataRoles(sets["fit"], sets["pick"], sets["validate"], blocks, gap_s, len(data) - used, layouts)
