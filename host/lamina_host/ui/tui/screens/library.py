"""Library: past scans; open (and process again), process again, export, delete (asked)."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import ClassVar, TypeVar

from rich.text import Text
from textual import on
from textual.app import ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal
from textual.screen import ModalScreen
from textual.widgets import DataTable, Input, Label, Static

from lamina_host.store.library import ScanSummary
from lamina_host.ui.tui.adapter import Results, process
from lamina_host.ui.tui.widgets import AskScreen, ConfirmScreen, LaminaScreen
from lamina_shared.errors import printable

T = TypeVar("T")

COLUMNS = ("scan", "subject", "side", "created", "status", "sect", "views", "result")


class LibraryScreen(LaminaScreen):
    """Past scans from the scan library."""

    MODE = "library"
    AUTO_FOCUS = "#scans"
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("o", "open", "Open"),
        Binding("p", "process", "Process"),
        Binding("e", "export", "Export"),
        Binding("d", "delete", "Delete"),
        Binding("u", "reload", "Update"),
        Binding("slash", "filter", "Filter"),
        Binding("escape", "leave_field", "Leave field"),
    ]

    def __init__(self) -> None:
        super().__init__()
        self.scans: list[ScanSummary] = []
        """The library's scans as last read (the table shows those the filter keeps)."""

    def body(self) -> ComposeResult:
        """The subject filter, the table of scans and a note on the chosen one."""
        with Horizontal(classes="row"):
            yield Label("Subject", classes="field-label")
            yield Input(placeholder="all subjects (type a code or its start)", id="filter",
                        compact=True)  # fmt: skip
        yield DataTable(id="scans", cursor_type="row", zebra_stripes=True)
        yield Static("", id="library-note")

    def action_filter(self) -> None:
        """Put the cursor in the subject filter."""
        self.query_one("#filter", Input).focus()

    def action_leave_field(self) -> None:
        """Leave the filter: the table takes the keys again."""
        self.query_one("#scans", DataTable).focus()

    @on(Input.Changed, "#filter")
    def _filter_changed(self) -> None:
        self.listed(self.scans)

    @on(Input.Submitted, "#filter")
    def _filter_submitted(self) -> None:
        self.action_leave_field()

    def on_mount(self) -> None:
        """Set up the columns."""
        self.query_one("#scans", DataTable).add_columns(*COLUMNS)

    def refresh_from_job(self) -> None:
        """Reload the list whenever the screen is shown."""
        self.action_reload()

    def action_reload(self) -> None:
        """Read the library's scans (in a thread: the file may be large or on a slow disk)."""
        self.in_thread("library", self.job.store.scans, self.listed)

    def listed(self, scans: list[ScanSummary]) -> None:
        """Fill the table with the scans whose subject code starts as the filter says."""
        self.scans = scans
        wanted = self.query_one("#filter", Input).value.strip().lower()
        shown = [s for s in scans if s.subject.lower().startswith(wanted)]
        table = self.query_one("#scans", DataTable)
        table.clear()
        for s in shown:
            table.add_row(
                str(s.id),
                Text(printable(s.subject)),  # plain text: an old code may hold markup or escapes
                s.side,
                s.created.replace("T", " ")[:16],
                s.status,
                str(s.sections),
                f"{s.received}/{s.views}",
                "yes" if s.has_result else "no",
                key=str(s.id),
            )
        count = f"{len(shown)} scan{'s' if len(shown) != 1 else ''}"
        if wanted:
            count += f" of {len(scans)} (subject {printable(wanted)!r})"
        note = f"{count}: o opens one, p processes it again, d deletes it"
        empty = f"no scan of a subject starting {printable(wanted)!r}" if wanted else "no scans yet"
        self.query_one("#library-note", Static).update(note if shown else empty)

    def _chosen(self) -> int | None:
        table = self.query_one("#scans", DataTable)
        if not table.row_count:
            self.say("the library has no scans yet: scan one (F5)", error=True)
            return None
        row_key = table.coordinate_to_cell_key(table.cursor_coordinate).row_key
        return int(str(row_key.value))

    def action_open(self) -> None:
        """Open the chosen scan and process it again."""
        scan_id = self._chosen()
        if scan_id is not None:
            self.say(f"opening scan {scan_id} ...")
            self.in_thread(
                "library-open",
                lambda: self._open(scan_id),
                lambda outcome: self.opened(scan_id, outcome),
            )

    def _open(self, scan_id: int) -> Results | int:
        """Load and process (in a worker); an incomplete scan gives its view count."""
        data = self.job.acquisition.open_scan(scan_id)
        return process(self.job) if data.complete else len(data.segments)

    def opened(self, scan_id: int, outcome: Results | int) -> None:
        """Show the processed scan, or say how to finish an incomplete one."""
        if isinstance(outcome, Results):
            self.say(f"scan {scan_id} processed again: see Results")
            self.app.switch_mode("results")
        else:
            self.say(f"scan {scan_id} is incomplete ({outcome} views): connect and resume (F5, p)")

    def action_process(self) -> None:
        """Process the chosen stored scan again (as ``lamina process``), then show Results."""
        scan_id = self._chosen()
        if scan_id is not None:
            self.say(f"processing scan {scan_id} again ...")
            self.in_thread(
                "library-open",
                lambda: self.job.processing.process_stored(scan_id),
                lambda _: self.processed(scan_id),
            )

    def processed(self, scan_id: int) -> None:
        """Say the scan is processed, refresh the list and show its results."""
        self.say(f"scan {scan_id} processed again: see Results")
        self.action_reload()
        self.app.switch_mode("results")

    def _ask_about_chosen(
        self, dialog: Callable[[int], ModalScreen[T]], answered: Callable[[int, T | None], None]
    ) -> None:
        """Ask ``dialog(scan_id)`` about the chosen scan; hand the answer to ``answered``."""
        scan_id = self._chosen()
        if scan_id is not None:
            self.app.push_screen(dialog(scan_id), lambda answer: answered(scan_id, answer))

    def action_export(self) -> None:
        """Ask for a folder and export the chosen scan into it."""
        self._ask_about_chosen(
            lambda scan_id: AskScreen(
                f"Export scan {scan_id} into folder:", "a new or empty folder"
            ),
            self._export_into,
        )

    def _export_into(self, scan_id: int, folder: str | None) -> None:
        """Export the scan into the folder answered (none: the user cancelled)."""
        if folder:
            path = Path(folder).expanduser()
            self.in_thread(
                "library-export",
                lambda: self.job.store.export_scan(scan_id, path),
                lambda paths: self.say(
                    f"exported scan {scan_id}: {', '.join(p.name for p in paths)}"
                ),
            )

    def action_delete(self) -> None:
        """Delete the chosen scan after asking."""
        self._ask_about_chosen(
            lambda scan_id: ConfirmScreen(f"Delete scan {scan_id} and everything recorded for it?"),
            self._delete_if,
        )

    def _delete_if(self, scan_id: int, yes: bool | None) -> None:
        """Delete the scan if the user confirmed; else say it is kept."""
        if not yes:
            self.say(f"scan {scan_id} kept")
            return
        self.in_thread(
            "library-delete", lambda: self.job.delete_scan(scan_id), lambda _: self.deleted(scan_id)
        )

    def deleted(self, scan_id: int) -> None:
        """Say so and refresh the list."""
        self.say(f"scan {scan_id} deleted")
        self.action_reload()
