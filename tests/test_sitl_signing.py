"""MAVLink 2 signing on the HIL link of `quadsr sitl --signing-key FILE` (real clients, real UDP)."""

from __future__ import annotations

import socket
import time
from collections import defaultdict

import pytest

from bridge.framing import pack_frame
from bridge.lockstep import LinkLost, LockstepClient
from bridge.messages import encode_heartbeat, encode_hil_actuator_controls
from bridge.signing import Signing, signing_timestamp_now
from sitl.status import parse_status

pytestmark = pytest.mark.e2e

KEY = bytes(range(1, 33))
OTHER_KEY = bytes(range(101, 133))


@pytest.fixture
def key_file(tmp_path):
    path = tmp_path / "hil.key"
    path.write_bytes(KEY)
    return path


def counters(sitl, after: int) -> defaultdict[str, int]:
    """The numeric fields of the first status line printed after line index `after` (absent: 0)."""
    line = sitl.wait_for(r" steps=", start=after, timeout=5.0).string
    return defaultdict(int, {k: int(v) for k, v in parse_status(line).items() if v.isdigit()})


def test_signed_companion_steps_and_the_sitl_signs_everything(start_sitl, key_file, raw_companion):
    sitl = start_sitl("--signing-key", str(key_file))
    with LockstepClient(sitl.hil, signing=key_file, timeout=5.0) as client:
        client.connect(10.0)
        for _ in range(50):
            obs = client.step([0.4] * 4)
        assert obs.time_usec == 200_000
        assert client.stats.unsigned == 0 and client.stats.bad_signature == 0
    companion = raw_companion(sitl.hil, signing=Signing(KEY))  # a new companion, same key
    frames = companion.connect()
    assert all(f[2] & 0x01 and f[-13] == 0 for _, f in frames)  # incompat flag "signed", link id 0


def test_unsigned_and_wrongly_signed_commands_are_refused_and_counted(start_sitl, key_file, raw_companion):
    # a patient lockstep bound: "the refused command did not step" must not depend on how fast this runs
    sitl = start_sitl("--signing-key", str(key_file), "--status-interval", "0.2", "--lockstep-timeout", "10")
    with LockstepClient(sitl.hil, timeout=1.0) as unsigned, pytest.raises(LinkLost):
        unsigned.connect(0.5)
    with LockstepClient(sitl.hil, signing=Signing(OTHER_KEY), timeout=1.0) as wrong, pytest.raises(LinkLost):
        wrong.connect(0.5)
    c = counters(sitl, len(sitl.lines))
    assert c["steps"] == 0 and c["unsigned"] >= 3 and c["bad_signature"] >= 3
    with LockstepClient(sitl.hil, signing=key_file, timeout=5.0) as client:
        client.connect(10.0)
        obs = client.step([0.4] * 4)
        # An unsigned and a wrongly signed answer to the current step must not advance the simulation.
        intruder = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        answer = encode_hil_actuator_controls(obs.time_usec, [1.0] * 4)
        intruder.sendto(pack_frame(answer, 0, 1, 1), ("127.0.0.1", sitl.hil_port))
        intruder.sendto(pack_frame(answer, 1, 1, 1, Signing(OTHER_KEY)), ("127.0.0.1", sitl.hil_port))
        time.sleep(0.3)
        mark = len(sitl.lines)
        c = counters(sitl, mark)
        assert c["steps"] == 1, "a refused command stepped the simulation"
        for _ in range(10):
            obs = client.step([0.4] * 4)
        assert obs.time_usec == 11 * 4000
        intruder.close()
    c = counters(sitl, len(sitl.lines))
    assert c["unsigned"] >= 4 and c["bad_signature"] >= 4


def test_a_forged_future_timestamp_does_not_lock_out_the_genuine_companion(start_sitl, key_file):
    """pymavlink 2.4.50 records a stream's timestamp before checking the signature; the SITL must not."""
    sitl = start_sitl("--signing-key", str(key_file), "--status-interval", "0.2")
    future = signing_timestamp_now() + 3600 * 100_000  # one hour ahead, in 10 us units
    forger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    for seq, msg in enumerate([encode_heartbeat(), encode_hil_actuator_controls(0, [1.0] * 4)]):
        frame = bytearray(pack_frame(msg, seq, 1, 1, Signing(OTHER_KEY)))  # the companion's stream, link 0
        frame[-12:-6] = future.to_bytes(6, "little")
        forger.sendto(bytes(frame), ("127.0.0.1", sitl.hil_port))
    forger.close()
    time.sleep(0.3)
    c = counters(sitl, len(sitl.lines))
    assert c["bad_signature"] == 2 and c["steps"] == 0
    with LockstepClient(sitl.hil, signing=key_file, timeout=5.0) as client:  # genuine: now-stamped frames
        client.connect(5.0)
        for _ in range(50):
            obs = client.step([0.4] * 4)
    assert obs.time_usec == 200_000
    c = counters(sitl, len(sitl.lines))
    assert c["replayed"] == 0 and c["bad_signature"] == 2
