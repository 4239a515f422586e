"""A message channel over any byte stream with pyserial's ``read``/``write`` interface.

Both ends use it over a pyserial port: the device on ``/dev/ttyGS0`` (or a
pseudo-terminal in simulation), the host on the matching port. Damaged frames are
counted and skipped; the message layer above (sequence numbers, acknowledgements,
retried requests) makes up for what the line loses.

Frames adapt to the line (protocol 4): a message longer than the line lets through is
sent as FRAGMENT frames, each checked on its own. A fragment names its message by the
CRC-32 of the whole payload, so the fragments of a repeated message (a WELCOME answering
a repeated HELLO, a resent segment, a cached reply) fill the gaps the earlier copies
left: a long message gets through a noisy line after a few repeats, not after the rare
repeat that arrives whole. Each end sizes its fragments from the byte error rate it
measures on what it receives (:class:`FrameSizer`), shrinking on CRC failures and
timeouts and growing back on a clean line.
"""

from __future__ import annotations

import math
import struct
import threading
import time
import zlib
from collections import OrderedDict, deque
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from lamina_shared.errors import LaminaError
from lamina_shared.limits import DeviceLimits
from lamina_shared.protocol import (
    MAX_PAYLOAD_BYTES,
    FrameDecoder,
    Kind,
    Message,
    ProtocolError,
    decode_frame,
    decode_message,
    encode_frame,
)

FRAGMENT_KIND = 10
"""Payload kind of a fragment: ``10 || message crc32 || total || offset || bytes`` (u32 LE).

It is a framing matter, below :class:`~lamina_shared.protocol.Kind`: a channel joins
fragments into the message's payload before decoding it."""
_FRAGMENT_HEAD = struct.Struct("<BIII")
REPAIR_KIND = 11
"""Payload kind of a repair request: ``11 || message crc32 || total || (offset, length)...``."""
_REPAIR_HEAD = struct.Struct("<BII")
_RANGE = struct.Struct("<II")
MAX_REPAIR_RANGES = 8
"""Most byte ranges one repair request names (it stays one small frame)."""
MAX_REPAIR_FRAMES = 32
"""Most repair requests sent at once for one message."""
FRAME_OVERHEAD_BYTES = 24
"""Bytes a fragment frame adds to its data: kind, header, CRC, COBS and delimiters."""


class ByteStream(Protocol):
    """The part of ``serial.Serial`` the channel needs."""

    timeout: float | None

    def read(self, size: int = 1) -> bytes: ...  # pragma: no cover - protocol

    def write(self, data: bytes) -> int | None: ...  # pragma: no cover - protocol

    @property
    def in_waiting(self) -> int: ...  # pragma: no cover - protocol


class LinkClosed(LaminaError, ConnectionError):
    """The other end went away (cable pulled, process ended)."""


@dataclass
class FrameSizer:
    """The largest fragment worth sending, from the byte error rate measured on the line.

    A frame of ``n`` bytes arrives with probability ``(1 - p)^n``; with fragments that
    combine across repeats, the useful bytes per byte sent peak near a frame of
    ``sqrt(overhead / p)`` bytes. ``p`` is estimated from the received bytes and the
    damaged frames among them over the last ``memory_bytes``; it starts pessimistic
    (small frames until the line proves clean), and a timeout (``penalise``) counts as
    one more error, so both ends shrink on a failing line and grow back on a clean one.
    """

    min_bytes: int = 96
    max_bytes: int = MAX_PAYLOAD_BYTES
    memory_bytes: float = 100_000.0
    errors: float = 1.0
    bytes_seen: float = 300.0

    def observe(self, nbytes: int, errors: int) -> None:
        """Count ``nbytes`` received, ``errors`` damaged frames among them."""
        self.errors += errors
        self.bytes_seen += nbytes
        if self.bytes_seen > self.memory_bytes:
            # Forget old evidence at the rate new bytes come in: an exponential window.
            fade = self.memory_bytes / self.bytes_seen
            self.errors *= fade
            self.bytes_seen = self.memory_bytes

    def penalise(self) -> None:
        """Count a timeout (something sent was not answered) as one error."""
        self.errors += 1.0

    @property
    def error_rate(self) -> float:
        """Return the estimated probability that a byte is damaged, dropped or doubled."""
        return self.errors / self.bytes_seen

    @property
    def fragment_bytes(self) -> int:
        """Return the most payload bytes one frame should carry now."""
        best = math.sqrt(FRAME_OVERHEAD_BYTES / max(self.error_rate, 1e-12))
        return int(min(self.max_bytes, max(self.min_bytes, best - FRAME_OVERHEAD_BYTES)))


def fragment_frames(payload: bytes, size: int, start: int = 0, stop: int | None = None) -> bytes:
    """Return the FRAGMENT frames of ``payload[start:stop]``, ``size`` payload bytes each."""
    crc, total = zlib.crc32(payload), len(payload)
    stop = total if stop is None else min(stop, total)
    return b"".join(
        encode_frame(
            _FRAGMENT_HEAD.pack(FRAGMENT_KIND, crc, total, at) + payload[at : min(at + size, stop)]
        )
        for at in range(start, stop, size)
    )


def repair_frame(crc: int, total: int, ranges: list[tuple[int, int]]) -> bytes:
    """Return a REPAIR frame asking for the byte ``ranges`` of fragmented message ``crc``."""
    body = b"".join(_RANGE.pack(offset, length) for offset, length in ranges[:MAX_REPAIR_RANGES])
    return encode_frame(_REPAIR_HEAD.pack(REPAIR_KIND, crc, total) + body)


def decode_repair(payload: bytes) -> tuple[tuple[int, int], list[tuple[int, int]]]:
    """Return ((crc, total), ranges) of a REPAIR payload; raise ProtocolError if malformed."""
    body = payload[_REPAIR_HEAD.size :]
    if len(payload) < _REPAIR_HEAD.size or len(body) % _RANGE.size:
        raise ProtocolError("malformed repair request")
    if len(body) // _RANGE.size > MAX_REPAIR_RANGES:
        raise ProtocolError("repair request names too many ranges")
    _, crc, total = _REPAIR_HEAD.unpack_from(payload)
    ranges = [_RANGE.unpack_from(body, at) for at in range(0, len(body), _RANGE.size)]
    if any(length == 0 or offset + length > total for offset, length in ranges):
        raise ProtocolError("repair range outside its message")
    if sum(length for _, length in ranges) > total:
        # Overlapping ranges must not make a short request cost many copies of a message.
        raise ProtocolError("repair ranges longer than their message")
    return (crc, total), ranges


@dataclass
class _Partial:
    data: bytearray
    have: np.ndarray
    missing: int
    touched_s: float
    frame_no: int
    repairs: int = 0
    asked_s: float = -math.inf


def _gaps(have: np.ndarray) -> list[tuple[int, int]]:
    """Return the (offset, length) runs where ``have`` is False."""
    edges = np.flatnonzero(np.diff(np.concatenate(([1], have.view(np.int8), [1]))))
    return [(int(a), int(b - a)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


@dataclass
class Reassembly:
    """Fragments put back together, whatever order, loss or repetition they came in.

    Bounded: at most ``max_messages`` messages and ``max_bytes`` of them in progress;
    beyond that the one that waited longest is dropped (its sender repeats it anyway).
    :meth:`repairs` names the gaps of messages whose fragments stopped coming, for the
    sender to fill from what it keeps (:class:`SentMessages`).
    """

    max_messages: int
    max_bytes: int
    idle_s: float = 0.05
    """A message nothing arrived for in this long has lost its missing pieces."""
    repeat_s: float = 0.25
    max_repairs: int = 10
    _partials: OrderedDict[tuple[int, int], _Partial] = field(default_factory=OrderedDict)
    _done: OrderedDict[tuple[int, int], None] = field(default_factory=OrderedDict)
    _held_bytes: int = 0
    _frames: int = 0

    def count_frame(self) -> None:
        """Note that a valid frame arrived: earlier messages' gaps are losses now."""
        self._frames += 1

    def take(self, payload: bytes, now_s: float) -> bytes | None:
        """Keep one fragment's payload; return the whole message's once complete.

        Raises:
            ProtocolError: a malformed fragment, or a whole whose CRC differs from its name.
        """
        if len(payload) <= _FRAGMENT_HEAD.size:
            raise ProtocolError("fragment shorter than its header")
        _, crc, total, offset = _FRAGMENT_HEAD.unpack_from(payload)
        data = payload[_FRAGMENT_HEAD.size :]
        if not 0 < total <= MAX_PAYLOAD_BYTES or offset + len(data) > total:
            raise ProtocolError("fragment runs past its message or the payload limit")
        key = (crc, total)
        partial = self._partials.pop(key, None)
        if partial is None:
            partial = self._open(total, now_s)
        self._partials[key] = partial  # the most recently touched goes last
        end = offset + len(data)
        new_bytes = len(data) - int(np.count_nonzero(partial.have[offset:end]))
        if new_bytes:
            partial.repairs = 0  # repairs bring it on: keep asking
        partial.missing -= new_bytes
        partial.have[offset:end] = True
        partial.data[offset:end] = data
        partial.touched_s, partial.frame_no = now_s, self._frames
        if partial.missing:
            return None
        self._drop(key)
        whole = bytes(partial.data)
        if zlib.crc32(whole) != crc:
            raise ProtocolError("fragments do not make up the message they name")
        self._done[key] = None
        self._done.move_to_end(key)
        while len(self._done) > self.max_messages:
            self._done.popitem(last=False)
        return whole

    def repairs(self, now_s: float) -> list[tuple[tuple[int, int], list[tuple[int, int]]]]:
        """Return the gaps to ask for now: (message key, missing ranges) per message.

        A message whose fragments stopped (a later frame came, or nothing for
        ``idle_s``) is asked for ``repeat_s`` apart, up to ``max_repairs`` times in a row
        without a new byte arriving; one
        completed before is not (a late copy of it is no loss, and a repeat the sender
        means to deliver comes whole or with its own repeat).
        """
        due = []
        for key, partial in self._partials.items():
            stopped = self._frames > partial.frame_no or now_s - partial.touched_s > self.idle_s
            if (
                stopped
                and partial.repairs < self.max_repairs
                and now_s - partial.asked_s > self.repeat_s
                and key not in self._done
            ):
                partial.repairs += 1
                partial.asked_s = now_s
                due.append((key, _gaps(partial.have)))
        return due

    def _open(self, total: int, now_s: float) -> _Partial:
        while self._partials and (
            len(self._partials) >= self.max_messages or self._held_bytes + total > self.max_bytes
        ):
            self._drop(next(iter(self._partials)))
        self._held_bytes += total
        return _Partial(bytearray(total), np.zeros(total, bool), total, now_s, self._frames)

    def _drop(self, key: tuple[int, int]) -> None:
        if self._partials.pop(key, None) is not None:
            self._held_bytes -= key[1]

    def __len__(self) -> int:
        return len(self._partials)

    @property
    def held_bytes(self) -> int:
        """Return the bytes of the messages in progress (bounded by ``max_bytes``)."""
        return self._held_bytes


@dataclass
class SentMessages:
    """The last fragmented messages sent, kept to fill the gaps the peer asks for; bounded."""

    max_messages: int
    max_bytes: int
    _kept: OrderedDict[tuple[int, int], bytes] = field(default_factory=OrderedDict)
    _held_bytes: int = 0

    def keep(self, payload: bytes) -> None:
        """Remember ``payload`` (sent in fragments), forgetting the oldest beyond the bounds."""
        key = (zlib.crc32(payload), len(payload))
        if key in self._kept:
            self._kept.move_to_end(key)
            return
        self._kept[key] = payload
        self._held_bytes += len(payload)
        while len(self._kept) > self.max_messages or self._held_bytes > self.max_bytes:
            _, old = self._kept.popitem(last=False)
            self._held_bytes -= len(old)

    def get(self, key: tuple[int, int]) -> bytes | None:
        """Return the payload named ``key``, if still kept."""
        return self._kept.get(key)


class Channel:
    """Send framed bytes and receive decoded messages with a deadline.

    ``send`` may be called from several threads (the device's scan worker and its
    reader); ``receive`` from one thread only.
    """

    def __init__(
        self,
        stream: ByteStream,
        poll_s: float = 0.05,
        write_timeout_s: float = 10.0,
        limits: DeviceLimits | None = None,
    ) -> None:
        self.stream = stream
        self.stream.timeout = poll_s
        if hasattr(stream, "write_timeout"):
            # A peer that stops reading must not block us forever (pyserial then raises
            # SerialTimeoutException, an OSError, which becomes LinkClosed).
            stream.write_timeout = write_timeout_s
        limits = limits or DeviceLimits()
        self._decoder = FrameDecoder()
        self.sizer = FrameSizer()
        """Sizes the frames sent from the error rate of what is received."""
        self._reassembly = Reassembly(limits.max_partial_messages, limits.max_reassembly_bytes)
        self._sent = SentMessages(limits.max_partial_messages, limits.max_reassembly_bytes)
        self.repairs_asked = 0
        self.repairs_served = 0
        self._pending: deque[Message] = deque()
        self._send_lock = threading.Lock()
        self.bad_messages = 0
        self.bytes_sent = 0
        self.bytes_received = 0
        self.last_received_s = time.monotonic()
        """When the last valid message arrived (``time.monotonic()``)."""
        self.reader: Any = None
        """The one reader of this channel (a ``lamina_shared.endpoint.Dispatcher``), if any."""

    @property
    def bad_frames(self) -> int:
        """Return how many damaged frames were skipped so far."""
        return self._decoder.errors

    def send(self, frame: bytes) -> None:
        """Write one encoded frame (see :mod:`lamina_shared.protocol`), fragmented if long.

        A frame longer than :attr:`sizer` allows goes as FRAGMENT frames (one write).
        """
        size = self.sizer.fragment_bytes
        if len(frame) > size + FRAME_OVERHEAD_BYTES:
            # Our own frame: its delimiters are the first and last bytes.
            payload = decode_frame(frame[1:-1])
            frame = fragment_frames(payload, size)
            with self._send_lock:
                self._sent.keep(payload)
        self._write(frame)

    def _write(self, frame: bytes) -> None:
        try:
            with self._send_lock:
                self.stream.write(frame)
                self.bytes_sent += len(frame)
        except (OSError, ValueError) as exc:
            raise LinkClosed(f"link closed while sending: {exc}") from exc

    def receive(self, timeout_s: float) -> Message | None:
        """Return the next message, or None if none arrived within ``timeout_s``."""
        deadline = time.monotonic() + timeout_s
        while not self._pending:
            if time.monotonic() >= deadline:
                return None
            self._read_some()
        return self._pending.popleft()

    def _read_some(self) -> None:
        try:
            waiting = self.stream.in_waiting
            data = self.stream.read(max(1, waiting))
        except (OSError, ValueError, TypeError) as exc:
            # pyserial raises SerialException (an OSError) when the peer hangs up.
            raise LinkClosed(f"link closed: {exc}") from exc
        self.bytes_received += len(data)
        errors = self._decoder.errors
        payloads = self._decoder.feed(data)
        self.sizer.observe(len(data), self._decoder.errors - errors)
        now = time.monotonic()
        for payload in payloads:
            self._reassembly.count_frame()
            try:
                if payload[0] == REPAIR_KIND:
                    self._repair(payload)
                    continue
                if payload[0] == FRAGMENT_KIND:
                    self.last_received_s = now  # a piece proves the peer is there
                    whole = self._reassembly.take(payload, now)
                    if whole is None:
                        continue
                    payload = whole
                self._pending.append(decode_message(payload))
                self.last_received_s = now
            except ProtocolError:
                self.bad_messages += 1
        for (crc, total), gaps in self._reassembly.repairs(now):
            self.repairs_asked += 1
            asks = range(
                0, min(len(gaps), MAX_REPAIR_FRAMES * MAX_REPAIR_RANGES), MAX_REPAIR_RANGES
            )
            self._write(
                b"".join(repair_frame(crc, total, gaps[at : at + MAX_REPAIR_RANGES]) for at in asks)
            )

    def _repair(self, payload: bytes) -> None:
        """Send again the pieces of one of our fragmented messages the peer lacks."""
        key, ranges = decode_repair(payload)
        with self._send_lock:
            kept = self._sent.get(key)
        if kept is None:
            return  # long gone: the layer above repeats what matters
        self.repairs_served += 1
        size = self.sizer.fragment_bytes
        self._write(b"".join(fragment_frames(kept, size, a, a + n) for a, n in ranges))


class Ticker:
    """Say when something periodic (a heartbeat) is due, without a thread of its own."""

    def __init__(self, period_s: float) -> None:
        self.period_s = period_s
        self._next_s = time.monotonic()

    def due(self) -> bool:
        """Return True (and restart the period) if the period has elapsed."""
        now = time.monotonic()
        if now < self._next_s:
            return False
        self._next_s = now + self.period_s
        return True


def error_body(request_id: int, code: str, message: str) -> dict[str, Any]:
    """Return the body of a failed REPLY."""
    return {"id": request_id, "ok": False, "error": {"code": code, "message": message}}


def ok_body(request_id: int, result: dict[str, Any]) -> dict[str, Any]:
    """Return the body of a successful REPLY."""
    return {"id": request_id, "ok": True, "result": result}


def is_count(value: object, limit: int = 2**32) -> bool:
    """Return True for a JSON integer in ``0..limit-1`` (bools are not integers here)."""
    return isinstance(value, int) and not isinstance(value, bool) and 0 <= value < limit


__all__ = [
    "FRAGMENT_KIND",
    "REPAIR_KIND",
    "ByteStream",
    "Channel",
    "FrameSizer",
    "Kind",
    "LinkClosed",
    "Reassembly",
    "SentMessages",
    "Ticker",
    "decode_repair",
    "error_body",
    "fragment_frames",
    "is_count",
    "ok_body",
    "repair_frame",
]
