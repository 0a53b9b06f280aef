"""Telemetry logs in the standard .tlog format: per frame, an 8-byte big-endian unix time in microseconds,
then the raw MAVLink frame. Written with one os.write per datagram so a killed process leaves a file that
pymavlink's mavlogdump.py reads."""

from __future__ import annotations

import os
import struct
import time
import warnings
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from bridge.errors import UserError
from bridge.framing import decode_frame, split_datagram
from bridge.stats import LinkStats

_STAMP = struct.Struct(">Q")


class TlogWriter:
    """Appends every frame crossing a link to a .tlog file (unbuffered: each datagram is one os.write)."""

    def __init__(self, path: str | Path, append: bool = False):
        self.path = Path(path)
        flags = os.O_WRONLY | os.O_CREAT | (os.O_APPEND if append else os.O_TRUNC)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fd: int | None = os.open(self.path, flags, 0o644)
        except OSError as exc:
            raise UserError(f"cannot open telemetry log {self.path} for writing: {exc.strerror}") from None
        self.frames = 0
        self.bytes = 0

    def write_frames(self, frames: Iterable[bytes], time_us: int | None = None) -> None:
        """Write frames that crossed the link together, stamped with time_us (unix us; default now)."""
        if self._fd is None:
            return
        stamp = _STAMP.pack(time.time_ns() // 1000 if time_us is None else time_us)
        parts = []
        for frame in frames:
            parts.append(stamp)
            parts.append(frame)
        if not parts:
            return
        record = b"".join(parts)
        os.write(self._fd, record)
        self.frames += len(parts) // 2
        self.bytes += len(record)

    def write_messages(self, msgs: Iterable[Any], time_us: int | None = None) -> None:
        """Write already-packed pymavlink messages (their get_msgbuf())."""
        self.write_frames((bytes(m.get_msgbuf()) for m in msgs), time_us)

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._fd is not None:
            os.close(self._fd)
            self._fd = None

    @property
    def closed(self) -> bool:
        """True once closed."""
        return self._fd is None

    def __enter__(self) -> TlogWriter:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_tlog(tlog: TlogWriter | str | Path | None) -> TlogWriter | None:
    """A TlogWriter from a writer, a path, or None."""
    if tlog is None or isinstance(tlog, TlogWriter):
        return tlog
    return TlogWriter(tlog)


def read_tlog(path: str | Path) -> Iterator[tuple[float, Any]]:
    """Yield (unix time s, pymavlink message) for every valid frame of a .tlog file.

    A truncated last record (a killed writer) gives a warning and the frames before it. A missing, empty
    or non-tlog file is a UserError.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise UserError(f"telemetry log {p} does not exist") from None
    except IsADirectoryError:
        raise UserError(f"telemetry log {p} is a directory, not a .tlog file") from None
    except OSError as exc:
        raise UserError(f"cannot read telemetry log {p}: {exc.strerror}") from None
    if not data:
        raise UserError(f"telemetry log {p} is empty", hint="was the flight started? is this the right file?")
    if len(data) < 8 + 12 or data[8] not in (0xFD, 0xFE):
        raise UserError(
            f"{p} is not a .tlog telemetry log (no timestamped MAVLink frame at its start)",
            hint="a .tlog holds an 8-byte big-endian time then a raw MAVLink frame, repeated",
        )
    return _iter_tlog(p, data)


def _iter_tlog(path: Path, data: bytes) -> Iterator[tuple[float, Any]]:
    stats = LinkStats()
    n = len(data)
    i = 0
    while i < n:
        if n - i < 8 + 3:
            warnings.warn(f"{path}: truncated last record ({n - i} bytes) ignored", stacklevel=2)
            return
        stx = data[i + 8]
        if stx == 0xFD:
            length = 12 + data[i + 9] + (13 if data[i + 10] & 0x01 else 0)
        elif stx == 0xFE:
            length = 8 + data[i + 9]
        else:
            i += 1  # not a record start: resynchronise byte by byte, like pymavlink's log reader
            continue
        end = i + 8 + length
        if end > n:
            warnings.warn(f"{path}: truncated last record ({n - i} bytes) ignored", stacklevel=2)
            return
        unknown = stats.unknown_id
        frames = split_datagram(data[i + 8 : end], stats)
        if not frames:
            # A well-formed frame of another dialect is skipped whole; a corrupt one byte by byte.
            i = end if stats.unknown_id > unknown else i + 1
            continue
        spec, frame, header_len, signature_len = frames[0]
        try:
            msg = decode_frame(frame, header_len, signature_len, spec)
        except Exception:
            i = end
            continue
        t_us = _STAMP.unpack_from(data, i)[0]
        i = end
        yield t_us * 1e-6, msg
