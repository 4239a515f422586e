"""The clinical view on the Results screen (key m), driven by Textual's Pilot."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from drive import open_first_scan, wait_for
from textual.widgets import DataTable, Input, Static
from textual_plotext import PlotextPlot

from lamina_host.ui.tui.app import LaminaApp
from lamina_host.ui.tui.clinical_view import ClinicalView

DIAMETER_MM = 19.05
"""The simulated cylinder of the scanned library (see conftest)."""


async def test_measure_key_shows_circumferences_of_the_processed_scan(
    scanned_library: Path,
) -> None:
    """Open the library's scan, press m: levels at the cylinder's true circumference."""
    app = LaminaApp("sim", scanned_library)
    async with app.run_test(size=(100, 30)) as pilot:
        await open_first_scan(pilot)
        await pilot.press("m")
        await wait_for(pilot, lambda: isinstance(app.screen, ClinicalView), "the clinical view")
        view = app.screen
        assert isinstance(view, ClinicalView) and view.measurement is not None
        levels = view.query_one("#levels", DataTable)
        assert levels.row_count == len(view.measurement.levels) >= 1
        for level in view.measurement.levels:
            assert level.circumference_mm == pytest.approx(math.pi * DIAMETER_MM, abs=0.1)
        # The report's other plots: the outlines at the levels, the subject's visits.
        outlines = view.query_one("#clinical-outlines", PlotextPlot).plt
        drawn = list(zip(outlines.monitor.x, outlines.monitor.y, strict=True))
        assert len(drawn) == len(view.measurement.levels)
        for xs, ys in drawn:
            x, y = np.asarray(xs)[:-1], np.asarray(ys)[:-1]  # drawn closed: first point twice
            radius = np.hypot(x - x.mean(), y - y.mean())
            assert radius == pytest.approx(DIAMETER_MM / 2.0, abs=0.1)
        assert [v.scan_id for v in view.visits] == [1]  # the library's one scan
        # A landmark outside the scan is refused in one line; the table is kept.
        view.query_one("#landmark", Input).value = "500"
        view.set_focus(view.query_one("#landmark", Input))
        await pilot.press("enter")
        summary = str(view.query_one("#clinical-summary", Static).render())
        assert "outside the measured range" in summary
        # k puts the landmark at the section picked on Results (row 0: z = 0).
        await pilot.press("k")
        assert view.query_one("#landmark", Input).value == "0"
        assert view.measurement.landmark_z_mm == 0.0
        await pilot.press("escape")
        await wait_for(pilot, lambda: not isinstance(app.screen, ClinicalView), "closing")
