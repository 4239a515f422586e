"""One workflow: the same plan through the command line and the terminal UI (Pilot).

Both front ends drive :mod:`lamina_host.workflow.job`, so the simulated device (same
object, noise, rig and seed) gives the same stored segments and the same report figures.
"""

from __future__ import annotations

import json
import math
from dataclasses import fields
from pathlib import Path
from typing import Any

import numpy as np
from drive import calibrate, connect, fill_scan_form, wait_for
from textual.widgets import Input

from lamina_host.cli import main
from lamina_host.store.library import Library
from lamina_host.ui.tui.app import LaminaApp
from lamina_shared.types import Segment

DIAMETER_MM = 19.05
"""The simulated device's default object: the thesis's calibration cylinder."""
AREA_MM2 = math.pi * (DIAMETER_MM / 2) ** 2
PLAN = ("2", "2", "8")
"""Sections, pitch (mm) and views per section, typed alike into both front ends."""


def _stored(path: Path) -> tuple[dict[str, list[Segment]], dict[str, Any]]:
    """Return the only scan's segments per target and its stored report."""
    with Library(path) as library:
        (summary,) = library.scans()
        segments = {t: library.segments(summary.id, t) for t in ("cylinder", "object")}
        report = library.result(summary.id)
    assert report is not None
    return segments, report


def _same_segments(a: list[Segment], b: list[Segment]) -> None:
    assert len(a) == len(b) > 0
    for one, other in zip(a, b, strict=True):
        for f in fields(Segment):
            x, y = getattr(one, f.name), getattr(other, f.name)
            if isinstance(x, np.ndarray):
                np.testing.assert_array_equal(x, y, err_msg=f.name)
            else:
                assert x == y, f.name


def _figures(report: dict[str, Any]) -> dict[str, Any]:
    """Return the report without what depends on the clock (its timings)."""
    figures = json.loads(json.dumps(report))
    figures.pop("timings_s")
    return figures


async def test_cli_and_tui_store_and_report_the_same(tmp_path: Path) -> None:
    """The same 2 x 8 plan of the simulated cylinder through `lamina scan` and the TUI."""
    cli_library = tmp_path / "cli.sqlite"
    sections, pitch, views = PLAN
    status = main(
        ["scan", "--device", "sim", "-o", str(tmp_path / "out"), "--library", str(cli_library),
         "--subject", "P001", "--sections", sections, "--pitch", pitch, "--views", views]
    )  # fmt: skip
    assert status == 0

    tui_library = tmp_path / "tui.sqlite"
    app = LaminaApp("sim", tui_library)
    async with app.run_test(size=(80, 24)) as pilot:
        await connect(pilot)
        await calibrate(pilot)
        await fill_scan_form(pilot, "P001", sections, pitch, views)
        await pilot.press("s")
        await wait_for(pilot, lambda: app.job.acquisition.data.complete, "the scan")
        await pilot.press("f6")
        app.screen.query_one("#harmonics", Input).focus()
        await pilot.press("enter")  # blank harmonics: the rule chooses, as on the command line
        await wait_for(pilot, lambda: app.job.processing.results is not None, "processing")
        results = app.job.processing.results

    cli_segments, cli_report = _stored(cli_library)
    tui_segments, tui_report = _stored(tui_library)
    for target in ("cylinder", "object"):
        _same_segments(cli_segments[target], tui_segments[target])
    assert len(cli_segments["object"]) == 16
    assert _figures(cli_report) == _figures(tui_report)

    # The figures are the workflow's result objects', and right for the known cylinder.
    assert results is not None and _figures(results.report.to_json()) == _figures(tui_report)
    assert [row.index for row in results.rows] == [0, 1]
    for row in results.rows:
        assert abs(row.area_mm2 - AREA_MM2) / AREA_MM2 < 0.02
    assert abs(results.volume_mm3 - 2.0 * AREA_MM2) / (2.0 * AREA_MM2) < 0.02
    assert cli_report["subject_id"] == tui_report["subject_id"] == "P001"
