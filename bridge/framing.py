"""MAVLink 2 framing without pymavlink's per-byte parser: pack frames, split datagrams, decode payloads.

pymavlink's `MAVLink.parse_buffer` costs ~14 us per frame and `MAVLink.decode` ~6.5 us (it re-checks the
CRC and verifies signatures in an order that is unsafe, see bridge.signing). Here each message class of the
common dialect gets a generated packer and builder, so a frame costs ~1-2 us each way, and the messages
produced are ordinary pymavlink message objects (equal to what `MAVLink.decode` returns).
"""

from __future__ import annotations

import inspect
import struct
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pymavlink.dialects.v20 import common as mavlink

if TYPE_CHECKING:
    from bridge.signing import Signing
    from bridge.stats import LinkStats

try:
    from fastcrc import crc16 as _fastcrc16

    _mcrf4xx = _fastcrc16.mcrf4xx
except ImportError:  # pragma: no cover - fastcrc is a declared dependency; keep working without it

    def _mcrf4xx(data: bytes, initial: int | None = None) -> int:
        crc = mavlink.x25crc(bytes(data))
        return crc.crc

STX_V2 = 0xFD
STX_V1 = 0xFE
IFLAG_SIGNED = 0x01
SIGNATURE_LEN = 13
HEADER_LEN_V2 = 10
HEADER_LEN_V1 = 6
MIN_FRAME_V2 = HEADER_LEN_V2 + 2  # empty payload never occurs, but the header+crc is the floor

_HEADER_V2 = struct.Struct("<BBBBBBBHB")
# what the splitter reads of a v2 header: length, incompat flags, system, component, message id (16 + 8 bits)
_SPLIT_V2 = struct.Struct("<xBBxxBBHB")
_CRC = struct.Struct("<H")
_Header = mavlink.MAVLink_header
# the CRC'd header after the start byte: length, incompat and compat flags, seq, system, component, message id
_FRAME_HEAD = struct.Struct("<BBBBBB3s")


@dataclass(frozen=True)
class MessageSpec:
    """How one message class goes to and from wire bytes."""

    cls: type
    msg_id: int
    crc_extra: int
    size: int
    unpack: Callable[[bytes], tuple]
    unpack_from: Callable[[bytes, int], tuple]  # (buffer, offset): a payload of exactly `size` bytes in place
    payload_of: Callable[[Any], bytes] | None  # None: class has char fields, packed through pymavlink
    values_of: Callable[[Any], tuple] | None  # values in wire order (as unpack gives); None: char fields
    build: Callable[..., Any]  # (unpacked tuple, header, msgbuf, payload, crc, signed, link_id) -> message
    make: Callable[..., Any]  # the constructor's signature, fast: new message from field values
    fast: bool = False  # build/make fill __dict__ directly (checked equal to pymavlink's constructor)


_new = object.__new__
_BASE_KEYS = ("_header", "_payload", "_msgbuf", "_crc", "_signed", "_link_id", "_instances")


def _set_class_defaults(cls: type) -> None:
    """Give a pymavlink message class, as class attributes, the per-instance constants its __init__ sets.

    Objects built here then carry only their fields (+ header, buffers) in __dict__: half the cost of
    the constructor. Instances made by pymavlink still set their own, so its behaviour is unchanged.
    """
    cls._type = cls.msgname
    cls._fieldnames = cls.fieldnames
    cls._instance_field = cls.instance_field
    cls._instance_offset = cls.instance_offset
    cls._instances = None
    cls._signed = False
    cls._link_id = None
    cls._payload = None
    cls._crc = None
    cls._msgbuf = b""
    cls._header = _Header(cls.id)


def _public_state(m: Any) -> dict:
    keys = ("_type", "_fieldnames", "_instance_field", "_instance_offset", "_instances", "_signed")
    state = {k: getattr(m, k) for k in (*keys, "_link_id")}
    state.update((n, getattr(m, n)) for n in m._fieldnames)
    state["_header"] = vars(m._header)
    return state


def _fast_objects_match(cls: type, names: list[str], slow_build: Any, build: Any, make: Any) -> bool:
    """True if the fast builders give objects equal to the constructor's (checked once per class)."""
    try:
        _set_class_defaults(cls)
        zero = cls.unpacker.unpack(bytes(cls.unpacker.size))
        ref = slow_build(zero, _Header(cls.id), bytearray(), b"", 0, False, None)
        fast = build(zero, _Header(cls.id), bytearray(), b"", 0, False, None)
        args = [getattr(ref, n) for n in names]
        same_decoded = _public_state(ref) == _public_state(fast)
        return same_decoded and _public_state(make(*args)) == _public_state(cls(*args))
    except Exception:
        return False


def _make_spec(cls: type) -> MessageSpec:
    """Generate the packer and the fast constructors of one message class.

    Classes without char fields are built by filling the instance __dict__ directly (what their __init__
    does, in one step: ~3x faster); it is checked here against the real constructor, else the constructor
    is used.
    """
    types = dict(zip(cls.fieldnames, cls.fieldtypes, strict=True))
    has_char = any(types[name] == "char" for name in cls.ordered_fieldnames)
    ns: dict[str, Any] = {"_pack": cls.unpacker.pack, "_cls": cls, "_new": _new, "_Header": _Header}
    payload_of = values_of = None
    fast = False
    if not has_char:
        args = []
        for name, alen in zip(cls.ordered_fieldnames, cls.array_lengths, strict=True):
            args.append(f"*m.{name}" if alen else f"m.{name}")
        exec(f"def payload_of(m):\n    return _pack({', '.join(args)})\n", ns)
        exec(f"def values_of(m):\n    return ({', '.join(args)},)\n", ns)
        payload_of = ns["payload_of"]
        values_of = ns["values_of"]
    # Field values in constructor (fieldnames) order from the wire-ordered unpacked tuple, as
    # MAVLink.decode does: orders[i] is the wire position of field i, lengths are per wire field.
    values = []
    lengths = cls.lengths
    for i, name in enumerate(cls.fieldnames):
        order = cls.orders[i]
        length = lengths[order]
        tip = sum(lengths[:order])
        if length == 1:
            expr = f"t[{tip}]"
            if types[name] == "char":
                expr = f"t[{tip}].rstrip(b'\\x00')"
        else:
            expr = f"list(t[{tip}:{tip + length}])"
        values.append(expr)
    exec(
        "def slow_build(t, header, msgbuf, payload, crc, signed, link_id):\n"
        f"    m = _cls({', '.join(values)})\n"
        "    m._header = header\n    m._msgbuf = msgbuf\n    m._payload = payload\n    m._crc = crc\n"
        "    m._signed = signed\n    m._link_id = link_id\n    return m\n",
        ns,
    )
    build = ns["slow_build"]
    make = cls
    if not has_char:
        names = list(cls.fieldnames)
        fields_from_t = ", ".join(f"{n!r}: {v}" for n, v in zip(names, values, strict=True))
        exec(
            "def build(t, header, msgbuf, payload, crc, signed, link_id):\n"
            "    m = _new(_cls)\n"
            "    if signed:\n"
            "        m.__dict__ = {'_header': header, '_msgbuf': msgbuf, '_payload': payload, '_crc': crc, "
            f"'_signed': True, '_link_id': link_id, {fields_from_t}}}\n"
            "    else:\n"
            "        m.__dict__ = {'_header': header, '_msgbuf': msgbuf, '_payload': payload, '_crc': crc, "
            f"{fields_from_t}}}\n"
            "    return m\n",
            ns,
        )
        sig = inspect.signature(cls.__init__)
        params = ", ".join(
            n if (d := sig.parameters[n].default) is inspect.Parameter.empty else f"{n}={d!r}" for n in names
        )
        fields_from_args = ", ".join(f"{n!r}: {n}" for n in names)
        exec(
            f"def make({params}):\n    m = _new(_cls)\n"
            f"    m.__dict__ = {{{fields_from_args}}}\n    return m\n",
            ns,
        )
        fast = _fast_objects_match(cls, names, ns["slow_build"], ns["build"], ns["make"])
        if fast:
            build = ns["build"]
            make = ns["make"]
    return MessageSpec(
        cls=cls,
        msg_id=cls.id,
        crc_extra=cls.crc_extra,
        size=cls.unpacker.size,
        unpack=cls.unpacker.unpack,
        unpack_from=cls.unpacker.unpack_from,
        payload_of=payload_of,
        values_of=values_of,
        build=build,
        make=make,
        fast=not has_char and fast,
    )


# Specs are generated on first use of a message id: all ~230 classes up front cost every process ~0.13 s at
# import, and a process meets a dozen of them.
SPECS_BY_ID: dict[int, MessageSpec] = {}
SPECS_BY_CLASS: dict[type, MessageSpec] = {}
_EXTRA_BYTES = {msg_id: bytes([cls.crc_extra]) for msg_id, cls in mavlink.mavlink_map.items()}


def spec_for_id(msg_id: int) -> MessageSpec | None:
    """The spec of a common-dialect message id (generated on first use), None for an unknown id."""
    spec = SPECS_BY_ID.get(msg_id)
    if spec is None:
        cls = mavlink.mavlink_map.get(msg_id)
        if cls is None:
            return None
        spec = _make_spec(cls)
        SPECS_BY_ID[msg_id] = SPECS_BY_CLASS[cls] = spec
    return spec


def spec_for(cls: type) -> MessageSpec:
    """The spec of a pymavlink message class (generated on first use)."""
    spec = SPECS_BY_CLASS.get(cls)
    if spec is None:
        spec = spec_for_id(cls.id)
        if spec is None or spec.cls is not cls:
            raise KeyError(f"{cls.__name__} is not a message of the common dialect")
    return spec

# Used only for classes with char fields (STATUSTEXT, PARAM_*, ...): pymavlink packs them (it handles the
# string encodings), and the payload is reframed here.
_PLAIN_MAV = mavlink.MAVLink(None, 0, 0)


def payload_bytes(msg: Any) -> bytes:
    """The wire payload of a message, trailing zeros stripped as MAVLink 2 requires (at least 1 byte)."""
    spec = SPECS_BY_CLASS.get(type(msg)) or spec_for(type(msg))
    if spec.payload_of is not None:
        payload = spec.payload_of(msg)
    else:
        frame = msg.pack(_PLAIN_MAV)
        payload = frame[HEADER_LEN_V2:-2]
    return payload.rstrip(b"\x00") or b"\x00"


def pack_frame(
    msg: Any, seq: int, system_id: int, component_id: int, signing: Signing | None = None
) -> bytes:
    """One MAVLink 2 frame for a pymavlink message (signed when signing is given)."""
    spec = SPECS_BY_CLASS.get(type(msg)) or spec_for(type(msg))
    payload = payload_bytes(msg)
    msg_id = spec.msg_id
    body = _HEADER_V2.pack(
        STX_V2,
        len(payload),
        IFLAG_SIGNED if signing is not None else 0,
        0,
        seq,
        system_id,
        component_id,
        msg_id & 0xFFFF,
        msg_id >> 16,
    ) + payload
    crc = _mcrf4xx(_EXTRA_BYTES[msg_id], _mcrf4xx(body[1:]))
    frame = body + _CRC.pack(crc)
    if signing is not None:
        frame = signing.sign(frame)
    return frame


def kind(cls: type) -> tuple[bytes, bytes, Callable[..., bytes]]:
    """(3-byte message id, CRC extra byte, payload packer in wire order) of a pymavlink message class."""
    return cls.id.to_bytes(3, "little"), bytes([cls.crc_extra]), cls.unpacker.pack


def part_of(msg: object) -> tuple[bytes, bytes, bytes]:
    """(3-byte message id, CRC extra byte, payload) of a pymavlink message, for Framer.frames."""
    cls = type(msg)
    return cls.id.to_bytes(3, "little"), bytes([cls.crc_extra]), payload_bytes(msg)


class Framer:
    """MAVLink 2 frames straight from payloads, for one system and component.

    The sequence number lives in `counter.seq` (a UdpLink, so that frames it packs itself share it).
    """

    def __init__(self, system_id: int, component_id: int, counter: object, signing: Signing | None = None):
        self.counter = counter
        self.signing = signing
        # Header bytes 2..3 (incompat flags, compat flags) and 5..6 (system, component ids) never change.
        self._flags = 0x01 if signing is not None else 0
        self._system_id = system_id
        self._component_id = component_id

    def frames(self, parts: list[tuple[bytes, bytes, bytes]]) -> list[bytes]:
        """Frames of (3-byte message id, CRC extra, payload) parts, numbered in sequence."""
        seq = self.counter.seq
        flags, signing = self._flags, self.signing
        system_id, component_id = self._system_id, self._component_id
        head, crc_bytes, crc = _FRAME_HEAD.pack, _CRC.pack, _mcrf4xx
        out = []
        for msg_id, extra, payload in parts:
            payload = payload.rstrip(b"\x00") or b"\x00"
            tail = head(len(payload), flags, 0, seq, system_id, component_id, msg_id) + payload
            frame = b"\xfd" + tail + crc_bytes(crc(extra, crc(tail)))
            out.append(frame if signing is None else signing.sign(frame))
            seq = (seq + 1) & 0xFF
        self.counter.seq = seq
        return out


def decode_frame(frame: bytes, header_len: int, signature_len: int, spec: MessageSpec) -> Any:
    """Build the pymavlink message of a frame whose CRC (and signature) were already checked."""
    end = len(frame) - 2 - signature_len
    payload = frame[header_len:end]
    size = spec.size
    if len(payload) < size:
        payload = payload + bytes(size - len(payload))
    elif len(payload) > size:
        payload = payload[:size]
    if header_len == HEADER_LEN_V2:
        header = _Header(spec.msg_id, frame[2], frame[3], frame[1], frame[4], frame[5], frame[6])
    else:
        header = _Header(spec.msg_id, 0, 0, frame[1], frame[2], frame[3], frame[4])
    crc = (frame[end + 1] << 8) | frame[end]
    if signature_len:
        link_id = frame[-SIGNATURE_LEN]
        values = spec.unpack(payload)
        return spec.build(values, header, bytearray(frame), frame[header_len:end], crc, True, link_id)
    return spec.build(spec.unpack(payload), header, bytearray(frame), frame[header_len:end], crc, False, None)


def _find_marker(data: bytes, start: int) -> int:
    """Index of the next MAVLink start byte (v2 or v1) at or after start, or -1."""
    a = data.find(b"\xfd", start)
    b = data.find(b"\xfe", start)
    if a < 0:
        return b
    if b < 0:
        return a
    return a if a < b else b


def parse_datagram(
    data: bytes,
    stats: LinkStats,
    signing: Signing | None = None,
    accept_system_ids: frozenset[int] | None = None,
) -> list[tuple[Any, bytes]]:
    """Split one datagram into frames and decode the valid ones: [(message, raw frame)].

    Rejected frames are counted in `stats` by reason (see split_datagram); none is raised.
    """
    out: list[tuple[Any, bytes]] = []
    for spec, frame, header_len, signature_len in split_datagram(data, stats, signing, accept_system_ids):
        try:
            msg = decode_frame(frame, header_len, signature_len, spec)
        except Exception:  # a payload pymavlink cannot instantiate: drop it like any bad frame
            stats.bad_payload += 1
            continue
        out.append((msg, frame))
    return out


def unpack_frame(frame: bytes, header_len: int, signature_len: int, spec: MessageSpec) -> tuple:
    """The payload values of a checked frame in WIRE order (ordered_fieldnames, arrays flattened)."""
    end = len(frame) - 2 - signature_len
    size = spec.size
    if end - header_len == size:  # not truncated: read in place
        return spec.unpack_from(frame, header_len)
    payload = frame[header_len:end]
    if len(payload) < size:
        payload = payload + bytes(size - len(payload))
    elif len(payload) > size:
        payload = payload[:size]
    return spec.unpack(payload)


def split_datagram(
    data: bytes,
    stats: LinkStats,
    signing: Signing | None = None,
    accept_system_ids: frozenset[int] | None = None,
) -> list[tuple[MessageSpec, bytes, int, int]]:
    """The valid frames of one datagram: [(spec, frame, header_len, signature_len)], not yet decoded.

    Valid: a known message id, a good CRC, and (signing on) a good signature on a fresh timestamp, and an
    accepted system id. Every rejected frame is counted once in `stats` by its reason; after a rejection
    the splitter resynchronises on the next start byte without counting the bytes it skips as more errors.
    """
    return _split(data, stats, signing, accept_system_ids, False)[0]


def split_stream(
    data: bytes,
    stats: LinkStats,
    signing: Signing | None = None,
    accept_system_ids: frozenset[int] | None = None,
) -> tuple[list[tuple[MessageSpec, bytes, int, int]], int]:
    """Like split_datagram for bytes read from a stream (TCP): (valid frames, bytes consumed).

    A frame cut off at the end of `data` is not an error here: splitting stops at its first byte, and the
    caller keeps data[consumed:] to prepend to the next read.
    """
    return _split(data, stats, signing, accept_system_ids, True)


def _split(
    data: bytes,
    stats: LinkStats,
    signing: Signing | None,
    accept_system_ids: frozenset[int] | None,
    stream: bool,
) -> tuple[list[tuple[MessageSpec, bytes, int, int]], int]:
    out: list[tuple[MessageSpec, bytes, int, int]] = []
    n = len(data)
    i = 0
    resync = False  # set after a rejection: failing candidates until the next good frame are not counted
    specs = SPECS_BY_ID
    extras = _EXTRA_BYTES
    crc16 = _mcrf4xx
    head_v2 = _SPLIT_V2.unpack_from
    while i < n:
        stx = data[i]
        if stx != STX_V2 and stx != STX_V1:
            j = _find_marker(data, i + 1)
            end = n if j < 0 else j
            if not resync:
                stats.garbage += 1
                resync = True
            stats.garbage_bytes += end - i
            i = end
            continue
        if stx == STX_V2:
            if n - i < MIN_FRAME_V2:
                if stream:
                    return out, i
                if not resync:
                    stats.truncated += 1
                    resync = True
                stats.garbage_bytes += 1
                i += 1
                continue
            length, incompat, system_id, component_id, id_low, id_high = head_v2(data, i)
            if incompat & ~IFLAG_SIGNED:
                if not resync:
                    stats.garbage += 1
                    resync = True
                stats.garbage_bytes += 1
                i += 1
                continue
            signature_len = SIGNATURE_LEN if incompat & IFLAG_SIGNED else 0
            header_len = HEADER_LEN_V2
            msg_id = id_low | (id_high << 16)
        else:
            if n - i < HEADER_LEN_V1 + 2:
                if stream:
                    return out, i
                if not resync:
                    stats.truncated += 1
                    resync = True
                stats.garbage_bytes += 1
                i += 1
                continue
            signature_len = 0
            header_len = HEADER_LEN_V1
            length = data[i + 1]
            msg_id = data[i + 5]
            system_id = data[i + 3]
            component_id = data[i + 4]
        crc_end = i + header_len + length
        frame_end = crc_end + 2 + signature_len
        if frame_end > n:
            if stream:
                return out, i
            if not resync:
                stats.truncated += 1
                resync = True
            stats.garbage_bytes += 1
            i += 1
            continue
        spec = specs.get(msg_id) or spec_for_id(msg_id)
        if spec is None:
            if resync:
                stats.garbage_bytes += 1
                i += 1
            else:
                stats.unknown_id += 1
                i = frame_end
            continue
        crc = crc16(extras[msg_id], crc16(data[i + 1 : crc_end]))
        if crc != (data[crc_end] | (data[crc_end + 1] << 8)):
            if not resync:
                stats.bad_crc += 1
                resync = True
            stats.garbage_bytes += 1
            i += 1
            continue
        resync = False
        frame = data[i:frame_end]
        i = frame_end
        if signing is not None:
            reason = signing.verify(frame, system_id, component_id)
            if reason is not None:
                setattr(stats, reason, getattr(stats, reason) + 1)
                continue
        if accept_system_ids is not None and system_id not in accept_system_ids:
            stats.wrong_system += 1
            continue
        out.append((spec, frame, header_len, signature_len))
    return out, n


def self_check() -> list[str]:
    """What of this module disagrees with the installed pymavlink (empty: all agree).

    For every common-dialect message: the fast constructors were accepted (no char fields), and a frame
    packed here, from a message with non-zero fields, is byte-equal to pymavlink's own and decodes back to
    equal field values. bridge relies on pymavlink internals (class attributes, unpacker, orders): this is
    the check that a pymavlink version still fits (pyproject.toml pins the range it passed for).
    """
    problems = []
    mav = mavlink.MAVLink(None, srcSystem=7, srcComponent=9)
    for msg_id, cls in sorted(mavlink.mavlink_map.items()):
        spec = spec_for_id(msg_id)
        if spec is None or spec.cls is not cls:
            problems.append(f"{cls.__name__}: no spec")
            continue
        if spec.payload_of is not None and not spec.fast:
            problems.append(f"{cls.__name__}: fast constructor refused")
        if spec.payload_of is None:
            continue
        values = tuple((i % 5) + 1 for i in range(len(spec.unpack(bytes(spec.size)))))
        wire = spec.unpack(cls.unpacker.pack(*values))
        msg = spec.build(wire, _Header(msg_id), bytearray(), b"", 0, False, None)
        mav.seq = 3
        theirs = bytes(msg.pack(mav))
        ours = pack_frame(msg, 3, 7, 9)
        if ours != theirs:
            problems.append(f"{cls.__name__}: frame differs from pymavlink's")
            continue
        decoded = mavlink.MAVLink(None).decode(bytearray(ours))
        if [getattr(decoded, n) for n in cls.fieldnames] != [getattr(msg, n) for n in cls.fieldnames]:
            problems.append(f"{cls.__name__}: decodes to other values")
    return problems
