"""The line laser, switched by one GPIO line through a transistor.

gpiozero drives the pin, so the same code runs on the Pi (lgpio) and in tests and
simulation (gpiozero's own MockFactory), where the pin's state history is checkable.
The laser is switched from more than one thread (the scan, the safety watchdog,
signal handlers), so every switch holds a lock, and it remembers when it last
changed so the camera can tell which frames were exposed entirely under one state,
and how long it has been on in all, on its own clock, so the safety watchdog can bound
its share of time however seldom it looks.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable

from gpiozero import DigitalOutputDevice
from gpiozero.pins import Factory

log = logging.getLogger(__name__)


MOCK_LASER_PIN = 17
"""The laser's GPIO pin on the simulated and replayed devices (a gpiozero mock pin)."""


class Laser:
    """A laser that starts off and is switched off again before its pin is released."""

    def __init__(
        self,
        pin: int | str,
        active_high: bool = True,
        pin_factory: Factory | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ):
        self._output = DigitalOutputDevice(
            pin, active_high=active_high, initial_value=False, pin_factory=pin_factory
        )
        self._lock = threading.RLock()
        self._clock_ns = clock_ns
        self._changed_ns = clock_ns()
        self._on_count = 0
        self._on_before_ns = 0  # on-time of the switch-ons that have ended

    @property
    def is_on(self) -> bool:
        """Return True while the laser emits."""
        with self._lock:
            return not self._output.closed and bool(self._output.is_active)

    @property
    def changed_ns(self) -> int:
        """Return when the laser last changed state (``clock_ns``, CLOCK_MONOTONIC by default)."""
        return self._changed_ns

    @property
    def on_count(self) -> int:
        """Return how many times the laser has been switched on."""
        return self._on_count

    def now_ns(self) -> int:
        """Return the time on the laser's clock (``clock_ns``: the simulator's is virtual)."""
        return self._clock_ns()

    def on_time_ns(self) -> int:
        """Return how long the laser has been on in all, up to now, on its clock."""
        with self._lock:
            if self.is_on:
                return self._on_before_ns + self._clock_ns() - self._changed_ns
            return self._on_before_ns

    def on(self) -> None:
        """Switch the laser on (refused once the laser has been released)."""
        with self._lock:
            if self._output.closed:
                raise RuntimeError("the laser has been released and cannot be switched on")
            if not self._output.is_active:
                self._output.on()
                self._changed_ns = self._clock_ns()
                self._on_count += 1

    def off(self) -> None:
        """Switch the laser off (safe to call at any time, also after :meth:`close`)."""
        with self._lock:
            if not self._output.closed and self._output.is_active:
                self._output.off()
                self._switched_off()

    def _switched_off(self) -> None:
        """Note the switch-off that just happened: its time and the on-time it ended."""
        now_ns = self._clock_ns()
        self._on_before_ns += now_ns - self._changed_ns
        self._changed_ns = now_ns

    def mock_pin_history(self) -> list[bool] | None:
        """Return the pin's recorded levels under gpiozero's MockFactory, else None.

        For tests and the simulated device only: a real pin records nothing.
        """
        with self._lock:
            pin = None if self._output.closed else self._output.pin
            states = getattr(pin, "states", None)
            return None if states is None else [bool(s.state) for s in states]

    def close(self) -> None:
        """Switch off, then release the pin (a released pin may float, so off comes first)."""
        with self._lock:
            if self._output.closed:
                return
            was_on = self._output.is_active
            self._output.off()
            if was_on:
                self._switched_off()
            history = self.mock_pin_history()
            if history is not None:
                # Test hook: a simulated device run with -v shows what its laser pin did.
                active = self._output.active_high
                states = " ".join("on" if level == active else "off" for level in history)
                log.info("laser released off; states seen on its pin: %s", states)
            self._output.close()
