"""The Scan screen's live time left: what the subject is told while the scan runs (issue 22).

Between two views the time left is counted down on the screen's own clock from the
latest progress's figure, and held while the scan is paused (a paused scan does not
run down). No device is needed: the screen is shown progress as the scan's thread
posts it.
"""

from __future__ import annotations

import re
from pathlib import Path

from drive import wait_for

from lamina_host.ui.tui.app import LaminaApp
from lamina_host.ui.tui.screens.scan import TICK_S, ScanEvent, ScanScreen
from lamina_shared.messages import Progress


def seconds_left(screen: ScanScreen) -> int:
    """Return the whole seconds the progress line says are left."""
    text = str(screen.query_one("#progress-text").render())
    found = re.search(r"view 4/20, section 1, (\d+) s left", text)
    assert found, text
    return int(found.group(1))


async def test_the_time_left_runs_down_between_views_and_holds_while_paused(
    tmp_path: Path,
) -> None:
    """A progress saying 40 s left (4 views in 10 s, 16 to go) is shown, then counted down
    by the seconds that pass; paused, the figure stays where it was."""
    app = LaminaApp("sim", tmp_path / "library.sqlite")
    async with app.run_test(size=(100, 30)) as pilot:
        await app.switch_mode("scan")
        screen = app.screen
        assert isinstance(screen, ScanScreen)
        screen.scanning = True  # as Start sets it; the views come as the scan thread posts
        progress = Progress("object", 4, 20, 1, elapsed_s=10.0, done_this_run=4)
        assert progress.left_s == 40.0
        screen.post_message(ScanEvent(progress=progress))
        await wait_for(
            pilot,
            lambda: "view 4/20" in str(screen.query_one("#progress-text").render()),
            "the progress",
        )
        first = seconds_left(screen)
        assert 38 <= first <= 40  # shown at once (a slow machine may be a tick late)
        await wait_for(pilot, lambda: seconds_left(screen) <= first - 2, "the count down")
        assert seconds_left(screen) >= first - 4  # it runs at the clock's pace, no faster

        screen.paused = True  # as p sets it before the device is asked to pause
        await pilot.pause(TICK_S * 1.2)
        held = seconds_left(screen)
        await pilot.pause(TICK_S * 2.5)
        assert seconds_left(screen) == held
        screen.paused = False
        await wait_for(pilot, lambda: seconds_left(screen) < held, "the count down resumed")
