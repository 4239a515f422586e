"""From segments to contours and a mesh: the host's processing, stage by stage.

Data flows one way (thesis figure 3.2): image points → world points (plane map,
chapter 4) → object frame (axis and correction factor, 6.2) → outlines with overlaps
averaged (6.3) → EFD contours (6.4) → mesh (chapter 7). Every stage has the thesis'
method and Lamina's default side by side; ``ProcessOptions.thesis()`` runs the thesis.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lamina_host.assembly import average_overlaps, split_outlines, to_object_frame, trim
from lamina_host.axis import AXIS_METHODS, AxisCalibration, find_axis, find_axis_joint
from lamina_host.calibration import (
    CALIBRATION_METHODS,
    CalibrationError,
    GridCalibration,
    calibrate_grid,
)
from lamina_host.efd import (
    HARMONIC_RULES,
    INTERPOLATIONS,
    PARAMETERS,
    EfdStack,
    EllipticFourier,
    choose_harmonics,
    efd_fit,
    nyquist_max,
)
from lamina_host.measure import centroid, perimeter
from lamina_host.mesh import (
    MESH_METHODS,
    ball_pivoting,
    contour_normals,
    screened_poisson,
    topology,
    tube_mesh,
)
from lamina_shared.types import BoardSpec, Segment

MIN_SEGMENT_POINTS = 10
"""Segments with fewer points than this after trimming carry no usable outline."""


@dataclass(frozen=True)
class ProcessOptions:
    """Choices of the processing stages; defaults are Lamina's best, ``thesis()`` the thesis'.

    Attributes:
        trim_fraction: share of each segment dropped at each end (thesis 6.1: 10 %).
        outline_points: samples per EFD contour (thesis Table 8.2: 500).
        harmonics: a fixed EFD order instead of ``harmonic_rule``.
        ball_radius_mm: ball radius for ball pivoting (default: the section pitch).
        calibration: one of ``CALIBRATION_METHODS``.
        distortion: estimate radial lens distortion with the ``"ml"`` calibration.
        axis: one of ``AXIS_METHODS``.
        angle_correction: estimate the turntable angle scale from the cylinder (joint only).
        harmonic_rule: one of ``HARMONIC_RULES``.
        efd_parameter: one of ``PARAMETERS``.
        split_gap_mm: outlines further apart than this are fitted separately; None keeps
            one outline per section (thesis).
        mesh: one of ``MESH_METHODS``.
        interpolation: how the contour mesh interpolates EFD coefficients along z.
    """

    trim_fraction: float = 0.10
    outline_points: int = 500
    harmonics: int | None = None
    ball_radius_mm: float | None = None
    calibration: str = CALIBRATION_METHODS[0]
    distortion: bool = False
    axis: str = AXIS_METHODS[0]
    angle_correction: bool = True
    harmonic_rule: str = HARMONIC_RULES[0]
    efd_parameter: str = PARAMETERS[0]
    split_gap_mm: float | None = 2.0
    mesh: str = MESH_METHODS[0]
    interpolation: str = INTERPOLATIONS[0]

    @classmethod
    def thesis(cls) -> ProcessOptions:
        """Return the thesis' pipeline: DLT, centroid of arc centres, HN, ball pivoting."""
        return cls(
            calibration="dlt",
            axis="centroid",
            angle_correction=False,
            harmonic_rule="thesis",
            efd_parameter="chord",
            split_gap_mm=None,
            mesh="ball-pivoting",
        )

    def check(self) -> None:
        """Raise ValueError naming the first option that is not one of its choices."""
        choices = {
            "calibration": CALIBRATION_METHODS,
            "axis": AXIS_METHODS,
            "harmonic_rule": HARMONIC_RULES,
            "efd_parameter": PARAMETERS,
            "mesh": MESH_METHODS,
            "interpolation": INTERPOLATIONS,
        }
        for name, allowed in choices.items():
            if getattr(self, name) not in allowed:
                raise ValueError(f"{name} {getattr(self, name)!r} is not one of {allowed}")
        if self.angle_correction and self.axis != "joint":
            raise ValueError("the angle correction needs the joint axis fit")
        if not 0.0 <= self.trim_fraction < 0.5:
            raise ValueError(f"trim fraction {self.trim_fraction} must be in [0, 0.5)")
        if self.split_gap_mm is not None and not self.split_gap_mm > 0:
            raise ValueError("the outline gap must be a positive number of mm")

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form (for the report)."""
        return dict(self.__dict__)

    @classmethod
    def from_dict(cls, recorded: dict[str, Any]) -> ProcessOptions:
        """Return the options a report recorded; fields this version lacks are ignored."""
        known = cls.__dataclass_fields__
        return cls(**{k: v for k, v in recorded.items() if k in known})


@dataclass(frozen=True)
class Section:
    """One closed outline of a planar section: raw assembled points and its EFD contour.

    A section with several separate outlines (two legs) gives one Section per outline,
    ``part`` 0 being the one with most points.
    """

    index: int
    z_mm: float
    segments: int
    raw: np.ndarray
    efd: EllipticFourier
    contour: np.ndarray
    part: int = 0

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
    options: ProcessOptions = field(default_factory=ProcessOptions)


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
    cylinder: list[Segment],
    grid: GridCalibration,
    diameter_mm: float,
    trim_fraction: float,
    method: str = AXIS_METHODS[0],
    angle_correction: bool = True,
) -> AxisCalibration:
    """Find the turntable axis and correction factor from the calibration cylinder (6.2)."""
    views = [(world_points(s, grid, trim_fraction), s.angle_deg) for s in cylinder]
    views = [(a, angle) for a, angle in views if len(a) >= MIN_SEGMENT_POINTS]
    if len(views) < 3:
        raise CalibrationError(
            f"only {len(views)} calibration-cylinder views show the stripe (3 or more needed): "
            "check the cylinder stands on the turntable inside the laser plane"
        )
    arcs = [a for a, _ in views]
    if method == "centroid":
        return find_axis(arcs, diameter_mm)
    angles = [angle for _, angle in views]
    return find_axis_joint(arcs, angles, diameter_mm, fit_angle_scale=angle_correction)


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
        angle = axis.true_angle_deg(segment.angle_deg)
        local = to_object_frame(points, angle, axis.axis_xy_mm, axis.correction_factor)
        by_section.setdefault(segment.section, []).append(local)
        heights[segment.section] = segment.z_mm
    return by_section, heights, skipped


def fit_outline(raw: np.ndarray, options: ProcessOptions) -> EllipticFourier:
    """Fit one closed outline's EFD with the chosen order rule and parameterisation (6.4)."""
    order = options.harmonics or choose_harmonics(raw, options.harmonic_rule, options.efd_parameter)
    order = max(1, min(order, nyquist_max(len(raw))))
    return efd_fit(raw, order, options.efd_parameter)


def fit_section(
    index: int, z_mm: float, parts: list[np.ndarray], options: ProcessOptions
) -> Section:
    """Average a section's overlaps and fit its EFD contour as one outline (thesis 6.3-6.4)."""
    raw = average_overlaps(parts)
    efd = fit_outline(raw, options)
    return Section(index, z_mm, len(parts), raw, efd, efd.evaluate(options.outline_points))


def fit_outlines(
    index: int, z_mm: float, parts: list[np.ndarray], options: ProcessOptions
) -> list[Section]:
    """Split a section into its separate outlines (thesis 9.2) and fit each on its own."""
    if options.split_gap_mm is None:
        return [fit_section(index, z_mm, parts, options)]
    groups = split_outlines(parts, options.split_gap_mm)
    if not groups:
        return [fit_section(index, z_mm, parts, options)]
    sections = []
    for k, pieces in enumerate(groups):
        raw = average_overlaps(pieces)
        if len(raw) < 3:
            continue
        efd = fit_outline(raw, options)
        contour = efd.evaluate(options.outline_points)
        sections.append(Section(index, z_mm, len(pieces), raw, efd, contour, k))
    return sections


def stack(contours: list[np.ndarray], heights: list[float]) -> np.ndarray:
    """Return planar contours as one (N, 3) array with their heights as z."""
    pairs = zip(contours, heights, strict=True)
    parts = [np.column_stack([c, np.full(len(c), z)]) for c, z in pairs]
    return np.vstack(parts) if parts else np.empty((0, 3))


def stacked_normals(contours: list[np.ndarray]) -> np.ndarray:
    """Return horizontal outward normals of planar contours, stacked like :func:`stack`."""
    parts = [np.column_stack([contour_normals(c), np.zeros(len(c))]) for c in contours]
    return np.vstack(parts) if parts else np.empty((0, 3))


def _resampled(sections: list[Section], pitch_mm: float) -> list[np.ndarray]:
    """Return each EFD contour sampled at a quarter of the section pitch."""
    contours = []
    for s in sections:
        count = max(16, int(np.ceil(perimeter(s.contour) / (pitch_mm / 4.0))))
        contours.append(s.efd.evaluate(count))
    return contours


def mesh_ball_pivoting(
    sections: list[Section], pitch_mm: float, radius_mm: float | None
) -> tuple[np.ndarray, np.ndarray]:
    """Mesh the EFD contours by ball pivoting (thesis ch. 7).

    Each contour is re-sampled at a quarter of the section pitch: ball pivoting needs
    samples spaced evenly compared with the ball, and a contour far denser than its
    neighbours' spacing leaves no empty ball to roll.
    """
    contours = _resampled(sections, pitch_mm)
    heights = [s.z_mm for s in sections]
    return ball_pivoting(stack(contours, heights), stacked_normals(contours), radius_mm or pitch_mm)


def mesh_poisson(sections: list[Section], pitch_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Mesh the EFD contours by screened Poisson reconstruction."""
    contours = _resampled(sections, pitch_mm)
    heights = [s.z_mm for s in sections]
    return screened_poisson(stack(contours, heights), stacked_normals(contours))


def chain_outlines(sections: list[Section]) -> list[list[Section]]:
    """Group outlines into vertical chains: each continues the nearest outline below it.

    An outline joins the chain whose last outline (in the section just below) has the
    nearest centroid, if that centroid lies inside its own mean radius; otherwise it
    starts a new chain (a branch, or an outline appearing).
    """
    chains: list[list[Section]] = []
    by_index: dict[int, list[Section]] = {}
    for s in sections:
        by_index.setdefault(s.index, []).append(s)
    open_chains: list[list[Section]] = []
    for index in sorted(by_index, key=lambda k: by_index[k][0].z_mm):
        still_open = []
        for s in by_index[index]:
            c = centroid(s.contour)
            reach = float(np.linalg.norm(s.contour - c, axis=1).mean())
            best, best_d = None, reach
            for chain in open_chains:
                d = float(np.linalg.norm(centroid(chain[-1].contour) - c))
                if d < best_d and chain not in still_open:
                    best, best_d = chain, d
            if best is None:
                best = [s]
                chains.append(best)
            else:
                best.append(s)
            still_open.append(best)
        open_chains = still_open
    return chains


def mesh_contours(
    sections: list[Section], points: int, interpolation: str
) -> tuple[np.ndarray, np.ndarray]:
    """Mesh each chain of outlines as a closed tube of aligned EFD contours."""
    verts, faces, offset = [], [], 0
    for chain in chain_outlines(sections):
        stack_ = EfdStack.from_sections(
            [s.z_mm for s in chain], [s.efd for s in chain], interpolation
        )
        v, f = tube_mesh(stack_.sample(points), stack_.z_mm)
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
    return np.vstack(verts), np.vstack(faces)


def section_pitch_mm(sections: list[Section]) -> float | None:
    """Return the median spacing between consecutive sections, or None for one section."""
    heights = sorted({s.z_mm for s in sections})
    gaps = np.diff(heights)
    gaps = gaps[gaps > 0]
    return float(np.median(gaps)) if len(gaps) else None


def build_mesh(
    sections: list[Section], options: ProcessOptions
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Mesh the contours with ``options.mesh``; return vertices, faces and warnings."""
    pitch = section_pitch_mm(sections)
    if options.mesh == "contours":
        return (*mesh_contours(sections, options.outline_points, options.interpolation), [])
    if pitch is None:
        return (
            np.empty((0, 3)),
            np.empty((0, 3), int),
            [f"a single section cannot be meshed by {options.mesh}; scan two or more"],
        )
    if options.mesh == "poisson":
        return (*mesh_poisson(sections, pitch), [])
    return (*mesh_ball_pivoting(sections, pitch, options.ball_radius_mm), [])


def process_segments(
    grid: GridCalibration,
    axis: AxisCalibration,
    segments: list[Segment],
    options: ProcessOptions,
    timer: Timer,
) -> tuple[list[Section], list[str]]:
    """Assemble the object's segments into sections and fit their outlines."""
    with timer.stage("assemble"):
        by_section, heights, skipped = assemble(segments, grid, axis, options.trim_fraction)
    warnings = []
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
        sections = [
            s
            for k in sorted(by_section)
            for s in fit_outlines(k, heights[k], by_section[k], options)
        ]
    return sections, warnings


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
    options.check()
    timer = Timer()
    with timer.stage("calibrate_grid"):
        grid = calibrate_grid(grid_image, board, options.calibration, options.distortion)
    with timer.stage("calibrate_axis"):
        axis = calibrate_axis(
            cylinder, grid, cylinder_mm, options.trim_fraction, options.axis,
            options.angle_correction,
        )  # fmt: skip
    sections, warnings = process_segments(grid, axis, segments, options, timer)
    warnings = [*grid.warnings, *axis.warnings, *warnings]
    with timer.stage("mesh"):
        vertices, faces, mesh_warnings = build_mesh(sections, options)
        topo = topology(vertices, faces) if len(faces) else {}
    warnings += mesh_warnings
    if topo and not (topo["watertight"] and topo["two_manifold"]):
        warnings.append(
            f"the {options.mesh} mesh is not watertight and manifold "
            f"({topo['boundary_edges']} boundary edges); use --mesh contours for a closed mesh"
        )
    return Reconstruction(
        grid, axis, sections, vertices, faces, topo, timer.seconds, warnings, options
    )
