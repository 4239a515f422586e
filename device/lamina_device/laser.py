"""The line laser, switched by one GPIO line through a transistor.

gpiozero drives the pin, so the same code runs on the Pi (lgpio) and in tests and
simulation (gpiozero's own MockFactory), where the pin's state history is checkable.
"""

from __future__ import annotations

from gpiozero import DigitalOutputDevice
from gpiozero.pins import Factory


class Laser:
    """A laser that starts off and is switched off again before its pin is released."""

    def __init__(
        self, pin: int | str, active_high: bool = True, pin_factory: Factory | None = None
    ):
        self._output = DigitalOutputDevice(
            pin, active_high=active_high, initial_value=False, pin_factory=pin_factory
        )

    @property
    def is_on(self) -> bool:
        """Return True while the laser emits."""
        return bool(self._output.is_active)

    def on(self) -> None:
        """Switch the laser on."""
        self._output.on()

    def off(self) -> None:
        """Switch the laser off."""
        self._output.off()

    def close(self) -> None:
        """Switch off, then release the pin (a released pin may float, so off comes first)."""
        if not self._output.closed:
            self._output.off()
            self._output.close()
