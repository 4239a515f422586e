"""Subject and scan: plan, start, progress with time left, live section points, abort."""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import ClassVar

from textual import on, work
from textual.app import ComposeResult
from textual.binding import Binding, BindingType
from textual.containers import Horizontal, Vertical
from textual.message import Message
from textual.widgets import Button, Input, Label, ProgressBar, Select, Static
from textual.worker import get_current_worker
from textual_plotext import PlotextPlot

from lamina_host.store.library import SIDES
from lamina_host.ui.tui.adapter import (
    USER_ERRORS,
    Progress,
    check_subject,
    choose_rig,
    is_simulated,
    parse_plan,
    scan_object,
    user_message,
)
from lamina_host.ui.tui.widgets import LaminaScreen, TickBox, name_choice
from lamina_host.workflow.checks import (
    PLAN_PRESETS,
    ObjectTooLarge,
    PlanPreset,
    PresetPlan,
    check_preset_fits,
    preset_plan,
)
from lamina_shared.durations import duration_text
from lamina_shared.presets import RIG_PRESETS
from lamina_shared.replies import ScanEstimate
from lamina_shared.types import ScanPlan, Segment


def progress_text(p: Progress, left_s: float | None = None) -> str:
    """Return e.g. 'object view 5/16, section 0, 3 s left' for the progress line.

    Args:
        p: the latest progress.
        left_s: the time left as counted down since (None: the progress's own estimate).
    """
    left = p.left_s if left_s is None else left_s
    left_text = "estimating time left" if left is None else f"{duration_text(left)} left"
    return f"{p.target} view {p.done}/{p.total}, section {p.section}, {left_text}"


SIDE_CHOICES = (("left", "left"), ("right", "right"), ("none: not a limb", SIDES[0]))
"""The Side field's choices (label, value); a scan of no limb is side ``none``."""
CUSTOM = "custom"
"""The Plan field's value when the numbers are typed rather than a preset's."""
PLAN_CHOICES = (*((name, name) for name in PLAN_PRESETS), ("my numbers", CUSTOM))
"""The Plan field's choices: the presets named for what they scan, then typed numbers."""
DEVICE_RIG = "device"
"""The Rig field's value for a scanner (not the simulator): its own rig, no choice."""
TICK_S = 1.0
"""How often the time left is counted down between views."""


PLAN_ERRORS: tuple[type[Exception], ...] = (*USER_ERRORS, ValueError)
"""What reading the typed plan may raise: each is told on the status line, never fatal."""

PLOT_INTERVAL_S = 0.25
"""How often the live section plot is redrawn while views arrive."""
PLOT_MAX_POINTS = 800
"""Points plotted at most; the section's points are thinned evenly beyond that."""


class ScanEvent(Message):
    """A segment or a progress report arrived from the device."""

    def __init__(self, segment: Segment | None = None, progress: Progress | None = None) -> None:
        super().__init__()
        self.segment = segment
        self.progress = progress


class ScanScreen(LaminaScreen):
    """Enter the subject and plan, run the scan and watch it."""

    MODE = "scan"
    AUTO_FOCUS = "#subject"
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("s", "start", "Start"),
        Binding("p", "pause", "Pause/resume"),
        Binding("b", "abort", "Abort"),
        Binding("r", "reconnect", "Reconnect"),
        Binding("escape", "leave_field", "Leave field"),
    ]

    def __init__(self) -> None:
        super().__init__()
        self._aborting = False
        self.paused = False
        self._section = -1
        self._segments: list[Segment] = []
        """The current section's views so far (the plot assembles them as the result will)."""
        self._plot_stale = False
        self.scanning = False
        self._estimate_s: float | None = None
        """The device's estimate of the typed plan (None: none yet)."""
        self._progress: Progress | None = None
        self._left: tuple[float, float] | None = None
        """(seconds left, when that was known): counted down between views."""
        self._rig_choices = [(name, name) for name in RIG_PRESETS]
        """The Rig field's choices now (the simulator's rigs, or the scanner's own)."""

    def body(self) -> ComposeResult:
        """Form, progress and the live plot of the current section."""
        with Horizontal(classes="row"):
            yield Label("Subject", classes="field-label")
            yield Input(placeholder="e.g. P-0042", id="subject", compact=True)
            yield Label("Side", classes="field-label")
            yield Select(SIDE_CHOICES, value=SIDES[0], allow_blank=False, id="side", compact=True)
            # Colour: each point's colour from the laser-off frames (a colour camera).
            yield TickBox("Colour", id="colour", compact=True)
        with Horizontal(classes="row"):
            yield Label("Plan", classes="field-label")
            yield Select(PLAN_CHOICES, value=CUSTOM, allow_blank=False, id="preset", compact=True)
            yield Label("Sections", classes="field-label")
            yield Input("2", id="sections", type="integer", compact=True, classes="short")
            yield Label("Pitch mm", classes="field-label")
            yield Input("2", id="pitch", type="number", compact=True, classes="short")
            yield Label("Views", classes="field-label")
            yield Input("8", id="views", type="integer", compact=True, classes="short")
        with Horizontal(classes="row"):
            yield Label("Rig", classes="field-label")
            yield name_choice(RIG_PRESETS, "rig")
            yield Button("Start", id="start", variant="primary", compact=True)
            yield Button("Abort", id="abort", variant="error", compact=True, disabled=True)
        with Horizontal(classes="row"):
            yield ProgressBar(total=1, show_eta=False, id="scan-progress")
            yield Static("not started", id="progress-text")
        with Horizontal():
            yield PlotextPlot(id="section-plot")
            with Vertical(id="scan-side", classes="panel"):
                yield Label("Link", classes="panel-title")
                yield Static("not connected", id="link-state")

    def on_mount(self) -> None:
        """Label the empty plot and redraw it at a steady pace while views arrive."""
        self._draw_points()
        self.query_one("#rig", Select).value = self.job.device.target.rig
        # Plotting every view as it lands kept the event loop busy for tens of ms per
        # view; a few redraws a second look the same and keep keys answered promptly.
        self.set_interval(PLOT_INTERVAL_S, self._redraw_if_stale)
        self.set_interval(TICK_S, self._count_down)

    def _redraw_if_stale(self) -> None:
        if self._plot_stale:
            self._draw_points()

    @property
    def plot_pending(self) -> bool:
        """Return True while views have arrived that the plot does not show yet."""
        return self._plot_stale

    def action_leave_field(self) -> None:
        """Leave the text field so the screen's keys work again."""
        self.set_focus(None)

    @on(Input.Submitted)
    def _next_field(self) -> None:
        self.focus_next()

    @on(Input.Changed, "#sections, #pitch, #views")
    def _plan_changed(self) -> None:
        preset = self._preset()
        if preset is not None and self._typed() != self._preset_numbers(preset):
            self.query_one("#preset", Select).value = CUSTOM  # the numbers are the user's now
        self.show_estimate(replace_progress=True)

    def _typed(self) -> tuple[str, str, str]:
        """Return the Sections, Pitch mm and Views fields as typed."""
        sections, pitch, views = (
            self.query_one(f"#{k}", Input).value.strip() for k in ("sections", "pitch", "views")
        )
        return sections, pitch, views

    def _preset(self) -> PlanPreset | None:
        """Return the chosen preset (None: the typed numbers)."""
        return PLAN_PRESETS.get(str(self.query_one("#preset", Select).value))

    def _preset_plan(self, preset: PlanPreset) -> PresetPlan:
        """Return the preset's plan on the connected device (its lift's travel)."""
        info = self.job.device.info
        return preset_plan(preset, info.axes if info else None)

    def _preset_numbers(self, preset: PlanPreset) -> tuple[str, str, str]:
        plan = self._preset_plan(preset)
        return str(plan.sections), f"{plan.pitch_mm:g}", str(plan.views)

    @on(Select.Changed, "#preset")
    def _preset_chosen(self) -> None:
        """Fill the numbers with the preset's plan (cut to the lift's travel, saying so)."""
        preset = self._preset()
        if preset is None or self._typed() == self._preset_numbers(preset):
            return
        numbers = self._preset_numbers(preset)
        for key, value in zip(("sections", "pitch", "views"), numbers, strict=True):
            self.query_one(f"#{key}", Input).value = value
        note = self._preset_plan(preset).note
        try:  # said now, not only at Start: the rig may be the wrong one for it
            check_preset_fits(preset, self.job.acquisition.field_radius_mm())
        except ObjectTooLarge as exc:
            self.say(str(exc), error=True)
            return
        self.say(f"{preset.name} plan: {note}" if note else f"{preset.name} plan chosen")

    @on(Select.Changed, "#rig")
    def _rig_chosen(self, event: Select.Changed) -> None:
        """Use the simulated rig chosen (the simulator starts again; calibrate again)."""
        rig = str(event.value)
        if rig == DEVICE_RIG or rig == self.job.device.target.rig:
            return
        if self.scanning:
            self.say("a scan is running: abort it (b) before changing the rig", error=True)
            self.query_one("#rig", Select).value = self.job.device.target.rig
            return
        self.say(f"changing to the simulated {rig} rig ...")
        self.in_thread("connect", lambda: choose_rig(self.job, rig), lambda _: self._rig_set(rig))

    def _rig_set(self, rig: str) -> None:
        self.refresh_from_job()
        self.say(f"simulated {rig} rig: calibrate on it before scanning (F4)")

    def show_estimate(self, replace_progress: bool = False) -> None:
        """Ask the device how long the typed plan would keep the subject still.

        Args:
            replace_progress: show it in place of the last scan's progress too (the plan
                was changed); otherwise only where nothing has been scanned yet.
        """
        if self.scanning or not self.job.device.connected:
            return
        shown = str(self.query_one("#progress-text", Static).render())
        if not (replace_progress or shown.startswith("not started")):
            return
        try:
            plan = self._plan_numbers()
        except PLAN_ERRORS:
            self.query_one("#progress-text", Static).update("not started")
            return
        self.estimate_worker(plan)

    @work(thread=True, group="estimate", exclusive=True)
    def estimate_worker(self, plan: ScanPlan) -> None:
        """Ask for the estimate in a thread; a newer plan's request supersedes this one."""
        try:
            estimate = self.job.device.estimate("object", plan)
        except USER_ERRORS:
            return  # busy (calibrating) or a plan beyond the device: Start will say why
        if estimate is not None and not get_current_worker().is_cancelled:
            self.app.call_from_thread(self._estimated, estimate)

    def _estimated(self, estimate: ScanEstimate) -> None:
        self._estimate_s = estimate.modelled_s
        if not self.scanning:
            self.query_one("#progress-text", Static).update(
                f"not started: {estimate.views} views take about "
                f"{duration_text(estimate.modelled_s)}; the subject holds still that long"
            )

    def _plan_numbers(self) -> ScanPlan:
        return parse_plan(*self._typed())

    def _plan(self) -> tuple[str, ScanPlan]:
        subject = check_subject(self.query_one("#subject", Input).value)
        return subject, self._plan_numbers()

    @on(Button.Pressed, "#start")
    def action_start(self) -> None:
        """Check the form and start the scan."""
        if self.scanning:
            self.say("a scan is running: abort it (b) before starting another", error=True)
            return
        try:
            subject, plan = self._plan()
        except PLAN_ERRORS as exc:  # a typed plan is the user's, whatever fails
            self.say(user_message(exc), error=True)
            return
        self._aborting, self.paused = False, False
        self._section, self._segments = -1, []
        self._set_scanning(True)
        self.query_one("#scan-progress", ProgressBar).update(total=len(plan.views), progress=0)
        self._progress = None
        now = time.monotonic()
        self._left = None if self._estimate_s is None else (self._estimate_s, now)
        self.query_one("#progress-text", Static).update("starting ...")
        side = str(self.query_one("#side", Select).value)
        self.say(
            f"scanning {subject} ({side}): {len(plan.sections)} sections, {len(plan.views)} views"
        )
        colour = self.query_one("#colour", TickBox).value
        preset = self._preset()
        # Segments and progress come back from the scan's thread as messages.
        self.in_thread(
            "scan",
            lambda: scan_object(
                self.job,
                subject,
                plan,
                on_segment=lambda s: self.post_message(ScanEvent(segment=s)),
                on_progress=lambda p: self.post_message(ScanEvent(progress=p)),
                on_notice=self._notice,
                colour=colour,
                side=side,
                preset=preset,
            ),
            self.finished,
        )

    def _notice(self, text: str) -> None:
        """Show a refused pause, resume or abort (called from the scan's thread)."""
        self.app.call_from_thread(self.say, text, error=True)

    def on_scan_event(self, event: ScanEvent) -> None:
        """Show a new view: progress, time left, the section's points so far."""
        if event.progress is not None:
            p = event.progress
            self.query_one("#scan-progress", ProgressBar).update(total=p.total, progress=p.done)
            self._progress = p
            if p.left_s is not None:
                self._left = (p.left_s, time.monotonic())
            self._count_down()
        if event.segment is not None:
            self._add_segment(event.segment)

    def _count_down(self) -> None:
        """Show the progress with the time left counted down since it was last known."""
        if not self.scanning:
            return
        left = None
        if self._left is not None:
            seconds, since = self._left
            held = self.paused  # a paused scan's time left does not run down
            left = seconds if held else max(seconds - (time.monotonic() - since), 0.0)
            if held:
                self._left = (seconds, time.monotonic())
        p = self._progress
        text = "starting ..." if left is None else f"starting: about {duration_text(left)} left"
        self.query_one("#progress-text", Static).update(
            text if p is None else progress_text(p, left)
        )

    def _add_segment(self, segment: Segment) -> None:
        self.lamina.latest_segment = segment  # the live screen draws its stripe
        if segment.section != self._section:
            self._section, self._segments = segment.section, []
        self._segments.append(segment)
        self._plot_stale = True

    def _draw_points(self) -> None:
        self._plot_stale = False
        plot = self.query_one("#section-plot", PlotextPlot)
        plt = plot.plt
        plt.clear_data()
        plt.title("current section (mm)" if self._section < 0 else f"section {self._section} (mm)")
        pts = self.job.acquisition.section_points(self._segments)
        if len(pts):
            # A terminal plot cannot show more points than it has braille dots.
            pts = pts[:: max(1, len(pts) // PLOT_MAX_POINTS)]
            plt.scatter(pts[:, 0].tolist(), pts[:, 1].tolist(), marker="braille")
        plot.refresh()

    def finished(self, segments: list[Segment]) -> None:
        """The scan is complete: say so and offer processing."""
        self._redraw_if_stale()
        self._set_scanning(False)
        self.say(f"scan complete: {len(segments)} views received; process it on Results (F6)")

    def failed(self, message: str) -> None:
        """The scan stopped: keep what arrived and say what to do."""
        self._set_scanning(False)
        if self._progress is None:  # refused before any view: nothing is under way
            self.query_one("#progress-text", Static).update("not started: see the line below")
        if self._aborting:
            self.say(f"{message}; p resumes")
        else:
            super().failed(
                message + ("; r reconnects, p resumes" if self.job.acquisition.resumable else "")
            )

    def _set_scanning(self, scanning: bool) -> None:
        self.scanning = scanning
        self.paused = False
        self.query_one("#start", Button).disabled = scanning
        self.query_one("#abort", Button).disabled = not scanning
        self.refresh_from_job()

    @on(Button.Pressed, "#abort")
    def action_abort(self) -> None:
        """Abort the scan on the device after the view in flight; the views received are kept."""
        if not self.scanning:
            self.say("no scan is running", error=True)
            return
        self._aborting = True
        self.say("aborting after the current view ...")
        self.control_worker(self.job.device.abort_scan)

    def action_pause(self) -> None:
        """Pause or resume the running scan on the device, or resume an aborted (dropped) one."""
        if self.scanning:
            self.paused = not self.paused
            if self.paused:
                self.say("paused after the current view, laser off; p resumes, b aborts")
                self.control_worker(self.job.device.pause_scan)
            else:
                self.say("resuming the scan ...")
                self.control_worker(self.job.device.resume_scan)
            return
        if not self.job.acquisition.resumable:
            self.say("no scan to resume: start one (s)", error=True)
            return
        self._aborting = False
        self._set_scanning(True)
        self.say(f"resuming: {len(self.job.acquisition.held)} views held, fetching the rest ...")
        self.in_thread(
            "scan",
            lambda: self.job.acquisition.fetch_object(
                on_segment=lambda s: self.post_message(ScanEvent(segment=s)),
                on_progress=lambda p: self.post_message(ScanEvent(progress=p)),
                on_notice=self._notice,
            ),
            self.finished,
        )

    @work(thread=True, group="control")
    def control_worker(self, send: Callable[[], None]) -> None:
        """Send pause, resume or abort in a thread; the scan's thread reads the reply."""
        try:
            send()
        except USER_ERRORS as exc:
            # The scan itself goes on (or has just ended): only say why the key did nothing.
            self.app.call_from_thread(self.say, user_message(exc), error=True)

    def action_reconnect(self) -> None:
        """Reconnect a dropped link; calibration and received views are kept."""
        if self.scanning:
            self.say("a scan is running: abort it (b) first", error=True)
            return
        self.say(f"reconnecting to {self.job.device.name} ...")
        self.in_thread("connect", self.job.connect, lambda _: self.reconnected())

    def reconnected(self) -> None:
        """Show the recovered link."""
        self.refresh_from_job()
        self.say("link recovered: calibration kept; start the scan again (s)")

    def refresh_from_job(self) -> None:
        """Show the link state."""
        device, acquisition = self.job.device, self.job.acquisition
        if device.connected:
            text = f"connected: {device.name}"
        elif acquisition.data.device:
            text = f"LINK LOST to {device.name}: press r to reconnect"
        else:
            text = "not connected (F2)"
        calibrated = "calibrated" if acquisition.axis is not None else "not calibrated (F4)"
        self.query_one("#link-state", Static).update(f"{text}\n{calibrated}")
        self._show_rig()
        self.show_estimate()  # the device may have changed: only before any scan

    def _show_rig(self) -> None:
        """Offer the simulator's rigs, or name the scanner's own (no choice).

        Called whenever the screen shows (the help closing too, during a scan): the
        choices are only built again when the device changed.
        """
        select = self.query_one("#rig", Select)
        if is_simulated(self.job):
            choices = [(name, name) for name in RIG_PRESETS]
            rig = self.job.device.target.rig
        else:
            info = self.job.device.info
            label = info.hardware if info and info.hardware != "?" else "the scanner's own"
            choices, rig = [(label, DEVICE_RIG)], DEVICE_RIG
        if choices != self._rig_choices:
            self._rig_choices = choices
            select.set_options(choices)
        if select.value != rig:
            select.value = rig
        select.disabled = self.scanning or rig == DEVICE_RIG
