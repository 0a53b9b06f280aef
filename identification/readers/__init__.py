"""What the log readers share: streams resampled onto one timeline, the rotor-speed-from-command model,
and the row filter that drops and counts bad rows before a Dataset is made.

Resampling: each stream (one log topic's columns) is linearly interpolated at the timeline's times
('linear'), held at its last value ('hold', for flags), or unwrapped before and wrapped after
interpolation ('angle'). A 'hold' stream with no max gap (a state such as armed or landed) holds its last
value after its last sample too. A row has a gap in a stream when the two samples around it are more than the
stream's max_gap apart, or the row lies outside the stream's time span; such rows are dropped and counted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from bridge.errors import UserError
from identification.flight_evidence import no_flight_evidence, raise_no_flight
from identification.table import Dataset, file_sha256
from identification.targets import contiguous_runs, nominal_step, wrap_angle

GAP_FACTOR = 4.0  # a stream's max gap: this many of its median sample intervals


@dataclass
class Stream:
    """One topic's samples: times (s), values (N,k), how to interpolate, and the longest allowed gap (s)."""

    name: str
    t: np.ndarray
    values: np.ndarray
    kind: str = "linear"  # linear | hold | angle | quaternion
    max_gap: float | None = None

    def __post_init__(self) -> None:
        t = np.asarray(self.t, dtype=float)
        v = np.asarray(self.values, dtype=float)
        if v.ndim == 1:
            v = v[:, None]
        order = np.argsort(t, kind="stable")
        t, v = t[order], v[order]
        keep = np.concatenate(([True], np.diff(t) > 0)) if len(t) else np.zeros(0, bool)
        self.t, self.values = t[keep], v[keep]
        if self.max_gap is None:
            dt = float(np.median(np.diff(self.t))) if len(self.t) > 1 else math.inf
            self.max_gap = GAP_FACTOR * dt

    @property
    def rate_hz(self) -> float:
        """Median sample rate, Hz."""
        return 1.0 / float(np.median(np.diff(self.t))) if len(self.t) > 1 else float("nan")

    def resample(self, timeline: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(values (M,k) at the timeline's times (s), ok (M,) False where the stream has a gap there)."""
        tl = np.asarray(timeline, dtype=float)
        m, k = len(tl), self.values.shape[1]
        out = np.full((m, k), np.nan)
        if len(self.t) == 0:
            return out, np.zeros(m, dtype=bool)
        if len(self.t) == 1:
            near = np.abs(tl - self.t[0]) <= (self.max_gap or 0.0)
            out[near] = self.values[0]
            return out, near
        i = np.searchsorted(self.t, tl, side="right")  # t[i-1] <= tl < t[i]
        inside = (tl >= self.t[0]) & ((tl <= self.t[-1]) | (self.kind == "hold" and self.max_gap == np.inf))
        lo = np.clip(i - 1, 0, len(self.t) - 1)
        hi = np.clip(i, 0, len(self.t) - 1)
        exact = inside & (self.t[lo] == tl)
        span = self.t[hi] - self.t[lo]
        ok = inside & ((span <= self.max_gap) | exact)
        if self.kind == "hold":
            out[:] = self.values[lo]
        elif self.kind == "angle":
            unwrapped = self.values.copy()  # over the finite samples: a NaN would end np.unwrap's sum
            for j in range(k):
                finite = np.isfinite(unwrapped[:, j])
                unwrapped[finite, j] = np.unwrap(unwrapped[finite, j])
            for j in range(k):
                out[:, j] = wrap_angle(np.interp(tl, self.t, unwrapped[:, j]))
        elif self.kind == "quaternion":
            q = self.values.copy()
            # q and -q are one attitude: make neighbours agree in sign before interpolating
            flips = (
                np.cumsum(np.concatenate(([0], (np.einsum("ij,ij->i", q[1:], q[:-1]) < 0).astype(int)))) % 2
            )
            q[flips == 1] *= -1.0
            for j in range(k):
                out[:, j] = np.interp(tl, self.t, q[:, j])
            out /= np.linalg.norm(out, axis=1, keepdims=True)
        else:
            for j in range(k):
                out[:, j] = np.interp(tl, self.t, self.values[:, j])
        out[~ok] = np.nan
        return out, ok


def uniform_timeline(streams: list[Stream], rate_hz: float) -> np.ndarray:
    """Times (s) at rate_hz over the span every stream covers."""
    start = max(s.t[0] for s in streams)
    stop = min(s.t[-1] for s in streams)
    if stop <= start:
        return np.zeros(0)
    n = int(math.floor((stop - start) * rate_hz + 1e-9)) + 1
    return np.minimum(start + np.arange(n) / rate_hz, stop)  # rounding must not put the last time past stop


# --------------------------------------------------------------------------------------------------------
# Rotor speeds from motor commands


@dataclass(frozen=True)
class RotorModel:
    """Steady rotor speed (rad/s) of a throttle in [0, 1] via a motor curve, optionally lagged by Tm (s)."""

    curve: Any
    time_constant: float | None
    description: str

    def speeds(self, t: np.ndarray, throttles: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rotor speeds (N,4) rad/s, settled (N,)) at times t (s) of throttle samples (N,4, NaN = unknown).

        With a lag the response restarts from the steady speed after each unknown sample, and rows within
        7 time constants of such a restart are not `settled` (their speed is not yet trustworthy).
        """
        thr = np.asarray(throttles, dtype=float)
        known = np.isfinite(thr).all(axis=1)
        f = np.vectorize(lambda s: float(self.curve.speed_for_throttle(float(s))))
        steady = np.full(thr.shape, np.nan)
        if known.any():
            steady[known] = f(np.clip(thr[known], 0.0, 1.0))
        settled = known.copy()
        if not self.time_constant or len(t) < 2:
            return steady, settled
        out = np.full(thr.shape, np.nan)
        alpha = 1.0 - np.exp(-np.diff(t) / self.time_constant)
        restart = -np.inf
        for i in range(len(t)):
            if not known[i]:
                continue
            if i == 0 or not known[i - 1]:
                out[i] = steady[i]
                restart = t[i]
            else:
                # command held between samples (zero-order hold): exact first-order response
                out[i] = out[i - 1] + alpha[i - 1] * (steady[i - 1] - out[i - 1])
            settled[i] = t[i] - restart >= 7.0 * self.time_constant
        return out, settled


def rotor_model(motor_curve: Any) -> RotorModel | None:
    """A RotorModel from --motor-curve: None, 'slope,offset', a vehicle name/file, or a curve object."""
    if motor_curve is None:
        return None
    if hasattr(motor_curve, "motor_curve") and hasattr(motor_curve, "motor"):  # a VehicleConfig
        return RotorModel(
            motor_curve.motor_curve,
            motor_curve.motor.time_constant,
            f"vehicle {motor_curve.name} (lag {motor_curve.motor.time_constant:g} s)",
        )
    if hasattr(motor_curve, "speed_for_throttle"):
        return RotorModel(motor_curve, None, "the given motor curve (no lag)")
    text = str(motor_curve).strip()
    parts = text.split(",")
    if len(parts) == 2:
        try:
            slope, offset = float(parts[0]), float(parts[1])
        except ValueError:
            slope = offset = math.nan
        if not (math.isfinite(slope) and math.isfinite(offset) and slope > 0):
            raise UserError(
                f"motor curve {text!r}: expected 'slope,offset' in rad/s with slope > 0 "
                f"(w = slope*throttle + offset)",
                hint="e.g. --motor-curve 1148,-141.4, or a vehicle name/file such as fang-chen-buaa",
            )
        from bridge.vehicle import MotorCurve

        return RotorModel(
            MotorCurve(slope, offset), None, f"w = {slope:g}*throttle + {offset:g} rad/s (no lag)"
        )
    from bridge.vehicle import load_vehicle

    vehicle = load_vehicle(text)
    return RotorModel(
        vehicle.motor_curve,
        vehicle.motor.time_constant,
        f"vehicle {vehicle.name} (lag {vehicle.motor.time_constant:g} s)",
    )


# --------------------------------------------------------------------------------------------------------
# Rows


@dataclass
class RowFilter:
    """Collects reasons to drop rows; the first reason that applies to a row is the one counted."""

    n: int
    reasons: list[tuple[str, np.ndarray]] = field(default_factory=list)

    def drop(self, reason: str, bad: np.ndarray) -> None:
        """Mark rows (boolean mask, True = drop) with a reason."""
        bad = np.asarray(bad, dtype=bool)
        if bad.any():
            self.reasons.append((reason, bad))

    def drop_nonfinite(self, reason: str, *arrays: np.ndarray) -> None:
        """Drop rows where any of the arrays (N,...) holds NaN or inf."""
        bad = np.zeros(self.n, dtype=bool)
        for a in arrays:
            a = np.asarray(a, dtype=float).reshape(self.n, -1)
            bad |= ~np.isfinite(a).all(axis=1)
        self.drop(reason, bad)

    def keep_mask(self) -> tuple[np.ndarray, dict[str, int]]:
        """(rows kept, count of dropped rows per reason)."""
        keep = np.ones(self.n, dtype=bool)
        counts: dict[str, int] = {}
        for reason, bad in self.reasons:
            newly = bad & keep
            c = int(newly.sum())
            if c:
                counts[reason] = counts.get(reason, 0) + c
            keep &= ~bad
        return keep, counts


def make_dataset(
    path: Path,
    fmt: str,
    target_source: str,
    t: np.ndarray,
    xi: np.ndarray,
    u: np.ndarray,
    targets: np.ndarray,
    rows: RowFilter,
    warnings: list[str],
    extra_dropped: dict[str, int] | None = None,
    aux: dict[str, np.ndarray] | None = None,
) -> Dataset:
    """The Dataset of the rows that survive the filter (plus NaN checks), with drops counted by reason.

    aux: side columns per timeline row (identification.table.AUX_NAMES), kept for the surviving rows."""
    rows.drop_nonfinite("NaN in states or rotor speeds", xi, u)
    rows.drop_nonfinite("no target (differentiation edge or gap)", targets)
    keep, counts = rows.keep_mask()
    for k, v in (extra_dropped or {}).items():
        counts[k] = counts.get(k, 0) + v
    if not keep.any():
        why = ", ".join(f"{k}: {v}" for k, v in counts.items()) or "no samples"
        evidence = no_flight_evidence(t, aux or {}, xi[:, 2] if len(xi) else None)
        if evidence is not None:
            raise_no_flight(f"{fmt} log {path}", evidence, also=f"it gives no complete rows ({why})")
        raise UserError(
            f"{fmt} log {path} gives no complete rows ({why})",
            hint="is the flight long enough, and does the log hold all the streams listed?",
        )
    return Dataset(
        t=t[keep],
        xi=xi[keep],
        u=u[keep],
        targets=targets[keep],
        source=str(path),
        format=fmt,
        target_source=target_source,
        dropped_rows=int(sum(counts.values())),
        drop_reasons=counts,
        warnings=list(warnings),
        sha256=file_sha256(path),
        aux={k: np.asarray(v, dtype=float)[keep] for k, v in (aux or {}).items()},
    )


def uniform_imu(t: np.ndarray, values: np.ndarray, notes: list[str]) -> tuple[np.ndarray, np.ndarray]:
    """IMU samples (times s, values) on a uniform grid when their times jitter (a 400 Hz loop on a 1 ms
    simulator clock logs at 2 and 3 ms spacings; PX4 at a high speed-up skips a sample now and then, and its
    mid-interval times then jitter): linearly interpolated at their mean spacing, NaN across gaps (more than
    GAP_FACTOR samples); unchanged when already uniform. No fixed-step differentiator spans such times."""
    step = nominal_step(t)
    if len(t) < 3 or len(contiguous_runs(t, step)) <= 1 + len(t) // 1000:
        return t, values
    stream = Stream("IMU", t, values)
    spacing = np.diff(stream.t)
    mean = float(np.mean(spacing[spacing <= stream.max_gap]))
    grid = uniform_timeline([stream], 1.0 / mean)
    out, ok = stream.resample(grid)
    out[~ok] = np.nan
    jitter = f"{spacing.min() * 1e3:.1f}-{np.percentile(spacing, 99) * 1e3:.1f}"
    notes.append(f"IMU times jitter (spacings {jitter} ms): resampled to a uniform {1.0 / mean:.0f} Hz "
                 "before differentiating")
    return grid, out
