"""A message channel over any byte stream with pyserial's ``read``/``write`` interface.

Both ends use it over a pyserial port: the device on ``/dev/ttyGS0`` (or a
pseudo-terminal in simulation), the host on the matching port. Damaged frames are
counted and skipped; the message layer above decides what to do about gaps.
"""

from __future__ import annotations

import time
from collections import deque
from typing import Any, Protocol

from lamina_shared.protocol import FrameDecoder, Kind, Message, ProtocolError, decode_message


class ByteStream(Protocol):
    """The part of ``serial.Serial`` the channel needs."""

    timeout: float | None

    def read(self, size: int = 1) -> bytes: ...  # pragma: no cover - protocol

    def write(self, data: bytes) -> int | None: ...  # pragma: no cover - protocol

    @property
    def in_waiting(self) -> int: ...  # pragma: no cover - protocol


class LinkClosed(ConnectionError):
    """The other end went away (cable pulled, process ended)."""


class Channel:
    """Send framed bytes and receive decoded messages with a deadline."""

    def __init__(self, stream: ByteStream, poll_s: float = 0.05) -> None:
        self.stream = stream
        self.stream.timeout = poll_s
        self._decoder = FrameDecoder()
        self._pending: deque[Message] = deque()
        self.bad_messages = 0

    @property
    def bad_frames(self) -> int:
        """Return how many damaged frames were skipped so far."""
        return self._decoder.errors

    def send(self, frame: bytes) -> None:
        """Write one encoded frame (see :mod:`lamina_shared.protocol`)."""
        try:
            self.stream.write(frame)
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
        for payload in self._decoder.feed(data):
            try:
                self._pending.append(decode_message(payload))
            except ProtocolError:
                self.bad_messages += 1


def error_body(request_id: int, code: str, message: str) -> dict[str, Any]:
    """Return the body of a failed REPLY."""
    return {"id": request_id, "ok": False, "error": {"code": code, "message": message}}


def ok_body(request_id: int, result: dict[str, Any]) -> dict[str, Any]:
    """Return the body of a successful REPLY."""
    return {"id": request_id, "ok": True, "result": result}


__all__ = ["ByteStream", "Channel", "Kind", "LinkClosed", "error_body", "ok_body"]
