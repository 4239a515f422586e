"""The Lamina wire protocol: framing, message kinds and their encodings.

See ``shared/PROTOCOL.md`` for the specification. A frame on the wire is
``0x00 || COBS(kind || body || crc32_le(kind || body)) || 0x00``: the zero byte only
ever appears as a delimiter, so a reader resynchronises at the next zero after garbage.
"""

from __future__ import annotations

import json
import struct
import zlib
from dataclasses import dataclass
from enum import IntEnum
from typing import Any

import numpy as np

from lamina_shared.types import TARGETS, Segment

PROTOCOL_VERSION = 1
MAX_PAYLOAD_BYTES = 64 * 1024
"""Largest decoded payload either end accepts; longer frames are discarded unread."""

CHUNK_BYTES = 4096
"""Size of the pieces a binary transfer (calibration image) is cut into."""


class ProtocolError(Exception):
    """A frame or message that does not follow the protocol."""


class Kind(IntEnum):
    """The first byte of every payload: what the rest of it is."""

    HELLO = 1
    WELCOME = 2
    REQUEST = 3
    REPLY = 4
    SEGMENT = 5
    EVENT = 6
    CHUNK = 7


JSON_KINDS = frozenset({Kind.HELLO, Kind.WELCOME, Kind.REQUEST, Kind.REPLY, Kind.EVENT})


@dataclass(frozen=True)
class Message:
    """One decoded message: JSON kinds carry a dict, binary kinds their decoded form."""

    kind: Kind
    body: Any


# --- COBS -----------------------------------------------------------------------------


def cobs_encode(data: bytes) -> bytes:
    """Return ``data`` with every zero byte removed by consistent overhead byte stuffing."""
    out = bytearray()
    for piece in data.split(b"\0"):
        # A block holds at most 254 data bytes; a full block (code 255) implies no zero.
        while len(piece) >= 254:
            out.append(255)
            out += piece[:254]
            piece = piece[254:]
        out.append(len(piece) + 1)
        out += piece
    return bytes(out)


def cobs_decode(data: bytes) -> bytes:
    """Invert :func:`cobs_encode`; raise :class:`ProtocolError` on malformed input."""
    out = bytearray()
    i, n = 0, len(data)
    while i < n:
        code = data[i]
        block = data[i + 1 : i + code]
        if code == 0 or len(block) != code - 1 or 0 in block:
            raise ProtocolError("malformed COBS block")
        out += block
        i += code
        if code != 255 and i < n:
            out.append(0)
    return bytes(out)


# --- frames ---------------------------------------------------------------------------


def encode_frame(payload: bytes) -> bytes:
    """Wrap a payload for the wire: CRC-32, COBS, delimiter."""
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise ProtocolError(f"payload of {len(payload)} bytes exceeds {MAX_PAYLOAD_BYTES}")
    crc = zlib.crc32(payload).to_bytes(4, "little")
    # The leading delimiter ends any garbage before the frame, so the frame survives it.
    return b"\0" + cobs_encode(payload + crc) + b"\0"


def decode_frame(frame: bytes) -> bytes:
    """Unwrap one delimiter-free frame and check its CRC; return the payload."""
    raw = cobs_decode(frame)
    if len(raw) < 5:
        raise ProtocolError("frame too short to hold a kind byte and a CRC")
    payload, crc = raw[:-4], raw[-4:]
    if zlib.crc32(payload).to_bytes(4, "little") != crc:
        raise ProtocolError("CRC mismatch")
    return payload


class FrameDecoder:
    """Split a byte stream into payloads, skipping garbage and damaged frames.

    Bytes after the last delimiter are kept for the next :meth:`feed`; a run longer
    than any valid frame is dropped so a noisy line cannot grow memory without bound.
    """

    _MAX_ENCODED = MAX_PAYLOAD_BYTES + 4 + (MAX_PAYLOAD_BYTES + 4) // 254 + 2

    def __init__(self) -> None:
        self._buffer = bytearray()
        self._overflow = False
        self.errors = 0

    def feed(self, data: bytes) -> list[bytes]:
        """Add received bytes; return the payloads of the frames they complete."""
        payloads = []
        self._buffer += data
        while True:
            end = self._buffer.find(0)
            if end == -1:
                break
            frame = bytes(self._buffer[:end])
            del self._buffer[: end + 1]
            if self._overflow:
                self._overflow = False
                self.errors += 1
                continue
            if not frame:
                continue
            try:
                payloads.append(decode_frame(frame))
            except ProtocolError:
                self.errors += 1
        if len(self._buffer) > self._MAX_ENCODED:
            self._buffer.clear()
            self._overflow = True
        return payloads


# --- messages -------------------------------------------------------------------------

_SEGMENT_HEAD = struct.Struct("<IBHHddI")
_CHUNK_HEAD = struct.Struct("<III")


def encode_json(kind: Kind, body: dict[str, Any]) -> bytes:
    """Return the framed bytes of a JSON message."""
    if kind not in JSON_KINDS:
        raise ProtocolError(f"{kind.name} is not a JSON message kind")
    text = json.dumps(body, separators=(",", ":"), allow_nan=False)
    return encode_frame(bytes([kind]) + text.encode())


def encode_segment(request_id: int, segment: Segment) -> bytes:
    """Return the framed bytes of one segment event (see PROTOCOL.md for the layout)."""
    head = _SEGMENT_HEAD.pack(
        request_id,
        TARGETS.index(segment.target),
        segment.section,
        segment.view,
        segment.z_mm,
        segment.angle_deg,
        len(segment),
    )
    body = b"".join(
        (
            head,
            np.ascontiguousarray(segment.cols, dtype="<u2").tobytes(),
            np.ascontiguousarray(segment.rows, dtype="<f4").tobytes(),
            np.ascontiguousarray(segment.peak, dtype="u1").tobytes(),
            np.ascontiguousarray(segment.width, dtype="u1").tobytes(),
        )
    )
    return encode_frame(bytes([Kind.SEGMENT]) + body)


def encode_chunk(request_id: int, offset: int, total: int, data: bytes) -> bytes:
    """Return the framed bytes of one piece of a binary transfer."""
    return encode_frame(bytes([Kind.CHUNK]) + _CHUNK_HEAD.pack(request_id, offset, total) + data)


@dataclass(frozen=True)
class Chunk:
    """One piece of a binary transfer answering request ``request_id``."""

    request_id: int
    offset: int
    total: int
    data: bytes


@dataclass(frozen=True)
class SegmentEvent:
    """A segment sent while request ``request_id`` runs."""

    request_id: int
    segment: Segment


def _decode_segment(body: bytes) -> SegmentEvent:
    if len(body) < _SEGMENT_HEAD.size:
        raise ProtocolError("segment message shorter than its header")
    req, target, section, view, z_mm, angle_deg, n = _SEGMENT_HEAD.unpack_from(body)
    if target >= len(TARGETS):
        raise ProtocolError(f"unknown segment target code {target}")
    if len(body) != _SEGMENT_HEAD.size + 8 * n:
        raise ProtocolError(f"segment of {n} points has {len(body)} bytes")
    if not (np.isfinite(z_mm) and np.isfinite(angle_deg)):
        raise ProtocolError("segment with a non-finite height or angle")
    at = _SEGMENT_HEAD.size
    cols = np.frombuffer(body, "<u2", n, at).astype(np.uint16)
    rows = np.frombuffer(body, "<f4", n, at + 2 * n).astype(np.float32)
    peak = np.frombuffer(body, "u1", n, at + 6 * n).copy()
    width = np.frombuffer(body, "u1", n, at + 7 * n).copy()
    segment = Segment(TARGETS[target], section, view, z_mm, angle_deg, cols, rows, peak, width)
    return SegmentEvent(req, segment)


def decode_message(payload: bytes) -> Message:
    """Decode a payload from :class:`FrameDecoder`; raise :class:`ProtocolError` if invalid."""
    if not payload:
        raise ProtocolError("empty payload")
    try:
        kind = Kind(payload[0])
    except ValueError:
        raise ProtocolError(f"unknown message kind {payload[0]}") from None
    body = payload[1:]
    if kind in JSON_KINDS:
        try:
            data = json.loads(body.decode())
        except (UnicodeDecodeError, json.JSONDecodeError) as exc:
            raise ProtocolError(f"{kind.name} body is not valid JSON: {exc}") from None
        if not isinstance(data, dict):
            raise ProtocolError(f"{kind.name} body must be a JSON object")
        return Message(kind, data)
    if kind is Kind.SEGMENT:
        return Message(kind, _decode_segment(body))
    if len(body) < _CHUNK_HEAD.size:
        raise ProtocolError("chunk message shorter than its header")
    req, offset, total = _CHUNK_HEAD.unpack_from(body)
    data = body[_CHUNK_HEAD.size :]
    if offset + len(data) > total:
        raise ProtocolError("chunk runs past the transfer's declared size")
    return Message(kind, Chunk(req, offset, total, data))
