"""Does a log hold a flight at all? A log that never armed (or, without an arming state, never ran its
motors and never left the ground) gives no model of flight, and the tool says so with the evidence.

`NoFlightError` is a UserError (exit 2) that callers can tell apart from other bad input (bench/real_logs.py
reports it as "no flight in the log"). `no_flight_evidence(t, aux, z)` reads the side columns a reader
made over the log's whole timeline (identification.table: `armed`, `throttle`, `accel_dev`) and the height
z (m, NED) and returns the evidence lines when the log holds no flight, else None.
"""

from __future__ import annotations

import numpy as np

from bridge.errors import UserError

MOTORS_AT_REST = 0.05  # a mean motor command (fraction of full) never above this: the motors never ran
FLAT_HEIGHT_M = 0.15  # m: a height range below this never left the ground (the segmentation's min height)


class NoFlightError(UserError):
    """A log that holds no flight: never armed, or motors never run and never off the ground."""


def _finite(v: np.ndarray | None) -> np.ndarray | None:
    if v is None:
        return None
    v = np.asarray(v, dtype=float)
    return v if np.isfinite(v).any() else None


def no_flight_evidence(t: np.ndarray, aux: dict[str, np.ndarray], z: np.ndarray | None) -> list[str] | None:
    """Evidence lines when the rows (times t s, side columns aux, height z m NED) hold no flight, else None.

    No flight: the log's arming state never says armed; or, without one, the motor commands never rise
    above MOTORS_AT_REST of full and the height never varies by FLAT_HEIGHT_M."""
    t = np.asarray(t, dtype=float)
    armed = _finite(aux.get("armed"))
    throttle = _finite(aux.get("throttle"))
    mean_cmd = None if throttle is None else np.nanmean(throttle.reshape(len(t), -1), axis=1)
    zs = None if z is None else np.asarray(z, dtype=float)
    zs = zs[np.isfinite(zs)] if zs is not None else None
    span = float(zs.max() - zs.min()) if zs is not None and len(zs) else None
    lines = [f"log time {t.min():.1f}-{t.max():.1f} s" if len(t) else "no samples"]
    never_armed = armed is not None and not (armed > 0.5).any()
    if armed is not None:
        n = int(np.isfinite(armed).sum())
        count = f"armed in {int((armed > 0.5).sum())} of {n} samples"
        lines.append(f"never armed in this log (arming state {count})" if never_armed else f"arming: {count}")
    if mean_cmd is not None:
        lines.append(f"motor commands: at most {np.nanmax(mean_cmd):.3f} of full (mean of the motors)")
    if span is not None:
        lines.append(f"height: varies by {span:.3f} m over the log")
    dev = _finite(aux.get("accel_dev"))
    if dev is not None:
        lines.append(f"accelerometer: | |f| - g | at most {np.nanmax(dev):.2f} m/s^2")
    motors_idle = mean_cmd is not None and np.nanmax(mean_cmd) <= MOTORS_AT_REST
    flat = span is not None and span < FLAT_HEIGHT_M
    if never_armed or (armed is None and motors_idle and flat):
        return lines
    return None


def raise_no_flight(source: str, evidence: list[str], also: str = "") -> None:
    """Raise NoFlightError for the log at source with its evidence lines (and what else was missing)."""
    more = f"; besides, {also}" if also else ""
    raise NoFlightError(
        f"{source} holds no flight to learn from or validate on: " + "; ".join(evidence) + more,
        hint="give a log of a flight (armed, motors running, airborne)",
    )
