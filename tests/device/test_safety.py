"""Laser safety: the watchdog, signals and exit, each proven from the MockFactory pin history."""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import subprocess
import sys
import threading
import time

import numpy as np
import pytest
import serial
from gpiozero.pins.mock import MockFactory
from hypothesis import given, settings
from hypothesis import strategies as st

from lamina_device.laser import Laser
from lamina_device.safety import LaserShutdown, LaserWatchdog
from lamina_host.link.client import DeviceClient
from lamina_host.link.spawn import PtyBridge
from lamina_shared.link import Channel


class FakeClock:
    """A monotonic clock the test moves by hand."""

    def __init__(self) -> None:
        self.now_s = 1000.0

    def __call__(self) -> float:
        return self.now_s

    def ns(self) -> int:
        """Return the time in nanoseconds (the laser's clock)."""
        return round(self.now_s * 1e9)


def laser_levels(factory: MockFactory, pin: int = 17) -> list[bool]:
    return [bool(s.state) for s in factory.pin(pin).states]


@pytest.fixture
def laser():
    factory = MockFactory()
    laser = Laser(17, pin_factory=factory)
    yield laser, factory
    laser.close()


@pytest.fixture
def timed():
    """A laser on a clock the test moves by hand: (laser, its pin factory, the clock)."""
    factory, clock = MockFactory(), FakeClock()
    laser = Laser(17, pin_factory=factory, clock_ns=clock.ns)
    yield laser, factory, clock
    laser.close()


def test_watchdog_switches_off_after_the_maximum_on_time(timed, caplog):
    laser, factory, clock = timed
    dog = LaserWatchdog(laser, max_on_s=2.0, clock=clock)
    laser.on()
    assert dog.check() is None  # first sight of this switch-on starts the count
    clock.now_s += 1.9
    assert dog.check() is None and laser.is_on
    clock.now_s += 0.2
    with caplog.at_level(logging.WARNING):
        reason = dog.check()
    assert reason is not None and "on for 2.10 s, longer than the 2 s limit" in reason
    assert "laser switched off" in caplog.text
    assert laser_levels(factory) == [False, True, False]


def test_each_new_switch_on_restarts_the_count(timed):
    laser, _, clock = timed
    dog = LaserWatchdog(laser, max_on_s=2.0, clock=clock)
    for _ in range(5):  # a scan: on for 1.5 s per frame, off in between, 7.5 s in all
        laser.on()
        dog.check()
        clock.now_s += 1.5
        assert dog.check() is None
        laser.off()
        dog.check()
    assert dog.trips == []


def test_watchdog_acts_on_its_own_thread_while_the_main_loop_is_stuck(laser):
    laser, factory = laser
    with LaserWatchdog(laser, max_on_s=0.2) as dog:
        assert dog.running
        laser.on()
        time.sleep(1.0)  # the "main loop" hangs with the laser on
        assert not laser.is_on
    assert not dog.running
    assert laser_levels(factory) == [False, True, False]
    assert len(dog.trips) == 1


def test_link_silence_switches_off_only_once_a_link_is_expected(laser):
    laser, factory = laser
    clock = FakeClock()
    dog = LaserWatchdog(laser, max_on_s=1e6, link_silence_s=10.0, clock=clock)
    laser.on()
    clock.now_s += 60.0
    assert dog.check() is None and laser.is_on  # recording: no host, no link watch
    dog.link_alive()
    clock.now_s += 9.0
    assert dog.check() is None
    dog.link_alive()
    clock.now_s += 10.5
    assert "host link has been silent for 10.5 s" in (dog.check() or "")
    assert laser_levels(factory) == [False, True, False]
    laser.on()
    clock.now_s += 5.0
    assert dog.check() is None  # one action per silence, not a stream of them
    dog.link_alive()
    clock.now_s += 11.0
    assert dog.check() is not None and not laser.is_on


def test_the_laser_is_timed_on_its_own_clock_and_the_link_on_real_time():
    """A simulator renders a laser-on frame far slower than it is exposed, and its clock
    jumps over each move: its laser's on-time and share of time are measured on that
    (virtual) clock, however the checks fall; the host's silence on real time."""
    factory, real, device = MockFactory(), FakeClock(), FakeClock()
    laser = Laser(17, pin_factory=factory, clock_ns=device.ns)
    dog = LaserWatchdog(laser, max_on_s=2.0, link_silence_s=10.0, clock=real)
    dog.link_alive()
    for _ in range(100):  # views: 20 ms on, then 1.5 s real rendering, then a 0.1 s move
        laser.on()
        device.now_s += 0.02
        for _ in range(30):
            real.now_s += 0.05
            assert dog.check() is None  # every check sees the laser on
        laser.off()
        device.now_s += 0.1
        laser.on()  # the next view's switch-on comes before the next check
        laser.off()
        dog.link_alive()
    assert dog.trips == [] and real.now_s - 1000.0 > 149.0 and device.now_s - 1000.0 > 11.0
    assert laser.on_time_ns() == pytest.approx(100 * 0.02e9)
    laser.on()
    assert dog.check() is None  # this switch-on seen
    device.now_s += 2.5  # on 2.5 s on the laser's own clock
    assert "on for 2.50 s" in (dog.check() or "")
    laser.on()
    assert dog.check() is None
    real.now_s += 10.5  # the host silent for 10.5 s while the laser's clock stood still
    assert "host link has been silent for 10.5 s" in (dog.check() or "")
    assert laser_levels(factory)[-4:] == [True, False, True, False]
    laser.close()


@pytest.mark.parametrize("on_share, trips", [(0.45, False), (0.55, True)])
def test_the_share_of_time_counts_what_the_checks_fell_between(timed, on_share, trips):
    """On for 45 % of the time in pulses the checks never see, or seen by every check
    while off is not: no trip at 45 %, a trip at 55 %."""
    laser, _, clock = timed
    dog = LaserWatchdog(laser, max_on_s=1.0, clock=FakeClock())
    reason = None
    for cycle in range(30):  # 30 s of 1 s cycles, each switch-on under the 1 s limit
        laser.on()
        for _ in range(20 if cycle % 2 else 0):  # every other cycle checked while on
            reason = reason or dog.check()
            clock.now_s += on_share / 20
        clock.now_s += 0 if cycle % 2 else on_share
        laser.off()
        reason = reason or dog.check()  # checked once while off
        clock.now_s += 1.0 - on_share
    assert (reason is not None) == trips
    if trips:
        assert "it was on 55% of the last" in (reason or "")


def test_sigterm_switches_the_laser_off_before_exiting(laser):
    laser, factory = laser
    with LaserShutdown(laser):
        laser.on()
        with pytest.raises(SystemExit) as exit_info:
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(1.0)  # the handler runs at the next bytecode boundary
        assert exit_info.value.code == 128 + signal.SIGTERM
        assert laser_levels(factory) == [False, True, False]
        laser.on()
        with pytest.raises(KeyboardInterrupt):
            os.kill(os.getpid(), signal.SIGINT)
            time.sleep(1.0)
        assert laser_levels(factory)[-2:] == [True, False]
    assert signal.getsignal(signal.SIGTERM) is not LaserShutdown._handle


def test_laser_is_off_at_interpreter_exit():
    # An earlier atexit hook runs later (LIFO): it sees the state after LaserShutdown's hook.
    script = """
import atexit
from gpiozero.pins.mock import MockFactory
from lamina_device.laser import Laser
from lamina_device.safety import LaserShutdown
factory = MockFactory()
laser = Laser(17, pin_factory=factory)
atexit.register(lambda: print([s.state for s in factory.pin(17).states]))
LaserShutdown(laser).install()
laser.on()
raise SystemExit(0)
"""
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 0, result.stderr
    assert result.stdout.strip() == "[False, True, False]"


def test_sigterm_to_a_serving_device_leaves_its_laser_off():
    bridge = PtyBridge()
    command = [sys.executable, "-m", "lamina_device", "-v", "serve", "--port",
               bridge.device_port, "--hardware", "sim"]  # fmt: skip
    process = subprocess.Popen(command, stderr=subprocess.PIPE, text=True)
    scanning = threading.Event()
    try:
        with serial.Serial(bridge.host_port, baudrate=115200, timeout=0.05) as port:
            client = DeviceClient(Channel(port), process)
            client.hello()

            def scan() -> None:
                # The device is about to be terminated mid-scan.
                with contextlib.suppress(Exception):
                    client.scan("object", on_segment=lambda seq, segment: scanning.set())

            worker = threading.Thread(target=scan, daemon=True)
            worker.start()
            assert scanning.wait(60), "no segment from the device"
            process.send_signal(signal.SIGTERM)
            process.wait(timeout=60)
            # The client drains the program's stderr while it runs (a full pipe would block it).
            assert client.stderr_tail is not None
            err = "\n".join(client.stderr_tail.lines(wait_s=10))
    finally:
        if process.poll() is None:
            process.kill()
            process.wait()
        bridge.close()
    assert process.returncode == 128 + signal.SIGTERM, err
    assert "Traceback" not in err
    history = [line for line in err.splitlines() if "states seen on its pin" in line]
    assert len(history) == 1, err
    states = history[0].split(":")[-1].split()
    assert "on" in states and states[-1] == "off"


@settings(max_examples=60, deadline=None)
@given(
    cycles=st.lists(st.tuples(st.floats(0.02, 0.2), st.floats(0.05, 0.45)), min_size=1, max_size=8),
    gaps=st.lists(st.floats(0.001, 2.0), min_size=5, max_size=40),
    high=st.booleans(),
)
def test_the_share_of_time_is_bounded_however_the_checks_fall(cycles, gaps, high):
    """Pulse trains of random short cycles, checked at random instants (between pulses,
    inside them, seconds apart): a train on at most 45 % of each cycle never trips; one on
    at least 55 % of each trips once a window has passed (a window's edges can add at most
    one 0.2 s cycle, 2 % of the 10 s window)."""
    clock = FakeClock()
    laser = Laser(17, pin_factory=MockFactory(), clock_ns=clock.ns)
    dog = LaserWatchdog(laser, max_on_s=1.0, clock=clock)
    switches: list[tuple[float, bool]] = []
    t = 0.0
    while t < 30.0:
        for cycle_s, share in cycles:
            on_share = 1.0 - share if high else share  # 55-95 % when high
            switches += [(t, True), (t + on_share * cycle_s, False)]
            t += cycle_s
    checks = np.cumsum(np.tile(gaps, int(30.0 / sum(gaps)) + 2))
    checks = checks[checks < 30.0]
    events = sorted([(s, 0, on) for s, on in switches] + [(c, 1, False) for c in checks])
    tripped_at = None
    for when_s, kind, on in events:
        clock.now_s = 1000.0 + when_s
        if kind == 0:
            laser.on() if on else laser.off()
        elif dog.check() is not None and tripped_at is None:
            tripped_at = when_s
    laser.close()
    if not high:
        assert tripped_at is None
    elif checks.size and checks[-1] - checks[0] >= 10.0 + max(gaps):
        assert tripped_at is not None
