"""Driving the Lamina app under Textual's Pilot: wait for workers, walk the workflow."""

from __future__ import annotations

import time
from collections.abc import Callable

from textual.pilot import Pilot
from textual.widgets import DataTable, Input

from lamina_host.tui.app import LaminaApp

TIMEOUT_S = 60.0


async def wait_for(pilot: Pilot, done: Callable[[], bool], what: str) -> None:
    """Let the app run until ``done()`` holds; fail with the status line after a timeout."""
    app = pilot.app
    deadline = time.monotonic() + TIMEOUT_S
    while not done():
        if time.monotonic() > deadline:
            raise AssertionError(f"timed out waiting for {what}; status: {app.status}")
        status, is_error = app.status
        if is_error:
            raise AssertionError(f"error while waiting for {what}: {status}")
        await pilot.pause(0.05)
    await pilot.pause()


async def connect(pilot: Pilot) -> None:
    """Pick ``sim`` in the port list and connect."""
    app = pilot.app
    assert isinstance(app, LaminaApp)
    await pilot.press("f2", "home", "enter")
    await wait_for(pilot, lambda: app.session.connected, "the connection")


async def calibrate(pilot: Pilot) -> None:
    """Capture and accept the chessboard, then scan the cylinder."""
    app = pilot.app
    assert isinstance(app, LaminaApp)
    await pilot.press("f4", "g")
    await wait_for(pilot, lambda: app.session.grid is not None, "the chessboard")
    await pilot.press("a", "y")
    await wait_for(pilot, lambda: app.session.axis is not None, "the cylinder axis")


async def fill_scan_form(pilot: Pilot, subject: str, sections: str, pitch: str, views: str) -> None:
    """Type the subject and the plan on the Scan screen, leaving the fields."""
    await pilot.press("f5")
    for field, value in (
        ("subject", subject),
        ("sections", sections),
        ("pitch", pitch),
        ("views", views),
    ):
        widget = pilot.app.screen.query_one(f"#{field}", Input)
        widget.value = ""
        widget.focus()
        await pilot.press(*value)
    await pilot.press("escape")


async def open_library(pilot: Pilot, rows: int = 1) -> DataTable:
    """Go to the Library screen and wait until its table lists ``rows`` scans."""
    await pilot.press("f7")
    table = pilot.app.screen.query_one("#scans", DataTable)
    await wait_for(pilot, lambda: table.row_count == rows, "the scan list")
    return table


async def open_first_scan(pilot: Pilot) -> None:
    """Open the library's only scan and wait until it is processed."""
    app = pilot.app
    assert isinstance(app, LaminaApp)
    await open_library(pilot)
    await pilot.press("o")
    await wait_for(pilot, lambda: app.session.results is not None, "processing")
    await pilot.pause(0.2)
