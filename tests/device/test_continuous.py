"""Continuous scans (issue 22): the step clock, the turning stepper, the streaming loop, its time.

The stepper turns on pulses the pin factory times (gpiozero's MockPWMPin records the rates
it was given); the simulator takes the same loop on its virtual clock, its frames rendered
with the rolling shutter and the motion of each exposure, on a small camera so that each
test takes seconds.
"""

from __future__ import annotations

import threading
import time
from dataclasses import replace
from functools import partial

import numpy as np
import pytest
from gpiozero.pins.mock import MockFactory, MockPWMPin
from hypothesis import given, settings
from hypothesis import strategies as st

import lamina_device.timing as timing
from lamina_device.acquisition import (
    ScanAborted,
    ScanControl,
    acquire,
    capture_lit,
    capture_moving,
    capture_next_turn,
    continuous_problem,
)
from lamina_device.camera import CameraError
from lamina_device.config import load_config
from lamina_device.motion import (
    SPIN_TICK_S,
    MotionError,
    Retiming,
    StepClock,
    StepperLift,
    StepperTurntable,
    slow_down,
    spin_rates,
    turntable_steps_per_rev,
)
from lamina_device.operations import scan_modes
from lamina_device.room_light import combine_off_frames, laser_off_reference
from lamina_device.safety import DUTY_WINDOWS, LaserWatchdog
from lamina_device.sim import Rig, open_sim
from lamina_device.sim.render import Exposure
from lamina_device.timing import (
    ARRIVE_EARLY_S,
    config_frame_timing,
    estimate_scan_time,
    laser_pulse,
    next_view,
    section_retiming,
    view_capture_s,
)
from lamina_shared.types import SCAN_MODES, ScanPlan
from tests.helpers.campaign import CampaignPlan


def tiny_limb_rig() -> Rig:
    """Return the limb rig's camera binned 16x (96 x 54 px): the same geometry, fast frames."""
    rig = Rig.limb()
    return replace(rig, image_size=(96, 54), focal_px=rig.focal_px / 16.0)


def tiny_sim(object_spec: str = "cylinder:d=60", **options):
    """Return the simulated limb rig on the tiny camera, its watchdog as the box's."""
    return open_sim(object_spec, 0, "none", "limb", tiny_limb_rig(), **options)


# --- the step clock and the turning stepper ------------------------------------------------


def test_the_step_clock_counts_each_rate_over_its_share_of_the_time():
    clock = StepClock(start_ns=1_000_000_000, steps=100)
    clock.set_rate(2_000_000_000, 400.0)  # at rest for the first second
    clock.set_rate(2_500_000_000, 800.0)
    assert clock.steps_at(0) == 100.0  # before the clock started: where it stood
    assert clock.steps_at(1_500_000_000) == 100.0
    assert clock.steps_at(2_250_000_000) == pytest.approx(200.0)
    assert clock.steps_at(3_000_000_000) == pytest.approx(300.0 + 400.0)
    assert clock.time_at(700.0 + 80.0) == 3_100_000_000
    clock.set_rate(3_000_000_000, 0.0)
    with pytest.raises(MotionError, match="not turning"):
        clock.time_at(800.0)


def test_a_continuous_turn_ramps_on_whole_microsecond_periods_at_the_tables_acceleration():
    table = load_config().turntable
    ramp, cruise = spin_rates(table, table.continuous_speed_deg_s)
    per_deg = 200 * table.microsteps * table.gear_ratio / 360.0
    for rate in [*ramp, cruise]:
        assert 1e6 / rate == pytest.approx(round(1e6 / rate), abs=1e-6)
    assert cruise == pytest.approx(360.0 * per_deg, rel=2e-3)  # 6400 steps/s, 156 us
    # Each tick gains the table's acceleration; near the top whole microseconds round two
    # ticks' rates to one period now and then, so a tick may gain nothing and the next two.
    gains = np.diff(ramp) / per_deg
    nominal = table.accel_deg_s2 * SPIN_TICK_S
    assert gains.mean() == pytest.approx(nominal, rel=0.02)
    assert gains.min() >= 0.0 and gains.max() <= 2.5 * nominal
    assert ramp[0] == pytest.approx(table.start_speed_deg_s * per_deg, rel=0.01)


def lost_deg(retiming: Retiming, per_deg: float) -> float:
    """Return the degrees a table turning at the retiming's last rate loses to its rates."""
    cruise = retiming.rates_sps[-1]
    held = np.diff(retiming.offsets_s)
    return float(((cruise - np.array(retiming.rates_sps[:-1])) * held).sum() / per_deg)


@settings(max_examples=60, deadline=None)
@given(
    loss_deg=st.floats(0.01, 44.0), within_s=st.floats(0.05, 2.0), speed=st.sampled_from([90, 360])
)
def test_a_slow_down_loses_what_it_is_asked_within_its_time_at_the_tables_acceleration(
    loss_deg, within_s, speed
):
    table = load_config().turntable
    per_deg = turntable_steps_per_rev(table) / 360.0
    _, cruise = spin_rates(table, speed)
    retiming = slow_down(table, speed, loss_deg, within_s)
    deepest = 0.25 * table.accel_deg_s2 * within_s**2  # a triangle down and up at full accel
    first_step = (cruise - 1e6 / (round(1e6 / cruise) + 1)) / per_deg  # the smallest dip
    if retiming is None:
        # Refused only near what the time allows, or below what one step down and up loses.
        assert loss_deg > 0.5 * deepest or loss_deg < first_step**2 / table.accel_deg_s2
        return
    assert lost_deg(retiming, per_deg) == pytest.approx(loss_deg, rel=1e-9)
    assert retiming.loss_deg == loss_deg
    assert retiming.offsets_s[0] == 0.0 and retiming.duration_s <= within_s + 1e-12
    assert retiming.rates_sps[-1] == cruise  # back at the turn's speed
    rates = np.array(retiming.rates_sps)
    periods_us = 1e6 / rates
    assert np.allclose(periods_us, np.round(periods_us), atol=1e-6)  # sent exactly
    assert (rates >= 0.5 * cruise).all() and (rates[:-1] < cruise).all()
    # Down, then up, one whole-microsecond period a step, each rate held before its step
    # long enough that the speed changes no faster than the table's acceleration.
    steps = np.diff(np.round(periods_us))
    lowest = int(np.argmax(periods_us))
    assert (steps[:lowest] == 1).all() and (steps[lowest:] == -1).all()
    changes = np.abs(np.diff(rates)) / per_deg  # change i: rates[i] to rates[i + 1]
    held = np.diff(retiming.offsets_s)  # how long rates[i] was held before it
    assert (changes[1:] / held[1:] <= table.accel_deg_s2 * (1 + 1e-9)).all()
    assert changes.max() < table.start_speed_deg_s  # a step the motor takes from standstill


def test_no_slow_down_where_nothing_is_lost_or_the_time_is_too_short():
    table = load_config().turntable
    assert slow_down(table, 360.0, 0.0, 1.0) is None
    assert slow_down(table, 360.0, 5.0, 0.0) is None
    assert slow_down(table, 360.0, 40.0, 1.0) is None  # 30 deg at most in a second
    assert slow_down(table, 360.0, 25.0, 1.0) is not None


def test_a_section_is_retimed_to_its_view_behind_and_left_alone_when_one_comes_at_once():
    table = replace(load_config().turntable, continuous_retime=True)
    angles = [0.0, 45.0, 90.0, 135.0, 180.0, 225.0, 270.0, 315.0]
    # The table would be 8 deg past the 90-degree view: it loses 8 deg and the early margin.
    retiming = section_retiming(table, 360.0, angles, 720.0 + 98.0, 1.0)
    assert retiming is not None
    assert retiming.loss_deg == pytest.approx(8.0 + 360.0 * ARRIVE_EARLY_S)
    # A view just ahead (within the margin) is simply taken; 40 deg behind cannot be lost.
    assert section_retiming(table, 360.0, angles, 89.5, 1.0) is None
    assert section_retiming(table, 360.0, angles, 130.0, 1.0) is None


def test_the_stepper_table_slows_down_on_the_lifts_own_time_line(pi_kit):
    """The box's lift moves while the table turns on; the table's new rates are given on
    the lift's pulse time line (one thread), each once its offset has come, and the table
    ends the move the slow-down's loss behind, turning at its speed again."""
    factory, pulsing = MockFactory(), MockFactory(pin_class=MockPWMPin)
    cfg = pi_kit.config
    carriage = pi_kit.LiftCarriage(factory, cfg.lift, start_steps=180)
    lift = StepperLift(cfg.lift, factory)
    table = StepperTurntable(cfg.turntable, pulsing)
    try:
        lift.home()
        table.spin()
        per_deg = table.steps_per_deg
        speed = cfg.turntable.continuous_speed_deg_s
        to_steps = round(2.0 * lift.steps_per_mm)
        move_s = timing.lift_move_s(cfg.lift, lift.position_steps, to_steps)
        retiming = slow_down(cfg.turntable, speed, 0.05 * speed * move_s, move_s)
        assert retiming is not None and len(retiming.rates_sps) >= 3
        made: list[tuple[float, float]] = []
        origin_s = 0.0

        def note(rate: float) -> None:
            made.append((time.perf_counter() - origin_s, rate))
            table.set_rate(rate)

        timeline = zip(retiming.offsets_s, retiming.rates_sps, strict=True)
        calls = [(offset_s, partial(note, rate)) for offset_s, rate in timeline]
        origin_s = time.perf_counter()
        start_ns = time.monotonic_ns()
        start_deg = table.angle_at(start_ns)
        lift.move_beside(2.0, calls)
        end_ns = time.monotonic_ns()
        assert carriage.position_steps == round((2.0 - cfg.lift.home_mm) * lift.steps_per_mm)
        assert [rate for _, rate in made] == list(retiming.rates_sps)
        late_s = [at - offset for (at, _), offset in zip(made, retiming.offsets_s, strict=True)]
        assert min(late_s) >= 0.0 and max(late_s) < 0.05
        assert pulsing.pin(cfg.turntable.step_pin).frequency == retiming.rates_sps[-1]
        turned = table.angle_at(end_ns) - start_deg
        at_speed = retiming.rates_sps[-1] / per_deg * (end_ns - start_ns) * 1e-9
        assert at_speed - turned == pytest.approx(retiming.loss_deg, rel=0.15)
        table.stop_spin()
        with pytest.raises(MotionError, match="not turning"):
            table.set_rate(retiming.rates_sps[-1])
    finally:
        lift.close()
        table.close()


class TickingClock:
    """A nanosecond clock that moves 1 ms on each reading (the step clock's time line)."""

    def __init__(self) -> None:
        self.now_ns = 0

    def __call__(self) -> int:
        self.now_ns += 1_000_000
        return self.now_ns


def test_the_stepper_table_turns_on_timed_pulses_and_keeps_its_count(pi_kit):
    factory = MockFactory(pin_class=MockPWMPin)
    cfg = pi_kit.config.turntable  # 400 steps a turn, a ramp of two ticks
    clock = TickingClock()
    table = StepperTurntable(cfg, factory, clock_ns=clock)
    step, enable = factory.pin(cfg.step_pin), factory.pin(cfg.enable_pin)  # EN: active low
    try:
        table.move_to(90.0)  # a stop-and-go move first: the turn starts from there
        assert table.spin_problem() is None
        table.spin()
        _, cruise = spin_rates(cfg, cfg.continuous_speed_deg_s)
        assert step.frequency == cruise and step.state == 0.5  # 50 % duty: one step a period
        assert table.driver.enabled and bool(enable.state) == cfg.enable_active_high
        started = clock.now_ns
        first = table.angle_at(started)
        assert table.angle_at(started + 500_000_000) == pytest.approx(
            first + 0.5 * cruise * 360.0 / 400.0
        )
        assert table.time_at(first + 90.0) == pytest.approx(
            started + 90.0 / (cruise * 360.0 / 400.0) * 1e9, abs=2
        )
        with pytest.raises(MotionError, match="turning continuously"):
            table.move_to(0.0)
        table.stop_spin()
        assert step.frequency is None and not step.state  # no pulse after the stop
        assert table.turns.last is not None
        count = table.turns.last.steps_at(clock.now_ns)
        assert table.position_steps == round(count) and table.position_steps > 100
        # A frame exposed while it turned still reads its angle from that turn's clock.
        assert table.angle_at(started) == first
        table.move_to(0.0)
        assert table.angle_deg == 0.0
    finally:
        table.close()


def test_a_table_that_cannot_time_its_pulses_refuses_to_turn(pi_kit):
    factory = MockFactory()  # plain mock pins: no PWM, as a factory without it
    cfg = pi_kit.config.turntable
    table = StepperTurntable(cfg, factory)
    try:
        assert "lgpio" in (table.spin_problem() or "")
        with pytest.raises(MotionError, match="lgpio"):
            table.spin()
    finally:
        table.close()
    still = StepperTurntable(replace(cfg, continuous_speed_deg_s=0.0), MockFactory())
    try:
        assert "continuous_speed_deg_s is 0" in (still.spin_problem() or "")
    finally:
        still.close()


# --- the loop on the simulator, against the model ---------------------------------------


def timed_scan(mode: str, plan: ScanPlan, later_off: bool = False, **options):
    """Scan ``plan`` in ``mode`` on the tiny simulator (laser-off frames a turn later with
    ``later_off``); return segments, seconds, the laser pin's history, whether it turns."""
    hardware = tiny_sim(**options)
    if later_off:
        next_turn(hardware)
    clock = hardware.turntable.clock
    segments = []
    try:
        hardware.lift.move_to(plan.views[0].z_mm)  # the estimate starts at the first section
        start_s = clock.now_s
        acquire(hardware, "object", plan.with_mode(mode), segments.append)
        laser = hardware.laser.mock_pin_history() or []
        spinning = hardware.turntable.turning
    finally:
        hardware.close()
    return segments, hardware.camera.last_frame_s - start_s, laser, spinning


PLAN = ScanPlan.regular(2, 10.0, 8)


@pytest.fixture(scope="module")
def scans():
    """Return the same plan scanned in each mode on the tiny simulator (once per module)."""
    return {mode: timed_scan(mode, PLAN) for mode in SCAN_MODES}


@pytest.mark.parametrize("mode", SCAN_MODES)
def test_the_estimate_agrees_with_the_simulators_clock_in_either_mode(scans, mode):
    segments, took_s, _, _ = scans[mode]
    estimate = estimate_scan_time(load_config(), PLAN.with_mode(mode))
    assert took_s == pytest.approx(estimate.modelled_s, rel=0.05)
    assert len(segments) == len(PLAN.views)


def test_a_slowed_table_brings_each_later_sections_view_round_as_the_lift_settles():
    """At a 10 mm pitch each section change lands the table just past a view (the next one
    about 100 ms on); slowed during the lift's move (``continuous_retime``), it brings that
    view round instead. The simulator's clock and the model agree on the time saved, and
    every view is still taken at its planned angle. The shipped configuration waits."""
    shipped = load_config()
    retimed = replace(shipped, turntable=replace(shipped.turntable, continuous_retime=True))
    plan = ScanPlan.regular(3, 10.0, 8, "continuous")
    segments, took_s, _, _ = timed_scan("continuous", plan, config=retimed)
    model = estimate_scan_time(retimed, plan)
    assert took_s == pytest.approx(model.modelled_s, rel=0.02)
    # Over the minimum: the first view's wait after the spin-up (at most a spacing, 125 ms)
    # and each later section's early arrival, no section change's wait.
    assert model.modelled_s - model.mechanical_minimum_s < 0.125 + 2 * 2 * ARRIVE_EARLY_S
    assert sorted((s.section, s.view) for s in segments) == [
        (k, v) for k in range(3) for v in range(8)
    ]
    turn_per_frame_deg = 360.0 * shipped.camera.frame_duration_us * 1e-6
    for segment in segments:  # measured within a frame's turn of the plan, as ever
        off = (segment.angle_deg - 45.0 * segment.view + 180.0) % 360.0 - 180.0
        assert abs(off) <= turn_per_frame_deg
    waited = estimate_scan_time(shipped, plan)
    _, waited_s, _, _ = timed_scan("continuous", plan)
    # Two section changes, each about 100 ms less (the wait less the early arrival); on
    # the simulator's clock too, within a frame period a change (the frames' phase).
    saved_s = waited.modelled_s - model.modelled_s
    assert saved_s == pytest.approx(2 * 0.1, abs=0.01)
    frame_s = shipped.camera.frame_duration_us * 1e-6
    assert waited_s - took_s == pytest.approx(saved_s, abs=2 * frame_s)


def test_a_continuous_scan_takes_every_view_once_at_its_measured_angle(scans):
    config = load_config()
    segments, took_s, laser, spinning = scans["continuous"]
    assert sorted((s.section, s.view) for s in segments) == [
        (k, v) for k in range(2) for v in range(8)
    ]
    speed = config.turntable.continuous_speed_deg_s
    period_s = config.camera.frame_duration_us * 1e-6
    for segment in segments:
        planned = 45.0 * segment.view
        off = (segment.angle_deg - planned + 180.0) % 360.0 - 180.0
        # The view starts a lead before its angle; the frames' phase leaves a period's turn.
        assert abs(off) <= speed * period_s
        assert 0.0 <= segment.angle_deg < 360.0
    # The laser: on once per view and off after each (the pin's own history); the table stopped.
    assert laser == [False, True] * 16 + [False]
    assert not spinning
    # Far below stop-and-go: a ramp-up, a lift move and two turns against 16 stops.
    assert took_s < scans["stop-and-go"][1] / 3


def _slowed_extraction(monkeypatch, delay_s: float, fail_at: int | None = None):
    """Make the acquisition's extraction take ``delay_s`` longer (and fail on call
    ``fail_at``); return the names of the threads running each call and the most at once."""
    from lamina_device import acquisition

    real = acquisition.extract
    seen = {"threads": [], "busy": 0, "most": 0, "calls": 0}
    lock = threading.Lock()

    def slowed(*args, **kwargs):
        with lock:
            seen["calls"] += 1
            seen["busy"] += 1
            seen["most"] = max(seen["most"], seen["busy"])
            seen["threads"].append(threading.current_thread().name)
            failing = seen["calls"] == fail_at
        try:
            threading.Event().wait(delay_s)
            if failing:
                raise RuntimeError("extraction failed")
            return real(*args, **kwargs)
        finally:
            with lock:
                seen["busy"] -= 1

    monkeypatch.setattr(acquisition, "extract", slowed)
    return seen


def _continuous_segments(workers: int) -> list:
    hardware = tiny_sim("cylinder:d=60")
    segments = []
    try:
        plan = ScanPlan.regular(2, 10.0, 8, "continuous")
        acquire(hardware, "object", plan, segments.append, workers=workers)
    finally:
        hardware.close()
    return segments


def test_views_processed_two_at_once_are_sent_in_plan_order_as_processed_one_at_a_time(
    monkeypatch,
):
    """A Pi's four cores process two continuous views at once (``view_workers``): each
    view's segment is the one a single thread makes, bit for bit, sent in the same order."""
    alone = _continuous_segments(workers=1)
    seen = _slowed_extraction(monkeypatch, delay_s=0.15)
    together = _continuous_segments(workers=2)
    assert seen["most"] == 2 and set(seen["threads"]) == {
        "scan-process_0",
        "scan-process_1",
    }
    assert len(together) == len(alone) == 16
    for a, b in zip(alone, together, strict=True):
        assert (a.section, a.view, a.angle_deg, a.turns) == (
            b.section,
            b.view,
            b.angle_deg,
            b.turns,
        )
        assert np.array_equal(a.cols, b.cols) and np.array_equal(a.rows, b.rows)
        assert np.array_equal(a.confidence, b.confidence)


def test_a_view_that_fails_on_a_processing_thread_ends_the_scan_with_its_error(monkeypatch):
    alone = _continuous_segments(workers=1)
    seen = _slowed_extraction(monkeypatch, delay_s=0.005, fail_at=5)
    hardware = tiny_sim()
    segments = []
    try:
        with pytest.raises(RuntimeError, match="extraction failed"):
            plan = ScanPlan.regular(2, 10.0, 8, "continuous")
            acquire(hardware, "object", plan, segments.append, workers=2)
        # The views taken before it, in the order taken; none after it. The fifth call
        # is the fifth view's or, where the two threads entered it out of turn, the sixth's.
        assert 4 <= len(segments) <= 5
        taken = [(s.section, s.view) for s in alone[: len(segments)]]
        assert [(s.section, s.view) for s in segments] == taken
        assert not hardware.turntable.turning and not hardware.laser.is_on
        assert hardware.lift.z_mm == 0.0  # home
    finally:
        hardware.close()
    assert seen["calls"] >= 5


def test_an_abort_stops_the_table_and_the_laser_and_keeps_what_was_taken():
    hardware = tiny_sim()
    control = ScanControl()
    segments = []

    def take(segment):
        segments.append(segment)
        if len(segments) == 3:
            control.abort()

    try:
        with pytest.raises(ScanAborted):
            plan = ScanPlan.regular(2, 10.0, 8, "continuous")
            acquire(hardware, "object", plan, take, control=control)
        assert 3 <= len(segments) < 16
        assert not hardware.turntable.turning and not hardware.laser.is_on
        assert hardware.lift.z_mm == 0.0  # home
    finally:
        hardware.close()


def test_a_view_is_off_on_off_frames_each_exposed_wholly_after_the_laser_switched():
    hardware = tiny_sim()
    try:
        hardware.place("object")
        hardware.lift.move_to(10.0)
        hardware.turntable.spin()
        frames = []
        original = hardware.camera.capture_timed

        def record():
            frame = original()
            frames.append((frame, hardware.laser.is_on, hardware.laser.changed_ns))
            return frame

        hardware.camera.capture_timed = record
        lit, off_before, off_after = capture_moving(hardware, hardware.camera)
        timing = hardware.camera.frame_timing
        (before, b_on, _), (on, o_on, switched_on), (after, a_on, switched_off) = frames
        assert (b_on, o_on, a_on) == (False, True, False)
        jitter_ns = 5 * 50_000  # the reported timestamps' jitter, five sigmas
        assert on.start_ns >= switched_on - jitter_ns and after.start_ns >= switched_off - jitter_ns
        gap_ns = round(laser_pulse(timing) * 1e9)
        assert on.start_ns - before.start_ns == pytest.approx(gap_ns, abs=2 * jitter_ns)
        assert off_before is before.image and off_after is after.image
        assert lit is on
        hardware.turntable.stop_spin()
    finally:
        hardware.close()


# --- the renderer: the rolling shutter and the blur -------------------------------------


def test_a_still_exposure_renders_the_still_view_and_a_turning_one_each_band_at_its_time():
    hardware = tiny_sim("ellipsoid:a=40,b=25,c=80,x=8")
    scene = hardware.camera.scene
    try:
        still = Exposure(0.0, 0.004, 1e-4, lambda t, around: (30.0, (0.0, 0.0)))
        moving = scene._moving_view("object", 40.0, still, True)
        view = scene._view("object", 30.0, 40.0, (0.0, 0.0))
        np.testing.assert_allclose(moving.ambient_dn, view.ambient_dn)
        np.testing.assert_allclose(moving.laser_dn, view.laser_dn, atol=1e-9)
        assert view.laser_dn.max() > 10.0
        # Turning 100 degrees a second, each band sees the arm where it is at its own time.
        turning = Exposure(0.0, 0.0, 2e-3, lambda t, around: (30.0 + 100.0 * t, (0.0, 0.0)))
        frame = scene._moving_view("object", 40.0, turning, False)
        bands = np.array_split(np.arange(54), 16)
        for band in (bands[0], bands[8], bands[-1]):
            middle = 0.5 * (band[0] + band[-1])
            at = scene._view("object", 30.0 + 100.0 * turning.row_middle_s(middle), 40.0, (0, 0))
            np.testing.assert_allclose(frame.ambient_dn[band], at.ambient_dn[band])
        first = scene._view("object", 30.0, 40.0, (0.0, 0.0)).ambient_dn
        assert not np.allclose(frame.ambient_dn, first)  # the later bands saw it turned on
    finally:
        hardware.close()


# --- what the device offers and refuses ---------------------------------------------------


def test_the_simulator_offers_continuous_scans_and_refuses_them_with_colour():
    hardware = tiny_sim()
    try:
        assert scan_modes(hardware) == SCAN_MODES
        plan = ScanPlan.regular(2, 10.0, 8, "continuous")
        assert continuous_problem(hardware, plan) is None
        assert "colour needs a stop-and-go" in (continuous_problem(hardware, plan, True) or "")
        with pytest.raises(Exception, match="cannot scan continuously"):
            acquire(hardware, "object", plan, lambda s: None, colour=True)
    finally:
        hardware.close()


def test_pulses_the_watchdog_would_not_bound_refuse_the_mode():
    hardware = tiny_sim()
    try:
        assert hardware.watchdog is not None
        hardware.watchdog.max_on_s = 0.02  # shorter than a view's pulse of two periods
        plan = ScanPlan.regular(1, 10.0, 8, "continuous")
        assert "on-time limit" in (continuous_problem(hardware, plan) or "")
        assert scan_modes(hardware) == SCAN_MODES[:1]
        hardware.watchdog.max_on_s = 2.0
        dense = ScanPlan.regular(1, 10.0, 60, "continuous")  # a pulse every 17 ms
        assert "of the time" in (continuous_problem(hardware, dense) or "")
    finally:
        hardware.close()


def test_the_watchdog_bounds_the_share_of_time_of_a_re_armed_laser():
    from lamina_device.laser import Laser

    now = [0.0]
    laser = Laser(17, pin_factory=MockFactory(), clock_ns=lambda: round(now[0] * 1e9))
    dog = LaserWatchdog(laser, max_on_s=1.0, clock=lambda: now[0])
    assert dog.pulse_problem(0.017, 0.125) is None
    for step in range(int(DUTY_WINDOWS / 0.05) + 2):
        # Switched off and on again between checks: each switch-on re-arms the on-time count.
        laser.off()
        laser.on()
        now[0] = step * 0.05
        reason = dog.check()
        if reason is not None:
            break
    assert reason is not None and "of the last 10 s" in reason
    assert not laser.is_on
    laser.close()


def test_the_model_takes_views_in_the_order_the_table_brings_them():
    assert next_view([0.0, 90.0, 180.0, 270.0], 100.0) == (2, 180.0)
    assert next_view([0.0, 90.0], 350.0 + 360.0) == (0, 720.0)
    config = load_config()
    camera = replace(config.camera, frame_duration_us=8333, exposure_us=4000, readout_us=7957)
    lead_s, view_s = view_capture_s(config_frame_timing(replace(config, camera=camera)))
    # Off frame half a period on average, the on frame two periods later (a 12 ms exposure
    # and read-out spans more than one), the second off frame two more.
    assert view_s == pytest.approx(0.5 * 8.333e-3 + 4 * 8.333e-3, rel=1e-3)
    assert 0.0 < lead_s < view_s


def test_a_paused_continuous_scan_stops_the_table_until_resumed():
    hardware = tiny_sim()
    control = ScanControl()
    table = hardware.turntable
    stops = []
    stop = table.stop_spin

    def counted_stop():
        stops.append(control.paused)
        stop()
        if control.paused:  # stopped for the pause: let it go on a little later
            threading.Timer(0.05, control.resume).start()

    table.stop_spin = counted_stop
    segments: list[object] = []

    def take(segment):
        segments.append(segment)
        if len(segments) == 2:
            control.pause()

    try:
        plan = ScanPlan.regular(1, 10.0, 4, "continuous")
        acquire(hardware, "object", plan, take, control=control)
        assert len(segments) == 4 and not table.turning
        assert stops == [True, False]  # stopped for the pause, then at the end
    finally:
        hardware.close()


# --- laser-off frames a turn later (continuous_off_frames = "next-turn") -------------------


def next_turn(hardware):
    """Set ``hardware``'s (simulated) box to take laser-off frames a turn later, with the
    frame period a turn divides (8320 us: ``test_config``); return it."""
    return CampaignPlan("limb", 1, 10.0, 8, off_frames="next-turn").box(hardware)


RELIEF_SHAPE = "random:seed=97104,scale=limb"
"""A random limb shape with skin relief of a few millimetres' wavelength."""


def _room_light_error(hardware, capture) -> np.ndarray:
    """Return how far a view's laser-off reference stands from its laser-on frame's own room
    light (the same exposure rendered with the laser off), pixel by pixel, in DN."""
    scene = hardware.camera.scene
    exposures = []
    render = scene.render_exposure

    def kept(target, z_mm, laser_on, exposure, key, **options):
        if laser_on:
            exposures.append((target, z_mm, exposure, key, options))
        return render(target, z_mm, laser_on, exposure, key, **options)

    scene.render_exposure = kept
    hardware.place("object")
    hardware.lift.move_to(10.0)
    hardware.turntable.spin()
    try:
        off = capture()
    finally:
        hardware.turntable.stop_spin()
    target, z_mm, exposure, key, options = exposures[-1]
    room, _ = render(target, z_mm, False, exposure, key, **options)
    return off.astype(float) - room.astype(float)


def test_a_continuous_views_laser_off_reference_is_its_laser_on_frames_own_room_light():
    """Interleaved, the off frames brought to the laser-on frame's instant; a turn later,
    the off frame taken at its angle: either is the laser-on frame's room light. The off
    frames merely combined are not: a fine relief's shading moved between them."""
    rig = replace(Rig.limb(), image_size=(384, 216), focal_px=Rig.limb().focal_px / 4.0)
    errors = {}
    for way in ("merely combined", "interleaved", "next-turn"):
        hardware = open_sim(RELIEF_SHAPE, 0, "none", "limb", rig)
        camera = hardware.camera
        try:
            if way == "next-turn":
                next_turn(hardware)

                def capture(hardware=hardware, camera=camera):
                    lit = capture_lit(hardware, camera)
                    return capture_next_turn(hardware, camera, lit)

            else:

                def capture(hardware=hardware, camera=camera, way=way):
                    lit, before, after = capture_moving(hardware, camera)
                    if way == "merely combined":
                        return combine_off_frames(before, after)
                    return laser_off_reference(before, lit.image, after)

            errors[way] = _room_light_error(hardware, capture)
        finally:
            hardware.close()
    # Where the room light stands 10 DN above the reference, the difference shows a false
    # stripe a sixth as bright as the limb rig's (about 58 DN on the harsh preset).
    false_light = {way: float(np.mean(e < -10.0)) for way, e in errors.items()}
    assert false_light["merely combined"] > 0.005, false_light  # 1.2 % of the frame
    assert false_light["interleaved"] < false_light["merely combined"] / 8, false_light  # 0.10 %
    assert np.abs(errors["next-turn"]).max() <= 1.0


def test_a_next_turn_scan_pulses_the_laser_once_a_view_and_takes_a_second_turn():
    """Each view: one laser-on frame on the section's first turn, its laser-off frame on the
    second; the model's time agrees with the simulator's clock, about a turn a section more."""
    segments, took_s, laser, spinning = timed_scan("continuous", PLAN, later_off=True)
    assert sorted((s.section, s.view) for s in segments) == [
        (k, v) for k in range(2) for v in range(8)
    ]
    assert laser == [False, True] * 16 + [False]
    assert not spinning
    config = next_turn(tiny_sim()).turntable.clock.config
    estimate = estimate_scan_time(config, PLAN.with_mode("continuous"))
    assert took_s == pytest.approx(estimate.modelled_s, rel=0.05)
    interleaved = estimate_scan_time(load_config(), PLAN.with_mode("continuous"))
    assert estimate.modelled_s - interleaved.modelled_s == pytest.approx(2 * 0.9984, abs=0.2)


def test_a_pause_before_the_second_turn_takes_the_sections_laser_on_frames_again():
    hardware = next_turn(tiny_sim())
    control = ScanControl()
    table = hardware.turntable
    taken = []
    original = hardware.camera.capture_timed

    def capture():
        frame = original()
        taken.append(hardware.laser.is_on)
        if taken.count(True) == 2 and not control.paused and len(taken) == 2:
            control.pause()
            threading.Timer(0.05, control.resume).start()
        return frame

    hardware.camera.capture_timed = capture
    segments = []
    try:
        plan = ScanPlan.regular(1, 10.0, 4, "continuous")
        acquire(hardware, "object", plan, segments.append, control=control)
        assert sorted(s.view for s in segments) == [0, 1, 2, 3] and not table.turning
        # Two laser-on frames before the pause, taken again after it with the other two.
        assert taken == [True, True, True, True, True, True, False, False, False, False]
    finally:
        hardware.close()


def _lit_then(hardware, late: int, buffered: bool = False):
    """Take a laser-on frame on the turning tiny simulator; then return it and the frames
    ``capture_next_turn`` was served when its first ``late`` captures come a period late
    (the device held up) and, with ``buffered``, a frame older than the one due first."""
    camera = hardware.camera
    hardware.place("object")
    hardware.turntable.spin()
    lit = capture_lit(hardware, camera)
    period_s = camera.frame_timing.period_s
    original = camera.capture_timed
    served = []

    def held_up():
        if buffered and not served:
            served.append(lit)
            return lit  # a frame the camera kept from before
        if len(served) < late:
            hardware.turntable.clock.advance(period_s)
        frame = original()
        served.append(frame)
        return frame

    camera.capture_timed = held_up
    try:
        capture_next_turn(hardware, camera, lit)
    finally:
        camera.capture_timed = original
        hardware.turntable.stop_spin()
    return lit, served


def test_a_next_turn_frame_buffered_early_is_passed_over_and_a_late_one_waits_a_turn():
    turn_ns = 0.9984e9  # 6400 steps of 156 us
    hardware = next_turn(tiny_sim())
    try:
        lit, served = _lit_then(hardware, 0, buffered=True)
        assert served[0] is lit and len(served) == 2
        assert served[1].start_ns - lit.start_ns == pytest.approx(turn_ns, abs=2e5)
        lit, served = _lit_then(hardware, 1)  # a period late: the next turn's frame
        assert len(served) == 2
        assert served[1].start_ns - lit.start_ns == pytest.approx(2 * turn_ns, abs=2e5)
        with pytest.raises(CameraError, match="missed 3 turns running"):
            _lit_then(hardware, 3)
    finally:
        hardware.close()


def test_a_simulated_laser_rendered_slowly_is_timed_on_the_simulators_clock():
    """The simulator renders a laser-on frame far slower than its exposure: the watchdog
    times the laser on the simulator's clock, so a next-turn scan (laser-on frames back to
    back for a turn) is not taken for a laser left on (it was, measured in real time)."""
    hardware = next_turn(tiny_sim())
    assert hardware.watchdog is not None
    hardware.watchdog.max_on_s = 0.25  # a 2.5 s duty window: shorter than the scan's renders
    scene = hardware.camera.scene
    render = scene.render_exposure

    def slowly(*args, **kwargs):
        if hardware.laser.is_on:
            threading.Event().wait(0.1)
        return render(*args, **kwargs)

    scene.render_exposure = slowly
    plan = ScanPlan.regular(3, 10.0, 8, "continuous")
    segments = []
    try:
        acquire(hardware, "object", plan, segments.append)
        trips = list(hardware.watchdog.trips)
        laser = hardware.laser.mock_pin_history() or []
    finally:
        hardware.close()
    assert trips == []
    assert laser.count(True) == len(plan.views)  # one pulse a view, none cut short
    assert len(segments) == len(plan.views) and all(len(s.cols) > 0 for s in segments)


@pytest.mark.parametrize("mode", ["stop-and-go", "continuous"])
def test_the_simulated_camera_notes_when_each_laser_on_frame_arrived(mode):
    """One time a view, in the order the views were taken, each when the laser was on:
    what a bench needs to know where a swaying subject was (a segment itself reaches its
    receiver later, when the extraction thread is done with it)."""
    hardware = tiny_sim()
    segments = []
    laser, clock = hardware.laser, hardware.turntable.clock
    try:
        acquire(hardware, "object", PLAN.with_mode(mode), segments.append)
        lit_s = list(hardware.camera.lit_frames_s)
        taken = hardware.camera.frames_taken
        history = laser.mock_pin_history() or []
    finally:
        hardware.close()
    assert len(lit_s) == len(segments) == len(PLAN.views) < taken  # off frames not noted
    assert (np.diff(lit_s) > 0).all()
    assert lit_s[-1] <= clock.now_s
    assert history.count(True) == len(lit_s)  # a laser pulse a view, its frame noted once
