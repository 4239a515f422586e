"""The host's end of the box's local endpoint (``--device local`` or ``socket://HOST:PORT``).

The device program on the same Pi listens (``lamina-device serve --listen local``); the
host opens it with pyserial's own ``socket://`` URL handler, so ``DeviceClient`` and
``Channel`` run unchanged. That handler reports at most one byte waiting, which would
make the channel read byte by byte, and leaves Nagle's algorithm on, which holds small
frames back; :class:`SocketPort` reports the socket's true count and sends at once.
"""

from __future__ import annotations

import array
import fcntl
import socket
import termios

import serial
from serial.urlhandler.protocol_socket import Serial as SocketSerial

from lamina_shared.errors import LaminaError
from lamina_shared.local import local_url, parse_endpoint

__all__ = ["SocketPort", "is_endpoint", "open_endpoint"]


class SocketPort(SocketSerial):
    """pyserial's socket:// port, with ``in_waiting`` counting every byte received."""

    def open(self) -> None:
        """Connect, then send small frames (acknowledgements) at once, not after Nagle's wait."""
        super().open()
        self._socket.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)

    @property
    def in_waiting(self) -> int:
        """Return how many received bytes wait to be read."""
        sock = self._socket  # close() may clear it from another thread
        if not self.is_open or sock is None:
            raise serial.PortNotOpenError()
        count = array.array("i", [0])
        fcntl.ioctl(sock.fileno(), termios.FIONREAD, count)
        # A closed peer reads as readable with 0 bytes: let read() find the end.
        return max(count[0], super().in_waiting)


def is_endpoint(device: str) -> bool:
    """Return True when ``device`` names a local endpoint rather than a serial port."""
    return device == "local" or device.startswith(("local:", "socket://"))


def open_endpoint(device: str, error: type[LaminaError]) -> SocketPort:
    """Open the endpoint ``device`` names; raise ``error`` (one line) when nothing answers."""
    try:
        host, port = parse_endpoint(device)
    except ValueError as exc:
        raise error(str(exc)) from None
    url = local_url(port, host)
    try:
        return SocketPort(url, timeout=0.05)
    except (serial.SerialException, OSError) as exc:
        reason = str(exc).rpartition("] ")[2] or str(exc)
        raise error(
            f"no device service answers at {url} ({reason}): start it on the box "
            "(sudo systemctl start lamina-device-local, or lamina-device serve --listen local)"
        ) from None
