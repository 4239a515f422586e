"""The scan-time model against move profiles worked out by hand, and two axes moving at once."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from gpiozero.pins.mock import MockFactory

from lamina_device.config import load_config
from lamina_device.motion import (
    DriverRun,
    StepperDriver,
    StepperLift,
    StepperTurntable,
    lift_intervals_s,
    move_axes,
    run_together,
    turntable_intervals_s,
)
from lamina_device.timing import (
    CONTINUOUS_PIPELINE_DEPTH,
    estimate_scan_time,
    frame_wait_s,
    view_workers,
)
from lamina_shared.durations import duration_text
from lamina_shared.types import ScanPlan, ViewSpec


def trapezoid_s(distance: float, v0: float, vmax: float, accel: float) -> float:
    """Return the time of a trapezoidal (or triangular) move, in closed form."""
    ramp = (vmax**2 - v0**2) / (2 * accel)
    if 2 * ramp <= distance:
        return 2 * (vmax - v0) / accel + (distance - 2 * ramp) / vmax
    peak = math.sqrt(v0**2 + accel * distance)
    return 2 * (peak - v0) / accel


@pytest.fixture(scope="module")
def config():
    return load_config()


def test_a_45_degree_view_costs_its_trapezoid_settle_and_two_frames(config):
    table, camera = config.turntable, config.camera
    plan = ScanPlan((ViewSpec(0, 0.0, 0.0), ViewSpec(0, 0.0, 45.0)))
    # From power-up the first view's backlash is taken up: start from an engaged table.
    first = estimate_scan_time(config, ScanPlan(plan.views[:1]))
    both = estimate_scan_time(config, plan)
    move = both.turntable_s - first.turntable_s
    truth = trapezoid_s(45.0, table.start_speed_deg_s, table.max_speed_deg_s, table.accel_deg_s2)
    assert move == pytest.approx(truth, rel=0.01)  # steps are discrete; the profile is not
    assert 1.1 < truth < 1.25  # the "about 1.2 s"
    frame = 0.5 * camera.frame_duration_us * 1e-6 + camera.exposure_us * 1e-6
    frame += camera.frame_duration_us * 1e-6
    assert frame_wait_s(camera.frame_duration_us, camera.exposure_us) == pytest.approx(frame)
    settle = max(table.settle_s, config.lift.settle_s)
    per_view = move + settle + 2 * frame
    assert both.modelled_s - first.modelled_s == pytest.approx(per_view, rel=1e-9)


def test_sequential_axes_cost_the_sum_and_the_minimum_the_longer_move(config):
    lift = config.lift
    plan = ScanPlan.regular(sections=2, pitch_mm=10.0, views=8)
    estimate = estimate_scan_time(config, plan, axes_together=False)
    truth = trapezoid_s(10.0, lift.start_speed_mm_s, lift.max_speed_mm_s, lift.accel_mm_s2)
    assert estimate.lift_s == pytest.approx(truth, rel=0.01)  # one section change
    # The change from 315 to 0 degrees continues counter-clockwise: 45 degrees, no rewind.
    table = config.turntable
    move = trapezoid_s(45.0, table.start_speed_deg_s, table.max_speed_deg_s, table.accel_deg_s2)
    assert estimate.mechanical_minimum_s == pytest.approx(
        estimate.modelled_s - estimate.lift_s + max(0.0, estimate.lift_s - move), rel=1e-3
    )
    assert estimate.ratio > 1.0
    # The box's steppers move together: the loop is the minimum.
    together = estimate_scan_time(config, plan)
    assert together.modelled_s == pytest.approx(estimate.mechanical_minimum_s)
    assert together.ratio == pytest.approx(1.0)


def test_processing_hides_behind_the_mechanics_unless_it_is_slower(config):
    plan = ScanPlan.regular(sections=2, pitch_mm=2.0, views=8)
    fast = estimate_scan_time(config, plan, processing_s_per_view=0.05)
    bare = estimate_scan_time(config, plan)
    assert fast.modelled_s == pytest.approx(bare.modelled_s + 0.05)  # the last view's only
    slow = estimate_scan_time(config, plan, processing_s_per_view=5.0)
    assert slow.modelled_s > 16 * 5.0 and slow.processing_s > 0.5 * slow.modelled_s


@pytest.mark.parametrize("per_view_s", [0.26, 0.7, 1.0])
def test_a_full_continuous_queue_holds_the_capture_up(config, per_view_s):
    """Slower processing than the table's 125 ms between views: the extraction thread's
    queue fills and the capture waits, so at most the queue's views, the one in hand and
    the last view itself (captured, waiting for room) are left to process after the last
    capture; the mechanics' minimum is unchanged."""
    plan = ScanPlan.regular(sections=40, pitch_mm=2.0, views=8, mode="continuous")
    bare = estimate_scan_time(config, plan)
    slow = estimate_scan_time(config, plan, processing_s_per_view=per_view_s)
    assert slow.mechanical_minimum_s == pytest.approx(bare.mechanical_minimum_s)
    assert slow.modelled_s >= len(plan.views) * per_view_s  # the thread is the bottleneck
    assert slow.modelled_s == pytest.approx(len(plan.views) * per_view_s, rel=0.1)
    assert slow.processing_s <= (CONTINUOUS_PIPELINE_DEPTH + 2) * per_view_s + 1e-9
    quick = estimate_scan_time(config, plan, processing_s_per_view=0.05)
    assert quick.modelled_s == pytest.approx(bare.modelled_s + 0.05)  # hidden but the last


@pytest.mark.parametrize("per_view_s", [0.2, 0.284, 0.6])
def test_two_processing_threads_take_a_view_at_half_the_pace_of_one(config, per_view_s):
    """Two views processed at once (a Pi's four cores, ``view_workers``) keep up as one
    thread at half the processing per view would, to within one view's processing (the
    last, which no second thread shares), and never take longer than one thread."""
    plan = ScanPlan.regular(sections=40, pitch_mm=10.0, views=8, mode="continuous")
    one = estimate_scan_time(config, plan, processing_s_per_view=per_view_s)
    two = estimate_scan_time(config, plan, processing_s_per_view=per_view_s, workers=2)
    half = estimate_scan_time(config, plan, processing_s_per_view=per_view_s / 2)
    assert two.modelled_s <= one.modelled_s
    assert abs(two.modelled_s - half.modelled_s) <= per_view_s + 1e-9
    assert two.mechanical_minimum_s == pytest.approx(one.mechanical_minimum_s)
    if per_view_s > 0.25:  # one thread falls behind the table and the lift's moves
        assert one.modelled_s > two.modelled_s + 5.0
    # A stop-and-go plan processes one view at a time whatever is asked.
    still = plan.with_mode("stop-and-go")
    assert estimate_scan_time(config, still, per_view_s, workers=2) == estimate_scan_time(
        config, still, per_view_s
    )


def test_a_view_keeps_two_cores_busy_so_four_cores_process_two_views():
    assert [view_workers(cores) for cores in (1, 2, 3, 4, 8, 64)] == [1, 1, 1, 2, 2, 2]


def test_an_empty_plan_takes_no_time_and_durations_read_in_minutes(config):
    estimate = estimate_scan_time(config, ScanPlan(()))
    assert estimate.modelled_s == 0.0 and estimate.ratio == 1.0 and estimate.views == 0
    assert duration_text(425.4) == "7 min 05 s" and duration_text(42.0) == "42 s"
    assert duration_text(float("nan")) == "unknown"


def test_a_clockwise_plan_pays_the_backlash_approach(config):
    forward = ScanPlan(tuple(ViewSpec(0, 0.0, a) for a in (0.0, 45.0, 90.0)))
    backward = ScanPlan(tuple(ViewSpec(0, 0.0, a) for a in (90.0, 45.0, 0.0)))
    ahead = estimate_scan_time(config, forward)
    back = estimate_scan_time(config, backward)
    # Each clockwise move overshoots by the backlash and comes back: two extra short runs.
    assert back.turntable_s > ahead.turntable_s + 0.1


class VirtualClock:
    """A clock that moves on by a microsecond each time it is read (no real waiting)."""

    def __init__(self) -> None:
        self.now_s = 0.0

    def __call__(self) -> float:
        self.now_s += 1e-6
        return self.now_s


def test_two_drivers_run_together_each_on_its_own_profile(pi_kit):
    factory = MockFactory()
    clock = VirtualClock()
    cfg = pi_kit.config
    table = StepperDriver(cfg.turntable, factory, clock)
    lift = StepperDriver(cfg.lift, factory, clock)
    table_iv = turntable_intervals_s(cfg.turntable, 100)
    lift_iv = lift_intervals_s(cfg.lift, 60)
    pulses: list[tuple[str, float]] = []
    for name, driver in (("table", table), ("lift", lift)):
        original = driver._pulse

        def pulse(original=original, name=name) -> None:
            pulses.append((name, clock.now_s))
            original()

        driver._pulse = pulse  # type: ignore[method-assign]
    counts = run_together([DriverRun(table, +1, table_iv), DriverRun(lift, -1, lift_iv)], clock)
    assert counts == [100, 60]
    assert pi_kit.rising_edges(factory.pin(cfg.turntable.step_pin)) == 100
    assert pi_kit.rising_edges(factory.pin(cfg.lift.step_pin)) == 60
    # Each axis keeps its own intervals (never shorter than planned)...
    for name, planned in (("table", table_iv), ("lift", lift_iv)):
        times = np.array([t for n, t in pulses if n == name])
        assert np.all(np.diff(times) >= planned[1:] - 1e-9)
    # ...and they overlap: the whole takes the longer move, not the sum.
    total = pulses[-1][1] - pulses[0][1]
    assert total < max(table_iv.sum(), lift_iv.sum()) + 0.01
    assert total < 0.8 * (table_iv.sum() + lift_iv.sum())
    names = [n for n, _ in pulses]
    assert names.index("lift") < len(names) - names[::-1].index("table") - 1


def test_a_section_change_moves_lift_and_table_at_once_and_both_arrive(pi_kit):
    factory = MockFactory()
    cfg = pi_kit.config
    carriage = pi_kit.LiftCarriage(factory, cfg.lift, start_steps=180)
    lift = StepperLift(cfg.lift, factory)
    table = StepperTurntable(cfg.turntable, factory)
    try:
        move_axes(lift, table, 0.0, 0.0)  # homes first
        move_axes(lift, table, 2.0, 90.0)
        assert lift.z_mm == pytest.approx(2.0) and table.angle_deg == 90.0
        assert carriage.position_steps == round((2.0 - cfg.lift.home_mm) * lift.steps_per_mm)
        # Back down while the table returns clockwise (overshoot, then approach).
        move_axes(lift, table, 0.0, 0.0)
        assert lift.z_mm == pytest.approx(0.0) and table.angle_deg == 0.0
    finally:
        lift.close()
        table.close()


def test_the_lift_still_stops_at_its_switch_when_moving_beside_the_table(pi_kit):
    factory = MockFactory()
    cfg = replace(pi_kit.config.lift)
    carriage = pi_kit.LiftCarriage(factory, cfg, start_steps=180)
    lift = StepperLift(cfg, factory)
    table = StepperTurntable(pi_kit.config.turntable, factory)
    try:
        move_axes(lift, table, 2.0, 0.0)
        carriage.connected = False  # the switch wire breaks: it reads "hit"
        with pytest.raises(Exception, match="limit switch"):
            move_axes(lift, table, 0.0, 180.0)
        assert not lift.homed and table.angle_deg == 180.0
    finally:
        lift.close()
        table.close()


def test_the_simulator_runs_on_the_modelled_clock(config):
    """A simulated scan advances a virtual clock as the box would; the estimate agrees."""
    from lamina_device.acquisition import acquire
    from lamina_device.backends import open_hardware

    plan = ScanPlan.regular(sections=2, pitch_mm=10.0, views=4)
    hardware = open_hardware("sim", "cylinder:d=19.05", noise="none")
    clock = hardware.turntable.clock
    try:
        hardware.lift.move_to(0.0)  # the estimate starts with the lift at the first section
        start_s = clock.now_s
        last_segment_s: list[float] = []
        acquire(hardware, "object", plan, lambda segment: last_segment_s.append(clock.now_s))
    finally:
        hardware.close()
    assert len(last_segment_s) == len(plan.views)
    estimate = estimate_scan_time(config, plan)
    # The sim's own bookkeeping (its axes, settle and frames) against the model's sums.
    assert last_segment_s[-1] - start_s == pytest.approx(estimate.modelled_s, rel=0.01)
    assert estimate.lift_s > 1.0  # a 10 mm section change is in both
