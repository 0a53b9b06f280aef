"""bridge.link / bridge.framing: endpoints, real UDP round trips, bad bytes dropped and counted."""

from __future__ import annotations

import select
import threading
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from bridge import messages as M
from bridge.errors import UserError
from bridge.framing import pack_frame, parse_datagram, spec_for
from bridge.link import Endpoint, UdpLink, parse_endpoint
from bridge.stats import LinkStats

ANY_PORT = Endpoint("127.0.0.1", 0)


def _sensor(t: int = 4000) -> mavlink.MAVLink_hil_sensor_message:
    return M.encode_hil_sensor(M.ImuSample(t, np.array((0.1, 0.2, -9.8)), np.array((0.01, 0.02, 0.03))))


def _pair(**kwargs) -> tuple[UdpLink, UdpLink]:
    """A listening link (sim seat, compid 51) and a client link sending to it (compid 1)."""
    server = UdpLink(ANY_PORT, None, 1, 51, **kwargs)
    client = UdpLink(None, server.local, 1, 1)
    return server, client


# ---- endpoints ----------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "text, host, port, kind",
    [
        ("udp:127.0.0.1:4560", "127.0.0.1", 4560, "udp"),
        ("udpin:0.0.0.0:14550", "0.0.0.0", 14550, "udpin"),
        ("udpout:localhost:14540", "localhost", 14540, "udpout"),
        ("udp://127.0.0.1:1", "127.0.0.1", 1, "udp"),
        ("  udp:10.0.0.2:0 ", "10.0.0.2", 0, "udp"),
    ],
)
def test_parse_endpoint_accepts_udp_forms(text, host, port, kind):
    ep = parse_endpoint(text)
    assert (ep.host, ep.port, ep.kind) == (host, port, kind)
    assert parse_endpoint(str(ep)) == ep


@pytest.mark.parametrize(
    "text",
    ["", "udp", "tcp:127.0.0.1:5760", "udp:127.0.0.1", "udp:127.0.0.1:99999", "udp:h:abc", "127.0.0.1:4560"],
)
def test_parse_endpoint_rejects_bad_strings_with_the_expected_form(text):
    with pytest.raises(UserError) as err:
        parse_endpoint(text)
    assert "udp:HOST:PORT" in str(err.value)


def test_port_in_use_is_a_user_error():
    first = UdpLink(ANY_PORT)
    try:
        with pytest.raises(UserError, match="cannot listen"):
            UdpLink(first.local)
    finally:
        first.close()


# ---- framing equals pymavlink -------------------------------------------------------------------------
def _sample_messages() -> list:
    return [
        _sensor(),
        M.encode_hil_actuator_controls(4000, [0.5, 0.6, 0.7, 0.8]),  # float array
        mavlink.MAVLink_statustext_message(4, b"quadsr failsafe: no actuator"),  # char field
        M.encode_heartbeat(),
        mavlink.MAVLink_command_long_message(1, 1, 511, 0, 33, 20000, 0, 0, 0, 0, 0),
        mavlink.MAVLink_param_set_message(1, 1, b"MPC_XY_P", 0.95, 9),
        *M.encode_raw_rpm([500.0, 510.0, 520.0, 530.0]),
    ]


def test_frames_are_byte_identical_to_pymavlink_and_decode_to_equal_messages():
    pm = mavlink.MAVLink(None, 1, 51)
    for seq, msg in enumerate(_sample_messages()):
        pm.seq = seq
        ours = pack_frame(msg, seq, 1, 51)
        assert ours == msg.pack(pm), msg.get_type()
        stats = LinkStats()
        [(decoded, frame)] = parse_datagram(ours, stats)
        assert frame == ours
        reference = mavlink.MAVLink(None).decode(bytearray(ours))
        assert decoded == reference, msg.get_type()
        assert decoded.get_srcComponent() == 51 and decoded.get_seq() == seq
        assert decoded.to_dict() == reference.to_dict()


def test_fast_constructor_equals_pymavlink_constructor():
    make = spec_for(mavlink.MAVLink_hil_sensor_message).make
    args = (4000, 0.1, 0.2, -9.8, 0.01, 0.02, 0.03, 0.2, 0.0, 0.4, 1013.25, 0.0, 10.0, 25.0, 0x1FFF, 0)
    assert make(*args).to_dict() == mavlink.MAVLink_hil_sensor_message(*args).to_dict()
    assert make(*args).get_type() == "HIL_SENSOR"


def test_mavlink1_frames_are_parsed():
    pm = mavlink.MAVLink(None, 3, 4)
    frame = M.encode_heartbeat().pack(pm, force_mavlink1=True)
    assert frame[0] == 0xFE
    [(msg, _)] = parse_datagram(frame, LinkStats())
    assert msg.get_type() == "HEARTBEAT" and msg.get_srcSystem() == 3


# ---- real UDP ----------------------------------------------------------------------------------------
def test_multi_frame_datagram_round_trip_and_reply_to_peer():
    server, client = _pair()
    try:
        msgs = _sample_messages()
        client.send(msgs)
        got = server.recv(2.0)
        assert [m.get_type() for m in got] == [m.get_type() for m in msgs]
        assert got[0].time_usec == 4000 and got[1].controls[:4] == pytest.approx([0.5, 0.6, 0.7, 0.8])
        assert got[2].text == "quadsr failsafe: no actuator"
        assert [m.get_seq() for m in got] == list(range(len(msgs)))
        assert server.stats.datagrams_received == 1 and server.stats.frames_received == len(msgs)
        assert client.stats.datagrams_sent == 1 and client.stats.frames_sent == len(msgs)
        assert server.peer == ("127.0.0.1", client.local.port)
        server.send([M.encode_heartbeat()])  # no remote: goes to the last peer
        [hb] = client.recv(2.0)
        assert hb.get_type() == "HEARTBEAT" and hb.get_srcComponent() == 51
    finally:
        server.close()
        client.close()


def test_nested_lists_are_flattened_into_one_datagram():
    server, client = _pair()
    try:
        client.send([M.encode_heartbeat(), M.encode_raw_rpm([1.0, 2.0, 3.0, 4.0]), _sensor()])
        got = server.recv(2.0)
        assert [m.get_type() for m in got] == ["HEARTBEAT"] + ["RAW_RPM"] * 4 + ["HIL_SENSOR"]
        assert server.stats.datagrams_received == 1
    finally:
        server.close()
        client.close()


def test_send_without_peer_is_counted_not_raised():
    link = UdpLink(ANY_PORT)
    try:
        link.send([M.encode_heartbeat()])
        assert link.stats.no_peer == 1 and link.stats.datagrams_sent == 0
        assert link.recv(0.0) == []
        assert link.recv(0.05) == []
    finally:
        link.close()


def test_bad_datagrams_are_dropped_and_counted_by_reason():
    server, client = _pair()
    try:
        good = pack_frame(_sensor(), 0, 1, 1)
        bad_crc = bytearray(good)
        bad_crc[20] ^= 0xFF
        unknown = bytearray(pack_frame(M.encode_heartbeat(), 0, 1, 1))
        unknown[7:10] = (0xDE, 0xBC, 0x0A)  # message id 0x0ABCDE: not in the common dialect
        cases = [
            (b"\x00\x01hello world, not mavlink", "garbage"),
            (good[:-3], "truncated"),
            (bytes(bad_crc), "bad_crc"),
            (bytes(unknown), "unknown_id"),
        ]
        for data, reason in cases:
            client.send_raw(data)
            assert server.recv(2.0) == [], reason
            assert getattr(server.stats, reason) == 1, (reason, server.stats)
        # garbage, a good frame, a bad-CRC frame, a good frame: both good frames survive
        client.send_raw(b"\x13\x37junk" + good + bytes(bad_crc) + good)
        got = server.recv(2.0)
        assert [m.get_type() for m in got] == ["HIL_SENSOR", "HIL_SENSOR"]
        assert server.stats.garbage == 2 and server.stats.bad_crc == 2
        assert server.stats.dropped == 6
        assert server.peer is not None  # set only by the datagram with valid frames
        summary = server.stats.summary()
        assert "dropped 6" in summary and "bad_crc 2" in summary and "garbage 2" in summary
    finally:
        server.close()
        client.close()


def test_wrong_system_id_is_dropped_and_counted():
    server = UdpLink(ANY_PORT, None, 1, 51, accept_system_ids={1})
    stranger = UdpLink(None, server.local, 7, 1)
    try:
        stranger.send([M.encode_heartbeat()])
        assert server.recv(2.0) == []
        assert server.stats.wrong_system == 1 and server.peer is None
    finally:
        server.close()
        stranger.close()


def test_fuzzed_datagrams_never_raise_and_the_parser_recovers():
    rng = np.random.default_rng(7)
    stats = LinkStats()
    good = pack_frame(_sensor(), 5, 1, 1)
    for _ in range(3000):
        kind = rng.integers(4)
        if kind == 0:
            data = rng.bytes(int(rng.integers(0, 300)))
        elif kind == 1:
            data = good[: int(rng.integers(0, len(good)))]
        elif kind == 2:
            b = bytearray(good)
            b[int(rng.integers(0, len(b)))] ^= int(rng.integers(1, 256))
            data = bytes(b)
        else:
            data = b"\xfd" + rng.bytes(int(rng.integers(0, 80)))
        for msg, _ in parse_datagram(data, stats):
            assert msg.get_type()
    assert stats.dropped > 2000
    [(msg, _)] = parse_datagram(good, stats)
    assert msg.time_usec == 4000


def test_drain_reads_every_queued_datagram():
    server, client = _pair()
    try:
        for t in range(5):
            client.send([_sensor(t * 4000)])
        assert select.select([server], [], [], 2.0)[0] == [server]
        time.sleep(0.05)  # loopback delivery of the other four
        got = server.drain()
        assert [m.time_usec for m in got] == [0, 4000, 8000, 12000, 16000]
        assert server.drain() == []
    finally:
        server.close()
        client.close()


def test_every_common_message_gets_a_spec_on_first_use_and_unknown_ids_none():
    """Specs are generated lazily (import stays cheap); every class of the dialect still gets one."""
    from bridge.framing import SPECS_BY_ID, spec_for_id

    for msg_id, cls in mavlink.mavlink_map.items():
        spec = spec_for_id(msg_id)
        assert spec is not None and spec.cls is cls and spec.msg_id == msg_id
        assert spec_for(cls) is spec and SPECS_BY_ID[msg_id] is spec
    assert spec_for_id(0xFFFFFF) is None


def test_a_polling_link_receives_what_comes_during_and_after_its_poll():
    server, client = _pair()
    try:
        server.spin_s = 0.002  # poll 2 ms before sleeping
        client.send([_sensor(4000)])
        time.sleep(0.01)
        assert [m.time_usec for m in server.recv(1.0)] == [4000]  # queued before the poll
        assert server.recv(0.001) == [] and server.recv(0.05) == []  # nothing comes: both bounds end it
        # sent after the poll ends: the sleep gets it
        late = threading.Timer(0.03, lambda: client.send([_sensor(8000)]))
        late.start()
        start = time.monotonic()
        assert [m.time_usec for m in server.recv(2.0)] == [8000]
        assert time.monotonic() - start < 1.0
    finally:
        server.close()
        client.close()
