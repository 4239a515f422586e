"""The numbers each screen shows, checked against the workflow's result objects and truth.

The snapshots (test_snapshots.py) hold layout and text with their numbers masked; the
figures are checked here, so a change of the simulator or of extraction changes no
snapshot, only (if it is wrong) these assertions.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from drive import calibrate, connect, fill_scan_form, open_library, wait_for
from textual.widgets import DataTable, Input, Select, Static

from lamina_host.reconstruct.axis import gear_ratio_factor
from lamina_host.reconstruct.pipeline import assemble
from lamina_host.store.outputs import OutlineEntry
from lamina_host.ui.tui.adapter import parse_plan
from lamina_host.ui.tui.app import LaminaApp
from lamina_host.ui.tui.screens.scan import ScanScreen
from lamina_host.workflow.job import TRIM_FRACTION
from lamina_shared.durations import duration_text
from lamina_shared.types import SCAN_MODES, from_first_turn

RADIUS_MM = 19.05 / 2
"""The simulated device's default object: the thesis's calibration cylinder."""


def text_of(app: LaminaApp, selector: str) -> str:
    """Return the plain text a Static on the current screen shows."""
    return str(app.screen.query_one(selector, Static).render())


async def test_screens_show_the_workflow_figures(tmp_path: Path) -> None:
    """Calibrate, Scan and Results show what the job computed, and that is right."""
    app = LaminaApp("sim", tmp_path / "library.sqlite")
    async with app.run_test(size=(80, 24)) as pilot:
        await connect(pilot)
        await calibrate(pilot)
        job = app.job
        grid, axis = job.acquisition.grid, job.acquisition.axis
        assert grid is not None and axis is not None
        grid_text, axis_text = text_of(app, "#grid-result"), text_of(app, "#axis-result")
        assert f"{grid.n_corners} corners" in grid_text and grid.n_corners == 143
        assert f"PASS: residual {grid.rms_mm:.3f} mm RMS" in grid_text and grid.rms_mm < 0.05
        assert f"correction     {axis.correction_factor:.5f}" in axis_text
        assert f"{axis.estimated_diameter_mm:.3f} mm measured" in axis_text
        assert abs(axis.estimated_diameter_mm - 2 * RADIUS_MM) < 0.1
        # The simulated table is geared 0.2 degrees per 45 short: the factor that mends it.
        factor = gear_ratio_factor(axis)
        assert factor is not None and abs(factor - 45.0 / 44.8) < 2e-4
        assert f"gear_ratio in the box's configuration by {factor:.5f}" in " ".join(
            axis_text.split()
        )

        await fill_scan_form(pilot, "P001", "2", "2", "8")
        # Before Start: the device's estimate of the typed plan, for the subject's sake.
        await wait_for(
            pilot, lambda: "16 views take about" in text_of(app, "#progress-text"), "estimate"
        )
        # Each mode's own estimate, as the device models it: continuous is far shorter.
        plan = parse_plan("2", "2", "8")
        said = {}
        for mode in reversed(SCAN_MODES):  # continuous, then back to the default
            app.screen.query_one("#mode", Select).value = mode
            estimate = job.device.estimate("object", plan.with_mode(mode))
            assert estimate is not None and estimate.views == 16
            said[mode] = text = f"16 views take about {duration_text(estimate.modelled_s)};"
            await wait_for(
                pilot,
                lambda text=text: text in text_of(app, "#progress-text"),
                f"{mode} estimate",
            )
        assert said["continuous"] != said["stop-and-go"], said
        await pilot.press("s")
        await wait_for(pilot, lambda: "scan complete" in app.status[0], "the scan")
        screen = app.screen
        assert isinstance(screen, ScanScreen)
        assert "object view 16/16" in text_of(app, "#progress-text")
        # The live plot's last section is assembled exactly as the final result is.
        held = job.acquisition.data.segments
        live = job.acquisition.section_points([s for s in held if s.section == 1])
        last = [s for s in from_first_turn(held) if s.section == 1]
        by_section, _, _ = assemble(last, grid, axis, TRIM_FRACTION)
        np.testing.assert_array_equal(live, np.vstack(by_section[1]))
        radii = np.hypot(live[:, 0], live[:, 1])
        assert len(live) > 1000 and abs(float(np.median(radii)) - RADIUS_MM) < 0.05

        await pilot.press("f6")
        app.screen.query_one("#harmonics", Input).focus()
        await pilot.press("5", "enter")
        await wait_for(pilot, lambda: job.processing.results is not None, "processing")
        results = job.processing.results
        assert results is not None
        table = app.screen.query_one("#sections", DataTable)
        shown = [[str(c) for c in table.get_row_at(i)] for i in range(table.row_count)]
        expected = [
            [str(r.index), f"{r.z_mm:.2f}", str(r.points), f"{r.coverage_percent:.0f}",
             r.status, f"{r.perimeter_mm:.2f}",
             f"{r.area_mm2:.1f}", f"{r.roundness:.4f}", str(r.harmonics)]
            for r in results.rows
        ]  # fmt: skip
        assert shown == expected
        area_mm2 = math.pi * RADIUS_MM**2
        assert all(abs(r.area_mm2 - area_mm2) / area_mm2 < 0.02 for r in results.rows)
        summary = text_of(app, "#summary")
        volume = results.volume_mm3
        assert f"volume {volume / 1000:.1f} mL ({volume:.0f} mm3)" in summary
        assert [s.area_mm2 for s in results.report.sections if isinstance(s, OutlineEntry)] == [
            r.area_mm2 for r in results.rows
        ]


async def test_library_screen_shows_the_stored_scan(scanned_library: Path) -> None:
    """The Library row shows the library's own summary of the processed scan."""
    app = LaminaApp("sim", scanned_library)
    async with app.run_test(size=(80, 24)) as pilot:
        table = await open_library(pilot)
        (summary,) = app.job.store.scans()
        row = [str(c) for c in table.get_row_at(0)]
        assert row[0] == str(summary.id) and row[1] == summary.subject == "CYL-1"
        assert f"{summary.received}/{summary.views}" in row and summary.views == 16
