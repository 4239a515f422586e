"""The handshake's messages as the host reads them: HELLO out, WELCOME or a refusal back.

The host repeats HELLO until the device answers (``DeviceClient.hello``); the WELCOME is
read with the shared schema (:class:`lamina_shared.messages.Welcome`), and a WELCOME
that ``refused`` the session (a device service that already serves a host) is turned
into the one line the host prints.
"""

from __future__ import annotations

from typing import Any

from lamina_host.link.errors import DeviceError
from lamina_shared.errors import printable
from lamina_shared.messages import Hello, MessageError, Welcome
from lamina_shared.protocol import PROTOCOL_VERSION

MAX_REFUSAL_CHARS = 200
"""Longest reason of a refusal the host repeats."""


def hello_body(session: str) -> dict[str, Any]:
    """Return the HELLO body of this host's ``session``."""
    return Hello(session, PROTOCOL_VERSION, "lamina-host").to_wire()


def read_welcome(body: Any) -> Welcome:
    """Return the WELCOME a device sent; raise DeviceError naming every problem.

    A device of another protocol version gets the mismatch named, both versions given.
    """
    try:
        welcome = Welcome.from_wire(body)
    except MessageError as exc:
        raise DeviceError(f"the device's handshake is malformed ({exc})") from None
    if welcome.protocol != PROTOCOL_VERSION:
        raise DeviceError(
            f"the device speaks protocol version {welcome.protocol}, this host speaks "
            f"{PROTOCOL_VERSION}: install matching lamina-device and lamina-host versions"
        )
    return welcome


def refusal_of(body: Any) -> str | None:
    """Return why a WELCOME turned this host away (printable, short), None if it did not."""
    refusal = body.get("refused") if isinstance(body, dict) else None
    if refusal is None:
        return None
    reason = refusal.get("message") if isinstance(refusal, dict) else None
    return printable(str(reason or "no reason given"))[:MAX_REFUSAL_CHARS]


def in_use(reason: str) -> DeviceError:
    """Return the error of a device that serves another host (``reason``: its refusal)."""
    return DeviceError(
        f"the device is in use by another host ({reason}): close the other "
        "terminal UI, browser tab or scan using it, or wait for it to finish, then "
        "connect again"
    )
