"""MAVLink 2 signing on the ground link of `quadsr sitl --signing-key FILE`, both ways (issue 16 item 3).

Out: every frame to the ground tools is signed with the key (link id 1). In: commands are answered only when
validly signed and fresh; unsigned, wrongly signed and replayed ones are refused. The signed client is
pymavlink's own signing (what MAVProxy's `signing key` uses), not ours; MAVSDK (no signing) still reads the
signed telemetry.
"""

from __future__ import annotations

import hashlib
import socket
import time

import pytest
from mavsdk import ComponentType, Configuration, Mavsdk
from mavsdk.plugins.telemetry import Telemetry
from pymavlink.dialects.v20 import common as mavlink

from bridge.signing import Signing, signing_timestamp_now

pytestmark = pytest.mark.e2e

KEY = hashlib.sha256(b"quadsr ground passphrase").digest()  # as MAVProxy's `signing key PASSPHRASE`


class Tool:
    """A ground tool on a UDP port (the SITL sends first), pymavlink-signed when given a key."""

    def __init__(self, port: int, key: bytes | None = None, system: int = 255):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.mav = mavlink.MAVLink(None, srcSystem=system, srcComponent=190)
        if key is not None:
            self.mav.signing.secret_key = key
            self.mav.signing.link_id = 2
            self.mav.signing.timestamp = signing_timestamp_now()
            self.mav.signing.sign_outgoing = True
        self.parser = mavlink.MAVLink(None)
        self.parser.robust_parsing = True
        self.sitl = None
        self.raw: list[bytes] = []
        self.got: list = []

    def read(self, seconds: float) -> None:
        """Read every datagram for `seconds`."""
        deadline = time.monotonic() + seconds
        while (left := deadline - time.monotonic()) > 0:
            self.sock.settimeout(left)
            try:
                data, self.sitl = self.sock.recvfrom(65535)
            except TimeoutError:
                return
            for m in self.parser.parse_buffer(data) or []:
                if m.get_type() != "BAD_DATA":
                    self.got.append(m)
                    self.raw.append(bytes(m.get_msgbuf()))

    def command(self, cmd: int, param1: float = 0.0) -> bytes:
        """Send a COMMAND_LONG to the vehicle; return the frame sent."""
        frame = mavlink.MAVLink_command_long_message(1, 1, cmd, 0, param1, 0, 0, 0, 0, 0, 0).pack(self.mav)
        self.sock.sendto(frame, self.sitl)
        return frame

    def acks(self) -> list:
        return [m for m in self.got if m.get_type() == "COMMAND_ACK"]

    def close(self) -> None:
        self.sock.close()


def test_ground_link_signs_everything_and_answers_only_signed_commands(start_sitl, tmp_path, udp_port):
    key_file = tmp_path / "ground.key"
    key_file.write_text(KEY.hex())  # 64 hex digits: the same key MAVProxy derives from the passphrase
    signed = Tool(udp_port, KEY)
    try:
        sitl = start_sitl("--signing-key", str(key_file), "--gcs", f"udp:127.0.0.1:{udp_port}")
        signed.read(0.5)
        assert signed.raw and signed.sitl is not None
        check = Signing(KEY)
        for raw in signed.raw:  # every frame signed, link id 1, signature valid and fresh
            assert raw[2] & 0x01 and raw[-13] == 1, raw
            assert check.verify(raw, 1, 1) is None
        assert check.verify(signed.raw[0], 1, 1) == "replayed"

        unsigned = mavlink.MAVLink(None, srcSystem=254, srcComponent=190)
        forged = Signing(bytes(32), link_id=2)  # a wrong key
        stranger = mavlink.MAVLink_command_long_message(
            1, 1, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 0, 0, 0, 0, 0, 0, 0, 0)
        signed.sock.sendto(stranger.pack(unsigned), signed.sitl)
        wrong = bytearray(stranger.pack(mavlink.MAVLink(None, srcSystem=253, srcComponent=190)))
        wrong[2] |= 0x01
        signed.sock.sendto(forged.sign(bytes(wrong)), signed.sitl)
        replay = signed.command(mavlink.MAV_CMD_GET_HOME_POSITION)
        signed.read(0.5)
        acks = signed.acks()
        assert [(a.command, a.target_system) for a in acks] == [(mavlink.MAV_CMD_GET_HOME_POSITION, 255)]
        assert not [m for m in signed.got if m.get_type() == "AUTOPILOT_VERSION"]  # the refused commands
        signed.sock.sendto(replay, signed.sitl)  # the same signed frame again: a replay
        signed.read(0.5)
        assert len(signed.acks()) == 1
        assert sitl.proc.poll() is None
    finally:
        signed.close()


def test_mavsdk_reads_a_signed_ground_link(start_sitl, tmp_path, udp_port):
    key_file = tmp_path / "ground.key"
    key_file.write_bytes(KEY)
    start_sitl("--signing-key", str(key_file), "--no-gcs", "--offboard", f"udp:127.0.0.1:{udp_port}",
               "--sensors", "ideal")
    drone = Mavsdk(Configuration.create_with_component_type(ComponentType.GROUND_STATION))
    try:
        drone.add_any_connection(f"udpin://0.0.0.0:{udp_port}")
        system = drone.first_autopilot(10.0)
        assert system is not None and system.is_connected()
        got = []
        Telemetry(system).subscribe_position_velocity_ned(lambda value, _user: got.append(value))
        deadline = time.monotonic() + 10.0
        while not got and time.monotonic() < deadline:
            time.sleep(0.05)
        assert got, "MAVSDK got no LOCAL_POSITION_NED from the signed SITL"
        assert got[-1].position.down_m == 0.0  # waiting on the ground for a companion
    finally:
        drone.destroy()
