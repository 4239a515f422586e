"""The terminal UI in a real browser (issue 14): ``lamina serve-ui`` and headless chromium.

Debian's chromium runs headless under playwright (no browser is downloaded). The page is
textual-serve's xterm.js terminal, drawn on a canvas; the test reads what xterm.js holds
on its screen (its buffer, the text the canvas shows) and types keys as a user would.
"""

from __future__ import annotations

import math
import re
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from drive import wait_for_text

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
pytestmark = pytest.mark.skipif(
    CHROMIUM is None,
    reason="chromium is not installed (apt-get install -y chromium); the browser test skips",
)
CHROMIUM_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
]
# textual-serve keeps its xterm.js Terminal private; the test gives the page a handle on it.
TERMINAL_NEW = re.compile(r"this\.terminal=new (\w+)\.Terminal\(")
SCREEN_JS = """() => {
    const term = window.__laminaTerminal;
    if (!term) return "";
    const lines = [];
    for (let i = 0; i < term.rows; i++) {
        const line = term.buffer.active.getLine(i);
        lines.push(line ? line.translateToString(true) : "");
    }
    return lines.join("\\n");
}"""
RADIUS_MM = 19.05 / 2
"""The simulated device's default object: the thesis's calibration cylinder."""


def free_port() -> int:
    """Return a TCP port nothing listens on."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.fixture
def ui_url(tmp_path: Path) -> Iterator[str]:
    """Run ``lamina serve-ui`` on a free loopback port with a fresh library: its URL."""
    port = free_port()
    command = [sys.executable, "-m", "lamina_host", "serve-ui", "--port", str(port)]
    command += ["--device", "sim", "--library", str(tmp_path / "library.sqlite")]
    with open(tmp_path / "serve-ui.log", "w") as log:
        process = subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and process.poll() is None:
            with socket.socket() as sock:
                if sock.connect_ex(("127.0.0.1", port)) == 0:
                    break
            time.sleep(0.1)
        else:
            pytest.fail(f"serve-ui did not start: {(tmp_path / 'serve-ui.log').read_text()}")
        yield f"http://127.0.0.1:{port}/"
    finally:
        process.terminate()
        process.wait(timeout=20)


class Screen:
    """The browser page's terminal: read its text, type keys."""

    def __init__(self, page: Any) -> None:
        self.page = page

    def text(self) -> str:
        """Return the terminal's visible text."""
        return str(self.page.evaluate(SCREEN_JS))

    def wait_for(self, text: str, timeout_s: float = 90.0) -> str:
        """Return the screen once it shows ``text``; fail with the screen otherwise."""
        return wait_for_text(self.text, text, timeout_s)

    def press(self, *keys: str) -> None:
        """Press keys (playwright names: c, F4, Escape)."""
        for key in keys:
            self.page.keyboard.press(key)


def expose_terminal(route: Any) -> None:
    """Serve textual-serve's script with its terminal reachable as window.__laminaTerminal."""
    response = route.fetch()
    script, found = TERMINAL_NEW.subn(
        r"this.terminal=window.__laminaTerminal=new \1.Terminal(", response.text()
    )
    assert found == 1, "textual-serve's textual.js changed: update TERMINAL_NEW"
    route.fulfill(response=response, body=script)


def test_browser_connects_scans_and_shows_results(ui_url: str) -> None:
    """Open the page, see Connect, connect to sim, calibrate, scan, process: the table."""
    sync_api = pytest.importorskip("playwright.sync_api", reason="pip install playwright")
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            page = browser.new_page(viewport={"width": 1280, "height": 800})
            page.route("**/static/js/textual.js", expose_terminal)
            page.goto(ui_url)
            screen = Screen(page)
            assert "Connect" in screen.wait_for("F2 Connect")
            page.locator(".xterm-helper-textarea").focus()
            screen.press("c")
            screen.wait_for("connected to sim: lamina-device")
            screen.press("F4")
            screen.wait_for("Chessboard")
            screen.press("g")
            screen.wait_for("corners")
            screen.press("a", "y")
            screen.wait_for("PASS: correction within 5% of 1")
            screen.press("F5")
            screen.wait_for("Subject")
            page.keyboard.type("WEB1")
            screen.press("Escape")
            time.sleep(0.5)  # Escape then "s" must not read as Alt+S
            screen.press("s")
            screen.wait_for("scan complete", timeout_s=180)
            screen.press("F6")
            screen.wait_for("perim mm")
            screen.press("p")
            table = screen.wait_for("measured", timeout_s=180)
        finally:
            browser.close()
    rows = [line.split() for line in table.splitlines() if "measured" in line]
    assert [row[0] for row in rows] == ["0", "1"]  # the default plan: two sections
    for row in rows:
        perimeter_mm, area_mm2 = float(row[5]), float(row[6])
        assert perimeter_mm == pytest.approx(2 * math.pi * RADIUS_MM, abs=0.2)
        assert area_mm2 == pytest.approx(math.pi * RADIUS_MM**2, abs=2.0)
