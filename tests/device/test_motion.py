"""Stepper axes under gpiozero's MockFactory: exact pin histories, timing, homing, refusals."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from gpiozero.pins.mock import MockFactory

from lamina_device.motion import (
    MotionError,
    StepperLift,
    StepperTurntable,
    trapezoid_intervals_s,
)


def levels(pin) -> list[bool]:
    return [bool(s.state) for s in pin.states]


def test_trapezoid_accelerates_cruises_and_decelerates_symmetrically():
    intervals = trapezoid_intervals_s(400, 100.0, 1000.0, 20_000.0)
    assert len(intervals) == 400
    # Ramp: (1000^2 - 100^2) / (2 * 20000) = 24.75 steps to full speed.
    assert intervals[0] == pytest.approx((math.sqrt(100**2 + 2 * 20_000) - 100) / 20_000)
    assert np.all(np.diff(intervals[:25]) < 0)
    assert np.allclose(intervals[30:370], 1e-3)
    np.testing.assert_allclose(intervals, intervals[::-1])
    # The ramp reaches cruise at the planned step: speed v after k steps is sqrt(v0^2 + 2ak).
    assert 1.0 / intervals[23] < 1000.0 <= 1.0 / intervals[25] + 1e-9


def test_short_move_is_a_triangle_and_zero_steps_is_empty():
    intervals = trapezoid_intervals_s(10, 100.0, 1000.0, 20_000.0)
    assert np.all(intervals > 1e-3)
    assert np.argmin(intervals) in (4, 5)
    assert trapezoid_intervals_s(0, 100.0, 1000.0, 20_000.0).size == 0


@pytest.fixture
def turntable(pi_kit):
    factory = MockFactory()
    table = StepperTurntable(pi_kit.config.turntable, factory)
    cfg = pi_kit.config.turntable
    pins = (factory.pin(cfg.step_pin), factory.pin(cfg.dir_pin), factory.pin(cfg.enable_pin))
    yield table, pins
    table.close()


def test_turntable_counts_steps_and_takes_up_backlash_counter_clockwise(turntable):
    table, (step, direction, enable) = turntable
    assert table.steps_per_rev == 400  # 200 full steps x 2 microsteps x gear 1
    assert enable.state is True  # EN is active low: the driver starts disabled
    # First move: the gear state is unknown, so go 5 steps (4.5 deg) short and approach.
    table.move_to(90.0)
    assert table.position_steps == 100 and table.angle_deg == 90.0
    edges = [s for s in levels(step)]
    assert edges.count(True) == 95 + 5
    assert levels(direction) == [False, True]  # 95 steps with DIR high, no reversal needed
    assert levels(enable)[-2:] == [True, False]
    step.clear_states()
    direction.clear_states()
    # Forward moves go straight; a move back overshoots and returns.
    table.move_to(135.0)
    assert levels(step).count(True) == 50 and levels(direction) == [True]
    step.clear_states()
    table.move_to(90.0)
    assert levels(step).count(True) == 50 + 5 + 5
    assert levels(direction) == [True, False, True]
    assert table.angle_deg == 90.0


def test_turntable_returns_the_short_way(turntable):
    table, (step, direction, _) = turntable
    for angle in (0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0):
        table.move_to(angle)
    step.clear_states()
    direction.clear_states()
    table.move_to(0.0)  # 45 degrees on, not 315 back
    assert levels(step).count(True) == 50
    assert levels(direction) == [True]
    assert table.angle_deg == 0.0 and table.position_steps == 400


@pytest.mark.wall_clock
def test_turntable_step_timing_follows_the_ramp(turntable, pi_kit):
    table, (step, _, _) = turntable
    table.move_to(0.0)  # take up backlash first
    step.clear_states()
    table.move_to(180.0)  # 200 steps: 100 -> 1000 steps/s and back
    rises = pi_kit.change_times_s(step)[np.array(levels(step))]
    measured = np.diff(rises)
    spd = table.steps_per_deg  # 400 steps per turn: 90 deg/s is 100 steps/s
    planned = trapezoid_intervals_s(200, 90.0 * spd, 900.0 * spd, 20_000.0 * spd)[1:]
    assert len(measured) == len(planned) == 199
    # Intervals shrink over the first steps and grow over the last ones.
    # Tolerances allow for a busy machine: Python's sleep runs late, never early.
    cruise_s = np.median(measured[50:150])
    assert cruise_s == pytest.approx(1e-3, rel=0.2)
    assert measured[:3].mean() > 1.5 * cruise_s and measured[-3:].mean() > 1.5 * cruise_s
    # Medians of successive blocks: robust against the odd late pulse.
    ramp_up = [np.median(measured[i : i + 8]) for i in (0, 8)]
    ramp_down = [np.median(measured[::-1][i : i + 8]) for i in (0, 8)]
    assert ramp_up[0] > ramp_up[1] > cruise_s and ramp_down[0] > ramp_down[1] > cruise_s
    # No interval is shorter than planned: a late pulse is never made up by a burst,
    # which a real motor could not follow (steps lost).
    assert (measured >= planned).all(), np.flatnonzero(measured < planned)
    assert rises[-1] - rises[0] >= planned.sum() - 5e-3


def test_turntable_refuses_non_finite_angles(turntable):
    table, (step, _, _) = turntable
    with pytest.raises(MotionError, match="finite"):
        table.move_to(float("nan"))
    assert levels(step) == [False]


@pytest.fixture
def lift_rig(pi_kit):
    factory = MockFactory()
    cfg = pi_kit.config.lift
    carriage = pi_kit.LiftCarriage(factory, cfg, start_steps=250)
    lift = StepperLift(cfg, factory)
    yield lift, carriage, factory
    lift.close()


def test_lift_homes_down_onto_its_switch_then_moves_in_whole_steps(lift_rig):
    lift, carriage, _ = lift_rig
    assert lift.steps_per_mm == 100.0 and not lift.homed
    assert not lift.switch_hit()
    lift.home()
    # 250 steps down to the trip point, where the switch opens and the pin reads high.
    assert carriage.position_steps == 0 and lift.switch_hit()
    assert levels(carriage.step_pin).count(True) == 250
    assert levels(carriage.dir_pin) == [False]  # down throughout (DIR high is up)
    assert levels(carriage.switch_pin)[-1] is True
    assert lift.homed and lift.z_mm == -1.0  # home_mm: the switch trips 1 mm below z = 0
    carriage.step_pin.clear_states()
    lift.move_to(2.5)
    assert levels(carriage.step_pin).count(True) == 350
    assert carriage.position_steps == 350 and lift.z_mm == 2.5
    assert levels(carriage.dir_pin) == [False, True]


def test_first_move_homes_and_rehoming_backs_off_then_creeps(lift_rig):
    lift, carriage, _ = lift_rig
    lift.move_to(0.0)
    assert lift.homed and carriage.position_steps == 100
    lift.move_to(10.0)
    carriage.step_pin.clear_states()
    carriage.dir_pin.clear_states()
    lift.home()
    # Fast down to the slow zone (1 mm above home), then creep onto the switch.
    assert levels(carriage.step_pin).count(True) == 1100
    assert carriage.position_steps == 0 and lift.z_mm == -1.0
    carriage.step_pin.clear_states()
    carriage.dir_pin.clear_states()
    lift.home()  # already on the switch: back off until it closes, then creep down again
    assert levels(carriage.dir_pin) == [False, True, False]
    assert levels(carriage.step_pin).count(True) == 2
    assert carriage.position_steps == 0


def test_lift_refuses_moves_outside_its_soft_limits(lift_rig):
    lift, carriage, _ = lift_rig
    lift.home()
    carriage.step_pin.clear_states()
    for z_mm in (-0.5, 20.01, float("inf")):
        with pytest.raises(MotionError, match=r"outside its soft limits 0\.\.20 mm"):
            lift.move_to(z_mm)
    assert levels(carriage.step_pin) == [False]
    assert lift.z_mm == -1.0


def test_lift_stops_when_its_switch_trips_during_a_move(lift_rig):
    lift, carriage, _ = lift_rig
    lift.move_to(5.0)
    carriage.position_steps -= 300  # the carriage slipped 3 mm: the switch is nearer
    carriage.step_pin.clear_states()
    with pytest.raises(MotionError, match="hit its limit switch"):
        lift.move_to(0.0)
    assert levels(carriage.step_pin).count(True) == 300
    assert not lift.homed


def test_homing_fails_cleanly_without_a_switch_signal(pi_kit):
    factory = MockFactory()
    cfg = replace(pi_kit.config.lift, max_mm=2.0)
    carriage = pi_kit.LiftCarriage(factory, cfg, start_steps=10**6)  # never reaches it
    lift = StepperLift(cfg, factory)
    with pytest.raises(MotionError, match="without reaching its limit switch"):
        lift.home()
    # The search covers the whole travel plus margins: 2 + 1 + 1 + 5 mm at 100 steps/mm.
    assert levels(carriage.step_pin).count(True) == 900
    carriage.connected = False  # a broken wire reads as "hit" and never releases
    carriage.switch_pin.follow()
    carriage.step_pin.clear_states()
    with pytest.raises(MotionError, match="does not release"):
        lift.home()
    assert levels(carriage.step_pin).count(True) == 300
    lift.close()
