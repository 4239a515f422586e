"""Driving the Lamina app under Textual's Pilot: wait for workers, walk the workflow."""

from __future__ import annotations

import asyncio
import csv
import time
from collections.abc import Callable
from pathlib import Path

from textual import events
from textual.pilot import Pilot
from textual.widgets import DataTable, Input

from lamina_host.clinical.report import LENGTH_UNITS
from lamina_host.ui.tui.app import LaminaApp
from lamina_host.ui.tui.widgets import HelpScreen

TIMEOUT_S = 60.0
CLINIC_PLAN = ("3", "5", "8")
"""The clinic tests' plan: three sections 5 mm apart (levels 0, 5, 10 mm at 5 mm spacing)."""
LEFT_ARM_SCALE = 1.1
"""The left arm the clinic tests scan is the right one (``right_arm_library``) scaled by
this: its circumferences are larger by about this, its volume by about its square."""


def wait_for_text(read: Callable[[], str], text: str, timeout_s: float = TIMEOUT_S) -> str:
    """Return ``read()`` once it shows ``text`` (a real terminal's or browser's screen);
    fail with the last screen after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        screen = read()
        if text in screen:
            return screen
        time.sleep(0.1)
    raise AssertionError(f"{text!r} never appeared; the screen was:\n{read()}")


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
    await wait_for(pilot, lambda: app.job.device.connected, "the connection")


async def calibrate(pilot: Pilot) -> None:
    """Capture and accept the chessboard, then scan the cylinder."""
    app = pilot.app
    assert isinstance(app, LaminaApp)
    await pilot.press("f4", "g")
    await wait_for(pilot, lambda: app.job.acquisition.grid is not None, "the chessboard")
    await pilot.press("a", "y")
    await wait_for(pilot, lambda: app.job.acquisition.axis is not None, "the cylinder axis")


async def connect_and_calibrate(pilot: Pilot) -> LaminaApp:
    """Connect to the simulated device and calibrate; return the app."""
    app = pilot.app
    assert isinstance(app, LaminaApp)
    await connect(pilot)
    await calibrate(pilot)
    return app


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
    await wait_for(pilot, lambda: app.job.processing.results is not None, "processing")
    await pilot.pause(0.2)


async def help_key_latencies_s(
    app: LaminaApp, poll_s: float = 0.001, pause_s: float = 0.0
) -> tuple[float, float]:
    """Send F1, then Escape ``pause_s`` after the help is up, as the terminal driver would.

    Return the seconds until the help screen is up and until it is gone again. Pilot's
    own ``press`` waits for the whole process to go idle, which a scan in a worker thread
    never is, so the keys go straight into the driver's queue instead.
    """
    assert app._driver is not None
    start = time.perf_counter()
    app._driver.send_message(events.Key("f1", None))
    while not isinstance(app.screen, HelpScreen):
        await asyncio.sleep(poll_s)
    opened_s = time.perf_counter() - start
    await asyncio.sleep(pause_s)
    closing = time.perf_counter()
    app._driver.send_message(events.Key("escape", None))
    while isinstance(app.screen, HelpScreen):
        await asyncio.sleep(poll_s)
    return opened_s, time.perf_counter() - closing


def csv_levels(path: Path) -> list[tuple[float, float, float]]:
    """Return a report CSV's level rows as (distance from the landmark, girth, the compared
    scan's girth), in mm whatever unit the table gives lengths in."""
    with path.open() as table:
        rows = [r for r in csv.DictReader(table) if r["row"] == "level"]
    [unit] = [u for u in LENGTH_UNITS if rows and f"girth_{u}" in rows[0]]
    mm = LENGTH_UNITS[unit]
    return [
        (
            float(r[f"from_landmark_{unit}"]) * mm,
            float(r[f"girth_{unit}"]) * mm,
            float(r[f"compared_girth_{unit}"]) * mm,
        )
        for r in rows
    ]
