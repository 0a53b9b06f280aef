"""A flight as a table (CSV or Parquet) -> Dataset: data from anywhere (motion capture, other autopilots).

One row per sample, named columns (README "Tables from anywhere"), any order, extra columns ignored:
- t: time, s (strictly increasing).
- x y z: position NED, m; vx vy vz: velocity NED, m/s.
- attitude: phi theta psi (ZYX Euler, rad) or qw qx qy qz (body FRD -> NED, scalar first).
- wx wy wz: body rates FRD, rad/s.
- motors: u1..u4 rotor speeds, rad/s (PX4 Quad-X order), or throttle1..throttle4 in [0, 1] (then through
  --motor-curve, or the fitted thrust curve of identification.motor_model).
- optional: ax ay az (NED, m/s^2) and dwx dwy dwz (FRD, rad/s^2); absent ones are the derivatives of the
  velocity and the rates (Savitzky-Golay, identification.targets.stream_derivative). voltage (V), landed
  and armed (0/1) feed the flight segmentation and the motor model.
Targets 'sensors' are not available from a table (it has no IMU); rate_hz resamples onto a uniform
timeline by linear interpolation.
"""

from __future__ import annotations

import csv
from pathlib import Path
from typing import Any

import numpy as np

from bridge.errors import UserError
from bridge.rotations import euler_from_quaternions
from identification.motor_model import ThrustCurve
from identification.readers import RowFilter, Stream, make_dataset, rotor_model, uniform_timeline
from identification.table import Dataset
from identification.targets import stream_derivative

REQUIRED = ("t", "x", "y", "z", "vx", "vy", "vz", "wx", "wy", "wz")
EULER = ("phi", "theta", "psi")
QUATERNION = ("qw", "qx", "qy", "qz")
SPEEDS = ("u1", "u2", "u3", "u4")
THROTTLES = ("throttle1", "throttle2", "throttle3", "throttle4")
LINEAR = ("ax", "ay", "az")
ANGULAR = ("dwx", "dwy", "dwz")
SIDE = ("voltage", "landed", "armed")
SCHEMA_HINT = (
    "columns: t, x y z, vx vy vz, phi theta psi (or qw qx qy qz), wx wy wz, u1..u4 (or throttle1..4); "
    "optional ax ay az, dwx dwy dwz, voltage, landed, armed (README: Tables from anywhere)"
)


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    """Columns of a CSV file by header name; UserError naming the line and column of a bad value."""
    try:
        with path.open(newline="", encoding="utf-8") as fh:
            rows = list(csv.reader(fh))
    except (OSError, UnicodeDecodeError) as exc:
        raise UserError(f"cannot read table {path}: {exc}") from None
    if not rows or not any(cell.strip() for cell in rows[0]):
        raise UserError(f"table {path} has no header line", hint=SCHEMA_HINT)
    header = [h.strip() for h in rows[0]]
    dupes = sorted({h for h in header if header.count(h) > 1})
    if dupes:
        raise UserError(f"table {path}: column {dupes[0]!r} appears twice in the header")
    data = np.full((len(rows) - 1, len(header)), np.nan)
    for i, row in enumerate(rows[1:]):
        if len(row) != len(header):
            raise UserError(
                f"table {path}, line {i + 2}: {len(row)} values for {len(header)} columns",
                hint="every line needs one value per header column (empty for unknown)",
            )
        for j, cell in enumerate(row):
            cell = cell.strip()
            if not cell:
                continue
            try:
                data[i, j] = float(cell)
            except ValueError:
                raise UserError(
                    f"table {path}, line {i + 2}, column {header[j]!r}: {cell!r} is not a number"
                ) from None
    return {h: data[:, j] for j, h in enumerate(header)}


def _read_parquet(path: Path) -> dict[str, np.ndarray]:
    """Columns of a Parquet file (numeric columns only)."""
    try:
        import pyarrow.parquet as pq
    except ImportError:
        raise UserError(
            f"reading {path} needs pyarrow", hint="pip install pyarrow (or give the table as CSV)"
        ) from None
    try:
        table = pq.read_table(path)
    except Exception as exc:  # pyarrow raises its own error types for damaged files
        raise UserError(f"table {path} is not a readable Parquet file ({exc})") from None
    out = {}
    for name in table.column_names:
        try:
            out[name] = np.asarray(table.column(name).to_numpy(zero_copy_only=False), dtype=float)
        except (TypeError, ValueError):
            continue  # a non-numeric column (a label, a note): not one of ours
    return out


def read_columns(path: Path) -> dict[str, np.ndarray]:
    """The table's columns by name, from CSV or Parquet (chosen by the content, then the extension)."""
    with path.open("rb") as fh:
        parquet = fh.read(4) == b"PAR1"
    return _read_parquet(path) if parquet or path.suffix.lower() == ".parquet" else _read_csv(path)


def _need(cols: dict[str, np.ndarray], names: tuple[str, ...], path: Path, what: str) -> np.ndarray:
    missing = [n for n in names if n not in cols]
    if missing:
        raise UserError(
            f"table {path} has no column {missing[0]!r} ({what})",
            hint=f"columns found: {', '.join(cols) or 'none'}; {SCHEMA_HINT}",
        )
    return np.column_stack([cols[n] for n in names])


def read_table_dataset(
    path: Path,
    targets: str = "truth",
    motor_curve: Any = None,
    rate_hz: float | None = None,
    gravity: float | None = None,
) -> Dataset:
    """Dataset of a CSV/Parquet flight table (module docstring: the columns and their units)."""
    if targets != "truth":
        raise UserError(
            f"table {path}: targets from 'sensors' need an IMU, which a table does not have",
            hint="use --targets-from truth (the default): ax..dwz columns, or the derivatives of the states",
        )
    cols = read_columns(path)
    t = _need(cols, ("t",), path, "time, s")[:, 0]
    if len(t) < 2:
        raise UserError(f"table {path} has {len(t)} rows; a flight needs many", hint=SCHEMA_HINT)
    if not (np.isfinite(t).all() and (np.diff(t) > 0).all()):
        bad = int(np.flatnonzero(~(np.diff(t) > 0) | ~np.isfinite(t[1:]))[0]) + 1 if len(t) > 1 else 0
        raise UserError(
            f"table {path}: column 't' must be finite and strictly increasing (s); row {bad + 1} is not",
            hint="sort the rows by time and remove duplicates",
        )
    pos = _need(cols, ("x", "y", "z", "vx", "vy", "vz"), path, "position NED m, velocity NED m/s")
    rates = _need(cols, ("wx", "wy", "wz"), path, "body rates FRD, rad/s")
    if all(n in cols for n in EULER):
        euler = np.column_stack([cols[n] for n in EULER])
    elif all(n in cols for n in QUATERNION):
        q = np.column_stack([cols[n] for n in QUATERNION])
        euler = euler_from_quaternions(q / np.linalg.norm(q, axis=1, keepdims=True))
    else:
        _need(cols, EULER, path, "the attitude: ZYX Euler rad, or qw qx qy qz")
    notes: list[str] = []
    throttle = None
    if all(n in cols for n in SPEEDS) and motor_curve is None:
        u = np.column_stack([cols[n] for n in SPEEDS])
    else:
        throttle = _need(cols, THROTTLES, path, "the rotor speeds u1..u4 rad/s, or throttle1..4 in [0, 1]")
        if np.nanmin(throttle) < 0 or np.nanmax(throttle) > 1:
            raise UserError(
                f"table {path}: throttle1..4 must lie in [0, 1] "
                f"(got {np.nanmin(throttle):g}..{np.nanmax(throttle):g})",
                hint="give throttles as fractions of full throttle, or rotor speeds as u1..u4 in rad/s",
            )
        rotor = rotor_model(motor_curve)
        if rotor is not None:
            u, _ = rotor.speeds(t, throttle)
            notes.append(f"rotor speeds from throttle1..4 through {rotor.description}")
        else:
            u = ThrustCurve().speeds(throttle, None)
            notes.append("no u1..u4: u from throttle1..4 through a thrust curve (identification.motor_model)")
    lin = np.column_stack([cols[n] for n in LINEAR]) if all(n in cols for n in LINEAR) else None
    ang = np.column_stack([cols[n] for n in ANGULAR]) if all(n in cols for n in ANGULAR) else None
    if lin is None:
        lin = stream_derivative(t, pos[:, 3:6])
        notes.append("no ax ay az columns: linear accelerations by differentiating vx vy vz")
    if ang is None:
        ang = stream_derivative(t, rates)
        notes.append("no dwx dwy dwz columns: angular accelerations by differentiating wx wy wz")
    side = {n: cols[n] for n in SIDE if n in cols}
    table = np.column_stack((pos, euler, rates, u, lin, ang))
    if rate_hz:
        base = Stream("table", t, table)
        timeline = uniform_timeline([base], rate_hz)
        table, _ = base.resample(timeline)
        side = {n: np.interp(timeline, t, v) for n, v in side.items()}
        if throttle is not None:
            throttle = Stream("throttle", t, throttle).resample(timeline)[0]
        t = timeline
    aux = dict(side)
    if throttle is not None:
        aux["throttle"] = throttle
    filt = RowFilter(len(t))
    xi = table[:, 0:12]
    ds = make_dataset(path, "table", "truth", t, xi, table[:, 12:16], table[:, 16:22], filt, notes, aux=aux)
    ds.u_from_throttle = throttle is not None and motor_curve is None
    return ds
