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


def fragment_frames(payload: bytes, size: int) -> list[bytes]:
    """Return the FRAGMENT frames of ``payload``, at most ``size`` payload bytes each."""
    crc, total = zlib.crc32(payload), len(payload)
    return [
        encode_frame(_FRAGMENT_HEAD.pack(FRAGMENT_KIND, crc, total, at) + payload[at : at + size])
        for at in range(0, total, size)
    ]


@dataclass
class _Partial:
    data: bytearray
    have: np.ndarray
    missing: int


@dataclass
class Reassembly:
    """Fragments put back together, whatever order, loss or repetition they came in.

    Bounded: at most ``max_messages`` messages and ``max_bytes`` of them in progress;
    beyond that the one that waited longest is dropped (its sender repeats it anyway).
    """

    max_messages: int
    max_bytes: int
    _partials: OrderedDict[tuple[int, int], _Partial] = field(default_factory=OrderedDict)
    _held_bytes: int = 0

    def take(self, payload: bytes) -> bytes | None:
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
            partial = self._open(total)
        self._partials[key] = partial  # the most recently touched goes last
        end = offset + len(data)
        partial.missing -= len(data) - int(np.count_nonzero(partial.have[offset:end]))
        partial.have[offset:end] = True
        partial.data[offset:end] = data
        if partial.missing:
            return None
        self._drop(key)
        whole = bytes(partial.data)
        if zlib.crc32(whole) != crc:
            raise ProtocolError("fragments do not make up the message they name")
        return whole

    def _open(self, total: int) -> _Partial:
        while self._partials and (
            len(self._partials) >= self.max_messages or self._held_bytes + total > self.max_bytes
        ):
            self._drop(next(iter(self._partials)))
        self._held_bytes += total
        return _Partial(bytearray(total), np.zeros(total, bool), total)

    def _drop(self, key: tuple[int, int]) -> None:
        if self._partials.pop(key, None) is not None:
            self._held_bytes -= key[1]

    def __len__(self) -> int:
        return len(self._partials)

    @property
    def held_bytes(self) -> int:
        """Return the bytes of the messages in progress (bounded by ``max_bytes``)."""
        return self._held_bytes


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
            frame = b"".join(fragment_frames(decode_frame(frame[1:-1]), size))
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
        for payload in payloads:
            try:
                if payload[0] == FRAGMENT_KIND:
                    self.last_received_s = time.monotonic()  # a piece proves the peer is there
                    whole = self._reassembly.take(payload)
                    if whole is None:
                        continue
                    payload = whole
                self._pending.append(decode_message(payload))
                self.last_received_s = time.monotonic()
            except ProtocolError:
                self.bad_messages += 1


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
    "ByteStream",
    "Channel",
    "FrameSizer",
    "Kind",
    "LinkClosed",
    "Reassembly",
    "Ticker",
    "error_body",
    "fragment_frames",
    "is_count",
    "ok_body",
]
