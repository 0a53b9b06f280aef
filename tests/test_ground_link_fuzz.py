"""Hostile ground tools never stop `quadsr sitl`: 100,000 frames on the ground link, then the same telemetry.

Frames: COMMAND_LONG / COMMAND_INT (stream and request commands among others) with NaN, inf, huge and
fractional parameters, PARAM_*, REQUEST_*, SET_* messages, random bytes, truncated frames and bad CRCs, from
several system ids. The SITL must answer a probe after every datagram (so it is alive and has read it all),
and afterwards its lockstep HIL telemetry must be bit-identical to a fresh SITL's, its ground streams intact.
"""

from __future__ import annotations

import math
import socket
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import common as mavlink

from bridge.framing import pack_frame

pytestmark = pytest.mark.e2e

N_FRAMES = 100_000
POOL = 2_000  # distinct hostile messages
DATAGRAM_BYTES = 48_000  # well under the 212 kB default receive buffer: nothing is lost before it is read
PROBE_SYSTEM = 250  # the probe's ACK comes back to this system id
SYSTEMS = (1, 2, 3, 42, 200, 255)
HOSTILE = (math.nan, math.inf, -math.inf, 1e38, -1e38, 3.4028234e38, -3.4028234e38, 1.5, -7.25, 2.0**24,
           -30.0, 1e-45, 0.0, 1.0, -1.0, 65535.0)
# As a message id these name no message (SET_MESSAGE_INTERVAL with them must not change any stream).
NOT_AN_ID = (math.nan, math.inf, -math.inf, 1e38, -1e38, 3.4028234e38, 1.5, -7.25, 2.0**24, -30.0, 1e-45,
             30.5, 1e7 + 0.5)
COMMANDS = (mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_CMD_REQUEST_MESSAGE,
            mavlink.MAV_CMD_GET_HOME_POSITION, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
            mavlink.MAV_CMD_COMPONENT_ARM_DISARM, mavlink.MAV_CMD_NAV_TAKEOFF, mavlink.MAV_CMD_DO_SET_MODE,
            mavlink.MAV_CMD_REQUEST_MESSAGE + 1, 0, 65535)


def _float(rng: np.random.Generator) -> float:
    return HOSTILE[int(rng.integers(len(HOSTILE)))] if rng.random() < 0.7 else float(rng.normal(0, 1e6))


def _params(rng: np.random.Generator, command: int) -> list[float]:
    params = [_float(rng) for _ in range(7)]
    if command == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
        params[0] = NOT_AN_ID[int(rng.integers(len(NOT_AN_ID)))]
    return params


def _message(rng: np.random.Generator, i: int):
    """One hostile pymavlink message (kind chosen by i)."""
    kind = i % 11
    target = (0, 1, int(rng.integers(0, 256)))[int(rng.integers(3))]
    comp = (0, 1, int(rng.integers(0, 256)))[int(rng.integers(3))]
    command = COMMANDS[int(rng.integers(len(COMMANDS)))]
    f = [_float(rng) for _ in range(16)]
    if kind in (0, 1, 2):
        return mavlink.MAVLink_command_long_message(target, comp, command, int(rng.integers(256)),
                                                    *_params(rng, command))
    if kind in (3, 4):
        p = _params(rng, command)
        return mavlink.MAVLink_command_int_message(target, comp, int(rng.integers(256)), command,
                                                   int(rng.integers(256)), int(rng.integers(256)), *p[:4],
                                                   int(rng.integers(-2**31, 2**31)),
                                                   int(rng.integers(-2**31, 2**31)), p[6])
    if kind == 5:
        return mavlink.MAVLink_param_set_message(target, comp, rng.bytes(16), f[0], int(rng.integers(256)))
    if kind == 6:
        return (mavlink.MAVLink_param_request_read_message(target, comp, rng.bytes(16),
                                                           int(rng.integers(-32768, 32768)))
                if i % 2 else mavlink.MAVLink_param_request_list_message(target, comp))
    if kind == 7:
        return mavlink.MAVLink_request_data_stream_message(target, comp, int(rng.integers(256)),
                                                           int(rng.integers(65536)), int(rng.integers(256)))
    if kind == 8:
        return mavlink.MAVLink_set_mode_message(target, int(rng.integers(256)), int(rng.integers(2**32)))
    if kind == 9:
        return mavlink.MAVLink_set_position_target_local_ned_message(
            int(rng.integers(2**32)), target, comp, int(rng.integers(256)), int(rng.integers(65536)), *f[:11])
    return mavlink.MAVLink_set_attitude_target_message(int(rng.integers(2**32)), target, comp,
                                                       int(rng.integers(256)), f[:4], *f[4:8])


def _hostile_datagrams(rng: np.random.Generator, n: int) -> list[bytes]:
    """n hostile frames (1 in 20 random bytes, truncated or with a bad CRC) packed into datagrams.

    POOL distinct hostile messages, each framed n / POOL times from other system ids, components and
    sequence numbers (building a pymavlink message costs 100x framing one).
    """
    pool = [_message(rng, i) for i in range(POOL)]
    components = rng.integers(0, 256, n)
    datagrams, chunk, size = [], [], 0
    for i in range(n):
        system = SYSTEMS[(i // POOL + i) % len(SYSTEMS)]
        frame = pack_frame(pool[i % POOL], i & 0xFF, system, int(components[i]))
        broken = i % 20
        if broken == 1:
            frame = rng.bytes(int(rng.integers(1, 80)))
        elif broken == 2:
            frame = frame[: int(rng.integers(1, len(frame)))]
        elif broken == 3:
            b = bytearray(frame)
            b[-1] ^= 0xFF
            frame = bytes(b)
        if size + len(frame) > DATAGRAM_BYTES:
            datagrams.append(b"".join(chunk))
            chunk, size = [], 0
        chunk.append(frame)
        size += len(frame)
    datagrams.append(b"".join(chunk))
    return datagrams


class Gcs:
    """A raw UDP ground tool: learns the SITL's ground address from its first datagram."""

    def __init__(self, port: int):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.sitl = None
        self.got: list = []

    def read(self, timeout: float) -> list:
        """Messages of the next datagram (empty after timeout s)."""
        self.sock.settimeout(timeout)
        try:
            data, self.sitl = self.sock.recvfrom(65535)
        except TimeoutError:
            return []
        self.parser.buf, self.parser.buf_index = bytearray(), 0
        msgs = [m for m in self.parser.parse_buffer(data) or [] if m.get_type() != "BAD_DATA"]
        self.got.extend(msgs)
        return msgs

    def probe(self, seq: int, timeout: float = 20.0) -> None:
        """Send a probe command; return when its ACK came back (the SITL read every earlier datagram)."""
        frame = pack_frame(mavlink.MAVLink_command_long_message(
            1, 1, mavlink.MAV_CMD_GET_HOME_POSITION, 0, 0, 0, 0, 0, 0, 0, 0), seq & 0xFF, PROBE_SYSTEM, 1)
        self.sock.sendto(frame, self.sitl)
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for m in self.read(0.5):
                if m.get_type() == "COMMAND_ACK" and m.target_system == PROBE_SYSTEM:
                    return
        raise AssertionError(f"no answer to probe {seq} within {timeout} s: the SITL stopped serving")

    def close(self) -> None:
        self.sock.close()


def _hil_telemetry(companion, steps: int = 60) -> list[bytes]:
    """The raw frames of `steps` lockstep steps at a fixed throttle, sequence byte cleared."""
    out = []
    frames = companion.connect()
    for k in range(steps):
        for _, raw in frames:
            out.append(raw[:4] + b"\0" + raw[5:])
        frames = companion.step([0.55 + 0.001 * k] * 4)
    return out


def test_100k_hostile_ground_frames_no_crash_and_telemetry_unchanged(start_sitl, raw_companion, udp_port):
    datagrams = _hostile_datagrams(np.random.default_rng(16), N_FRAMES)
    gcs = Gcs(udp_port)
    try:
        sitl = start_sitl("--gcs", f"udp:127.0.0.1:{udp_port}", "--sensors", "ideal",
                          "--lockstep-timeout", "20")
        while gcs.sitl is None:
            assert gcs.read(10.0), "no telemetry from the SITL's ground link"
        for k, datagram in enumerate(datagrams):
            gcs.sock.sendto(datagram, gcs.sitl)
            try:
                gcs.probe(k)
            except AssertionError:
                raise AssertionError(f"exit code {sitl.proc.poll()}; output:\n{sitl.output}") from None
        assert sitl.proc.poll() is None
        start = len(gcs.got)
        while len([m for m in gcs.got[start:] if m.get_type() == "HEARTBEAT"]) < 2:
            assert gcs.read(5.0), "the ground streams stopped"
        fuzzed = _hil_telemetry(raw_companion(sitl.hil))
        assert sitl.stop() == 0 and "Traceback" not in sitl.output
    finally:
        gcs.close()
    # the streams are as configured: ATTITUDE at 50 Hz of wall time, none switched off or sped up
    att = [m.time_boot_ms for m in gcs.got[start:] if m.get_type() == "ATTITUDE"]
    assert len(att) >= 40 and min(np.diff(att)) >= 19
    fresh = start_sitl("--no-gcs", "--sensors", "ideal", "--lockstep-timeout", "20")
    assert _hil_telemetry(raw_companion(fresh.hil)) == fuzzed
