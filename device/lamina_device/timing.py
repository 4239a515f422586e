"""How long a scan plan keeps the patient still: a model of the acquisition from the config.

The figure a patient feels is the time from the first view to the last, so the model
follows the acquisition loop view by view with the axes' own move profiles (the same
trapezoids and backlash rule the steppers run, :mod:`lamina_device.motion`), the settle
after every move, and the camera frames a view waits for: after a move or a laser
switch, the next frame whose exposure starts afterwards (half a frame period on
average), its exposure, and its rolling read-out (at most one frame period). Extraction
and sending run in a worker thread beside the next move, so they add only where they
are slower than the mechanics, and once for the last view.

The *mechanical minimum* is what no loop can beat on this hardware: every move with the
lift and the turntable turning together, its settle and its two frames, nothing else.
Homing the lift before the first view and after the last is not the patient's wait and
is left out of both.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from typing import NamedTuple

from lamina_device.camera import LASER_LATENCY_NS, FrameTiming
from lamina_device.config import DeviceConfig, LiftConfig, TurntableConfig, pulse_rate
from lamina_device.motion import (
    SPIN_TICK_S,
    Retiming,
    lift_intervals_s,
    lift_steps_per_mm,
    slow_down,
    spin_rates,
    turntable_intervals_s,
    turntable_runs,
    turntable_steps_per_rev,
)
from lamina_shared.types import ScanPlan

__all__ = [
    "CONTINUOUS_FRAMES",
    "FRAMES_PER_VIEW",
    "ScanTime",
    "config_frame_timing",
    "estimate_scan_time",
    "frame_wait_s",
    "frames_apart",
    "laser_pulse",
    "lift_move_s",
    "lit_capture_s",
    "next_turn_start_ns",
    "next_view",
    "section_retiming",
    "spin_up_s",
    "turn_speed_deg_s",
    "turntable_move_s",
    "view_capture_s",
    "view_workers",
]

FRAMES_PER_VIEW = 2
"""A view is a laser-off and a laser-on frame (the difference image, thesis 5.1)."""
CONTINUOUS_FRAMES = 3
"""A continuous view: laser off, on, off, three streamed frames in a row (the two off
frames bracket the on frame, the table turning between them)."""


@dataclass(frozen=True)
class ScanTime:
    """A plan's modelled duration, and what it is made of (seconds).

    Attributes:
        modelled_s: first move to the last view's segment sent, as the loop runs.
        mechanical_minimum_s: the axes moving together, settle and frames, nothing else.
        turntable_s: the turntable's moves, summed.
        lift_s: the lift's moves, summed.
        settle_s: the settles after each view's move, summed.
        frames_s: waiting for and exposing each view's frames, summed.
        processing_s: extraction and sending not hidden behind the mechanics.
        views: the plan's views.
    """

    modelled_s: float
    mechanical_minimum_s: float
    turntable_s: float
    lift_s: float
    settle_s: float
    frames_s: float
    processing_s: float
    views: int

    @property
    def ratio(self) -> float:
        """Return the modelled time over the mechanical minimum (1.0 for an empty plan)."""
        return self.modelled_s / self.mechanical_minimum_s if self.mechanical_minimum_s else 1.0


def frame_wait_s(frame_duration_us: float, exposure_us: float) -> float:
    """Return the mean time from a request to a frame exposed entirely after it.

    Args:
        frame_duration_us: the camera's frame period (an exposure beyond it stretches it).
        exposure_us: the exposure time.

    Returns:
        Half a period to the next frame start, the exposure, and one period of read-out.
    """
    period_s = max(frame_duration_us, exposure_us) * 1e-6
    return 0.5 * period_s + exposure_us * 1e-6 + period_s


class _ViewMoves(NamedTuple):
    """One view's moves, in seconds."""

    lift_s: float
    """The lift's move (none within a section)."""
    table_first_s: float
    """The turntable's first run: the lift can move beside it."""
    table_rest_s: float
    """The turntable's backlash return, if the move needed one."""

    def sequential_s(self) -> float:
        return self.lift_s + self.table_first_s + self.table_rest_s

    def together_s(self) -> float:
        # The lift runs beside the table's first run (motion.StepperLift.move_with).
        return max(self.lift_s, self.table_first_s) + self.table_rest_s


# --- continuous scans -------------------------------------------------------------------


def config_frame_timing(config: DeviceConfig, exposure_us: float | None = None) -> FrameTiming:
    """Return the camera's streaming timing as ``config`` describes it."""
    camera = config.camera
    exposure = camera.exposure_us if exposure_us is None else exposure_us
    period_s = max(camera.frame_duration_us, exposure) * 1e-6
    return FrameTiming(period_s, exposure * 1e-6, camera.readout_s, camera.height)


def frames_apart(timing: FrameTiming) -> int:
    """Return the frame periods between two captures when the laser switches in between.

    The laser switches as soon as a frame has arrived (its last row read); the next
    frame exposed wholly after the switch is the first to start after it, so with a
    rolling shutter whose exposure and read-out span more than a period the next frame
    or two are lost (two at 120 fps: 12 ms of exposure and read-out in 8.3 ms periods).
    """
    return max(1, math.ceil((timing.span_s + LASER_LATENCY_NS * 1e-9) / timing.period_s - 1e-9))


def view_capture_s(timing: FrameTiming) -> tuple[float, float]:
    """Return a continuous view's mean lead and duration (seconds from its start).

    The first (laser-off) frame is the next to arrive, on average half a period after the
    view starts; the laser-on frame and the second laser-off frame follow
    :func:`frames_apart` periods apart.

    Returns:
        The time to the middle of the laser-on frame's exposure at its middle row (the
        moment the view's angle should be the planned one), and to the last frame's arrival.
    """
    gap_s = frames_apart(timing) * timing.period_s
    first_arrival_s = 0.5 * timing.period_s
    lead_s = first_arrival_s - timing.span_s + gap_s + 0.5 * (timing.exposure_s + timing.readout_s)
    return lead_s, first_arrival_s + 2.0 * gap_s


def lit_capture_s(timing: FrameTiming) -> tuple[float, float]:
    """Return a next-turn view's mean lead and duration on its first turn (seconds).

    The laser switches on as the view starts; the first frame to start after the switch
    (and the laser's latency) is its laser-on frame, on average half a period later. Its
    laser-off frame is taken a turn later (:func:`next_turn_start_ns`).

    Returns:
        The time to the middle of the laser-on frame's exposure at its middle row, and to
        the frame's arrival.
    """
    start_s = LASER_LATENCY_NS * 1e-9 + 0.5 * timing.period_s
    return start_s + 0.5 * (timing.exposure_s + timing.readout_s), start_s + timing.span_s


def next_turn_start_ns(timing: FrameTiming, lit_start_ns: int, turn_ns: float) -> int:
    """Return when the streamed frame a turn after a laser-on frame starts (monotonic ns).

    The sensor streams frames a period apart; of those, the one whose start lies nearest
    ``turn_ns`` after the laser-on frame's sees the table at the laser-on frame's angle
    (exactly, when a turn is a whole number of periods: 120 at 120 fps and a turn a
    second).
    """
    period_ns = timing.period_s * 1e9
    return round(lit_start_ns + round(turn_ns / period_ns) * period_ns)


def laser_pulse(timing: FrameTiming) -> float:
    """Return how long the laser stays on for one continuous view (seconds).

    From the first laser-off frame's arrival to the laser-on frame's arrival.
    """
    return frames_apart(timing) * timing.period_s


def next_view(angles_deg: Sequence[float], from_deg: float) -> tuple[int, float]:
    """Return the view a table turning counter-clockwise from ``from_deg`` reaches first.

    Args:
        angles_deg: the planned angles still to take.
        from_deg: the earliest (unwrapped) angle a view can still be taken at.

    Returns:
        The index into ``angles_deg``, and the unwrapped angle the table reaches it at.
    """
    ahead = [(a - from_deg) % 360.0 for a in angles_deg]
    k = min(range(len(ahead)), key=ahead.__getitem__)
    return k, from_deg + ahead[k]


def turn_speed_deg_s(config: TurntableConfig, speed_deg_s: float) -> float:
    """Return the speed a continuous turn asked ``speed_deg_s`` really has: its step rate
    is the nearest the driver sends exactly (:func:`~lamina_device.config.pulse_rate`;
    360.6 deg/s for the shipped 360), which over a section change's second is a margin's
    worth of angle."""
    per_deg = turntable_steps_per_rev(config) / 360.0
    return pulse_rate(speed_deg_s * per_deg) / per_deg


ARRIVE_EARLY_S = 0.002
"""A slowed table is brought this far ahead of a section's first view, so that a rate
change made a little late still leaves the view to come, not just missed."""


def section_retiming(
    config: TurntableConfig,
    speed_deg_s: float,
    angles_deg: Sequence[float],
    reach_deg: float,
    within_s: float,
) -> Retiming | None:
    """Return the slow-down that brings one of a section's views round as the lift settles.

    At its one speed the table reaches the section's next view whenever the phase says,
    up to a view's spacing after the lift has moved and settled (every section alike
    where the pitch is even: 103 ms of each 10 mm section change at the shipped speeds).
    Slowed during the lift's move by what it turned past the view before (and
    :data:`ARRIVE_EARLY_S`), it brings that view round instead: the views stay at their
    planned angles, taken at the turn's speed.

    Args:
        config: the turntable's configuration.
        speed_deg_s: the turn's speed.
        angles_deg: the section's planned angles.
        reach_deg: the unwrapped angle the table, at its speed, would reach by the time
            the section's first view can start (lift moved and settled, the view's lead).
        within_s: the lift move's duration.

    Returns:
        The slow-down, or None to wait for the next view (the configuration leaves
        ``continuous_retime`` off, the view comes within :data:`ARRIVE_EARLY_S`, or no
        slow-down within the move loses enough).
    """
    if not config.continuous_retime:
        return None
    _, ahead_deg = next_view(angles_deg, reach_deg)
    if ahead_deg - reach_deg <= speed_deg_s * ARRIVE_EARLY_S:
        return None
    behind_deg = min((reach_deg - a) % 360.0 for a in angles_deg)
    return slow_down(config, speed_deg_s, behind_deg + speed_deg_s * ARRIVE_EARLY_S, within_s)


def spin_up_s(config: TurntableConfig, speed_deg_s: float) -> tuple[float, float]:
    """Return a continuous turn's ramp-up: its duration and the angle turned meanwhile."""
    ramp, cruise = spin_rates(config, speed_deg_s)
    steps_per_deg = cruise / speed_deg_s if speed_deg_s else 1.0
    turned = sum(rate * SPIN_TICK_S for rate in [*ramp, cruise]) / steps_per_deg
    return (len(ramp) + 1) * SPIN_TICK_S, turned


ROOM_LIGHT_THREADS = 2
"""Threads one continuous view's processing keeps busy: its two laser-off frames are
matched side by side (``room_light``)."""
MAX_VIEW_WORKERS = 2
"""The most continuous views processed at once (:func:`view_workers`)."""


def view_workers(cores: int | None = None) -> int:
    """Return how many continuous views the device processes at once on ``cores`` cores.

    Each view keeps :data:`ROOM_LIGHT_THREADS` busy, so a Pi's four cores process two
    views side by side (each 2-4x slower than on an x86 core): the table's time between
    views (125 ms at the shipped speed) is then met with a view's processing up to twice
    that. A 2-core machine processes one at a time, as it gains nothing by two. At most
    :data:`MAX_VIEW_WORKERS`: the capture, the camera and the link need a core too.

    Args:
        cores: the cores the device program may use; None: those this process may run on.

    Returns:
        At least 1.
    """
    if cores is None:
        usable = os.sched_getaffinity(0) if hasattr(os, "sched_getaffinity") else None
        cores = len(usable) if usable is not None else os.cpu_count() or 1
    return max(1, min(MAX_VIEW_WORKERS, cores // ROOM_LIGHT_THREADS))


CONTINUOUS_PIPELINE_DEPTH = 16
"""Captured views a continuous scan holds for its extraction thread (``acquisition``),
whose capture cannot wait: a view held up misses its angle and waits a turn. The thread
also brings each view's laser-off frames to the laser-on frame's instant (``room_light``),
which can take longer than the table's time between views (8 a turn at one turn a
second: 125 ms); it catches up while the lift moves between sections. 16 views of three
1536x864 frames hold 64 MB."""


def _continuous_time(
    config: DeviceConfig,
    plan: ScanPlan,
    processing_s_per_view: float,
    exposure_us: float | None,
    workers: int = 1,
) -> ScanTime:
    """Return the modelled time of a continuous plan, as the loop takes it.

    The table ramps up once and turns on at ``continuous_speed_deg_s`` through every
    section; each section waits for its lift move and the lift's settle (the table slowed
    during the move where that brings a view round as the lift settles:
    :func:`section_retiming`), then takes its views in the order the table reaches them
    (:func:`next_view`), each one started a lead before its angle comes round; with
    ``continuous_off_frames = "next-turn"`` a view is sent a turn later, when its laser-off
    frame has come round. Each view is handed to the extraction stage, whose queue holds
    :data:`CONTINUOUS_PIPELINE_DEPTH` views: ``workers`` threads process them in turn, each
    view as soon as one is free, and one thread sends them in the plan's order, taking the
    next view off the queue once the one before it is sent. Where the processing outlasts
    the table's time to the next view and the lift moves do not take up the backlog, the
    queue fills and holds the capture up, and the views still to take wait for their angles
    to come round again. The mechanical minimum: the ramp, the lift moves and settles, each
    section's turn from its first view to its last (and the turn on, next-turn), and one
    view's frames.
    """
    table = config.turntable
    if table.continuous_speed_deg_s <= 0:
        raise ValueError("this configuration turns no continuous scan: continuous_speed_deg_s 0")
    speed = turn_speed_deg_s(table, table.continuous_speed_deg_s)
    timing = config_frame_timing(config, exposure_us)
    next_turn = table.continuous_off_frames == "next-turn"
    lead_s, view_s = lit_capture_s(timing) if next_turn else view_capture_s(timing)
    turn_s = 360.0 / speed
    ramp_s, angle = spin_up_s(table, speed)
    now_s = ramp_s
    steps_per_mm = lift_steps_per_mm(config.lift)
    lift_at: int | None = None
    lost_deg = 0.0  # what the table's slow-downs beside the lift's moves lost
    lift_total = settle_total = frames_total = turning = minimum = 0.0
    finished_s = delivered_s = 0.0
    free_s = [0.0] * max(1, workers)  # when each processing thread is next free
    taken_s: list[float] = []  # when the sending thread took each view off the queue

    def hand_over(sent_s: float) -> float:
        """Queue a view sent at ``sent_s`` for the extraction stage; return when the
        hand-over returns: at once, or, with the queue full, when the sending thread takes
        the view :data:`CONTINUOUS_PIPELINE_DEPTH` places earlier (the capture waits so)."""
        nonlocal delivered_s, finished_s
        taken_s.append(max(sent_s, delivered_s))
        worker = min(range(len(free_s)), key=free_s.__getitem__)
        free_s[worker] = max(sent_s, free_s[worker]) + processing_s_per_view
        delivered_s = max(delivered_s, free_s[worker])
        finished_s = sent_s
        earlier = len(taken_s) - 1 - CONTINUOUS_PIPELINE_DEPTH
        return max(sent_s, taken_s[earlier]) if earlier >= 0 else sent_s

    for section in plan.sections:
        views = [v for v in plan.views if v.section == section]
        lift_to = round(views[0].z_mm * steps_per_mm)
        pending = [v.angle_deg for v in views]
        if lift_at is not None and lift_to != lift_at:
            lift_s = lift_move_s(config.lift, lift_at, lift_to)
            move_s = lift_s + config.lift.settle_s
            reach = angle - lost_deg + speed * (now_s + move_s + lead_s - ramp_s)
            if retiming := section_retiming(table, speed, pending, reach, lift_s):
                lost_deg += retiming.loss_deg
            lift_total += lift_s
            settle_total += config.lift.settle_s
            now_s += move_s
            minimum += move_s
        lift_at = lift_to
        first_s = None
        lit_done: list[float] = []
        while pending:
            reach = angle - lost_deg + speed * (now_s - ramp_s) + speed * lead_s
            k, target = next_view(pending, reach)
            start_s = ramp_s + (target - angle + lost_deg) / speed - lead_s
            first_s = start_s if first_s is None else first_s
            now_s = start_s + view_s
            frames_total += view_s
            pending.pop(k)
            if next_turn:
                lit_done.append(now_s)
            else:  # a full queue holds the capture up: the next view may wait a turn
                now_s = hand_over(now_s)
        # A next-turn view is sent once its laser-off frame, a turn on, has arrived.
        for done_s in lit_done:
            now_s = hand_over(done_s + turn_s)
        assert first_s is not None
        turning += now_s - first_s
        minimum += now_s - first_s
    modelled = max(finished_s, delivered_s)
    if processing_s_per_view > 0:  # a full queue's waits are not mechanics
        minimum = _continuous_time(config, plan, 0.0, exposure_us).mechanical_minimum_s - ramp_s
    return ScanTime(
        modelled_s=modelled,
        mechanical_minimum_s=ramp_s + minimum,
        turntable_s=ramp_s + turning,
        lift_s=lift_total,
        settle_s=settle_total,
        frames_s=frames_total,
        processing_s=modelled - finished_s,
        views=len(plan.views),
    )


def lift_move_s(config: LiftConfig, from_steps: int, to_steps: int) -> float:
    """Return the duration of a lift move between two microstep positions."""
    return float(lift_intervals_s(config, abs(to_steps - from_steps)).sum())


def turntable_move_s(
    config: TurntableConfig, position_steps: int, engaged: bool, angle_deg: float
) -> tuple[tuple[int, ...], float, float]:
    """Return a turntable move's runs, its first run's duration and the rest's.

    The runs follow the steppers' own rule (:func:`lamina_device.motion.turntable_runs`):
    the short way, arriving counter-clockwise.
    """
    runs = turntable_runs(config, position_steps, engaged, angle_deg)
    runs_s = [float(turntable_intervals_s(config, abs(run)).sum()) for run in runs]
    return runs, (runs_s[0] if runs_s else 0.0), sum(runs_s[1:])


def _moves_s(config: DeviceConfig, plan: ScanPlan) -> list[_ViewMoves]:
    """Return each view's moves, in plan order, from the axes' own profiles and rules."""
    steps_per_mm = lift_steps_per_mm(config.lift)
    lift_at: int | None = None  # the lift homes first: the move from home is not modelled
    table_at, engaged = 0, False
    out: list[_ViewMoves] = []
    for view in plan.views:
        lift_to = round(view.z_mm * steps_per_mm)
        lift_s = 0.0 if lift_at is None else lift_move_s(config.lift, lift_at, lift_to)
        lift_at = lift_to
        runs, first_s, rest_s = turntable_move_s(
            config.turntable, table_at, engaged, view.angle_deg
        )
        if runs:
            table_at += sum(runs)
            engaged = runs[-1] > 0
        out.append(_ViewMoves(lift_s, first_s, rest_s))
    return out


def estimate_scan_time(
    config: DeviceConfig,
    plan: ScanPlan,
    processing_s_per_view: float = 0.0,
    exposure_us: float | None = None,
    axes_together: bool = True,
    workers: int = 1,
) -> ScanTime:
    """Return the modelled duration of ``plan`` on the hardware ``config`` describes.

    Args:
        config: the device's configuration (axes, settle, camera timing).
        plan: the views to acquire, in order.
        processing_s_per_view: extraction and sending of one view (the worker thread).
        exposure_us: the exposure in use (default: the configured one at start).
        axes_together: the lift moves beside the turntable (the box's steppers do,
            :func:`lamina_device.motion.move_axes`); False: one after the other
            (stop-and-go plans only).
        workers: continuous views processed at once (:func:`view_workers`); a
            stop-and-go plan processes one view at a time.

    Returns:
        The modelled time, the mechanical minimum and their parts.

    Raises:
        ValueError: a continuous plan on a configuration without a continuous speed.
    """
    if not plan.views:
        return ScanTime(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0)
    if plan.continuous:
        return _continuous_time(config, plan, processing_s_per_view, exposure_us, workers)
    camera = config.camera
    exposure = camera.exposure_us if exposure_us is None else exposure_us
    frames_s = FRAMES_PER_VIEW * frame_wait_s(camera.frame_duration_us, exposure)
    settle_s = max(config.turntable.settle_s, config.lift.settle_s)
    moves = _moves_s(config, plan)
    fixed_s = settle_s + frames_s
    minimum = sum(m.together_s() + fixed_s for m in moves)
    mechanics = [(m.together_s() if axes_together else m.sequential_s()) + fixed_s for m in moves]
    # The worker extracts view k while view k + 1 is acquired: it holds the loop up only
    # where it is slower than the mechanics, and the last view's processing always shows.
    finished_s = 0.0
    worker_free_s = 0.0
    for view_s in mechanics:
        finished_s += view_s
        worker_free_s = max(worker_free_s, finished_s) + processing_s_per_view
    modelled = max(finished_s, worker_free_s)
    return ScanTime(
        modelled_s=modelled,
        mechanical_minimum_s=minimum,
        turntable_s=sum(m.table_first_s + m.table_rest_s for m in moves),
        lift_s=sum(m.lift_s for m in moves),
        settle_s=settle_s * len(moves),
        frames_s=frames_s * len(moves),
        processing_s=modelled - finished_s,
        views=len(moves),
    )
