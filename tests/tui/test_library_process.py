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
from textual.widgets import DataTable, Static

import lamina_host.reconstruct.pipeline as pipeline
import lamina_host.workflow.processing as processing
from lamina_host.reconstruct.calibration import CalibrationError
from lamina_host.store.library import Library
from lamina_host.ui.tui.app import LaminaApp

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
        assert str(table.get_row_at(0)[4]) == "processed"
        monkeypatch.setattr(processing, "reconstruct", broken)
        await pilot.press("p")
        await wait_until(pilot, lambda: app.status[1], "the failure")
        message = app.status[0]
        assert message.startswith("processing failed: internal error (ZeroDivisionError")
        # In the screen's words, never a command to type (issue 24).
        assert "process it again: p on the Library screen" in message
        assert "lamina " not in message and "--" not in message
        assert app.job.processing.results is None
        monkeypatch.undo()
        with Library(library) as lib:  # nothing stored was touched by the failure
            assert lib.scans()[0].status == "processed" and lib.result(1) == before

        # Now one outline cannot be processed: it fails alone, the other is measured.
        original = pipeline.fit_section

        def fit(index: int, *args, **kwargs):
            if index == 1:
                raise CalibrationError("injected refusal")
            return original(index, *args, **kwargs)

        monkeypatch.setattr(pipeline, "fit_section", fit)
        app.status = ("", False)
        await pilot.press("p")
        await wait_for(pilot, lambda: app.job.processing.results is not None, "processing")
        await wait_for(pilot, lambda: app.current_mode == "results", "the Results screen")
        assert "scan 1 processed again" in app.status[0]
        rows = app.job.processing.results.rows
        assert [r.status for r in rows] == ["measured", "failed"]
        assert rows[0].perimeter_mm == pytest.approx(math.pi * DIAMETER_MM, abs=0.3)
        await pilot.pause(0.2)
        table = app.screen.query_one("#sections", DataTable)
        cells = [[str(c) for c in table.get_row_at(k)] for k in range(table.row_count)]
        assert cells[1][:2] == ["1", "2.00"] and cells[1][3:] == ["-", "failed", "-", "-", "-", "-"]
        summary = str(app.screen.query_one("#summary", Static).render())
        assert "outline 1.0 (z 2.00) failed: injected refusal" in summary
        # Section 0 is processed; alone, it is a curve without surface (said, not meshed).
        warnings = app.job.processing.results.report.warnings
        assert any("0.0 continue no outline" in w for w in warnings), warnings
    with Library(library) as lib:
        assert [(s.status, s.has_result) for s in lib.scans()] == [("processed", True)]
        stored = lib.result(1)["sections"]
        assert [(s["status"], s.get("reason")) for s in stored] == [
            ("measured", None), ("failed", "injected refusal"),
        ]  # fmt: skip


async def wait_until(pilot: Pilot, done: Callable[[], object], what: str) -> None:
    """Let the app run until ``done()`` holds (an error on the status line allowed)."""
    deadline = time.monotonic() + 60.0
    while not done():
        assert time.monotonic() < deadline, f"timed out waiting for {what}"
        await pilot.pause(0.05)
