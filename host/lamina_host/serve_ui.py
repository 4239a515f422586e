"""``lamina serve-ui``: the terminal UI in a web browser, through ``textual-serve``.

Each browser tab gets its own ``lamina tui`` process (textual-serve runs the command per
connection), so what the tablet on the ward shows is exactly the terminal UI. The UI has
no login of its own: it listens on the loopback interface unless told otherwise, and
binding elsewhere needs ``--allow-remote`` and prints a warning.
"""

from __future__ import annotations

import shlex
import sys
from collections.abc import Sequence
from typing import Any

from aiohttp import web
from textual_serve.server import Server

from lamina_shared.errors import LaminaError
from lamina_shared.local import is_loopback

__all__ = ["RemoteRefused", "UiServer", "serve_ui", "tui_command"]


class RemoteRefused(LaminaError):
    """A bind beyond this machine was asked for without ``--allow-remote``."""


class UiServer(Server):
    """textual-serve's server, linking its page to the address the browser used.

    textual-serve writes absolute URLs from the bind address into the page, which a
    browser cannot reach for a wildcard bind (0.0.0.0): the page here names the host
    the request came to instead.
    """

    async def on_startup(self, app: web.Application) -> None:
        """Say where the UI is served (instead of textual-serve's banner)."""
        print(f"lamina: serving the terminal UI on http://{self.host}:{self.port} (Ctrl+C stops)")

    async def handle_index(self, request: web.Request) -> Any:
        """Serve the page that opens the app's websocket on the requested host."""
        self.public_url = f"{request.scheme}://{request.host}"
        return await super().handle_index(request)


def tui_command(tui_options: Sequence[str]) -> str:
    """Return the shell command that runs ``lamina tui`` with these options."""
    return shlex.join([sys.executable, "-m", "lamina_host", "tui", *tui_options])


def serve_ui(host: str, port: int, tui_options: Sequence[str], allow_remote: bool = False) -> None:
    """Serve the terminal UI on http://HOST:PORT until interrupted.

    Raises:
        RemoteRefused: ``host`` is not a loopback address and ``allow_remote`` is False.
        OSError: the address cannot be bound (in use, not this machine's).
    """
    if not is_loopback(host):
        if not allow_remote:
            raise RemoteRefused(
                f"--host {host} would let any machine that reaches it drive the scanner, with "
                "no login: add --allow-remote if that network is the box's own, or use "
                "127.0.0.1 and an SSH tunnel"
            )
        print(
            f"lamina: WARNING: serving the scanner's UI on {host}:{port} without a login; "
            "anyone who reaches it can drive the scanner and read the scan library",
            file=sys.stderr,
            flush=True,
        )
    server = UiServer(tui_command(tui_options), host, port, title="Lamina")
    server.serve()
