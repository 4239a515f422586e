"""The Lamina terminal UI: the whole workflow from connecting to exporting, by keyboard.

``lamina tui --device sim`` runs it; over SSH it needs nothing but a terminal of at
least 80 x 24. Every blocking step (serial I/O, calibration, meshing) runs in a thread
worker of the screen that asked for it, so keys are answered while the scanner works.
"""

from __future__ import annotations

import gc
from collections.abc import Iterable
from functools import partial
from pathlib import Path
from typing import ClassVar

from textual.app import SystemCommand
from textual.binding import Binding, BindingType
from textual.screen import Screen

from lamina_host.ui.tui.adapter import DeviceTarget, ScanJob
from lamina_host.ui.tui.screens.calibrate import CalibrateScreen
from lamina_host.ui.tui.screens.connect import ConnectScreen
from lamina_host.ui.tui.screens.library import LibraryScreen
from lamina_host.ui.tui.screens.live import LiveScreen
from lamina_host.ui.tui.screens.results import ResultsScreen
from lamina_host.ui.tui.screens.scan import ScanScreen
from lamina_host.ui.tui.widgets import SCREENS, HelpScreen, JobApp

MIN_SIZE = (80, 24)
"""The smallest terminal the layout is designed for (columns, rows)."""
FULL_COLLECTIONS_RARER = 10
"""While the app runs, the garbage collector's oldest generation is collected this many
times less often than it was (``gc.set_threshold``; restored on unmount)."""


class LaminaApp(JobApp):
    """Connect, calibrate, scan, process, export and browse past scans."""

    CSS_PATH = "lamina.tcss"
    TITLE = "Lamina"
    MODES: ClassVar[dict[str, str | type[Screen]]] = {  # type: ignore[assignment]
        "connect": ConnectScreen,
        "live": LiveScreen,
        "calibrate": CalibrateScreen,
        "scan": ScanScreen,
        "results": ResultsScreen,
        "library": LibraryScreen,
    }
    DEFAULT_MODE = "connect"
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("f1", "help", "Help"),
        *(
            Binding(key, f"switch_mode('{mode}')", title, show=False)
            for mode, key, title in SCREENS
        ),
    ]
    # Textual declares these without ClassVar, so mypy refuses one here.
    HORIZONTAL_BREAKPOINTS = [  # noqa: RUF012
        (0, "-too-narrow"),
        (MIN_SIZE[0], "-normal"),
    ]
    VERTICAL_BREAKPOINTS = [  # noqa: RUF012
        (0, "-too-short"),
        (MIN_SIZE[1], "-normal-height"),
    ]

    def __init__(
        self,
        device: str = "sim",
        library: Path | None = None,
        object_spec: str | None = None,
        noise: str = "thesis",
        rig: str = "thesis",
    ) -> None:
        target = DeviceTarget(device, object_spec, noise=noise, rig=rig)
        # Processed apart: a processing thread here took the interpreter's lock from the
        # keys' answers, past 100 ms in a quarter of the bench's runs.
        super().__init__(ScanJob(target, library, process_apart=True))
        self._gc_thresholds = gc.get_threshold()  # restored on unmount

    def on_mount(self) -> None:
        """Install the help once: laid out on first use, it then opens at once, even during a
        scan (its text is long); set aside what is loaded by now from the garbage collector."""
        self.install_screen(HelpScreen(), "help")
        # A full collection walks every object the process holds: with the host's libraries
        # and Textual loaded (about 130,000 objects) it stalled the app 100-140 ms a few
        # times a scan, and a key pressed then waited for it. What exists now (modules, the
        # app) lives as long as the app, so the collector need not walk it again; freed
        # objects are still freed by their reference counts. Undone on unmount.
        gc.freeze()
        # What a scan and processing make after that still brought a full collection (40-70
        # ms) about eight times a bench run; ten times fewer of them leave the rest to the
        # young generations, which free short-lived cycles in a millisecond or two.
        young, middle, old = self._gc_thresholds
        gc.set_threshold(young, middle, old * FULL_COLLECTIONS_RARER)

    def action_help(self) -> None:
        """Show the keys and the workflow."""
        if not isinstance(self.screen, HelpScreen):
            self.push_screen("help")

    def get_system_commands(self, screen: Screen) -> Iterable[SystemCommand]:
        """Offer every screen and the help in the command palette."""
        yield from super().get_system_commands(screen)
        for mode, key, title in SCREENS:
            yield SystemCommand(
                f"Go to {title}",
                f"Show the {title} screen ({key.upper()})",
                partial(self.switch_mode, mode),
            )
        yield SystemCommand("Help", "Show every key and the workflow (F1)", self.action_help)

    def on_unmount(self) -> None:
        """Stop the device program this host started, if any; give what was set aside back to
        the garbage collector (a cycle among it is then collected as usual)."""
        self.job.close()
        gc.unfreeze()
        gc.set_threshold(*self._gc_thresholds)
