"""Running a scan plan: move, capture the laser-off/laser-on pair, extract, hand on.

The laser is on only while its frame is exposed (thesis appendix A asks for
automatic shut-off safeguards): it is switched on just before the laser-on capture
and off straight after, and off again whatever goes wrong.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lamina_device.extract import ExtractSettings, extract, to_segment
from lamina_device.hardware import Hardware
from lamina_shared.types import ScanPlan, Segment, ViewSpec


@dataclass(frozen=True)
class Progress:
    """Where a running scan is: ``done`` of ``total`` views."""

    target: str
    done: int
    total: int
    section: int


FrameSink = Callable[[str, ViewSpec, int, np.ndarray, np.ndarray], None]
"""Receives (target, view, index in section, laser-on frame, laser-off frame): recording."""


def grab_grid(hardware: Hardware) -> np.ndarray:
    """Capture the calibration board image with the laser off."""
    hardware.place("grid")
    hardware.laser.off()
    return hardware.camera.capture()


def capture_pair(hardware: Hardware) -> tuple[np.ndarray, np.ndarray]:
    """Capture one view's laser-off then laser-on frame; the laser ends off."""
    hardware.laser.off()
    off = hardware.camera.capture()
    try:
        hardware.laser.on()
        on = hardware.camera.capture()
    finally:
        hardware.laser.off()
    return on, off


def acquire(
    hardware: Hardware,
    target: str,
    plan: ScanPlan,
    on_segment: Callable[[Segment], None],
    on_progress: Callable[[Progress], None] | None = None,
    settings: ExtractSettings | None = None,
    sink: FrameSink | None = None,
) -> int:
    """Scan ``target`` along ``plan``; return the number of segments produced.

    Args:
        hardware: the device's hardware.
        target: ``cylinder`` or ``object``.
        plan: the views to visit, in order.
        on_segment: called with each view's segment as soon as it is extracted.
        on_progress: called after each view.
        settings: extraction settings (Otsu, p = 1 by default).
        sink: called with the raw frames of each view, for recording captures.

    Returns:
        How many segments were handed to ``on_segment``.
    """
    hardware.place(target)
    index_in_section: dict[int, int] = {}
    try:
        for done, view in enumerate(plan.views, start=1):
            hardware.lift.move_to(view.z_mm)
            hardware.turntable.move_to(view.angle_deg)
            on, off = capture_pair(hardware)
            index = index_in_section.get(view.section, 0)
            index_in_section[view.section] = index + 1
            if sink is not None:
                sink(target, view, index, on, off)
            points = extract(on, off, settings)
            on_segment(to_segment(points, target, view.section, index, view.z_mm, view.angle_deg))
            if on_progress is not None:
                on_progress(Progress(target, done, len(plan.views), view.section))
    finally:
        hardware.laser.off()
        hardware.lift.move_to(0.0)
    return len(plan.views)
