"""Every screen at 80 x 24, compared with the committed SVG snapshots.

Deterministic by construction: the simulated device runs with seed 0, the port list
is pinned (the machine's own serial ports would differ), the library's creation time
is fixed (see conftest), and nothing on screen shows a clock. Screens that show the
simulator's figures are compared by layout and text only (``layout_compare``: digits
masked, plots emptied, frames greyed); their numbers are checked against the workflow's
result objects in test_screen_numbers.py. Update the snapshots with
``pytest tests/tui --snapshot-update`` after an intended change of layout.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest
from drive import connect_and_calibrate, fill_scan_form, open_first_scan, open_library, wait_for
from textual.pilot import Pilot

from lamina_host.ui.tui.app import LaminaApp
from lamina_host.ui.tui.screens.scan import ScanScreen

SIZE = (80, 24)


@pytest.fixture(autouse=True)
def pinned_ports(monkeypatch: pytest.MonkeyPatch) -> None:
    """List only the simulated device: real serial ports differ between machines."""
    monkeypatch.setattr("lamina_host.ui.tui.screens.connect.serial_ports", lambda: [])


def test_connect_screen(snap_compare, tmp_path: Path) -> None:
    """Connect, before connecting."""
    assert snap_compare(LaminaApp("sim", tmp_path / "l.sqlite"), terminal_size=SIZE)


def test_help_screen(snap_compare, tmp_path: Path) -> None:
    """The help over the Connect screen."""
    assert snap_compare(LaminaApp("sim", tmp_path / "l.sqlite"), press=["f1"], terminal_size=SIZE)


def test_scan_screen_with_bad_input(snap_compare, tmp_path: Path) -> None:
    """Scan, with the error line for a missing subject id."""

    async def run_before(pilot: Pilot) -> None:
        await fill_scan_form(pilot, "", "2", "2", "8")
        await pilot.press("s")

    app = LaminaApp("sim", tmp_path / "l.sqlite")
    assert snap_compare(app, run_before=run_before, terminal_size=SIZE)


def test_calibrate_screen(layout_compare, tmp_path: Path) -> None:
    """Calibrate after the chessboard and the cylinder, on the simulated device."""

    async def run_before(pilot: Pilot) -> None:
        app = await connect_and_calibrate(pilot)
        app.clear_notifications()

    app = LaminaApp("sim", tmp_path / "l.sqlite")
    assert layout_compare(app, run_before, SIZE)


def test_live_screen(layout_compare, tmp_path: Path) -> None:
    """Live: a preview frame with the last cylinder view's stripe over it."""

    async def run_before(pilot: Pilot) -> None:
        app = await connect_and_calibrate(pilot)
        await pilot.press("f3", "g")
        await wait_for(pilot, lambda: "frame 640 x 480" in app.status[0], "the frame")

    app = LaminaApp("sim", tmp_path / "l.sqlite")
    assert layout_compare(app, run_before, SIZE)


def test_scan_screen_after_scan(layout_compare, tmp_path: Path) -> None:
    """Scan, complete: progress at the end and the last section's points."""

    async def run_before(pilot: Pilot) -> None:
        app = await connect_and_calibrate(pilot)
        await fill_scan_form(pilot, "P001", "2", "2", "8")
        await pilot.press("s")
        await wait_for(pilot, lambda: "scan complete" in app.status[0], "the scan")
        screen = app.screen
        assert isinstance(screen, ScanScreen)
        await wait_for(pilot, lambda: not screen.plot_pending, "the section plot")

    app = LaminaApp("sim", tmp_path / "l.sqlite")
    assert layout_compare(app, run_before, SIZE)


async def asking_to_delete(pilot: Pilot) -> None:
    """Show the library and ask to delete its scan (the snapshot answers no: nothing is lost)."""
    await open_library(pilot)
    await pilot.press("d")


@pytest.mark.parametrize("shown", [open_library, asking_to_delete], ids=["list", "delete"])
def test_library_screen(
    layout_compare, scanned_library: Path, shown: Callable[[Pilot], Awaitable[object]]
) -> None:
    """Library, with one processed scan; then asking before deleting it."""
    assert layout_compare(LaminaApp("sim", scanned_library), shown, SIZE)


def test_results_screen(layout_compare, scanned_library: Path) -> None:
    """Results of the library's scan, opened and processed again with 5 harmonics."""

    async def run_before(pilot: Pilot) -> None:
        await open_first_scan(pilot)

    app = LaminaApp("sim", scanned_library)
    assert layout_compare(app, run_before, SIZE)
