"""Counters of what crossed a link and what was dropped, by reason."""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields

# Frame-level reasons for dropping received bytes; each rejected frame (or run of garbage) counts once.
DROP_REASONS = (
    "garbage",  # bytes that do not start a frame (counted once per run)
    "truncated",  # a frame whose length runs past the end of the datagram
    "bad_crc",
    "unknown_id",  # a message id outside the common dialect (its CRC cannot be checked)
    "bad_payload",  # a payload pymavlink cannot turn into a message
    "unsigned",  # signing on, frame not signed
    "bad_signature",  # signing on, signature does not match the key
    "replayed",  # signing on, timestamp not newer than the stream's last accepted one
    "bad_timestamp",  # signing on, a new stream whose timestamp is far from our clock
    "wrong_system",  # a system id the link does not accept
)


@dataclass
class LinkStats:
    """What one link sent and received (datagrams, frames, bytes) and what it dropped, by reason."""

    datagrams_sent: int = 0
    frames_sent: int = 0
    bytes_sent: int = 0
    send_errors: int = 0  # sendto failed (no route, buffer full, ...)
    no_peer: int = 0  # send() with no remote and nobody heard from yet: nothing sent
    datagrams_received: int = 0
    frames_received: int = 0  # valid frames handed to the caller
    bytes_received: int = 0
    garbage: int = 0
    garbage_bytes: int = 0  # bytes skipped while resynchronising (not a drop reason by itself)
    truncated: int = 0
    bad_crc: int = 0
    unknown_id: int = 0
    bad_payload: int = 0
    unsigned: int = 0
    bad_signature: int = 0
    replayed: int = 0
    bad_timestamp: int = 0
    wrong_system: int = 0

    @property
    def sent(self) -> int:
        """Frames sent."""
        return self.frames_sent

    @property
    def received(self) -> int:
        """Valid frames received."""
        return self.frames_received

    @property
    def dropped(self) -> int:
        """Received frames (or garbage runs) dropped, all reasons."""
        return sum(getattr(self, name) for name in DROP_REASONS)

    def drops(self) -> dict[str, int]:
        """Non-zero drop counts by reason."""
        return {name: getattr(self, name) for name in DROP_REASONS if getattr(self, name)}

    def as_dict(self) -> dict[str, int]:
        """All counters as a plain dict (for JSON/YAML reports)."""
        return asdict(self)

    def merge(self, other: LinkStats) -> LinkStats:
        """Sum of two links' counters."""
        return LinkStats(**{f.name: getattr(self, f.name) + getattr(other, f.name) for f in fields(self)})

    def summary(self) -> str:
        """One line: sent, received, dropped with reasons."""
        drops = self.drops()
        detail = f" ({', '.join(f'{k} {v}' for k, v in drops.items())})" if drops else ""
        errors = f", send errors {self.send_errors}" if self.send_errors else ""
        return (
            f"sent {self.frames_sent} frames/{self.datagrams_sent} dgrams, "
            f"recv {self.frames_received} frames/{self.datagrams_received} dgrams, "
            f"dropped {self.dropped}{detail}{errors}"
        )
