"""The flight table: time, the 12 states, the 4 rotor speeds and the 6 targets per row, with provenance.

Columns (units and frames as docs/design.md):
  t (s, log time); xi = x y z (NED m), vx vy vz (NED m/s), phi theta psi (ZYX rad), wx wy wz (FRD rad/s);
  u = u1..u4 rotor speeds (rad/s, PX4 Quad-X order: front-right CCW, rear-left CCW, front-left CW,
  rear-right CW); targets = ax ay az (NED m/s^2), dwx dwy dwz (FRD rad/s^2).
Optional per-row side columns (`aux`, used by segmentation and the motor model, never learned from):
  throttle (N,4) motor commands in [0, 1]; voltage (N,) battery V; landed (N,) the log's land detector
  (1 landed, 0 flying); armed (N,) the log's arming state (1 armed, 0 disarmed); accel_dev (N,) the
  largest | |specific force| - g | (m/s^2) around the row; ground_s (N,) the log time (s) from the row to
  the nearest log row where the vehicle rests on the ground (our .tlog: the SITL holds it on its ground
  plane; inf: it never rests), so that segmentation can drop the lift-off and touch-down; step_nodes
  (N,32) for rows that are steps' means (our .tlog's raw sensor targets): the state xi and rotor speeds u
  at the step's two Gauss nodes less the row's (identification.step_targets.step_node_offsets), which
  Dataset.at_step_nodes turns into two rows per step.
Readers (identification.readers.*) build these; identification.dataset loads them from files.
"""

from __future__ import annotations

import csv
import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from bridge.errors import UserError

STATE_NAMES = ("x", "y", "z", "vx", "vy", "vz", "phi", "theta", "psi", "wx", "wy", "wz")
INPUT_NAMES = ("u1", "u2", "u3", "u4")
TARGET_NAMES = ("ax", "ay", "az", "dwx", "dwy", "dwz")
FORMATS = ("tlog", "ulog", "dataflash", "table")
TARGET_SOURCES = ("truth", "sensors")
AUX_NAMES = ("throttle", "voltage", "landed", "armed", "accel_dev", "ground_s", "step_nodes")


@dataclass(frozen=True)
class FlightInfo:
    """Where one flight's rows came from: the file, its SHA-256, its format and how many rows it gave."""

    file: str
    sha256: str
    format: str
    rows: int
    target_source: str


@dataclass
class Dataset:
    """Rows of (t, xi, u, targets) from one or more flights; see the module docstring for units and frames.

    dropped_rows: rows of the log that did not make a row, total; drop_reasons: the count per reason.
    flight: (N,) index into `flights` per row (0 for a single flight).
    aux: optional side columns per row (see the module docstring), carried through select and concat.
    segments: what the flight segmentation kept and why (lines to print; identification.segmentation).
    gravity_estimates: (file, g, its standard error) m/s^2: the gravity each flight's truth accelerations
    and accelerometer agree on, where its log holds both (identification.log_gravity).
    u_from_throttle: u is not measured but made from aux `throttle` by a thrust curve (motor_model).
    target_noise: per target (6, in TARGET_NAMES' order), its raw noise as a filter of the sensor's white
    noise along consecutive rows (identification.weak_noise), where the reader states it; None: not stated.
    nodes: rows per step (at_step_nodes): consecutive rows with the same t are one step's Gauss nodes, each
    with the step's target, and the step's value of any quantity is their mean (1: a row is a sample).
    """

    t: np.ndarray
    xi: np.ndarray
    u: np.ndarray
    targets: np.ndarray
    source: str
    format: str
    target_source: str
    dropped_rows: int = 0
    drop_reasons: dict[str, int] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    sha256: str = ""
    flight: np.ndarray | None = None
    flights: list[FlightInfo] = field(default_factory=list)
    aux: dict[str, np.ndarray] = field(default_factory=dict)
    segments: list[str] = field(default_factory=list)
    u_from_throttle: bool = False
    gravity_estimates: list[tuple[str, float, float]] = field(default_factory=list)
    target_noise: tuple[tuple[float, ...] | None, ...] | None = None
    nodes: int = 1

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=float).reshape(-1)
        n = len(self.t)
        self.xi = np.asarray(self.xi, dtype=float).reshape(n, len(STATE_NAMES))
        self.u = np.asarray(self.u, dtype=float).reshape(n, len(INPUT_NAMES))
        self.targets = np.asarray(self.targets, dtype=float).reshape(n, len(TARGET_NAMES))
        self.flight = np.zeros(n, dtype=int) if self.flight is None else np.asarray(self.flight, dtype=int)
        if not self.flights:
            self.flights = [FlightInfo(self.source, self.sha256, self.format, n, self.target_source)]
        for k, v in self.aux.items():
            if k not in AUX_NAMES:
                raise ValueError(f"unknown aux column {k!r}; known: {', '.join(AUX_NAMES)}")
            v = np.asarray(v, dtype=float)
            if len(v) != n:
                raise ValueError(f"aux column {k!r} has {len(v)} rows, the table {n}")
            self.aux[k] = v

    def __len__(self) -> int:
        return len(self.t)

    @property
    def columns(self) -> tuple[str, ...]:
        """Column names of the table: t, the states, the inputs, the targets."""
        return ("t", *STATE_NAMES, *INPUT_NAMES, *TARGET_NAMES)

    def column(self, name: str) -> np.ndarray:
        """One column by name (t, a state, an input or a target)."""
        if name == "t":
            return self.t
        for names, data in ((STATE_NAMES, self.xi), (INPUT_NAMES, self.u), (TARGET_NAMES, self.targets)):
            if name in names:
                return data[:, names.index(name)]
        raise KeyError(f"no column {name!r}; columns: {', '.join(self.columns)}")

    def select(self, rows: np.ndarray | slice) -> Dataset:
        """A dataset of the given rows (boolean mask, indices or slice), same provenance."""
        flight = self.flight[rows]
        infos = [replace(f, rows=int(np.count_nonzero(flight == i))) for i, f in enumerate(self.flights)]
        return replace(
            self,
            t=self.t[rows],
            xi=self.xi[rows],
            u=self.u[rows],
            targets=self.targets[rows],
            flight=flight,
            flights=infos,
            drop_reasons=dict(self.drop_reasons),
            warnings=list(self.warnings),
            aux={k: v[rows] for k, v in self.aux.items()},
            segments=list(self.segments),
        )

    @staticmethod
    def concat(datasets: Sequence[Dataset]) -> Dataset:
        """All rows of several datasets (flights kept apart by `flight`); drops and warnings summed."""
        if not datasets:
            raise ValueError("Dataset.concat needs at least one dataset")
        flights: list[FlightInfo] = []
        flight_ids = []
        reasons: dict[str, int] = {}
        for d in datasets:
            flight_ids.append(d.flight + len(flights))
            flights.extend(d.flights)
            for k, v in d.drop_reasons.items():
                reasons[k] = reasons.get(k, 0) + v
        aux = {}
        for k in set().union(*(d.aux for d in datasets)):
            parts = []
            for d in datasets:
                if k in d.aux:
                    parts.append(d.aux[k])
                else:
                    width = next(e.aux[k] for e in datasets if k in e.aux).shape[1:]
                    parts.append(np.full((len(d), *width), np.nan))
            aux[k] = np.concatenate(parts)
        formats = {f.format for f in flights}
        sources = {f.target_source for f in flights}
        noise = {d.target_noise for d in datasets}
        return Dataset(
            t=np.concatenate([d.t for d in datasets]),
            xi=np.concatenate([d.xi for d in datasets]),
            u=np.concatenate([d.u for d in datasets]),
            targets=np.concatenate([d.targets for d in datasets]),
            source=", ".join(f.file for f in flights),
            format=formats.pop() if len(formats) == 1 else "mixed",
            target_source=sources.pop() if len(sources) == 1 else "mixed",
            dropped_rows=sum(d.dropped_rows for d in datasets),
            drop_reasons=reasons,
            warnings=[w for d in datasets for w in d.warnings],
            segments=[line for d in datasets for line in d.segments],
            u_from_throttle=all(d.u_from_throttle for d in datasets),
            gravity_estimates=[e for d in datasets for e in d.gravity_estimates],
            sha256=flights[0].sha256 if len(flights) == 1 else "",
            flight=np.concatenate(flight_ids),
            flights=flights,
            aux=aux,
            target_noise=noise.pop() if len(noise) == 1 else None,
            nodes=max(d.nodes for d in datasets),
        )

    def at_step_nodes(self) -> Dataset:
        """Each step row as its two Gauss-node rows (aux step_nodes: the node states less the row's), in order
        and with the step's t and targets; the dataset itself when it has no step_nodes."""
        if "step_nodes" not in self.aux:
            return self
        off = self.aux["step_nodes"].reshape(len(self), -1, 16)
        k = off.shape[1]
        finite = np.isfinite(off).all(axis=(1, 2))  # a flight concatenated without nodes: rows stay one
        rep = np.where(finite, k, 1)
        node = np.concatenate([np.arange(r) for r in rep]) if len(rep) else np.zeros(0, int)
        src = np.repeat(np.arange(len(self)), rep)
        dev = np.where(finite[src, None], off[src, np.minimum(node, k - 1)], 0.0)
        flight = self.flight[src]
        infos = [replace(f, rows=int(np.count_nonzero(flight == i))) for i, f in enumerate(self.flights)]
        return replace(
            self, t=self.t[src], xi=self.xi[src] + dev[:, :12], u=self.u[src] + dev[:, 12:],
            targets=self.targets[src], flight=flight, flights=infos,
            aux={n: v[src] for n, v in self.aux.items() if n != "step_nodes"},
            drop_reasons=dict(self.drop_reasons), warnings=list(self.warnings), segments=list(self.segments),
            nodes=k,
        )

    def split(self, holdout_fraction: float) -> tuple[Dataset, Dataset]:
        """(train, holdout): the last holdout_fraction of each flight's rows (in time) is held out; rows of
        one time (a step's node rows: at_step_nodes) stay on one side, the cut at the first such time (at the
        second time where that would be the flight's first)."""
        if not (0.0 < holdout_fraction < 1.0):
            raise UserError(f"holdout fraction must be between 0 and 1 (exclusive), got {holdout_fraction}")
        hold = np.zeros(len(self), dtype=bool)
        for i in range(len(self.flights)):
            idx = np.flatnonzero(self.flight == i)
            if len(idx) < 2:
                continue
            idx = idx[np.argsort(self.t[idx], kind="stable")]
            n_hold = min(max(int(round(holdout_fraction * len(idx))), 1), len(idx) - 1)
            t = self.t[idx]
            first = int(np.searchsorted(t, t[len(idx) - n_hold], side="left"))
            if first == 0:  # the cut at the flight's first time: its rows stay in train
                first = int(np.searchsorted(t, t[0], side="right"))
            hold[idx[first:]] = True
        return self.select(~hold), self.select(hold)

    def to_csv(self, path: str | Path) -> Path:
        """Write the table as CSV (header: flight, t, states, inputs, targets); returns the path."""
        p = Path(path)
        try:
            p.parent.mkdir(parents=True, exist_ok=True)
            with p.open("w", newline="", encoding="utf-8") as fh:
                w = csv.writer(fh)
                w.writerow(("flight", *self.columns))
                table = np.column_stack((self.t, self.xi, self.u, self.targets))
                for fid, row in zip(self.flight, table, strict=True):
                    w.writerow((int(fid), *(f"{v:.10g}" for v in row)))
        except OSError as exc:
            raise UserError(f"cannot write dataset CSV {p}: {exc.strerror}") from None
        return p

    def summary(self) -> str:
        """A few lines: rows, time span, every drop reason with its count (largest first), warnings."""
        span = f"{self.t.min():.3f}..{self.t.max():.3f} s" if len(self) else "empty"
        lines = [
            f"{self.source}: kept {len(self)} rows ({self.format}, targets from {self.target_source}), "
            f"t {span}"
        ]
        if self.dropped_rows:
            lines.append(f"  dropped {self.dropped_rows} rows:")
            for k, v in sorted(self.drop_reasons.items(), key=lambda kv: -kv[1]):
                lines.append(f"    {v:6d}  {k}")
        lines.extend(f"  warning: {w}" for w in self.warnings)
        return "\n".join(lines)


# --------------------------------------------------------------------------------------------------------


def file_sha256(path: str | Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for chunk in iter(lambda: fh.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()
