"""Hand-packed frames are byte for byte what pymavlink itself packs.

sitl.hil (each step's datagram: checked in tests/test_sitl_e2e.py with pymavlink_frames below) and
bridge.framing (every other frame: the companion's HIL_ACTUATOR_CONTROLS, STATUSTEXT, the ground link's) build
MAVLink 2 frames without pymavlink's packer, for speed. The same messages, with the same sequence numbers and
ids, go through pymavlink's `MAVLink_message.pack` and the bytes must be equal, payload truncation and CRC
included.
"""

from __future__ import annotations

import numpy as np
from pymavlink.dialects.v20 import common as mavlink

from bridge.framing import pack_frame
from bridge.messages import encode_hil_actuator_controls


def pymavlink_frames(msgs: list, seq: int, system_id: int, component_id: int) -> list[bytes]:
    """Frames of messages packed by pymavlink, numbered from seq."""
    mav = mavlink.MAVLink(None, srcSystem=system_id, srcComponent=component_id)
    out = []
    for msg in msgs:
        mav.seq = seq
        out.append(bytes(msg.pack(mav)))
        seq = (seq + 1) & 0xFF
    return out


def test_actuator_frames_are_pymavlinks_bytes():
    """The companion's HIL_ACTUATOR_CONTROLS (bridge.framing.pack_frame) equal pymavlink's, also with zeros
    at the end of the payload (a zero mode byte is truncated away)."""
    rng = np.random.default_rng(5)
    for k in range(50):
        throttles = list(rng.uniform(0, 1, 4)) if k % 5 else [0.0] * 4
        msg = encode_hil_actuator_controls(4000 * k, throttles, lockstep=bool(k % 2))
        if k % 7 == 0:
            msg.mode = 0
        seq = (k * 37) & 0xFF
        assert pack_frame(msg, seq, 1, 1) == pymavlink_frames([msg], seq, 1, 1)[0]
