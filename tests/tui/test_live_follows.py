"""The live screen follows the app's state as it changes: the latest scanned view, the axes.

Worker threads never touch these; a screen sets them on the UI thread, and the live
screen watches them (no polling). Set here directly, as the scan and live screens do.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from textual.widgets import Static

from lamina_host.ui.tui.app import LaminaApp
from lamina_host.workflow.device_session import Pose
from lamina_shared.types import Segment


def _segment(section: int, view: int, points: int) -> Segment:
    """Return a segment of ``points`` stripe points (positions do not matter here)."""
    line = np.arange(points, dtype=float)
    return Segment("object", section, view, 2.0 * section, 45.0 * view, line, line, line, line)


def _text(app: LaminaApp, selector: str) -> str:
    return str(app.screen.query_one(selector, Static).render())


async def test_the_live_screen_shows_each_new_scanned_view(tmp_path: Path) -> None:
    app = LaminaApp("sim", tmp_path / "library.sqlite")
    async with app.run_test(size=(80, 24)) as pilot:
        await pilot.press("f3")
        await pilot.pause()
        assert _text(app, "#stripe-info") == "no view scanned yet"
        for view, points in ((2, 40), (3, 12)):
            app.latest_segment = _segment(1, view, points)
            await pilot.pause()
            shown = _text(app, "#stripe-info")
            assert shown.startswith(f"object section 1, view {view}: {points} points")


async def test_a_view_scanned_while_away_is_shown_on_return(tmp_path: Path) -> None:
    app = LaminaApp("sim", tmp_path / "library.sqlite")
    async with app.run_test(size=(80, 24)) as pilot:
        await pilot.press("f3")
        await pilot.pause()
        await pilot.press("f5")
        await pilot.pause()
        app.latest_segment = _segment(0, 5, 7)
        await pilot.press("f3")
        await pilot.pause()
        assert _text(app, "#stripe-info").startswith("object section 0, view 5: 7 points")


async def test_the_live_screen_shows_where_the_axes_went(tmp_path: Path) -> None:
    app = LaminaApp("sim", tmp_path / "library.sqlite")
    async with app.run_test(size=(80, 24)) as pilot:
        await pilot.press("f3")
        await pilot.pause()
        assert _text(app, "#axes").startswith("turntable 0.0 deg\nlift 0.0 mm")
        app.pose = Pose(lift_mm=3.0, turntable_deg=30.0)
        await pilot.pause()
        assert _text(app, "#axes").startswith("turntable 30.0 deg\nlift 3.0 mm")
