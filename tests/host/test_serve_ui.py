"""`lamina serve-ui` refusals: one line each, non-zero status (the page: tui/test_browser)."""

from __future__ import annotations

import socket
import subprocess
import sys
from collections.abc import Callable

from lamina_host.serve_ui import tui_command


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
        line = refusal(serve_ui("--port", str(port)))
    assert f"cannot serve the UI on 127.0.0.1:{port}" in line


def test_each_browser_session_runs_the_tui_command() -> None:
    """The served command is ``lamina tui`` with the options given, quoted for the shell."""
    command = tui_command(["--device", "local", "--library", "/srv/my library.sqlite"])
    assert command.endswith("-m lamina_host tui --device local --library '/srv/my library.sqlite'")
