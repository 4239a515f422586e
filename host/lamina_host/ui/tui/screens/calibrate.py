"""Calibrate, guided: what to place, what the camera sees, and whether each step passed.

First the chessboard, flat on the laser plane: the picture is the camera's frame with the
corners found drawn in red, and the residual is judged against a stated limit before it is
accepted. Then the calibration cylinder on the turntable: the axis and the correction
factor, judged against 5 % (thesis sections 4.2 and 6.2 give the method).
"""

from __future__ import annotations

from typing import ClassVar

import numpy as np
from textual import on
from textual.app import ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, Vertical
from textual.message import Message
from textual.widgets import Button, Label, ProgressBar, Static

from lamina_host.reconstruct.axis import CF_WARNING, AxisCalibration, gear_advice
from lamina_host.reconstruct.calibration import GridCalibration
from lamina_host.ui.tui.adapter import Progress
from lamina_host.ui.tui.widgets import FrameView, LaminaScreen
from lamina_shared.errors import LaminaError
from lamina_shared.types import BoardSpec, Segment

GRID_RMS_LIMIT_MM = 0.05
"""The chessboard's residual RMS passes at or below this (or 1 % of a square, if more)."""
GRID_RMS_LIMIT_SQUARE = 0.01

BOARD_STEP = "Place the chessboard flat on the laser plane, every square in view; press g."
CYLINDER_STEP = (
    "Take the board away, stand the {d}calibration cylinder upright on the turntable; press y."
)


def board_outline(grid: GridCalibration, board: BoardSpec) -> np.ndarray:
    """Return the detected corners round the board's edge (every corner would hide it)."""
    nx, ny = board.inner_corners
    pts = np.asarray(grid.image_pts)
    if len(pts) != nx * ny:
        return pts
    grid_uv = pts.reshape(ny, nx, 2)
    edge = np.zeros((ny, nx), dtype=bool)
    edge[[0, -1], :] = True
    edge[:, [0, -1]] = True
    return grid_uv[edge]


def grid_limit_mm(grid: GridCalibration, square_mm: float | None) -> float:
    """Return the residual RMS the chessboard must not exceed (mm)."""
    return max(GRID_RMS_LIMIT_MM, GRID_RMS_LIMIT_SQUARE * (square_mm or 0.0))


def grid_passes(grid: GridCalibration, square_mm: float | None) -> bool:
    """Return True when the chessboard's residual RMS is within its limit."""
    return grid.rms_mm <= grid_limit_mm(grid, square_mm)


def grid_summary(
    grid: GridCalibration | None, accepted: bool, square_mm: float | None = None
) -> str:
    """Return the chessboard result as text: pass or fail against the limit, then the state."""
    if grid is None:
        return "no chessboard captured yet"
    limit = grid_limit_mm(grid, square_mm)
    verdict = "PASS" if grid_passes(grid, square_mm) else "FAIL"
    state = "accepted" if accepted else "a accepts, x rejects (then g again)"
    lines = [
        f"{verdict}: residual {grid.rms_mm:.3f} mm RMS",
        f"limit {limit:.2f} mm; {grid.n_corners} corners",
        state,
    ]
    return "\n".join(lines + [f"warning: {w}" for w in grid.warnings])


def axis_summary(axis: AxisCalibration | None) -> str:
    """Return the cylinder result as text, with the 5% correction-factor warning."""
    if axis is None:
        return "cylinder not scanned yet (accept the chessboard first)"
    good = abs(axis.correction_factor - 1.0) <= CF_WARNING
    lines = [
        f"PASS: correction within {CF_WARNING:.0%} of 1"
        if good
        else f"FAIL: correction beyond {CF_WARNING:.0%} of 1",
        f"correction     {axis.correction_factor:.5f}",
        f"axis           ({axis.axis_xy_mm[0]:.3f}, {axis.axis_xy_mm[1]:.3f}) mm",
        f"diameter       {axis.estimated_diameter_mm:.3f} mm measured, "
        f"{axis.actual_diameter_mm:.3f} mm true",
    ]
    advice = gear_advice(axis)
    notes = [f"WARNING: {w}" for w in axis.warnings] + ([f"NOTE: {advice}"] if advice else [])
    return "\n".join(lines + notes)


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
        """Two panels, in the order they are done: the chessboard, then the cylinder."""
        with Horizontal():
            with Vertical(classes="panel"):
                yield Label("1. Chessboard", classes="panel-title")
                yield Static(BOARD_STEP, id="board-step", classes="step")
                yield FrameView(id="board-view")
                yield Static(id="grid-result")
                with Horizontal(classes="buttons"):
                    yield Button("Capture", id="capture", compact=True)
                    yield Button("Accept", id="accept", variant="success", compact=True)
                    yield Button("Reject", id="reject", variant="error", compact=True)
            with Vertical(classes="panel"):
                yield Label("2. Calibration cylinder", classes="panel-title")
                yield Static(CYLINDER_STEP.format(d=""), id="cylinder-step", classes="step")
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
            passed = grid_passes(grid, self._square_mm())
            self.say(
                f"chessboard {'passes' if passed else 'FAILS'}: residual {grid.rms_mm:.3f} mm "
                + ("RMS; a accepts, x rejects" if passed else "RMS: place it again, press g"),
                error=not passed,
            )

    def failed(self, message: str) -> None:
        """Show the frame the camera gave (the board not found in it) and say why."""
        self.refresh_from_job()
        super().failed(message)

    def _square_mm(self) -> float | None:
        board = self.job.acquisition.data.board
        return board.square_mm if board else None

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
        """Show the job's calibration: the board's frame and corners, and both verdicts."""
        s = self.job.acquisition
        grid_text = self.query_one("#grid-result", Static)
        grid_text.update(grid_summary(s.grid, s.grid_accepted, self._square_mm()))
        grid_text.set_class(s.grid is not None and not grid_passes(s.grid, self._square_mm()),
                            "-warning")  # fmt: skip
        view = self.query_one("#board-view", FrameView)
        view.image = s.data.grid_image
        board = s.data.board
        view.stripe_uv = None if s.grid is None or board is None else board_outline(s.grid, board)
        axis_text = self.query_one("#axis-result", Static)
        axis_text.update(axis_summary(s.axis))
        axis_text.set_class(bool(s.axis and s.axis.warnings), "-warning")
        info = self.job.device.info
        diameter = (
            f"{info.cylinder_diameter_mm:g} mm " if info and info.cylinder_diameter_mm else ""
        )
        self.query_one("#cylinder-step", Static).update(CYLINDER_STEP.format(d=diameter))
