"""The Lamina wire protocol: framing, message kinds and their encodings.

See ``shared/PROTOCOL.md`` for the specification. A frame on the wire is
``0x00 || COBS(kind || body || crc32_le(kind || body)) || 0x00``: the zero byte only
ever appears as a delimiter, so a reader resynchronises at the next zero after garbage.

Decoding anything received raises nothing but :class:`ProtocolError`, and allocates at
most a small multiple of :data:`MAX_PAYLOAD_BYTES` whatever the bytes say.
"""

from __future__ import annotations

import json
import math
import struct
import zlib
from dataclasses import dataclass, replace
from enum import IntEnum
from functools import lru_cache
from typing import Any

import numpy as np

from lamina_shared.errors import LaminaError
from lamina_shared.types import CONFIDENCE_SCALE, TARGETS, Segment

PROTOCOL_VERSION = 5
MAX_PAYLOAD_BYTES = 64 * 1024
"""Largest decoded payload either end accepts; longer frames are discarded unread."""

CHUNK_BYTES = 512
"""Size of the pieces a binary transfer is cut into: small enough that most pieces still
get through a line with one byte error in a thousand."""

MAX_TRANSFER_BYTES = 32 * 1024 * 1024
"""Largest binary transfer (calibration image, preview frame) either end accepts."""

ROW_SCALE = 64
"""Stripe rows travel as fixed-point integers in units of 1/ROW_SCALE pixel."""

MAX_SEGMENT_POINTS = 65_535
"""A segment holds at most one point per image column and at most this many."""

MAX_ACK_SEQS = 1024
"""Most sequence numbers one ACK may carry."""

_RICE_BLOCK = 32  # values per Rice block: each block picks its own parameter k
_RICE_MAX_K = 15  # k travels as a 4-bit nibble
_ROW_LIMIT_Q = 65_536 * ROW_SCALE  # rows stay below 65,536 px
_SCALE_BITS = 8  # confidence scales travel in 1/256: confidence = peak * scale / 256
_SCALE_LIMIT = 1 << 20  # above any scale a confidence byte needs (255 * 256 + 128)
COLOUR_FLAG = 0x80
"""Set in a SEGMENT's target byte when its points carry sRGB colour (negotiated, PROTOCOL.md)."""


class ProtocolError(LaminaError):
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
    ACK = 8
    HEARTBEAT = 9


JSON_KINDS = frozenset(
    {Kind.HELLO, Kind.WELCOME, Kind.REQUEST, Kind.REPLY, Kind.EVENT, Kind.ACK, Kind.HEARTBEAT}
)


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
    if len(frame) > FrameDecoder.MAX_ENCODED:
        raise ProtocolError("frame longer than the largest valid frame")
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

    MAX_ENCODED = MAX_PAYLOAD_BYTES + 4 + (MAX_PAYLOAD_BYTES + 4) // 254 + 2
    _MAX_ENCODED = MAX_ENCODED  # the name protocol v1 tests used

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
        if len(self._buffer) > self.MAX_ENCODED:
            self._buffer.clear()
            self._overflow = True
        return payloads


# --- varints and Rice codes -------------------------------------------------------------


def _put_varint(out: bytearray, value: int) -> None:
    """Append an unsigned LEB128 varint."""
    while value >= 0x80:
        out.append((value & 0x7F) | 0x80)
        value >>= 7
    out.append(value)


def _get_varint(data: bytes, at: int) -> tuple[int, int]:
    """Return (value, next offset) of the u32 varint at ``at``."""
    value = 0
    for shift in range(0, 35, 7):
        if at >= len(data):
            raise ProtocolError("segment ends inside a varint")
        byte = data[at]
        at += 1
        value |= (byte & 0x7F) << shift
        if not byte & 0x80:
            if value >= 2**32:
                raise ProtocolError("varint exceeds 32 bits")
            return value, at
    raise ProtocolError("varint longer than 5 bytes")


def _zigzag(values: np.ndarray) -> np.ndarray:
    """Map signed integers to unsigned ones, small magnitudes to small codes."""
    return (values << 1) ^ (values >> 63)


def _unzigzag(codes: np.ndarray) -> np.ndarray:
    """Invert :func:`_zigzag`."""
    return (codes >> 1) ^ -(codes & 1)


def _rice_parameters(values: np.ndarray) -> np.ndarray:
    """Return the cheapest Rice parameter k of each block of ``values`` (int64, >= 0)."""
    blocks = -(-len(values) // _RICE_BLOCK)
    padded = np.zeros(blocks * _RICE_BLOCK, np.int64)
    padded[: len(values)] = values
    counts = np.full(blocks, _RICE_BLOCK)
    if len(values) % _RICE_BLOCK:
        counts[-1] = len(values) % _RICE_BLOCK
    grid = padded.reshape(blocks, _RICE_BLOCK)
    # Cost of block b with parameter k: sum(v >> k) unary bits + count * (1 + k) bits.
    costs = np.stack([(grid >> k).sum(axis=1) + counts * (1 + k) for k in range(_RICE_MAX_K + 1)])
    return np.argmin(costs, axis=0).astype(np.int64)


def _rice_encode(fields: list[np.ndarray]) -> bytes:
    """Rice-code non-negative integer fields; per block, unary and remainder parts apart.

    Keeping all unary parts in one bit stream and all remainders in another lets the
    decoder find every value with whole-array operations: the unary stream's one bits
    are exactly the terminators.
    """
    ks_per_field = [_rice_parameters(f) for f in fields]
    nibbles = np.concatenate([*ks_per_field, np.zeros(0, np.int64)])
    values = np.concatenate([*fields, np.zeros(0, np.int64)])
    k = np.concatenate(
        [np.repeat(ks, _RICE_BLOCK)[: len(f)] for ks, f in zip(ks_per_field, fields, strict=True)]
        + [np.zeros(0, np.int64)]
    )
    quotient = values >> k
    unary = np.zeros(int((quotient + 1).sum()), np.uint8)
    unary[np.cumsum(quotient + 1) - 1] = 1
    remainder = values & ((1 << k) - 1)
    starts = np.cumsum(k) - k
    bits = np.zeros(int(k.sum()), np.uint8)
    for j in range(_RICE_MAX_K):
        take = j < k
        bits[starts[take] + j] = (remainder[take] >> (k[take] - 1 - j)) & 1
    if len(nibbles) % 2:
        nibbles = np.append(nibbles, 0)
    packed_k = (nibbles[0::2] << 4 | nibbles[1::2]).astype(np.uint8).tobytes()
    unary_bytes = np.packbits(unary).tobytes()
    out = bytearray(packed_k)
    _put_varint(out, len(unary_bytes))
    return bytes(out) + unary_bytes + np.packbits(bits).tobytes()


def _rice_decode(data: bytes, at: int, lengths: list[int]) -> list[np.ndarray]:
    """Invert :func:`_rice_encode` for fields of ``lengths`` values; the data must end there."""
    blocks = [-(-n // _RICE_BLOCK) for n in lengths]
    nibble_bytes = -(-sum(blocks) // 2)
    if at + nibble_bytes > len(data):
        raise ProtocolError("segment ends inside its Rice parameters")
    packed = np.frombuffer(data, np.uint8, nibble_bytes, at).astype(np.int64)
    nibbles = np.stack([packed >> 4, packed & 15], axis=1).ravel()[: sum(blocks)]
    unary_len, at = _get_varint(data, at + nibble_bytes)
    total = sum(lengths)
    if at + unary_len > len(data) or 8 * unary_len < total:
        raise ProtocolError("segment's unary stream does not fit its length")
    unary = np.unpackbits(np.frombuffer(data, np.uint8, unary_len, at))
    ends = np.flatnonzero(unary)
    if len(ends) != total or (total and unary_len != ends[-1] // 8 + 1):
        raise ProtocolError("segment's unary stream holds the wrong number of values")
    quotient = np.diff(ends, prepend=-1).astype(np.int64) - 1
    k_parts, start = [], 0
    for n, b in zip(lengths, blocks, strict=True):
        k_parts.append(np.repeat(nibbles[start : start + b], _RICE_BLOCK)[:n])
        start += b
    k = np.concatenate([*k_parts, np.zeros(0, np.int64)])
    rest = data[at + unary_len :]
    if len(rest) != -(-int(k.sum()) // 8):
        raise ProtocolError("segment's remainder stream has the wrong length")
    bits = np.unpackbits(np.frombuffer(rest, np.uint8)).astype(np.int64)
    starts = np.cumsum(k) - k
    remainder = np.zeros(total, np.int64)
    for j in range(_RICE_MAX_K):
        take = j < k
        remainder[take] = (remainder[take] << 1) | bits[starts[take] + j]
    values = (quotient << k) | remainder
    return list(np.split(values, np.cumsum(lengths)[:-1]))


# --- segments ---------------------------------------------------------------------------


def quantise_rows(rows: np.ndarray) -> np.ndarray:
    """Return stripe rows rounded to the wire's 1/ROW_SCALE px grid, as float32 (exact)."""
    q = np.rint(np.asarray(rows, np.float64) * ROW_SCALE)
    return (q / ROW_SCALE).astype(np.float32)


def quantise_segment(segment: Segment) -> Segment:
    """Return ``segment`` as it will arrive: rows on the wire's fixed-point grid.

    The device applies this before it sends or buffers a segment, so a live scan, its
    replay and every retransmission carry identical bits.
    """
    return replace(segment, rows=quantise_rows(segment.rows))


def _scale_bounds(peak: np.ndarray, confidence: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return per point the integer scales q with ``confidence == _confidence(peak, q)``."""
    p = np.maximum(peak, 1)
    lo = np.maximum(-(-(256 * confidence - 128) // p), 0)
    hi = np.where(confidence >= 255, _SCALE_LIMIT, -(-(256 * confidence + 128) // p) - 1)
    free = peak == 0  # a point without a peak has confidence 0 whatever the scale
    if np.any(free & (confidence != 0)):
        raise ProtocolError("a segment point with peak 0 must have confidence 0")
    return np.where(free, 0, lo), np.where(free, _SCALE_LIMIT, hi)


def _confidence(peak: np.ndarray, scale: np.ndarray | int) -> np.ndarray:
    """Return ``round(peak * scale / 256)`` capped at 255: the decoder's confidence."""
    return np.minimum((peak * scale + (1 << (_SCALE_BITS - 1))) >> _SCALE_BITS, 255)


def confidence_bytes(peak: np.ndarray, noise_sigma_dn: float) -> np.ndarray:
    """Return each point's confidence byte: peak over ``noise_sigma_dn`` (see ``Segment``).

    Computed as the decoder does, through one integer scale, so a segment whose points
    share one noise travels with a single scale run.
    """
    scale = round((CONFIDENCE_SCALE << _SCALE_BITS) / max(noise_sigma_dn, 1e-3))
    scale = min(scale, _SCALE_LIMIT - 1)
    if isinstance(peak, np.ndarray) and peak.dtype == np.uint8 and peak.ndim:
        # The device's 8-bit peaks: one look-up instead of five passes (the same bytes).
        return _confidence_table(scale)[peak]
    return _confidence(np.asarray(peak, np.int64), scale).astype(np.uint8)


@lru_cache(maxsize=256)
def _confidence_table(scale: int) -> np.ndarray:
    """Return the confidence byte of every 8-bit peak at ``scale`` (read-only, shared).

    A view's noise, hence its scale, changes little from view to view, so a scan
    reuses a few tables.
    """
    table = _confidence(np.arange(256, dtype=np.int64), scale).astype(np.uint8)
    table.flags.writeable = False
    return table


def _scale_runs(peak: np.ndarray, confidence: np.ndarray) -> list[tuple[int, int]]:
    """Return the fewest (run length, scale) pairs that reproduce ``confidence`` from ``peak``.

    The device's confidence is peak over a noise that changes slowly along the stripe,
    so one scale holds for long runs of points: each run costs a few bytes where the
    confidence bytes themselves would cost as much as the peaks. Greedy interval
    intersection gives the fewest runs.
    """
    lo, hi = _scale_bounds(peak, confidence)
    runs: list[tuple[int, int]] = []
    low, high, length, previous = 0, _SCALE_LIMIT, 0, 0
    for a, b in zip(lo.tolist(), hi.tolist(), strict=True):
        if max(low, a) > min(high, b):
            previous = min(max(previous, low), high)
            runs.append((length, previous))
            low, high, length = a, b, 0
        low, high, length = max(low, a), min(high, b), length + 1
    if length:
        runs.append((length, min(max(previous, low), high)))
    return runs


_SEGMENT_HEAD = struct.Struct("<IIBHHddiHIBB")
"""request id, seq, target, section, view, z_mm, angle_deg, turns, n, first row (1/64 px),
first peak, first width."""


def encode_segment_body(request_id: int, seq: int, segment: Segment) -> bytes:
    """Return the compact binary body of one SEGMENT message (see PROTOCOL.md).

    Raises:
        ProtocolError: if the segment cannot travel exactly (rows off the fixed-point
            grid, columns not strictly increasing, too many points).
    """
    n = len(segment)
    if n > MAX_SEGMENT_POINTS:
        raise ProtocolError(f"segment of {n} points exceeds {MAX_SEGMENT_POINTS}")
    cols = segment.cols.astype(np.int64)
    if n and (np.any(np.diff(cols) <= 0) or cols[0] < 0 or cols[-1] > 65_535):
        raise ProtocolError("segment columns must be strictly increasing u16 values")
    scaled = segment.rows.astype(np.float64) * ROW_SCALE
    rows_q = np.rint(scaled).astype(np.int64)
    if np.any(rows_q != scaled) or np.any((rows_q < 0) | (rows_q >= _ROW_LIMIT_Q)):
        raise ProtocolError("segment rows must be quantised (quantise_segment) and in range")
    peak, width = segment.peak.astype(np.int64), segment.width.astype(np.int64)
    firsts = (int(rows_q[0]), int(peak[0]), int(width[0])) if n else (0, 0, 0)
    coloured = segment.has_colour
    head = _SEGMENT_HEAD.pack(
        request_id,
        seq,
        TARGETS.index(segment.target) | (COLOUR_FLAG if coloured else 0),
        segment.section,
        segment.view,
        segment.z_mm,
        segment.angle_deg,
        segment.turns,
        n,
        *firsts,
    )
    out = bytearray(head)
    # Columns come in runs of neighbours: (gap before the run, run length - 1) pairs.
    breaks = np.flatnonzero(np.diff(cols) != 1) + 1
    run_starts = np.concatenate([[0], breaks]) if n else np.zeros(0, np.int64)
    run_ends = np.concatenate([breaks, [n]]) if n else np.zeros(0, np.int64)
    _put_varint(out, len(run_starts))
    previous_end = 0
    for s, e in zip(run_starts.tolist(), run_ends.tolist(), strict=True):
        _put_varint(out, int(cols[s]) - previous_end)
        _put_varint(out, e - s - 1)
        previous_end = int(cols[e - 1]) + 1
    # Confidence: runs of points sharing one scale, (length - 1, zigzag scale change).
    scale_runs = _scale_runs(peak, segment.confidence.astype(np.int64)) if n else []
    _put_varint(out, len(scale_runs))
    previous_scale = 0
    for length, scale in scale_runs:
        _put_varint(out, length - 1)
        change = scale - previous_scale
        _put_varint(out, 2 * change if change >= 0 else -2 * change - 1)  # zigzag
        previous_scale = scale
    channels = list(segment.colour.astype(np.int64).T) if coloured else []
    if coloured:
        out += bytes(int(c[0]) for c in channels)  # the first point's r, g, b
    fields = [_zigzag(np.diff(a)) for a in (rows_q, peak, width, *channels)] if n else []
    return bytes(out) + (_rice_encode(fields) if n > 1 else b"")


def encode_segment(request_id: int, seq: int, segment: Segment) -> bytes:
    """Return the framed bytes of one SEGMENT message."""
    return encode_frame(bytes([Kind.SEGMENT]) + encode_segment_body(request_id, seq, segment))


@dataclass(frozen=True)
class SegmentEvent:
    """Segment ``seq`` (its index in the scan plan) sent while request ``request_id`` runs."""

    request_id: int
    seq: int
    segment: Segment


def _decode_columns(body: bytes, at: int, n: int) -> tuple[np.ndarray, int]:
    """Return the segment's columns from their run-length form and the next offset."""
    runs, at = _get_varint(body, at)
    if runs > n or (n and not runs):
        raise ProtocolError("segment has an impossible number of column runs")
    starts: list[int] = []
    lengths: list[int] = []
    previous_end = count = 0
    for _ in range(runs):
        gap, at = _get_varint(body, at)
        length, at = _get_varint(body, at)
        start = previous_end + gap
        previous_end = start + length + 1
        count += length + 1
        if (starts and gap == 0) or previous_end > 65_536 or count > n:
            raise ProtocolError("segment column runs overlap or leave the u16 range")
        starts.append(start)
        lengths.append(length + 1)
    if count != n:
        raise ProtocolError("segment column runs do not add up to its point count")
    cols = np.concatenate(
        [np.arange(s, s + m, dtype=np.uint16) for s, m in zip(starts, lengths, strict=True)]
        + [np.zeros(0, np.uint16)]
    )
    return cols, at


def _decode_scale_runs(body: bytes, at: int, n: int) -> tuple[np.ndarray, int]:
    """Return each point's confidence scale from the scale runs and the next offset."""
    runs, at = _get_varint(body, at)
    if runs > n or (n and not runs):
        raise ProtocolError("segment has an impossible number of confidence runs")
    lengths, scales = np.zeros(runs, np.int64), np.zeros(runs, np.int64)
    scale = 0
    for k in range(runs):
        length, at = _get_varint(body, at)
        change, at = _get_varint(body, at)
        scale += change >> 1 if not change & 1 else -(change >> 1) - 1  # zigzag
        if not 0 <= scale < _SCALE_LIMIT or length >= n:
            raise ProtocolError("segment confidence run out of range")
        lengths[k], scales[k] = length + 1, scale
    if lengths.sum() != n:
        raise ProtocolError("segment confidence runs do not add up to its point count")
    return np.repeat(scales, lengths), at


def decode_segment_body(body: bytes) -> SegmentEvent:
    """Invert :func:`encode_segment_body`; raise :class:`ProtocolError` if malformed."""
    if len(body) < _SEGMENT_HEAD.size:
        raise ProtocolError("segment message shorter than its header")
    head = _SEGMENT_HEAD.unpack_from(body)
    request_id, seq, target, section, view, z_mm, angle_deg, turns, n, row0, peak0, width0 = head
    coloured = bool(target & COLOUR_FLAG)
    target &= ~COLOUR_FLAG
    if target >= len(TARGETS):
        raise ProtocolError(f"unknown segment target code {target}")
    if not (math.isfinite(z_mm) and math.isfinite(angle_deg)):
        raise ProtocolError("segment with a non-finite height or angle")
    cols, at = _decode_columns(body, _SEGMENT_HEAD.size, n)
    scales, at = _decode_scale_runs(body, at, n)
    if coloured and n == 0:
        raise ProtocolError("an empty segment cannot carry colour")
    firsts = [row0, peak0, width0]
    if coloured:
        if at + 3 > len(body):
            raise ProtocolError("segment ends inside its first colour")
        firsts += list(body[at : at + 3])
        at += 3
    if n > 1:
        diffs = _rice_decode(body, at, [n - 1] * len(firsts))
    elif at != len(body) or (n == 0 and (row0 or peak0 or width0)):
        raise ProtocolError("segment carries bytes after its last point")
    else:
        diffs = [np.zeros(0, np.int64)] * len(firsts)
    rows_q, peak, width, *channels = (
        np.cumsum(np.concatenate([[first], _unzigzag(d)]))[:n]
        for first, d in zip(firsts, diffs, strict=True)
    )
    if np.any((rows_q < 0) | (rows_q >= _ROW_LIMIT_Q)):
        raise ProtocolError("segment row outside 0..65535 px")
    if np.any((peak < 0) | (peak > 255) | (width < 0) | (width > 255)):
        raise ProtocolError("segment peak or width outside 0..255")
    colour = np.stack(channels, axis=1) if coloured else np.zeros((0, 3), np.int64)
    if np.any((colour < 0) | (colour > 255)):
        raise ProtocolError("segment colour outside 0..255")
    segment = Segment(
        TARGETS[target],
        section,
        view,
        z_mm,
        angle_deg,
        cols,
        (rows_q / ROW_SCALE).astype(np.float32),
        peak.astype(np.uint8),
        width.astype(np.uint8),
        _confidence(peak, scales).astype(np.uint8),
        colour.astype(np.uint8),
        turns,
    )
    return SegmentEvent(request_id, seq, segment)


# --- other messages ---------------------------------------------------------------------

_CHUNK_HEAD = struct.Struct("<IIII")


def encode_json(kind: Kind, body: dict[str, Any]) -> bytes:
    """Return the framed bytes of a JSON message."""
    if kind not in JSON_KINDS:
        raise ProtocolError(f"{kind.name} is not a JSON message kind")
    text = json.dumps(body, separators=(",", ":"), allow_nan=False)
    return encode_frame(bytes([kind]) + text.encode())


def encode_chunk(request_id: int, transfer: int, offset: int, total: int, data: bytes) -> bytes:
    """Return the framed bytes of one piece of binary transfer ``transfer``."""
    head = _CHUNK_HEAD.pack(request_id, transfer, offset, total)
    return encode_frame(bytes([Kind.CHUNK]) + head + data)


@dataclass(frozen=True)
class Chunk:
    """Bytes ``offset..offset+len(data)`` of transfer ``transfer`` (``total`` bytes long)."""

    request_id: int
    transfer: int
    offset: int
    total: int
    data: bytes


def _reject_constant(name: str) -> Any:
    raise ProtocolError(f"JSON constant {name} is not allowed")


def _decode_json(kind: Kind, body: bytes) -> Message:
    try:
        data = json.loads(body.decode(), parse_constant=_reject_constant)
    except (UnicodeDecodeError, ValueError, RecursionError) as exc:
        # ValueError covers JSONDecodeError and integers too long to convert.
        raise ProtocolError(f"{kind.name} body is not valid JSON: {exc}") from None
    if not isinstance(data, dict):
        raise ProtocolError(f"{kind.name} body must be a JSON object")
    return Message(kind, data)


def decode_message(payload: bytes) -> Message:
    """Decode a payload from :class:`FrameDecoder`; raise :class:`ProtocolError` if invalid."""
    if not payload:
        raise ProtocolError("empty payload")
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise ProtocolError("payload longer than the protocol allows")
    try:
        kind = Kind(payload[0])
    except ValueError:
        raise ProtocolError(f"unknown message kind {payload[0]}") from None
    body = payload[1:]
    if kind in JSON_KINDS:
        return _decode_json(kind, body)
    if kind is Kind.SEGMENT:
        return Message(kind, decode_segment_body(body))
    if len(body) < _CHUNK_HEAD.size:
        raise ProtocolError("chunk message shorter than its header")
    request_id, transfer, offset, total = _CHUNK_HEAD.unpack_from(body)
    data = body[_CHUNK_HEAD.size :]
    if total > MAX_TRANSFER_BYTES or offset + len(data) > total:
        raise ProtocolError("chunk runs past its transfer's size or the transfer limit")
    return Message(kind, Chunk(request_id, transfer, offset, total, data))


def segment_bytes_per_point(segment: Segment) -> float:
    """Return the framed wire size of ``segment`` divided by its point count."""
    return len(encode_segment(0, 0, quantise_segment(segment))) / max(1, len(segment))
