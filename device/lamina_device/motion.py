"""The two motion axes: the turntable (degrees) and the lift (millimetres).

The acquisition only sees :class:`Turntable` and :class:`Lift`; each declares its soft
limits so the device can report and enforce them without knowing the implementation.
This module holds those interfaces and the stepper axes of the scanner box: step/dir
drivers (A4988, DRV8825, TMC2209 class) through gpiozero outputs, trapezoidal
acceleration with the step timing computed up front, position kept in whole
microsteps, a homing limit switch and soft limits on the lift, and backlash take-up on
the turntable. The simulated axes, with their mechanical error model, live with the
rest of the virtual rig in ``lamina_device/sim/axes.py``.
"""

from __future__ import annotations

import bisect
import logging
import math
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from functools import partial
from typing import Protocol, runtime_checkable

import numpy as np
from gpiozero import DigitalInputDevice, DigitalOutputDevice
from gpiozero.pins import Factory

from lamina_device.config import DriverConfig, LiftConfig, TurntableConfig, pulse_rate
from lamina_shared.errors import LaminaError

log = logging.getLogger(__name__)


class MotionError(LaminaError, ValueError):
    """A move was refused or failed; the message says why and what to do."""


class Turntable(Protocol):
    """A rotary axis holding the subject."""

    @property
    def angle_deg(self) -> float:
        """Return the angle the axis is at, in [0, 360) for stepper axes."""
        ...  # pragma: no cover - protocol

    @property
    def count_deg(self) -> float:
        """Return the rotation the step count has made since power-up, unwrapped."""
        ...  # pragma: no cover - protocol

    @property
    def min_deg(self) -> float | None:
        """Return the lowest angle the axis may be sent to; None for a continuous table."""
        ...  # pragma: no cover - protocol

    @property
    def max_deg(self) -> float | None:
        """Return the highest angle the axis may be sent to; None for a continuous table."""
        ...  # pragma: no cover - protocol

    def move_to(self, angle_deg: float) -> None:
        """Rotate to ``angle_deg`` (counter-clockwise seen from above)."""
        ...  # pragma: no cover - protocol

    def close(self) -> None:
        """Release the axis."""
        ...  # pragma: no cover - protocol


class Lift(Protocol):
    """The vertical axis that moves the laser plane relative to the subject."""

    @property
    def z_mm(self) -> float:
        """Return the height the axis is at."""
        ...  # pragma: no cover - protocol

    @property
    def min_mm(self) -> float:
        """Return the lowest height the axis may be sent to (its lower soft limit)."""
        ...  # pragma: no cover - protocol

    @property
    def max_mm(self) -> float:
        """Return the highest height the axis may be sent to (its upper soft limit)."""
        ...  # pragma: no cover - protocol

    def move_to(self, z_mm: float) -> None:
        """Move so the laser plane is ``z_mm`` above the first section."""
        ...  # pragma: no cover - protocol

    def home(self) -> None:
        """Return to the home position (re-referencing it where the axis can)."""
        ...  # pragma: no cover - protocol

    def close(self) -> None:
        """Release the axis."""
        ...  # pragma: no cover - protocol


# --- Stepper axes on step/dir drivers -------------------------------------------------

_SPIN_S = 0.0005  # sleep until this close to a step's deadline, then spin (sleep overshoots)
_ENABLE_SETTLE_S = 0.001  # drivers want about 1 ms between EN and the first STEP edge


def trapezoid_intervals_s(
    steps: int, start_speed_sps: float, max_speed_sps: float, accel_sps2: float
) -> np.ndarray:
    """Return the wait before each step pulse of a trapezoidal move, computed up front.

    The axis starts at ``start_speed_sps`` (below the motor's pull-in rate), gains
    speed at ``accel_sps2`` up to ``max_speed_sps`` and slows down symmetrically, so
    intervals shrink, stay at ``1 / max_speed_sps`` and grow again (a triangle when
    the move is too short to reach full speed).

    Args:
        steps: number of step pulses (0 gives an empty profile).
        start_speed_sps: speed at the first and last step, steps per second.
        max_speed_sps: cruising speed, steps per second.
        accel_sps2: acceleration, steps per second squared.

    Returns:
        ``steps`` intervals in seconds.
    """
    if steps <= 0:
        return np.empty(0)
    # Under constant acceleration from v0, step k is reached at t = (sqrt(v0^2 + 2ak) - v0) / a.
    k = np.arange(steps + 1, dtype=np.float64)
    t_s = (np.sqrt(start_speed_sps**2 + 2.0 * accel_sps2 * k) - start_speed_sps) / accel_sps2
    ramp = np.diff(t_s)
    return np.maximum(np.maximum(ramp, ramp[::-1]), 1.0 / max_speed_sps)


def _wait_until(deadline_s: float, clock: Callable[[], float]) -> None:
    """Sleep, then spin, until ``clock()`` reaches ``deadline_s``."""
    remaining = deadline_s - clock()
    if remaining > _SPIN_S:
        time.sleep(remaining - _SPIN_S)
    while clock() < deadline_s:
        pass


@dataclass(frozen=True)
class DriverRun:
    """One driver's part of a move: its direction, step intervals and optional stop test."""

    driver: StepperDriver
    direction: int
    intervals_s: np.ndarray
    stop_when: Callable[[], bool] | None = None


TimedCall = tuple[float, Callable[[], None]]
"""A call made ``offset_s`` after a move's start, on the move's own time line."""


def run_together(
    runs: Sequence[DriverRun],
    clock: Callable[[], float] = time.perf_counter,
    calls: Sequence[TimedCall] = (),
) -> list[int]:
    """Run several drivers at once from one thread; return each run's steps made.

    The pulses of all runs are merged on one time line: each axis keeps its own profile,
    and each pulse waits its planned interval after that axis's previous pulse (a late
    pulse lengthens that axis's move, never shortens its next interval), so two axes
    move together as each would alone. One thread rather than one per axis: two Python
    threads spinning on the clock would take turns with the interpreter lock and make
    both axes' pulses late by milliseconds.

    Args:
        runs: the moves, one per driver (a driver at most once).
        clock: the time source the intervals are measured on.
        calls: ``(offset_s, call)`` pairs, offsets ascending from the moves' start: each
            call is made on the same time line (a turning table's new step rate, say, which
            a second thread would make late); those the moves outlast are made at their end.

    Returns:
        The steps each run made, in the order of ``runs`` (fewer where ``stop_when`` ended it).
    """
    switched = [run.driver._prepare(run.direction) for run in runs]  # every one, in order
    if any(switched):
        _wait_until(clock() + _ENABLE_SETTLE_S, clock)
    intervals = [run.intervals_s.tolist() for run in runs]
    start_s = clock()
    last_s = [start_s] * len(runs)
    next_k = [0] * len(runs)
    live = [i for i, steps in enumerate(intervals) if steps]
    pending = list(calls)
    while live:
        i = min(live, key=lambda j: last_s[j] + intervals[j][next_k[j]])
        due_s = last_s[i] + intervals[i][next_k[i]]
        if pending and start_s + pending[0][0] <= due_s:
            offset_s, call = pending.pop(0)
            _wait_until(start_s + offset_s, clock)
            call()
            continue
        _wait_until(due_s, clock)
        run = runs[i]
        if run.stop_when is not None and run.stop_when():
            live.remove(i)
            continue
        run.driver._pulse()
        # Read after the edge, so the next interval is timed from no earlier than it.
        last_s[i] = clock()
        next_k[i] += 1
        if next_k[i] == len(intervals[i]):
            live.remove(i)
    for _, call in pending:
        call()
    return [run.driver.last_run_steps for run in runs]


class StepperDriver:
    """One step/dir driver: STEP, DIR and EN lines as gpiozero outputs.

    Drivers count STEP edges, so timing jitter from Python changes the speed but
    never the step count. Each pulse waits its planned interval after the previous
    pulse: a late pulse makes the move longer, never the next interval shorter, because
    catching up (a burst of pulses after a stall) would ask the motor for a speed the
    ramp never planned, and a stepper that cannot follow loses steps silently.
    """

    def __init__(
        self,
        config: DriverConfig,
        pin_factory: Factory | None = None,
        clock: Callable[[], float] = time.perf_counter,
    ) -> None:
        self._step = DigitalOutputDevice(
            config.step_pin, initial_value=False, pin_factory=pin_factory
        )
        self._dir = DigitalOutputDevice(
            config.dir_pin, initial_value=False, pin_factory=pin_factory
        )
        self._enable = DigitalOutputDevice(
            config.enable_pin,
            active_high=config.enable_active_high,
            initial_value=False,
            pin_factory=pin_factory,
        )
        self._dir_high_positive = config.dir_high_positive
        self._clock = clock
        self.last_run_steps = 0
        self._pulse_problem: str | None = None

    @property
    def enabled(self) -> bool:
        """Return True while the driver powers the motor."""
        return bool(self._enable.is_active)

    def run(
        self,
        direction: int,
        intervals_s: np.ndarray,
        stop_when: Callable[[], bool] | None = None,
    ) -> int:
        """Step once per interval in ``direction`` (+1 or -1); return the steps made.

        ``stop_when`` is checked before every pulse; the move ends early when it
        returns True. ``last_run_steps`` counts pulses as they go out, so the caller
        knows the position even if the move is interrupted by an exception.
        """
        return run_together([DriverRun(self, direction, intervals_s, stop_when)], self._clock)[0]

    def pulse_train_problem(self) -> str | None:
        """Return why this driver's STEP line cannot be pulsed by the pin factory, or None.

        A continuous turn needs step pulses timed outside Python (lgpio's PWM thread on
        the Pi): a probe at zero duty cycle, which sends no pulse, tells whether the pin
        can. The answer is kept: the pin factory does not change while the device runs.
        """
        if self._pulse_problem is None:
            pin = self._step.pin
            try:
                pin.frequency = 1000.0  # zero duty: no edge goes out
                pin.frequency = None
                self._pulse_problem = ""
            except Exception as exc:  # gpiozero's PinPWMUnsupported and the like
                self._pulse_problem = (
                    f"the STEP pin cannot be pulsed by the pin factory ({type(exc).__name__}): "
                    "a continuous turn needs the lgpio pin factory (GPIOZERO_PIN_FACTORY=lgpio)"
                )
        return self._pulse_problem or None

    def pulse_at(self, rate_sps: float) -> None:
        """Send step pulses at ``rate_sps`` (timed by the pin factory) until told otherwise.

        The caller set the direction and enabled the driver (:meth:`_prepare`); 0 stops.
        """
        pin = self._step.pin
        if rate_sps <= 0:
            pin.frequency = None
            self._step.off()
            return
        pin.frequency = rate_sps
        pin.state = 0.5

    def _prepare(self, direction: int) -> bool:
        """Set DIR for ``direction``; return True if EN had to be switched on first."""
        self.last_run_steps = 0
        switched = not self._enable.is_active
        if switched:
            self._enable.on()
        self._dir.value = (direction > 0) == self._dir_high_positive
        return switched

    def _pulse(self) -> None:
        # Each gpiozero call takes longer than the drivers' minimum pulse (<= 2 us).
        self._step.on()
        self._step.off()
        self.last_run_steps += 1

    def disable(self) -> None:
        """Cut the motor current (the axis may then be turned by hand)."""
        if not self._enable.closed:
            self._enable.off()

    def close(self) -> None:
        """Disable the driver, then release its pins."""
        self.disable()
        for device in (self._enable, self._step, self._dir):
            device.close()


def turntable_steps_per_rev(config: TurntableConfig) -> int:
    """Return the microsteps of one table revolution."""
    return round(config.full_steps_per_rev * config.microsteps * config.gear_ratio)


def lift_steps_per_mm(config: LiftConfig) -> float:
    """Return the lift's microsteps per millimetre of travel."""
    return config.full_steps_per_rev * config.microsteps * config.gear_ratio / config.lead_mm


def turntable_intervals_s(config: TurntableConfig, steps: int) -> np.ndarray:
    """Return the step intervals of a turntable move of ``steps`` microsteps (one direction)."""
    spd = turntable_steps_per_rev(config) / 360.0
    return trapezoid_intervals_s(
        steps,
        config.start_speed_deg_s * spd,
        config.max_speed_deg_s * spd,
        config.accel_deg_s2 * spd,
    )


def lift_intervals_s(config: LiftConfig, steps: int) -> np.ndarray:
    """Return the step intervals of a lift move of ``steps`` microsteps (one direction)."""
    spm = lift_steps_per_mm(config)
    return trapezoid_intervals_s(
        steps, config.start_speed_mm_s * spm, config.max_speed_mm_s * spm, config.accel_mm_s2 * spm
    )


def turntable_runs(
    config: TurntableConfig, position_steps: int, engaged: bool, angle_deg: float
) -> tuple[int, ...]:
    """Return the signed runs of microsteps that take the table to ``angle_deg``.

    The short way round, arriving counter-clockwise: a move that would end clockwise (or
    a first move, with the backlash not yet taken up) overshoots by ``backlash_deg`` and
    comes back. The one rule for both the stepper and the scan-time model.

    Args:
        config: the turntable's configuration.
        position_steps: where the table is, in microsteps since power-up.
        engaged: whether the last move ended counter-clockwise (backlash taken up).
        angle_deg: the target angle.

    Returns:
        The runs in order (an empty tuple when the table is there already).
    """
    rev = turntable_steps_per_rev(config)
    target = round((angle_deg % 360.0) * rev / 360.0) % rev
    delta = (target - position_steps) % rev
    if delta > rev // 2:
        delta -= rev
    backlash = round(config.backlash_deg * rev / 360.0)
    if backlash == 0 or (delta >= 0 and engaged):
        return (delta,) if delta else ()
    return tuple(run for run in (delta - backlash, backlash) if run)


SPIN_TICK_S = 0.01
"""A continuous turn's ramp changes the step rate this often (the pulses between are timed
by the pin factory, so a late change only lengthens that rate's share)."""


def spin_rates(config: TurntableConfig, speed_deg_s: float) -> tuple[list[float], float]:
    """Return a continuous turn's ramp (a rate per :data:`SPIN_TICK_S`) and its cruise rate.

    The ramp starts at ``start_speed_deg_s`` and gains ``accel_deg_s2`` each second, as
    every move of the table does; each rate is a :func:`pulse_rate`.

    Returns:
        The ramp's rates in steps per second (ramp-down: the same, reversed), and the rate
        at ``speed_deg_s``.
    """
    per_deg = turntable_steps_per_rev(config) / 360.0
    cruise = pulse_rate(speed_deg_s * per_deg)
    start = min(config.start_speed_deg_s, speed_deg_s)
    ticks = max(0, math.ceil((speed_deg_s - start) / (config.accel_deg_s2 * SPIN_TICK_S)))
    ramp = [
        pulse_rate((start + config.accel_deg_s2 * SPIN_TICK_S * k) * per_deg) for k in range(ticks)
    ]
    return ramp, cruise


@dataclass(frozen=True)
class Retiming:
    """A turning table's slow-down beside a lift move (:func:`slow_down`).

    The table takes ``rates_sps[i]`` from ``offsets_s[i]`` after the move's start; the last
    rate is the turn's own again, so the table ends ``loss_deg`` behind where it would
    have been, turning as before.
    """

    offsets_s: tuple[float, ...]
    rates_sps: tuple[float, ...]
    loss_deg: float

    @property
    def duration_s(self) -> float:
        """Return when the table is back at its speed, from the move's start."""
        return self.offsets_s[-1]

    def calls(self, set_rate: Callable[[float], None]) -> list[TimedCall]:
        """Return the timed calls that give a table (``set_rate``) each rate at its offset."""
        timeline = zip(self.offsets_s, self.rates_sps, strict=True)
        return [(offset_s, partial(set_rate, rate)) for offset_s, rate in timeline]


def slow_down(
    config: TurntableConfig, speed_deg_s: float, loss_deg: float, within_s: float
) -> Retiming | None:
    """Return the shallowest slow-down that loses ``loss_deg`` within ``within_s``, or None.

    A continuous scan's lift moves between sections while the table turns on; at the
    turn's one speed the table brings the next section's first view round whenever the
    phase says, up to a view's spacing after the lift has settled. Slowing the table a
    little during the move brings a view round as the lift settles instead. The rate
    steps down through the rates the driver sends exactly (:func:`pulse_rate`), each
    step held as long as ``accel_deg_s2`` asks, holds the lowest, and steps back up the
    same way; the hold is timed so that the loss is exact. One step (about 2 deg/s at
    the shipped speed) is less than ``start_speed_deg_s``, which the motor takes from
    standstill.

    Args:
        config: the turntable's configuration.
        speed_deg_s: the turn's speed, to which the table returns.
        loss_deg: how far the table is to fall behind.
        within_s: the time the slow-down may take (the lift's move).

    Returns:
        The rate changes, or None where nothing is to be lost or no slow-down within the
        time (down to half the speed) loses that much: the view is then waited for.
    """
    if not (loss_deg > 0 and within_s > 0 and speed_deg_s > 0):
        return None
    per_deg = turntable_steps_per_rev(config) / 360.0
    cruise = pulse_rate(speed_deg_s * per_deg)
    period_us = round(1e6 / cruise)
    rates, deficits = [cruise], [0.0]
    ramp_loss = ramp_s = 0.0  # of the levels above the lowest, down and up
    for level in range(1, period_us + 1):
        rate = 1e6 / (period_us + level)
        if rate < 0.5 * cruise:
            return None
        deficit = (cruise - rate) / per_deg
        if level > 1:
            # The level above is held as long as the fall to this one takes on the way
            # down, and the rise to the one above it on the way up.
            held_s = (deficit - deficits[-2]) / config.accel_deg_s2
            ramp_loss += deficits[-1] * held_s
            ramp_s += held_s
        rates.append(rate)
        deficits.append(deficit)
        hold_s = (loss_deg - ramp_loss) / deficit
        if hold_s < (deficit - deficits[-2]) / config.accel_deg_s2:
            return None  # this level overshoots even held briefly; the one above took too long
        if ramp_s + hold_s <= within_s:
            return _retiming(rates, deficits, hold_s, config.accel_deg_s2, loss_deg)
    return None


def _retiming(
    rates: list[float], deficits: list[float], hold_s: float, accel: float, loss_deg: float
) -> Retiming:
    """Return the slow-down through ``rates[1:]`` and back to ``rates[0]``.

    Each level is held as long as the next step's change takes at ``accel`` (deg/s^2):
    on the way down the step to the level below, on the way up the step to the level
    above; the lowest level is held ``hold_s``.
    """
    lowest = len(rates) - 1
    down = [(n, (deficits[n + 1] - deficits[n]) / accel) for n in range(1, lowest)]
    up = [(n, (deficits[n] - deficits[n - 1]) / accel) for n in range(lowest - 1, 0, -1)]
    offsets, chosen, at_s = [], [], 0.0
    for n, held_s in [*down, (lowest, hold_s), *up]:
        offsets.append(at_s)
        chosen.append(rates[n])
        at_s += held_s
    offsets.append(at_s)
    chosen.append(rates[0])
    return Retiming(tuple(offsets), tuple(chosen), loss_deg)


class StepClock:
    """Where a turning table is at any moment: the step rates it was given, and when.

    The pulses of a continuous turn are timed by the pin factory, not counted one by one
    in Python, so the position at a time (a frame's exposure, say) is the sum of each
    rate's steps over its share of the time line. Thread-safe: the scan's worker reads it
    while the scan's thread gives new rates.
    """

    def __init__(self, start_ns: int, steps: float) -> None:
        self._lock = threading.Lock()
        self._times_ns = [start_ns]
        self._steps = [float(steps)]
        self._rates = [0.0]

    def set_rate(self, at_ns: int, rate_sps: float) -> None:
        """Note that the step rate became ``rate_sps`` at ``at_ns`` (monotonic, ns)."""
        with self._lock:
            at_ns = max(at_ns, self._times_ns[-1])
            steps = self._steps[-1] + self._rates[-1] * (at_ns - self._times_ns[-1]) * 1e-9
            self._times_ns.append(at_ns)
            self._steps.append(steps)
            self._rates.append(float(rate_sps))

    @property
    def rate_sps(self) -> float:
        """Return the step rate now."""
        return self._rates[-1]

    def steps_at(self, at_ns: int) -> float:
        """Return the (fractional) step count at ``at_ns``; before the first rate, the start."""
        with self._lock:
            k = max(0, bisect.bisect_right(self._times_ns, at_ns) - 1)
            return self._steps[k] + self._rates[k] * max(0, at_ns - self._times_ns[k]) * 1e-9

    def time_at(self, steps: float) -> int:
        """Return when the count reaches ``steps`` at the present rate (ns).

        Raises:
            MotionError: the table is not turning forwards.
        """
        with self._lock:
            rate, since_ns, since = self._rates[-1], self._times_ns[-1], self._steps[-1]
        if rate <= 0:
            raise MotionError("the turntable is not turning: no time reaches that angle")
        return since_ns + round((steps - since) / rate * 1e9)


class TurnLog:
    """A table's continuous turns: the step clock of the one under way, and of the last.

    A finished turn's clock still answers for its own time (the last views of a scan are
    extracted after the table has stopped); after it, the table's position does.
    """

    def __init__(self) -> None:
        self.current: StepClock | None = None
        self.last: StepClock | None = None
        self._last_end_ns = 0

    @property
    def turning(self) -> bool:
        """Return True while a turn is under way."""
        return self.current is not None

    def start(self, at_ns: int, steps: int) -> StepClock:
        """Start a turn from ``steps``; return its (still resting) step clock."""
        self.current = StepClock(at_ns, steps)
        return self.current

    def finish(self, at_ns: int) -> int:
        """End the turn under way at ``at_ns``; return the whole steps it ended on."""
        clock = self.current
        assert clock is not None
        clock.set_rate(at_ns, 0.0)
        self.current, self.last, self._last_end_ns = None, clock, at_ns
        return round(clock.steps_at(at_ns))

    def steps_at(self, at_ns: int, position: int) -> float:
        """Return the step count at ``at_ns``: on the clock of the turn then, else ``position``."""
        if self.current is not None:
            return self.current.steps_at(at_ns)
        if self.last is not None and at_ns <= self._last_end_ns:
            return self.last.steps_at(at_ns)
        return float(position)

    def for_rate(self, rate_sps: float) -> StepClock:
        """Return the clock of the turn under way, to be given the new rate ``rate_sps``.

        Raises:
            MotionError: no turn is under way, or the rate would stop it (stop it instead).
        """
        if self.current is None or rate_sps <= 0:
            raise MotionError("the turntable is not turning: start a continuous turn first")
        return self.current

    def time_at(self, steps: float) -> int:
        """Return when the turn under way reaches ``steps``.

        Raises:
            MotionError: no turn is under way.
        """
        if self.current is None:
            raise MotionError("the turntable is not turning: start a continuous turn first")
        return self.current.time_at(steps)


@runtime_checkable
class SpinningTable(Protocol):
    """A turntable that can also turn at constant speed while frames stream (continuous scans).

    Angles here are the step count's, unwrapped (360 is one turn on from 0): the host
    corrects them for the gear exactly as it does a commanded angle.
    """

    def spin_problem(self) -> str | None:
        """Return why this table cannot turn continuously, or None when it can."""
        ...  # pragma: no cover - protocol

    @property
    def turning(self) -> bool:
        """Return True while a continuous turn is under way."""
        ...  # pragma: no cover - protocol

    @property
    def spin_speed_deg_s(self) -> float:
        """Return the configured speed of a continuous turn."""
        ...  # pragma: no cover - protocol

    @property
    def off_frames(self) -> str:
        """Return where a continuous view's laser-off frames come from (``OFF_FRAMES``)."""
        ...  # pragma: no cover - protocol

    def spin(self, speed_deg_s: float | None = None) -> None:
        """Ramp up counter-clockwise to ``speed_deg_s`` (default: configured); return at speed."""
        ...  # pragma: no cover - protocol

    def stop_spin(self) -> None:
        """Ramp down and stop; the position is kept (a no-op when not turning)."""
        ...  # pragma: no cover - protocol

    def set_rate(self, rate_sps: float) -> None:
        """Turn on at ``rate_sps`` from now (a :class:`Retiming`'s step)."""
        ...  # pragma: no cover - protocol

    def angle_at(self, at_ns: int) -> float:
        """Return the table's angle at monotonic time ``at_ns`` from its step clock."""
        ...  # pragma: no cover - protocol

    def time_at(self, angle_deg: float) -> int:
        """Return when a turning table reaches the unwrapped ``angle_deg`` (monotonic ns)."""
        ...  # pragma: no cover - protocol


class ContinuousTurntable:
    """Base of a turntable that turns without end: it has no angle limits."""

    min_deg: float | None = None
    max_deg: float | None = None


class StepperTurntable(ContinuousTurntable):
    """The turntable on a stepper: position in whole microsteps, reported in degrees.

    Every view is approached counter-clockwise (the positive way): a move that must
    end clockwise overshoots by ``backlash_deg`` and comes back, so gear backlash is
    always taken up the same way. Moves take the short way round.
    """

    def __init__(
        self,
        config: TurntableConfig,
        pin_factory: Factory | None = None,
        clock_ns: Callable[[], int] = time.monotonic_ns,
    ) -> None:
        self.config = config
        self.driver = StepperDriver(config, pin_factory)
        self.steps_per_rev = turntable_steps_per_rev(config)
        self._position = 0
        # Unknown at power-up: the first move takes the backlash up before it arrives.
        self._engaged = False
        self._clock_ns = clock_ns
        self.turns = TurnLog()

    @property
    def steps_per_deg(self) -> float:
        """Return microsteps per table degree."""
        return self.steps_per_rev / 360.0

    @property
    def position_steps(self) -> int:
        """Return the position in microsteps since power-up (not wrapped)."""
        return self._position

    @property
    def angle_deg(self) -> float:
        """Return the table angle in [0, 360)."""
        return (self._position % self.steps_per_rev) / self.steps_per_deg

    @property
    def count_deg(self) -> float:
        """Return the rotation since power-up, unwrapped (the step count in degrees)."""
        return self._position / self.steps_per_deg

    def move_to(self, angle_deg: float) -> None:
        """Rotate to ``angle_deg`` the short way, arriving counter-clockwise."""
        for run in self.runs_to(angle_deg):
            self._move(run)

    # --- continuous turns (SpinningTable) ----------------------------------------------

    @property
    def spin_speed_deg_s(self) -> float:
        """Return ``[turntable] continuous_speed_deg_s``."""
        return self.config.continuous_speed_deg_s

    @property
    def off_frames(self) -> str:
        """Return ``[turntable] continuous_off_frames``."""
        return self.config.continuous_off_frames

    def spin_problem(self) -> str | None:
        """Return why this table cannot turn continuously, or None when it can."""
        if self.config.continuous_speed_deg_s <= 0:
            return (
                "[turntable] continuous_speed_deg_s is 0 in this box's configuration: set the "
                "speed its table and load allow (hardware/README.md, Speeds)"
            )
        return self.driver.pulse_train_problem()

    def spin(self, speed_deg_s: float | None = None) -> None:
        """Ramp up counter-clockwise to ``speed_deg_s``; the pin factory times the pulses.

        Raises:
            MotionError: the table cannot turn continuously (:meth:`spin_problem`).
        """
        if self.turns.turning:
            return
        if problem := self.spin_problem():
            raise MotionError(problem)
        ramp, cruise = spin_rates(self.config, speed_deg_s or self.spin_speed_deg_s)
        if self.driver._prepare(+1):
            time.sleep(_ENABLE_SETTLE_S)
        self.turns.start(self._clock_ns(), self._position)
        self._engaged = True
        self._ramp([*ramp, cruise])

    @property
    def turning(self) -> bool:
        """Return True while a continuous turn is under way."""
        return self.turns.turning

    def _ramp(self, rates: Sequence[float]) -> None:
        """Give the driver each rate in turn, one tick apart, noting each on the step clock."""
        clock = self.turns.current
        assert clock is not None
        next_s = time.monotonic()
        for rate in rates:
            self.driver.pulse_at(rate)
            clock.set_rate(self._clock_ns(), rate)
            next_s += SPIN_TICK_S
            _wait_until(next_s, time.monotonic)

    def set_rate(self, rate_sps: float) -> None:
        """Turn on at ``rate_sps`` (steps/s, positive) from now, noted on the step clock.

        Raises:
            MotionError: the table is not turning.
        """
        clock = self.turns.for_rate(rate_sps)
        self.driver.pulse_at(rate_sps)
        clock.set_rate(self._clock_ns(), rate_sps)

    def stop_spin(self) -> None:
        """Ramp down and stop; the position becomes the step clock's count."""
        clock = self.turns.current
        if clock is None:
            return
        try:
            ramp, _ = spin_rates(self.config, clock.rate_sps / self.steps_per_deg)
            self._ramp(ramp[::-1])
        finally:
            self.driver.pulse_at(0.0)
            self._position = self.turns.finish(self._clock_ns())

    def angle_at(self, at_ns: int) -> float:
        """Return the table's unwrapped angle at ``at_ns`` from its step clock."""
        return self.turns.steps_at(at_ns, self._position) / self.steps_per_deg

    def time_at(self, angle_deg: float) -> int:
        """Return when the turning table reaches the unwrapped ``angle_deg``."""
        return self.turns.time_at(angle_deg * self.steps_per_deg)

    def _move(self, steps: int) -> None:
        if steps:
            self._run_with(steps, None)

    def runs_to(self, angle_deg: float) -> tuple[int, ...]:
        """Return the signed runs of microsteps a move to ``angle_deg`` makes from here."""
        if not math.isfinite(angle_deg):
            raise MotionError(f"turntable angle must be finite, not {angle_deg}")
        if self.turns.turning:
            raise MotionError("the turntable is turning continuously: stop it before a move")
        return turntable_runs(self.config, self._position, self._engaged, angle_deg)

    def _run_with(self, steps: int, other: DriverRun | None) -> list[int]:
        """Turn ``steps`` (non-zero) while ``other`` runs beside it; return both runs' steps.

        The caller owns ``other``'s position; this keeps the table's, even if the move fails.
        """
        direction = 1 if steps > 0 else -1
        run = DriverRun(self.driver, direction, turntable_intervals_s(self.config, abs(steps)))
        runs = [run] if other is None else [run, other]
        try:
            return run_together(runs, self.driver._clock)
        finally:
            self._position += direction * self.driver.last_run_steps
            self._engaged = direction > 0

    def close(self) -> None:
        """Stop any turn, disable the driver and release the pins."""
        if self.turns.turning:
            self.driver.pulse_at(0.0)  # no ramp: the box is closing (a fault, a shutdown)
            self._position = self.turns.finish(self._clock_ns())
        self.driver.close()


class StepperLift:
    """The lift on a lead screw: homes down onto its limit switch, refuses soft-limit breaches.

    The switch is normally closed to ground with the pin pulled up, so a pressed
    switch and a broken wire both read high, i.e. "hit": the lift then stops rather
    than drive into the end of its travel.
    """

    def __init__(self, config: LiftConfig, pin_factory: Factory | None = None) -> None:
        self.config = config
        self.driver = StepperDriver(config, pin_factory)
        self._switch = DigitalInputDevice(config.limit_pin, pull_up=True, pin_factory=pin_factory)
        self.steps_per_mm = lift_steps_per_mm(config)
        self._position = 0
        self._homed = False

    @property
    def step_mm(self) -> float:
        """Return the height of one microstep (the finest section pitch the lift makes)."""
        return 1.0 / self.steps_per_mm

    @property
    def min_mm(self) -> float:
        """Return the lower soft limit, ``[lift] min_mm``."""
        return self.config.min_mm

    @property
    def max_mm(self) -> float:
        """Return the upper soft limit, ``[lift] max_mm``."""
        return self.config.max_mm

    @property
    def homed(self) -> bool:
        """Return True once the position is referenced to the limit switch."""
        return self._homed

    @property
    def position_steps(self) -> int:
        """Return the position in microsteps (0 at z = 0 once homed)."""
        return self._position

    @property
    def z_mm(self) -> float:
        """Return the height in mm."""
        return self._position / self.steps_per_mm

    def switch_hit(self) -> bool:
        """Return True when the limit switch is pressed or its wire is broken."""
        # With pull_up=True gpiozero calls a low pin "active": the closed switch.
        return not self._switch.is_active

    def move_to(self, z_mm: float) -> None:
        """Move to ``z_mm``, homing first if the lift has not been homed.

        Raises:
            MotionError: ``z_mm`` lies outside the soft limits, or the switch trips on the way.
        """
        self.move_with(None, z_mm, 0.0)

    def move_beside(self, z_mm: float, calls: Sequence[TimedCall]) -> None:
        """Move to ``z_mm``, making ``calls`` on the move's time line (:func:`run_together`).

        Raises:
            MotionError: ``z_mm`` lies outside the soft limits, or the switch trips on the way.
        """
        self.move_with(None, z_mm, 0.0, calls)

    def move_with(
        self,
        turntable: Turntable | None,
        z_mm: float,
        angle_deg: float,
        calls: Sequence[TimedCall] = (),
    ) -> None:
        """Move to ``z_mm`` while ``turntable`` (if any) turns to ``angle_deg``, both at once.

        The lift and a stepper table's first run share one pulse time line
        (:func:`run_together`; the table's backlash return, if any, follows), so a
        section change costs the longer of the two moves, not their sum. Another kind
        of table turns after the lift has arrived.

        Raises:
            MotionError: ``z_mm`` lies outside the soft limits, or the switch trips on the way.
        """
        if calls and turntable is not None:
            raise ValueError("timed calls go with a lift move alone (move_beside)")
        low, high = self.min_mm, self.max_mm
        if not (math.isfinite(z_mm) and low <= z_mm <= high):
            raise MotionError(
                f"lift height {z_mm} mm is outside its soft limits {low:g}..{high:g} mm; "
                "choose sections within them or change [lift] min_mm/max_mm in the config"
            )
        if not self._homed:
            log.info("homing the lift before its first move")
            self.home()
        if turntable is not None and not isinstance(turntable, StepperTurntable):
            self.move_with(None, z_mm, angle_deg)
            turntable.move_to(angle_deg)
            return
        steps = round(z_mm * self.steps_per_mm) - self._position
        lift = self._lift_run(steps) if steps else None
        table = turntable.runs_to(angle_deg) if turntable is not None else ()
        done = 0
        if turntable is not None and table:
            try:
                done = turntable._run_with(table[0], lift)[-1]
            finally:
                if lift is not None:
                    self._position += lift.direction * self.driver.last_run_steps
            for run in table[1:]:
                turntable._move(run)
        elif lift is not None:
            done = self._run(lift.direction, lift.intervals_s, lift.stop_when, calls)
        else:
            for _, call in calls:  # no move to time them by: made at its (empty) end
                call()
        if lift is not None and done < abs(steps):
            self._homed = False
            raise MotionError(
                f"the lift hit its limit switch at z={self.z_mm:.2f} mm on the way down: it has "
                "lost steps or the switch wire is broken; it will home again before its next move"
            )

    def _lift_run(self, steps: int) -> DriverRun:
        """Return the run of ``steps`` (non-zero); a move down stops at the switch."""
        direction = 1 if steps > 0 else -1
        stop = self.switch_hit if direction < 0 else None
        return DriverRun(self.driver, direction, lift_intervals_s(self.config, abs(steps)), stop)

    def _run(
        self,
        direction: int,
        intervals: np.ndarray,
        stop_when: Callable[[], bool] | None,
        calls: Sequence[TimedCall] = (),
    ) -> int:
        """Run the driver, keeping the position even if the move is interrupted."""
        run = DriverRun(self.driver, direction, intervals, stop_when)
        try:
            return run_together([run], self.driver._clock, calls)[0]
        finally:
            self._position += direction * self.driver.last_run_steps

    def _creep(self, direction: int, max_mm: float, until_hit: bool) -> bool:
        """Step slowly until the switch reads ``until_hit``; return False if it never did."""
        count = max(1, math.ceil(max_mm * self.steps_per_mm))
        interval_s = 1.0 / (self.config.homing_speed_mm_s * self.steps_per_mm)
        intervals = np.full(count, interval_s)
        self._run(direction, intervals, lambda: self.switch_hit() == until_hit)
        return self.switch_hit() == until_hit

    def home(self) -> None:
        """Creep down onto the limit switch and take its trip point as ``home_mm``.

        Raises:
            MotionError: the switch never trips, or never releases.
        """
        cfg = self.config
        slow_zone_mm = cfg.homing_slow_zone_mm
        if self.switch_hit() and not self._creep(+1, slow_zone_mm + 2.0, until_hit=False):
            # Back off first so the trip point is always reached from above.
            raise MotionError(
                f"the lift's limit switch (GPIO{cfg.limit_pin}) reads hit and does not release: "
                "check the switch and its wire (normally closed to ground)"
            )
        search_mm = cfg.max_mm - cfg.home_mm + slow_zone_mm + 5.0
        if self._homed:
            above_mm = self.z_mm - (cfg.home_mm + slow_zone_mm)
            if above_mm > 0:
                steps = round(above_mm * self.steps_per_mm)
                self._run(-1, lift_intervals_s(self.config, steps), self.switch_hit)
            search_mm = 2.0 * slow_zone_mm + 5.0
        if not self._creep(-1, search_mm, until_hit=True):
            self._homed = False
            raise MotionError(
                f"the lift went {search_mm:g} mm down without reaching its limit switch "
                f"(GPIO{cfg.limit_pin}): check the switch, the motor and its driver wiring"
            )
        self._position = round(cfg.home_mm * self.steps_per_mm)
        self._homed = True

    def close(self) -> None:
        """Disable the driver and release the pins."""
        self.driver.close()
        self._switch.close()


@runtime_checkable
class TimedLift(Protocol):
    """A lift that can make timed calls on its move's time line (a table's new rates)."""

    def move_beside(self, z_mm: float, calls: Sequence[TimedCall]) -> None:
        """Move to ``z_mm``, making each ``(offset_s, call)`` that long after the start."""
        ...  # pragma: no cover - protocol


@runtime_checkable
class JointLift(Protocol):
    """A lift that can move while a turntable turns (both axes at once)."""

    def move_with(self, turntable: Turntable | None, z_mm: float, angle_deg: float) -> None:
        """Move to ``z_mm`` while ``turntable`` (if any) turns to ``angle_deg``."""
        ...  # pragma: no cover - protocol


def move_axes(lift: Lift, turntable: Turntable, z_mm: float, angle_deg: float) -> None:
    """Take the lift to ``z_mm`` and the turntable to ``angle_deg``, together where they can.

    A :class:`JointLift` (the box's stepper lift, the simulator's) moves beside the
    table; any other lift first, then the table.

    Raises:
        MotionError: a height outside the lift's soft limits, an angle that is not finite,
            or the lift's switch tripping on the way.
    """
    if isinstance(lift, JointLift):
        lift.move_with(turntable, z_mm, angle_deg)
    else:
        lift.move_to(z_mm)
        turntable.move_to(angle_deg)
