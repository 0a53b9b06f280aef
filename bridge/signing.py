"""MAVLink 2 message signing that verifies a signature BEFORE it records the stream's timestamp.

pymavlink 2.4.50 (`MAVLink.check_signature`) stores a stream's timestamp first and checks the signature
after, so one forged frame with a far-future timestamp makes every later genuine frame look like a replay.
Here a stream's timestamp only moves when a frame's signature is valid and its timestamp is acceptable.
"""

from __future__ import annotations

import hashlib
import hmac
import time
from pathlib import Path

from bridge.errors import UserError

# MAVLink signing timestamps count 10 us units since 2015-01-01 00:00:00 UTC.
SIGNING_EPOCH_UNIX_S = 1420070400
TICKS_PER_S = 100_000
KEY_LEN = 32
SIGNATURE_LEN = 13


def signing_timestamp_now() -> int:
    """The current time in MAVLink signing units (10 us since 2015-01-01 UTC)."""
    return (time.time_ns() // 10_000) - SIGNING_EPOCH_UNIX_S * TICKS_PER_S


class Signing:
    """A secret key and link id: signs outgoing MAVLink 2 frames and verifies incoming ones.

    Incoming frames are accepted per stream (system id, component id, link id) only if the signature is
    valid AND the timestamp is newer than the stream's last accepted one; a new stream's timestamp must be
    within `max_skew_s` of our clock. Only then is the stream's timestamp updated.
    """

    def __init__(self, key: bytes, link_id: int = 0, max_skew_s: float = 60.0):
        if not isinstance(key, (bytes, bytearray)) or len(key) != KEY_LEN:
            raise UserError(
                f"a MAVLink signing key must be exactly {KEY_LEN} bytes (got {len(key)})",
                hint="make one with: python -c \"import os; open('key.bin','wb').write(os.urandom(32))\"",
            )
        if not 0 <= int(link_id) <= 255:
            raise UserError(f"signing link id must be 0..255 (got {link_id})")
        self.key = bytes(key)
        self.link_id = int(link_id)
        self.max_skew_ticks = int(max_skew_s * TICKS_PER_S)
        self._last_sent = 0
        self._streams: dict[tuple[int, int, int], int] = {}

    @classmethod
    def from_file(cls, path: str | Path, link_id: int = 0) -> Signing:
        """Signing with the key in a file (32 raw bytes, or 64 hex digits)."""
        return cls(load_key(path), link_id)

    def sign(self, frame: bytes) -> bytes:
        """Append the 13-byte signature block to a frame (incompat flag 0x01 already set, CRC included)."""
        ts = signing_timestamp_now()
        if ts <= self._last_sent:
            ts = self._last_sent + 1
        self._last_sent = ts
        block = bytes((self.link_id,)) + ts.to_bytes(6, "little")
        signature = hashlib.sha256(self.key + frame + block).digest()[:6]
        return frame + block + signature

    def verify(self, frame: bytes, system_id: int, component_id: int) -> str | None:
        """None when a received frame is acceptable, else the drop reason (a LinkStats field name)."""
        if len(frame) < SIGNATURE_LEN + 12 or frame[0] != 0xFD or not frame[2] & 0x01:
            return "unsigned"
        expected = hashlib.sha256(self.key + frame[:-6]).digest()[:6]
        if not hmac.compare_digest(expected, frame[-6:]):
            return "bad_signature"
        link_id = frame[-SIGNATURE_LEN]
        ts = int.from_bytes(frame[-12:-6], "little")
        stream = (system_id, component_id, link_id)
        last = self._streams.get(stream)
        if last is None:
            now = signing_timestamp_now()
            if ts > now + self.max_skew_ticks or ts < now - self.max_skew_ticks:
                return "bad_timestamp"
        elif ts <= last:
            return "replayed"
        self._streams[stream] = ts
        if ts > self._last_sent:  # as the MAVLink spec asks: never send older than what we accepted
            self._last_sent = ts
        return None

    def stream_timestamp(self, system_id: int, component_id: int, link_id: int = 0) -> int | None:
        """Last accepted timestamp of a stream (10 us units since 2015), None if never heard."""
        return self._streams.get((system_id, component_id, link_id))


def load_key(path: str | Path) -> bytes:
    """Read a 32-byte signing key: a file of exactly 32 raw bytes, or 64 hex digits (whitespace ignored)."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise UserError(f"signing key file {p} does not exist", hint="give a 32-byte key file") from None
    except OSError as exc:
        raise UserError(f"cannot read signing key file {p}: {exc.strerror}") from None
    if len(data) == KEY_LEN:
        return data
    try:
        text = data.decode("ascii").strip()
        if len(text) == 2 * KEY_LEN:
            return bytes.fromhex(text)
    except (UnicodeDecodeError, ValueError):
        pass
    raise UserError(
        f"signing key file {p} holds {len(data)} bytes; "
        f"it must be exactly {KEY_LEN} raw bytes or {2 * KEY_LEN} hex digits",
        hint="make one with: python -c \"import os; open('key.bin','wb').write(os.urandom(32))\"",
    )
