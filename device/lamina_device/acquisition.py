"""Acquisition: a scan plan run as a pipeline (move, settle, capture off/on, extract, send).

The main thread drives the mechanics and the camera; a worker thread extracts each
view's stripe and hands the segment on, so the next move and capture overlap the
extraction and sending of the previous view. The queue between them is short
(memory stays bounded) and first-in first-out (segments keep the plan's order); an
exception on either side ends the scan and is raised to the caller.

The laser is on only while its frame is exposed (thesis appendix A asks for
automatic shut-off safeguards): it is switched on just before the laser-on capture
and off straight after, and off again whatever goes wrong. The lift goes home at
the end of every scan, finished, failed or aborted.

A continuous plan (``ScanPlan.mode``, issue 22) is taken without stopping the table: it
ramps up once and turns at constant speed through every section while the camera
streams; the lift moves between sections with the table still turning. Each view is
three frames in a row, laser off, on, off: the table turns a few degrees from one to the
next, so the extraction stage brings both off frames to the laser-on frame's instant
before it takes their room light from it
(:func:`~lamina_device.room_light.laser_off_reference`). That keeps two cores busy for
longer than the table takes from one view to the next on a Pi, so where there are cores
for it (:func:`~lamina_device.timing.view_workers`: a Pi's four) two views are processed
at once, and sent in their order. Each view's
angle is the table's step count when the laser-on frame exposed the stripe's middle row
(the sensor's timestamp on the step clock), not the planned angle, which the view is
only started to come near.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import threading
import time
from collections import Counter
from collections.abc import Callable, Generator, Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import closing
from dataclasses import dataclass

import numpy as np

from lamina_device.camera import CameraError, ColourCamera, TimedCamera, TimedFrame
from lamina_device.extract import ExtractSettings, StripePoints, extract, to_segment
from lamina_device.hardware import Hardware
from lamina_device.motion import SpinningTable, TimedLift, lift_steps_per_mm, move_axes
from lamina_device.room_light import laser_off_reference
from lamina_device.timing import (
    CONTINUOUS_PIPELINE_DEPTH,
    laser_pulse,
    lift_move_s,
    lit_capture_s,
    next_turn_start_ns,
    next_view,
    section_retiming,
    turn_speed_deg_s,
    view_capture_s,
    view_workers,
)
from lamina_shared.messages import Progress
from lamina_shared.types import ScanPlan, Segment, ViewSpec

log = logging.getLogger(__name__)

PIPELINE_DEPTH = 2
"""Captured views waiting for extraction: enough to keep both stages busy, little memory."""


class ScanAborted(Exception):
    """The scan was aborted through its :class:`ScanControl`; the laser is off, the lift home."""


class ScanControl:
    """Pause, resume or abort a running scan from another thread (thread-safe).

    The scan checks it between views: a pause takes effect after the current view's
    capture, with the laser off, and an abort also ends a pause.
    """

    def __init__(self) -> None:
        self._changed = threading.Condition()
        self._paused = False
        self._aborted = False

    @property
    def paused(self) -> bool:
        """Return True while a pause is requested."""
        return self._paused

    def pause(self) -> None:
        """Hold the scan at the next view boundary."""
        self._request(paused=True)

    def resume(self) -> None:
        """Let a paused scan go on."""
        self._request(paused=False)

    def abort(self) -> None:
        """End the scan at the next view boundary (or at once if it is paused)."""
        self._request(aborted=True)

    def _request(self, paused: bool | None = None, aborted: bool | None = None) -> None:
        # One place changes the flags, under the lock, and wakes a waiting checkpoint.
        with self._changed:
            if paused is not None:
                self._paused = paused
            if aborted is not None:
                self._aborted = aborted
            self._changed.notify_all()

    def checkpoint(self) -> None:
        """Block while paused; raise ScanAborted if an abort was requested."""
        with self._changed:
            self._changed.wait_for(lambda: self._aborted or not self._paused)
            if self._aborted:
                raise ScanAborted("scan aborted")


FrameSink = Callable[[str, ViewSpec, int, np.ndarray, np.ndarray], None]
"""Receives (target, view, index in section, laser-on frame, laser-off frame): recording."""


@dataclass(frozen=True)
class _Captured:
    """One view's frames on their way from the capture stage to the extraction stage."""

    view: ViewSpec
    index: int
    done: int
    on: np.ndarray
    off: np.ndarray
    rgb_off: np.ndarray | None = None
    timed: TimedFrame | None = None
    """The laser-on frame's timing (continuous scans: the angle comes from it)."""
    off_after: np.ndarray | None = None
    """A continuous view's second laser-off frame, ``off`` its first: the extraction
    thread makes their room light at the laser-on frame's instant (the capture thread
    is not held up by it)."""
    count_deg: float = 0.0
    """The table's step count where the view was taken (stop-and-go; unwrapped degrees)."""


@dataclass(frozen=True)
class _Processed:
    """One view's stripe points, and the laser-off frame (or room light) they came from."""

    points: StripePoints
    off: np.ndarray


def grab_grid(hardware: Hardware) -> np.ndarray:
    """Capture the calibration board image with the laser off."""
    hardware.place("grid")
    hardware.laser.off()
    return hardware.camera.capture()


def capture_pair(hardware: Hardware) -> tuple[np.ndarray, np.ndarray]:
    """Capture one view's laser-off then laser-on frame; the laser ends off."""
    on, off, _ = capture_views(hardware, colour=False)
    return on, off


def capture_views(
    hardware: Hardware, colour: bool
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Capture one view's laser-off then laser-on frame, and with ``colour`` the off frame's sRGB.

    The colour comes from the laser-off exposure itself (the Pi's YUV420 chroma), so
    the stripe extraction sees the same frames with or without colour.
    """
    hardware.laser.off()
    camera = hardware.camera
    rgb_off: np.ndarray | None = None
    if colour:
        if not isinstance(camera, ColourCamera):
            raise CameraError("this camera gives no colour: scan without colour")
        off, rgb_off = camera.capture_colour()
    else:
        off = camera.capture()
    try:
        hardware.laser.on()
        on = hardware.camera.capture()
    finally:
        hardware.laser.off()
    return on, off, rgb_off


class _Stage:
    """Views processed on ``workers`` threads, then handed on one by one in their order.

    ``process`` (the room light and the extraction: the costly part, free of shared
    state) runs on a pool of ``workers`` threads, each view as soon as one is free;
    ``deliver`` (the view's angle, recording, sending) runs on one thread, in the order
    the views were put. A view is submitted when it is put, so the queue bounds the views
    held, processed or waiting. After a failure the stage keeps draining the queue (so the
    producer never blocks) and :meth:`raise_error` re-raises the failure in the
    producer's thread.
    """

    def __init__(
        self,
        process: Callable[[_Captured], _Processed],
        deliver: Callable[[_Captured, _Processed], None],
        depth: int = PIPELINE_DEPTH,
        workers: int = 1,
    ) -> None:
        self._process = process
        self._deliver = deliver
        self._pool = (
            ThreadPoolExecutor(workers, thread_name_prefix="scan-process") if workers > 1 else None
        )
        # Each view with its processing under way (None: done on delivery); None ends.
        self._queue: queue.Queue[tuple[_Captured, Future[_Processed] | None] | None]
        self._queue = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="scan-extract", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while (entry := self._queue.get()) is not None:
            item, pending = entry
            if self._error is not None:
                if pending is not None:
                    pending.cancel()  # nothing after a failure is sent: spare the work
                continue
            try:
                processed = self._process(item) if pending is None else pending.result()
                self._deliver(item, processed)
            except BaseException as exc:  # re-raised in the scan's thread
                self._error = exc

    def raise_error(self) -> None:
        """Re-raise the stage's failure, if any, in the calling thread."""
        if self._error is not None:
            raise self._error

    def put(self, item: _Captured) -> None:
        """Queue ``item`` (blocks while the queue is full); raise an earlier failure."""
        self.raise_error()
        pending: Future[_Processed] | None = None
        if self._pool is not None:
            pending = self._pool.submit(self._process, item)
        self._queue.put((item, pending))

    def finish(self) -> None:
        """Let the stage process and deliver everything queued, then stop its threads."""
        self._queue.put(None)
        self._thread.join()
        if self._pool is not None:
            self._pool.shutdown(wait=True)


def _progress(
    target: str, item: _Captured, total: int, started_s: float, control: ScanControl
) -> Progress:
    elapsed_s = time.monotonic() - started_s
    state = "done" if item.done == total else "paused" if control.paused else "scanning"
    return Progress(target, item.done, total, item.view.section, state, elapsed_s, item.done)


def acquire(
    hardware: Hardware,
    target: str,
    plan: ScanPlan,
    on_segment: Callable[[Segment], None],
    on_progress: Callable[[Progress], None] | None = None,
    settings: ExtractSettings | None = None,
    sink: FrameSink | None = None,
    control: ScanControl | None = None,
    numbers: Sequence[int] | None = None,
    colour: bool = False,
    resumed: bool = False,
    workers: int | None = None,
) -> int:
    """Scan ``target`` along ``plan``; return the number of segments produced.

    Args:
        hardware: the device's hardware.
        target: ``cylinder`` or ``object``.
        plan: the views to visit, in order.
        on_segment: called with each view's segment, in plan order, from the worker thread.
        on_progress: called after each view's segment, from the worker thread.
        settings: extraction settings (ExtractSettings() by default: Otsu, p = 1, noise gate).
        sink: called with the raw frames of each view (recording), from the worker thread.
        control: pause, resume and abort from another thread.
        numbers: each view's index in its section (:func:`views_in_section` of the
            whole scan when ``plan`` is the part of it still to acquire); by default
            ``plan``'s own numbering.
        colour: sample each point's sRGB from the view's laser-off frame.
        resumed: the scan goes on from views already held, the target still standing
            where it was (:meth:`~lamina_device.hardware.Hardware.place`).
        workers: continuous views processed at once; by default as many as this
            machine's cores allow (:func:`~lamina_device.timing.view_workers`).

    Returns:
        How many segments were handed to ``on_segment``.

    Raises:
        ScanAborted: ``control`` aborted the scan; views captured before it were sent.
    """
    control = control or ScanControl()
    total = len(plan.views)
    started_s = time.monotonic()

    if plan.continuous and (problem := continuous_problem(hardware, plan, colour)):
        raise CameraError(f"this device cannot scan continuously: {problem}")

    def process(item: _Captured) -> _Processed:
        off = item.off
        if item.off_after is not None:
            off = laser_off_reference(item.off, item.on, item.off_after)
        return _Processed(extract(item.on, off, settings), off)

    def deliver(item: _Captured, processed: _Processed) -> None:
        view, count_deg = item.view, item.count_deg
        points, off = processed.points, processed.off
        if item.timed is not None:
            count_deg = _stripe_count_deg(hardware, points, item.timed)
            view = ViewSpec(view.section, view.z_mm, _within_turn_deg(count_deg))
        if sink is not None:
            sink(target, view, item.index, item.on, off)
        turns = whole_turns(count_deg, view.angle_deg)
        segment = to_segment(
            points, target, view.section, item.index, view.z_mm, view.angle_deg,
            item.rgb_off, turns,
        )  # fmt: skip
        on_segment(segment)
        if on_progress is not None:
            on_progress(_progress(target, item, total, started_s, control))

    hardware.place(target, again=resumed)
    if plan.continuous:
        stage = _Stage(process, deliver, CONTINUOUS_PIPELINE_DEPTH, workers or view_workers())
    else:  # a view's extraction takes milliseconds against a move's second or more
        stage = _Stage(process, deliver, PIPELINE_DEPTH)
    index_in_section = list(numbers) if numbers is not None else views_in_section(plan)
    if len(index_in_section) != total:
        raise ValueError(f"{len(index_in_section)} view numbers for {total} views")
    captured = 0
    ok = False
    try:
        try:
            take = _take_continuous if plan.continuous else _take_stopping
            # Closed here, not when collected: its own cleanup stops a turning table.
            with closing(take(hardware, plan, index_in_section, control, colour)) as views:
                for done, item in enumerate(views, 1):
                    stage.put(dataclasses.replace(item, done=done))
                    captured = done
        finally:
            hardware.laser.off()
            # Views already captured are still extracted and sent: nothing recorded is lost.
            stage.finish()
        stage.raise_error()
        ok = True
    except ScanAborted:
        log.info("scan of %s aborted after %d of %d views", target, captured, total)
        raise ScanAborted(f"scan of {target} aborted after {captured} of {total} views") from None
    finally:
        hardware.laser.off()
        _home(hardware, raise_errors=ok)
    return total


def _take_stopping(
    hardware: Hardware, plan: ScanPlan, numbers: list[int], control: ScanControl, colour: bool
) -> Generator[_Captured, None, None]:
    """Yield each view of a stop-and-go plan: move, settle, laser-off and laser-on frames."""
    for view, number in zip(plan.views, numbers, strict=True):
        control.checkpoint()
        move_axes(hardware.lift, hardware.turntable, view.z_mm, view.angle_deg)
        hardware.settle()
        on, off, rgb_off = capture_views(hardware, colour)
        count_deg = hardware.turntable.count_deg
        yield _Captured(view, number, 0, on, off, rgb_off, count_deg=count_deg)


def continuous_problem(hardware: Hardware, plan: ScanPlan, colour: bool = False) -> str | None:
    """Return why ``hardware`` cannot take ``plan`` continuously, or None when it can.

    The table must turn by itself at constant speed (its pulses timed by the pin factory),
    the camera must stream timestamped frames, colour is not offered (the laser-off frames
    are taken degrees away from the stripe), and the laser pulses a view asks for must be
    accepted by the watchdog (:meth:`lamina_device.safety.LaserWatchdog.pulse_problem`).
    """
    table, camera = hardware.turntable, hardware.camera
    if not isinstance(table, SpinningTable):
        return "its turntable cannot turn at constant speed by itself"
    if problem := table.spin_problem():
        return problem
    if not isinstance(camera, TimedCamera):
        return "its camera does not stream timestamped frames"
    if colour:
        return (
            "colour needs a stop-and-go scan (a continuous view's laser-off frames are "
            "taken degrees away from its stripe)"
        )
    watchdog = hardware.watchdog
    if watchdog is not None and plan.views:
        per_turn = max(Counter(view.section for view in plan.views).values())
        every_s = 360.0 / (per_turn * table.spin_speed_deg_s)
        if problem := watchdog.pulse_problem(laser_pulse(camera.frame_timing), every_s):
            return f"the laser watchdog refuses its pulses: {problem}"
    return None


def _take_continuous(
    hardware: Hardware, plan: ScanPlan, numbers: list[int], control: ScanControl, colour: bool
) -> Generator[_Captured, None, None]:
    """Yield each view of a continuous plan, section by section, the table turning throughout.

    The lift goes to the first section before the table starts; each later section waits
    for its lift move and the lift's settle while the table turns on. A section's views
    are taken in the order the table brings them round (:func:`~lamina_device.timing.next_view`),
    each started a lead before its angle so that the laser-on frame meets it. A pause
    stops the table (laser off) and starts it again on resume.
    """
    table, camera = hardware.turntable, hardware.camera
    assert isinstance(table, SpinningTable) and isinstance(camera, TimedCamera)
    next_turn = table.off_frames == "next-turn"
    lead_s, _ = (lit_capture_s if next_turn else view_capture_s)(camera.frame_timing)
    speed = table.spin_speed_deg_s
    sections: dict[int, list[tuple[ViewSpec, int]]] = {}
    for view, number in zip(plan.views, numbers, strict=True):
        sections.setdefault(view.section, []).append((view, number))
    first = plan.views[0]
    hardware.lift.move_to(first.z_mm)
    hardware.settle_lift()
    table.spin(speed)
    try:
        for views in sections.values():
            z_mm = views[0][0].z_mm
            if hardware.lift.z_mm != z_mm:
                _lift_beside_turn(hardware, table, z_mm, [v.angle_deg for v, _ in views], lead_s)
                hardware.settle_lift()
            lit_views: list[tuple[ViewSpec, int, TimedFrame]] = []
            while views:
                if control.paused:
                    table.stop_spin()
                    control.checkpoint()
                    table.spin(speed)
                    # Laser-on frames waiting for their turn are taken again after a pause.
                    views += [(view, number) for view, number, _ in lit_views]
                    lit_views.clear()
                control.checkpoint()
                reach = table.angle_at(hardware.clock_ns()) + speed * lead_s
                k, angle = next_view([view.angle_deg for view, _ in views], reach)
                view, number = views.pop(k)
                hardware.sleep_until_ns(table.time_at(angle) - round(lead_s * 1e9))
                if next_turn:
                    lit_views.append((view, number, capture_lit(hardware, camera)))
                    continue
                lit, before, after = capture_moving(hardware, camera)
                yield _Captured(view, number, 0, lit.image, before, None, lit, off_after=after)
            for view, number, lit in lit_views:
                off = capture_next_turn(hardware, camera, lit)
                yield _Captured(view, number, 0, lit.image, off, None, lit)
    finally:
        hardware.laser.off()
        table.stop_spin()


def _lift_beside_turn(
    hardware: Hardware, table: SpinningTable, z_mm: float, angles_deg: list[float], lead_s: float
) -> None:
    """Move the lift to the next section, slowing the table meanwhile where that brings one
    of the section's views round as the lift settles
    (:func:`~lamina_device.timing.section_retiming`).

    The table's new rates are made on the lift move's own time line (a second thread
    would make the lift's pulses late); a lift or a configuration that cannot time them
    moves alone, and the first view is waited for.
    """
    lift, config = hardware.lift, hardware.timing
    if config is None or not isinstance(lift, TimedLift):
        lift.move_to(z_mm)
        return
    per_mm = lift_steps_per_mm(config.lift)
    move_s = lift_move_s(config.lift, round(lift.z_mm * per_mm), round(z_mm * per_mm))
    speed = turn_speed_deg_s(config.turntable, table.spin_speed_deg_s)
    ready_s = move_s + hardware.lift_settle_wait_s + lead_s
    reach = table.angle_at(hardware.clock_ns()) + speed * ready_s
    retiming = section_retiming(config.turntable, speed, angles_deg, reach, move_s)
    lift.move_beside(z_mm, [] if retiming is None else retiming.calls(table.set_rate))


def capture_moving(
    hardware: Hardware, camera: TimedCamera
) -> tuple[TimedFrame, np.ndarray, np.ndarray]:
    """Capture laser-off, laser-on and laser-off frames in a row; the laser ends off.

    Returns:
        The laser-on frame with its timing, and the laser-off frames before and after it
        (:func:`~lamina_device.room_light.laser_off_reference` makes its room light of them).
    """
    laser = hardware.laser
    laser.off()
    before = camera.capture_timed()
    try:
        laser.on()
        lit = camera.capture_timed()
    finally:
        laser.off()
    after = camera.capture_timed()
    return lit, before.image, after.image


def capture_lit(hardware: Hardware, camera: TimedCamera) -> TimedFrame:
    """Capture one laser-on frame; the laser ends off (a next-turn view's first turn)."""
    laser = hardware.laser
    try:
        laser.on()
        return camera.capture_timed()
    finally:
        laser.off()


NEXT_TURN_TRIES = 3
"""Turns a next-turn view's laser-off frame may be missed before the scan fails."""


def capture_next_turn(hardware: Hardware, camera: TimedCamera, lit: TimedFrame) -> np.ndarray:
    """Return the laser-off frame a turn after ``lit``: the table at ``lit``'s angle again.

    The frame is the streamed one that starts nearest a turn after ``lit`` started
    (:func:`~lamina_device.timing.next_turn_start_ns`); it is waited for from half a
    period before it is due to arrive. A frame that started earlier (one a camera kept
    in its buffers) is passed over; one that started later than half a period after it
    (the device was held up) missed the angle, which then comes round again a turn on.

    Raises:
        CameraError: the angle was missed :data:`NEXT_TURN_TRIES` turns running.
    """
    table = hardware.turntable
    assert isinstance(table, SpinningTable)
    timing = camera.frame_timing
    half_ns = 0.5 * timing.period_s * 1e9
    middle_ns = lit.row_middle_ns(0.5 * (lit.image.shape[0] - 1))
    angle = table.angle_at(middle_ns)
    wait_ns = round(timing.span_s * 1e9 - half_ns)
    turns = 1
    for _ in range(NEXT_TURN_TRIES):
        turn_ns = table.time_at(angle + 360.0 * turns) - middle_ns
        start_ns = next_turn_start_ns(timing, lit.start_ns, turn_ns)
        turns += 1
        if start_ns + wait_ns < hardware.clock_ns():
            continue  # already past: a turn on
        hardware.sleep_until_ns(start_ns + wait_ns)
        frame = camera.capture_timed()
        while frame.start_ns < start_ns - half_ns:
            frame = camera.capture_timed()
        if frame.start_ns <= start_ns + half_ns:
            return frame.image
    raise CameraError(
        f"the laser-off frame a turn after a view's laser-on frame was missed "
        f"{NEXT_TURN_TRIES} turns running (the device is too busy to catch it): set "
        '[turntable] continuous_off_frames = "interleaved", or scan stop-and-go'
    )


def _stripe_count_deg(hardware: Hardware, points: StripePoints, lit: TimedFrame) -> float:
    """Return the table's step count (unwrapped degrees) when the laser-on frame exposed
    the stripe's middle row.

    The rolling shutter exposes each row at its own time; one angle serves a segment, so
    it is taken at the median row of the stripe found (the frame's middle row if none).
    """
    table = hardware.turntable
    assert isinstance(table, SpinningTable)
    rows = points.rows
    row = float(np.median(rows)) if len(rows) else 0.5 * (lit.image.shape[0] - 1)
    return table.angle_at(lit.row_middle_ns(row))


def _within_turn_deg(count_deg: float) -> float:
    """Return a step count's angle within the turn, in [0, 360)."""
    angle = count_deg % 360.0
    return 0.0 if angle >= 360.0 else angle  # a hair below 0 wraps to 360.0 in floats


def whole_turns(count_deg: float, angle_deg: float) -> int:
    """Return the whole turns that take a view's ``angle_deg`` to the step count
    ``count_deg`` (a segment's ``turns``: the count is ``angle_deg + 360 * turns``).

    A stop-and-go view's count is its commanded angle's to within a microstep, whatever
    turn the table is on; a continuous view's angle is its count's within the turn.
    """
    return round((count_deg - angle_deg) / 360.0)


def row_turn_deg(hardware: Hardware) -> float:
    """Return the table's turn from one image row's exposure to the next's in a continuous
    scan (degrees): its speed times the rolling shutter's row time.

    :func:`_stripe_count_deg` gives a view the angle of its stripe's median row; a point
    ``d`` rows below it was exposed ``d`` times this later. Across a stripe of 200 rows
    at a turn a second that is 0.7 degrees, 1 mm at 80 mm from the axis: the host turns
    each point by its own share (the WELCOME's ``row_turn_deg``).
    """
    table, camera = hardware.turntable, hardware.camera
    assert isinstance(table, SpinningTable) and isinstance(camera, TimedCamera)
    return table.spin_speed_deg_s * camera.frame_timing.row_s


def off_frames(hardware: Hardware) -> str:
    """Return where a continuous scan's laser-off frames come from (``OFF_FRAMES``).

    The host keeps it with each scan: frames a turn of the count later are misregistered
    on a table that turns short of its count, which only the host's calibration shows.
    """
    table = hardware.turntable
    assert isinstance(table, SpinningTable)
    return table.off_frames


def views_in_section(plan: ScanPlan) -> list[int]:
    """Return each view's index within its section: the one place views are numbered."""
    seen: dict[int, int] = {}
    out = []
    for view in plan.views:
        out.append(seen.get(view.section, 0))
        seen[view.section] = out[-1] + 1
    return out


def _home(hardware: Hardware, raise_errors: bool) -> None:
    """Send the lift home; while another error is on its way out, only log a failure."""
    try:
        hardware.lift.home()
    except Exception:
        if raise_errors:
            raise
        log.exception("the lift could not go home after the scan failed")
