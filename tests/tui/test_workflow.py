"""The whole workflow under Pilot: simulated device over a pseudo-terminal, real library."""

from __future__ import annotations

import asyncio
import json
import math
import statistics
from pathlib import Path

import pymeshlab
import pytest
from drive import calibrate, connect, fill_scan_form, help_key_latencies_s, wait_for
from textual.widgets import DataTable, Input

from lamina_host.store.library import Library
from lamina_host.ui.tui.app import LaminaApp

DIAMETER_MM = 19.05
"""The simulated device's default object: the thesis's calibration cylinder."""
AREA_MM2 = math.pi * (DIAMETER_MM / 2) ** 2
PERIMETER_MM = math.pi * DIAMETER_MM


def table_rows(app: LaminaApp) -> list[list[str]]:
    """Return the Results table's cells as text."""
    table = app.screen.query_one("#sections", DataTable)
    return [[str(c) for c in table.get_row_at(i)] for i in range(table.row_count)]


async def test_whole_workflow(tmp_path: Path) -> None:
    """Connect, calibrate, scan 2 x 8, process with 5 harmonics, export; check the files."""
    library, out = tmp_path / "library.sqlite", tmp_path / "export"
    app = LaminaApp("sim", library)
    async with app.run_test(size=(80, 24)) as pilot:
        await connect(pilot)
        assert app.job.device.info is not None and app.job.device.info.cylinder_diameter_mm == 19.05
        await calibrate(pilot)
        assert app.job.acquisition.grid is not None and app.job.acquisition.grid.n_corners == 143
        assert abs(app.job.acquisition.axis.correction_factor - 1.0) < 0.01

        await fill_scan_form(pilot, "P001", "2", "2", "8")
        await pilot.press("s")
        latencies = []
        while not app.job.acquisition.data.complete:
            latencies.append((await help_key_latencies_s(app))[0])
            await asyncio.sleep(0.05)
        await wait_for(pilot, lambda: "scan complete" in app.status[0], "the scan")
        # The median must meet the 100 ms requirement; single presses may wait for a
        # busy shared machine (the suite runs in two processes on two cores: 1.1 s seen
        # once at load 10), but none may look like a freeze (processing or a view's
        # acquisition on the UI's loop holds it for several seconds).
        assert latencies, "the scan ended before a key could be pressed during it"
        assert statistics.median(latencies) < 0.1, f"key latency during the scan: {latencies}"
        assert max(latencies) < 2.0, f"key latency during the scan: {latencies}"
        assert len(app.job.acquisition.data.segments) == 16

        await pilot.press("f6")
        harmonics = app.screen.query_one("#harmonics", Input)
        harmonics.focus()
        await pilot.press("5", "enter")
        await wait_for(pilot, lambda: app.job.processing.results is not None, "processing")
        rows = table_rows(app)
        assert [r[0] for r in rows] == ["0", "1"]
        for _, _, _, cover, closed, perimeter, area, roundness, harm in rows:
            assert float(cover) == 100.0 and closed == "measured"  # 8 views see it all round
            assert abs(float(area) - AREA_MM2) / AREA_MM2 < 0.02
            assert abs(float(perimeter) - PERIMETER_MM) / PERIMETER_MM < 0.02
            assert float(roundness) > 0.98
            assert harm == "5"
        assert abs(app.job.processing.results.volume_mm3 - 2.0 * AREA_MM2) / (2.0 * AREA_MM2) < 0.02

        export = app.screen.query_one("#export-dir", Input)
        export.focus()
        await pilot.press(*str(out), "enter")
        await wait_for(pilot, lambda: "exported" in app.status[0], "the export")

    faces = set()
    for name in ("mesh.ply", "mesh.obj", "mesh.stl"):
        meshes = pymeshlab.MeshSet()
        meshes.load_new_mesh(str(out / name))
        faces.add(meshes.current_mesh().face_number())
    assert len(faces) == 1 and faces.pop() > 100
    report = json.loads((out / "report.json").read_text())
    assert report["subject_id"] == "P001"
    assert [s["harmonics"] for s in report["sections"]] == [5, 5]
    with Library(library) as lib:
        (summary,) = lib.scans()
    assert (summary.subject, summary.received, summary.views) == ("P001", 16, 16)
    assert summary.has_result


async def test_abort_keeps_views_and_resume_finishes(tmp_path: Path) -> None:
    """Abort mid-scan keeps what arrived; resume fetches only the missing views."""
    app = LaminaApp("sim", tmp_path / "library.sqlite")
    async with app.run_test(size=(80, 24)) as pilot:
        await connect(pilot)
        await calibrate(pilot)
        await fill_scan_form(pilot, "P002", "2", "2", "8")
        await pilot.press("s")
        await wait_for(pilot, lambda: len(app.job.acquisition.held) >= 3, "three views")
        # Pause on the device: after the view in flight, no more views arrive.
        await pilot.press("p")
        await pilot.pause(1.5)
        paused_at = len(app.job.acquisition.held)
        await pilot.pause(1.0)
        assert app.screen.paused and len(app.job.acquisition.held) == paused_at < 16
        await pilot.press("p")
        await wait_for(
            pilot, lambda: len(app.job.acquisition.held) > paused_at, "the resumed views"
        )
        # Pause again and abort while paused: an abort pressed while views stream can come
        # after the last of them on a quick machine (a clean clone once had all 16 in).
        await pilot.press("p")
        await pilot.pause(1.5)
        await pilot.press("b")
        await wait_for(pilot, lambda: not app.screen.scanning, "the abort")
        kept = len(app.job.acquisition.held)
        assert 3 <= kept < 16
        assert "views received are kept" in app.status[0]
        app.status = ("", False)
        await pilot.press("p")
        await wait_for(pilot, lambda: app.job.acquisition.data.complete, "the resumed scan")
        assert sorted(app.job.acquisition.held) == list(range(16))


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        (("", "2", "2", "8"), "enter a subject id"),
        (("P1", "0", "2", "8"), "sections 0 must be between 1 and 500"),
        (("P1", "2", "-1", "8"), "pitch -1 mm must be above 0"),
        (("P1", "2", "2", "2"), "views 2 must be between 3 and 360"),
    ],
)
async def test_bad_scan_input_is_one_clear_line(
    tmp_path: Path, fields: tuple[str, str, str, str], message: str
) -> None:
    """Bad plan input is refused with a message naming the field; nothing starts."""
    app = LaminaApp("sim", tmp_path / "library.sqlite")
    async with app.run_test(size=(80, 24)) as pilot:
        await fill_scan_form(pilot, *fields)
        await pilot.press("s")
        await pilot.pause()
        status, is_error = app.status
        assert is_error and message in status
        assert not app.screen.scanning


async def test_missing_port_and_early_steps_explain_themselves(tmp_path: Path) -> None:
    """A port that does not exist and steps out of order give one line each, no traceback."""
    app = LaminaApp(str(tmp_path / "ttyNONE"), tmp_path / "library.sqlite")
    async with app.run_test(size=(80, 24)) as pilot:
        await pilot.press("c")
        await wait_for(pilot, lambda: app.status[1], "the connection error")
        assert app.status[0].startswith(f"serial port {tmp_path / 'ttyNONE'} does not exist")
        await pilot.press("f4", "g")
        await wait_for(pilot, lambda: "no device connected" in app.status[0], "the refusal")
        await pilot.press("y")
        await wait_for(pilot, lambda: "accept the chessboard first" in app.status[0], "refusal")
        await pilot.press("f6", "p")
        await wait_for(pilot, lambda: "nothing to process" in app.status[0], "the refusal")
