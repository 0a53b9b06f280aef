"""One table per flight: time, the 12 states, the 4 rotor speeds and the 6 targets, from any supported log.

Columns (units and frames as docs/design.md):
  t (s); xi = x y z (NED m), vx vy vz (NED m/s), phi theta psi (ZYX rad), wx wy wz (FRD rad/s);
  u = u1..u4 true rotor speeds (rad/s, PX4 Quad-X order: front-right CCW, rear-left CCW, front-left CW,
  rear-right CW); targets = ax ay az (NED m/s^2), dwx dwy dwz (FRD rad/s^2).

`load_dataset(path)` reads our .tlog, a PX4 ULog (.ulg) or an ArduPilot DataFlash log (.bin), chosen by the
file's first bytes (the extension only breaks ties).
"""

from __future__ import annotations

import csv
import hashlib
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from bridge.errors import UserError

STATE_NAMES = ("x", "y", "z", "vx", "vy", "vz", "phi", "theta", "psi", "wx", "wy", "wz")
INPUT_NAMES = ("u1", "u2", "u3", "u4")
TARGET_NAMES = ("ax", "ay", "az", "dwx", "dwy", "dwz")
FORMATS = ("tlog", "ulog", "dataflash")
TARGET_SOURCES = ("truth", "sensors")

ULOG_MAGIC = b"ULog\x01\x12\x35"
DATAFLASH_MAGIC = b"\xa3\x95\x80"  # a FMT record: every DataFlash log starts with them


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

    def __post_init__(self) -> None:
        self.t = np.asarray(self.t, dtype=float).reshape(-1)
        n = len(self.t)
        self.xi = np.asarray(self.xi, dtype=float).reshape(n, len(STATE_NAMES))
        self.u = np.asarray(self.u, dtype=float).reshape(n, len(INPUT_NAMES))
        self.targets = np.asarray(self.targets, dtype=float).reshape(n, len(TARGET_NAMES))
        self.flight = np.zeros(n, dtype=int) if self.flight is None else np.asarray(self.flight, dtype=int)
        if not self.flights:
            self.flights = [FlightInfo(self.source, self.sha256, self.format, n, self.target_source)]

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
        formats = {f.format for f in flights}
        sources = {f.target_source for f in flights}
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
            sha256=flights[0].sha256 if len(flights) == 1 else "",
            flight=np.concatenate(flight_ids),
            flights=flights,
        )

    def split(self, holdout_fraction: float) -> tuple[Dataset, Dataset]:
        """(train, holdout): the last holdout_fraction of each flight's rows (in time) is held out."""
        if not (0.0 < holdout_fraction < 1.0):
            raise UserError(f"holdout fraction must be between 0 and 1 (exclusive), got {holdout_fraction}")
        hold = np.zeros(len(self), dtype=bool)
        for i in range(len(self.flights)):
            idx = np.flatnonzero(self.flight == i)
            if len(idx) < 2:
                continue
            idx = idx[np.argsort(self.t[idx], kind="stable")]
            n_hold = min(max(int(round(holdout_fraction * len(idx))), 1), len(idx) - 1)
            hold[idx[len(idx) - n_hold :]] = True
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
        """A few lines: rows, time span, drops with reasons, warnings."""
        span = f"{self.t.min():.3f}..{self.t.max():.3f} s" if len(self) else "empty"
        lines = [
            f"{self.source}: {len(self)} rows ({self.format}, targets from {self.target_source}), t {span}"
        ]
        if self.dropped_rows:
            why = ", ".join(f"{k}: {v}" for k, v in sorted(self.drop_reasons.items()))
            lines.append(f"  dropped {self.dropped_rows} rows ({why})")
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


def detect_format(path: str | Path) -> str:
    """'tlog', 'ulog' or 'dataflash' from the file's first bytes; UserError if none matches."""
    p = Path(path)
    if not p.exists():
        raise UserError(f"flight log {p} does not exist")
    if p.is_dir():
        raise UserError(f"flight log {p} is a directory, not a log file")
    try:
        with p.open("rb") as fh:
            head = fh.read(16)
    except OSError as exc:
        raise UserError(f"cannot read flight log {p}: {exc.strerror}") from None
    if not head:
        raise UserError(f"flight log {p} is empty", hint="was the flight recorded? is this the right file?")
    if head.startswith(ULOG_MAGIC[:4]):
        return "ulog"
    if head.startswith(DATAFLASH_MAGIC):
        return "dataflash"
    if len(head) > 8 and head[8] in (0xFD, 0xFE):
        return "tlog"
    what = {
        ".tlog": "a MAVLink .tlog",
        ".ulg": "a PX4 ULog",
        ".ulog": "a PX4 ULog",
        ".bin": "an ArduPilot DataFlash log",
    }.get(p.suffix.lower(), "a known flight log")
    raise UserError(
        f"flight log {p} is not {what}: its first bytes match no .tlog, ULog or DataFlash header (corrupt?)",
        hint="supported: MAVLink .tlog, PX4 ULog .ulg, ArduPilot DataFlash .bin",
    )


def load_dataset(
    path: str | Path,
    targets: str = "truth",
    motor_curve: Any = None,
    rate_hz: float | None = None,
    *,
    gravity: float | None = None,
) -> Dataset:
    """Read one flight log into a Dataset (format from the file's content; targets 'truth' or 'sensors').

    motor_curve: for logs without rotor speeds (or to use the motor commands instead): a vehicle name or
    file, 'slope,offset' (rad/s per unit throttle, rad/s), or an object with speed_for_throttle().
    rate_hz: the common timeline's rate (default: the log's natural one). gravity: m/s^2 added to the
    rotated specific force for sensor targets (default 9.80665).
    """
    if targets not in TARGET_SOURCES:
        raise UserError(f"targets must be one of {', '.join(TARGET_SOURCES)}, got {targets!r}")
    if rate_hz is not None and not (np.isfinite(rate_hz) and rate_hz > 0):
        raise UserError(f"rate must be a positive number of Hz, got {rate_hz}")
    fmt = detect_format(path)
    if fmt == "tlog":
        from identification.readers.tlog import read_tlog_dataset as reader
    elif fmt == "ulog":
        from identification.readers.ulog import read_ulog_dataset as reader
    else:
        from identification.readers.dataflash import read_dataflash_dataset as reader
    return reader(Path(path), targets=targets, motor_curve=motor_curve, rate_hz=rate_hz, gravity=gravity)
