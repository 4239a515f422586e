"""Live view: a camera frame with the stripe the device detects there; jog, laser, exposure."""

from __future__ import annotations

from typing import ClassVar

from textual import work
from textual.app import ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, Vertical
from textual.widgets import Label, Static

from lamina_host.link.client import Preview
from lamina_host.ui.tui.widgets import FrameView, LaminaScreen
from lamina_shared.types import Segment

JOG_DEG = 15.0
JOG_MM = 1.0
EXPOSURE_STEP = 1.25
"""Each exposure key press multiplies or divides the exposure by this."""


class LiveScreen(LaminaScreen):
    """A preview frame, the stripe the device extracts where the axes stand, and the axes."""

    MODE = "live"
    _shown: Segment | None = None
    _followed: Segment | None = None
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("g", "grab", "Grab"),
        Binding("l", "laser", "Laser"),
        Binding("left", "jog('turntable', -1)", "Turn -15", show=False),
        Binding("right", "jog('turntable', 1)", "Turn"),
        Binding("up", "jog('lift', 1)", "Lift"),
        Binding("down", "jog('lift', -1)", "Lift -1", show=False),
        Binding("h", "home", "Home"),
        Binding("plus,equals_sign", "exposure(1)", "Exp +"),
        Binding("minus", "exposure(-1)", "Exp -"),
    ]

    def __init__(self) -> None:
        super().__init__()
        self.laser = False
        self.exposure_us: int | None = None

    def body(self) -> ComposeResult:
        """Frame on the left, what it shows on the right."""
        with Horizontal():
            yield FrameView(id="frame")
            with Vertical(id="live-side", classes="panel"):
                yield Label("Axes and laser", classes="panel-title")
                yield Static(id="axes")
                yield Label("Stripe (red)", classes="panel-title")
                yield Static("no view scanned yet", id="stripe-info")
                yield Static("exposure: grab a frame (g), then + / -", id="exposure")

    def on_mount(self) -> None:
        """Follow the stripe while a scan runs on another screen, and the axes as they move."""
        self.watch(self.lamina, "latest_segment", self._follow, init=False)
        self.watch(self.lamina, "pose", lambda _: self._show_axes(), init=False)

    def _follow(self, latest: Segment | None) -> None:
        """Show a newly scanned view (a preview's stripe stays until one arrives)."""
        if self.is_current and latest is not None and latest is not self._followed:
            self._followed = latest
            self.show_segment(latest)

    def action_grab(self) -> None:
        """Fetch a preview frame from the device."""
        self.say(f"grabbing a frame, laser {'on' if self.laser else 'off'} ...")
        laser = self.laser
        # In a thread: the frame crosses the serial link in chunks.
        self.in_thread("grab", lambda: self.job.device.preview(laser), self.grabbed)

    def action_laser(self) -> None:
        """Switch the laser for the next preview frames and grab one."""
        self.laser = not self.laser
        self._show_axes()
        self.action_grab()

    def grabbed(self, preview: Preview) -> None:
        """Show the new frame and the stripe the device found in it."""
        image = preview.image
        self.query_one(FrameView).image = image
        if preview.stripe is not None:
            self.show_segment(preview.stripe, "live")
        self.say(f"frame {image.shape[1]} x {image.shape[0]} px")

    def action_exposure(self, direction: int) -> None:
        """Step the camera's exposure up or down, then grab a frame to show its effect."""
        self.exposure_worker(direction)

    @work(thread=True, exclusive=True, group="grab")
    def exposure_worker(self, direction: int) -> None:
        """Read the exposure if unknown, step it, then grab a frame (all in a thread)."""

        def job() -> tuple[int, Preview]:
            current = self.exposure_us or self.job.device.exposure()[0]
            wanted = round(current * EXPOSURE_STEP**direction)
            exposure_us = self.job.device.set_exposure(wanted)
            return exposure_us, self.job.device.preview(self.laser)

        def done(result: tuple[int, Preview]) -> None:
            self.exposure_us = result[0]
            self._show_exposure()
            self.grabbed(result[1])

        self.attempt(job, done)

    def _show_exposure(self) -> None:
        text = "unknown" if self.exposure_us is None else f"{self.exposure_us} us"
        self.query_one("#exposure", Static).update(f"exposure {text} (+ / -)")

    def action_jog(self, axis: str, direction: int) -> None:
        """Move the turntable by 15 deg or the lift by 1 mm, then grab a frame."""
        step = JOG_DEG if axis == "turntable" else JOG_MM
        self.move_worker({axis: self.lamina.pose.at(axis) + direction * step})

    def action_home(self) -> None:
        """Move the lift and the turntable back to 0."""
        self.move_worker({"lift": 0.0, "turntable": 0.0})

    @work(thread=True, exclusive=True, group="grab")
    def move_worker(self, targets: dict[str, float]) -> None:
        """Move in a thread, then take a frame where the axes stand."""

        def job() -> Preview:
            for axis, position in targets.items():
                self.job.device.move(axis, position)
            return self.job.device.preview(self.laser)

        self.attempt(job, self.grabbed)
        # Where the axes went, also when a move failed half way (the pose is a value).
        pose = self.job.device.pose

        def show_pose() -> None:
            self.lamina.pose = pose

        self.app.call_from_thread(show_pose)

    def show_segment(self, segment: Segment, source: str = "scanned") -> None:
        """Draw ``segment``'s stripe over the frame and say where it came from (live or scanned)."""
        self._shown = segment
        self.query_one(FrameView).stripe_uv = segment.uv
        where = (
            f"live {segment.target}"
            if source == "live"
            else f"{segment.target} section {segment.section}, view {segment.view}"
        )
        self.query_one("#stripe-info", Static).update(
            f"{where}: "
            f"{len(segment)} points at {segment.angle_deg:.0f} deg, z {segment.z_mm:.1f} mm"
        )

    def _show_axes(self) -> None:
        pose = self.lamina.pose
        self.query_one("#axes", Static).update(
            f"turntable {pose.turntable_deg:.1f} deg\nlift {pose.lift_mm:.1f} mm\n"
            f"laser {'on' if self.laser else 'off'}"
        )

    def refresh_from_job(self) -> None:
        """Show the job's frame, the axes and the latest scanned view."""
        self._show_axes()
        view = self.query_one(FrameView)
        if view.image is None and self.job.acquisition.data.grid_image is not None:
            view.image = self.job.acquisition.data.grid_image
        latest = self.lamina.latest_segment
        if latest is not None and latest is not self._followed:
            self._followed = latest
            self.show_segment(latest)
