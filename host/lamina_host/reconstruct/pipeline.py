"""From segments to contours and a mesh: the host's processing, stage by stage.

Data flows one way (thesis figure 3.2): image points → world points (plane map,
chapter 4) → object frame (axis and correction factor, 6.2) → outlines with overlaps
averaged (6.3) → EFD contours (6.4) → mesh (chapter 7). Every stage has the thesis'
method and Lamina's default side by side; ``ProcessOptions.thesis()`` runs the thesis.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field, replace
from functools import partial
from types import MappingProxyType
from typing import Any

import numpy as np

from lamina_host.reconstruct.assembly import (
    DEFAULT_TRIM_FRACTION,
    THESIS_TRIM_FRACTION,
    Blend,
    average_overlap_colours,
    blend_overlaps,
    join_arcs,
    separate_bodies,
    split_outlines,
    to_object_frame,
    trim,
    trim_problem,
)
from lamina_host.reconstruct.axis import (
    AXIS_METHODS,
    AxisCalibration,
    find_axis,
    find_axis_joint,
    fit_circle,
    next_turn_warning,
)
from lamina_host.reconstruct.calibration import (
    CALIBRATION_METHODS,
    DISTORTION_MODES,
    CalibrationError,
    GridCalibration,
    LiftCalibration,
    calibrate_grid,
    calibrate_lift,
)
from lamina_host.reconstruct.coverage import (
    CONTINUOUS_STEP_MM,
    MEASURED_TOLERANCE_MM,
    Coverage,
    bridge_gaps,
    estimated_samples,
    match_sides,
    measure_coverage,
)
from lamina_host.reconstruct.efd import (
    CLINICAL_INTERPOLATION,
    HARMONIC_RULES,
    INTERPOLATIONS,
    PARAMETERS,
    EfdStack,
    EllipticFourier,
    MeasuredPoints,
    choose_harmonics,
    efd_fit,
    harmonics_problem,
    nyquist_max,
)
from lamina_host.reconstruct.measure import centroid_or_mean, perimeter, signed_area
from lamina_host.reconstruct.mesh import (
    MESH_METHODS,
    MeshlabMissing,
    MeshTopology,
    ball_pivoting,
    contour_normals,
    mesh_kind,
    open_tube_mesh,
    screened_poisson,
)
from lamina_host.reconstruct.outliers import MIN_RUN_POINTS, OutlierRules, Rejected, clean_section
from lamina_host.reconstruct.precision import (
    MOTION_WARN_MM,
    disagreement_of,
    pair_differences,
    precision_of,
)
from lamina_host.reconstruct.status import CLOSED, OutlineStatus
from lamina_host.reconstruct.workers import in_batches, map_in_workers, workers_for
from lamina_shared.centreline import refined_segments
from lamina_shared.errors import LaminaError
from lamina_shared.types import BoardSpec, LiftReference, Segment, from_first_turn

MIN_SEGMENT_POINTS = 10
"""Segments with fewer points than this after trimming carry no usable outline."""


DEFAULT_SPLIT_GAP_MM = 2.0
"""Outlines further apart than this are separate (also used to cluster for rejection)."""

OPTION_CHOICES: Mapping[str, tuple[str, ...]] = MappingProxyType(
    {
        "calibration": CALIBRATION_METHODS,
        "distortion": DISTORTION_MODES,
        "axis": AXIS_METHODS,
        "harmonic_rule": HARMONIC_RULES,
        "efd_parameter": PARAMETERS,
        "mesh": MESH_METHODS,
        "interpolation": INTERPOLATIONS,
    }
)
"""The :class:`ProcessOptions` fields that name a method, and the methods each may name:
the one list the command line's choices, the terminal UI and :meth:`ProcessOptions.check`
read."""

ANGLE_CORRECTION_AXIS = "joint"
"""The one axis method that estimates the turntable's angle scale (``angle_correction``)."""

DISTORTION_CALIBRATION = "ml"
"""The one calibration that estimates lens distortion (``distortion`` other than off)."""

PER_VIEW_ANGLES = False
"""Whether processing fits each cylinder view's own angle offset by default. They were
there for the once-per-turn gear error the joint fit now models (``angle_wave_deg``);
left on, they only add their own scatter, which the cylinder measures worse than their
standard errors say: about 0.1 degrees between two scans of the same simulated limb rig
(0.17 mm at 100 mm from the axis), interpolated into every view between them."""


@dataclass(frozen=True)
class ProcessOptions:
    """Choices of the processing stages; defaults are Lamina's best, ``thesis()`` the thesis'.

    Attributes:
        trim_fraction: share of each segment dropped at each end (thesis 6.1: 10 %;
            Lamina's default none, ``DEFAULT_TRIM_FRACTION``).
        outline_points: samples per EFD contour (thesis Table 8.2: 500), and per mesh ring.
        contour_spacing_mm: a longer outline's contour is sampled at least this finely
            (``contour_samples``): 500 samples of a 300 mm limb outline lie 0.6 mm apart,
            coarser than the stripe measures it; None keeps ``outline_points`` (thesis).
        harmonics: a fixed EFD order instead of ``harmonic_rule``.
        ball_radius_mm: ball radius for ball pivoting (default: the section pitch).
        calibration: one of ``CALIBRATION_METHODS``.
        distortion: one of ``DISTORTION_MODES``: radial lens distortion estimated with the
            ``"ml"`` calibration and kept where the board shows it (auto), always (on) or
            never (off); the other calibrations have none.
        axis: one of ``AXIS_METHODS``.
        angle_correction: estimate the turntable angle scale from the cylinder (joint only).
        per_view_angles: with ``angle_correction``, also fit each view's own angle offset
            from the cylinder (scanned at the same view angles), absorbing a repeatable
            gear error of more than once a turn; False (the default) keeps the gear's
            scale and once-per-turn error alone (:data:`PER_VIEW_ANGLES`).
        harmonic_rule: one of ``HARMONIC_RULES``.
        efd_parameter: one of ``PARAMETERS``.
        split_gap_mm: outlines further apart than this are fitted separately; None keeps
            one outline per section (thesis).
        mesh: one of ``MESH_METHODS``.
        interpolation: how the contour mesh interpolates EFD coefficients along z (default:
            the clinical measurements' own, so mesh and contour-stack volumes agree).
        reject_outliers: reject points outside the working volume, stripe spikes, points
            the overlapping views contradict and outlines too poorly supported
            (:mod:`.outliers`); False assembles every point (thesis).
        working_radius_mm: the working volume's radius about the axis; None: the disc the
            camera sees at every turntable angle, from the calibration.
        max_bridge_deg: the widest unseen gap EFD may close on its own (flagged as
            estimated); wider gaps are filled from neighbouring sections or the outline
            is left open (not meshed). None lets EFD close every gap (thesis).
        max_efd_points: longer outlines are thinned to this many points before the EFD
            fit (``thin_outline``); None fits every point (thesis).
        refine_stripes: fit every segment's stripe centres along its chains before they
            become world points (``lamina_shared.centreline``: less speckle, no pull on
            curves); False takes the device's centres as sent (thesis).
    """

    trim_fraction: float = DEFAULT_TRIM_FRACTION
    outline_points: int = 500
    contour_spacing_mm: float | None = 0.1
    harmonics: int | None = None
    ball_radius_mm: float | None = None
    calibration: str = CALIBRATION_METHODS[0]
    distortion: str = DISTORTION_MODES[0]
    axis: str = AXIS_METHODS[0]
    angle_correction: bool = True
    harmonic_rule: str = HARMONIC_RULES[0]
    efd_parameter: str = PARAMETERS[0]
    split_gap_mm: float | None = DEFAULT_SPLIT_GAP_MM
    mesh: str = MESH_METHODS[0]
    interpolation: str = CLINICAL_INTERPOLATION
    per_view_angles: bool = PER_VIEW_ANGLES
    reject_outliers: bool = True
    working_radius_mm: float | None = None
    max_bridge_deg: float | None = 30.0
    max_efd_points: int | None = 4096
    refine_stripes: bool = True

    @classmethod
    def thesis(cls) -> ProcessOptions:
        """Return the thesis' pipeline: DLT, centroid of arc centres, HN, ball pivoting."""
        return cls(
            trim_fraction=THESIS_TRIM_FRACTION,
            calibration="dlt",
            distortion="off",
            axis="centroid",
            angle_correction=False,
            harmonic_rule="thesis",
            efd_parameter="chord",
            split_gap_mm=None,
            mesh="ball-pivoting",
            per_view_angles=False,
            reject_outliers=False,
            max_bridge_deg=None,
            max_efd_points=None,
            contour_spacing_mm=None,
            refine_stripes=False,
        )

    def check(self) -> None:
        """Raise ValueError naming the first option that is not allowed (:meth:`problem`)."""
        if problem := self.problem():
            raise ValueError(problem)

    def problem(
        self, names: Mapping[str, str] | None = None, hints: Mapping[str, str] | None = None
    ) -> str | None:
        """Return the one line naming the first option that is not allowed, or None.

        The rules of the options live here alone; each front end only names the fields
        its own way.

        Args:
            names: how the asking front end names each field (``{"axis": "--axis"}``);
                a field not named is shown by its name with spaces.
            hints: text added to the problem of a field (", or blank for auto").
        """
        named = dict(names or {})

        def name(field_name: str) -> str:
            return named.get(field_name, field_name.replace("_", " "))

        for field_name, text in self._field_problems(name):
            if text is not None:
                return text + (hints or {}).get(field_name, "")
        return None

    def _field_problems(self, name: Callable[[str], str]) -> Iterator[tuple[str, str | None]]:
        """Yield each field checked with its problem (None where it is allowed), in order."""
        for option, allowed in OPTION_CHOICES.items():
            value = getattr(self, option)
            if value not in allowed:
                yield option, f"{name(option)} {value!r} is not one of {', '.join(allowed)}"
        if self.angle_correction and self.axis != ANGLE_CORRECTION_AXIS:
            yield (
                "angle_correction",
                (f"{name('angle_correction')} needs {name('axis')} {ANGLE_CORRECTION_AXIS}"),
            )
        if self.distortion == "on" and self.calibration != DISTORTION_CALIBRATION:
            yield (
                "distortion",
                (f"{name('distortion')} on needs {name('calibration')} {DISTORTION_CALIBRATION}"),
            )
        yield "trim_fraction", trim_problem(self.trim_fraction, name("trim_fraction"))
        yield "harmonics", harmonics_problem(self.harmonics, name("harmonics"))
        if self.split_gap_mm is not None and not self.split_gap_mm > 0:
            yield "split_gap_mm", "the outline gap must be a positive number of mm"
        if self.working_radius_mm is not None and not self.working_radius_mm > 0:
            yield "working_radius_mm", "the working radius must be a positive number of mm"
        if self.max_efd_points is not None and self.max_efd_points < 16:
            yield "max_efd_points", "the EFD needs at least 16 points per outline"
        if self.max_bridge_deg is not None and not 0 <= self.max_bridge_deg <= 360:
            yield "max_bridge_deg", "the widest gap to bridge must be 0 to 360 degrees"
        if self.contour_spacing_mm is not None and not self.contour_spacing_mm >= 0.01:
            yield "contour_spacing_mm", "the contour spacing must be at least 0.01 mm"

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form (for the report)."""
        return dict(self.__dict__)

    @classmethod
    def from_dict(cls, recorded: dict[str, Any]) -> ProcessOptions:
        """Return the options a report recorded; fields this version lacks are ignored."""
        known = cls.__dataclass_fields__
        options = {k: v for k, v in recorded.items() if k in known}
        if isinstance(options.get("distortion"), bool):  # recorded before the modes
            options["distortion"] = "on" if options["distortion"] else "off"
        return cls(**options)


OWN_BRIDGE_FRACTION = 0.75
"""An outline at least this much covered is closed from its own points, however wide its
gap; neighbouring sections fill only outlines mostly unseen (their shape may differ: a
thin part ending, a tip)."""

INTERP_REACH_SECTIONS = 3
"""A large gap is filled only from outlines at most this many section pitches away."""

GAP_FILL_SAMPLES = 720
"""Samples of the neighbours' interpolated contour offered to fill a gap."""


@dataclass(frozen=True, eq=False)
class Section:
    """One outline of a planar section: measured points, EFD contour and how it was closed.

    A section with several separate outlines (two legs) gives one Section per outline,
    ``part`` 0 being the one with most points. ``segments`` counts the stripe pieces
    averaged into it (with outlier rejection, runs of one view's stripe). ``raw`` holds
    measured points only; ``estimated`` marks the contour samples not backed by a
    measurement (in an unseen gap; see ``status`` and ``Coverage.unseen``).
    """

    index: int
    z_mm: float
    segments: int
    raw: np.ndarray
    efd: EllipticFourier
    contour: np.ndarray
    part: int = 0
    coverage: Coverage | None = None
    status: OutlineStatus = OutlineStatus.MEASURED
    estimated: np.ndarray | None = None
    colour_points: np.ndarray | None = None
    """(M, 2) measured object-frame points that carry colour (a colour scan), by angle."""
    colours: np.ndarray | None = None
    """(M, 3) uint8 sRGB of ``colour_points``, averaged over the views that saw them."""
    precision_mm: float | None = None
    """The per-point precision from where the views overlap (``precision``); None: no overlap."""
    views_apart_mm: float = 0.0
    """How far apart the overlapping views stand beyond their noise (``precision``)."""

    @property
    def views_moved(self) -> bool:
        """Return whether the views stand apart beyond ``MOTION_WARN_MM``: the subject moved."""
        return self.views_apart_mm > MOTION_WARN_MM

    @property
    def harmonics(self) -> int:
        """Return the number of EFD harmonics fitted."""
        return self.efd.order

    @property
    def closed(self) -> bool:
        """Return whether the outline is closed (meshed whole; else only where seen)."""
        return self.status in CLOSED

    @property
    def measured_contour(self) -> np.ndarray:
        """Return the contour samples that are not estimated (in seen stretches)."""
        return self.contour if self.estimated is None else self.contour[~self.estimated]


@dataclass(frozen=True)
class FailedSection:
    """An outline, or a whole section, that could not be processed: where, and why.

    ``part`` is the outline's place among its section's outlines (0 when the whole
    section failed, e.g. in outlier rejection); ``points`` counts its stripe points.
    """

    index: int
    z_mm: float
    part: int
    points: int
    reason: str

    @property
    def status(self) -> OutlineStatus:
        """Return ``failed`` (the report's and the screens' status of the outline)."""
        return OutlineStatus.FAILED

    def to_dict(self) -> dict[str, Any]:
        """Return the report's entry for the outline (no EFD, contour or coverage)."""
        return {
            "section": self.index,
            "part": self.part,
            "z_mm": self.z_mm,
            "raw_points": self.points,
            "status": self.status,
            "reason": self.reason,
        }


def failure_reason(exc: Exception) -> str:
    """Return the one line a failed outline's report gives: Lamina's own message, or the
    kind of an unexpected error (a bug, so it asks for a report)."""
    if isinstance(exc, LaminaError):
        return str(exc)
    return f"internal error ({type(exc).__name__}: {exc}); please report it"


@dataclass(eq=False)
class Reconstruction:
    """Everything the processing produced, ready to be written and reported.

    ``vertex_colours`` (V, 3) uint8 is set for a colour scan, else None.
    """

    grid: GridCalibration
    axis: AxisCalibration
    sections: list[Section]
    vertices: np.ndarray
    faces: np.ndarray
    mesh_topology: MeshTopology | None
    """The mesh's topology; None when there is no mesh."""
    timings_s: dict[str, float] = field(default_factory=dict)
    warnings: list[str] = field(default_factory=list)
    options: ProcessOptions = field(default_factory=ProcessOptions)
    rejected: Rejected = field(default_factory=Rejected)
    vertex_colours: np.ndarray | None = None
    failed: list[FailedSection] = field(default_factory=list)
    """Outlines that could not be processed (not in ``sections``, not meshed)."""
    lift: LiftCalibration | None = None
    """The lift's scale from the calibration cylinder's grooves (None: no lift reference)."""

    @property
    def lift_scale(self) -> float:
        """Return the factor every section height was multiplied by (1: the lift trusted)."""
        return self.lift.scale if self.lift is not None and self.lift.applied else 1.0


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

    def add(self, seconds: dict[str, float]) -> None:
        """Add another timer's stage times (a worker process's) to these."""
        for name, spent in seconds.items():
            self.seconds[name] = self.seconds.get(name, 0.0) + spent


def world_points(segment: Segment, grid: GridCalibration, trim_fraction: float) -> np.ndarray:
    """Return a segment's trimmed points in the laser plane, in mm (thesis 6.1)."""
    order = trimmed_order(segment, trim_fraction)
    return grid.homography.apply(segment.uv[order])


def trimmed_order(segment: Segment, trim_fraction: float) -> np.ndarray:
    """Return the indices of a segment's points along the stripe, ends trimmed (thesis 6.1)."""
    return trim(np.argsort(segment.cols, kind="stable"), trim_fraction)


def calibrate_axis(
    cylinder: list[Segment],
    grid: GridCalibration,
    diameter_mm: float,
    trim_fraction: float,
    method: str = AXIS_METHODS[0],
    angle_correction: bool = True,
    per_view: bool = False,
) -> AxisCalibration:
    """Find the turntable axis and correction factor from the calibration cylinder (6.2)."""
    views = [(world_points(s, grid, trim_fraction), s.count_deg) for s in cylinder]
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
    # The radius is known: holding it keeps stripe noise out of the axis and scale (axis.py).
    return find_axis_joint(
        arcs,
        angles,
        diameter_mm,
        fit_angle_scale=angle_correction,
        per_view=per_view,
        fit_radius=False,
    )


def assemble(
    segments: list[Segment],
    grid: GridCalibration,
    axis: AxisCalibration,
    trim_fraction: float,
    row_turn_deg: float = 0.0,
) -> tuple[dict[int, list[np.ndarray]], dict[int, float], int]:
    """Group object-frame segment points by section; return them, heights, and skips.

    ``row_turn_deg`` (a continuous scan's, :func:`lamina_host.link.identity.row_turn_deg`)
    gives each point the angle of its own row's exposure; 0.0 gives a view one angle.
    """
    by_section: dict[int, list[np.ndarray]] = {}
    heights: dict[int, float] = {}
    skipped = 0
    for segment in segments:
        order = trimmed_order(segment, trim_fraction)
        if len(order) < MIN_SEGMENT_POINTS:
            skipped += 1
            continue
        local = object_points(segment, order, grid, axis, row_turn_deg)
        by_section.setdefault(segment.section, []).append(local)
        heights[segment.section] = segment.z_mm
    return by_section, heights, skipped


def object_points(
    segment: Segment,
    order: np.ndarray,
    grid: GridCalibration,
    axis: AxisCalibration,
    row_turn_deg: float = 0.0,
) -> np.ndarray:
    """Return a segment's points ``order`` in the object frame, in mm (thesis 6.1-6.2).

    The one transform of a view's points: the laser plane's homography, then the turn to
    the object's frame at the view's true angle, taken at its step count
    (:attr:`Segment.count_deg`; turns counted from the scan's first,
    :func:`~lamina_shared.types.from_first_turn`).
    ``row_turn_deg`` (a continuous scan's, :func:`lamina_host.link.identity.row_turn_deg`)
    adds each point's own row's share: the view's count is the table's when its
    stripe's median row was exposed (the device's ``_stripe_count_deg``, over every
    point it sent), each row below it one row time later. Each row's count goes through
    the calibration on its own: a stripe whose rows span a whole turn of the count (the
    0-degree view) has rows on either side of it, and the gear's periodic error is taken
    on each row's side.
    """
    points = grid.homography.apply(segment.uv[order])
    angle: float | np.ndarray
    if row_turn_deg:
        rows = segment.rows[order].astype(float) - float(np.median(segment.rows))
        angle = axis.true_angle_deg(segment.count_deg + row_turn_deg * rows)
    else:
        angle = axis.true_angle_deg(segment.count_deg)
    return to_object_frame(points, angle, axis.axis_xy_mm, axis.correction_factor)


ColourViews = dict[int, list[tuple[np.ndarray, np.ndarray]]]
"""Per section index, each coloured view's object-frame (K, 2) points and (K, 3) colours."""

COLOUR_GATE_MM = 1.0
"""A coloured point further than this from its outline's contour (an outlier) lends no colour."""


def assemble_colours(
    segments: list[Segment], grid: GridCalibration, axis: AxisCalibration, trim_fraction: float
) -> ColourViews:
    """Return the coloured segments' points in the object frame with their colours, by section.

    The same trimming and transform as :func:`assemble`, so colour and geometry agree.
    """
    views: ColourViews = {}
    for segment in segments:
        if not segment.has_colour:
            continue
        order = trimmed_order(segment, trim_fraction)
        if len(order) < MIN_SEGMENT_POINTS:
            continue
        local = object_points(segment, order, grid, axis)
        views.setdefault(segment.section, []).append((local, segment.colour[order]))
    return views


def colour_section(section: Section, views: list[tuple[np.ndarray, np.ndarray]]) -> Section:
    """Return ``section`` with the colour of its measured points, overlaps averaged.

    Only points within :data:`COLOUR_GATE_MM` of the section's contour count (outliers
    and other outlines of the same height lend no colour); each then takes the mean of
    its own colour and that of every other view covering its angle
    (:func:`~lamina_host.reconstruct.assembly.average_overlap_colours`).
    """
    from scipy.spatial import cKDTree  # deferred: only colour scans need it

    tree = cKDTree(section.contour)
    pieces, colours = [], []
    for points, colour in views:
        near = tree.query(points)[0] <= COLOUR_GATE_MM
        if np.count_nonzero(near) >= 2:
            pieces.append(points[near])
            colours.append(colour[near])
    if not pieces:
        return section
    points, mean = average_overlap_colours(pieces, colours)
    rgb = np.clip(np.rint(mean), 0, 255).astype(np.uint8)
    return replace(section, colour_points=points, colours=rgb)


def colour_sections(sections: list[Section], views: ColourViews) -> list[Section]:
    """Colour every section from its coloured views (unchanged when none carry colour).

    Args:
        sections: the fitted outlines.
        views: per section index, its coloured views (:func:`assemble_colours`).
    """
    if not any(views.values()):
        return sections
    return [_coloured_or_not(s, views.get(s.index, [])) for s in sections]


def _coloured_or_not(section: Section, views: list[tuple[np.ndarray, np.ndarray]]) -> Section:
    """Return the section coloured, or uncoloured when its colour cannot be averaged."""
    try:
        return colour_section(section, views)
    except Exception:  # colour is an addition: the outline stands without it
        return section


def coloured_cloud(sections: list[Section]) -> tuple[np.ndarray, np.ndarray]:
    """Return all coloured measured points as (N, 3) mm (z = section height) and (N, 3) uint8."""
    coloured = [s for s in sections if s.colour_points is not None and s.colours is not None]
    if not coloured:
        return np.empty((0, 3)), np.empty((0, 3), np.uint8)
    points = stack([s.colour_points for s in coloured], [s.z_mm for s in coloured])  # type: ignore[misc]
    return points, np.vstack([s.colours for s in coloured])  # type: ignore[misc]


def vertex_colours(
    vertices: np.ndarray, points: np.ndarray, colours: np.ndarray, neighbours: int = 4
) -> np.ndarray:
    """Return each vertex's colour: the inverse-distance mean of its nearest coloured points."""
    from scipy.spatial import cKDTree  # deferred: only colour scans need it

    k = min(neighbours, len(points))
    distance, index = cKDTree(points).query(vertices, k=k)
    distance, index = distance.reshape(len(vertices), k), index.reshape(len(vertices), k)
    weight = 1.0 / np.maximum(distance, 1e-6)
    mean = (colours[index].astype(float) * weight[..., None]).sum(axis=1) / weight.sum(axis=1)[
        :, None
    ]
    return np.clip(np.rint(mean), 0, 255).astype(np.uint8)


def thin_outline(points: np.ndarray, max_points: int | None) -> np.ndarray:
    """Return an ordered outline with runs of k consecutive points averaged into one,
    k the smallest that leaves at most ``max_points`` (None or few points: unchanged).

    Overlap-averaged outlines interleave the views' points, several per stripe step; a
    mean over a few neighbours along the outline keeps its shape and the EFD's cost,
    proportional to the point count, falls by k.
    """
    pts = np.asarray(points, dtype=float)
    if max_points is None or len(pts) <= max_points:
        return pts
    k = -(-len(pts) // max_points)
    starts = np.arange(0, len(pts), k)
    counts = np.diff(np.append(starts, len(pts)))[:, None]
    return np.add.reduceat(pts, starts, axis=0) / counts


def fit_outline(
    raw: np.ndarray, options: ProcessOptions, measured: MeasuredPoints | None = None
) -> EllipticFourier:
    """Fit one closed outline's EFD with the chosen order rule and parameterisation (6.4).

    ``measured`` (the views' own points and their noise) is what the default order rule
    judges the fit by; without it that rule falls back to the spectrum's noise floor.
    """
    pts = thin_outline(raw, options.max_efd_points)
    order = options.harmonics or choose_harmonics(
        pts, options.harmonic_rule, options.efd_parameter, measured
    )
    order = max(1, min(order, nyquist_max(len(pts))))
    return efd_fit(pts, order, options.efd_parameter)


def contour_samples(efd: EllipticFourier, options: ProcessOptions) -> np.ndarray:
    """Return an outline's contour: ``options.outline_points`` samples, or more where the
    outline is so long that they would lie further apart than ``contour_spacing_mm``."""
    contour = efd.evaluate(options.outline_points)
    if options.contour_spacing_mm is None:
        return contour
    wanted = math.ceil(perimeter(contour) / options.contour_spacing_mm)
    return contour if wanted <= options.outline_points else efd.evaluate(wanted)


def measured_points(blend: Blend) -> MeasuredPoints | None:
    """Return what the order rule needs of a blend: its points and noise (None: unknown)."""
    if blend.noise_mm is None or not blend.noise_mm > 0:
        return None
    return MeasuredPoints(blend.frame, blend.angle_rad, blend.radius_mm, blend.noise_mm)


def fit_section(
    index: int, z_mm: float, parts: list[np.ndarray], options: ProcessOptions, part: int = 0
) -> Section:
    """Average an outline's overlaps, fit its EFD (thesis 6.3-6.4) and measure its coverage.

    The status is "measured" without unseen gaps; "bridged" when the widest gap is at most
    ``options.max_bridge_deg`` or the outline is mostly measured (at least
    ``OWN_BRIDGE_FRACTION`` covered): each gap is then bridged from the outline's own
    points on its sides (``coverage.bridge_gaps``; with ``max_bridge_deg`` None the EFD
    closes every gap alone, as the thesis); and "open" otherwise, until
    :func:`fill_gaps` fills it from neighbouring sections. Samples in gaps are flagged
    estimated.
    """
    blend = blend_overlaps(parts)
    raw = blend.points
    coverage = measure_coverage(raw, blend.frame, parts)
    gap = coverage.largest_gap_deg
    limit = options.max_bridge_deg
    # A gap of a mostly measured outline is bridged from its own sides (an EFD closing it
    # alone draws a chord, and its kinks cost harmonics); None leaves it to EFD (thesis).
    own = limit is not None and (gap <= limit or coverage.fraction >= OWN_BRIDGE_FRACTION)
    # An open outline is bridged too, for the fit alone (the bridge is flagged estimated
    # and not meshed): an EFD jumping across the gap rings near the seen stretch's ends.
    fitted = bridge_gaps(raw, coverage.frame) if limit is not None and gap > 0 else raw
    efd = fit_outline(fitted, options, measured_points(blend))
    contour = contour_samples(efd, options)
    status = (
        OutlineStatus.MEASURED
        if gap == 0
        else OutlineStatus.BRIDGED
        if limit is None or own
        else OutlineStatus.OPEN
    )
    estimated = estimated_samples(coverage, contour, raw)
    pairs = pair_differences(parts, blend.frame)  # once, for precision and disagreement
    return Section(
        index, z_mm, len(parts), raw, efd, contour, part, coverage, status, estimated,
        precision_mm=precision_of(pairs),
        views_apart_mm=disagreement_of(pairs, parts, blend.frame),
    )  # fmt: skip


def outline_groups(
    parts: list[np.ndarray], options: ProcessOptions, rules: OutlierRules
) -> tuple[list[list[np.ndarray]], Rejected]:
    """Return a section's outlines (each a list of per-view pieces) and what was rejected.

    With ``reject_outliers`` the outliers go first and only well-supported outlines stay
    (:mod:`.outliers`), arcs of one outline are joined and an outline of several bodies
    that no frame orders is split (:func:`.assembly.separate_bodies`); they are fitted
    apart if ``split_gap_mm`` is set, together otherwise. Without it, the section splits
    at ``split_gap_mm`` (thesis 9.2) or stays one outline (thesis).
    """
    if options.reject_outliers:
        gap = options.split_gap_mm or DEFAULT_SPLIT_GAP_MM
        outlines, rejected = clean_section(parts, gap, rules)
        bodies = [body for o in join_arcs(outlines) for body in separate_bodies(o, gap)]
        outlines = sorted(bodies, key=lambda o: -sum(len(p) for p in o))  # part 0: the most
        if options.split_gap_mm is None and outlines:
            outlines = [[piece for outline in outlines for piece in outline]]
        return outlines, rejected
    if options.split_gap_mm is None:
        return [parts], Rejected()
    return split_outlines(parts, options.split_gap_mm) or [parts], Rejected()


def fit_groups(
    index: int, z_mm: float, groups: list[list[np.ndarray]], options: ProcessOptions
) -> list[Section]:
    """Fit every outline of one section (outlines of fewer than 3 points are skipped)."""
    sections: list[Section] = []
    for pieces in groups:
        if sum(len(p) for p in pieces) < 3:
            continue
        sections.append(fit_section(index, z_mm, pieces, options, len(sections)))
    return sections


@dataclass(eq=False)
class SectionOutcome:
    """What processing one section gave: its fitted outlines, the ones that failed, and
    the points outlier rejection removed."""

    sections: list[Section] = field(default_factory=list)
    failed: list[FailedSection] = field(default_factory=list)
    rejected: Rejected = field(default_factory=Rejected)


def process_section(
    index: int,
    z_mm: float,
    pieces: list[np.ndarray],
    options: ProcessOptions,
    rules: OutlierRules,
    timer: Timer | None = None,
) -> SectionOutcome:
    """Reject one section's outliers and fit each of its outlines; never raises.

    An outline whose processing fails becomes a :class:`FailedSection` with the reason,
    and the section's other outlines are fitted as usual; a failure of the outlier
    rejection fails the whole section (part 0). Outlines of fewer than 3 points are
    skipped, as in :func:`fit_groups`. ``timer`` adds the time taken to its "reject" and
    "fit_efd" stages.
    """
    timer = timer or Timer()
    outcome = SectionOutcome()
    seen = int(sum(len(p) for p in pieces))
    try:
        with timer.stage("reject"):
            groups, outcome.rejected = outline_groups(pieces, options, rules)
    except Exception as exc:  # any failure here is this section's, not the scan's
        outcome.failed.append(FailedSection(index, z_mm, 0, seen, failure_reason(exc)))
        return outcome
    for outline in groups:
        points = int(sum(len(p) for p in outline))
        if points < 3:
            continue
        part = len(outcome.sections) + len(outcome.failed)
        try:
            with timer.stage("fit_efd"):
                outcome.sections.append(fit_section(index, z_mm, outline, options, part))
        except Exception as exc:
            outcome.failed.append(FailedSection(index, z_mm, part, points, failure_reason(exc)))
    if seen and not outcome.sections and not outcome.failed:
        reason = all_left_out(seen, outcome.rejected)
        outcome.failed.append(FailedSection(index, z_mm, 0, seen, reason))
    return outcome


@dataclass(frozen=True)
class SectionContext:
    """What every section's processing shares: the calibration, the options and the rules."""

    grid: GridCalibration
    axis: AxisCalibration
    options: ProcessOptions
    rules: OutlierRules
    lift_scale: float = 1.0
    row_turn_deg: float = 0.0


@dataclass(eq=False)
class SectionDone:
    """What processing a section gave: its outcome, and what the scan's warnings and colour
    need of it."""

    index: int
    outcome: SectionOutcome
    points: int
    """Stripe points assembled, before the outlier tests."""
    beyond_view: int
    """Of them, those beyond the disc the camera sees at every angle."""
    colour_views: list[tuple[np.ndarray, np.ndarray]]
    """The coloured views' object-frame points and colours (:func:`assemble_colours`)."""

    @property
    def assembled(self) -> bool:
        """False: every segment of the section was too short after trimming (no section)."""
        return self.points > 0


@dataclass(eq=False)
class BatchDone:
    """What a batch of sections gave (:func:`process_batch`)."""

    sections: list[SectionDone]
    """Each section's result, in the order of its index."""
    skipped: int
    """Segments left out for fewer than ``MIN_SEGMENT_POINTS`` points after trimming."""
    seconds: dict[str, float]
    """The batch's stage times (:class:`Timer`)."""


def process_batch(segments: list[Segment], context: SectionContext) -> BatchDone:
    """Fit, assemble and process the sections of ``segments`` (:func:`process_section`).

    The stripe fit and the assembly of a section depend on its own segments alone, so
    they run in the workers with the rest: done up front for the whole scan, they were a
    sixth of its processing time on one core. A batch holds several whole sections, as
    the stripe fit costs less per segment when given many at once. Module-level, so
    :func:`map_in_workers` can run it in a worker; a section's failure is its outcome's,
    not an exception (only a fault of the fit or the assembly raises, as it did when
    they ran up front).

    Args:
        segments: every segment of the batch's sections, as the device sent them.
        context: the calibration, options and rules every section shares.

    Returns:
        Each section's result in the order of its index, the segments left out and the
        batch's stage times.
    """
    timer = Timer()
    if context.options.refine_stripes:
        with timer.stage("refine_stripes"):
            segments = refined_segments(segments)
    grid, axis, trim = context.grid, context.axis, context.options.trim_fraction
    with timer.stage("assemble"):
        by_section, heights, skipped = assemble(segments, grid, axis, trim, context.row_turn_deg)
        colours = assemble_colours(segments, grid, axis, trim)
    done = []
    for index in sorted({s.section for s in segments}):
        pieces = by_section.get(index, [])
        if not pieces:
            done.append(SectionDone(index, SectionOutcome(), 0, 0, []))
            continue
        z_mm = heights[index] * context.lift_scale
        outcome = process_section(index, z_mm, pieces, context.options, context.rules, timer)
        seen = int(sum(len(p) for p in pieces))
        beyond = beyond_view_count(pieces, context.rules)
        done.append(SectionDone(index, outcome, seen, beyond, colours.get(index, [])))
    return BatchDone(done, skipped, timer.seconds)


def all_left_out(seen: int, rejected: Rejected) -> str:
    """Return the reason of a section the outlier tests left no outline of.

    Such a section has nothing to fit; without its own status it would vanish from the
    result unsaid (a limb-scale object wider than the view lost whole sections so).

    Args:
        seen: the section's stripe points before the tests.
        rejected: what the tests removed from it.
    """
    rest = "" if rejected.points >= seen else ", and the rest are too few for an outline"
    return (
        f"{rejected.points} of its {seen} stripe points were left out as outliers "
        f"({rejected.one_view} seen by one view alone with no second view to confirm them, "
        f"{rejected.view_consensus} contradicted by other views, "
        f"{rejected.spikes + rejected.short_runs} stray){rest}: scan again with the object "
        "centred and more views per section"
    )


def failure_warning(failed: list[FailedSection]) -> list[str]:
    """Return the line naming the outlines that could not be processed, or none."""
    if not failed:
        return []
    names = ", ".join(f"{f.index}.{f.part}" for f in failed)
    return [
        f"outline(s) {names} could not be processed (status failed, reasons in report.json; "
        f"first: {failed[0].reason}); the others are processed and meshed"
    ]


def _neighbours(section: Section, solid: list[Section], reach_mm: float) -> list[Section]:
    """Return the nearest closed outline below and above ``section`` that continues it.

    A candidate continues the outline when its EFD centre lies within its own mean radius
    of the outline's coverage centre and it is at most ``reach_mm`` away in z.
    """
    assert section.coverage is not None
    centre = np.asarray(section.coverage.centre_mm)
    best: dict[bool, Section] = {}
    for other in solid:
        dz = other.z_mm - section.z_mm
        if other.index == section.index or abs(dz) > reach_mm:
            continue
        c = np.array([other.efd.a0, other.efd.c0])
        if np.linalg.norm(c - centre) > np.linalg.norm(other.contour - c, axis=1).mean():
            continue
        side = dz > 0
        if side not in best or abs(dz) < abs(best[side].z_mm - section.z_mm):
            best[side] = other
    return list(best.values())


def fill_gap(section: Section, neighbours: list[Section], options: ProcessOptions) -> Section:
    """Close a large unseen gap with the neighbouring sections' contour (z-interpolated).

    The neighbours' EFDs are interpolated to this height (``EfdStack``, thesis ref. [86]);
    its samples inside the gap, moved to meet the gap's measured sides
    (``coverage.match_sides``), join the measured points and the outline is refitted.
    ``raw`` keeps the measured points only; the contour samples in the gap are flagged.
    """
    assert section.coverage is not None
    stack_ = EfdStack.from_sections([s.z_mm for s in neighbours], [s.efd for s in neighbours])
    predicted = stack_.section(section.z_mm).evaluate(GAP_FILL_SAMPLES)
    coverage = section.coverage
    # Only what falls in the gaps: the neighbour's size differs, and where this outline
    # was measured its own points say where it is.
    fill = predicted[~coverage.covered[coverage.bins_of(predicted)]]
    fill = match_sides(section.raw, fill, coverage.frame)
    merged = np.concatenate([section.raw, fill])
    merged = merged[np.argsort(section.coverage.frame.to_local(merged)[0], kind="stable")]
    # The order the outline's own points chose (the filled curve adds no detail to judge).
    efd = fit_outline(merged, replace(options, harmonics=options.harmonics or section.harmonics))
    contour = contour_samples(efd, options)
    estimated = estimated_samples(section.coverage, contour, section.raw)
    return replace(
        section, efd=efd, contour=contour, status=OutlineStatus.INTERPOLATED, estimated=estimated
    )


def fill_gaps(sections: list[Section], options: ProcessOptions) -> list[Section]:
    """Fill each open outline's gap from closed outlines of neighbouring sections.

    Only outlines closed from their own data ("measured" or "bridged") are used, within
    ``INTERP_REACH_SECTIONS`` pitches; with no such neighbour the outline stays open.
    """
    pitch = section_pitch_mm(sections)
    if pitch is None or all(s.closed for s in sections):
        return sections
    solid = [s for s in sections if s.status in (OutlineStatus.MEASURED, OutlineStatus.BRIDGED)]
    reach = INTERP_REACH_SECTIONS * pitch
    out = []
    for s in sections:
        near = _neighbours(s, solid, reach) if s.status == OutlineStatus.OPEN else []
        try:
            out.append(fill_gap(s, near, options) if near else s)
        except Exception:  # the neighbours could not fill it: it stays open, as it is
            out.append(s)
    return out


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
        still_open: list[list[Section]] = []
        for s in by_index[index]:
            c = centroid_or_mean(s.contour)
            reach = float(np.linalg.norm(s.contour - c, axis=1).mean())
            best, best_d = None, reach
            for chain in open_chains:
                d = float(np.linalg.norm(centroid_or_mean(chain[-1].contour) - c))
                if d < best_d and chain not in still_open:  # Sections compare by identity
                    best, best_d = chain, d
            if best is None:
                best = [s]
                chains.append(best)
            else:
                best.append(s)
            still_open.append(best)
        open_chains = still_open
    return chains


MIN_SEEN_RUN = 3
"""Seen stretches of an open outline shorter than this many contour samples are not meshed
(a sample or two where the EFD's bridge crosses measured radii); then unseen stretches this
short between seen ones are (a sample off by more than the measured tolerance)."""


def _clean_runs(mask: np.ndarray, min_run: int = MIN_SEEN_RUN) -> np.ndarray:
    """Return a circular mask with True runs shorter than ``min_run`` cleared, then False
    runs shorter than ``min_run`` between True ones set."""
    out = np.asarray(mask, dtype=bool).copy()
    for value in (True, False):
        if out.all() or not out.any():
            return out
        start = int(np.flatnonzero(out != np.roll(out, 1))[0])  # a run starts here
        rolled = np.roll(out, -start)
        edges = np.flatnonzero(np.diff(rolled.astype(np.int8))) + 1
        for run in np.split(np.arange(len(out)), edges):
            if rolled[run[0]] == value and len(run) < min_run:
                rolled[run] = not value
        out = np.roll(rolled, start)
    return out


def seen_samples(section: Section, ring: np.ndarray) -> np.ndarray:
    """Return which points of ``ring`` (the section's contour, aligned) are on seen surface.

    A closed outline (measured, or closed across its gaps and flagged estimated) is all
    seen: it is meshed whole. An open one is seen where its measured points back it: in a
    covered bin within the measured radii (``Coverage.unseen``) and within
    ``MEASURED_TOLERANCE_MM`` of a measured point, which leaves out where the closed EFD
    curve swings off an open outline's ends; in stretches of at least
    :data:`MIN_SEEN_RUN` samples.
    """
    if section.closed or section.coverage is None:
        return np.ones(len(ring), dtype=bool)
    from scipy.spatial import cKDTree  # deferred: only open outlines need it

    measured = _along_steps(section.raw, CONTINUOUS_STEP_MM, MEASURED_TOLERANCE_MM / 2.0)
    near = cKDTree(measured).query(ring, distance_upper_bound=MEASURED_TOLERANCE_MM)[0]
    return _clean_runs(~section.coverage.unseen(ring) & np.isfinite(near))


def _along_steps(points: np.ndarray, step_mm: float, spacing_mm: float) -> np.ndarray:
    """Return ``points`` (in order along the outline) with samples every ``spacing_mm`` on
    each step between consecutive ones of at most ``step_mm``: the stripe saw the surface
    between them, as coverage counts it (``coverage.CONTINUOUS_STEP_MM``)."""
    if len(points) < 2:
        return points
    step = np.diff(points, axis=0)
    length = np.hypot(step[:, 0], step[:, 1])
    fill = np.flatnonzero((length > spacing_mm) & (length <= step_mm))
    if not len(fill):
        return points
    counts = np.ceil(length[fill] / spacing_mm).astype(np.int64)
    owner = np.repeat(fill, counts - 1)
    frac = np.concatenate([np.arange(1, c) / c for c in counts])
    return np.vstack([points, points[owner] + frac[:, None] * step[owner]])


def _ring_seen(chain: list[Section], rings: np.ndarray, measured: np.ndarray) -> np.ndarray:
    """Return (R, M) seen flags of a chain's rings: each section's own at its ring, and at a
    ring the interpolation inserted between two sections, seen where both are."""
    at = np.flatnonzero(measured)
    own = np.stack([seen_samples(s, rings[k]) for s, k in zip(chain, at, strict=True)])
    slab = np.clip(np.searchsorted(at, np.arange(len(rings)), side="right") - 1, 0, len(at) - 1)
    below, above = own[slab], own[np.minimum(slab + 1, len(at) - 1)]
    return np.where(measured[:, None], own[np.cumsum(measured) - 1], below & above)


def _runs(mask: np.ndarray) -> list[np.ndarray]:
    """Return the index runs of True in a circular mask, each in order (one may wrap)."""
    if mask.all():
        return [np.arange(len(mask))]
    if not mask.any():
        return []
    start = int(np.flatnonzero(~mask)[0])
    order = np.roll(np.arange(len(mask)), -start)
    edges = np.flatnonzero(np.diff(mask[order].astype(np.int8))) + 1
    return [run for run in np.split(order, edges) if mask[run[0]]]


def radial_ring(
    section: Section, points: int, oversample: int = 8
) -> tuple[np.ndarray, np.ndarray] | None:
    """Return the section's contour at ``points`` equal angles about its coverage centre
    (from -180 degrees, counter-clockwise) and which of them are seen; None where it is not
    star-shaped about the centre.

    An open outline's EFD closes it by a curve across the unseen gap, so its parameter
    does not fall on the same stretch of surface as a closed neighbour's: rings joined
    sample by sample would twist. Equal angles about the centre join them where the
    surface is the same. Only the seen stretches (:func:`seen_samples`) are sampled so:
    the invented curve may pass the centre on the wrong side (a half-seen outline).
    A closed outline must be star-shaped all round; None also when less than 75 % of a
    seen stretch advances round the centre, or when the outline was blended along a
    reference curve (not star-shaped about its centre).
    """
    if section.coverage is not None and not section.coverage.frame.polar:
        return None
    centre = np.asarray(
        section.coverage.centre_mm if section.coverage else (section.efd.a0, section.efd.c0)
    )
    dense = section.efd.evaluate(oversample * points)
    seen = seen_samples(section, dense)
    d = dense - centre
    angle = np.unwrap(np.arctan2(d[:, 1], d[:, 0]))
    if signed_area(dense) < 0.0:  # counter-clockwise, so what was seen advances round
        dense, angle, seen = dense[::-1], angle[::-1], seen[::-1]
    target = -np.pi + 2.0 * np.pi * np.arange(points) / points
    ring = np.repeat(centre[None], points, axis=0)  # unseen samples: dropped by the mesh
    hit = np.zeros(points, dtype=bool)
    # Shortest first: where stretches overlap in angle the longest is the one meshed.
    for run in sorted(_runs(seen), key=len):
        run_angle = np.unwrap(angle[run])
        if np.ptp(run_angle) < MIN_SEEN_RUN * 2.0 * np.pi / points:
            continue  # narrower than the shortest stretch meshed (a hook at an end)
        xy = dense[run]
        if len(run) == len(seen):  # closed: round the wrap, and it must be star-shaped
            run_angle = np.append(run_angle, run_angle[0] + 2.0 * np.pi)
            xy = np.vstack([xy, xy[:1]])
            if np.any(np.diff(run_angle) <= 0.0):
                return None
        # A seen stretch may hook back at an open outline's end, where the EFD turns into
        # the curve it invents across the gap: only the part that advances is sampled.
        ahead = np.concatenate([[True], np.diff(run_angle) > 0.0]) & (
            run_angle >= np.maximum.accumulate(run_angle)
        )
        if ahead.mean() < 0.75:
            return None  # not star-shaped about the centre
        run_angle, xy = run_angle[ahead], xy[ahead]
        t = run_angle[0] + (target - run_angle[0]) % (2.0 * np.pi)
        inside = t <= run_angle[-1]
        ring[inside, 0] = np.interp(t[inside], run_angle, xy[:, 0])
        ring[inside, 1] = np.interp(t[inside], run_angle, xy[:, 1])
        hit |= inside
    seen_ring = _clean_runs(hit)
    filled = seen_ring & ~hit  # a sample or two between seen ones: from its neighbours
    if filled.any():
        k = np.arange(points)
        for axis in (0, 1):
            ring[filled, axis] = np.interp(k[filled], k[hit], ring[hit, axis], period=points)
    return ring, seen_ring


def chain_rings(
    chain: list[Section], points: int, interpolation: str
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return a chain's mesh rings (R, M, 2), their heights and which were seen (R, M).

    Closed chains follow the aligned EFD stack and its interpolation along z (rings
    inserted where it curves). A chain holding an open outline is sampled at equal angles
    about each outline's centre (:func:`radial_ring`) and joined straight between
    sections: coefficients interpolated between a closed outline and one closed across
    an invented gap describe neither.
    """
    z = np.array([s.z_mm for s in chain])
    if any(not s.closed for s in chain):
        radial = [radial_ring(s, points) for s in chain]
        if all(r is not None for r in radial):
            rings = np.stack([r[0] for r in radial if r is not None])
            return rings, z, np.stack([r[1] for r in radial if r is not None])
        interpolation = "linear"  # not star-shaped: joined by parameter, but straight
    stack_ = EfdStack.from_sections(list(z), [s.efd for s in chain], interpolation)
    heights, measured = stack_.ring_heights()
    rings = stack_.sample(points, heights)
    return rings, heights, _ring_seen(chain, rings, measured)


def mesh_contours(
    sections: list[Section], points: int, interpolation: str
) -> tuple[np.ndarray, np.ndarray]:
    """Mesh each chain of outlines as a tube of aligned EFD contours.

    Between sections the tube follows ``interpolation``: where it curves along z (PCHIP
    over a rounded end) rings interpolated by it are inserted (``EfdStack.ring_heights``),
    so the mesh encloses the volume the clinical measurements integrate. A chain of closed
    outlines gives a closed tube; where an outline is open the tube keeps only the seen
    stretches (:func:`~lamina_host.reconstruct.mesh.open_tube_mesh`, :func:`chain_rings`), an open
    surface. An outline in a chain of its own (seen in one section only,
    :func:`lone_outlines`) is a curve with no surface: not meshed.
    """
    vertices, faces, _ = _contour_mesh(sections, points, interpolation)
    return vertices, faces


def _contour_mesh(
    sections: list[Section], points: int, interpolation: str
) -> tuple[np.ndarray, np.ndarray, list[list[Section]]]:
    """Return :func:`mesh_contours`'s mesh and the chains of outlines that gave no face.

    A chain of open outlines gives no face when what was seen of them is too narrow to
    mesh, or does not overlap in angle from one section to the next.
    """
    verts, faces, bare, offset = [], [], [], 0
    for chain in chain_outlines(sections):
        if len(chain) < 2:
            continue
        rings, heights, seen = chain_rings(chain, points, interpolation)
        v, f = open_tube_mesh(rings, heights, seen)
        if not len(f):
            bare.append(chain)
            continue
        verts.append(v)
        faces.append(f + offset)
        offset += len(v)
    if not faces:
        return np.empty((0, 3)), np.empty((0, 3), np.int64), bare
    return np.vstack(verts), np.vstack(faces), bare


def lone_outlines(sections: list[Section]) -> list[Section]:
    """Return the outlines that continue none in a neighbouring section (chains of one)."""
    return [chain[0] for chain in chain_outlines(sections) if len(chain) == 1]


def section_pitch_mm(sections: list[Section]) -> float | None:
    """Return the median spacing between consecutive sections, or None for one section."""
    heights = sorted({s.z_mm for s in sections})
    gaps = np.diff(heights)
    gaps = gaps[gaps > 0]
    return float(np.median(gaps)) if len(gaps) else None


def build_mesh(
    sections: list[Section], options: ProcessOptions
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Mesh the contours with ``options.mesh``; return vertices, faces and warnings.

    The contour mesh keeps what was measured: closed outlines give a closed surface, open
    ones (a wide unseen gap nothing could fill) the stretches that were seen. Ball pivoting
    and Poisson mesh the closed outlines only (Poisson would close an open surface).
    """
    if not sections:
        return np.empty((0, 3)), np.empty((0, 3), np.int64), ["no outline: nothing to mesh"]
    if options.mesh == "contours":
        lone = ", ".join(f"{s.index}.{s.part}" for s in lone_outlines(sections))
        warnings = [] if not lone else [
            f"outline(s) {lone} continue no outline of a neighbouring section: a curve "
            "without surface, not meshed; scan more sections there"
        ]  # fmt: skip
        vertices, faces, bare = _contour_mesh(
            sections, options.outline_points, options.interpolation
        )
        if bare:
            names = ", ".join(
                f"{chain[0].index}.{chain[0].part} to {chain[-1].index}.{chain[-1].part}"
                for chain in bare
            )
            warnings.append(
                f"outline(s) {names}: too little of them was seen, or not at the same angles "
                "from one section to the next, to mesh a surface between them; scan more "
                "views there"
            )
        return vertices, faces, warnings
    closed = [s for s in sections if s.closed]
    warnings = []
    if len(closed) < len(sections):
        warnings.append(
            f"{len(sections) - len(closed)} open outline(s) are left out of the "
            f"{options.mesh} mesh; use --mesh contours to mesh what was seen of them"
        )
    empty = np.empty((0, 3)), np.empty((0, 3), np.int64)
    if not closed:
        return *empty, [*warnings, "no outline is closed: nothing to mesh"]
    pitch = section_pitch_mm(closed)
    if pitch is None:
        single = f"a single section cannot be meshed by {options.mesh}; scan two or more"
        return *empty, [*warnings, single]
    if options.mesh == "poisson":
        return (*mesh_poisson(closed, pitch), warnings)
    return (*mesh_ball_pivoting(closed, pitch, options.ball_radius_mm), warnings)


def mesh_warning(method: str, topo: dict[str, Any]) -> str | None:
    """Return the line saying what is wrong with a mesh that should be closed, or None.

    A contour mesh of outlines not seen all round is an open surface by design (the
    outlines are named by :func:`gap_warnings`); otherwise a boundary or a shared edge
    is a fault of the method, and the contour mesh is the closed alternative.
    """
    kind = mesh_kind(topo)
    if kind in ("closed", "none") or (method == "contours" and kind == "open surface"):
        return None
    if kind == "open surface":
        problem = f"is not closed ({topo['boundary_edges']} boundary edges)"
    else:
        problem = (
            f"is not two-manifold ({topo['non_manifold_edges']} non-manifold edges, "
            f"{topo['non_manifold_vertices']} non-manifold vertices)"
        )
    advice = "" if method == "contours" else "; use --mesh contours for a closed mesh"
    return f"the {method} mesh {problem}{advice}"


def safe_mesh(
    sections: list[Section], options: ProcessOptions
) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """Return :func:`build_mesh`'s mesh, or none and one warning when meshing fails.

    The contours stand without a mesh (points.ply and the report keep them), so a shape
    the mesher cannot take costs the mesh only, never the processed scan.
    """
    try:
        return build_mesh(sections, options)
    except MeshlabMissing:
        raise  # the user's installation, not the shape: say what to install
    except Exception as exc:
        return (
            np.empty((0, 3)),
            np.empty((0, 3), int),
            [f"the {options.mesh} mesh could not be built ({failure_reason(exc)}); the "
             "contours are in points.ply: process again with another --mesh"],
        )  # fmt: skip


def camera_disc_mm(
    grid: GridCalibration, image_shape: tuple[int, ...], axis: AxisCalibration
) -> float | None:
    """Return the radius about the axis of the disc the camera sees at every turntable angle.

    The image border is mapped into the laser plane; the disc reaches the nearest border
    point (object-frame mm). None when the axis is not inside the camera's view.
    """
    h, w = image_shape[:2]
    t = np.linspace(0.0, 1.0, 64, endpoint=False)
    u, v = (w - 1) * t, (h - 1) * t
    top, bottom = np.zeros_like(u), np.full_like(u, h - 1.0)
    left, right = np.zeros_like(v), np.full_like(v, w - 1.0)
    border = np.concatenate(  # round the image, back to the start
        [np.stack([u, top], 1), np.stack([right, v], 1), np.stack([w - 1 - u, bottom], 1),
         np.stack([left, h - 1 - v], 1), [[0.0, 0.0]]]
    )  # fmt: skip
    world = grid.homography.apply(border)
    d = world - np.asarray(axis.axis_xy_mm)
    winding = np.diff(np.unwrap(np.arctan2(d[:, 1], d[:, 0])))
    if not np.isfinite(world).all() or abs(winding.sum()) < np.pi:
        return None  # the border does not wind round the axis
    return float(np.hypot(d[:, 0], d[:, 1]).min() * axis.correction_factor)


def beyond_view_count(pieces: list[np.ndarray], rules: OutlierRules) -> int:
    """Return how many of a section's points lie beyond ``rules.working_radius_mm`` (or 0)."""
    if rules.working_radius_mm is None:
        return 0
    return sum(int(np.sum(np.hypot(p[:, 0], p[:, 1]) > rules.working_radius_mm)) for p in pieces)


def beyond_view_warning(beyond: int, rules: OutlierRules, rejected: Rejected) -> str | None:
    """Return the line saying the object reaches beyond the camera's view, or None.

    Stripe points further from the axis than the disc the camera sees at every angle are
    kept where other views confirm them (:mod:`.outliers`), but the views that turned that
    part out of the image saw nothing of it: the object is wider than the rig's view.

    Args:
        beyond: the scan's stripe points beyond that disc (:func:`beyond_view_count`).
        rules: the outlier rules, with the disc's radius.
        rejected: what the outlier tests removed.
    """
    if rules.working_radius_mm is None:
        return None
    kept = beyond - rejected.outside_volume
    if kept <= 0:
        return None
    return (
        f"{kept} stripe point(s) lie further than {rules.working_radius_mm:.1f} mm from the "
        "turntable axis, beyond what the camera sees at every angle: the object is wider "
        "than this rig's view, so some views missed that part and it may be left open; "
        "kept where two views agree (a rig with a wider view sees it all)"
    )


KEPT_LITTLE_SHARE = 0.5
"""Below this share of its stripe points kept as surface, a scan is told what it lost."""


def kept_little_warning(total_points: int, rejected: Rejected) -> str | None:
    """Return the line saying most of what the camera saw was left out, or None.

    The outlier tests keep a stretch of stripe where a second view confirms it or where
    it continues one that is confirmed. Where the views barely overlap (an object wider
    than the view, standing off the axis, or deep folds each view sees alone), most of
    the stripe is a stretch one view saw: nothing contradicts it, nothing confirms it,
    and it is left out. A result built from the rest is honest but small (a random
    limb-scale star 280 mm across kept 109 of 3,545 points); the user must be told why
    and what to do, not only given open outlines.

    Args:
        total_points: the scan's stripe points before the outlier tests.
        rejected: what the tests removed.

    Returns:
        One line when less than :data:`KEPT_LITTLE_SHARE` of the points were kept and most
        of those left out were seen by one view alone.
    """
    if total_points <= 0 or rejected.points <= (1.0 - KEPT_LITTLE_SHARE) * total_points:
        return None
    if 2 * rejected.one_view <= rejected.points:
        return None  # mostly contradicted by other views: reflections, said by its own line
    kept = total_points - rejected.points
    return (
        f"only {kept} of {total_points} stripe points ({100.0 * kept / total_points:.0f} %) "
        f"were kept as surface: {rejected.one_view} were seen by one view alone, with no second "
        "view to confirm them (beyond the disc every view sees, or in stretches no other "
        "view overlapped), and were left out, so the result shows only a part of what the "
        "camera saw; centre the object on the turntable and scan again with more views per "
        "section, so that neighbouring views overlap"
    )


def rejection_warning(rejected: Rejected) -> str:
    """Return one line saying how many points the outlier tests removed and why."""
    return (
        f"{rejected.points} stripe point(s) rejected as outliers: {rejected.outside_volume} "
        f"outside the working volume, {rejected.spikes} spikes, {rejected.view_consensus} "
        f"contradicted by overlapping views, {rejected.unsupported_clusters} in "
        f"{rejected.clusters} cluster(s) too small or seen by too few views to be an outline, "
        f"{rejected.short_runs} in stray stretches of under {MIN_RUN_POINTS} points"
    )


def gap_warnings(sections: list[Section]) -> list[str]:
    """Return lines naming the outlines that are estimated in part or left open."""

    def names(status: OutlineStatus) -> str:
        return ", ".join(f"{s.index}.{s.part}" for s in sections if s.status == status)

    lines = []
    if filled := names(OutlineStatus.INTERPOLATED):
        lines.append(
            f"outline(s) {filled} had unseen gaps too wide to bridge; filled from the "
            "neighbouring sections (flagged estimated, left out of points.ply)"
        )
    if left := names(OutlineStatus.OPEN):
        lines.append(
            f"outline(s) {left} had unseen gaps too wide to bridge and no closed neighbour: "
            "left open, only their seen stretches meshed (an open surface); add views or "
            "sections to close them"
        )
    return lines


def process_segments(
    grid: GridCalibration,
    axis: AxisCalibration,
    segments: list[Segment],
    options: ProcessOptions,
    timer: Timer,
    rules: OutlierRules | None = None,
    lift_scale: float = 1.0,
    workers: int | None = None,
    row_turn_deg: float = 0.0,
) -> tuple[list[Section], list[str], Rejected, list[FailedSection]]:
    """Fit and assemble the object's stripes, reject outliers, fit the outlines, close gaps.

    Each section is processed on its own (:func:`process_batch`: its stripes fitted when
    ``options.refine_stripes``, then assembled and processed by :func:`process_section`):
    one that fails is returned among the failed outlines with its reason, and the others
    go on. Each section's height is its commanded lift height times ``lift_scale`` (the
    calibrated lift, :func:`lift_calibration`). Sections are shared among ``workers``
    processes (:func:`workers_for`: None, every core where the scan is large enough), in
    batches of whole sections (:func:`in_batches`), with the same result bit for bit;
    ``timer``'s "refine_stripes", "assemble", "reject" and "fit_efd" then add up the
    workers' times, so they can exceed the wall time. ``row_turn_deg`` turns each point
    of a continuous scan by its row's share (:func:`assemble`).

    Raises:
        CalibrationError: no view shows the stripe, or no section gave an outline.
    """
    rules = rules or OutlierRules(working_radius_mm=options.working_radius_mm)
    context = SectionContext(grid, axis, options, rules, lift_scale, row_turn_deg)
    by_section: dict[int, list[Segment]] = {}
    for segment in segments:
        by_section.setdefault(segment.section, []).append(segment)
    count = workers_for(len(by_section), workers)
    sections_in = in_batches([by_section[k] for k in sorted(by_section)], count)
    batches = [list(itertools.chain.from_iterable(b)) for b in sections_in]
    done: list[SectionDone] = []
    skipped = 0
    for batch in map_in_workers(partial(process_batch, context=context), batches, count):
        done += batch.sections
        skipped += batch.skipped
        timer.add(batch.seconds)
    warnings = []
    if skipped:
        warnings.append(
            f"{skipped} segment(s) had fewer than {MIN_SEGMENT_POINTS} points "
            "after trimming and were left out"
        )
    done = [d for d in done if d.assembled]
    if not done:
        raise CalibrationError(
            "no view of the object shows the laser stripe: check the object "
            "stands inside the laser plane and the laser works"
        )
    rejected = Rejected()
    sections: list[Section] = []
    failed: list[FailedSection] = []
    for d in done:
        rejected.add(d.outcome.rejected)
        sections += d.outcome.sections
        failed += d.outcome.failed
    if rejected.points:
        warnings.append(rejection_warning(rejected))
    if line := beyond_view_warning(sum(d.beyond_view for d in done), rules, rejected):
        warnings.append(line)
    total = sum(d.points for d in done)
    if sections and (line := kept_little_warning(total, rejected)):
        warnings.append(line)
    if not sections:
        if rules.working_radius_mm is not None and rejected.outside_volume * 2 > total:
            raise CalibrationError(
                f"{rejected.outside_volume} of {total} stripe points lie further than "
                f"{rules.working_radius_mm:.1f} mm from the turntable axis, outside what the "
                "camera sees at every angle: the object is larger than this rig's field of "
                "view; scan it on a rig with a wider view (the simulator: --rig limb)"
            )
        why = f" ({failed[0].reason})" if failed else ""
        raise CalibrationError(
            f"no section has an outline seen well enough by two or more views{why}: check "
            "the object stands inside the laser plane and that neighbouring views overlap "
            "(scan with more views per section)"
        )
    with timer.stage("fit_efd"):
        sections = fill_gaps(sections, options)
    with timer.stage("colour"):
        sections = colour_sections(sections, {d.index: d.colour_views for d in done})
    warnings += failure_warning(failed) + gap_warnings(sections)
    return sections, warnings, rejected, failed


def lift_sections(
    cylinder: list[Segment], reference: LiftReference | None
) -> tuple[list[Segment], list[list[Segment]]]:
    """Split the cylinder's views: those for the axis, and those at each lift mark."""
    if reference is None:
        return cylinder, []
    marks: list[list[Segment]] = [[] for _ in reference.marks_mm]
    axis_views: list[Segment] = []
    for segment in cylinder:
        at = [k for k, z in enumerate(reference.marks_mm) if abs(segment.z_mm - z) <= 1e-6]
        (marks[at[0]] if at else axis_views).append(segment)
    return axis_views, marks


def lift_calibration(
    marks: list[list[Segment]],
    reference: LiftReference,
    grid: GridCalibration,
    axis: AxisCalibration,
    trim_fraction: float,
) -> LiftCalibration:
    """Measure the lift's scale on the cylinder's grooves (:func:`calibrate_lift`)."""

    def local(s: Segment) -> np.ndarray:
        return object_points(s, trimmed_order(s, trim_fraction), grid, axis)

    def circle(points: np.ndarray) -> tuple[float, float]:
        fitted = fit_circle(points)
        return fitted.r, fitted.rms_mm

    arcs = [[local(s) for s in views] for views in marks]
    return calibrate_lift(arcs, reference, axis.actual_diameter_mm / 2.0, circle)


def calibrate_rig(
    grid_image: np.ndarray,
    board: BoardSpec,
    cylinder: list[Segment],
    cylinder_mm: float,
    options: ProcessOptions,
    lift_reference: LiftReference | None = None,
    timer: Timer | None = None,
) -> tuple[GridCalibration, AxisCalibration, list[list[Segment]]]:
    """Calibrate the laser plane from the board and the turntable from the cylinder (6.1-6.2).

    Args:
        grid_image: the board's image.
        board: the board's layout.
        cylinder: the cylinder's views as the device sent them (their turns are counted
            from the first here).
        cylinder_mm: the cylinder's diameter.
        options: the processing options (calibration method, distortion, axis method,
            trim, angle correction, stripe fit).
        lift_reference: the cylinder's lift marks, None when it has none.
        timer: where the stages' times go (None: nowhere).

    Returns:
        The plane's calibration, the turntable's, and the cylinder's views at each lift
        mark (for :func:`lift_calibration`).

    Raises:
        CalibrationError: the board or the cylinder could not be used.
    """
    timer = timer or Timer()
    cylinder = from_first_turn(cylinder)
    if options.refine_stripes:  # the object's stripes are fitted section by section
        with timer.stage("refine_stripes"):
            cylinder = refined_segments(cylinder)
    with timer.stage("calibrate_grid"):
        distortion = options.distortion if options.calibration == "ml" else "off"
        grid = calibrate_grid(grid_image, board, options.calibration, distortion)
    axis_views, marks = lift_sections(cylinder, lift_reference)
    with timer.stage("calibrate_axis"):
        axis = calibrate_axis(
            axis_views, grid, cylinder_mm, options.trim_fraction, options.axis,
            options.angle_correction, options.per_view_angles,
        )  # fmt: skip
    return grid, axis, marks


def reconstruct(
    grid_image: np.ndarray,
    board: BoardSpec,
    cylinder: list[Segment],
    cylinder_mm: float,
    segments: list[Segment],
    options: ProcessOptions | None = None,
    lift_reference: LiftReference | None = None,
    workers: int | None = None,
    row_turn_deg: float = 0.0,
    laser_off_turn_later: bool = False,
) -> Reconstruction:
    """Run every stage from the raw calibration data and segments to the mesh.

    With a ``lift_reference`` the cylinder's views at its marks calibrate the lift
    (:func:`lift_calibration`) and the others the axis; every section height is then
    the commanded one times the lift's scale. ``workers`` processes share the sections
    (:func:`process_segments`; None: as many as the cores and the scan's size allow).
    ``row_turn_deg`` is a continuous scan's turn per image row (:func:`assemble`);
    ``laser_off_turn_later`` says its laser-off frames were taken a turn of the count
    later, which the scan's warnings then judge against the calibrated gear
    (:func:`~lamina_host.reconstruct.axis.next_turn_warning`).

    Raises:
        CalibrationError: the board or the cylinder could not be used.
    """
    options = options or ProcessOptions()
    options.check()
    timer = Timer()
    segments = from_first_turn(segments)
    grid, axis, marks = calibrate_rig(
        grid_image, board, cylinder, cylinder_mm, options, lift_reference, timer
    )
    lift = None
    if lift_reference is not None:
        with timer.stage("calibrate_lift"):
            lift = lift_calibration(marks, lift_reference, grid, axis, options.trim_fraction)
    scale = lift.scale if lift is not None and lift.applied else 1.0
    radius = options.working_radius_mm or camera_disc_mm(grid, grid_image.shape, axis)
    rules = OutlierRules(working_radius_mm=radius)
    sections, warnings, rejected, failed = process_segments(
        grid, axis, segments, options, timer, rules, scale, workers, row_turn_deg
    )
    lift_warnings = list(lift.warnings) if lift is not None else []
    warnings = [*grid.warnings, *axis.warnings, *lift_warnings, *warnings]
    if laser_off_turn_later and (line := next_turn_warning(axis)):
        warnings.append(line)
    with timer.stage("mesh"):
        vertices, faces, mesh_warnings = safe_mesh(sections, options)
        topo = MeshTopology.of(vertices, faces)
    warnings += mesh_warnings
    if line := mesh_warning(options.mesh, topo.to_dict() if topo else {}):
        warnings.append(line)
    points, colours = coloured_cloud(sections)
    colour = vertex_colours(vertices, points, colours) if len(points) and len(vertices) else None
    return Reconstruction(
        grid, axis, sections, vertices, faces, topo, timer.seconds, warnings, options, rejected,
        colour, failed, lift,
    )  # fmt: skip
