"""Fixtures for the terminal UI tests: a scan library with one processed simulated scan."""

from __future__ import annotations

import re
import sqlite3
import sys
from collections.abc import Awaitable, Callable
from pathlib import Path

import numpy as np
import pytest
from pytest_textual_snapshot import SVGImageExtension
from syrupy.assertion import SnapshotAssertion
from textual._doc import take_svg_screenshot
from textual.app import App
from textual.pilot import Pilot
from textual_plotext import PlotextPlot

from lamina_host.ui.tui.adapter import DeviceTarget, ScanJob, parse_plan, process, scan_object
from lamina_host.ui.tui.widgets import FrameView

# The helpers in drive.py sit beside the tests; pytest's importlib mode does not add
# this folder to the import path by itself.
sys.path.insert(0, str(Path(__file__).parent))
from drive import CLINIC_PLAN

FIXED_CREATED = "2025-01-01T09:00:00+00:00"


@pytest.fixture(scope="session")
def right_arm_library(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Return a library holding one processed scan of P-0077's right arm (the arm phantom)."""
    path = tmp_path_factory.mktemp("clinic") / "library.sqlite"
    job = ScanJob(DeviceTarget("sim", "arm"), path)
    try:
        job.connect()
        job.acquisition.calibrate_grid()
        job.acquisition.accept_grid(True)
        job.acquisition.calibrate_axis()
        scan_object(job, "P-0077", parse_plan(*CLINIC_PLAN), side="right")
        process(job)
    finally:
        job.close()
    return path


@pytest.fixture(scope="session")
def scanned_library(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Return a library holding one 2 x 8 scan of the simulated 19.05 mm cylinder, processed."""
    path = tmp_path_factory.mktemp("library") / "library.sqlite"
    job = ScanJob(DeviceTarget("sim"), path)
    try:
        job.connect()
        job.acquisition.calibrate_grid()
        job.acquisition.accept_grid(True)
        job.acquisition.calibrate_axis()
        scan_object(job, "CYL-1", parse_plan("2", "2", "8"))
        process(job, harmonics=5)
    finally:
        job.close()
    # Snapshots must not show the clock: give the scan a fixed creation time.
    with sqlite3.connect(path) as db:
        db.execute("UPDATE scans SET created = ?", (FIXED_CREATED,))
    return path


TEXT_NODE = re.compile(r"(<text[^>]*>)(.*?)(</text>)", re.S)
DIGIT = re.compile(r"&#?\w+;|[A-Za-z]\d+|\d")
"""A digit; or kept whole: an XML entity (``&#160;`` is a space) or digits after a letter
(key names such as F2, codes such as P001, units such as mm2)."""


def mask_numbers(svg: str) -> str:
    """Return a screenshot with every number shown on screen masked, digit by digit, by ``#``."""

    def mask(node: re.Match[str]) -> str:
        text = DIGIT.sub(lambda m: "#" if m.group().isdigit() else m.group(), node[2])
        return node[1] + text + node[3]

    return TEXT_NODE.sub(mask, svg)


async def blank_data(pilot: Pilot) -> None:
    """Empty every plot and grey every camera frame: their dots and pixels are numbers too."""
    for plot in pilot.app.screen.query(PlotextPlot):
        plot.plt.clear_data()
        plot.refresh()
    for view in pilot.app.screen.query(FrameView):
        if view.image is not None:
            view.image = np.full_like(view.image, 128)
        view.stripe_uv = None
    await pilot.pause()


LayoutCompare = Callable[[App, Callable[[Pilot], Awaitable[None]]], bool]


@pytest.fixture
def layout_compare(snapshot: SnapshotAssertion) -> LayoutCompare:
    """Compare a screen with its snapshot by layout and text, its numbers masked.

    Simulator figures change whenever extraction or calibration improves; a snapshot
    holding them would have to be regenerated each time. The numbers are checked by
    Pilot tests against the workflow's result objects instead (test_screen_numbers.py).
    """
    svg_snapshot = snapshot.use_extension(SVGImageExtension)

    def compare(
        app: App, run_before: Callable[[Pilot], Awaitable[None]], size: tuple[int, int] = (80, 24)
    ) -> bool:
        async def prepared(pilot: Pilot) -> None:
            await run_before(pilot)
            await blank_data(pilot)

        svg = take_svg_screenshot(app=app, terminal_size=size, run_before=prepared)
        return bool(svg_snapshot == mask_numbers(svg))

    return compare
