"""bridge.tlog: what a real link writes is read back by pymavlink's mavlogdump.py, even after SIGKILL."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import numpy as np
import pytest

from bridge import messages as M
from bridge.errors import UserError
from bridge.link import Endpoint, UdpLink
from bridge.tlog import TlogWriter, read_tlog

MAVLOGDUMP = Path(sys.executable).parent / "mavlogdump.py"
REPO = Path(__file__).resolve().parents[1]


def _mavlogdump_types(path: Path) -> list[str]:
    """Message types of every line mavlogdump.py prints for a tlog (in a separate process)."""
    out = subprocess.run(
        [sys.executable, str(MAVLOGDUMP), str(path)], capture_output=True, text=True, timeout=60
    )
    assert out.returncode == 0, out.stderr
    types = []
    for line in out.stdout.splitlines():
        stamp, rest = line.split(": ", 1)  # "2026-11-21 23:32:53.40: HEARTBEAT {...}"
        assert int(stamp[:4]) >= 2020, line  # the tlog's unix-time stamps were read
        types.append(rest.split(" ", 1)[0])
    return types


def _step(t: int) -> list:
    state = M.TrueState.from_quaternion(t, (0.0, 0.0, -1.0), (0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0), (0, 0, 0))
    return [
        M.encode_hil_state_quaternion(state, 47.0, 8.0, 500.0),
        M.encode_local_position_ned(state),
        M.encode_hil_sensor(M.ImuSample(t, np.array((0.0, 0.0, -9.8)), np.zeros(3))),
    ]


def test_link_tlog_holds_both_directions_and_mavlogdump_reads_it(tmp_path):
    log = tmp_path / "hil.tlog"
    sim = UdpLink(Endpoint("127.0.0.1", 0), None, 1, 51)
    companion = UdpLink(None, sim.local, 1, 1, tlog=str(log))
    try:
        for k in range(10):
            companion.send([M.encode_heartbeat()])
            assert [m.get_type() for m in sim.recv(2.0)] == ["HEARTBEAT"]
            sim.send(_step(k * 4000))
            assert len(companion.recv(2.0)) == 3
    finally:
        companion.close()
        sim.close()
    assert companion.tlog.closed  # the link opened it from a path, so it closed it
    types = _mavlogdump_types(log)
    assert len(types) == 40
    assert types.count("HEARTBEAT") == 10 and types.count("HIL_SENSOR") == 10
    records = list(read_tlog(log))
    assert [m.get_type() for _, m in records] == types
    stamps = [t for t, _ in records]
    assert stamps == sorted(stamps) and abs(stamps[0] - time.time()) < 60


def test_killed_writer_leaves_a_readable_tlog(tmp_path):
    log = tmp_path / "killed.tlog"
    child_code = textwrap.dedent(
        f"""
        import sys
        sys.path.insert(0, {str(REPO)!r})
        from bridge import messages as M
        from bridge.link import Endpoint, UdpLink
        sink = UdpLink(Endpoint("127.0.0.1", 0))
        link = UdpLink(None, sink.local, 1, 1, tlog={str(log)!r})
        t = 0
        while True:
            link.send([M.encode_heartbeat(), M.encode_hil_actuator_controls(t, [0.5] * 4)])
            sink.drain()
            t += 4000
        """
    )
    child = subprocess.Popen([sys.executable, "-c", child_code])
    try:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and (not log.exists() or log.stat().st_size < 20000):
            time.sleep(0.02)
    finally:
        os.kill(child.pid, signal.SIGKILL)
        child.wait(10)
    assert child.returncode == -signal.SIGKILL
    assert log.stat().st_size >= 20000
    types = _mavlogdump_types(log)
    assert len(types) > 100
    assert set(types) == {"HEARTBEAT", "HIL_ACTUATOR_CONTROLS"}
    assert len(list(read_tlog(log))) == len(types)


def test_read_tlog_truncated_last_record_warns_and_keeps_the_rest(tmp_path):
    log = tmp_path / "cut.tlog"
    with TlogWriter(log) as w:
        w.write_messages(_packed(_step(0)))
        w.write_messages(_packed(_step(4000)))
    data = log.read_bytes()
    log.write_bytes(data[:-7])
    with pytest.warns(UserWarning, match="truncated"):
        records = list(read_tlog(log))
    assert [m.get_type() for _, m in records] == [
        "HIL_STATE_QUATERNION",
        "LOCAL_POSITION_NED",
        "HIL_SENSOR",
    ] + [
        "HIL_STATE_QUATERNION",
        "LOCAL_POSITION_NED",
    ]


def _packed(msgs: list) -> list:
    from pymavlink.dialects.v20 import common as mavlink

    mav = mavlink.MAVLink(None, 1, 51)
    for m in msgs:
        m.pack(mav)
    return msgs


@pytest.mark.parametrize("content", [None, b"", b"this is a text file, not a telemetry log\n" * 3])
def test_read_tlog_rejects_missing_empty_and_foreign_files(tmp_path, content):
    path = tmp_path / "x.tlog"
    if content is not None:
        path.write_bytes(content)
    with pytest.raises(UserError, match=str(path.name)):
        list(read_tlog(path))


def test_signed_frames_and_foreign_frames_in_a_tlog(tmp_path):
    from bridge.framing import pack_frame
    from bridge.signing import Signing

    log = tmp_path / "signed.tlog"
    signed = [pack_frame(m, k, 1, 1, Signing(bytes(32))) for k, m in enumerate(_step(4000))]
    foreign = bytearray(pack_frame(M.encode_heartbeat(), 9, 1, 1))
    foreign[7:10] = (0x34, 0x12, 0x00)  # message id 0x1234: another dialect's, skipped whole
    with TlogWriter(log) as w:
        w.write_frames(signed[:2])
        w.write_frames([bytes(foreign)])
        w.write_frames(signed[2:])
    records = list(read_tlog(log))
    assert [m.get_type() for _, m in records] == ["HIL_STATE_QUATERNION", "LOCAL_POSITION_NED", "HIL_SENSOR"]
    assert all(m.get_signed() for _, m in records)
    dumped = _mavlogdump_types(log)
    assert dumped == ["HIL_STATE_QUATERNION", "LOCAL_POSITION_NED", "UNKNOWN_4660", "HIL_SENSOR"]
