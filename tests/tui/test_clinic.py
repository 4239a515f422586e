"""Issue 24: a clinic runs a limb scan from the terminal UI alone, at 80 x 24.

A technician types the subject, picks the side, scans; the physiotherapist compares with
the other limb and exports the PDF report, its table and the DICOM file; every screen's
controls and keys are on screen at 80 x 24. Each of the problems the issue listed has a
test here that failed before its fix.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

import pydicom
import pytest
from drive import CLINIC_PLAN as PLAN
from drive import LEFT_ARM_SCALE as SCALE
from drive import calibrate, connect, csv_levels, fill_scan_form, open_first_scan, wait_for
from textual.pilot import Pilot
from textual.screen import Screen
from textual.widget import Widget
from textual.widgets import Checkbox, DataTable, Input, Select, Static
from textual.widgets._footer import FooterKey
from textual_plotext import PlotextPlot

from lamina_host.store.library import Library
from lamina_host.ui.tui.adapter import (
    DeviceTarget,
    ScanJob,
    choose_rig,
    parse_plan,
    user_message,
)
from lamina_host.ui.tui.app import LaminaApp
from lamina_host.ui.tui.clinical_view import ClinicalView
from lamina_host.ui.tui.screens.scan import CUSTOM, ScanScreen
from lamina_host.ui.tui.widgets import HELP_TEXT, SCREENS, HelpScreen, TickBox
from lamina_host.workflow.checks import PLAN_PRESETS, preset_plan
from lamina_shared.errors import InputError

SIZE = (80, 24)


def visible(screen: Screen, widget: Widget) -> bool:
    """Return True when the widget is whole on the screen and nothing covers its corner."""
    region = widget.region
    if region.width <= 0 or region.height <= 0 or not screen.region.contains_region(region):
        return False
    top, _ = screen.get_widget_at(region.x, region.y)
    return top is widget or widget in top.ancestors


def assert_controls_visible(screen: Screen) -> list[str]:
    """Assert every control of the screen and its footer's keys are whole on screen; return
    the keys the footer shows."""
    controls = screen.query("Input, Button, Select, Checkbox, DataTable, PlotextPlot, FrameView")
    assert controls, f"{type(screen).__name__} shows no control"
    for widget in controls:
        assert visible(screen, widget), f"{type(screen).__name__}: {widget!r} is cut or hidden"
    for plot in screen.query(PlotextPlot):
        assert plot.region.width >= 20, f"{plot.id} is {plot.region.width} columns wide"
    keys = list(screen.query(FooterKey))
    assert keys, f"{type(screen).__name__} has no footer keys"
    for key in keys:
        assert screen.region.contains_region(key.region), f"{key.key} runs off the footer"
    return [key.key for key in keys]


async def test_every_screen_shows_its_controls_and_keys_at_80_by_24(
    scanned_library: Path,
) -> None:
    """Before: the Scan screen lost Views, Start and Abort; the Results table ran into the
    plot; the clinical plot had one column; Measure (m) was not in the footer; the clinical
    view had no footer; the Live footer ran off the screen."""
    app = LaminaApp("sim", scanned_library)
    async with app.run_test(size=SIZE) as pilot:
        for mode, key, _ in SCREENS:
            await pilot.press(key)
            await pilot.pause(0.1)
            keys = assert_controls_visible(app.screen)
            if mode == "scan":  # the Subject field has the keys: the footer says how to leave
                assert "escape" in keys
                await pilot.press("escape")
                await pilot.pause(0.1)
                assert {"s", "b", "p"} <= set(assert_controls_visible(app.screen))
        await open_first_scan(pilot)
        keys = assert_controls_visible(app.screen)
        assert {"p", "m", "e"} <= set(keys)
        table = app.screen.query_one("#sections", DataTable)
        plot = app.screen.query_one("#profile", PlotextPlot)
        assert table.region.right < plot.region.x  # a gap: the table never runs into it
        await pilot.press("m")
        await wait_for(pilot, lambda: isinstance(app.screen, ClinicalView), "the clinical view")
        keys = assert_controls_visible(app.screen)
        assert {"escape", "k"} <= set(keys)


async def test_help_scrolls_and_covers_every_screen(tmp_path: Path) -> None:
    """Before: the help stopped after step 4 at any size and did not scroll."""
    for title in ("Connect", "Live", "Calibrate", "Scan", "Results", "Clinical view", "Library"):
        assert f"**{title}" in HELP_TEXT
    app = LaminaApp("sim", tmp_path / "library.sqlite")
    async with app.run_test(size=SIZE) as pilot:
        await pilot.press("f1")
        await wait_for(pilot, lambda: isinstance(app.screen, HelpScreen), "the help")
        box = app.screen.query_one("#help")
        assert box.max_scroll_y > 0  # more than one screenful at 80 x 24
        for _ in range(20):
            await pilot.press("pagedown")
        await pilot.pause(0.3)
        assert box.scroll_y == box.max_scroll_y  # the end can be reached
        await pilot.press("escape")
        await wait_for(pilot, lambda: not isinstance(app.screen, HelpScreen), "closing")


async def test_the_top_bar_switches_screens_on_click(tmp_path: Path) -> None:
    """Before: clicking (or tapping, in a browser) "F5 Scan" in the top bar did nothing."""
    app = LaminaApp("sim", tmp_path / "library.sqlite")
    async with app.run_test(size=SIZE) as pilot:
        nav = app.screen.query_one("#nav")
        text = str(nav.render())
        for mode, key, title in SCREENS:
            x = text.index(f"{key.upper()} {title}")
            await pilot.click("#nav", offset=(x + 1, 0))
            await wait_for(pilot, lambda mode=mode: app.current_mode == mode, f"the {title} screen")


def test_a_plan_error_names_only_the_wrong_field() -> None:
    """Before: "sections ('') and views ('8') must be whole numbers" blamed a valid field."""
    with pytest.raises(InputError) as refused:
        parse_plan("", "2", "8")
    assert str(refused.value).startswith("Sections is empty") and "Views" not in str(refused.value)
    with pytest.raises(InputError, match=r"^Views is 'x'"):
        parse_plan("2", "2", "x")
    with pytest.raises(InputError, match=r"^Pitch mm is 'two'"):
        parse_plan("2", "two", "8")


async def test_ui_errors_name_no_command_line_option(tmp_path: Path) -> None:
    """Before: a port that does not exist said "... or use --device sim" on the screen."""
    app = LaminaApp(str(tmp_path / "ttyNONE"), tmp_path / "library.sqlite")
    async with app.run_test(size=SIZE) as pilot:
        await pilot.press("c")
        await wait_for(pilot, lambda: app.status[1], "the connection error")
        message = app.status[0]
        assert "does not exist" in message and "pick sim in the port list" in message
        assert "--" not in message
    for line in (
        "the device does not know its calibration cylinder: pass --cylinder-mm",
        "scan 3 has no result yet: finish it with lamina scan --resume 3",
        "scan 3 has no result yet: its views are all in; process it again with lamina process "
        "3 [options] (or p on the terminal UI's Library screen)",
        "x; scan 3 is kept in the library: process it again with lamina process 3 [options] "
        "(or p on the terminal UI's Library screen)",
    ):
        shown = user_message(InputError(line))
        assert "--" not in shown and "lamina " not in shown, shown


async def test_an_unticked_colour_box_shows_no_mark(tmp_path: Path) -> None:
    """Before: the Colour box showed "X" ticked or not."""
    app = LaminaApp("sim", tmp_path / "library.sqlite")
    async with app.run_test(size=SIZE) as pilot:
        await pilot.press("f5")
        box = app.screen.query_one("#colour", TickBox)
        assert isinstance(box, Checkbox) and "X" not in str(box.render())
        box.value = True
        await pilot.pause()
        assert "X" in str(box.render())


async def test_a_clinic_scans_the_left_arm_compares_and_exports_the_report(
    right_arm_library: Path, tmp_path: Path
) -> None:
    """The whole limb scan from the UI at 80 x 24: subject, side, plan, scan, process,
    compare with the other limb (known truth: the left arm is the right one scaled by 1.1),
    export the PDF report, its CSV table and the DICOM file. First the refusals before a
    scan (:func:`_refused_starts`)."""
    library = tmp_path / "library.sqlite"
    shutil.copyfile(right_arm_library, library)
    out = tmp_path / "P-0077-left"
    app = LaminaApp("sim", library, f"arm:scale={SCALE}")
    async with app.run_test(size=SIZE) as pilot:
        await connect(pilot)
        screen = await _refused_starts(pilot, library)
        await fill_scan_form(pilot, "P-0077", *PLAN)
        assert screen.query_one("#preset", Select).value == CUSTOM  # typed numbers now
        screen.query_one("#side", Select).value = "left"
        await wait_for(
            pilot, lambda: "take about" in str(screen.query_one("#progress-text").render()),
            "the estimate",
        )  # fmt: skip
        await pilot.press("s")
        shown = await _progress_lines(pilot, screen)
        assert any(" left" in line and "view" in line for line in shown), shown
        await wait_for(pilot, lambda: "scan complete" in app.status[0], "the scan")

        await pilot.press("f6", "p")
        await wait_for(pilot, lambda: app.job.processing.results is not None, "processing")
        compare = app.screen.query_one("#compare", Select)
        await wait_for(pilot, lambda: len(app.screen.choices) == 1, "the comparison choices")
        assert app.screen.choices[0].label.startswith("other limb (right): scan 1")
        compare.value = 0
        await pilot.press("m")
        await wait_for(pilot, lambda: isinstance(app.screen, ClinicalView), "the clinical view")
        view = app.screen
        view.query_one("#spacing", Input).value = "5"
        view.set_focus(view.query_one("#spacing", Input))
        await pilot.press("enter")
        assert view.comparison is not None and len(view.comparison.levels) == 3
        excess = view.comparison.difference_percent
        assert 100 * (SCALE**2 - 1) * 0.6 < excess < 100 * (SCALE**2 - 1) * 1.4, excess
        summary = str(view.query_one("#clinical-summary", Static).render())
        assert "excess over other limb (right): scan 1" in summary
        assert f"{view.comparison.difference_ml:+.1f} mL ({excess:+.1f} %)" in summary
        levels = view.query_one("#levels", DataTable)
        assert all(str(levels.get_row_at(k)[3]).startswith("+") for k in range(3))
        await pilot.press("escape")
        await wait_for(pilot, lambda: not isinstance(app.screen, ClinicalView), "closing")

        app.screen.query_one("#export-dir", Input).value = str(out)
        await pilot.click("#export")
        await wait_for(pilot, lambda: "exported" in app.status[0], "the export")

    with Library(library) as opened:
        scans = {s.id: s for s in opened.scans()}
    assert (scans[2].subject, scans[2].side, scans[2].has_result) == ("P-0077", "left", True)
    assert (out / "report.pdf").read_bytes().startswith(b"%PDF")
    levels = csv_levels(out / "measures.csv")
    assert [offset for offset, _, _ in levels] == pytest.approx([0.0, 5.0, 10.0])  # the view's
    for level in levels:  # each level against the right arm: larger, as the scale says
        assert math.isclose(level[1] / level[2], SCALE, rel_tol=0.08), level
    dicom = pydicom.dcmread(out / "scan.dcm")
    assert dicom.PatientID == "P-0077"
    assert {p.name for p in out.iterdir()} >= {"mesh.stl", "report.json", "report.pdf"}


async def _refused_starts(pilot: Pilot, library: Path) -> ScanScreen:
    """A preset fills the plan (cut to the lift); not calibrated, or the preset's object too
    wide for the rig, Start is refused before anything is recorded, and (before: it stayed
    at "starting ...") the progress line says nothing is under way. Ends calibrated."""
    app = pilot.app
    assert isinstance(app, LaminaApp)
    await pilot.press("f5", "escape")
    screen = app.screen
    assert isinstance(screen, ScanScreen)
    screen.query_one("#subject", Input).value = "P-0077"
    screen.query_one("#preset", Select).value = "arm"
    await pilot.pause(0.2)
    info = app.job.device.info
    assert info is not None
    expected = preset_plan(PLAN_PRESETS["arm"], info.axes)
    assert screen._typed() == (str(expected.sections), "10", "8")
    assert "arm plan: cut to the lift's 200 mm travel" in app.status[0]
    for refusal in ("calibration cylinder first", "an arm is up to 130 mm across"):
        await pilot.press("s")
        await wait_for(pilot, lambda: not screen.scanning and app.status[1], "the refusal")
        assert refusal in app.status[0]
        assert "starting" not in str(screen.query_one("#progress-text", Static).render())
        app.status = ("", False)
        if refusal.startswith("calibration"):
            await calibrate(pilot)
            await pilot.press("f5", "escape")
    with Library(library) as opened:
        assert len(opened.scans()) == 1  # the right arm's alone: nothing recorded
    return screen


async def _progress_lines(pilot: Pilot, screen: ScanScreen) -> list[str]:
    """Return the progress line as it changed while the scan ran."""
    shown: list[str] = []
    while screen.scanning or not shown:
        text = str(screen.query_one("#progress-text", Static).render())
        if not shown or shown[-1] != text:
            shown.append(text)
        await pilot.pause(0.05)
    return shown


def test_choosing_a_rig_forgets_the_calibration_and_is_the_simulators_alone(
    tmp_path: Path,
) -> None:
    """The Rig field: the simulator's next connection uses it, the calibration made on the
    other rig is forgotten; a scanner (not the simulator) is its own rig."""
    job = ScanJob(DeviceTarget("sim"), tmp_path / "library.sqlite")
    job.acquisition.axis = object()  # type: ignore[assignment]  # as if calibrated
    job.acquisition.grid_accepted = True
    assert choose_rig(job, "limb") is None  # not connected: nothing restarts
    assert job.device.target.rig == "limb"
    assert job.acquisition.axis is None and not job.acquisition.grid_accepted
    with pytest.raises(InputError, match="Rig 'huge' is not one of thesis, limb"):
        choose_rig(job, "huge")
    port = ScanJob(DeviceTarget("/dev/ttyACM0"), tmp_path / "library.sqlite")
    with pytest.raises(InputError, match="a scanner is its own rig"):
        choose_rig(port, "limb")


async def test_questions_are_answered_by_touch(scanned_library: Path, tmp_path: Path) -> None:
    """A tablet has no y, n, Enter or Escape: the Library's questions have buttons."""
    library = tmp_path / "library.sqlite"
    shutil.copyfile(scanned_library, library)
    app = LaminaApp("sim", library)
    async with app.run_test(size=SIZE) as pilot:
        await pilot.press("f7")
        table = app.screen.query_one("#scans", DataTable)
        await wait_for(pilot, lambda: table.row_count == 1, "the scan list")
        await pilot.press("d")
        await wait_for(pilot, lambda: bool(app.screen.query("#no")), "the question")
        await pilot.click("#no")
        await wait_for(pilot, lambda: "kept" in app.status[0], "the answer")
        await pilot.press("e")
        await wait_for(pilot, lambda: bool(app.screen.query("#answer")), "the question")
        app.screen.query_one("#answer", Input).value = str(tmp_path / "out")
        await pilot.click("#ok")
        await wait_for(pilot, lambda: "exported scan 1" in app.status[0], "the export")
        assert (tmp_path / "out" / "mesh.stl").is_file()
        await pilot.press("d")
        await wait_for(pilot, lambda: bool(app.screen.query("#yes")), "the question")
        await pilot.click("#yes")
        await wait_for(pilot, lambda: "deleted" in app.status[0], "the deletion")
