"""The terminal UI in a real browser (issues 14, 24): ``lamina serve-ui`` and headless chromium.

Debian's chromium runs headless under playwright (no browser is downloaded). The page is
textual-serve's xterm.js terminal, drawn on a canvas; the test reads what xterm.js holds
on its screen (its buffer, the text the canvas shows) and taps what a tablet user taps
(touch emulation: a tablet has no F-keys), typing only into fields. Every request the
page makes is recorded: none may leave the box.
"""

from __future__ import annotations

import re
import shutil
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any
from urllib.parse import urlsplit

import pytest
from drive import CLINIC_PLAN, LEFT_ARM_SCALE, csv_levels, wait_for_text

from lamina_host.store.library import Library

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
TAP_SETTLE_S = 0.6
"""A mobile browser sends a tap's mouse events late (it waits to see if a second tap makes
a double tap): keys typed at once would reach the app before the field has the focus."""
CELLS_JS = """() => {
    const term = window.__laminaTerminal;
    const box = term.element.querySelector(".xterm-screen").getBoundingClientRect();
    return [box.left, box.top, box.width / term.cols, box.height / term.rows];
}"""


def free_port() -> int:
    """Return a TCP port nothing listens on."""
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.fixture
def ui_url(tmp_path: Path, right_arm_library: Path) -> Iterator[str]:
    """Run ``lamina serve-ui`` on a free loopback port: its URL. The library holds P-0077's
    right arm; the simulator holds the left one (the right scaled by LEFT_ARM_SCALE)."""
    shutil.copyfile(right_arm_library, tmp_path / "library.sqlite")
    port = free_port()
    command = [sys.executable, "-m", "lamina_host", "serve-ui", "--port", str(port)]
    command += ["--device", "sim", "--library", str(tmp_path / "library.sqlite")]
    command += ["--object", f"arm:scale={LEFT_ARM_SCALE}"]
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

    def type_into(self, label: str, value: str, row: str | None = None) -> None:
        """Tap the field after ``label`` and replace its text with ``value``; tap again if
        the field does not show it (a loaded machine may deliver the tap after the keys)."""
        for _ in range(5):
            self.tap(label, row=row, after=True)
            time.sleep(TAP_SETTLE_S)
            self.press("End", *["Backspace"] * 12)
            self.page.keyboard.type(value)
            try:
                self.wait_for(f"{label} {value} ", timeout_s=5.0)
                return
            except AssertionError:
                continue
        raise AssertionError(f"{label} never showed {value!r}:\n{self.text()}")

    def type_fresh(self, placeholder: str, value: str) -> None:
        """Tap the empty field showing ``placeholder`` and type ``value`` into it.

        The rest of ``value`` is typed only once the field itself shows its first character
        (which must be a key the screen does not bind), read twice where the placeholder
        began: the letters of a path are keys a screen binds (the Results screen's m, p, e),
        and a tap delivered late on a loaded machine would send them to the screen. A value
        that does not appear whole (keys lost in the browser) is cleared and typed again."""
        y, x = self.find(placeholder)
        for _ in range(3):
            if placeholder in self.text():
                self.tap(placeholder)
                time.sleep(TAP_SETTLE_S)
            self.press("End", *["Backspace"] * (len(value) + 2), value[0])
            if not self.field_starts_with(y, x, value[0], placeholder):
                continue
            self.page.keyboard.type(value[1:])
            try:
                self.wait_for(value[-20:], timeout_s=10.0)
                return
            except AssertionError:
                continue
        raise AssertionError(f"the field {placeholder!r} never took {value!r}:\n{self.text()}")

    def find(self, text: str, timeout_s: float = 10.0) -> tuple[int, int]:
        """Return the line and column where ``text`` first shows on the screen, waiting up
        to ``timeout_s`` for it: a screen just shown may draw its fields a moment after its
        labels (CI once read "Subject" before the field beside it held its placeholder)."""
        screen = self.wait_for(text, timeout_s=timeout_s)
        for y, line in enumerate(screen.splitlines()):
            if text in line:
                return y, line.index(text)
        raise AssertionError(f"{text!r} is not on one line of the screen:\n{screen}")

    def field_starts_with(self, y: int, x: int, key: str, placeholder: str) -> bool:
        """Whether the field at line ``y``, column ``x`` shows ``key`` where its placeholder
        was, on two reads 0.2 s apart (one read may catch a line the terminal is redrawing);
        wait up to 5 s for it."""
        seen = 0
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline:
            lines = self.text().splitlines()
            line = lines[y] if y < len(lines) else ""
            shown = placeholder not in line and line[x : x + 1] == key
            seen = seen + 1 if shown else 0
            if seen == 2:
                return True
            time.sleep(0.2)
        return False

    def tap_until(self, text: str, shown: str, row: str | None = None) -> str:
        """Tap ``text`` until ``shown`` appears (a tap on a redrawing line may be lost)."""
        for _ in range(3):
            self.tap(text, row=row)
            try:
                return self.wait_for(shown, timeout_s=8.0)
            except AssertionError:
                continue
        raise AssertionError(f"tapping {text!r} never showed {shown!r}:\n{self.text()}")

    def tap(self, text: str, row: str | None = None, below: int = -1, after: bool = False) -> int:
        """Tap the first ``text`` on the screen (the last one on the line holding ``row``, if
        given) on a line below ``below`` (``after``: just right of it, in the field a label
        names); return the line tapped."""
        left, top, width, height = self.page.evaluate(CELLS_JS)
        for y, line in enumerate(self.text().splitlines()):
            if y <= below or text not in line or (row is not None and row not in line):
                continue
            x = line.rindex(text) if row is not None else line.index(text)
            centre_x = left + (x + (len(text) + 2.5 if after else len(text) / 2)) * width
            self.page.touchscreen.tap(centre_x, top + (y + 0.5) * height)
            return y
        raise AssertionError(f"{text!r} is not on the screen:\n{self.text()}")


def expose_terminal(route: Any) -> None:
    """Serve textual-serve's script with its terminal reachable as window.__laminaTerminal."""
    response = route.fetch()
    script, found = TERMINAL_NEW.subn(
        r"this.terminal=window.__laminaTerminal=new \1.Terminal(", response.text()
    )
    assert found == 1, "textual-serve's textual.js changed: update TERMINAL_NEW"
    route.fulfill(response=response, body=script)


def test_a_tablet_scans_by_touch_with_nothing_fetched_from_outside(
    ui_url: str, tmp_path: Path
) -> None:
    """By taps alone (typing only into fields): connect, calibrate, scan P-0077's left arm
    (side tapped), process, compare with the right arm, measure at 5 mm, export the PDF,
    CSV and DICOM; the figures are right and every request stays on 127.0.0.1."""
    sync_api = pytest.importorskip("playwright.sync_api", reason="pip install playwright")
    out = tmp_path / "export"
    requests: list[str] = []
    with sync_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=CHROMIUM, args=CHROMIUM_ARGS)
        try:
            context = browser.new_context(
                viewport={"width": 1180, "height": 820}, has_touch=True, is_mobile=True
            )
            page = context.new_page()
            page.on("request", lambda request: requests.append(request.url))
            page.route("**/static/js/textual.js", expose_terminal)
            page.goto(ui_url)
            screen = Screen(page)
            assert "Connect" in screen.wait_for("F2 Connect")
            screen.tap("Connect", row="Device")  # the button beside the device field
            screen.wait_for("connected to sim: lamina-device")
            screen.tap("F4 Calibrate")
            screen.wait_for("1. Chessboard")
            screen.tap("Capture")
            screen.wait_for("143 corners")
            screen.tap("Accept")
            screen.wait_for("accepted")
            screen.tap("Scan cylinder")
            screen.wait_for("PASS: correction within 5% of 1")
            screen.tap("F5 Scan")
            screen.wait_for("Subject")
            screen.type_fresh("e.g. P-0042", "P-0077")  # a tablet's keyboard comes up
            for field, value in zip(("Sections", "Pitch mm", "Views"), CLINIC_PLAN, strict=True):
                screen.type_into(field, value, row="Sections")
            side = screen.tap("none: not a limb")
            screen.wait_for("right")
            screen.tap("left", below=side)
            screen.wait_for("Side left")
            # On a loaded machine a late tap can send one field's keys into another.
            for field, value in zip(("Sections", "Pitch mm", "Views"), CLINIC_PLAN, strict=True):
                if f"{field} {value} " not in screen.text():
                    screen.type_into(field, value, row="Sections")
            screen.tap("Start", row="Rig")
            screen.wait_for("scan complete", timeout_s=180)
            screen.tap("F6 Results")
            screen.wait_for("perim mm")
            screen.tap("Process", row="Mesh")
            table = screen.wait_for("measured", timeout_s=180)
            time.sleep(TAP_SETTLE_S)  # the choices are read from the library meanwhile
            compare = screen.tap("no comparison")
            screen.wait_for("other limb (right)", timeout_s=10)
            screen.tap("other limb (right)", below=compare)
            screen.wait_for("Compare other limb")
            screen.wait_for("m Measure")
            screen.tap_until("Measure", "Spacing mm")  # the footer's m
            screen.type_into("Spacing mm", "5", row="Spacing mm")
            screen.press("Enter")
            clinical = screen.wait_for("excess over other limb")
            screen.tap_until("Close", "Export to")  # the footer's Escape
            screen.type_fresh("a new folder", str(out))
            screen.tap("Export", row="Export to")
            screen.wait_for("exported to", timeout_s=120)
        finally:
            browser.close()
    rows = [line.split() for line in table.splitlines() if "measured" in line]
    assert [row[0] for row in rows] == ["0", "1", "2"]  # the three sections typed
    assert "3 sections" not in clinical and "mL (+" in clinical  # larger than the right arm
    levels = csv_levels(out / "measures.csv")
    assert [offset for offset, _, _ in levels] == pytest.approx([0.0, 5.0, 10.0])
    for level in levels:
        assert level[1] / level[2] == pytest.approx(LEFT_ARM_SCALE, rel=0.08), level
    assert (out / "report.pdf").read_bytes().startswith(b"%PDF")
    assert (out / "scan.dcm").is_file()
    with Library(tmp_path / "library.sqlite") as library:  # the ui_url fixture's library
        scans = library.scans()
    assert [(s.subject, s.side, s.has_result) for s in scans] == [
        ("P-0077", "right", True), ("P-0077", "left", True),
    ]  # fmt: skip
    assert requests and all(urlsplit(url).hostname == "127.0.0.1" for url in requests), requests
