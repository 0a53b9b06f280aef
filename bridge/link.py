"""UDP MAVLink 2 links opened from strings like `udp:127.0.0.1:4560`: one datagram per send, every frame of
a received datagram parsed, bad bytes dropped and counted (never raised)."""

from __future__ import annotations

import errno
import os
import re
import select
import socket
import struct
import time
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Any

from bridge.errors import UserError
from bridge.framing import decode_frame, pack_frame, split_datagram
from bridge.signing import Signing
from bridge.stats import LinkStats
from bridge.tlog import TlogWriter, open_tlog

ENDPOINT_FORM = "udp:HOST:PORT (e.g. udp:127.0.0.1:4560; udpin:/udpout: also accepted)"
_ENDPOINT_RE = re.compile(r"^(udp|udpin|udpout)(?:://|:)(\[[^\]]+\]|[^:\s]*):(\d+)$")
MAX_DATAGRAM = 65535
_DONTWAIT = socket.MSG_DONTWAIT
# Waits at least this long (s) block in recvfrom under SO_RCVTIMEO; shorter ones poll() first, as the kernel
# rounds SO_RCVTIMEO up to its tick (4 ms at HZ=250), too coarse for the real-time pacing's sub-step waits.
RCVTIMEO_MIN_S = 0.05
# A lockstep peer answers within tens of microseconds. Sleeping in the kernel for that answer costs a wake-up
# (on an idle core of a virtual machine: the hypervisor's too); polling for it first keeps the process on its
# core. sched_yield() between polls hands the core to the peer when both share it.
LOCKSTEP_SPIN_S = 200e-6
_TIMEVAL = struct.Struct("@ll")  # struct timeval (tv_sec, tv_usec) on LP64 Linux


@dataclass(frozen=True)
class Endpoint:
    """A UDP address. kind: 'udp' (plain), 'udpin' (listen here) or 'udpout' (send there)."""

    host: str
    port: int
    kind: str = "udp"

    def __str__(self) -> str:
        return f"{self.kind}:{self.host}:{self.port}"

    @property
    def address(self) -> tuple[str, int]:
        """(host, port) as socket calls take it."""
        return (self.host, self.port)


def parse_endpoint(text: str) -> Endpoint:
    """Parse `udp:HOST:PORT` (or `udpin:`/`udpout:`, optionally with `//`) into an Endpoint."""
    m = _ENDPOINT_RE.match(text.strip()) if isinstance(text, str) else None
    if m is None:
        raise UserError(f"bad link address {text!r}", hint=f"expected {ENDPOINT_FORM}")
    kind, host, port_text = m.groups()
    host = host.strip("[]") or "0.0.0.0"
    port = int(port_text)
    if not 0 <= port <= 65535:
        raise UserError(
            f"bad port {port} in link address {text!r}",
            hint=f"a UDP port is 0..65535; expected {ENDPOINT_FORM}",
        )
    return Endpoint(host, port, kind)


def _resolve(endpoint: Endpoint) -> tuple[str, int]:
    try:
        host = socket.gethostbyname(endpoint.host)
    except OSError:
        raise UserError(f"cannot resolve host {endpoint.host!r} of link address {endpoint}") from None
    return (host, endpoint.port)


def _as_endpoint(value: Endpoint | str | None) -> Endpoint | None:
    if value is None or isinstance(value, Endpoint):
        return value
    return parse_endpoint(value)


def bind_hint(errno_value: int | None) -> str:
    """What to do when binding a UDP address failed with this errno."""
    if errno_value == errno.EADDRINUSE:
        return "another process (an earlier SITL?) uses that port: stop it or pick another (udp:HOST:PORT)"
    if errno_value == errno.EADDRNOTAVAIL:
        return "that host is not an address of this machine: use 127.0.0.1 (this machine) or 0.0.0.0 (all)"
    if errno_value == errno.EACCES:
        return "ports below 1024 need privileges: pick a port from 1024 to 65535"
    return "give another address as udp:HOST:PORT"


class UdpLink:
    """A MAVLink 2 (common dialect) link over one UDP socket.

    Bound to `local` if given (else an ephemeral port), sending to `remote` if given, else to the last peer
    that sent a valid frame. Every frame sent or received is written to `tlog` if given.
    """

    def __init__(
        self,
        local: Endpoint | str | None = None,
        remote: Endpoint | str | None = None,
        system_id: int = 1,
        component_id: int = 1,
        signing: Signing | None = None,
        tlog: TlogWriter | str | None = None,
        accept_system_ids: Iterable[int] | None = None,
    ):
        local = _as_endpoint(local)
        remote = _as_endpoint(remote)
        self.system_id = int(system_id)
        self.component_id = int(component_id)
        self.signing = signing
        self.accept_system_ids = frozenset(accept_system_ids) if accept_system_ids is not None else None
        self.stats = LinkStats()
        self.remote = _resolve(remote) if remote is not None else None
        self.peer: tuple[str, int] | None = None
        self.seq = 0
        self.last_recv_time = 0.0  # time.monotonic() of the last datagram with a valid frame
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 1 << 20)
            if local is not None:
                self._sock.bind(_resolve(local))
            else:
                loopback = self.remote is not None and self.remote[0].startswith("127.")
                self._sock.bind(("127.0.0.1" if loopback else "0.0.0.0", 0))
        except OSError as exc:
            self._sock.close()
            where = str(local) if local is not None else "a free local UDP port"
            raise UserError(f"cannot listen on {where}: {exc.strerror}", hint=bind_hint(exc.errno)) from None
        self.local = Endpoint(*self._sock.getsockname()[:2])
        # The socket stays in blocking mode with no Python timeout (which would add a poll() before each send
        # and receive). A wait of RCVTIMEO_MIN_S or more is ONE blocking recvfrom bounded by the kernel's
        # SO_RCVTIMEO (set again only when the wait changes: the lockstep loops wait the same every step);
        # a shorter one is a poll() then a MSG_DONTWAIT recvfrom. Every sendto is one MSG_DONTWAIT syscall.
        self._poller = select.poll()
        self._poller.register(self._sock.fileno(), select.POLLIN)
        self._rcvtimeo = 0.0  # s, the socket's SO_RCVTIMEO (0: none)
        self.spin_s = 0.0  # s wall: poll this long without sleeping before a blocking wait (LOCKSTEP_SPIN_S)
        self._owns_tlog = tlog is not None and not isinstance(tlog, TlogWriter)
        try:
            self.tlog = open_tlog(tlog)
        except UserError:
            self._sock.close()
            raise

    # -- sending -------------------------------------------------------------------------------------
    def pack(self, msgs: Iterable[Any]) -> list[bytes]:
        """Frames (bytes) for messages, with this link's ids, sequence numbers and signing."""
        frames = []
        seq = self.seq
        for msg in msgs:
            if isinstance(msg, (list, tuple)):  # e.g. encode_raw_rpm's four messages inside a step's list
                for sub in msg:
                    frames.append(pack_frame(sub, seq, self.system_id, self.component_id, self.signing))
                    seq = (seq + 1) & 0xFF
                continue
            frames.append(pack_frame(msg, seq, self.system_id, self.component_id, self.signing))
            seq = (seq + 1) & 0xFF
        self.seq = seq
        return frames

    def send(self, msgs: Any) -> None:
        """Send messages (a list, nested lists flattened, or one) as ONE datagram to remote or last peer."""
        if not isinstance(msgs, (list, tuple)):
            msgs = [msgs]
        self.send_frames(self.pack(msgs))

    def send_frames(self, frames: list[bytes]) -> None:
        """Send already-packed frames as one datagram (logged to the tlog)."""
        if self._send_datagram(b"".join(frames)):
            self.stats.frames_sent += len(frames)
            if self.tlog is not None:
                self.tlog.write_frames(frames)

    def send_raw(self, data: bytes) -> None:
        """Send raw bytes as one datagram, unlogged and uncounted as frames (fuzzing, tests)."""
        self._send_datagram(data)

    def _send_datagram(self, data: bytes) -> bool:
        target = self.remote or self.peer
        if target is None:
            self.stats.no_peer += 1
            return False
        try:
            self._sock.sendto(data, _DONTWAIT, target)
        except OSError:
            self.stats.send_errors += 1
            return False
        self.stats.datagrams_sent += 1
        self.stats.bytes_sent += len(data)
        return True

    # -- receiving -----------------------------------------------------------------------------------
    def _datagram(self, timeout: float | None) -> tuple[bytes, tuple[str, int]] | None:
        if self.spin_s > 0.0 and (timeout is None or timeout > 0.0):
            got = self._spin(self.spin_s if timeout is None or timeout > self.spin_s else timeout)
            if got is not None:
                return got
        try:
            if timeout is None or timeout >= RCVTIMEO_MIN_S:
                limit = 0.0 if timeout is None else timeout
                if limit != self._rcvtimeo:
                    self._set_rcvtimeo(limit)
                return self._sock.recvfrom(MAX_DATAGRAM)  # EAGAIN (BlockingIOError) when the limit passes
            if timeout > 0.0 and not self._poller.poll(timeout * 1000.0):
                return None
            return self._sock.recvfrom(MAX_DATAGRAM, _DONTWAIT)
        except (BlockingIOError, ConnectionError):  # ConnectionError: an ICMP unreachable came back
            return None

    def _spin(self, seconds: float) -> tuple[bytes, tuple[str, int]] | None:
        """The next datagram if one comes within seconds (wall), polled without sleeping; else None."""
        recvfrom, end = self._sock.recvfrom, time.monotonic() + seconds
        while True:
            try:
                return recvfrom(MAX_DATAGRAM, _DONTWAIT)
            except BlockingIOError:
                if time.monotonic() >= end:
                    return None
                os.sched_yield()
            except ConnectionError:  # an ICMP unreachable came back
                return None

    def _set_rcvtimeo(self, seconds: float) -> None:
        """Bound a blocking recvfrom to seconds (0: no bound), as the kernel's SO_RCVTIMEO (a timeval)."""
        whole = int(seconds)
        self._sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO,
                              _TIMEVAL.pack(whole, int((seconds - whole) * 1e6)))
        self._rcvtimeo = seconds

    def recv(self, timeout: float | None = 0.0) -> list[Any]:
        """Messages of ONE datagram, waiting up to timeout s (0: don't wait, None: forever); [] if none.

        Bad frames are dropped and counted in .stats, never raised.
        """
        got = self._datagram(timeout)
        if got is None:
            return []
        return self._decode(self._accept(*got))

    def recv_frames(self, timeout: float | None = 0.0) -> list[tuple[Any, bytes]]:
        """Like recv, but [(message, raw frame)] (e.g. to forward frames unchanged)."""
        got = self._datagram(timeout)
        if got is None:
            return []
        out = []
        for item in self._accept(*got):
            decoded = self._decode([item])
            if decoded:
                out.append((decoded[0], item[1]))
        return out

    def recv_split(self, timeout: float | None = 0.0) -> list[tuple]:
        """Like recv, but the checked, undecoded frames [(spec, frame, header_len, signature_len)] of
        bridge.framing.split_datagram (for clients that unpack payloads without building messages)."""
        got = self._datagram(timeout)
        if got is None:
            return []
        return self._accept(*got)

    def drain(self, max_datagrams: int = 1000) -> list[Any]:
        """All messages of the datagrams already queued (no waiting), up to max_datagrams."""
        out: list[Any] = []
        for _ in range(max_datagrams):
            got = self._datagram(0.0)
            if got is None:
                break
            out.extend(self._decode(self._accept(*got)))
        return out

    def drain_split(self, max_datagrams: int = 1000) -> list[tuple]:
        """Like drain, as recv_split gives frames."""
        out: list[tuple] = []
        for _ in range(max_datagrams):
            got = self._datagram(0.0)
            if got is None:
                break
            out.extend(self._accept(*got))
        return out

    def handle_datagram(self, data: bytes, addr: tuple[str, int]) -> list[Any]:
        """Parse a datagram received from addr (as recv does); useful when the caller owns the socket read."""
        return self._decode(self._accept(data, addr))

    def _accept(self, data: bytes, addr: tuple[str, int]) -> list[tuple]:
        """Split and check a datagram; count, set the peer, log the valid frames."""
        stats = self.stats
        stats.datagrams_received += 1
        stats.bytes_received += len(data)
        frames = split_datagram(data, stats, self.signing, self.accept_system_ids)
        if frames:
            stats.frames_received += len(frames)
            self.peer = addr
            self.last_recv_time = time.monotonic()
            if self.tlog is not None:
                self.tlog.write_frames([f[1] for f in frames])
        return frames

    def _decode(self, frames: list[tuple]) -> list[Any]:
        out = []
        for spec, frame, header_len, signature_len in frames:
            try:
                out.append(decode_frame(frame, header_len, signature_len, spec))
            except Exception:  # a payload pymavlink cannot instantiate: dropped like any bad frame
                self.stats.bad_payload += 1
                self.stats.frames_received -= 1
        return out

    # -- plumbing ------------------------------------------------------------------------------------
    def fileno(self) -> int:
        """The socket's file descriptor (for select/poll)."""
        return self._sock.fileno()

    @property
    def closed(self) -> bool:
        """True once close() was called."""
        return self._sock.fileno() < 0

    def close(self) -> None:
        """Close the socket (the tlog is closed too if this link opened it from a path)."""
        self._sock.close()
        if self._owns_tlog and self.tlog is not None:
            self.tlog.close()

    def __enter__(self) -> UdpLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"UdpLink(local={self.local}, remote={self.remote}, peer={self.peer})"
