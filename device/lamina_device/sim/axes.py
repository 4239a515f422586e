"""Simulated motion axes: a turntable and a lift that land where real mechanics would.

They answer :class:`lamina_device.motion.Turntable` and :class:`~lamina_device.motion.Lift`
like the stepper axes, but move without waiting: each move advances the simulator's
virtual clock (:class:`SimClock`) by the time the box's steppers would take (the shipped
configuration's profiles, :mod:`lamina_device.timing`), so a simulated scan knows how long
it kept the patient still in no time at all. They carry a mechanical error model, so the
simulated scanner puts objects where real mechanics would, not where they were asked
to go: a gear-ratio error (the thesis measured about 0.2 degrees undershoot per 45
degree step, section 8.3), a once-per-revolution runout, and a small repeatable jitter
per position. :meth:`Mechanics.harsh` adds an eccentric gear: a once-per-turn angle
error of 0.15 degrees that no angle scale can absorb.
"""

from __future__ import annotations

import hashlib
import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace

from lamina_device.camera import Stage
from lamina_device.config import DeviceConfig, TurntableConfig, load_config
from lamina_device.motion import (
    SPIN_TICK_S,
    ContinuousTurntable,
    MotionError,
    TimedCall,
    TurnLog,
    Turntable,
    lift_steps_per_mm,
    spin_rates,
    turntable_steps_per_rev,
)
from lamina_device.timing import frame_wait_s, lift_move_s, turntable_move_s
from lamina_shared.presets import make_preset

__all__ = [
    "MAX_LIFT_ERROR_PERCENT",
    "SIM_LIFT_TRAVEL_MM",
    "Mechanics",
    "SimClock",
    "SimLift",
    "SimTurntable",
]

SIM_LIFT_TRAVEL_MM = 200.0
"""The simulated lift's travel above its home (z = 0)."""

MAX_LIFT_ERROR_PERCENT = 5.0
"""Largest lift scale error the simulator takes (``--lift-error``)."""


@dataclass
class SimClock:
    """The simulator's virtual time: moves, settles and frames advance it, nothing waits.

    Its rates are the shipped configuration's (the box the simulator stands in for).
    """

    config: DeviceConfig = field(default_factory=load_config)
    now_s: float = 0.0

    def advance(self, seconds: float) -> None:
        """Let ``seconds`` pass."""
        self.now_s += seconds

    def now_ns(self) -> int:
        """Return the virtual time in nanoseconds (what CLOCK_MONOTONIC is on the box)."""
        return round(self.now_s * 1e9)

    def sleep_until_ns(self, at_ns: int) -> None:
        """Let the time pass until ``at_ns`` (nothing if it has passed)."""
        self.advance(max(0.0, (at_ns - self.now_ns()) * 1e-9))

    def frame(self, exposure_us: float) -> None:
        """Let the wait for one fresh frame at ``exposure_us`` pass."""
        self.advance(frame_wait_s(self.config.camera.frame_duration_us, exposure_us))

    @property
    def settle_s(self) -> float:
        """Return the settle after a move (the longer of the two axes')."""
        return max(self.config.turntable.settle_s, self.config.lift.settle_s)


def _repeatable_unit_noise(*key: float) -> float:
    """Return a repeatable number in [-1, 1) derived from ``key`` (not from call order)."""
    digest = hashlib.blake2b(struct.pack(f"<{len(key)}d", *key), digest_size=8).digest()
    return int.from_bytes(digest, "little") / 2**63 - 1.0


@dataclass(frozen=True)
class Mechanics:
    """Error model of the simulated axes; :meth:`ideal` has none."""

    angle_scale_error: float = -0.2 / 45.0
    """Relative turntable undershoot: 0.2 degrees short per 45 degrees (thesis 8.3)."""
    angle_runout_deg: float = 0.02
    """Amplitude of the once-per-turn angle error, ``runout * sin(commanded)``."""
    angle_jitter_deg: float = 0.01
    """Largest repeatable angle noise of one commanded position."""
    lift_scale_error: float = 0.002
    """Relative lift travel error (0.2 % too far)."""
    lift_jitter_mm: float = 0.005
    """Largest repeatable height noise of one commanded height."""
    angle_eccentric_deg: float = 0.0
    """Amplitude of an off-centre gear's error, ``eccentric * sin(commanded + phase)``."""
    angle_eccentric_phase_deg: float = 0.0
    """Phase of the off-centre gear's error."""
    angle_error_accumulates: bool = True
    """True (the default): the table's error is a function of its whole rotation since
    power-up (the box's step count, turned the short way as the box turns), so the
    undershoot grows by one turn's worth (1.6 degrees at the thesis's 0.2 per 45) each
    time a scan turns on through a whole turn, as a table's does that turns short of its
    count with no index to re-reference it (the thesis's motor: its sections came out
    under-rotated and the object skewed, 8.3; a ``gear_ratio`` that does not match the
    pulleys). The device sends each view's whole turns and the host corrects over them.
    False: the error starts again at each commanded 0, as no real table's does; kept to
    measure what a host that corrects within the turn only would make of it."""

    @classmethod
    def ideal(cls) -> Mechanics:
        """Return perfect mechanics (for tests that isolate other error sources)."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0)

    @classmethod
    def harsh(cls) -> Mechanics:
        """Return the thesis mechanics plus a 0.15 degree eccentric gear error (phase 40 deg).

        The undershoot per step (a scale error the host's angle correction can fit), the
        runout and the jitter stay as measured in the thesis (8.3); the eccentric term is
        mid-range of the 0.1-0.2 degrees a cheap printed or cast gear shows. Its phase
        makes the error non-zero at the home angle, so the host's frame starts turned.
        """
        return cls(angle_eccentric_deg=0.15, angle_eccentric_phase_deg=40.0)

    @classmethod
    def preset(cls, noise: str) -> Mechanics:
        """Return the mechanics that go with a noise preset (``thesis``, ``harsh``, ``wide``,
        ``none``)."""
        makers: dict[str, Callable[[], Mechanics]] = {
            "thesis": cls,
            "harsh": cls.harsh,
            "wide": cls.harsh,
            "none": cls.ideal,
        }
        return make_preset("noise", noise, makers)

    def on_box(self, table: TurntableConfig, pulley_ratio: float) -> Mechanics:
        """Return these mechanics on a box whose configuration says ``table``.

        The simulated table's pulleys turn it once per ``pulley_ratio`` motor turns (the
        shipped configuration's ``gear_ratio``), and ``angle_scale_error`` is its shortfall
        with that ratio configured. A box configured with another ratio counts a degree
        in another number of steps, so its table turns (configured steps / pulley steps)
        times as far per degree of its count: a ratio multiplied by the factor the host's
        calibration names (``lamina_host.reconstruct.axis.gear_ratio_factor``) takes the
        shortfall out, as it would on a real box. The shipped ratio changes nothing.

        Args:
            table: the box's turntable configuration.
            pulley_ratio: motor turns per table turn of the simulated pulleys.

        Returns:
            The mechanics with the configured ratio's scale error (``self`` when none).
        """
        pulley_steps = table.full_steps_per_rev * table.microsteps * pulley_ratio
        factor = turntable_steps_per_rev(table) / pulley_steps
        if factor == 1.0:
            return self
        return replace(self, angle_scale_error=(1.0 + self.angle_scale_error) * factor - 1.0)

    def with_lift_error(self, percent: float) -> Mechanics:
        """Return these mechanics with the lift running ``percent`` % long (negative: short).

        Raises:
            ValueError: a value that is not a finite number within
                +-:data:`MAX_LIFT_ERROR_PERCENT`.
        """
        if not (math.isfinite(percent) and abs(percent) <= MAX_LIFT_ERROR_PERCENT):
            raise ValueError(
                f"lift error {percent} % must be a number within +-{MAX_LIFT_ERROR_PERCENT:g} % "
                "(a leadscrew's pitch error is a fraction of a percent)"
            )
        return replace(self, lift_scale_error=percent / 100.0)

    def true_angle_deg(self, commanded_deg: float) -> float:
        """Return where the turntable really is when told ``commanded_deg``."""
        runout = self.angle_runout_deg * math.sin(math.radians(commanded_deg))
        jitter = self.angle_jitter_deg * _repeatable_unit_noise(1.0, commanded_deg)
        angle = commanded_deg * (1.0 + self.angle_scale_error) + runout + jitter
        if self.angle_eccentric_deg:
            phase = math.radians(commanded_deg + self.angle_eccentric_phase_deg)
            angle += self.angle_eccentric_deg * math.sin(phase)
        return angle

    def true_z_mm(self, commanded_mm: float) -> float:
        """Return where the lift really is when told ``commanded_mm``."""
        jitter = self.lift_jitter_mm * _repeatable_unit_noise(2.0, commanded_mm)
        return commanded_mm * (1.0 + self.lift_scale_error) + jitter if commanded_mm else jitter


class SimTurntable(ContinuousTurntable):
    """A simulated continuous turntable: instant moves, real positions from :class:`Mechanics`.

    It turns continuously as the box's stepper does (:class:`~lamina_device.motion.SpinningTable`):
    the same ramp, the step rates noted on a step clock against the virtual time.
    """

    def __init__(
        self, mechanics: Mechanics, clock: SimClock | None = None, stage: Stage | None = None
    ) -> None:
        self.mechanics = mechanics
        self.clock = clock if clock is not None else SimClock()
        self.stage = stage
        self._angle_deg = 0.0
        self._steps = 0  # where the box's stepper would be, for the move's duration
        self._engaged = False
        self.turns = TurnLog()

    @property
    def steps_per_deg(self) -> float:
        """Return the box's microsteps per table degree."""
        return turntable_steps_per_rev(self.clock.config.turntable) / 360.0

    @property
    def spin_speed_deg_s(self) -> float:
        """Return the shipped configuration's continuous speed."""
        return self.clock.config.turntable.continuous_speed_deg_s

    @property
    def off_frames(self) -> str:
        """Return the configuration's ``continuous_off_frames``."""
        return self.clock.config.turntable.continuous_off_frames

    def spin_problem(self) -> str | None:
        """Return why the simulated table cannot turn continuously (its config says 0)."""
        if self.spin_speed_deg_s <= 0:
            return "the simulated box's configuration sets no continuous_speed_deg_s"
        return None

    def spin(self, speed_deg_s: float | None = None) -> None:
        """Ramp up to ``speed_deg_s`` as the box's stepper would, on the virtual clock."""
        if self.turns.turning:
            return
        if problem := self.spin_problem():
            raise MotionError(problem)
        ramp, cruise = spin_rates(self.clock.config.turntable, speed_deg_s or self.spin_speed_deg_s)
        self.turns.start(self.clock.now_ns(), self._steps)
        self._engaged = True
        self._ramp([*ramp, cruise])

    @property
    def turning(self) -> bool:
        """Return True while a continuous turn is under way."""
        return self.turns.turning

    def _ramp(self, rates: list[float]) -> None:
        clock = self.turns.current
        assert clock is not None
        for rate in rates:
            clock.set_rate(self.clock.now_ns(), rate)
            self.clock.advance(SPIN_TICK_S)

    def set_rate(self, rate_sps: float) -> None:
        """Turn on at ``rate_sps`` (steps/s, positive) from the virtual now.

        Raises:
            MotionError: the table is not turning.
        """
        self.turns.for_rate(rate_sps).set_rate(self.clock.now_ns(), rate_sps)

    def stop_spin(self) -> None:
        """Ramp down and stop; the commanded angle becomes where the step count ended."""
        clock = self.turns.current
        if clock is None:
            return
        ramp, _ = spin_rates(self.clock.config.turntable, clock.rate_sps / self.steps_per_deg)
        self._ramp(ramp[::-1])
        self._steps = self.turns.finish(self.clock.now_ns())
        self._angle_deg = (self._steps / self.steps_per_deg) % 360.0

    def angle_at(self, at_ns: int) -> float:
        """Return the commanded (step count) angle at ``at_ns``, unwrapped."""
        return self.turns.steps_at(at_ns, self._steps) / self.steps_per_deg

    def time_at(self, angle_deg: float) -> int:
        """Return when the turning table reaches the unwrapped ``angle_deg`` (virtual ns)."""
        return self.turns.time_at(angle_deg * self.steps_per_deg)

    def true_angle_near(self, at_ns: int, reference_deg: float) -> float:
        """Return the true angle at ``at_ns`` of a table turning past ``reference_deg``.

        The mechanics map a commanded angle within one turn (the count modulo 360, as a
        view's angle is reported and corrected by the host) to the true one, so the error
        model jumps where the count passes a whole turn. A band of a frame's rows is
        rendered about its own reference angle, the error there plus the turn since
        scaled as the gear scales it: the object turns smoothly through each band's blur,
        and each band sits on the side of the jump its own count says. A gear whose error
        accumulates (:attr:`Mechanics.angle_error_accumulates`) has no jump: the count since
        power-up gives the angle.
        """
        if self.mechanics.angle_error_accumulates:
            return self._object_angle_deg(self.angle_at(at_ns))
        turned = self.angle_at(at_ns) - reference_deg
        base = self.mechanics.true_angle_deg(reference_deg % 360.0)
        return base + turned * (1.0 + self.mechanics.angle_scale_error)

    @property
    def angle_deg(self) -> float:
        """Return the commanded angle."""
        return self._angle_deg

    @property
    def true_angle_deg(self) -> float:
        """Return the angle the object is really at."""
        if self.mechanics.angle_error_accumulates:
            return self._object_angle_deg(self.count_deg)
        return self.mechanics.true_angle_deg(self._angle_deg)

    def _object_angle_deg(self, count_deg: float) -> float:
        """Return the angle the object on the stage is really at when the count is
        ``count_deg``: the gear's error over the turns since the object was put on, its
        frame starting at the whole turn nearest that count (the turns of shortfall the
        table gathered before only set where the table stood). The whole turns before it
        are left out (a turn changes nothing), so a scan renders the same frames however
        long the device has run."""
        placed = self.stage.placed_count_deg if self.stage is not None else 0.0
        origin_deg = 360.0 * round(placed / 360.0)
        return self.mechanics.true_angle_deg(count_deg - origin_deg)

    @property
    def count_deg(self) -> float:
        """Return the commanded rotation since power-up, unwrapped: the box's step count,
        turned the short way as the box turns (between continuous turns)."""
        return self._steps / self.steps_per_deg

    def move_to(self, angle_deg: float) -> None:
        """Rotate to ``angle_deg``."""
        first_s, rest_s = self.plan_move(angle_deg)
        self.clock.advance(first_s + rest_s)
        self._angle_deg = angle_deg

    def plan_move(self, angle_deg: float) -> tuple[float, float]:
        """Take the move to ``angle_deg`` as the box would; return its runs' durations (s).

        Returns:
            The first run's duration and the rest's (a backlash return).
        """
        if not math.isfinite(angle_deg):
            raise MotionError(f"turntable angle must be finite, not {angle_deg}")
        if self.turns.turning:
            raise MotionError("the turntable is turning continuously: stop it before a move")
        runs, first_s, rest_s = turntable_move_s(
            self.clock.config.turntable, self._steps, self._engaged, angle_deg
        )
        if runs:
            self._steps += sum(runs)
            self._engaged = runs[-1] > 0
        return first_s, rest_s

    def close(self) -> None:
        """Stop turning (nothing else to release)."""
        if self.turns.turning:
            self._steps = self.turns.finish(self.clock.now_ns())


class SimLift:
    """A simulated lift between soft limits ``0..travel_mm``."""

    def __init__(
        self,
        mechanics: Mechanics,
        travel_mm: float = SIM_LIFT_TRAVEL_MM,
        clock: SimClock | None = None,
    ) -> None:
        self.mechanics = mechanics
        self.travel_mm = travel_mm
        self.clock = clock if clock is not None else SimClock()
        self._z_mm = 0.0

    @property
    def z_mm(self) -> float:
        """Return the commanded height."""
        return self._z_mm

    @property
    def min_mm(self) -> float:
        """Return the lower soft limit: home, z = 0."""
        return 0.0

    @property
    def max_mm(self) -> float:
        """Return the upper soft limit: the travel."""
        return self.travel_mm

    @property
    def true_z_mm(self) -> float:
        """Return the height the laser plane is really at."""
        return self.mechanics.true_z_mm(self._z_mm)

    def _travel(self, z_mm: float) -> float:
        """Go to ``z_mm`` (refusing heights outside ``0..travel_mm``); return the move's s."""
        if not (math.isfinite(z_mm) and self.min_mm <= z_mm <= self.max_mm):
            raise MotionError(
                f"lift height {z_mm} mm is outside {self.min_mm:g}..{self.max_mm:g} mm; "
                "choose sections within the simulated lift's travel"
            )
        config = self.clock.config.lift
        steps_per_mm = lift_steps_per_mm(config)
        duration_s = lift_move_s(
            config, round(self._z_mm * steps_per_mm), round(z_mm * steps_per_mm)
        )
        self._z_mm = z_mm
        return duration_s

    def move_to(self, z_mm: float) -> None:
        """Move to ``z_mm``; refuse heights outside ``0..travel_mm``."""
        self.clock.advance(self._travel(z_mm))

    def move_beside(self, z_mm: float, calls: Sequence[TimedCall]) -> None:
        """Move to ``z_mm``, making each ``(offset_s, call)`` that long after the start on
        the virtual clock (those the move outlasts at its end), as the box's lift does."""
        duration_s = self._travel(z_mm)
        elapsed_s = 0.0
        for offset_s, call in calls:
            at_s = min(offset_s, duration_s)
            if at_s > elapsed_s:
                self.clock.advance(at_s - elapsed_s)
                elapsed_s = at_s
            call()
        self.clock.advance(duration_s - elapsed_s)

    def move_with(self, turntable: Turntable | None, z_mm: float, angle_deg: float) -> None:
        """Move to ``z_mm`` while a simulated ``turntable`` turns: the longer move counts."""
        if not isinstance(turntable, SimTurntable):
            self.move_to(z_mm)
            if turntable is not None:
                turntable.move_to(angle_deg)
            return
        lift_s = self._travel(z_mm)
        first_s, rest_s = turntable.plan_move(angle_deg)
        turntable._angle_deg = angle_deg
        self.clock.advance(max(lift_s, first_s) + rest_s)

    def home(self) -> None:
        """Return to z = 0."""
        self.move_to(0.0)

    def close(self) -> None:
        """Nothing to release."""
