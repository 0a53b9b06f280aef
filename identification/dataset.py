"""Flight logs in, one Dataset out: read each log (format from its content), keep its airborne rows (or
the windows you chose), and join several logs into one table.

`load_dataset(path)` reads one log: our .tlog, a PX4 ULog (.ulg), an ArduPilot DataFlash log (.bin) or a
CSV/Parquet table (README: "Tables from anywhere"), chosen by the file's first bytes (the extension only
breaks ties), then keeps the airborne rows (identification.segmentation). `load_datasets(paths, windows)`
does so for several logs and concatenates them. The table's columns and units: identification.table.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from bridge.errors import UserError
from identification.flight_evidence import no_flight_evidence, raise_no_flight
from identification.readers.registry import detect_format, reader_for
from identification.segmentation import SegmentationSettings, Window, segment
from identification.table import (  # noqa: F401  (re-exported: the table's names live in identification.table)
    AUX_NAMES,
    FORMATS,
    INPUT_NAMES,
    STATE_NAMES,
    TARGET_NAMES,
    TARGET_SOURCES,
    Dataset,
    FlightInfo,
    file_sha256,
)
from identification.targets import SensorTargetSettings

__all__ = ["Dataset", "FlightInfo", "detect_format", "file_sha256", "load_dataset", "load_datasets"]


def load_dataset(
    path: str | Path,
    targets: str = "truth",
    motor_curve: Any = None,
    rate_hz: float | None = None,
    *,
    gravity: float | None = None,
    airborne: bool = True,
    windows: Sequence[Window] | None = None,
    segmentation: SegmentationSettings | None = None,
    sensor_settings: SensorTargetSettings | None = None,
) -> Dataset:
    """Read one flight log into a Dataset (format from the file's content; targets 'truth' or 'sensors').

    motor_curve: for logs without rotor speeds (or to use the motor commands instead): a vehicle name or
    file, 'slope,offset' (rad/s per unit throttle, rad/s), or an object with speed_for_throttle().
    rate_hz: the common timeline's rate (default: the log's natural one). gravity: m/s^2 added to the
    rotated specific force for sensor targets (default 9.80665). airborne: keep only the rows the
    segmentation finds airborne (default); windows: (start, end) log seconds to keep instead.
    What the segmentation kept and why rows were dropped: `dataset.segments` (lines to print).
    sensor_settings: the differentiator of sensor targets (logs with an IMU; a table brings its own targets).
    Raw step targets (our .tlog with weak_form.RAW_SENSOR_TARGETS) come as two rows per step, the step's
    Gauss nodes (Dataset.at_step_nodes).
    """
    if targets not in TARGET_SOURCES:
        raise UserError(f"targets must be one of {', '.join(TARGET_SOURCES)}, got {targets!r}")
    if rate_hz is not None and not (np.isfinite(rate_hz) and rate_hz > 0):
        raise UserError(f"rate must be a positive number of Hz, got {rate_hz}")
    fmt = detect_format(path)
    reader = reader_for(fmt)
    extra = {"sensor_settings": sensor_settings} if sensor_settings is not None and fmt != "table" else {}
    ds = reader(
        Path(path), targets=targets, motor_curve=motor_curve, rate_hz=rate_hz, gravity=gravity, **extra
    )
    if airborne or windows:
        kept = segment(ds, windows=windows, settings=segmentation)
        if not len(kept) and not windows:
            evidence = no_flight_evidence(ds.t, ds.aux, ds.xi[:, 2])
            if evidence is not None:
                raise_no_flight(f"flight log {path}", evidence)
        ds = kept
    return ds.at_step_nodes()  # rows that are steps' means: two node rows each (weak_form.node_groups)


def load_datasets(
    paths: Sequence[str | Path],
    windows: Sequence[Window] | None = None,
    **options: Any,
) -> Dataset:
    """Several logs (each read and segmented by load_dataset with the same options) as one Dataset.

    windows apply to every log (log seconds); a log that keeps no row is an error naming it.
    """
    if not paths:
        raise UserError(
            "no flight log given", hint="pass one or more .tlog, .ulg, .bin, .csv or .parquet files"
        )
    parts = []
    for p in paths:
        d = load_dataset(p, windows=windows, **options)
        if len(d) == 0:
            raise UserError(
                f"flight log {p} kept no rows",
                hint="check its airborne part (see the drop reasons above) or the --window you gave",
            )
        parts.append(d)
    measured = [str(p) for p, d in zip(paths, parts, strict=True) if not d.u_from_throttle]
    if measured and len(measured) < len(parts):
        raise UserError(
            f"some logs have rotor speeds ({', '.join(measured)}) and some only motor commands: "
            "their u would not be the same quantity",
            hint="pass --motor-curve (your motor's throttle -> rad/s) so every log gives rotor speeds",
        )
    return parts[0] if len(parts) == 1 else Dataset.concat(parts)
