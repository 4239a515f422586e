"""Pieces every Lamina screen shares: navigation bar, status line, frame view, worker helper."""

from __future__ import annotations

from collections.abc import Callable
from functools import partial
from typing import ClassVar, TypeVar

import numpy as np
from rich.text import Text
from textual.app import ComposeResult, RenderResult
from textual.binding import Binding, BindingType
from textual.containers import Container
from textual.reactive import reactive
from textual.screen import ModalScreen, Screen
from textual.widget import Widget
from textual.widgets import Footer, Input, Markdown, Static

from lamina_host.ui.tui.adapter import USER_ERRORS, Session, user_message
from lamina_host.ui.tui.render import cell_grid, grid_text

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


class NavBar(Static):
    """One line naming every screen and its key, the current one highlighted."""

    def __init__(self, current: str) -> None:
        super().__init__(id="nav")
        self.current = current

    def render(self) -> RenderResult:
        """Draw the screen list."""
        text = Text(" Lamina ", style="bold")
        for mode, key, title in SCREENS:
            style = "reverse bold" if mode == self.current else ""
            text.append(f" {key.upper()} {title} ", style=style)
        return text


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


HELP_TEXT = """\
# Lamina: keys and workflow

Everything works from the keyboard. **F2-F7** switch screens, **Tab** moves between
fields and buttons, **Enter** presses a button, **Escape** leaves a field,
**Ctrl+P** opens the command palette, **Ctrl+Q** quits.

1. **Connect (F2)**: choose a port (or `sim`, `replay:DIR`) and press **c**.
2. **Live (F3)**: **g** grabs a frame, **l** switches the laser, arrows jog the
   turntable and the lift, **h** homes; the last scanned stripe is drawn in red.
3. **Calibrate (F4)**: **g** captures the chessboard (corners, residuals in mm);
   **a** accepts, **x** rejects; **y** scans the calibration cylinder (axis and
   correction factor; more than 5% from 1 is flagged).
4. **Scan (F5)**: enter the subject id and plan, **s** starts; **p** pauses or
   resumes, **b** aborts (views already received are kept); **r** reconnects a
   dropped link.
5. **Results (F6)**: **p** processes again with the chosen harmonics and mesh
   method; **e** exports PLY, OBJ, STL and the report into the folder given.
6. **Library (F7)**: past scans; **o** opens one, **e** exports, **d** deletes
   (asks first).

Press **Escape** to close this help.
"""


class HelpScreen(ModalScreen[None]):
    """The key bindings and the workflow, over the current screen."""

    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("escape,f1,q", "dismiss", "Close help"),
    ]

    def compose(self) -> ComposeResult:
        """Lay out the help text."""
        with Container(id="help"):
            yield Markdown(HELP_TEXT)
        yield Footer()


class LaminaScreen(Screen[None]):
    """A workflow screen: navigation bar, the screen's body, status line and footer."""

    MODE = ""

    def compose(self) -> ComposeResult:
        """Lay out the frame around :meth:`body`."""
        yield NavBar(self.MODE)
        with Container(classes="body"):
            yield from self.body()
        yield StatusLine(id="status")
        yield Footer()

    def body(self) -> ComposeResult:
        """Yield this screen's own widgets."""
        yield from ()

    @property
    def session(self) -> Session:
        """Return the app's session (device, calibration, scan, results)."""
        session: Session = getattr(self.app, "session")  # noqa: B009 - avoids an import cycle
        return session

    def say(self, message: str, error: bool = False) -> None:
        """Show ``message`` on the status line (and as a notification when it is an error)."""
        setattr(self.app, "status", (message, error))  # noqa: B010 - see session
        if error:
            self.notify(message, severity="error", timeout=8)

    def attempt(self, job: Callable[[], T], done: Callable[[T], None]) -> None:
        """In a thread worker: run ``job``; hand its result to ``done``, or say what went wrong.

        Errors a user can act on become one line on the status line; anything else is
        logged and reported as an internal error, so the UI never shows a traceback.
        """
        try:
            value = job()
        except USER_ERRORS as exc:
            self.app.call_from_thread(self.failed, user_message(exc))
            return
        except Exception as exc:  # the app must outlive a bug; the log keeps the details
            self.log.error("worker failed", exc_info=exc)
            self.app.call_from_thread(
                self.failed, f"internal error ({type(exc).__name__}: {exc}); please report"
            )
            return
        self.app.call_from_thread(done, value)

    def in_thread(self, group: str, job: Callable[[], T], done: Callable[[T], None]) -> None:
        """Run ``job`` in a thread worker (a new one cancels the running one of its ``group``).

        ``done`` gets the result on the UI thread; failures go to :meth:`failed`, as
        :meth:`attempt` says.
        """
        self.run_worker(partial(self.attempt, job, done), thread=True, exclusive=True, group=group)

    def failed(self, message: str) -> None:
        """Show a worker's failure; screens extend this to reset their controls."""
        self.say(message, error=True)

    def on_screen_resume(self) -> None:
        """Refresh from the session whenever the screen is shown."""
        self.refresh_from_session()

    def refresh_from_session(self) -> None:
        """Show what the session holds now (screens override)."""


class ConfirmScreen(ModalScreen[bool]):
    """Ask a yes/no question; y confirms, n or Escape cancels."""

    BINDINGS: ClassVar[list[BindingType]] = [
        Binding("y", "answer(True)", "Yes"),
        Binding("n,escape", "answer(False)", "No"),
    ]

    def __init__(self, question: str) -> None:
        super().__init__()
        self.question = question

    def compose(self) -> ComposeResult:
        """The question and the two keys."""
        with Container(classes="dialog"):
            yield Static(self.question)
            yield Static("y: yes    n: no", classes="dim")

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
        """The question and the field."""
        with Container(classes="dialog"):
            yield Static(self.question)
            yield Input(placeholder=self.placeholder, id="answer", compact=True)

    def on_input_submitted(self, event: Input.Submitted) -> None:
        """Answer with the text typed."""
        self.dismiss(event.value.strip() or None)

    def action_cancel(self) -> None:
        """Close without an answer."""
        self.dismiss(None)
