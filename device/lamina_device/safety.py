"""Laser safety: automatic shut-off independent of the scan (thesis appendix A).

Three layers keep the laser from staying on. The scan switches it on only while a
laser-on frame is exposed and off in ``finally`` blocks. :class:`LaserWatchdog`
runs on its own thread and switches it off when it has been on too long or the host
link has gone quiet, whatever the main loop is doing. :class:`LaserShutdown`
switches it off on SIGTERM (systemd's stop, which skips atexit), on SIGINT and at
interpreter exit.

A continuous scan switches the laser on once per view, several times a second, and each
switch-on starts the watchdog's on-time count afresh. So the watchdog also bounds the
share of time the laser is on (:data:`MAX_LASER_DUTY` over a long window), which no
train of re-armed pulses can pass, and a scan mode whose pulses would not be accepted
(:meth:`LaserWatchdog.pulse_problem`) is refused before anything moves.

The laser's times (its on-time, its share) are measured on the laser's own clock, the
host link's silence on real time. On a box the two are the same clock; the simulator's
laser runs on its virtual clock, which stands still while a frame is rendered (far
longer than the exposure it stands for) and jumps over a move: measured in real time, or
by sampling its state, a simulated scan would look like a laser left on.
"""

from __future__ import annotations

import atexit
import logging
import signal
import threading
import time
from collections import deque
from collections.abc import Callable
from types import FrameType
from typing import Protocol

from lamina_shared.scoped import Scoped

log = logging.getLogger(__name__)

MAX_LASER_DUTY = 0.5
"""The largest share of time the laser may be on over :data:`DUTY_WINDOWS` on-time limits."""
DUTY_WINDOWS = 10
"""The duty window, in on-time limits: long enough that one full-length pulse passes."""


class Switchable(Protocol):
    """The part of :class:`lamina_device.laser.Laser` the safety layers use."""

    @property
    def is_on(self) -> bool:
        """Return True while the laser emits."""
        ...  # pragma: no cover - protocol

    @property
    def on_count(self) -> int:
        """Return how many times the laser has been switched on."""
        ...  # pragma: no cover - protocol

    def now_ns(self) -> int:
        """Return the time on the laser's clock."""
        ...  # pragma: no cover - protocol

    def on_time_ns(self) -> int:
        """Return how long the laser has been on in all, up to now, on its clock."""
        ...  # pragma: no cover - protocol

    def off(self) -> None:
        """Switch the laser off."""
        ...  # pragma: no cover - protocol


class LaserWatchdog(Scoped):
    """Switch the laser off after ``max_on_s`` on, or after ``link_silence_s`` without the host.

    The link is only watched once :meth:`link_alive` has been called (a recording
    run has no host). The watchdog measures on-time from the moment it sees a new
    switch-on, so it does not trust the code it guards; it polls often enough that the
    overrun past ``max_on_s`` is at most one poll.

    Args:
        laser: The laser to watch and switch off; its on-time and share of time are
            measured on its clock.
        max_on_s: The longest the laser may stay on after one switch-on.
        link_silence_s: The longest the host may be silent once it has been heard.
        clock: Real time in seconds, on which the host link's silence is measured.
    """

    def __init__(
        self,
        laser: Switchable,
        max_on_s: float = 2.0,
        link_silence_s: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        if not (max_on_s > 0 and link_silence_s > 0):
            raise ValueError("watchdog times must be positive")
        self.laser = laser
        self.max_on_s = max_on_s
        self.link_silence_s = link_silence_s
        self.clock = clock
        self.poll_s = min(0.05, max_on_s / 20.0)
        self.trips: list[str] = []
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._seen_on_count: int | None = None
        self._on_since: float | None = None
        self._last_link: float | None = None
        self._link_tripped = False
        self._samples: deque[tuple[float, float]] = deque()  # (laser clock, on-time) in s

    def start(self) -> None:
        """Start watching on a daemon thread (idempotent)."""
        if self._thread is not None and self._thread.is_alive():
            return
        self._stop.clear()
        self._thread = threading.Thread(target=self._run, name="laser-watchdog", daemon=True)
        self._thread.start()

    def stop(self) -> None:
        """Stop watching and switch the laser off."""
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join()
        self._thread = None
        self.laser.off()

    @property
    def running(self) -> bool:
        """Return True while the watchdog thread runs."""
        return self._thread is not None and self._thread.is_alive()

    def link_alive(self) -> None:
        """Note that the host was just heard from (the server calls this per message)."""
        with self._lock:
            self._last_link = self.clock()
            self._link_tripped = False

    def pulse_problem(self, on_s: float, every_s: float) -> str | None:
        """Return why pulses of ``on_s`` once every ``every_s`` are not acceptable, or None.

        Each pulse must end well within the on-time limit, and the train must keep the
        laser off most of the time: re-armed at each switch-on, the on-time limit alone
        would not bound it.
        """
        if on_s >= 0.5 * self.max_on_s:
            return (
                f"the laser would stay on {on_s:.3f} s a view, more than half the "
                f"{self.max_on_s:g} s on-time limit"
            )
        if every_s <= 0 or on_s / every_s > MAX_LASER_DUTY:
            return (
                f"the laser would be on {on_s:.3f} s every {every_s:.3f} s, more than "
                f"{MAX_LASER_DUTY:.0%} of the time"
            )
        return None

    def check(self) -> str | None:
        """Check once; switch the laser off and return the reason if a limit was passed."""
        now, laser_now = self.clock(), self.laser.now_ns() * 1e-9
        with self._lock:
            reason = (
                self._on_time_reason(laser_now)
                or self._duty_reason(laser_now)
                or self._link_reason(now)
            )
        if reason is not None:
            self.laser.off()
            self.trips.append(reason)
            log.warning("safety: laser switched off: %s", reason)
        return reason

    def _on_time_reason(self, now: float) -> str | None:
        if not self.laser.is_on:
            self._on_since = None
            return None
        count = self.laser.on_count
        if self._on_since is None or count != self._seen_on_count:
            self._on_since, self._seen_on_count = now, count
            return None
        on_s = now - self._on_since
        if on_s <= self.max_on_s:
            return None
        self._on_since = None
        return f"it was on for {on_s:.2f} s, longer than the {self.max_on_s:g} s limit"

    def _duty_reason(self, now: float) -> str | None:
        """Return why the laser was on too large a share of the last window.

        Each check notes the laser's total on-time; the share is what it grew by since the
        last check at least a window ago, so a switch the checks fell between still counts.
        """
        window_s = DUTY_WINDOWS * self.max_on_s
        samples = self._samples
        if samples and samples[-1][0] >= now:
            samples.pop()  # the clock stood still since: keep one note per instant
        samples.append((now, self.laser.on_time_ns() * 1e-9))
        while len(samples) > 1 and samples[1][0] <= now - window_s:
            samples.popleft()
        since_s, on_then_s = samples[0]
        if since_s > now - window_s:
            return None  # not watched for a whole window yet
        share = (samples[-1][1] - on_then_s) / (now - since_s)
        if share <= MAX_LASER_DUTY:
            return None
        samples.clear()
        return f"it was on {share:.0%} of the last {window_s:g} s, more than {MAX_LASER_DUTY:.0%}"

    def _link_reason(self, now: float) -> str | None:
        if self._last_link is None or self._link_tripped:
            return None
        silent_s = now - self._last_link
        if silent_s <= self.link_silence_s:
            return None
        # Act once per silence: the laser stays off until the host is heard again.
        self._link_tripped = True
        limit_s = self.link_silence_s
        return f"the host link has been silent for {silent_s:.1f} s (limit {limit_s:g} s)"

    def _run(self) -> None:
        while not self._stop.wait(self.poll_s):
            try:
                self.check()
            except Exception:  # the guard must outlive any one failure
                log.exception("safety: watchdog check failed; switching the laser off")
                self.laser.off()

    def enter(self) -> None:
        """Start watching (``with watchdog:``)."""
        self.start()

    def leave(self) -> None:
        """Stop watching at the end of the ``with`` block."""
        self.stop()


class LaserShutdown(Scoped):
    """Switch the laser off on SIGTERM, SIGINT and interpreter exit (a context manager).

    SIGTERM becomes ``SystemExit(143)`` and SIGINT ``KeyboardInterrupt``, after the
    laser is already off, so ``finally`` blocks still run. Install from the main thread.
    """

    SIGNALS = (signal.SIGTERM, signal.SIGINT)

    def __init__(self, laser: Switchable) -> None:
        self.laser = laser
        self._previous: dict[int, object] = {}

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self.laser.off()
        log.info("safety: laser off on signal %s", signal.Signals(signum).name)
        if signum == signal.SIGINT:
            raise KeyboardInterrupt
        raise SystemExit(128 + signum)

    def install(self) -> None:
        """Install the signal handlers and the exit hook."""
        for signum in self.SIGNALS:
            self._previous[signum] = signal.signal(signum, self._handle)
        atexit.register(self.laser.off)

    def uninstall(self) -> None:
        """Restore the previous signal handlers and drop the exit hook."""
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)  # type: ignore[arg-type]
        self._previous.clear()
        atexit.unregister(self.laser.off)

    def enter(self) -> None:
        """Install the handlers (``with LaserShutdown(laser):``)."""
        self.install()

    def leave(self) -> None:
        """Switch the laser off and restore what was there before."""
        self.laser.off()
        self.uninstall()
