"""The laser pin under gpiozero's MockFactory: levels, active level, release."""

from __future__ import annotations

import logging

import pytest
from gpiozero.pins.mock import MockFactory

from lamina_device.laser import Laser


def test_laser_switches_its_pin_and_remembers_when():
    factory = MockFactory()
    ticks = iter(range(100, 200))
    laser = Laser(17, pin_factory=factory, clock_ns=lambda: next(ticks))
    created_ns = laser.changed_ns
    laser.on()
    laser.on()  # no change, no new timestamp
    assert laser.is_on and laser.on_count == 1 and laser.changed_ns == created_ns + 1
    laser.off()
    assert not laser.is_on and laser.changed_ns == created_ns + 2
    assert [s.state for s in factory.pin(17).states] == [False, True, False]


def test_active_low_laser_drives_its_pin_low_to_emit():
    factory = MockFactory()
    laser = Laser(22, active_high=False, pin_factory=factory)
    pin = factory.pin(22)
    assert pin.state is True and not laser.is_on
    laser.on()
    assert pin.state is False and laser.is_on
    laser.close()
    assert [s.state for s in pin.states][-2:] == [False, True]


def test_close_switches_off_first_and_logs_the_history(caplog):
    factory = MockFactory()
    laser = Laser(17, pin_factory=factory)
    laser.on()
    with caplog.at_level(logging.INFO, logger="lamina_device.laser"):
        laser.close()
    assert "states seen on its pin: off on off" in caplog.text
    assert [s.state for s in factory.pin(17).states][-1] is False
    laser.off()  # harmless after release
    assert not laser.is_on and laser.mock_pin_history() is None
    with pytest.raises(RuntimeError, match="released"):
        laser.on()
