"""MAVLink 2 over a TCP byte stream, listening side: what PX4's `simulator_mavlink -c PORT` connects to.

`TcpLink` listens on `tcp:HOST:PORT` and serves one connection at a time (a second one is closed at once;
a restarted autopilot reconnects after its old connection ended). It offers the calls of
bridge.link.UdpLink that a server uses (pack, send_frames, recv_split, stats, seq, local, peer, close), with
the same bad-frame counting: the stream is split into frames by bridge.framing.split_stream, a frame cut off
at the end of a read waits for the next read. A send counts as one "datagram" in the stats, a read as one
received "datagram".
"""

from __future__ import annotations

import re
import select
import socket
import time
from collections.abc import Callable, Iterable

from bridge.errors import UserError
from bridge.framing import split_stream
from bridge.link import Endpoint, UdpLink
from bridge.signing import Signing
from bridge.stats import LinkStats
from bridge.tlog import TlogWriter, open_tlog

TCP_FORM = "tcp:HOST:PORT (e.g. tcp:127.0.0.1:4560, where PX4 instance 0 connects)"
_TCP_RE = re.compile(r"^tcp(?:://|:)(\[[^\]]+\]|[^:\s]*):(\d+)$")
READ_SIZE = 1 << 16
SEND_TIMEOUT_S = 5.0  # wall s: a peer that takes no bytes for this long is dropped
MAX_PENDING = 1 << 16  # bytes kept of an unfinished frame: more is garbage, not a frame (max frame 280 B)


def is_tcp_address(text: str) -> bool:
    """True if text names a TCP address (`tcp:...`)."""
    return isinstance(text, str) and text.strip().lower().startswith("tcp:")


def parse_tcp_endpoint(text: str) -> Endpoint:
    """Parse `tcp:HOST:PORT` into an Endpoint of kind 'tcp' (UserError naming the form otherwise)."""
    m = _TCP_RE.match(text.strip()) if isinstance(text, str) else None
    if m is None:
        raise UserError(f"bad TCP address {text!r}", hint=f"expected {TCP_FORM}")
    host = m.group(1).strip("[]") or "0.0.0.0"
    port = int(m.group(2))
    if not 0 <= port <= 65535:
        raise UserError(f"bad port {port} in TCP address {text!r}",
                        hint=f"a TCP port is 0..65535; {TCP_FORM}")
    return Endpoint(host, port, "tcp")


class TcpLink:
    """A listening TCP MAVLink 2 link (common dialect) serving one peer connection at a time.

    `on_change(text)` is called with "connected HOST:PORT" when a peer connects and "disconnected: WHY"
    when it goes away (end of stream, reset, or it stopped reading for SEND_TIMEOUT_S).
    """

    def __init__(
        self,
        local: Endpoint,
        system_id: int = 1,
        component_id: int = 1,
        signing: Signing | None = None,
        tlog: TlogWriter | str | None = None,
        accept_system_ids: Iterable[int] | None = None,
        on_change: Callable[[str], None] | None = None,
    ):
        self.system_id = int(system_id)
        self.component_id = int(component_id)
        self.signing = signing
        self.accept_system_ids = frozenset(accept_system_ids) if accept_system_ids is not None else None
        self.on_change = on_change
        self.stats = LinkStats()
        self.seq = 0
        self.peer: tuple[str, int] | None = None  # the connected peer's address (assignments are ignored)
        self.connections = 0  # peers accepted so far
        self.refused = 0  # connections closed at once because a peer was connected
        self.last_recv_time = 0.0
        self._conn: socket.socket | None = None
        self._conn_peer: tuple[str, int] | None = None
        self._pending = b""
        self._server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        try:
            self._server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._server.bind((socket.gethostbyname(local.host), local.port))
            self._server.listen(1)
        except OSError as exc:
            self._server.close()
            raise UserError(
                f"cannot listen on {local}: {exc.strerror}",
                hint="is another simulator (or an earlier quadsr sitl) using that port? pick another "
                "tcp:HOST:PORT (PX4 instance N connects to 4560+N)",
            ) from None
        self.local = Endpoint(*self._server.getsockname()[:2], "tcp")
        self._owns_tlog = tlog is not None and not isinstance(tlog, TlogWriter)
        try:
            self.tlog = open_tlog(tlog)
        except UserError:
            self._server.close()
            raise

    # -- connection ----------------------------------------------------------------------------------
    @property
    def connected(self) -> bool:
        """True while a peer is connected."""
        return self._conn is not None

    def _accept(self) -> None:
        conn, addr = self._server.accept()
        if self._conn is not None:  # one peer at a time: a second connection cannot take the link over
            conn.close()
            self.refused += 1
            self._notify(f"refused a second connection from {addr[0]}:{addr[1]}")
            return
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.setblocking(False)  # no poll before each send and recv (a timeout socket polls first)
        self._conn = conn
        self._conn_peer = addr[:2]
        self._pending = b""
        self.connections += 1
        self._notify(f"connected {addr[0]}:{addr[1]}")

    def _drop(self, why: str) -> None:
        if self._conn is None:
            return
        try:
            self._conn.close()
        finally:
            self._conn = None
            self._conn_peer = None
            self._pending = b""
            self._notify(f"disconnected: {why}")

    def _notify(self, text: str) -> None:
        if self.on_change is not None:
            self.on_change(text)

    # -- sending -------------------------------------------------------------------------------------
    pack = UdpLink.pack  # frames with this link's ids, sequence numbers and signing (same code)
    send = UdpLink.send  # messages (a list, nested lists flattened, or one) sent as one write

    def send_frames(self, frames: list[bytes]) -> None:
        """Send already-packed frames to the connected peer (logged to the tlog); nothing if none."""
        if self._send_bytes(b"".join(frames)):
            self.stats.frames_sent += len(frames)
            if self.tlog is not None:
                self.tlog.write_frames(frames)

    def send_raw(self, data: bytes) -> None:
        """Send raw bytes, unlogged and uncounted as frames (tests)."""
        self._send_bytes(data)

    def _send_bytes(self, data: bytes) -> bool:
        conn = self._conn
        if conn is None:
            self.stats.no_peer += 1
            return False
        try:
            _send_all(conn, data)
        except TimeoutError:
            self.stats.send_errors += 1
            self._drop(f"the peer took no data for {SEND_TIMEOUT_S:g} s")
            return False
        except OSError as exc:
            self.stats.send_errors += 1
            self._drop(exc.strerror or type(exc).__name__)
            return False
        self.stats.datagrams_sent += 1
        self.stats.bytes_sent += len(data)
        return True

    # -- receiving -----------------------------------------------------------------------------------
    def recv_split(self, timeout: float | None = 0.0) -> list[tuple]:
        """Checked, undecoded frames [(spec, frame, header_len, signature_len)] of one read.

        Waits up to timeout s (None: forever); [] if none. Also accepts a waiting connection. Bad bytes are
        counted in .stats, never raised."""
        sock = self._conn if self._conn is not None else self._server
        try:
            ready, _, _ = select.select([sock, self._server] if sock is not self._server else [sock], [], [],
                                        timeout)
        except (OSError, ValueError):
            return []
        if self._server in ready:
            self._accept()
            return []
        if not ready or self._conn is None:
            return []
        return self._read(self._conn)

    def _read(self, conn: socket.socket) -> list[tuple]:
        """One read from a ready connection, split into checked frames; a closed or failed peer is dropped."""
        try:
            data = conn.recv(READ_SIZE, socket.MSG_DONTWAIT)
        except (BlockingIOError, InterruptedError, TimeoutError):
            return []
        except OSError as exc:
            self._drop(exc.strerror or type(exc).__name__)
            return []
        if not data:
            self._drop("the peer closed the connection")
            return []
        return self._accept_bytes(data)

    def _accept_bytes(self, data: bytes) -> list[tuple]:
        stats = self.stats
        stats.datagrams_received += 1
        stats.bytes_received += len(data)
        buf = self._pending + data if self._pending else data
        frames, consumed = split_stream(buf, stats, self.signing, self.accept_system_ids)
        rest = buf[consumed:]
        if len(rest) > MAX_PENDING:  # cannot be one unfinished frame: skip it as garbage
            stats.garbage += 1
            stats.garbage_bytes += len(rest)
            rest = b""
        self._pending = rest
        if frames:
            stats.frames_received += len(frames)
            self.peer = self._conn_peer
            self.last_recv_time = time.monotonic()
            if self.tlog is not None:
                self.tlog.write_frames([f[1] for f in frames])
        return frames

    # -- plumbing ------------------------------------------------------------------------------------
    def fileno(self) -> int:
        """The descriptor to wait on: the connection's, else the listening socket's."""
        return (self._conn or self._server).fileno()

    @property
    def closed(self) -> bool:
        """True once close() was called."""
        return self._server.fileno() < 0

    def close(self) -> None:
        """Close the connection and the listening socket (and the tlog if this link opened it)."""
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        self._server.close()
        if self._owns_tlog and self.tlog is not None:
            self.tlog.close()

    def __enter__(self) -> TcpLink:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"TcpLink(local={self.local}, peer={self._conn_peer})"


def _send_all(conn: socket.socket, data: bytes) -> None:
    """Write all of data to a non-blocking connection: one send() when the kernel takes it at once (the usual
    case, with no poll before it as sendall on a socket with a timeout makes), else waiting for room up to
    SEND_TIMEOUT_S wall s (then TimeoutError)."""
    try:
        sent = conn.send(data)
    except BlockingIOError:
        sent = 0
    if sent == len(data):
        return
    view = memoryview(data)[sent:]
    deadline = time.monotonic() + SEND_TIMEOUT_S
    while view:
        remaining = deadline - time.monotonic()
        if remaining <= 0.0:
            raise TimeoutError
        select.select([], [conn], [], remaining)
        try:
            view = view[conn.send(view):]
        except BlockingIOError:
            pass


class TcpClientLink(TcpLink):
    """A TCP MAVLink 2 link that connects to a listening peer (ArduPilot SITL's SERIAL0, tcp:HOST:5760+10N),
    with the calls of bridge.link.UdpLink a client uses (send, recv, drain, stats, close). Connection refused
    is retried for connect_timeout wall s (ArduPilot opens its port a moment after it starts); a lost
    connection is not reopened (recv then returns [])."""

    def __init__(self, remote: Endpoint, system_id: int = 1, component_id: int = 1,
                 tlog: TlogWriter | str | None = None, connect_timeout: float = 30.0):
        self.system_id = int(system_id)
        self.component_id = int(component_id)
        self.signing = None
        self.accept_system_ids = None
        self.on_change = None
        self.stats = LinkStats()
        self.seq = 0
        self.connections = self.refused = 0
        self.last_recv_time = 0.0
        self._pending = b""
        self._closed = False
        self._server = None
        deadline = time.monotonic() + connect_timeout
        while True:
            try:
                conn = socket.create_connection((remote.host, remote.port), timeout=SEND_TIMEOUT_S)
                break
            except ConnectionRefusedError:
                if time.monotonic() > deadline:
                    raise UserError(f"nothing accepts a connection at tcp:{remote.host}:{remote.port} (tried "
                                    f"for {connect_timeout:g} s)",
                                    hint="is ArduPilot running (quadsr ardupilot)? its MAVLink port is "
                                         "tcp:127.0.0.1:5760+10*N for instance -I N") from None
                time.sleep(0.2)
            except OSError as exc:
                raise UserError(f"cannot connect to tcp:{remote.host}:{remote.port}: {exc.strerror or exc}",
                                hint="give the autopilot's address as tcp:HOST:PORT") from None
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.setblocking(False)
        self._conn = conn
        self._conn_peer = self.peer = conn.getpeername()[:2]
        self.local = Endpoint(*conn.getsockname()[:2], "tcp")
        self.connections = 1
        self._owns_tlog = tlog is not None and not isinstance(tlog, TlogWriter)
        self.tlog = open_tlog(tlog)

    def recv_split(self, timeout: float | None = 0.0) -> list[tuple]:
        """Checked, undecoded frames of one read (waiting up to timeout s); [] if none or disconnected."""
        conn = self._conn
        if conn is None:
            if timeout:
                time.sleep(timeout)
            return []
        try:
            ready, _, _ = select.select([conn], [], [], timeout)
        except (OSError, ValueError):
            return []
        if not ready:
            return []
        return self._read(conn)

    _decode = UdpLink._decode

    def recv(self, timeout: float | None = 0.0) -> list:
        """Messages of one read, waiting up to timeout s; [] if none."""
        return self._decode(self.recv_split(timeout))

    def drain(self, max_reads: int = 1000) -> list:
        """All messages already received (no waiting), up to max_reads reads."""
        out: list = []
        for _ in range(max_reads):
            frames = self.recv_split(0.0)
            if not frames:
                break
            out.extend(self._decode(frames))
        return out

    def fileno(self) -> int:
        """The connection's descriptor (-1 once it is gone)."""
        return self._conn.fileno() if self._conn is not None else -1

    @property
    def closed(self) -> bool:
        """True once close() was called."""
        return self._closed

    def close(self) -> None:
        """Close the connection (and the tlog if this link opened it)."""
        if self._conn is not None:
            self._conn.close()
            self._conn = None
        if not self._closed and self._owns_tlog and self.tlog is not None:
            self.tlog.close()
        self._closed = True

    def __repr__(self) -> str:
        return f"TcpClientLink(local={self.local}, peer={self._conn_peer})"
