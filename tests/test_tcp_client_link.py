"""bridge.stream_link.TcpClientLink over real loopback TCP: MAVLink 2 both ways through a listening
TcpLink, frames split across reads reassembled, a lost peer seen as silence, a refused connection a clear
UserError."""

from __future__ import annotations

import socket
import time

import pytest

from bridge.errors import UserError
from bridge.link import Endpoint
from bridge.messages import mavlink
from bridge.stream_link import TcpClientLink, TcpLink


def _heartbeat():
    return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                             0, 4, mavlink.MAV_STATE_STANDBY, 3)


def _until(receive, timeout=10.0):
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        got = receive()
        if got:
            return got
    return []


def test_client_exchanges_mavlink_with_a_listening_link():
    server = TcpLink(Endpoint("127.0.0.1", 0, "tcp"), system_id=1)
    client = TcpClientLink(Endpoint("127.0.0.1", server.local.port, "tcp"), system_id=245, component_id=191,
                           connect_timeout=5.0)
    try:
        _until(lambda: server.recv_split(0.1) or server.connected)  # accept
        server.send([_heartbeat(), _heartbeat()])
        msgs = _until(lambda: client.recv(0.1))
        assert msgs and msgs[0].get_type() == "HEARTBEAT" and msgs[0].get_srcSystem() == 1
        assert msgs[0].custom_mode == 4
        client.send([mavlink.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0)])
        frames = _until(lambda: server.recv_split(0.1))
        assert frames and client.stats.frames_sent == 1
        # one frame written in two pieces: the client keeps the first part until the rest arrives
        frame = server.pack([_heartbeat()])[0]
        server.send_raw(frame[:7])
        assert client.recv(0.2) == []
        server.send_raw(frame[7:])
        assert [m.get_type() for m in _until(lambda: client.recv(0.1))] == ["HEARTBEAT"]
        server.close()  # the peer goes away: silence, never an exception
        assert _until(lambda: client.recv(0.1) or client.fileno() < 0)
        assert client.recv(0.05) == [] and client.drain() == []
    finally:
        client.close()
        server.close()
    assert client.closed


def test_refused_connection_is_a_clear_user_error():
    sock = socket.socket()
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    sock.close()  # nothing listens there now
    with pytest.raises(UserError, match=f"nothing accepts a connection at tcp:127.0.0.1:{port}"):
        TcpClientLink(Endpoint("127.0.0.1", port, "tcp"), connect_timeout=0.5)
