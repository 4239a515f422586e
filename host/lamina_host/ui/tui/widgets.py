"""Pieces every Lamina screen shares: the app's state, navigation bar, status line, frame
view and the worker helper."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from functools import partial
from typing import ClassVar, TypeVar

import numpy as np
from rich.console import Console
from rich.markdown import Markdown as RichMarkdown
from rich.text import Text
from textual import events
from textual.app import App, ComposeResult, RenderResult
from textual.binding import Binding, BindingType
from textual.containers import Container, Horizontal, VerticalScroll
from textual.content import Content
from textual.geometry import Size
from textual.reactive import reactive
from textual.screen import ModalScreen, Screen
from textual.widget import Widget
from textual.widgets import Button, Checkbox, Footer, Input, Select, Static
from textual.worker import get_current_worker

from lamina_host.ui.tui.adapter import USER_ERRORS, ScanJob, user_message
from lamina_host.ui.tui.render import cell_grid, grid_text
from lamina_host.workflow.device_session import Pose
from lamina_shared.types import Segment

T = TypeVar("T")

SCREENS: tuple[tuple[str, str, str], ...] = (
    ("connect", "f2", "Connect"),
    ("live", "f3", "Live"),
    ("calibrate", "f4", "Calibrate"),
    ("scan", "f5", "Scan"),
    ("results", "f6", "Results"),
    ("library", "f7", "Library"),
)
"""(mode name, key, title) of each screen, in workflow order."""


class JobApp(App[None]):
    """An app holding one scan job, and the state its screens show as it changes.

    Worker threads never change these: a screen sets them on the UI thread (from a
    worker's result or a message), and the screens that show them watch them.
    """

    status: reactive[tuple[str, bool]] = reactive(
        ("F2 Connect to start; F1 shows every key", False)
    )
    """The latest status line (message, is_error), shown on every screen."""
    latest_segment: reactive[Segment | None] = reactive(None)
    """The view the device sent last during a scan (the live screen draws its stripe)."""
    pose: reactive[Pose] = reactive(Pose())
    """Where the axes stand since the last move."""

    def __init__(self, job: ScanJob) -> None:
        super().__init__()
        self.job = job


NAV_TITLE = " Lamina "


def nav_spans() -> list[tuple[int, int, str]]:
    """Return (first column, end column, mode) of each screen's name in the top bar."""
    spans, x = [], len(NAV_TITLE)
    for mode, key, title in SCREENS:
        width = len(f" {key.upper()} {title} ")
        spans.append((x, x + width, mode))
        x += width
    return spans


class NavBar(Static):
    """One line naming every screen and its key, the current one highlighted.

    A click (or a tap in the browser) on a screen's name shows that screen: a tablet has
    no F-keys.
    """

    def __init__(self, current: str) -> None:
        super().__init__(id="nav")
        self.current = current

    def render(self) -> RenderResult:
        """Draw the screen list."""
        text = Text(NAV_TITLE, style="bold")
        for mode, key, title in SCREENS:
            style = "reverse bold" if mode == self.current else ""
            text.append(f" {key.upper()} {title} ", style=style)
        return text

    def on_click(self, event: events.Click) -> None:
        """Show the screen whose name was clicked."""
        for first, end, mode in nav_spans():
            if first <= event.x < end:
                self.app.switch_mode(mode)
                return


class StatusLine(Static):
    """The app's latest status message (errors in red), on every screen."""

    def on_mount(self) -> None:
        """Follow the app's status."""
        self.watch(self.app, "status", self._show, init=True)

    def _show(self, status: tuple[str, bool]) -> None:
        message, is_error = status
        self.set_class(is_error, "-error")
        self.update(Text(message))


class FrameView(Widget):
    """A camera frame in half-block characters with the stripe points drawn in red."""

    image: reactive[np.ndarray | None] = reactive(None, always_update=True)
    stripe_uv: reactive[np.ndarray | None] = reactive(None, always_update=True)

    def render(self) -> RenderResult:
        """Fit the frame into the widget's size."""
        if self.image is None:
            return Text("no frame yet: press g to grab one from the device", style="dim")
        size = self.content_size
        grid = cell_grid(self.image, max(size.width, 1), max(size.height, 1), self.stripe_uv)
        return grid_text(grid)


def name_choice(names: Sequence[str], widget_id: str) -> Select[str]:
    """Return a compact field choosing one of ``names`` (the first at start)."""
    return Select(
        [(name, name) for name in names],
        value=names[0],
        allow_blank=False,
        id=widget_id,
        compact=True,
    )


class TickBox(Checkbox):
    """A checkbox that shows a tick only when ticked (Textual's shows a dim X either way)."""

    @property
    def _button(self) -> Content:
        self.BUTTON_INNER = "X" if self.value else " "
        return super()._button


HELP_TEXT = """\
# Lamina: keys and workflow

Everything works from the keyboard, and by mouse or touch: **click or tap** a screen's
name in the top bar, a key in the footer, a button or a field. **F2-F7** switch screens,
**Tab** moves between fields and buttons, **Enter** presses a button, **Escape** leaves a
field, **Ctrl+P** opens the command palette, **Ctrl+Q** quits. This help scrolls:
**arrows**, **Page Up/Down**, the mouse wheel or a swipe.

1. **Connect (F2)**: pick a port in the list (or `sim`, the simulated scanner) and press
   **c** (or type a device and press Enter); **d** disconnects, **l** lists the ports again.
2. **Live (F3)**: **g** grabs a frame, **l** switches the laser, the arrows turn the
   turntable and move the lift, **h** homes, **+** and **-** change the exposure; the
   last scanned stripe is drawn in red.
3. **Calibrate (F4)**: place the chessboard flat on the laser plane and press **g**: the
   picture shows what the camera sees, the corners found in red, and whether the residual
   passes its limit; **a** accepts, **x** rejects. Then place the calibration cylinder
   upright on the turntable and press **y**: the axis and the correction factor (more than
   5% from 1 fails).
4. **Scan (F5)**: type the **Subject** code (never a name), choose the **Side** (left,
   right, or none for what is not a limb) and the **Plan**: a preset named for what it
   scans (arm, leg, hand, cast), cut to the lift's travel, or your own numbers
   (sections, pitch, views). The **Rig** is the simulator's (thesis or limb; choosing one
   starts it again, so calibrate again) or the scanner's own. **s** starts: the first view
   is checked against the camera's view before any other is taken; the time left counts
   down. **p** pauses or resumes, **b** aborts (views received are kept), **r** reconnects
   a dropped link.
5. **Results (F6)**: **p** processes again with the harmonics and mesh method chosen; **m**
   opens the clinical view; **Compare** picks the other limb's latest scan or an earlier
   visit of the same side; **e** exports into the new folder typed: the mesh (PLY, OBJ,
   STL), report.json, the clinical report report.pdf, its table measures.csv and the
   DICOM file scan.dcm.
6. **Clinical view (m on Results)**: circumferences every **Spacing mm** from the
   **Landmark** (distal, bottom, top or a height in mm); **k** puts the landmark at the
   row picked on Results; with a comparison, each level's difference and the excess or
   change in mL and %; **Escape** closes it. The exported report measures the same way.
7. **Library (F7)**: past scans with their side; **/** filters by subject code; **o** opens
   one, **p** processes it again, **e** exports it, **d** deletes it (asks first), **u**
   reads the list again.

In a browser (`lamina serve-ui`), everything above works by tap: the top bar's names
switch screens, the footer's keys run, and a tap in a field brings up the keyboard.

Press **Escape** (or tap *Close help*) to close this help.
"""


class HelpText(Static):
    """The help's text, laid out once per width: Rich lays out Markdown in tens of ms, which
    delayed the keys pressed while a scan ran."""

    def __init__(self) -> None:
        super().__init__(id="help-text")
        self._laid_out: dict[int, Text] = {}

    def laid_out(self, width: int) -> Text:
        """Return the help laid out ``width`` cells wide (from the cache after the first time)."""
        width = max(width, 20)
        if width not in self._laid_out:
            console = Console(width=width, color_system="truecolor", force_terminal=True)
            with console.capture() as captured:
                console.print(RichMarkdown(HELP_TEXT))
            self._laid_out[width] = Text.from_ansi(captured.get().rstrip("\n"))
        return self._laid_out[width]

    def get_content_height(self, container: Size, viewport: Size, width: int) -> int:
        """Return the laid-out help's line count at ``width``."""
        return self.laid_out(width).plain.count("\n") + 1

    def render(self) -> RenderResult:
        """Return the help laid out for this width."""
        return self.laid_out(self.content_size.width)


class HelpScreen(ModalScreen[None]):
    """The key bindings and the workflow, over the current screen."""

    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("escape,f1,q", "dismiss", "Close help"),
        Binding("down", "scroll('down')", "Scroll", key_display="↑↓"),
        Binding("up", "scroll('up')", "Scroll up", show=False),
        Binding("pagedown,space", "scroll('page_down')", "Page down", show=False),
        Binding("pageup", "scroll('page_up')", "Page up", show=False),
    ]

    def compose(self) -> ComposeResult:
        """Lay out the help text in a scrolling box."""
        with VerticalScroll(id="help"):
            # One widget: Textual's Markdown makes one per paragraph and list item, and
            # laying those out each time the help opens slowed keys during a scan.
            yield HelpText()
        yield Footer(compact=True, show_command_palette=False)

    def action_scroll(self, how: str) -> None:
        """Scroll the help: ``up``, ``down``, ``page_up`` or ``page_down``."""
        box = self.query_one("#help", VerticalScroll)
        getattr(box, f"scroll_{how}")()


class LaminaScreen(Screen[None]):
    """A workflow screen: navigation bar, the screen's body, status line and footer."""

    MODE = ""

    def compose(self) -> ComposeResult:
        """Lay out the frame around :meth:`body`."""
        yield NavBar(self.MODE)
        with Container(classes="body"):
            yield from self.body()
        yield StatusLine(id="status")
        # Compact, without the palette's key (Ctrl+P, in the help): every key fits at 80.
        yield Footer(compact=True, show_command_palette=False)

    def body(self) -> ComposeResult:
        """Yield this screen's own widgets."""
        yield from ()

    def check_action(self, action: str, parameters: tuple[object, ...]) -> bool | None:
        """Offer "leave field" (Escape) only while a text field has the keys."""
        if action == "leave_field":
            return isinstance(self.focused, Input)
        return True

    @property
    def lamina(self) -> JobApp:
        """Return the app this screen belongs to (every Lamina screen runs in a JobApp)."""
        app = self.app
        if not isinstance(app, JobApp):
            raise TypeError(f"a Lamina screen runs in a JobApp, not in {type(app).__name__}")
        return app

    @property
    def job(self) -> ScanJob:
        """Return the app's scan job (device, acquisition, processing, library)."""
        return self.lamina.job

    def say(self, message: str, error: bool = False) -> None:
        """Show ``message`` on the status line (and as a notification when it is an error)."""
        self.lamina.status = (message, error)
        if error:
            self.notify(message, severity="error", timeout=8)

    def attempt(self, job: Callable[[], T], done: Callable[[T], None]) -> None:
        """In a thread worker: run ``job``; hand its result to ``done``, or say what went wrong.

        Errors a user can act on become one line on the status line; anything else is
        logged and reported as an internal error, so the UI never shows a traceback. A
        worker cancelled meanwhile (a newer one of its group replaced it) delivers
        nothing: its result or failure would overwrite the newer one's.
        """
        try:
            value = job()
        except USER_ERRORS as exc:
            self._deliver(self.failed, user_message(exc))
            return
        except Exception as exc:  # the app must outlive a bug; the log keeps the details
            self.log.error("worker failed", exc_info=exc)
            self._deliver(
                self.failed, f"internal error ({type(exc).__name__}: {exc}); please report"
            )
            return
        self._deliver(done, value)

    def _deliver(self, to: Callable[[T], None], value: T) -> None:
        """Hand ``value`` to ``to`` on the UI thread, unless this worker was cancelled.

        The check runs on the UI thread, where a newer worker cancels this one, so a
        cancellation just before delivery is seen too.
        """
        worker = get_current_worker()

        def deliver() -> None:
            if worker.is_cancelled:
                self.log.info(f"worker {worker.name!r} was superseded; its outcome is dropped")
                return
            to(value)

        self.app.call_from_thread(deliver)

    def in_thread(self, group: str, job: Callable[[], T], done: Callable[[T], None]) -> None:
        """Run ``job`` in a thread worker (a new one cancels the running one of its ``group``).

        ``done`` gets the result on the UI thread; failures go to :meth:`failed`, as
        :meth:`attempt` says; a cancelled worker's outcome is dropped. (A thread cannot be
        stopped: a cancelled ``job`` still runs to its end.)
        """
        self.run_worker(partial(self.attempt, job, done), thread=True, exclusive=True, group=group)

    def failed(self, message: str) -> None:
        """Show a worker's failure; screens extend this to reset their controls."""
        self.say(message, error=True)

    def on_screen_resume(self) -> None:
        """Refresh from the job whenever the screen is shown."""
        self.refresh_from_job()

    def refresh_from_job(self) -> None:
        """Show what the job holds now (screens override)."""


class ConfirmScreen(ModalScreen[bool]):
    """Ask a yes/no question; y confirms, n or Escape cancels."""

    AUTO_FOCUS = "#no"  # Enter on a question about deleting must not say yes
    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("y", "answer(True)", "Yes"),
        Binding("n,escape", "answer(False)", "No"),
    ]

    def __init__(self, question: str) -> None:
        super().__init__()
        self.question = question

    def compose(self) -> ComposeResult:
        """The question, the two keys and their buttons (a tablet has no keys to press)."""
        with Container(classes="dialog"):
            yield Static(self.question)
            yield Static("y: yes    n: no", classes="dim")
            with Horizontal(classes="buttons"):
                yield Button("Yes", id="yes", variant="error", compact=True)
                yield Button("No", id="no", compact=True)

    def on_button_pressed(self, event: Button.Pressed) -> None:
        """Answer with the button pressed."""
        self.dismiss(event.button.id == "yes")

    def action_answer(self, yes: bool) -> None:
        """Close with the answer."""
        self.dismiss(yes)


class AskScreen(ModalScreen[str | None]):
    """Ask for one line of text; Enter answers, Escape cancels."""

    BINDINGS: ClassVar[list[BindingType]] = [Binding("escape", "cancel", "Cancel")]

    def __init__(self, question: str, placeholder: str = "") -> None:
        super().__init__()
        self.question = question
        self.placeholder = placeholder

    def compose(self) -> ComposeResult:
        """The question, the field and the buttons (a tablet has no Enter or Escape key)."""
        with Container(classes="dialog"):
            yield Static(self.question)
            yield Input(placeholder=self.placeholder, id="answer", compact=True)
            with Horizontal(classes="buttons"):
                yield Button("OK", id="ok", variant="primary", compact=True)
                yield Button("Cancel", id="cancel", compact=True)

    def on_input_submitted(self, event: Input.Submitted) -> None:
        """Answer with the text typed."""
        self.dismiss(event.value.strip() or None)

    def on_button_pressed(self, event: Button.Pressed) -> None:
        """Answer with the text typed (OK) or nothing (Cancel)."""
        text = self.query_one("#answer", Input).value.strip()
        self.dismiss(text or None if event.button.id == "ok" else None)

    def action_cancel(self) -> None:
        """Close without an answer."""
        self.dismiss(None)
