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
"""

from __future__ import annotations

import logging
import queue
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np

from lamina_device.camera import CameraError, ColourCamera
from lamina_device.extract import ExtractSettings, extract, to_segment
from lamina_device.hardware import Hardware
from lamina_device.motion import move_axes
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
    """A worker thread applying ``handle`` to queued items in order.

    After a failure it keeps draining the queue (so the producer never blocks) and
    :meth:`raise_error` re-raises the failure in the producer's thread.
    """

    _END = object()

    def __init__(self, handle: Callable[[_Captured], None], depth: int = PIPELINE_DEPTH) -> None:
        self._handle = handle
        self._queue: queue.Queue[object] = queue.Queue(maxsize=depth)
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="scan-extract", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while (item := self._queue.get()) is not self._END:
            if self._error is None:
                try:
                    self._handle(item)  # type: ignore[arg-type]
                except BaseException as exc:  # re-raised in the scan's thread
                    self._error = exc

    def raise_error(self) -> None:
        """Re-raise the worker's failure, if any, in the calling thread."""
        if self._error is not None:
            raise self._error

    def put(self, item: _Captured) -> None:
        """Queue ``item`` (blocks while the queue is full); raise an earlier worker failure."""
        self.raise_error()
        self._queue.put(item)

    def finish(self) -> None:
        """Let the worker handle everything queued, then stop it."""
        self._queue.put(self._END)
        self._thread.join()


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

    Returns:
        How many segments were handed to ``on_segment``.

    Raises:
        ScanAborted: ``control`` aborted the scan; views captured before it were sent.
    """
    control = control or ScanControl()
    total = len(plan.views)
    started_s = time.monotonic()

    def handle(item: _Captured) -> None:
        if sink is not None:
            sink(target, item.view, item.index, item.on, item.off)
        view = item.view
        points = extract(item.on, item.off, settings)
        on_segment(
            to_segment(
                points, target, view.section, item.index, view.z_mm, view.angle_deg, item.rgb_off
            )
        )
        if on_progress is not None:
            on_progress(_progress(target, item, total, started_s, control))

    hardware.place(target)
    stage = _Stage(handle)
    index_in_section = list(numbers) if numbers is not None else views_in_section(plan)
    if len(index_in_section) != total:
        raise ValueError(f"{len(index_in_section)} view numbers for {total} views")
    captured = 0
    ok = False
    try:
        try:
            for done, view in enumerate(plan.views, start=1):
                control.checkpoint()
                move_axes(hardware.lift, hardware.turntable, view.z_mm, view.angle_deg)
                hardware.settle()
                on, off, rgb_off = capture_views(hardware, colour)
                stage.put(_Captured(view, index_in_section[done - 1], done, on, off, rgb_off))
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
