"""Clinical limb measurements: circumferences from a landmark, volumes, comparisons, history.

A lymphoedema clinic tapes circumferences every 4 cm (or 8 cm) along the limb from a fixed
landmark and turns consecutive pairs into truncated cones, V = h (C1^2 + C1 C2 + C2^2) /
(12 pi); it reports the limb volume, the excess of the affected limb over the other and the
change from the baseline visit (issue #13). Here the tape is replaced by the scan's EFD
sections (thesis 6.4): the coefficients are interpolated along z (``EfdStack``, thesis
9.2), so a circumference can be taken at any level inside the measured range and never
outside it. The exact volume integrates the interpolated sections' enclosed area along z;
the frustum volume from the same circumferences is given too, so results compare with tape
records. Sections the coverage work left open are not part of the stack; levels that
depend on an outline closed by estimation (bridged or filled from neighbours) or that lie
across an open section say so.

All distances along the limb are measured along its axis: the turntable axis (z) by
default, or a straight centre line fitted through the section centroids for a limb that
does not stand upright. Then a circumference is that of the horizontal section projected
onto the plane normal to the centre line (exact for a limb that is straight along it).
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Any

import numpy as np

from lamina_host.reconstruct.efd import CLINICAL_INTERPOLATION, EfdStack, EllipticFourier, efd_area
from lamina_host.reconstruct.measure import centroid
from lamina_host.reconstruct.status import CLOSED, OutlineStatus
from lamina_shared.errors import InputError

AXES = ("auto", "turntable", "centreline")
"""How distances along the limb are measured; the first is the default. ``auto`` measures
along the centre line where the limb stands measurably tilted (:func:`fit_axis`), else
along the turntable axis."""

AUTO_TILT_DEG = 0.5
"""``auto`` takes the centre line only for a limb tilted more than this. Measuring a limb
tilted by t along the turntable axis overstates lengths and volumes by 1/cos t - 1 and
circumferences by about t^2/4: at 0.5 deg 0.004 % and 0.005 mm on a 270 mm forearm, far
below what a clinic can see, while the centre line fitted to a straight upright limb on the
limb rig leans 0.01-0.05 deg (bench_repeat, README "Repeatability"); a limb put back 3 deg
off upright reads 0.14 % more volume on the turntable axis."""

AUTO_TILT_SIGMAS = 3.5
"""``auto`` also wants the tilt this many standard errors of the fit beyond zero: a fitted
tilt of an upright limb exceeds 3.5 standard errors once in 450 scans."""

LANDMARK_KINDS = ("distal", "bottom", "top")
"""Named landmarks; a number is a section height in mm. ``distal`` is the narrower end."""

DEFAULT_SPACING_MM = 40.0
"""Tape spacing in clinics: 4 cm (8 cm is also in use)."""

OUTLINE_SAMPLES = 1024
"""Samples per outline for a circumference: the polygon's shortfall on a circle is
(pi / n)^2 / 6 of it, 1.6e-6 (0.001 mm on a 600 mm thigh)."""

_LEVEL_TOLERANCE_MM = 1e-6

DISTAL_MARGIN = 0.01
"""The top end is taken as distal only when its circumference is this share smaller than
the bottom end's; a limb of even girth is measured from the bottom."""


class ClinicalError(InputError):
    """A measurement cannot be made as asked; the text names why and what to do."""


@dataclass(frozen=True, eq=False)
class LimbSection:
    """One outline of a limb scan: its height, EFD and how it was closed.

    A failed outline (``OutlineStatus.FAILED``, not processed) has no EFD: it is a gap,
    as an open outline is, and a level measured across it says so.
    """

    z_mm: float
    efd: EllipticFourier | None
    status: OutlineStatus = OutlineStatus.MEASURED

    @property
    def closed(self) -> bool:
        """Return whether the outline is closed (so it is part of the volume)."""
        return self.status in CLOSED and self.efd is not None


@dataclass(frozen=True)
class Landmark:
    """Where level 0 lies: a named end (``LANDMARK_KINDS``) or a height (``kind`` "height")."""

    kind: str = "distal"
    z_mm: float | None = None

    def describe(self) -> str:
        """Return the landmark in words (for tables and reports)."""
        if self.kind == "height":
            return f"section height {self.z_mm:.1f} mm"
        return {"distal": "distal end", "bottom": "lowest section", "top": "highest section"}[
            self.kind
        ]


def parse_landmark(text: str) -> Landmark:
    """Return the landmark a user typed: ``distal``, ``bottom``, ``top`` or a height in mm.

    Raises:
        ClinicalError: anything else.
    """
    word = text.strip().lower()
    if word in LANDMARK_KINDS:
        return Landmark(word)
    try:
        z = float(word.removeprefix("z=").removesuffix("mm"))
    except ValueError:
        z = math.nan
    if not math.isfinite(z):
        raise ClinicalError(
            f"landmark {text!r} must be distal, bottom, top or a section height in mm"
        )
    return Landmark("height", z)


@dataclass(frozen=True)
class Thresholds:
    """When a comparison is flagged (issue #13: the thresholds clinics use)."""

    limb_difference_ml: float = 200.0
    limb_difference_percent: float = 5.0
    circumference_mm: float = 20.0
    change_percent: float = 3.0


@dataclass(frozen=True)
class LimbAxis:
    """The limb's axis: through ``origin_mm`` along the unit ``direction`` (z component > 0)."""

    method: str
    origin_mm: tuple[float, float, float]
    direction: tuple[float, float, float]
    choice: str = ""
    """Why ``auto`` took this axis (empty when the axis was asked for by name)."""

    @property
    def tilt_deg(self) -> float:
        """Return the angle between the axis and the turntable axis."""
        return math.degrees(math.acos(min(1.0, self.direction[2])))

    def position_mm(self, z_mm: float | np.ndarray) -> Any:
        """Return the distance along the axis of the horizontal plane at ``z_mm``."""
        return (np.asarray(z_mm, dtype=float) - self.origin_mm[2]) / self.direction[2]

    def height_mm(self, position_mm: float) -> float:
        """Return the height of the horizontal plane at ``position_mm`` along the axis."""
        return float(self.origin_mm[2] + position_mm * self.direction[2])

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form."""
        return {
            "method": self.method,
            "origin_mm": list(self.origin_mm),
            "direction": list(self.direction),
            "tilt_deg": self.tilt_deg,
            "choice": self.choice,
        }


def fit_axis(sections: Sequence[LimbSection], method: str = AXES[0]) -> LimbAxis:
    """Return the limb axis: the turntable's, a line fitted through the outline centroids,
    or (``auto``) the fitted line where the limb is measurably tilted.

    The centre line is the least-squares fit x = x0 + a z, y = y0 + b z to the centroids
    of the closed outlines (it needs two heights at least). ``auto`` takes it when its tilt
    exceeds both :data:`AUTO_TILT_DEG` and :data:`AUTO_TILT_SIGMAS` standard errors of the
    fit (from the centroids' scatter about the line; three heights at least), and the
    turntable axis otherwise; :attr:`LimbAxis.choice` says which and why.

    Raises:
        ClinicalError: an unknown method, or a centre line from fewer than two sections.
    """
    if method not in AXES:
        raise ClinicalError(f"axis {method!r} must be one of {', '.join(AXES)}")
    closed = [s for s in sections if s.closed]
    turntable = LimbAxis("turntable", (0.0, 0.0, 0.0), (0.0, 0.0, 1.0))
    if method == "turntable":
        return turntable
    if method == "auto" and len({s.z_mm for s in closed}) < 3:
        return replace(turntable, choice="auto: fewer than three sections to fit a centre line")
    if len({s.z_mm for s in closed}) < 2:
        raise ClinicalError("a centre line needs closed sections at two heights at least")
    line, tilt_se_deg = _centre_line(closed)
    if method == "centreline":
        return line
    limit = max(AUTO_TILT_DEG, AUTO_TILT_SIGMAS * tilt_se_deg)
    why = f"centre line tilted {line.tilt_deg:.2f} deg (+-{tilt_se_deg:.2f})"
    if line.tilt_deg > limit:
        return replace(line, choice=f"auto: {why}, beyond {limit:.2f} deg")
    return replace(turntable, choice=f"auto: {why}, within {limit:.2f} deg of upright")


def _centre_line(closed: Sequence[LimbSection]) -> tuple[LimbAxis, float]:
    """Return the centre line through the outlines' centroids and its tilt's standard error
    in degrees (NaN from two heights: no scatter to judge it by)."""
    z = np.array([s.z_mm for s in closed])
    c = np.array([centroid(s.efd.evaluate(OUTLINE_SAMPLES)) for s in closed if s.efd is not None])
    design = np.column_stack([np.ones_like(z), z])
    (x0, ax), *_ = np.linalg.lstsq(design, c[:, 0], rcond=None)
    (y0, ay), *_ = np.linalg.lstsq(design, c[:, 1], rcond=None)
    d = np.array([ax, ay, 1.0]) / math.sqrt(ax * ax + ay * ay + 1.0)
    line = LimbAxis(
        "centreline", (float(x0), float(y0), 0.0), (float(d[0]), float(d[1]), float(d[2]))
    )
    residual = c - design @ np.array([[x0, y0], [ax, ay]])
    sxx = float(np.sum((z - z.mean()) ** 2))
    dof = 2 * (len(z) - 2)
    if dof <= 0 or sxx <= 0.0:
        return line, math.nan
    slope_se = math.sqrt(float(np.sum(residual**2)) / dof / sxx)  # each of a and b
    return line, math.degrees(slope_se)


@dataclass(frozen=True)
class Level:
    """One tape level: its distance from the landmark and the circumference there.

    ``offset_mm`` grows from the landmark towards the other end of the limb; ``source``
    is ``measured`` or ``estimated`` (then ``note`` says why).
    """

    offset_mm: float
    z_mm: float
    circumference_mm: float
    area_mm2: float
    source: str
    note: str = ""

    @property
    def radius_mm(self) -> float:
        """Return the radius of the circle with this circumference."""
        return self.circumference_mm / (2.0 * math.pi)


@dataclass(frozen=True)
class SegmentVolume:
    """The limb between two consecutive levels: exact and frustum volumes in mm^3."""

    offset_lo_mm: float
    offset_hi_mm: float
    volume_mm3: float
    frustum_mm3: float


@dataclass(frozen=True, eq=False)
class LimbMeasurement:
    """A limb's tape table, volumes and profile, all in mm (volumes in mm^3)."""

    axis: LimbAxis
    landmark: Landmark
    landmark_z_mm: float
    spacing_mm: float
    coverage_mm: tuple[float, float]
    levels: tuple[Level, ...]
    segments: tuple[SegmentVolume, ...]
    volume_mm3: float
    stack: EfdStack
    profile_z_mm: np.ndarray
    profile_circumference_mm: np.ndarray
    notes: tuple[str, ...] = ()

    @property
    def levels_volume_mm3(self) -> float:
        """Return the exact volume between the first and the last level."""
        return float(sum(s.volume_mm3 for s in self.segments))

    @property
    def frustum_volume_mm3(self) -> float:
        """Return the frustum (tape) volume between the first and the last level."""
        return float(sum(s.frustum_mm3 for s in self.segments))

    def outline(self, z_mm: float, samples: int = 256) -> np.ndarray:
        """Return the (samples, 2) horizontal outline at ``z_mm`` inside the coverage."""
        return _section_at(self, z_mm).evaluate(samples)

    def table(self) -> list[dict[str, Any]]:
        """Return the measurement table: one row per level with its segment volumes."""
        rows = []
        for k, level in enumerate(self.levels):
            seg = self.segments[k] if k < len(self.segments) else None
            rows.append(
                {
                    "offset_mm": round(level.offset_mm, 3),
                    "z_mm": round(level.z_mm, 3),
                    "circumference_mm": round(level.circumference_mm, 2),
                    "area_mm2": round(level.area_mm2, 1),
                    "segment_volume_ml": round(seg.volume_mm3 / 1000.0, 2) if seg else None,
                    "segment_frustum_ml": round(seg.frustum_mm3 / 1000.0, 2) if seg else None,
                    "source": level.source,
                    "note": level.note,
                    "axis": self.axis.method,
                    "axis_tilt_deg": round(self.axis.tilt_deg, 2),
                }
            )
        return rows

    def summary(self) -> dict[str, Any]:
        """Return the JSON form of the figures (not the stack)."""
        return {
            "axis": self.axis.to_dict(),
            "landmark": self.landmark.describe(),
            "landmark_z_mm": self.landmark_z_mm,
            "spacing_mm": self.spacing_mm,
            "coverage_mm": list(self.coverage_mm),
            "volume_ml": self.volume_mm3 / 1000.0,
            "levels_volume_ml": self.levels_volume_mm3 / 1000.0,
            "frustum_volume_ml": self.frustum_volume_mm3 / 1000.0,
            "levels": self.table(),
            "notes": list(self.notes),
        }


def frustum_volume_mm3(c1_mm: float, c2_mm: float, height_mm: float) -> float:
    """Return the truncated-cone volume between circumferences C1 and C2 ``height_mm`` apart.

    V = h (C1^2 + C1 C2 + C2^2) / (12 pi), the tape model clinics use.
    """
    return height_mm * (c1_mm * c1_mm + c1_mm * c2_mm + c2_mm * c2_mm) / (12.0 * math.pi)


def _section_at(m: LimbMeasurement, z_mm: float) -> EllipticFourier:
    lo, hi = m.coverage_mm
    if not lo - _LEVEL_TOLERANCE_MM <= z_mm <= hi + _LEVEL_TOLERANCE_MM:
        raise ClinicalError(
            f"height {z_mm:.1f} mm lies outside the measured range {lo:.1f}..{hi:.1f} mm"
        )
    return m.stack.section(z_mm)


TAPE_RESOLUTION_MM = 10.0
"""Circumferences leave out what varies faster than this round the outline: skin folds a
tape spans. The outline's series keeps harmonic n only while its wavelength round the
outline, perimeter / n, is at least this long. Folds of a few tenths of a mm at 4-10 mm
add up to 1 mm to a forearm's exact perimeter; whether an outline's series holds them
depends on the order its points' noise allowed, which changes from scan to scan of the
same limb (26 to 43 harmonics on a forearm with 0.16 mm folds at 8 mm: its level
circumference then varied by 0.8 mm, against 0.2 mm without them; bench_repeat)."""


def _tape_outline(efd: EllipticFourier) -> EllipticFourier:
    """Return the outline's series without the harmonics shorter than ``TAPE_RESOLUTION_MM``."""
    pts = efd.evaluate(OUTLINE_SAMPLES)
    length = float(np.linalg.norm(np.diff(np.vstack([pts, pts[:1]]), axis=0), axis=1).sum())
    keep = max(1, int(length / TAPE_RESOLUTION_MM))
    return efd if efd.order <= keep else EllipticFourier(efd.a0, efd.c0, efd.coeffs[:keep])


def _circumference(efd: EllipticFourier, z_mm: float, axis: LimbAxis) -> float:
    """Return the outline's length measured in the plane normal to the axis, at the tape's
    resolution (:data:`TAPE_RESOLUTION_MM`)."""
    pts = _tape_outline(efd).evaluate(OUTLINE_SAMPLES)
    if axis.direction == (0.0, 0.0, 1.0):
        closed = np.vstack([pts, pts[:1]])
        return float(np.linalg.norm(np.diff(closed, axis=0), axis=1).sum())
    u = np.asarray(axis.direction)
    p3 = np.column_stack([pts, np.full(len(pts), z_mm)])
    flat = p3 - np.outer(p3 @ u, u)  # projected along the axis onto its normal plane
    closed = np.vstack([flat, flat[:1]])
    return float(np.linalg.norm(np.diff(closed, axis=0), axis=1).sum())


def stack_volume_mm3(stack: EfdStack, z_lo_mm: float, z_hi_mm: float) -> float:
    """Return the volume between two heights: the enclosed area integrated along z.

    Area is bilinear in the EFD coefficients. Between sections linearly interpolated
    coefficients make it quadratic in z, so Simpson's rule on each slab is exact; PCHIP
    (and the smoothing spline) are cubic between sections, so the area is of degree 6
    and 4-point Gauss-Legendre on each slab (exact to degree 7) is exact too.
    """
    if z_hi_mm <= z_lo_mm:
        return 0.0
    inner = stack.z_mm[(stack.z_mm > z_lo_mm) & (stack.z_mm < z_hi_mm)]
    edges = np.concatenate([[z_lo_mm], inner, [z_hi_mm]])
    if stack.kind == "linear" or len(stack.z_mm) < 3:
        nodes, weights = np.array([-1.0, 0.0, 1.0]), np.array([1.0, 4.0, 1.0]) / 3.0
    else:
        nodes, weights = np.polynomial.legendre.leggauss(4)
    total = 0.0
    for a, b in itertools.pairwise(edges):
        z = 0.5 * (a + b) + 0.5 * (b - a) * nodes
        area = np.array([abs(efd_area(stack.section(float(v)))) for v in z])
        total += float(0.5 * (b - a) * (weights @ area))
    return total


def _level_source(
    z_mm: float, closed: list[LimbSection], opened: list[LimbSection]
) -> tuple[str, str]:
    """Return whether a level rests on measured outlines only, and a note if not."""
    heights = np.array([s.z_mm for s in closed])
    exact = np.flatnonzero(np.abs(heights - z_mm) <= _LEVEL_TOLERANCE_MM)
    if len(exact):
        used = [closed[int(exact[0])]]
        between: list[LimbSection] = []
    else:
        k = int(np.clip(np.searchsorted(heights, z_mm), 1, len(heights) - 1))
        used = [closed[k - 1], closed[k]]
        between = [s for s in opened if used[0].z_mm < s.z_mm < used[1].z_mm]
    notes = [
        f"outline at z={s.z_mm:.1f} mm {s.status}"
        for s in used
        if s.status != OutlineStatus.MEASURED
    ]
    notes += [f"{s.status} section at z={s.z_mm:.1f} mm bridged by interpolation" for s in between]
    return ("estimated", "; ".join(notes)) if notes else (OutlineStatus.MEASURED, "")


def _landmark_position(
    landmark: Landmark, axis: LimbAxis, lo_mm: float, hi_mm: float, distal_top: bool
) -> float:
    """Return the landmark's position along the axis, refusing one outside the coverage."""
    if landmark.kind == "height":
        z = float(landmark.z_mm if landmark.z_mm is not None else math.nan)
        if not lo_mm - _LEVEL_TOLERANCE_MM <= z <= hi_mm + _LEVEL_TOLERANCE_MM:
            raise ClinicalError(
                f"landmark height {z:.1f} mm lies outside the measured range "
                f"{lo_mm:.1f}..{hi_mm:.1f} mm; give a height inside it"
            )
        return float(axis.position_mm(min(max(z, lo_mm), hi_mm)))
    top = landmark.kind == "top" or (landmark.kind == "distal" and distal_top)
    return float(axis.position_mm(hi_mm if top else lo_mm))


def measure_limb(
    sections: Sequence[LimbSection],
    spacing_mm: float = DEFAULT_SPACING_MM,
    landmark: Landmark | None = None,
    axis: str = AXES[0],
    interpolation: str = CLINICAL_INTERPOLATION,
) -> LimbMeasurement:
    """Measure a limb: circumferences every ``spacing_mm`` from the landmark, and volumes.

    Levels run from the landmark towards the limb's other (proximal) end and, for a
    landmark given as a height, also towards the distal end; only levels inside the
    closed sections' range are measured (never extrapolated). The distal end is the end
    with the smaller circumference (the bottom one when they differ by under 1 %).

    Args:
        sections: the limb's outlines (one per height; open ones are left out of volumes).
        spacing_mm: distance between levels along the axis.
        landmark: level 0 (default: the distal end).
        axis: one of ``AXES``.
        interpolation: how EFD coefficients are interpolated along z (``INTERPOLATIONS``;
            default :data:`CLINICAL_INTERPOLATION`).

    Raises:
        ClinicalError: no closed section, a bad spacing, or a landmark outside the range.
    """
    landmark = landmark or Landmark()
    if not (math.isfinite(spacing_mm) and spacing_mm > 0):
        raise ClinicalError(f"the level spacing {spacing_mm} must be a positive number of mm")
    closed = sorted((s for s in sections if s.closed), key=lambda s: s.z_mm)
    if not closed:
        raise ClinicalError("the scan has no closed section to measure; scan the limb again")
    opened = sorted((s for s in sections if not s.closed), key=lambda s: s.z_mm)
    limb_axis = fit_axis(closed, axis)
    efds = [s.efd for s in closed if s.efd is not None]  # every closed outline has one
    stack = EfdStack.from_sections([s.z_mm for s in closed], efds, interpolation)
    lo, hi = float(stack.z_mm[0]), float(stack.z_mm[-1])
    profile_c = np.array([_circumference(stack.section(z), z, limb_axis) for z in stack.z_mm])
    distal_top = len(profile_c) > 1 and profile_c[-1] < (1.0 - DISTAL_MARGIN) * profile_c[0]
    start = _landmark_position(landmark, limb_axis, lo, hi, distal_top)
    # Levels run away from a named end, else away from the distal end (proximally).
    upward = {"bottom": True, "top": False}.get(landmark.kind, not distal_top)
    sign = 1.0 if upward else -1.0
    s_lo, s_hi = float(limb_axis.position_mm(lo)), float(limb_axis.position_mm(hi))
    d_lo, d_hi = sorted((sign * (s_lo - start), sign * (s_hi - start)))
    tol = _LEVEL_TOLERANCE_MM / spacing_mm
    levels = []
    for k in range(math.ceil(d_lo / spacing_mm - tol), math.floor(d_hi / spacing_mm + tol) + 1):
        offset = k * spacing_mm
        z = min(max(limb_axis.height_mm(start + sign * offset), lo), hi)
        efd = stack.section(z)
        source, note = _level_source(z, closed, opened)
        circ = _circumference(efd, z, limb_axis)
        area = abs(efd_area(efd)) * limb_axis.direction[2]
        levels.append(Level(offset, z, circ, area, source, note))
    segments = tuple(
        SegmentVolume(
            a.offset_mm,
            b.offset_mm,
            stack_volume_mm3(stack, min(a.z_mm, b.z_mm), max(a.z_mm, b.z_mm)),
            frustum_volume_mm3(a.circumference_mm, b.circumference_mm, b.offset_mm - a.offset_mm),
        )
        for a, b in itertools.pairwise(levels)
    )
    notes = [f"{s.status} section at z={s.z_mm:.1f} mm left out of the volume" for s in opened]
    if limb_axis.choice:
        notes.append(f"axis {limb_axis.method} ({limb_axis.choice})")
    elif limb_axis.method == "centreline":
        notes.append(f"centre line tilted {limb_axis.tilt_deg:.1f} deg from the turntable axis")
    return LimbMeasurement(
        axis=limb_axis,
        landmark=landmark,
        landmark_z_mm=limb_axis.height_mm(start),
        spacing_mm=float(spacing_mm),
        coverage_mm=(lo, hi),
        levels=tuple(levels),
        segments=segments,
        volume_mm3=stack_volume_mm3(stack, lo, hi),
        stack=stack,
        profile_z_mm=stack.z_mm.copy(),
        profile_circumference_mm=profile_c,
        notes=tuple(notes),
    )


def sections_from_reconstruction(result: Any) -> list[LimbSection]:
    """Return the limb outlines of a :class:`~lamina_host.reconstruct.pipeline.Reconstruction`.

    A limb has one outline per section: where a section split into several, the main
    one (part 0) is the limb.
    """
    outlines = [
        LimbSection(s.z_mm, s.efd, getattr(s, "status", OutlineStatus.MEASURED))
        for s in result.sections
        if s.part == 0
    ]
    outlines += [
        LimbSection(f.z_mm, None, f.status) for f in getattr(result, "failed", []) if f.part == 0
    ]
    return sorted(outlines, key=lambda s: s.z_mm)


def sections_from_report(report: dict[str, Any], scan_id: int | None = None) -> list[LimbSection]:
    """Return the limb outlines stored in a scan's ``report.json`` (with EFD coefficients).

    Raises:
        ClinicalError: the report holds no EFD coefficients (processed by an older Lamina).
    """
    every = [r for r in report.get("sections", []) if r.get("part", 0) == 0]
    rows = [r for r in every if r.get("status") != OutlineStatus.FAILED]
    failed = [LimbSection(float(r["z_mm"]), None, OutlineStatus.FAILED) for r in every
              if r.get("status") == OutlineStatus.FAILED]  # fmt: skip
    if not rows or any("efd" not in r for r in rows):
        which = f"scan {scan_id}" if scan_id is not None else "the scan"
        raise ClinicalError(
            f"{which} was processed without EFD coefficients in its report; process it again "
            "with this version of Lamina"
        )
    outlines = [
        LimbSection(
            float(r["z_mm"]),
            EllipticFourier.from_dict(r["efd"]),
            OutlineStatus(r.get("status", OutlineStatus.MEASURED)),
        )
        for r in rows
    ]
    return sorted(outlines + failed, key=lambda s: s.z_mm)


@dataclass(frozen=True)
class LevelDifference:
    """One level of a comparison: this limb's circumference against the reference's."""

    offset_mm: float
    circumference_mm: float
    reference_mm: float
    flagged: bool

    @property
    def difference_mm(self) -> float:
        """Return this limb's circumference minus the reference's."""
        return self.circumference_mm - self.reference_mm


COMPARISONS = ("limbs", "visits")
"""``limbs``: affected against other limb (excess); ``visits``: visit against baseline."""


@dataclass(frozen=True)
class Comparison:
    """Two scans aligned by their landmarks, over the levels both measured."""

    kind: str
    levels: tuple[LevelDifference, ...]
    volume_mm3: float
    reference_volume_mm3: float
    flags: tuple[str, ...] = field(default=())

    @property
    def difference_ml(self) -> float:
        """Return the excess (limbs) or change (visits) in mL over the common levels."""
        return (self.volume_mm3 - self.reference_volume_mm3) / 1000.0

    @property
    def difference_percent(self) -> float:
        """Return the excess or change as a percentage of the reference volume."""
        return 100.0 * (self.volume_mm3 - self.reference_volume_mm3) / self.reference_volume_mm3

    @property
    def span_mm(self) -> tuple[float, float]:
        """Return the first and last common level's offsets from the landmark."""
        return self.levels[0].offset_mm, self.levels[-1].offset_mm

    def summary(self) -> dict[str, Any]:
        """Return the JSON form."""
        return {
            "kind": self.kind,
            "span_mm": list(self.span_mm),
            "volume_ml": self.volume_mm3 / 1000.0,
            "reference_volume_ml": self.reference_volume_mm3 / 1000.0,
            "difference_ml": self.difference_ml,
            "difference_percent": self.difference_percent,
            "levels": [
                {
                    "offset_mm": d.offset_mm,
                    "circumference_mm": d.circumference_mm,
                    "reference_mm": d.reference_mm,
                    "difference_mm": d.difference_mm,
                    "flagged": d.flagged,
                }
                for d in self.levels
            ],
            "flags": list(self.flags),
        }


def _common(a: Iterable[float], b: Iterable[float]) -> list[float]:
    keys_b = {round(x, 6) for x in b}
    return [x for x in a if round(x, 6) in keys_b]


def compare(
    scan: LimbMeasurement,
    reference: LimbMeasurement,
    kind: str = COMPARISONS[0],
    thresholds: Thresholds | None = None,
) -> Comparison:
    """Compare a limb with a reference (other limb or baseline visit) level by level.

    Both are aligned by their landmarks: level offsets are distances from each scan's own
    landmark. Volumes are the exact volumes between the first and last level both scans
    measured; flags follow ``thresholds``.

    Raises:
        ClinicalError: different spacings, or fewer than two common levels.
    """
    if kind not in COMPARISONS:
        raise ClinicalError(f"comparison {kind!r} must be one of {', '.join(COMPARISONS)}")
    limits = thresholds or Thresholds()
    if abs(scan.spacing_mm - reference.spacing_mm) > _LEVEL_TOLERANCE_MM:
        raise ClinicalError("compare scans measured at the same level spacing")
    offsets = _common(
        [lv.offset_mm for lv in scan.levels], [lv.offset_mm for lv in reference.levels]
    )
    if len(offsets) < 2:
        raise ClinicalError(
            "the two scans share fewer than two levels from their landmarks; use a smaller "
            "spacing or a landmark both scans cover"
        )
    by_a = {round(lv.offset_mm, 6): lv for lv in scan.levels}
    by_b = {round(lv.offset_mm, 6): lv for lv in reference.levels}
    diffs = []
    for off in offsets:
        ca, cb = by_a[round(off, 6)].circumference_mm, by_b[round(off, 6)].circumference_mm
        diffs.append(LevelDifference(off, ca, cb, abs(ca - cb) >= limits.circumference_mm))
    lo, hi = min(offsets), max(offsets)

    def span_volume(m: LimbMeasurement) -> float:
        inside = [s for s in m.segments if lo - 1e-6 <= min(s.offset_lo_mm, s.offset_hi_mm)]
        return float(
            sum(s.volume_mm3 for s in inside if max(s.offset_lo_mm, s.offset_hi_mm) <= hi + 1e-6)
        )

    comparison = Comparison(kind, tuple(diffs), span_volume(scan), span_volume(reference))
    return Comparison(
        kind, comparison.levels, comparison.volume_mm3, comparison.reference_volume_mm3,
        tuple(_flags(comparison, limits)),
    )  # fmt: skip


def _flags(c: Comparison, limits: Thresholds) -> list[str]:
    """Return one line per threshold the comparison crosses."""
    flags = []
    if c.kind == "limbs":
        if abs(c.difference_ml) > limits.limb_difference_ml:
            flags.append(
                f"volume difference {c.difference_ml:+.0f} mL exceeds "
                f"{limits.limb_difference_ml:.0f} mL"
            )
        if abs(c.difference_percent) > limits.limb_difference_percent:
            flags.append(
                f"volume difference {c.difference_percent:+.1f} % exceeds "
                f"{limits.limb_difference_percent:.1f} %"
            )
    elif abs(c.difference_percent) >= limits.change_percent:
        flags.append(
            f"volume change {c.difference_percent:+.1f} % reaches {limits.change_percent:.1f} %"
        )
    for d in c.levels:
        if d.flagged:
            flags.append(
                f"circumference at {d.offset_mm:.0f} mm differs by {d.difference_mm:+.1f} mm "
                f"(threshold {limits.circumference_mm:.0f} mm)"
            )
    return flags


SIDES = ("none", "left", "right")
"""The limb side a scan records (as :data:`lamina_host.store.library.SIDES`)."""

_OTHER_SIDE = {"left": "right", "right": "left"}


@dataclass(frozen=True)
class Visit:
    """One processed scan of a subject: its volume, change and excess over the other limb.

    ``change_*`` is against the first scan of the same side (the baseline); ``excess_*``
    is this limb over the other side's scan nearest in time (NaN when there is none, or
    for side ``none``), measured over the levels both share.
    """

    scan_id: int
    created: str
    volume_ml: float
    change_ml: float
    change_percent: float
    flags: tuple[str, ...] = ()
    side: str = SIDES[0]
    excess_ml: float = math.nan
    excess_percent: float = math.nan
    excess_over: int | None = None


def _days(created: str) -> float:
    """Return an ISO 8601 time as days since the epoch (NaN if it cannot be read)."""
    try:
        stamp = datetime.fromisoformat(created)
    except ValueError:
        return math.nan
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=UTC)
    return stamp.timestamp() / 86400.0


def _change(
    scan_id: int, created: str, m: LimbMeasurement, baseline: LimbMeasurement,
    thresholds: Thresholds | None, side: str,
) -> Visit:  # fmt: skip
    """Return a visit compared with its side's baseline (NaN and the reason if it cannot be)."""
    try:
        c = compare(m, baseline, "visits", thresholds)
    except ClinicalError as exc:
        return Visit(scan_id, created, m.volume_mm3 / 1000.0, math.nan, math.nan, (str(exc),),
                     side)  # fmt: skip
    return Visit(
        scan_id, created, m.volume_mm3 / 1000.0, c.difference_ml, c.difference_percent,
        c.flags, side,
    )  # fmt: skip


def history(
    scans: Sequence[tuple[int, str, LimbMeasurement]],
    thresholds: Thresholds | None = None,
    sides: Mapping[int, str] | None = None,
) -> list[Visit]:
    """Return the visits in time order, each compared with its side's first (the baseline).

    Args:
        scans: (scan id, creation time ISO 8601, measurement) of one subject's scans.
        thresholds: when a change or an excess is flagged.
        sides: each scan's limb side (:data:`SIDES`; a scan not named is ``none``).

    Left and right limbs are followed apart: a visit's change is measured against the
    first scan of the same side, between the first and last level it shares with it
    (scans of one limb may cover more or less of it). A left or right visit also gets
    its excess over the other side's scan nearest in time (the limbs comparison). A
    visit sharing fewer than two levels has no change (NaN) and says why.
    """
    side_of = {scan_id: (sides or {}).get(scan_id, SIDES[0]) for scan_id, _, _ in scans}
    ordered = sorted(scans, key=lambda item: (item[1], item[0]))
    baselines: dict[str, tuple[int, LimbMeasurement]] = {}
    visits = []
    for scan_id, created, m in ordered:
        side = side_of[scan_id]
        base_id, baseline = baselines.setdefault(side, (scan_id, m))
        if scan_id == base_id:
            visit = Visit(scan_id, created, m.volume_mm3 / 1000.0, 0.0, 0.0, (), side)
        else:
            visit = _change(scan_id, created, m, baseline, thresholds, side)
        visits.append(_with_excess(visit, m, ordered, side_of, thresholds))
    return visits


def _with_excess(
    visit: Visit,
    m: LimbMeasurement,
    scans: Sequence[tuple[int, str, LimbMeasurement]],
    side_of: Mapping[int, str],
    thresholds: Thresholds | None,
) -> Visit:
    """Return ``visit`` with its excess over the other side's scan nearest in time."""
    other = _OTHER_SIDE.get(visit.side)
    candidates = [item for item in scans if side_of[item[0]] == other]
    if not candidates:
        return visit
    when = _days(visit.created)
    other_id, _, other_m = min(
        candidates, key=lambda item: (abs(_days(item[1]) - when), item[1], item[0])
    )
    try:
        c = compare(m, other_m, "limbs", thresholds)
    except ClinicalError as exc:
        return replace(visit, flags=(*visit.flags, f"no excess over scan {other_id}: {exc}"))
    flags = tuple(f"{visit.side} over {other} scan {other_id}: {f}" for f in c.flags)
    return replace(
        visit,
        flags=visit.flags + flags,
        excess_ml=c.difference_ml,
        excess_percent=c.difference_percent,
        excess_over=other_id,
    )
