"""Calibrate: the chessboard (corners, residuals, accept or reject) and the cylinder axis."""

from __future__ import annotations

from typing import ClassVar

from textual import on
from textual.app import ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, Vertical
from textual.message import Message
from textual.widgets import Button, Label, ProgressBar, Static

from lamina_host.reconstruct.axis import CF_WARNING, AxisCalibration
from lamina_host.reconstruct.calibration import GridCalibration
from lamina_host.ui.tui.adapter import Progress
from lamina_host.ui.tui.widgets import LaminaScreen
from lamina_shared.errors import LaminaError
from lamina_shared.types import Segment


def grid_summary(grid: GridCalibration | None, accepted: bool) -> str:
    """Return the chessboard result as text."""
    if grid is None:
        return "no chessboard captured: press g"
    state = "accepted" if accepted else "waiting: a accepts, x rejects"
    lines = [
        f"corners        {grid.n_corners}",
        f"residual RMS   {grid.rms_mm:.4f} mm",
        f"residual max   {grid.max_mm:.4f} mm",
        f"state          {state}",
    ]
    return "\n".join(lines + [f"warning: {w}" for w in grid.warnings])


def axis_summary(axis: AxisCalibration | None) -> str:
    """Return the cylinder result as text, with the 5% correction-factor warning."""
    if axis is None:
        return "cylinder not scanned: accept the chessboard, then press y"
    lines = [
        f"axis           ({axis.axis_xy_mm[0]:.3f}, {axis.axis_xy_mm[1]:.3f}) mm",
        f"correction     {axis.correction_factor:.5f}",
        f"diameter       {axis.estimated_diameter_mm:.3f} mm measured, "
        f"{axis.actual_diameter_mm:.3f} mm true",
    ]
    if abs(axis.correction_factor - 1.0) <= CF_WARNING:
        lines.append(f"correction within {CF_WARNING:.0%} of 1: good")
    return "\n".join(lines + [f"WARNING: {w}" for w in axis.warnings])


class CylinderProgress(Message):
    """A view of the calibration cylinder arrived."""

    def __init__(self, progress: Progress) -> None:
        super().__init__()
        self.progress = progress


class CylinderView(Message):
    """A view of the calibration cylinder arrived (the live screen draws its stripe)."""

    def __init__(self, segment: Segment) -> None:
        super().__init__()
        self.segment = segment


class CalibrateScreen(LaminaScreen):
    """Grid calibration, then the turntable axis and correction factor."""

    MODE = "calibrate"
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("g", "capture", "Capture board"),
        Binding("a", "accept(True)", "Accept"),
        Binding("x", "accept(False)", "Reject"),
        Binding("y", "cylinder", "Scan cylinder"),
    ]

    def body(self) -> ComposeResult:
        """Two panels: the chessboard and the cylinder."""
        with Horizontal():
            with Vertical(classes="panel"):
                yield Label("Chessboard (thesis 4.2)", classes="panel-title")
                yield Static(id="grid-result")
                with Horizontal(classes="buttons"):
                    yield Button("Capture", id="capture", compact=True)
                    yield Button("Accept", id="accept", variant="success", compact=True)
                    yield Button("Reject", id="reject", variant="error", compact=True)
            with Vertical(classes="panel"):
                yield Label("Cylinder axis (thesis 6.2)", classes="panel-title")
                yield Static(id="axis-result")
                yield ProgressBar(total=1, show_eta=False, id="cylinder-progress")
                yield Button("Scan cylinder", id="cylinder", compact=True)

    @on(Button.Pressed, "#capture")
    def action_capture(self) -> None:
        """Capture the chessboard and fit the homography."""
        self.say("capturing the chessboard ...")
        self.in_thread("grid", self.job.acquisition.calibrate_grid, lambda _: self.calibrated())

    def calibrated(self) -> None:
        """Show the chessboard result."""
        self.refresh_from_job()
        grid = self.job.acquisition.grid
        if grid is not None:
            self.say(f"chessboard: {grid.n_corners} corners, RMS {grid.rms_mm:.4f} mm; a/x")

    @on(Button.Pressed, "#accept")
    def _accept_pressed(self) -> None:
        self.action_accept(True)

    @on(Button.Pressed, "#reject")
    def _reject_pressed(self) -> None:
        self.action_accept(False)

    def action_accept(self, accept: bool) -> None:
        """Accept or reject the chessboard calibration."""
        try:
            self.job.acquisition.accept_grid(accept)
        except LaminaError as exc:
            self.say(str(exc), error=True)
            return
        self.refresh_from_job()
        self.say("chessboard accepted" if accept else "chessboard rejected: capture it again")

    @on(Button.Pressed, "#cylinder")
    def action_cylinder(self) -> None:
        """Scan the calibration cylinder and find the axis."""
        self.query_one("#cylinder-progress", ProgressBar).update(total=1, progress=0)
        self.say("scanning the calibration cylinder ...")
        self.in_thread(
            "cylinder",
            lambda: self.job.acquisition.calibrate_axis(
                lambda p: self.post_message(CylinderProgress(p)),
                lambda s: self.post_message(CylinderView(s)),
            ),
            self.axis_found,
        )

    def on_cylinder_view(self, message: CylinderView) -> None:
        """Keep the view as the latest one scanned."""
        self.lamina.latest_segment = message.segment

    def on_cylinder_progress(self, message: CylinderProgress) -> None:
        """Advance the progress bar."""
        p = message.progress
        self.query_one("#cylinder-progress", ProgressBar).update(total=p.total, progress=p.done)

    def axis_found(self, axis: AxisCalibration) -> None:
        """Show the axis and the correction factor (and flag a factor far from 1)."""
        self.refresh_from_job()
        far = abs(axis.correction_factor - 1.0) > CF_WARNING
        self.say(
            f"correction factor {axis.correction_factor:.5f}"
            + (f": more than {CF_WARNING:.0%} from 1, check the calibration" if far else ""),
            error=far,
        )

    def refresh_from_job(self) -> None:
        """Show the job's calibration."""
        s = self.job.acquisition
        self.query_one("#grid-result", Static).update(grid_summary(s.grid, s.grid_accepted))
        axis_text = self.query_one("#axis-result", Static)
        axis_text.update(axis_summary(s.axis))
        axis_text.set_class(bool(s.axis and s.axis.warnings), "-warning")
