"""Which reader reads which log: the format from a file's first bytes (or its extension for tables) and
the reader function of each format. identification.dataset is the interface that uses it."""

from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path

from bridge.errors import UserError

ULOG_MAGIC = b"ULog\x01\x12\x35"
DATAFLASH_MAGIC = b"\xa3\x95\x80"  # a FMT record: every DataFlash log starts with them
PARQUET_MAGIC = b"PAR1"
TABLE_SUFFIXES = (".csv", ".parquet")

# format -> (module, function) of its reader; every reader takes (path, targets=, motor_curve=,
# rate_hz=, gravity=) and returns an identification.table.Dataset
READERS = {
    "tlog": ("identification.readers.tlog", "read_tlog_dataset"),
    "ulog": ("identification.readers.ulog", "read_ulog_dataset"),
    "dataflash": ("identification.readers.dataflash", "read_dataflash_dataset"),
    "table": ("identification.readers.table_file", "read_table_dataset"),
}


def reader_for(fmt: str) -> Callable:
    """The reader function of a format name (one of READERS)."""
    module, name = READERS[fmt]
    return getattr(importlib.import_module(module), name)


def detect_format(path: str | Path) -> str:
    """'tlog', 'ulog', 'dataflash' or 'table' (CSV/Parquet) from the file's first bytes; UserError if none."""
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
    if head.startswith(PARQUET_MAGIC) or p.suffix.lower() in TABLE_SUFFIXES:
        return "table"
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
        hint="supported: MAVLink .tlog, PX4 ULog .ulg, ArduPilot DataFlash .bin, a .csv or .parquet table",
    )
