"""The box's local endpoint: host and device on the same Pi, joined by a TCP socket.

The device program listens (``lamina-device serve --listen``); the host opens the same
address with pyserial's ``socket://`` URL handler, so the same ``DeviceClient`` and
``Channel`` code runs as over a USB serial line. The device link has no authentication,
so the endpoint listens on the loopback interface unless told otherwise.
"""

from __future__ import annotations

import ipaddress

from lamina_shared.errors import LaminaError

__all__ = [
    "LOCAL_HOST",
    "LOCAL_PORT",
    "EndpointError",
    "is_loopback",
    "local_url",
    "parse_endpoint",
]

LOCAL_HOST = "127.0.0.1"
"""Where the box's device service listens by default: this machine only."""

LOCAL_PORT = 5187
"""The default TCP port of the box's device service (``--device local``)."""

SOCKET_SCHEME = "socket://"


class EndpointError(LaminaError, ValueError):
    """A local endpoint address that cannot be used."""


def parse_endpoint(text: str, listening: bool = False) -> tuple[str, int]:
    """Return (host, port) of ``socket://HOST:PORT``, ``HOST:PORT``, ``local`` or ``local:PORT``.

    Port 0 (any free port, printed when serving) is accepted only when ``listening``.
    """
    spec = text.strip()
    if spec == "local":
        return LOCAL_HOST, LOCAL_PORT
    if spec.startswith("local:"):
        host, port_text = LOCAL_HOST, spec.removeprefix("local:")
    else:
        host, sep, port_text = spec.removeprefix(SOCKET_SCHEME).rpartition(":")
        if not sep or not host:
            raise EndpointError(
                f"{text!r} is not an endpoint: write socket://HOST:PORT, e.g. "
                f"{local_url(LOCAL_PORT)}, or local"
            )
    host = host.strip("[]")
    lowest = 0 if listening else 1
    if not port_text.isdigit() or not lowest <= int(port_text) < 65536:
        raise EndpointError(f"{text!r}: the port must be a number from {lowest} to 65535")
    return host, int(port_text)


def local_url(port: int = LOCAL_PORT, host: str = LOCAL_HOST) -> str:
    """Return the pyserial URL of an endpoint."""
    return f"{SOCKET_SCHEME}{host}:{port}"


def is_loopback(host: str) -> bool:
    """Return True when ``host`` names only this machine (localhost or a loopback address)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False
