"""Flight segmentation: which rows of a flight log are free flight (airborne), and why the others go.

Detectors (each abstains when its log lacks what it needs; the kept rows are those every voting detector
calls airborne):
- arming state: disarmed rows are on the ground (PX4 vehicle_status.arming_state; aux column `armed`).
- land detector: the log's own flag (PX4 vehicle_land_detected.landed; aux column `landed`).
- height: height above the take-off point (m, up) > min_height_m. The take-off point is the median z (NED)
  of the rows at rest (speed < rest_speed m/s) in the first rest_s seconds; no rest at the start: abstains.
- motors: the mean motor command (aux `throttle`, else the mean rotor speed) above
  rest + motor_fraction * (flight - rest), rest = its median at rest at the start (or while landed), flight
  = its median where the height detector says airborne (else its 90th percentile).
- accelerometer: | |specific force| - g | (aux `accel_dev`, m/s^2) above impact_accel marks ground contact
  (touch-down, bumps); rows within impact_margin_s of one go.
Then rows within edge_margin_s of a ground row (lift-off, touch-down: ground effect and transients) and
airborne pieces shorter than min_segment_s go. Our .tlog needs no detector: its reader drops the rows
where the SITL holds the vehicle on its ground plane, from the SITL's own state, and says how far each
row is from them (aux `ground_s`), so the edge margin is all that is left to drop. Near the ground just
after lift-off the vehicle is below where a ground-effect law holds (the SITL clamps it at min_height) and
at h -> 0 a law in 1/h is not defined: kept, a handful of rows there would own any 1/h feature.

With windows ((start, end) log seconds, by hand) only the rows inside them are kept, no detector drops a
row, and the detectors' view of those rows is printed as a cross-check.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from bridge.errors import UserError
from identification.table import Dataset

Window = tuple[float, float]


@dataclass(frozen=True)
class SegmentationSettings:
    """Thresholds of the airborne detectors (SI units: m, m/s, m/s^2, s)."""

    min_height_m: float = 0.15
    rest_speed: float = 0.2
    rest_s: float = 1.0
    motor_fraction: float = 0.4
    impact_accel: float = 15.0
    impact_margin_s: float = 0.3
    edge_margin_s: float = 0.3
    min_segment_s: float = 1.0


@dataclass(frozen=True)
class Vote:
    """One detector's verdict: airborne (N,) bool, or None when it abstains, and a line saying what it saw."""

    name: str
    airborne: np.ndarray | None
    note: str


def parse_window(text: str) -> Window:
    """'START:END' in log seconds -> (start, end); UserError naming the flag and the fix."""
    parts = str(text).split(":")
    try:
        start, end = (float(p) for p in parts)
    except ValueError:
        start = end = float("nan")
    if len(parts) != 2 or not (np.isfinite(start) and np.isfinite(end)) or end <= start:
        raise UserError(
            f"--window {text!r}: expected START:END in seconds of log time with END > START",
            hint="e.g. --window 19.5:27 (repeat --window for several pieces)",
        )
    return (start, end)


def _intervals(t: np.ndarray, mask: np.ndarray, gap: float) -> list[tuple[float, float]]:
    """Time intervals (s) of consecutive True rows (a time gap > gap s also splits)."""
    out: list[tuple[float, float]] = []
    start = None
    for i in range(len(t)):
        if mask[i] and start is None:
            start = i
        end_here = mask[i] and (i + 1 == len(t) or not mask[i + 1] or t[i + 1] - t[i] > gap)
        if end_here and start is not None:
            out.append((float(t[start]), float(t[i])))
            start = None
    return out


def _describe(intervals: list[tuple[float, float]]) -> str:
    if not intervals:
        return "none"
    text = ", ".join(f"{a:.2f}-{b:.2f} s" for a, b in intervals[:4])
    return text + (f" (+{len(intervals) - 4} more)" if len(intervals) > 4 else "")


def seconds_to_nearest(t: np.ndarray, times: np.ndarray) -> np.ndarray:
    """For each time t (s), the distance (s) to the nearest of `times` (s, sorted); inf when none."""
    t = np.asarray(t, float)
    if len(times) == 0:
        return np.full(len(t), np.inf)
    i = np.searchsorted(times, t)
    before = np.abs(t - times[np.clip(i - 1, 0, len(times) - 1)])
    after = np.abs(times[np.clip(i, 0, len(times) - 1)] - t)
    return np.minimum(before, after)


def _near(t: np.ndarray, mask: np.ndarray, margin: float) -> np.ndarray:
    """Rows within margin s (in time) of a True row."""
    if margin <= 0 or not mask.any():
        return mask.copy()
    return seconds_to_nearest(t, t[mask]) <= margin


def _motor_signal(ds: Dataset) -> tuple[np.ndarray, str]:
    """(mean motor command per row, or mean rotor speed when no command is logged; what it is)."""
    thr = ds.aux.get("throttle")
    if thr is not None and np.isfinite(thr).any():
        return np.nanmean(np.where(np.isfinite(thr), thr, np.nan), axis=1), "mean motor command"
    return ds.u.mean(axis=1), "mean rotor speed"


def _rest_at_start(ds: Dataset, s: SegmentationSettings) -> np.ndarray | None:
    """Rows on the ground at the start: at rest (speed < rest_speed) with the motors far below their flight
    level (a quarter of their 90th percentile) in the first rest_s seconds; None if there are too few."""
    if not len(ds):
        return None
    first = ds.t <= ds.t[0] + s.rest_s
    speed = np.linalg.norm(ds.xi[:, 3:6], axis=1)
    signal, _ = _motor_signal(ds)
    with np.errstate(invalid="ignore"):
        low = signal < 0.25 * np.nanpercentile(signal, 90)
    rest = first & (speed < s.rest_speed) & low
    return rest if rest.sum() >= max(3, 0.5 * first.sum()) else None


def detector_votes(ds: Dataset, settings: SegmentationSettings | None = None) -> list[Vote]:
    """Each detector's airborne verdict on the rows of ds (see the module docstring)."""
    s = settings or SegmentationSettings()
    votes = []
    armed = ds.aux.get("armed")
    if armed is not None and np.isfinite(armed).any():
        air = armed > 0.5
        votes.append(Vote("armed", air, f"arming state: armed {_describe(_intervals(ds.t, air, 1.0))}"))
    landed = ds.aux.get("landed")
    if landed is not None and np.isfinite(landed).any():
        air = ~(landed > 0.5)
        votes.append(
            Vote("land detector", air, f"land detector: airborne {_describe(_intervals(ds.t, air, 1.0))}")
        )
    else:
        votes.append(Vote("land detector", None, "land detector: not in this log"))

    rest = _rest_at_start(ds, s)
    height_air = None
    if rest is not None:
        z0 = float(np.median(ds.xi[rest, 2]))
        height = z0 - ds.xi[:, 2]  # m, up from the take-off point
        height_air = height > s.min_height_m
        votes.append(
            Vote(
                "height",
                height_air,
                f"height above take-off (z0 = {z0:.2f} m NED) > {s.min_height_m:g} m: "
                f"{_describe(_intervals(ds.t, height_air, 1.0))}",
            )
        )
    else:
        votes.append(Vote("height", None, "height above take-off: abstains (the log does not start at rest)"))

    signal, what = _motor_signal(ds)
    ground = rest if rest is not None else (landed > 0.5 if landed is not None else None)
    if ground is not None and ground.any() and np.isfinite(signal[ground]).any():
        lo = float(np.nanmedian(signal[ground]))
        ref = height_air if height_air is not None and height_air.any() else None
        hi = float(np.nanmedian(signal[ref])) if ref is not None else float(np.nanpercentile(signal, 90))
        if hi > lo:
            level = lo + s.motor_fraction * (hi - lo)
            air = signal > level
            votes.append(
                Vote(
                    "motors",
                    air,
                    f"motors ({what} > {level:.3g}; rest {lo:.3g}, flight {hi:.3g}): "
                    f"{_describe(_intervals(ds.t, air, 1.0))}",
                )
            )
        else:
            votes.append(Vote("motors", None, f"motors: abstain ({what} not higher in flight than at rest)"))
    else:
        votes.append(Vote("motors", None, "motors: abstain (no rows known to be on the ground)"))

    dev = ds.aux.get("accel_dev")
    if dev is not None and np.isfinite(dev).any():
        impact = _near(ds.t, np.nan_to_num(dev) > s.impact_accel, s.impact_margin_s)
        n_imp = len(_intervals(ds.t, np.nan_to_num(dev) > s.impact_accel, 0.5))
        votes.append(
            Vote(
                "accelerometer",
                ~impact,
                f"accelerometer: {n_imp} impact(s) (| |f| - g | > {s.impact_accel:g} m/s^2)",
            )
        )
    else:
        votes.append(Vote("accelerometer", None, "accelerometer: not in this table"))
    return votes


REASONS = {
    "armed": "motors disarmed (the log's arming state)",
    "land detector": "on the ground (the log's land detector)",
    "height": "below {h:g} m above the take-off point",
    "motors": "motors at ground level (below the flight level)",
    "accelerometer": "ground contact on the accelerometer (impact)",
}


def segment(
    ds: Dataset, windows: Sequence[Window] | None = None, settings: SegmentationSettings | None = None
) -> Dataset:
    """The airborne rows of ds (or those in windows), with each drop reason counted and `segments` filled."""
    s = settings or SegmentationSettings()
    n = len(ds)
    if n == 0:
        return ds
    gap = 4.0 * float(np.median(np.diff(ds.t))) if n > 1 else 1.0
    lines = [f"{ds.source}: flight segmentation"]
    reasons: dict[str, int] = {}
    keep = np.ones(n, dtype=bool)

    def drop(reason: str, bad: np.ndarray) -> None:
        newly = bad & keep
        if newly.any():
            reasons[reason] = reasons.get(reason, 0) + int(newly.sum())
            keep[newly] = False

    if ds.format == "tlog" and not windows:
        lines.append(
            "  .tlog: rows where the SITL holds the vehicle on its ground plane were dropped by the reader"
        )
        if "ground_s" in ds.aux:
            near = ds.aux["ground_s"] <= s.edge_margin_s
            drop(f"within {s.edge_margin_s:g} s of lift-off or touch-down", near)
        return _finish(ds, keep, reasons, lines, gap)
    votes = detector_votes(ds, s)
    voting = [v for v in votes if v.airborne is not None]
    for v in votes:
        lines.append(f"  {v.note}")
    if windows:
        inside = np.zeros(n, dtype=bool)
        for a, b in windows:
            inside |= (ds.t >= a) & (ds.t <= b)
        drop("outside --window", ~inside)
        for v in voting:
            doubt = int((~v.airborne & keep).sum())
            if doubt:
                lines.append(
                    f"  cross-check: {v.name} calls {doubt} rows inside your windows ground rows (kept)"
                )
        return _finish(ds, keep, reasons, lines, gap)
    if not voting:
        lines.append("  no detector could vote: all rows kept (use --window to choose by hand)")
        return _finish(ds, keep, reasons, lines, gap)
    all_air = np.logical_and.reduce([v.airborne for v in voting])
    any_air = np.logical_or.reduce([v.airborne for v in voting])
    disagree = int((any_air & ~all_air).sum())
    if disagree:
        firsts = []
        for v in voting:
            iv = _intervals(ds.t, v.airborne, gap)
            firsts.append(f"{v.name} from {iv[0][0]:.2f} s" if iv else f"{v.name} never")
        lines.append(
            f"  cross-check: the detectors disagree on {disagree} rows "
            f"(first airborne: {', '.join(firsts)}); "
            "kept only rows every detector calls airborne"
        )
    for v in voting:
        drop(REASONS[v.name].format(h=s.min_height_m), ~v.airborne)
    drop(f"within {s.edge_margin_s:g} s of lift-off or touch-down", _near(ds.t, ~all_air, s.edge_margin_s))
    for a, b in _intervals(ds.t, keep, gap):
        if b - a < s.min_segment_s:
            drop(f"airborne piece shorter than {s.min_segment_s:g} s", (ds.t >= a) & (ds.t <= b))
    return _finish(ds, keep, reasons, lines, gap)


def _finish(ds: Dataset, keep: np.ndarray, reasons: dict[str, int], lines: list[str], gap: float) -> Dataset:
    """ds.select(keep) with the reasons added to its drops and the account in `segments`."""
    pieces = _intervals(ds.t, keep, gap)
    total = sum(b - a for a, b in pieces)
    lines.append(
        f"  kept {int(keep.sum())} of {len(ds)} rows in {len(pieces)} segment(s): "
        f"{_describe(pieces)} ({total:.1f} s)"
    )
    for k, v in sorted(reasons.items(), key=lambda kv: -kv[1]):
        lines.append(f"  dropped {v:6d} rows: {k}")
    out = ds.select(keep)
    for k, v in reasons.items():
        out.drop_reasons[k] = out.drop_reasons.get(k, 0) + v
    out.dropped_rows = ds.dropped_rows + sum(reasons.values())
    out.segments = [*ds.segments, *lines]
    return out
