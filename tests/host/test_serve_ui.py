"""`lamina serve-ui` refusals: one line each, non-zero status (the page: tui/test_browser)."""

from __future__ import annotations

import contextlib
import re
import signal
import socket
import subprocess
import sys
from collections.abc import AsyncIterator, Callable

import aiohttp
import pytest
from aiohttp import web
from aiohttp.test_utils import TestServer, make_mocked_request

from lamina_host.ui.browser import UiServer, allowed_names, tui_command


def serve_ui(*args: str) -> subprocess.CompletedProcess[str]:
    """Run ``lamina serve-ui`` in a fresh process (it must end by itself here)."""
    return subprocess.run(
        [sys.executable, "-m", "lamina_host", "serve-ui", *args],
        capture_output=True,
        text=True,
        timeout=60,
    )


Refusal = Callable[[subprocess.CompletedProcess[str]], str]


def test_other_binds_need_allow_remote(refusal: Refusal) -> None:
    """A bind beyond loopback without --allow-remote is refused before anything listens."""
    line = refusal(serve_ui("--host", "0.0.0.0", "--port", "1"))
    assert "--allow-remote" in line and "no login" in line


def test_port_in_use_is_one_line(refusal: Refusal) -> None:
    """A taken port names itself and what to do."""
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        done = serve_ui("--port", str(port))
        line = refusal(done)
    assert f"cannot serve the UI on 127.0.0.1:{port}" in line
    assert "serving" not in done.stdout  # it said 'serving on ...' before failing to bind


def test_each_browser_session_runs_the_tui_command() -> None:
    """The served command is ``lamina tui`` with the options given, quoted for the shell."""
    command = tui_command(["--device", "local", "--library", "/srv/my library.sqlite"])
    assert command.endswith("-m lamina_host tui --device local --library '/srv/my library.sqlite'")


# --- issue 19: another site must not drive the scanner through a visitor's browser ------


def _free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@contextlib.asynccontextmanager
async def _served(host: str = "127.0.0.1") -> AsyncIterator[tuple[aiohttp.ClientSession, str, int]]:
    """Serve the UI app (running ``true`` per websocket) on a free port of ``host``."""
    port = _free_port()
    server = UiServer("true", host, port, title="Lamina")
    test_server = TestServer(await server._make_app(), host="127.0.0.1", port=port)
    await test_server.start_server()
    try:
        async with aiohttp.ClientSession() as session:
            yield session, f"http://127.0.0.1:{port}", port
    finally:
        await test_server.close()


async def _status(session: aiohttp.ClientSession, url: str, **headers: str) -> tuple[int, str]:
    async with session.get(url, headers=headers, allow_redirects=False) as response:
        return response.status, await response.text()


async def test_a_page_asked_for_under_another_host_is_refused():
    """DNS rebinding: Host evil.example.com was served a page pointing its websocket there."""
    async with _served() as (session, base, port):
        for host in ("127.0.0.1", "localhost", "[::1]"):
            status, page = await _status(session, f"{base}/", Host=f"{host}:{port}")
            assert status == 200 and f'"ws://{host}:{port}/ws"' in page.replace("&#34;", '"')
        hostile = [
            "evil.example.com", f"evil.example.com:{port}", f"127.0.0.1:{port + 1}", "127.0.0.1",
            f"127.0.0.1.evil.example.com:{port}", f"localhost.:{port}0", f"10.0.0.1:{port}",
            f"[::2]:{port}", f"::1:{port}", f"127.0.0.1:{port}:{port}", f"127.0.0.1 :{port}",
        ]  # fmt: skip
        for host in hostile:
            for path in ("/", "/static/css/xterm.css", "/download/x"):
                status, page = await _status(session, f"{base}{path}", Host=host)
                assert status in (400, 403), (host, path, status)
                assert "evil" not in page and "ws://" not in page


async def test_a_websocket_from_another_origin_is_refused():
    """Origin: http://evil.example.com was accepted and its keys connected the scanner."""
    async with _served() as (session, base, port):
        for origin in (
            "http://evil.example.com", f"http://evil.example.com:{port}", "null",
            f"http://127.0.0.1:{port + 1}", f"http://127.0.0.1:{port}.evil.example.com",
            f"ws://127.0.0.1:{port}", f"http://localhost:{port}", None,
        ):  # fmt: skip
            headers = {} if origin is None else {"Origin": origin}
            with pytest.raises(aiohttp.WSServerHandshakeError) as refused:
                await session.ws_connect(f"{base}/ws", headers=headers)
            assert refused.value.status == 403, origin
        socket_ = await session.ws_connect(f"{base}/ws", headers={"Origin": base})
        await socket_.close()  # the page's own origin opens it


def test_a_wildcard_bind_accepts_this_machines_addresses_not_other_names():
    names, any_address = allowed_names("0.0.0.0")
    assert any_address and {"localhost", "127.0.0.1", "::1"} <= names
    assert "evil.example.com" not in names
    names, any_address = allowed_names("127.0.0.1")
    assert not any_address and names == {"localhost", "127.0.0.1", "::1"}
    names, any_address = allowed_names("192.168.7.2")
    assert not any_address and names == {"192.168.7.2"}
    server = UiServer("true", "0.0.0.0", 8000)
    for host, expected in (("192.168.7.2:8000", "192.168.7.2:8000"), ("[fe80::1]:8000", None)):
        request = make_mocked_request("GET", "/", headers={"Host": host})
        assert server.checked_host(request) == (expected or "[fe80::1]:8000")
    for host in ("evil.example.com:8000", "192.168.7.2:8001", "192.168.7.2"):
        with pytest.raises(web.HTTPForbidden):
            server.checked_host(make_mocked_request("GET", "/", headers={"Host": host}))


def test_serving_is_said_only_once_the_port_is_bound():
    """It printed 'serving on ...' before binding (then the bind error on a taken port)."""
    port = _free_port()
    process = subprocess.Popen(
        [sys.executable, "-m", "lamina_host", "serve-ui", "--port", str(port)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert process.stdout is not None
        line = process.stdout.readline()
        assert f"serving the terminal UI on http://127.0.0.1:{port}" in line
        with socket.create_connection(("127.0.0.1", port), timeout=5):
            pass  # already listening when it said so
    finally:
        process.terminate()
        process.wait(timeout=20)
    assert process.returncode in (0, -signal.SIGTERM)


async def test_the_page_fetches_nothing_from_outside_the_box():
    """Issue 24: the page asked a web-font service for its font, which fails on an isolated
    ward network; every URL it names is now this server's, and the font is served here."""
    async with _served() as (session, base, port):
        status, page = await _status(session, f"{base}/", Host=f"127.0.0.1:{port}")
        assert status == 200
        named = re.findall(r"""(?:href|src|url)\s*[=(]\s*["']?([^"')\s>]+)""", page)
        assert named, "the page names no URL at all: the pattern is wrong"
        for url in named:
            assert not re.match(r"(https?:)?//", url) or url.startswith(base), url
        assert "Roboto Mono" in page
        fonts = re.findall(r"url\('([^']+\.ttf)'\)", page)
        assert fonts
        for font in fonts:
            async with session.get(f"{base}{font}", headers={"Host": f"127.0.0.1:{port}"}) as got:
                assert got.status == 200 and len(await got.read()) > 10_000, font
