"""From segments to contours and a mesh: the host's processing, stage by stage.

Data flows one way (thesis figure 3.2): image points → world points (homography,
chapter 4) → object frame (axis and correction factor, 6.2) → sections with
overlaps averaged (6.3) → EFD contours (6.4) → mesh (chapter 7).
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lamina_host.assembly import average_overlaps, to_object_frame, trim
from lamina_host.axis import AxisCalibration, find_axis
from lamina_host.calibration import CalibrationError, GridCalibration, calibrate_grid
from lamina_host.efd import EllipticFourier, choose_harmonics, efd_fit, nyquist_max
from lamina_host.measure import perimeter
from lamina_host.mesh import ball_pivoting, contour_normals, topology
from lamina_shared.types import BoardSpec, Segment

MIN_SEGMENT_POINTS = 10
"""Segments with fewer points than this after trimming carry no usable outline."""


@dataclass(frozen=True)
class ProcessOptions:
    """Choices of the processing stages (defaults follow the thesis)."""

    trim_fraction: float = 0.10
    outline_points: int = 500
    harmonics: int | None = None
    ball_radius_mm: float | None = None


@dataclass(frozen=True)
class Section:
    """One planar section: its raw assembled outline and its EFD contour."""

    index: int
    z_mm: float
    segments: int
    raw: np.ndarray
    efd: EllipticFourier
    contour: np.ndarray

    @property
    def harmonics(self) -> int:
        """Return the number of EFD harmonics fitted."""
        return self.efd.order


@dataclass
class Reconstruction:
    """Everything the processing produced, ready to be written and reported."""

    grid: GridCalibration
    axis: AxisCalibration
    sections: list[Section]
    vertices: np.ndarray
    faces: np.ndarray
    mesh_topology: dict[str, Any]
    timings_s: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)


class Timer:
    """Collects how long each named stage took."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the enclosed block as stage ``name``."""
        start = time.perf_counter()
        try:
            yield
        finally:
            self.seconds[name] = self.seconds.get(name, 0.0) + time.perf_counter() - start


def world_points(segment: Segment, grid: GridCalibration, trim_fraction: float) -> np.ndarray:
    """Return a segment's trimmed points in the laser plane, in mm (thesis 6.1)."""
    order = np.argsort(segment.cols, kind="stable")
    return trim(grid.homography.apply(segment.uv[order]), trim_fraction)


def calibrate_axis(
    cylinder: list[Segment], grid: GridCalibration, diameter_mm: float, trim_fraction: float
) -> AxisCalibration:
    """Find the turntable axis and correction factor from the calibration cylinder (6.2)."""
    arcs = [world_points(s, grid, trim_fraction) for s in cylinder]
    arcs = [a for a in arcs if len(a) >= MIN_SEGMENT_POINTS]
    if len(arcs) < 3:
        raise CalibrationError(
            f"only {len(arcs)} calibration-cylinder views show the stripe (3 or more needed): "
            "check the cylinder stands on the turntable inside the laser plane"
        )
    return find_axis(arcs, diameter_mm)


def assemble(
    segments: list[Segment], grid: GridCalibration, axis: AxisCalibration, trim_fraction: float
) -> tuple[dict[int, list[np.ndarray]], dict[int, float], int]:
    """Group object-frame segment points by section; return them, heights, and skips."""
    by_section: dict[int, list[np.ndarray]] = {}
    heights: dict[int, float] = {}
    skipped = 0
    for segment in segments:
        points = world_points(segment, grid, trim_fraction)
        if len(points) < MIN_SEGMENT_POINTS:
            skipped += 1
            continue
        local = to_object_frame(points, segment.angle_deg, axis.axis_xy_mm, axis.correction_factor)
        by_section.setdefault(segment.section, []).append(local)
        heights[segment.section] = segment.z_mm
    return by_section, heights, skipped


def fit_section(
    index: int, z_mm: float, parts: list[np.ndarray], options: ProcessOptions
) -> Section:
    """Average a section's overlaps and fit its EFD contour (thesis 6.3-6.4)."""
    raw = average_overlaps(parts)
    order = options.harmonics or choose_harmonics(raw)
    order = max(1, min(order, nyquist_max(len(raw))))
    efd = efd_fit(raw, order)
    return Section(index, z_mm, len(parts), raw, efd, efd.evaluate(options.outline_points))


def stack(contours: list[np.ndarray], heights: list[float]) -> np.ndarray:
    """Return planar contours as one (N, 3) array with their heights as z."""
    pairs = zip(contours, heights, strict=True)
    parts = [np.column_stack([c, np.full(len(c), z)]) for c, z in pairs]
    return np.vstack(parts) if parts else np.empty((0, 3))


def stacked_normals(contours: list[np.ndarray]) -> np.ndarray:
    """Return horizontal outward normals of planar contours, stacked like :func:`stack`."""
    parts = [np.column_stack([contour_normals(c), np.zeros(len(c))]) for c in contours]
    return np.vstack(parts) if parts else np.empty((0, 3))


def mesh_ball_pivoting(
    sections: list[Section], pitch_mm: float, radius_mm: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """Mesh the EFD contours by ball pivoting (thesis ch. 7).

    Each contour is re-sampled at a quarter of the section pitch: ball pivoting needs
    samples spaced evenly compared with the ball, and a contour far denser than its
    neighbours' spacing leaves no empty ball to roll.
    """
    contours = []
    for s in sections:
        count = max(16, int(np.ceil(perimeter(s.contour) / (pitch_mm / 4.0))))
        contours.append(s.efd.evaluate(count))
    heights = [s.z_mm for s in sections]
    return ball_pivoting(stack(contours, heights), stacked_normals(contours), radius_mm or pitch_mm)


def section_pitch_mm(sections: list[Section]) -> float | None:
    """Return the median spacing between consecutive sections, or None for one section."""
    heights = sorted(s.z_mm for s in sections)
    gaps = np.diff(heights)
    gaps = gaps[gaps > 0]
    return float(np.median(gaps)) if len(gaps) else None


def reconstruct(
    grid_image: np.ndarray,
    board: BoardSpec,
    cylinder: list[Segment],
    cylinder_mm: float,
    segments: list[Segment],
    options: ProcessOptions | None = None,
) -> Reconstruction:
    """Run every stage from the raw calibration data and segments to the mesh.

    Raises:
        CalibrationError: the board or the cylinder could not be used.
    """
    options = options or ProcessOptions()
    timer = Timer()
    with timer.stage("calibrate_grid"):
        grid = calibrate_grid(grid_image, board)
    with timer.stage("calibrate_axis"):
        axis = calibrate_axis(cylinder, grid, cylinder_mm, options.trim_fraction)
    with timer.stage("assemble"):
        by_section, heights, skipped = assemble(segments, grid, axis, options.trim_fraction)
    warnings = [*grid.warnings, *axis.warnings]
    if skipped:
        warnings.append(
            f"{skipped} segment(s) had fewer than {MIN_SEGMENT_POINTS} points "
            "after trimming and were left out"
        )
    if not by_section:
        raise CalibrationError(
            "no view of the object shows the laser stripe: check the object "
            "stands inside the laser plane and the laser works"
        )
    with timer.stage("fit_efd"):
        sections = [fit_section(k, heights[k], by_section[k], options) for k in sorted(by_section)]
    vertices, faces, topo = np.empty((0, 3)), np.empty((0, 3), int), {}
    pitch = section_pitch_mm(sections)
    if pitch is None:
        warnings.append("a single section cannot be meshed; scan two or more sections")
    else:
        with timer.stage("mesh"):
            vertices, faces = mesh_ball_pivoting(sections, pitch, options.ball_radius_mm)
            topo = topology(vertices, faces)
    return Reconstruction(grid, axis, sections, vertices, faces, topo, timer.seconds, warnings)
