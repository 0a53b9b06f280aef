"""bridge.signing: signed frames accepted, unsigned/forged/replayed refused and counted, and one forged frame
with a future timestamp does not lock out the genuine sender (as it does in pymavlink 2.4.50)."""

from __future__ import annotations

import hashlib

import pytest
from pymavlink.dialects.v20 import common as mavlink

from bridge import messages as M
from bridge.errors import UserError
from bridge.framing import pack_frame
from bridge.link import Endpoint, UdpLink
from bridge.signing import Signing, load_key, signing_timestamp_now

KEY = bytes(range(32))
OTHER_KEY = bytes(range(1, 33))
TEN_DAYS = 10 * 86400 * 100_000  # in 10 us signing units


def _cmd(t: int) -> mavlink.MAVLink_hil_actuator_controls_message:
    return M.encode_hil_actuator_controls(t, [0.5, 0.5, 0.5, 0.5])


def _links(receiver_key=KEY, sender_key=KEY):
    receiver = UdpLink(
        Endpoint("127.0.0.1", 0), None, 1, 51, signing=Signing(receiver_key) if receiver_key else None
    )
    sender = UdpLink(None, receiver.local, 1, 1, signing=Signing(sender_key) if sender_key else None)
    return receiver, sender


def _resign(frame: bytes, key: bytes, timestamp: int, link_id: int = 0) -> bytes:
    """A signed frame re-signed with a chosen timestamp, computed from the MAVLink spec independently."""
    body = frame[:-13]
    block = bytes((link_id,)) + timestamp.to_bytes(6, "little")
    return body + block + hashlib.sha256(key + body + block).digest()[:6]


def _pymavlink_accepts(parser: mavlink.MAVLink, frame: bytes) -> bool:
    msgs = parser.parse_buffer(frame) or []
    return any(not isinstance(m, mavlink.MAVLink_bad_data) for m in msgs)


def _pymavlink_parser() -> mavlink.MAVLink:
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = True  # bad frames come back as MAVLink_bad_data instead of raising
    parser.signing.secret_key = KEY
    return parser


def test_signed_frames_are_accepted_and_marked_signed():
    receiver, sender = _links()
    try:
        sender.send([_cmd(4000), M.encode_heartbeat()])
        got = receiver.recv(2.0)
        assert [m.get_type() for m in got] == ["HIL_ACTUATOR_CONTROLS", "HEARTBEAT"]
        assert all(m.get_signed() and m.get_link_id() == 0 for m in got)
        assert receiver.stats.dropped == 0
        # pymavlink agrees that our signatures are valid
        frame = pack_frame(_cmd(8000), 0, 1, 1, Signing(KEY))
        assert frame[2] & 0x01 and len(frame) == 12 + frame[1] + 13
        assert _pymavlink_accepts(_pymavlink_parser(), frame)
    finally:
        receiver.close()
        sender.close()


def test_unsigned_and_wrongly_signed_frames_are_refused_and_counted():
    receiver, unsigned = _links(sender_key=None)
    forger = UdpLink(None, receiver.local, 1, 1, signing=Signing(OTHER_KEY))
    try:
        unsigned.send([_cmd(4000)])
        assert receiver.recv(2.0) == []
        forger.send([_cmd(4000)])
        assert receiver.recv(2.0) == []
        assert receiver.stats.unsigned == 1 and receiver.stats.bad_signature == 1
        assert receiver.peer is None  # refused frames do not make a peer
        assert "unsigned 1" in receiver.stats.summary() and "bad_signature 1" in receiver.stats.summary()
    finally:
        for link in (receiver, unsigned, forger):
            link.close()


def test_forged_future_timestamp_does_not_lock_out_the_genuine_sender():
    receiver, sender = _links()
    try:
        genuine_first = sender.pack([_cmd(4000)])[0]
        # The forgery: the genuine frame with its timestamp moved 10 days ahead (so its signature is wrong).
        forged_ts = signing_timestamp_now() + TEN_DAYS
        forged = genuine_first[:-12] + forged_ts.to_bytes(6, "little") + genuine_first[-6:]
        sender.send_raw(forged)
        assert receiver.recv(2.0) == [] and receiver.stats.bad_signature == 1
        # The genuine sender keeps talking: every frame is accepted.
        sender.send_raw(genuine_first)
        later = [sender.pack([_cmd(8000 + 4000 * k)])[0] for k in range(3)]
        for frame in later:
            sender.send_raw(frame)
        got = [m for _ in range(4) for m in receiver.recv(2.0)]
        assert [m.time_usec for m in got] == [4000, 8000, 12000, 16000]
        assert receiver.stats.bad_signature == 1 and receiver.stats.replayed == 0

        # The same sequence through pymavlink 2.4.50's own verification: the genuine frames are refused,
        # because it stored the forged timestamp before finding the signature bad.
        control = _pymavlink_parser()
        assert _pymavlink_accepts(control, genuine_first)  # without the forgery, pymavlink accepts it
        victim = _pymavlink_parser()
        assert not _pymavlink_accepts(victim, forged)
        assert not _pymavlink_accepts(victim, genuine_first)
        assert not any(_pymavlink_accepts(victim, frame) for frame in later)
        assert victim.signing.badsig_count == 5
    finally:
        receiver.close()
        sender.close()


def test_replayed_frame_is_refused():
    receiver, sender = _links()
    try:
        frame = sender.pack([_cmd(4000)])[0]
        sender.send_raw(frame)
        assert len(receiver.recv(2.0)) == 1
        sender.send_raw(frame)  # same timestamp again
        assert receiver.recv(2.0) == []
        older = _resign(frame, KEY, int.from_bytes(frame[-12:-6], "little") - 1)  # validly signed, but older
        sender.send_raw(older)
        assert receiver.recv(2.0) == []
        assert receiver.stats.replayed == 2
        sender.send([_cmd(8000)])  # the stream goes on
        assert [m.time_usec for m in receiver.recv(2.0)] == [8000]
    finally:
        receiver.close()
        sender.close()


def test_new_stream_far_from_our_clock_is_refused():
    verifier = Signing(KEY)
    frame = pack_frame(_cmd(4000), 0, 1, 1, Signing(KEY))
    future = _resign(frame, KEY, signing_timestamp_now() + TEN_DAYS)
    past = _resign(frame, KEY, signing_timestamp_now() - TEN_DAYS)
    assert verifier.verify(future, 1, 1) == "bad_timestamp"
    assert verifier.verify(past, 1, 1) == "bad_timestamp"
    assert verifier.stream_timestamp(1, 1) is None  # nothing recorded from refused frames
    assert verifier.verify(frame, 1, 1) is None
    assert verifier.stream_timestamp(1, 1) == int.from_bytes(frame[-12:-6], "little")


def test_sign_matches_an_independent_implementation():
    frame = pack_frame(_cmd(4000), 7, 1, 1, Signing(KEY, link_id=3))
    ts = int.from_bytes(frame[-12:-6], "little")
    assert frame[-13] == 3
    assert _resign(frame, KEY, ts, link_id=3) == frame
    assert abs(ts - signing_timestamp_now()) < 100_000 * 5


def test_load_key(tmp_path):
    raw = tmp_path / "raw.key"
    raw.write_bytes(KEY)
    assert load_key(raw) == KEY
    hexfile = tmp_path / "hex.key"
    hexfile.write_text(KEY.hex() + "\n")
    assert load_key(hexfile) == KEY
    short = tmp_path / "short.key"
    short.write_bytes(KEY[:31])
    with pytest.raises(UserError, match="short.key.*32"):
        load_key(short)
    with pytest.raises(UserError, match="does not exist"):
        load_key(tmp_path / "missing.key")
    with pytest.raises(UserError, match="32 bytes"):
        Signing(b"too short")
