"""The real app in a real terminal: tmux runs ``lamina tui``, keys go in, the screen is read."""

from __future__ import annotations

import os
import shlex
import shutil
import subprocess
import sys
import time
import uuid
from pathlib import Path

import pytest
from drive import wait_for_text

pytestmark = pytest.mark.skipif(
    shutil.which("tmux") is None,
    reason="tmux is not installed (apt-get install tmux); the Pilot tests cover the UI",
)

REPO = Path(__file__).resolve().parents[2]


class Terminal:
    """One detached tmux session of 80 x 24 running a command."""

    def __init__(self, command: str) -> None:
        self.name = f"lamina-test-{uuid.uuid4().hex[:8]}"
        subprocess.run(
            ["tmux", "new-session", "-d", "-s", self.name, "-x", "80", "-y", "24", command],
            check=True,
        )

    def keys(self, *keys: str) -> None:
        """Type keys (tmux key names, e.g. F4, Enter)."""
        subprocess.run(["tmux", "send-keys", "-t", self.name, *keys], check=True)

    def screen(self) -> str:
        """Return the visible screen as text."""
        return subprocess.run(
            ["tmux", "capture-pane", "-p", "-t", self.name],
            check=True,
            capture_output=True,
            text=True,
        ).stdout

    def wait_for(self, text: str, timeout_s: float = 60.0) -> str:
        """Return the screen once it shows ``text``; fail with the screen otherwise."""
        return wait_for_text(self.screen, text, timeout_s)

    def close(self) -> None:
        """End the session (and the app in it)."""
        subprocess.run(["tmux", "kill-session", "-t", self.name], check=False)


@pytest.mark.parametrize("where", ["sim", "local endpoint"])
def test_keys_drive_the_app_in_tmux(
    where: str, tmp_path: Path, request: pytest.FixtureRequest
) -> None:
    """Connect, calibrate and scan by keys alone in a real 80 x 24 terminal; quit cleanly.

    Over the simulated device the app starts itself, and over the local endpoint of the
    box's device service (issue 14: ``lamina tui --device local`` on the Pi).
    """
    device = "sim" if where == "sim" else request.getfixturevalue("device_service")
    env = {
        "PYTHONPATH": os.pathsep.join(str(REPO / p) for p in ("shared", "device", "host")),
        "TERM": "xterm-256color",
    }
    exports = " ".join(f"{k}={shlex.quote(v)}" for k, v in env.items())
    done = tmp_path / "exit-status"
    command = (
        f"{exports} {shlex.quote(sys.executable)} -m lamina_host tui --device {device} "
        f"--library {shlex.quote(str(tmp_path / 'library.sqlite'))}; echo $? > {done}"
    )
    term = Terminal(command)
    try:
        term.wait_for("F2 Connect")
        term.keys("c")
        term.wait_for("protocol     ")
        term.keys("F4")
        term.wait_for("Chessboard")
        term.keys("g")
        term.wait_for("143 corners")
        term.keys("a", "y")
        screen = term.wait_for("PASS: correction within 5% of 1")
        assert "correction     " in screen
        term.keys("F5")
        term.wait_for("Subject")
        term.keys("T", "M", "U", "X", "Escape")
        # A terminal cannot tell Escape then "s" from Alt+S unless time passes between them.
        time.sleep(0.5)
        term.keys("s")
        screen = term.wait_for("scan complete")
        assert "object view 16/16" in screen
        term.keys("F1")
        term.wait_for("keys and workflow")
        term.keys("Escape")
        time.sleep(0.5)
        term.keys("C-q")
        deadline = time.monotonic() + 20
        while not done.exists() and time.monotonic() < deadline:
            time.sleep(0.1)
        assert done.read_text().strip() == "0"
    finally:
        term.close()
