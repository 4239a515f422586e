"""A new worker of a group cancels the running one: the superseded one delivers nothing.

A thread cannot be stopped, so a cancelled worker runs to its end; what it returns (or
the error it raises) must not reach the screen, where it would overwrite the newer
worker's outcome. The screen here runs in the real app base (:class:`JobApp`) under Pilot.
"""

from __future__ import annotations

import threading
from pathlib import Path

from drive import wait_for

from lamina_host.ui.tui.adapter import DeviceTarget, ScanJob
from lamina_host.ui.tui.widgets import JobApp, LaminaScreen
from lamina_shared.errors import InputError

WAIT_S = 10.0
"""At most this long for the first worker's release (the test releases it at once)."""


class ProbeScreen(LaminaScreen):
    """A Lamina screen that records what its workers deliver."""

    def __init__(self) -> None:
        super().__init__()
        self.delivered: list[str] = []
        self.failures: list[str] = []

    def failed(self, message: str) -> None:
        """Record a worker's failure instead of showing it."""
        self.failures.append(message)


class ProbeApp(JobApp):
    """The app base every Lamina screen runs in, showing the probe screen."""

    def on_mount(self) -> None:
        """Show the probe."""
        self.push_screen(ProbeScreen())


def _held_worker(release: threading.Event, finished: threading.Event, outcome: str):
    """Return a job that waits for ``release``, then returns or raises ``outcome``."""

    def job() -> str:
        try:
            if not release.wait(WAIT_S):
                raise AssertionError("the test never released the first worker")
            if outcome == "raise":
                raise InputError("the superseded worker's failure")
            return outcome
        finally:
            finished.set()

    return job


async def _run(tmp_path: Path, outcome: str) -> ProbeScreen:
    """Start a held worker, supersede it with a quick one, then let the first one end."""
    app = ProbeApp(ScanJob(DeviceTarget("sim"), tmp_path / "library.sqlite"))
    release, finished = threading.Event(), threading.Event()
    async with app.run_test() as pilot:
        screen = app.screen
        assert isinstance(screen, ProbeScreen)
        screen.in_thread("probe", _held_worker(release, finished, outcome), screen.delivered.append)
        await pilot.pause()
        screen.in_thread("probe", lambda: "second", screen.delivered.append)
        await wait_for(pilot, lambda: screen.delivered == ["second"], "the second worker")
        release.set()
        await wait_for(pilot, finished.is_set, "the superseded worker's end")
        for _ in range(5):  # what it would deliver goes through the event loop
            await pilot.pause(0.05)
        app.job.close()
    return screen


async def test_a_superseded_worker_delivers_no_result(tmp_path: Path) -> None:
    """The first worker returns after the second: only the second's result is shown."""
    screen = await _run(tmp_path, "first")
    assert screen.delivered == ["second"]
    assert screen.failures == []


async def test_a_superseded_worker_reports_no_failure(tmp_path: Path) -> None:
    """The first worker fails after the second succeeded: the failure is not shown."""
    screen = await _run(tmp_path, "raise")
    assert screen.delivered == ["second"]
    assert screen.failures == []
