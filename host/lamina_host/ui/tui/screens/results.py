"""Results: per-section measurements, radius profile, volume; process again; export."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import ClassVar

from rich.text import Text
from textual import on
from textual.app import ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal
from textual.widgets import Button, DataTable, Input, Label, Select, Static
from textual_plotext import PlotextPlot

from lamina_host.clinical.measures import LimbMeasurement, Visit, sections_from_reconstruction
from lamina_host.clinical.report import MeasureRequest, measure_stored, subject_visits
from lamina_host.reconstruct.efd import HARMONIC_RULES
from lamina_host.reconstruct.mesh import MESH_METHODS
from lamina_host.reconstruct.status import ESTIMATED
from lamina_host.ui.tui.adapter import (
    CompareChoice,
    Results,
    UserError,
    compare_choices,
    export_all,
    process,
    radius_profile,
)
from lamina_host.ui.tui.clinical_view import ClinicalView
from lamina_host.ui.tui.widgets import LaminaScreen, name_choice
from lamina_host.workflow.results import SectionRow, colour_bins, mesh_summary
from lamina_shared.errors import LaminaError

COLUMNS = ("sec", "z mm", "pts", "cov %", "closed", "perim mm", "area mm2", "round", "harm")
"""Per-outline table; roundness is 4 pi A / P^2 (1 for a circle); cover % is the share of
the circumference the views saw; closed says how: measured all round, bridged (small gaps
closed by EFD), interpolated (a wide gap filled from the neighbouring sections) or open
(not closed, not meshed) or failed (not processed: the summary says why). Bridged and
interpolated stretches are estimated, not measured."""


def coverage_cells(row: SectionRow) -> tuple[str, str]:
    """Return the cover % and closed cells of one outline ("-" cover for a failed one)."""
    return ("-" if row.failed else f"{row.coverage_percent:.0f}"), row.status


def parse_harmonics(text: str) -> tuple[int | None, str | None]:
    """Return (fixed harmonic count, harmonic rule) typed in the harmonics field.

    A number fixes the count; a rule name (``noise``, ``power``, ``thesis``, ``nyquist``)
    lets that rule choose per section; blank or ``auto`` keeps the default rule.
    """
    text = text.strip().lower()
    if not text or text == "auto":
        return None, None
    if text in HARMONIC_RULES:
        return None, text
    try:
        return int(text), None
    except ValueError:
        rules = ", ".join(HARMONIC_RULES)
        raise UserError(
            f"harmonics {text!r} must be a whole number, a rule ({rules}) or blank for auto"
        ) from None


COLOUR_SECTORS = 32
"""Angular sectors of each section's colour strip on the Results screen."""


def colour_strip(results: Results | None) -> Text | None:
    """Return one strip per coloured outline: its mean colour round the section, or None.

    Each block is one of :data:`COLOUR_SECTORS` sectors counter-clockwise from +x; a
    sector no coloured point fell in is a blank.
    """
    if results is None:
        return None
    text = Text()
    for section in results.reconstruction.sections:
        bins = colour_bins(section, COLOUR_SECTORS)
        if bins is None:
            continue
        text.append(f"\ncolour {section.index}.{section.part} z {section.z_mm:6.2f} ")
        for r, g, b in bins.round().astype(int).tolist():
            text.append(" " if r < 0 else "\u2588", style="" if r < 0 else f"rgb({r},{g},{b})")
    return text if text else None


def summary_text(results: Results | None) -> str:
    """Return the volume, mesh and warnings as lines."""
    if results is None:
        return "nothing processed yet: scan (F5) or open a scan (F7), then press p"
    result = results.reconstruction
    mesh = f"mesh ({results.mesh_method}): {mesh_summary(results.report.mesh)}"
    lines = [
        f"volume {results.volume_mm3 / 1000:.1f} mL ({results.volume_mm3:.0f} mm3) between "
        "the first and last section",
        mesh,
    ]
    estimated = [s for s in result.sections if s.status in ESTIMATED]
    if estimated or not all(s.closed for s in result.sections):
        lines.append(
            f"{len(estimated)} outline(s) closed across unseen gaps (estimated stretches, "
            f"not in points.ply), {sum(not s.closed for s in result.sections)} left open "
            "(meshed where seen)"
        )
    lines += [
        f"outline {f.index}.{f.part} (z {f.z_mm:.2f}) {f.status}: {f.reason}" for f in result.failed
    ]
    return "\n".join(lines + [f"warning: {w}" for w in result.warnings])


class ResultsScreen(LaminaScreen):
    """The processed scan, the choices to process it again, and export."""

    MODE = "results"
    AUTO_FOCUS = "#sections"
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("p", "process", "Process"),
        Binding("m", "clinical", "Measure"),
        Binding("e", "export", "Export"),
        Binding("escape", "leave_field", "Leave field"),
    ]

    def __init__(self) -> None:
        super().__init__()
        self.measure_request = MeasureRequest()
        """How the clinical view last measured (the report exports the same)."""
        self.choices: list[CompareChoice] = []
        """What the open scan may be compared with (the Compare field's choices)."""

    def body(self) -> ComposeResult:
        """Options row, table and profile, summary, export row."""
        with Horizontal(classes="row"):
            yield Label("Harmonics", classes="field-label")
            yield Input(placeholder="auto", id="harmonics", compact=True)
            yield Label("Mesh", classes="field-label")
            yield name_choice(MESH_METHODS, "mesh-method")
            yield Button("Process", id="process", variant="primary", compact=True)
        with Horizontal(id="results-main"):
            yield DataTable(id="sections", cursor_type="row", zebra_stripes=True)
            yield PlotextPlot(id="profile")
        yield Static(summary_text(None), id="summary")
        with Horizontal(classes="row"):
            yield Label("Compare", classes="field-label")
            yield Select([], prompt="no comparison", id="compare", compact=True, allow_blank=True)
        with Horizontal(classes="row"):
            yield Label("Export to", classes="field-label")
            yield Input(placeholder="a new folder, e.g. out/P-0042", id="export-dir", compact=True)
            yield Button("Export", id="export", compact=True)

    def on_mount(self) -> None:
        """Set up the table columns and the empty profile."""
        self.query_one("#sections", DataTable).add_columns(*COLUMNS)
        self._draw_profile(None)

    def action_clinical(self) -> None:
        """Open the clinical measurements (lamina_host.ui.tui.clinical_view) of the results."""
        results = self.job.processing.results
        if results is None:
            self.say("process a scan first (p), then measure it (m)", error=True)
            return
        row = self.query_one("#sections", DataTable).cursor_row
        picked = results.rows[row].z_mm if 0 <= row < len(results.rows) else None
        choice = self.chosen_comparison()
        self.app.push_screen(
            ClinicalView(
                sections_from_reconstruction(results.reconstruction),
                picked,
                self._visits(),
                choice,
                None if choice is None else self._reference(choice),
                self._measured,
            )
        )

    def _reference(self, choice: CompareChoice) -> Callable[[MeasureRequest], LimbMeasurement]:
        """Return what measures the compared scan as the clinical view asks."""
        library = self.job.store.library()
        return lambda request: measure_stored(library, choice.scan_id, request)

    def _measured(self, request: MeasureRequest) -> None:
        """Keep how the clinical view measured: the exported report measures the same."""
        self.measure_request = request

    def chosen_comparison(self) -> CompareChoice | None:
        """Return the scan chosen in the Compare field (None: no comparison)."""
        value = self.query_one("#compare", Select).value
        return self.choices[value] if isinstance(value, int) else None

    def _visits(self) -> list[Visit]:
        """Return the visits of the open scan's subject in the library (none if unsaved)."""
        scan_id = self.job.scan_id
        if scan_id is None:
            return []
        try:
            library = self.job.store.library()  # the job's own: one connection a process
            return subject_visits(library, library.scan(scan_id).subject, MeasureRequest())
        except LaminaError:
            return []  # the view still measures this scan; only the history is missing

    def action_leave_field(self) -> None:
        """Leave the text field so the screen's keys work again."""
        self.set_focus(None)

    @on(Button.Pressed, "#process")
    @on(Input.Submitted, "#harmonics")
    def action_process(self) -> None:
        """Process the scan again with the chosen harmonics and mesh method."""
        try:
            harmonics, rule = parse_harmonics(self.query_one("#harmonics", Input).value)
        except UserError as exc:
            self.say(str(exc), error=True)
            return
        method = str(self.query_one("#mesh-method", Select).value)
        self.query_one("#process", Button).disabled = True
        self.say("processing ...")
        # In a thread: calibration, EFD and meshing take seconds.
        self.in_thread(
            "process", lambda: process(self.job, harmonics, method, rule), self.processed
        )

    def processed(self, results: Results) -> None:
        """Show the new results."""
        self.query_one("#process", Button).disabled = False
        self.refresh_from_job()
        failed = len(results.reconstruction.failed)
        self.say(
            f"processed {len(results.rows)} sections; volume {results.volume_mm3 / 1000:.1f} mL"
            + (f"; {failed} outline(s) failed (see the summary)" if failed else "")
        )

    def failed(self, message: str) -> None:
        """Re-enable the controls and say what went wrong."""
        self.query_one("#process", Button).disabled = False
        self.query_one("#export", Button).disabled = False
        super().failed(message)

    @on(Button.Pressed, "#export")
    @on(Input.Submitted, "#export-dir")
    def action_export(self) -> None:
        """Export the mesh (PLY, OBJ, STL), the JSON report, the clinical report (PDF) and
        its table (CSV) with the comparison chosen, and the DICOM file into the folder typed."""
        field = self.query_one("#export-dir", Input)
        folder = field.value.strip()
        if not folder:
            field.focus()
            self.say("Export to is empty: type a new folder to export into, then Enter", error=True)
            return
        self.query_one("#export", Button).disabled = True
        self.say(f"exporting to {folder} ...")
        path = Path(folder).expanduser()
        request, choice = self.measure_request, self.chosen_comparison()
        self.in_thread("export", lambda: export_all(self.job, path, request, choice), self.exported)

    def exported(self, paths: list[Path]) -> None:
        """Say what was written."""
        self.query_one("#export", Button).disabled = False
        self.say(f"exported to {paths[0].parent}: {', '.join(p.name for p in paths)}")

    def _draw_profile(self, results: Results | None) -> None:
        plot = self.query_one("#profile", PlotextPlot)
        plt = plot.plt
        plt.clear_data()
        plt.title("radius profile")
        plt.xlabel("z mm")
        if results is not None and results.rows:
            z, radius = radius_profile(results.rows)
            plt.plot(z, radius, marker="braille")
        plot.refresh()

    def refresh_from_job(self) -> None:
        """Show the job's results."""
        results = self.job.processing.results
        table = self.query_one("#sections", DataTable)
        table.clear()
        for r in results.rows if results else []:
            measures = (
                ("-", "-", "-", "-")
                if r.failed
                else (f"{r.perimeter_mm:.2f}", f"{r.area_mm2:.1f}", f"{r.roundness:.4f}",
                      str(r.harmonics))
            )  # fmt: skip
            table.add_row(str(r.index), f"{r.z_mm:.2f}", str(r.points), *coverage_cells(r),
                          *measures)  # fmt: skip
        self._draw_profile(results)
        summary: str | Text = summary_text(results)
        strip = colour_strip(results)
        if strip is not None:
            summary = Text(str(summary)) + strip
        self.query_one("#summary", Static).update(summary)
        self.in_thread("compare", lambda: compare_choices(self.job), self._offer)

    @on(Select.Changed, "#compare")
    def _compared(self) -> None:
        """Give the keys back to the table: the footer shows the screen's keys again."""
        self.query_one("#sections", DataTable).focus()

    def _offer(self, choices: list[CompareChoice]) -> None:
        """Offer the scans the open one may be compared with (keeping the choice made)."""
        kept = self.chosen_comparison()
        self.choices = choices
        select = self.query_one("#compare", Select)
        select.set_options([(c.label, k) for k, c in enumerate(choices)])
        for k, choice in enumerate(choices):
            if kept is not None and (choice.scan_id, choice.kind) == (kept.scan_id, kept.kind):
                select.value = k
        select.prompt = "no comparison" if choices else "no other scan of this subject"
