"""A message channel over any byte stream with pyserial's ``read``/``write`` interface.

Both ends use it over a pyserial port: the device on ``/dev/ttyGS0`` (or a
pseudo-terminal in simulation), the host on the matching port. Damaged frames are
counted and skipped; the message layer above (sequence numbers, acknowledgements,
retried requests) makes up for what the line loses.
"""

from __future__ import annotations

import threading
import time
from collections import deque
from typing import Any, Protocol

from lamina_shared.errors import LaminaError
from lamina_shared.protocol import FrameDecoder, Kind, Message, ProtocolError, decode_message


class ByteStream(Protocol):
    """The part of ``serial.Serial`` the channel needs."""

    timeout: float | None

    def read(self, size: int = 1) -> bytes: ...  # pragma: no cover - protocol

    def write(self, data: bytes) -> int | None: ...  # pragma: no cover - protocol

    @property
    def in_waiting(self) -> int: ...  # pragma: no cover - protocol


class LinkClosed(LaminaError, ConnectionError):
    """The other end went away (cable pulled, process ended)."""


class Channel:
    """Send framed bytes and receive decoded messages with a deadline.

    ``send`` may be called from several threads (the device's scan worker and its
    reader); ``receive`` from one thread only.
    """

    def __init__(
        self, stream: ByteStream, poll_s: float = 0.05, write_timeout_s: float = 10.0
    ) -> None:
        self.stream = stream
        self.stream.timeout = poll_s
        if hasattr(stream, "write_timeout"):
            # A peer that stops reading must not block us forever (pyserial then raises
            # SerialTimeoutException, an OSError, which becomes LinkClosed).
            stream.write_timeout = write_timeout_s
        self._decoder = FrameDecoder()
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
        """Write one encoded frame (see :mod:`lamina_shared.protocol`)."""
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
        for payload in self._decoder.feed(data):
            try:
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
    "ByteStream",
    "Channel",
    "Kind",
    "LinkClosed",
    "Ticker",
    "error_body",
    "is_count",
    "ok_body",
]
