"""The device's end of the box's local endpoint: a listening TCP socket as a byte stream.

``lamina-device serve --listen 127.0.0.1:5187`` serves the host running on the same Pi
(``lamina tui --device local``), which opens the address with pyserial's ``socket://``
handler. :class:`ListeningPort` gives the server the part of ``serial.Serial`` its
``Channel`` uses, and serves one host at a time: a host that goes away reads as a
broken link once (the server puts the hardware in its safe state), then the port waits
for the next host; a second host while one is connected is told so and turned away.
"""

from __future__ import annotations

import array
import fcntl
import logging
import select
import socket
import termios
import time
from contextlib import suppress

from lamina_shared.local import is_loopback, parse_endpoint
from lamina_shared.protocol import Kind, encode_json

__all__ = ["ListeningPort", "open_listener"]

log = logging.getLogger(__name__)

REFUSAL = {
    "refused": {
        "code": "in-use",
        "message": "another host is connected to this device; one host at a time",
    }
}
"""The WELCOME a second host gets before its connection is closed."""
TURN_AWAY_S = 1.0
"""How long a turned-away connection stays half-open so the host reads the refusal."""


class ListeningPort:
    """Serve one host at a time on a listening TCP socket (pyserial's read/write shape)."""

    def __init__(self, host: str, port: int) -> None:
        self.timeout: float | None = 0.05
        self.write_timeout: float | None = 10.0
        self._listener = socket.create_server((host, port), backlog=1)
        self._listener.setblocking(False)
        self._conn: socket.socket | None = None
        self._turned_away: dict[socket.socket, tuple[float, bool]] = {}
        """Second hosts' connections: when each is closed, and whether it was told why."""

    @property
    def address(self) -> tuple[str, int]:
        """Return the (host, port) listened on (the port the system chose for port 0)."""
        host, port = self._listener.getsockname()[:2]
        return str(host), int(port)

    @property
    def connected(self) -> bool:
        """Return True while a host is connected."""
        return self._conn is not None

    @property
    def in_waiting(self) -> int:
        """Return how many received bytes wait to be read (0 with no host)."""
        if self._conn is None:
            return 0
        count = array.array("i", [0])
        fcntl.ioctl(self._conn.fileno(), termios.FIONREAD, count)
        return count[0]

    def read(self, size: int = 1) -> bytes:
        """Return up to ``size`` bytes, b"" after ``timeout`` with nothing to read.

        Raises:
            ConnectionError: the host closed its end (reported once; then a new host is awaited).
        """
        watch = [self._listener] if self._conn is None else [self._listener, self._conn]
        ready, _, _ = select.select([*watch, *self._turned_away], [], [], self.timeout)
        if self._turned_away:
            self._serve_turned_away(ready)
        if self._listener in ready:
            self._accept()
        if self._conn is None or self._conn not in ready:
            return b""
        try:
            data = self._conn.recv(max(size, 1))
        except OSError:
            self._drop()
            raise
        if not data:
            self._drop()
            raise ConnectionResetError("the host closed the connection")
        return data

    def write(self, data: bytes) -> int:
        """Send all of ``data`` to the connected host within ``write_timeout``."""
        if self._conn is None:
            raise ConnectionError("no host is connected")
        try:
            self._conn.sendall(data)
        except OSError:
            self._drop()
            raise
        return len(data)

    def _accept(self) -> None:
        try:
            conn, peer = self._listener.accept()
        except BlockingIOError:
            return
        if self._conn is not None:
            log.warning("turned away a second host from %s: one host at a time", peer)
            self._turn_away(conn)
            return
        log.info("host connected from %s", peer)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        conn.settimeout(self.write_timeout)
        self._conn = conn

    def _turn_away(self, conn: socket.socket) -> None:
        """Keep a second host's connection until it speaks, to tell it why it is refused.

        The refusal is a WELCOME with ``refused`` (``shared/PROTOCOL.md``), so the host
        can say the device is in use rather than that the link broke. It answers the
        host's first bytes (its HELLO): sent at once, it could arrive before the host
        opened its port, and pyserial empties the input buffer on opening.
        """
        conn.setblocking(False)
        self._turned_away[conn] = (time.monotonic() + 5 * TURN_AWAY_S, False)

    def _serve_turned_away(self, ready: list[socket.socket]) -> None:
        """Answer turned-away hosts that spoke; close those whose time is up."""
        now = time.monotonic()
        for conn, (until, refused) in list(self._turned_away.items()):
            if conn in ready:
                data = b""
                with suppress(OSError):
                    data = conn.recv(4096)  # what the host sent: closing unread would reset
                if not data:
                    until = now  # the host hung up (or the socket failed)
                elif not refused:
                    with suppress(OSError):
                        conn.setblocking(True)
                        conn.settimeout(0.5)
                        conn.sendall(encode_json(Kind.WELCOME, REFUSAL))
                        conn.shutdown(socket.SHUT_WR)
                        conn.setblocking(False)
                    until, refused = now + TURN_AWAY_S, True
            if now >= until:
                conn.close()
                del self._turned_away[conn]
            else:
                self._turned_away[conn] = (until, refused)

    def _drop(self) -> None:
        if self._conn is not None:
            self._conn.close()
            self._conn = None

    def close(self) -> None:
        """Close the connection and stop listening."""
        for conn in self._turned_away:
            conn.close()
        self._turned_away.clear()
        self._drop()
        self._listener.close()


def open_listener(spec: str) -> ListeningPort:
    """Listen on ``spec`` (``socket://HOST:PORT``, ``HOST:PORT`` or ``local``; port 0: any).

    Raises:
        EndpointError: the address is malformed.
        OSError: the address cannot be listened on (in use, not this machine's).
    """
    host, port = parse_endpoint(spec, listening=True)
    if not is_loopback(host):
        log.warning(
            "listening on %s: any machine that reaches it can drive the laser and motors; "
            "use 127.0.0.1 unless the network is the box's own",
            host,
        )
    return ListeningPort(host, port)
