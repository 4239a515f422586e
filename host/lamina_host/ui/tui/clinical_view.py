"""The clinical measurements of the processed scan on the Results screen (key ``m``).

A modal view over the Results screen: the table of levels from the landmark, the volumes
and the report's three plots (textual-plotext): the circumference profile along the axis,
the outlines at the levels, and the volume over the subject's visits (per side). The
landmark is typed (distal, bottom, top or a height in mm) or taken from the section picked
in the Results table (key ``k``).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import ClassVar

from textual import on
from textual.app import ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, Vertical
from textual.screen import ModalScreen
from textual.widgets import DataTable, Footer, Input, Label, Static
from textual_plotext import PlotextPlot

from lamina_host.clinical.measures import (
    COMPARISONS,
    DEFAULT_SPACING_MM,
    ClinicalError,
    Comparison,
    LimbMeasurement,
    LimbSection,
    Visit,
    compare,
    measure_limb,
    parse_landmark,
)
from lamina_host.clinical.report import MeasureRequest
from lamina_host.ui.tui.adapter import CompareChoice

OUTLINE_POINTS = 90
"""Samples per outline in the terminal plot (a few per character cell)."""

LEVEL_COLUMNS = ("mark mm", "z mm", "circ mm", "diff mm", "seg mL", "source")
"""The levels table: distance from the landmark, height, circumference, its difference
from the compared scan (blank without one), the segment's volume up to the next level."""


def comparison_line(comparison: Comparison, choice: CompareChoice) -> str:
    """Return the excess over the other limb, or the change since a visit, in one line."""
    what = "excess over" if comparison.kind == COMPARISONS[0] else "change since"
    first, last = comparison.span_mm
    return (
        f"{what} {choice.label}: {comparison.difference_ml:+.1f} mL "
        f"({comparison.difference_percent:+.1f} %) from {first:g} to {last:g} mm"
    )


def summary_lines(m: LimbMeasurement) -> str:
    """Return the volumes and notes of a measurement as lines."""
    lines = [
        f"landmark {m.landmark.describe()} at z = {m.landmark_z_mm:.1f} mm; "
        f"range {m.coverage_mm[0]:.1f}..{m.coverage_mm[1]:.1f} mm",
        f"volume {m.volume_mm3 / 1000:.1f} mL; between the levels "
        f"{m.levels_volume_mm3 / 1000:.1f} mL (frustum {m.frustum_volume_mm3 / 1000:.1f} mL)",
    ]
    return "\n".join(lines + [f"note: {n}" for n in m.notes])


class ClinicalView(ModalScreen[None]):
    """Circumferences every ``spacing`` mm from a landmark, the profile and the volumes."""

    AUTO_FOCUS = "#levels"
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("escape", "dismiss", "Close"),
        Binding("k", "use_picked", "Landmark at picked row"),
        Binding("f1", "app.help", "Help"),
    ]
    DEFAULT_CSS = """
    ClinicalView { align: center top; }
    #clinical-box { width: 100%; height: 1fr; border: round $accent; background: $surface; }
    #clinical-box > .row { margin: 0; }
    #clinical-main { height: 1fr; }
    #levels { width: 3fr; max-width: 62; height: 1fr; }
    #clinical-profile { width: 2fr; min-width: 24; height: 1fr; margin-left: 1; }
    #clinical-plots { height: 1fr; }
    #clinical-outlines, #clinical-visits { width: 1fr; height: 1fr; }
    #clinical-summary { height: auto; max-height: 5; }
    #spacing { width: 8; }
    """

    def __init__(
        self,
        sections: Sequence[LimbSection],
        picked_z_mm: float | None = None,
        visits: Sequence[Visit] = (),
        compared: CompareChoice | None = None,
        reference: Callable[[MeasureRequest], LimbMeasurement] | None = None,
        on_measured: Callable[[MeasureRequest], object] | None = None,
    ) -> None:
        """Measure ``sections``.

        Args:
            sections: the processed scan's EFD sections.
            picked_z_mm: the height of the section picked on Results (key ``k``).
            visits: the subject's visits in the library.
            compared: the scan chosen to compare with (None: no comparison).
            reference: measures that scan as asked (needed with ``compared``).
            on_measured: hears each measurement's spacing and landmark (the report's).
        """
        super().__init__()
        self.sections = list(sections)
        self.picked_z_mm = picked_z_mm
        self.visits = list(visits)
        self.compared = compared if reference is not None else None
        self.reference = reference
        self.on_measured = on_measured
        self.measurement: LimbMeasurement | None = None
        self.comparison: Comparison | None = None
        self.reference_measurement: LimbMeasurement | None = None

    def compose(self) -> ComposeResult:
        """Fields, then the table beside the profile, then the plots and the volumes."""
        with Vertical(id="clinical-box"):
            with Horizontal(classes="row"):
                yield Label("Spacing mm", classes="field-label")
                yield Input(f"{DEFAULT_SPACING_MM:g}", id="spacing", compact=True)
                yield Label("Landmark", classes="field-label")
                yield Input("distal", id="landmark", compact=True)
            with Horizontal(id="clinical-main"):
                yield DataTable(id="levels", cursor_type="row", zebra_stripes=True)
                yield PlotextPlot(id="clinical-profile")
            with Horizontal(id="clinical-plots"):
                yield PlotextPlot(id="clinical-outlines")
                yield PlotextPlot(id="clinical-visits")
            yield Static("", id="clinical-summary")
        yield Footer(compact=True, show_command_palette=False)

    def on_mount(self) -> None:
        """Measure with the defaults."""
        self.query_one("#levels", DataTable).add_columns(*LEVEL_COLUMNS)
        self._draw_visits()
        self.remeasure()

    def action_use_picked(self) -> None:
        """Put the landmark at the section picked on the Results screen."""
        if self.picked_z_mm is None:
            self.query_one("#clinical-summary", Static).update("no section picked on Results")
            return
        self.query_one("#landmark", Input).value = f"{self.picked_z_mm:g}"
        self.remeasure()

    @on(Input.Submitted)
    def remeasure(self) -> None:
        """Measure again with the spacing and landmark typed; the table takes the keys again."""
        self.set_focus(self.query_one("#levels", DataTable))
        summary = self.query_one("#clinical-summary", Static)
        try:
            spacing = float(self.query_one("#spacing", Input).value)
            if not math.isfinite(spacing) or spacing <= 0:
                raise ValueError
        except ValueError:
            summary.update("spacing must be a positive number of mm, e.g. 40")
            return
        try:
            landmark = parse_landmark(self.query_one("#landmark", Input).value)
            self.measurement = measure_limb(self.sections, spacing, landmark)
        except ClinicalError as exc:
            summary.update(str(exc))
            return
        request = MeasureRequest(spacing, landmark)
        if self.on_measured is not None:
            self.on_measured(request)
        self.comparison, problem = self._compare(self.measurement, request)
        self._show(self.measurement)
        if problem:
            summary.update(f"{summary_lines(self.measurement)}\nno comparison: {problem}")

    def _compare(
        self, m: LimbMeasurement, request: MeasureRequest
    ) -> tuple[Comparison | None, str]:
        """Compare with the chosen scan at the same spacing and landmark (or say why not)."""
        if self.compared is None or self.reference is None:
            return None, ""
        try:
            self.reference_measurement = self.reference(request)
            kind, limits = self.compared.kind, request.thresholds
            return compare(m, self.reference_measurement, kind, limits), ""
        except ClinicalError as exc:
            return None, str(exc)

    def _show(self, m: LimbMeasurement) -> None:
        table = self.query_one("#levels", DataTable)
        table.clear()
        differences = {
            round(d.offset_mm, 6): d for d in (self.comparison.levels if self.comparison else ())
        }
        for k, level in enumerate(m.levels):
            seg = m.segments[k] if k < len(m.segments) else None
            d = differences.get(round(level.offset_mm, 6))
            table.add_row(
                f"{level.offset_mm:.0f}",
                f"{level.z_mm:.1f}",
                f"{level.circumference_mm:.1f}",
                "" if d is None else f"{d.difference_mm:+.1f}" + (" !" if d.flagged else ""),
                f"{seg.volume_mm3 / 1000:.1f}" if seg else "",
                level.source,
            )
        plot = self.query_one("#clinical-profile", PlotextPlot)
        plt = plot.plt
        plt.clear_data()
        plt.title("circumference along the axis")
        plt.xlabel("z mm")
        plt.plot(list(m.profile_z_mm), list(m.profile_circumference_mm), marker="braille")
        ref = self.reference_measurement if self.comparison is not None else None
        if ref is not None:  # drawn from this scan's landmark, as the levels are compared
            shift = m.landmark_z_mm - ref.landmark_z_mm
            z = [float(v) + shift for v in ref.profile_z_mm]
            plt.plot(z, list(ref.profile_circumference_mm), marker="braille", label="compared")
        plt.scatter(
            [lv.z_mm for lv in m.levels], [lv.circumference_mm for lv in m.levels], marker="o"
        )
        plot.refresh()
        self._draw_outlines(m)
        lines = summary_lines(m)
        if self.comparison is not None and self.compared is not None:
            lines += "\n" + comparison_line(self.comparison, self.compared)
            lines += "".join(f"\nflag: {flag}" for flag in self.comparison.flags)
        self.query_one("#clinical-summary", Static).update(lines)

    def _draw_outlines(self, m: LimbMeasurement) -> None:
        """Draw the outline at every level, as the report does."""
        plot = self.query_one("#clinical-outlines", PlotextPlot)
        plt = plot.plt
        plt.clear_data()
        plt.title("outlines at the levels")
        for level in m.levels:
            xy = m.stack.section(level.z_mm).evaluate(OUTLINE_POINTS)
            closed = [*xy, xy[0]]
            plt.plot([p[0] for p in closed], [p[1] for p in closed], marker="braille",
                     label=f"{level.offset_mm:g}")  # fmt: skip
        plot.refresh()

    def _draw_visits(self) -> None:
        """Draw the volume over the subject's visits, one line per side."""
        plot = self.query_one("#clinical-visits", PlotextPlot)
        plt = plot.plt
        plt.clear_data()
        plt.title("volume over visits (mL)")
        for side in ("left", "right", "none"):
            at = [(k, v) for k, v in enumerate(self.visits) if v.side == side]
            if at:
                plt.plot([k for k, _ in at], [v.volume_ml for _, v in at], marker="o", label=side)
        if self.visits:  # each visit by its date (the day: the axis has little room)
            plt.xticks(
                [float(k) for k in range(len(self.visits))], [v.created[5:10] for v in self.visits]
            )
        plot.refresh()
