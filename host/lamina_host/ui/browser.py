"""``lamina serve-ui``: the terminal UI in a web browser, through ``textual-serve``.

Each browser tab gets its own ``lamina tui`` process (textual-serve runs the command per
connection), so what the tablet on the ward shows is exactly the terminal UI. The UI has
no login of its own: it listens on the loopback interface unless told otherwise, and
binding elsewhere needs ``--allow-remote`` and prints a warning.

A page on another site must not drive the scanner through the visitor's browser: every
request must name this server in its ``Host`` (the configured address and port; for a
wildcard bind an address of this machine or its name), a websocket must come from one
of the origins those imply, and anything else gets 403 Forbidden. That also closes DNS
rebinding, where another site's name is pointed at this address. The page names the
address the check accepted, rebuilt from its parsed parts, never the request's text.

Nothing the page loads comes from outside the box (a ward network may reach nothing else):
textual-serve's page asks a web-font service for Roboto Mono, so the page is served with
that link replaced by the same font from textual-serve's own static folder.
"""

from __future__ import annotations

import asyncio
import ipaddress
import re
import shlex
import signal
import socket
import sys
from collections.abc import Awaitable, Callable, Sequence
from contextlib import suppress
from typing import Any

from aiohttp import web
from textual_serve.server import Server

from lamina_shared.errors import LaminaError
from lamina_shared.local import is_loopback

__all__ = ["RemoteRefused", "UiServer", "allowed_names", "serve_ui", "tui_command"]

WILDCARDS = frozenset({"", "0.0.0.0", "::"})
"""Bind addresses meaning every interface of this machine."""
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")
"""What a browser on this machine may call a loopback server."""

OUTSIDE_FONT = re.compile(r"<link\b[^>]*\bhref=\"https?://fonts\.googleapis\.com/[^>]*>", re.S)
"""textual-serve's link to a web-font service (the only thing its page fetches from outside)."""
LOCAL_FONT = (
    "<style>@font-face {{ font-family: 'Roboto Mono'; font-weight: 100 700; "
    "src: url('{static}fonts/RobotoMono-VariableFont_wght.ttf') format('truetype'); }}</style>"
)
"""The same font from textual-serve's own static folder (``{static}``: its URL)."""

CHECKED_HOST = web.RequestKey("lamina_checked_host", str)
"""The request's ``Host`` as :meth:`UiServer.checked_host` accepted it."""

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


class RemoteRefused(LaminaError):
    """A bind beyond this machine was asked for without ``--allow-remote``."""


def _canonical(name: str) -> str:
    """Return a host name or address in one form: lower case, an IPv6 address compressed."""
    name = name.lower()
    try:
        return str(ipaddress.ip_address(name))
    except ValueError:
        return name


def _machine_names() -> set[str]:
    """Return this machine's names and the addresses they resolve to."""
    names = {socket.gethostname(), socket.getfqdn()}
    names |= {f"{name.split('.')[0]}.local" for name in set(names) if name}
    with suppress(OSError):
        for info in socket.getaddrinfo(socket.gethostname(), None):
            names.add(str(info[4][0]))
    return {_canonical(name) for name in names if name}


def allowed_names(host: str) -> tuple[frozenset[str], bool]:
    """Return the host names a request may name for a server bound to ``host``.

    Args:
        host: the bind address (``--host``).

    Returns:
        The accepted names (canonical form), and whether any IP address literal is
        accepted too (a wildcard bind: the browser typed one of this machine's addresses,
        which no other site can borrow).
    """
    names = {_canonical(host)} if host not in WILDCARDS else set()
    if is_loopback(host) or host in WILDCARDS:
        names |= {_canonical(name) for name in LOOPBACK_NAMES}
    if host in WILDCARDS:
        names |= _machine_names()
    return frozenset(names), host in WILDCARDS


def _split_host(header: str) -> tuple[str, int | None] | None:
    """Return (name, port) of a ``Host`` header value, or None if it is malformed."""
    if header.startswith("["):
        name, bracket, rest = header[1:].partition("]")
        if not bracket or (rest and not rest.startswith(":")):
            return None
        port_text = rest[1:] if rest else ""
    else:
        name, colon, port_text = header.rpartition(":")
        if not colon:
            name, port_text = header, ""
        elif ":" in name:
            return None  # an IPv6 address must be bracketed
    if port_text and not (port_text.isdigit() and len(port_text) <= 5):
        return None
    return name, int(port_text) if port_text else None


class UiServer(Server):
    """textual-serve's server, answering only requests addressed to it from its own pages.

    textual-serve writes absolute URLs into the page; for a wildcard bind (0.0.0.0) the
    bind address is not one a browser can reach, so the page names the address the
    request came to, once that address passed :meth:`checked_host`.
    """

    def __init__(self, command: str, host: str, port: int, title: str | None = None) -> None:
        super().__init__(command, host, port, title=title)
        self.names, self.any_address = allowed_names(host)

    def checked_host(self, request: web.Request) -> str:
        """Return the request's ``Host`` as this server's ``name:port``, or raise 403.

        Raises:
            web.HTTPForbidden: the request names another host or port.
        """
        header = request.headers.get("Host", "")
        parsed = _split_host(header)
        if parsed is not None:
            name, port = parsed
            canonical = _canonical(name)
            port_ok = port == self.port or (port is None and self.port == 80)
            literal = False
            with suppress(ValueError):
                ipaddress.ip_address(canonical)
                literal = True
            if port_ok and (canonical in self.names or (self.any_address and literal)):
                shown = f"[{canonical}]" if ":" in canonical else canonical
                return f"{shown}:{self.port}"
        raise web.HTTPForbidden(text="this Lamina UI answers only requests addressed to it\n")

    @web.middleware
    async def guard(self, request: web.Request, handler: Handler) -> web.StreamResponse:
        """Refuse (403) a request to another host, or one from another site's page.

        The websocket (it drives the scanner) must name its origin, and that origin
        must be the page this server sent: ``http://`` the same checked host.
        """
        host = self.checked_host(request)
        origin = request.headers.get("Origin")
        if origin is None and request.path == "/ws":
            raise web.HTTPForbidden(text="the UI's websocket needs an Origin\n")
        if origin is not None and origin.lower() not in (f"http://{host}", f"https://{host}"):
            raise web.HTTPForbidden(text="this Lamina UI is driven only from its own page\n")
        request[CHECKED_HOST] = host
        return await handler(request)

    async def _make_app(self) -> web.Application:
        """Return textual-serve's application with :meth:`guard` in front of every route."""
        app = await super()._make_app()
        app.middlewares.append(self.guard)
        return app

    async def on_startup(self, app: web.Application) -> None:
        """Print nothing yet: :meth:`serve` says where the UI is once the port is bound."""

    async def handle_index(self, request: web.Request) -> Any:
        """Serve the page that opens the app's websocket on the checked host, its font
        from this server rather than a web-font service."""
        self.public_url = f"http://{request.get(CHECKED_HOST) or self.checked_host(request)}"
        response = await super().handle_index(request)
        if isinstance(response, web.Response) and response.text is not None:
            font = LOCAL_FONT.format(static="/static/")
            response.text = OUTSIDE_FONT.sub(lambda _: font, response.text)
        return response

    def serve(self, debug: bool = False) -> None:
        """Bind, say where the UI is, and serve until SIGINT or SIGTERM.

        Raises:
            OSError: the address cannot be bound (before anything is printed).
        """
        self.debug = debug
        self.initialize_logging()
        asyncio.run(self._serve())

    async def _serve(self) -> None:
        runner = web.AppRunner(await self._make_app(), handle_signals=False)
        await runner.setup()
        try:
            await web.TCPSite(runner, self.host, self.port).start()
            print(
                f"lamina: serving the terminal UI on http://{self.host}:{self.port} (Ctrl+C stops)",
                flush=True,
            )
            stop = asyncio.Event()
            loop = asyncio.get_running_loop()
            for number in (signal.SIGINT, signal.SIGTERM):
                loop.add_signal_handler(number, stop.set)
            await stop.wait()
        finally:
            await runner.cleanup()


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
