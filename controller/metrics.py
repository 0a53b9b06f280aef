"""Tracking metrics of one flight: position and yaw errors, settling, motor saturation, control step timing.

Inputs are per-control-step samples: time [s], actual and desired position [m, NED], yaw [rad], whether any
motor command was clipped, and the wall time each control step took [s].
"""

from __future__ import annotations

import csv
import math
from dataclasses import asdict, dataclass, fields
from pathlib import Path

import numpy as np

SETTLE_TOLERANCE = 0.05  # m, 3-D position error that counts as settled
TRANSIENT = 5.0  # s, "RMS after 5 s" excludes the take-off transient before this time


@dataclass(frozen=True)
class FlightMetrics:
    """Summary of one tracking flight (SI units; None where a figure is undefined)."""

    controller: str
    trajectory: str
    duration_s: float  # s, simulated time covered by the samples
    samples: int
    completed: bool  # the flight ran to its planned end (no lost link, no divergence)
    crashed: bool  # the vehicle came back down onto the ground or tilted past 80 deg after take-off
    rms_m: float  # m, RMS of the 3-D position error over the whole flight
    rms_after_5s_m: float | None  # m, RMS of the 3-D position error for t >= 5 s
    max_m: float  # m, largest 3-D position error
    max_after_5s_m: float | None  # m, largest 3-D position error for t >= 5 s
    overshoot_m: float  # m, furthest the vehicle went past the reference along the direction it started from
    final_m: float  # m, 3-D position error at the last sample
    settle_time_s: float | None  # s, first time after which the error stays within 5 cm (None: never)
    yaw_rms_rad: float  # rad, RMS of the wrapped yaw error
    yaw_max_rad: float  # rad, largest absolute wrapped yaw error
    motor_limit_share: float  # fraction of steps with any motor command clipped to 0 or w_max
    max_tilt_deg: float  # deg, largest angle between body z and earth z (nan when not recorded)
    step_median_us: float  # us, median wall time of one control step
    step_p99_us: float  # us, 99th percentile wall time of one control step


def wrap_angle(a: np.ndarray | float) -> np.ndarray:
    """Angle(s) wrapped to [-pi, pi) rad."""
    return (np.asarray(a, dtype=float) + math.pi) % (2.0 * math.pi) - math.pi


def settle_time(t: np.ndarray, error: np.ndarray, tolerance: float = SETTLE_TOLERANCE) -> float | None:
    """First time [s] from which |error| stays within tolerance to the end; None if the last sample is out."""
    t = np.asarray(t, dtype=float)
    outside = np.flatnonzero(~(np.abs(np.asarray(error, dtype=float)) <= tolerance))
    if outside.size == 0:
        return float(t[0]) if t.size else None
    last = int(outside[-1])
    if last == t.size - 1:
        return None
    return float(t[last + 1])


def overshoot(position: np.ndarray, position_desired: np.ndarray, start_gap: float = 0.1) -> float:
    """How far [m] the vehicle went past the reference along the direction it was first sent: from its start
    to the reference's first point when that is more than start_gap [m] away (Case I, II); else the
    reference starts at the vehicle (a take-off phase) and the direction is the reference's own first move,
    to its first point more than start_gap from its start (for a take-off the height above the reference;
    with an estimated state the take-off starts where the estimate puts the vehicle, a few cm off, and the
    direction from the true start would lean that way); 0 when it never did."""
    p = np.asarray(position, dtype=float)
    r = np.asarray(position_desired, dtype=float)
    if p.shape[0] == 0:
        return 0.0
    origin = p[0] if np.linalg.norm(r[0] - p[0]) > start_gap else r[0]
    gaps = np.linalg.norm(r - origin, axis=1)
    away = np.flatnonzero(gaps > start_gap)
    if away.size == 0:
        return 0.0
    u = r[away[0]] - origin
    n = float(np.linalg.norm(u))
    past = (p - r) @ (u / n)
    past = past[np.isfinite(past)]
    return float(max(0.0, np.max(past))) if past.size else 0.0


def _rms(values: np.ndarray) -> float:
    return float(math.sqrt(np.mean(np.square(values)))) if values.size else float("nan")


def compute_metrics(
    t: np.ndarray,
    position: np.ndarray,
    position_desired: np.ndarray,
    yaw: np.ndarray,
    yaw_desired: np.ndarray,
    saturated: np.ndarray,
    step_time_s: np.ndarray,
    *,
    controller: str = "",
    trajectory: str = "",
    completed: bool = True,
    crashed: bool = False,
    tilt_rad: np.ndarray | None = None,
) -> FlightMetrics:
    """Metrics from per-step samples: t [s], positions (N, 3) [m, NED], yaw [rad], step wall time [s]."""
    t = np.asarray(t, dtype=float)
    if t.size == 0:
        raise ValueError("no samples: the flight recorded no control step")
    err = np.linalg.norm(np.asarray(position, float) - np.asarray(position_desired, float), axis=1)
    finite = np.where(np.isfinite(err), err, np.inf)
    after = t >= TRANSIENT
    yaw_err = wrap_angle(np.asarray(yaw, float) - np.asarray(yaw_desired, float))
    steps_us = np.asarray(step_time_s, dtype=float) * 1e6
    return FlightMetrics(
        controller=controller,
        trajectory=trajectory,
        duration_s=float(t[-1] - t[0]),
        samples=int(t.size),
        completed=bool(completed and np.all(np.isfinite(err))),
        crashed=bool(crashed),
        rms_m=_rms(finite),
        rms_after_5s_m=_rms(finite[after]) if np.any(after) else None,
        max_m=float(np.max(finite)),
        max_after_5s_m=float(np.max(finite[after])) if np.any(after) else None,
        overshoot_m=overshoot(position, position_desired),
        final_m=float(finite[-1]),
        settle_time_s=settle_time(t, finite),
        yaw_rms_rad=_rms(yaw_err),
        yaw_max_rad=float(np.max(np.abs(yaw_err))),
        motor_limit_share=float(np.mean(np.asarray(saturated, dtype=bool))),
        max_tilt_deg=float(np.degrees(np.max(tilt_rad))) if tilt_rad is not None and len(tilt_rad)
        else float("nan"),
        step_median_us=float(np.median(steps_us)) if steps_us.size else float("nan"),
        step_p99_us=float(np.percentile(steps_us, 99)) if steps_us.size else float("nan"),
    )


_LABELS = {
    "controller": ("controller", ""),
    "trajectory": ("trajectory", ""),
    "duration_s": ("flown", "s"),
    "samples": ("control steps", ""),
    "completed": ("flown to the end", ""),
    "crashed": ("crashed", ""),
    "rms_m": ("RMS 3-D position error", "m"),
    "rms_after_5s_m": ("RMS 3-D position error after 5 s", "m"),
    "max_m": ("max 3-D position error", "m"),
    "max_after_5s_m": ("max 3-D position error after 5 s", "m"),
    "overshoot_m": ("overshoot past the reference (along the start's approach)", "m"),
    "final_m": ("final 3-D position error", "m"),
    "settle_time_s": ("time to settle within 5 cm (and stay)", "s"),
    "yaw_rms_rad": ("RMS yaw error", "rad"),
    "yaw_max_rad": ("max yaw error", "rad"),
    "motor_limit_share": ("share of steps at a motor limit", ""),
    "max_tilt_deg": ("max tilt", "deg"),
    "step_median_us": ("control step time, median", "us"),
    "step_p99_us": ("control step time, p99", "us"),
}


def _format(value: object) -> str:
    if value is None:
        return "n/a"
    if isinstance(value, bool):
        return "yes" if value else "no"
    if isinstance(value, float):
        return "nan" if math.isnan(value) else f"{value:.6g}"
    return str(value)


def metrics_markdown(m: FlightMetrics) -> str:
    """The metrics as a Markdown table (one row per figure, with units)."""
    lines = [f"# Tracking metrics: {m.controller} on {m.trajectory}", "", "| metric | value | unit |",
             "|---|---|---|"]
    for f in fields(m):
        label, unit = _LABELS[f.name]
        value = getattr(m, f.name)
        text = "never settled" if f.name == "settle_time_s" and value is None else _format(value)
        lines.append(f"| {label} | {text} | {unit} |")
    return "\n".join(lines) + "\n"


def write_metrics(m: FlightMetrics, out_dir: str | Path) -> tuple[Path, Path]:
    """Write metrics.md and metrics.csv (header row of field names, one value row) into out_dir."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    md = out / "metrics.md"
    md.write_text(metrics_markdown(m), encoding="utf-8")
    path_csv = out / "metrics.csv"
    row = asdict(m)
    with path_csv.open("w", newline="", encoding="utf-8") as fh:
        writer = csv.writer(fh)
        writer.writerow(list(row))
        writer.writerow(["" if v is None else v for v in row.values()])
    return md, path_csv


def read_metrics_csv(path: str | Path) -> dict[str, str]:
    """Read a metrics.csv written by write_metrics back as a field -> text mapping."""
    with Path(path).open(newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    return dict(zip(rows[0], rows[1], strict=True))


def metrics_from_csv(path: str | Path) -> FlightMetrics:
    """A metrics.csv written by write_metrics back as FlightMetrics (empty cells: None)."""
    text = read_metrics_csv(path)
    values: dict[str, object] = {}
    for f in fields(FlightMetrics):
        v = text[f.name]
        if f.type in ("str", str):
            values[f.name] = v
        elif f.type in ("bool", bool):
            values[f.name] = v == "True"
        elif f.type in ("int", int):
            values[f.name] = int(v)
        else:
            values[f.name] = None if v == "" else float(v)
    return FlightMetrics(**values)
