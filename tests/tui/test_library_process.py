"""The Library screen processes a stored scan again: one whose processing failed is not lost."""

from __future__ import annotations

import math
import shutil
import time
from collections.abc import Callable
from pathlib import Path

import pytest
from drive import open_library, wait_for
from textual.pilot import Pilot

import lamina_host.workflow.job as job
from lamina_host.store import Library
from lamina_host.tui.app import LaminaApp

DIAMETER_MM = 19.05
"""The simulated device's default object: the thesis's calibration cylinder."""


async def test_library_p_processes_a_stored_scan_again_after_a_failure(
    scanned_library: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    library = tmp_path / "library.sqlite"
    shutil.copyfile(scanned_library, library)  # the shared library stays as it is
    with Library(library) as lib:
        before = lib.result(1)

    def broken(*args, **kwargs):
        raise ZeroDivisionError("injected")

    app = LaminaApp("sim", library)
    async with app.run_test(size=(100, 30)) as pilot:
        table = await open_library(pilot)
        assert str(table.get_row_at(0)[3]) == "processed"
        monkeypatch.setattr(job, "reconstruct", broken)
        await pilot.press("p")
        await wait_until(pilot, lambda: app.status[1], "the failure")
        message = app.status[0]
        assert message.startswith("processing failed: internal error (ZeroDivisionError")
        assert "lamina process 1" in message and "Library screen" in message
        assert app.session.results is None
        monkeypatch.undo()
        with Library(library) as lib:  # nothing stored was touched by the failure
            assert lib.scans()[0].status == "processed" and lib.result(1) == before

        app.status = ("", False)
        await pilot.press("p")
        await wait_for(pilot, lambda: app.session.results is not None, "processing")
        await wait_for(pilot, lambda: app.current_mode == "results", "the Results screen")
        assert "scan 1 processed again" in app.status[0]
        rows = app.session.results.rows
        assert [r.status for r in rows] == ["measured", "measured"]
        for r in rows:  # the simulated cylinder's true perimeter
            assert r.perimeter_mm == pytest.approx(math.pi * DIAMETER_MM, abs=0.3)
    with Library(library) as lib:
        assert [(s.status, s.has_result) for s in lib.scans()] == [("processed", True)]
        assert lib.result(1)["sections"] != before["sections"]  # default harmonics, not 5


async def wait_until(pilot: Pilot, done: Callable[[], object], what: str) -> None:
    """Let the app run until ``done()`` holds (an error on the status line allowed)."""
    deadline = time.monotonic() + 60.0
    while not done():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await pilot.pause(0.05)
