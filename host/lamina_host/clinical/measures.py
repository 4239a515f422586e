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

Comparisons and the clinic's metrics (issue #23): two scans are compared over the whole
stretch of limb both measured from their landmarks (:func:`compare`: the excess over the
other limb or the change from another visit, per level and per segment too); the relative
volume change RVC = (A2 x U1) / (U2 x A1) - 1 of an affected limb A against the other U
between visits 1 and 2 (:func:`rvc_percent`, :func:`relative_volume_change`, whole and by
segment); and a subject's :func:`trend`, per side and in time order, over the stretch every
visit measured. Every value that reaches a threshold (:class:`Thresholds`, the clinics'
conventions by default) is a :class:`Flag` that says which threshold it reached.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Any

import numpy as np

from lamina_host.reconstruct.efd import CLINICAL_INTERPOLATION, EfdStack, EllipticFourier, efd_area
from lamina_host.reconstruct.measure import centroid_or_mean
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
    """When a value is flagged: the conventions lymphoedema clinics use (issues #13, #23).

    Attributes:
        limb_difference_ml: the excess of one limb over the other (200 mL).
        limb_difference_percent: the same as a share of the other limb (5 %).
        circumference_mm: a girth difference at one level (2 cm).
        change_percent: a limb's change from its own first visit, the baseline (3 %).
        rvc_percent: the relative volume change (RVC) that marks lymphoedema (5 %; some
            clinics use 10 %).
        subclinical_percent: the RVC that marks subclinical change (3 %).
    """

    limb_difference_ml: float = 200.0
    limb_difference_percent: float = 5.0
    circumference_mm: float = 20.0
    change_percent: float = 3.0
    rvc_percent: float = 5.0
    subclinical_percent: float = 3.0


WHOLE_LIMB = "whole limb"
"""Where a flag lies when it is about the whole compared range."""

_FLAG_WORDS = {
    "excess_ml": ("excess", "mL"),
    "excess_percent": ("excess", "%"),
    "change_percent": ("change", "%"),
    "rvc_percent": ("RVC", "%"),
    "girth_mm": ("girth difference", "mm"),
}
"""What each flagged quantity is called, and its unit."""


@dataclass(frozen=True)
class Flag:
    """One value that reached a threshold, and which threshold it reached.

    Attributes:
        quantity: ``excess_ml``, ``excess_percent``, ``change_percent``, ``rvc_percent``
            or ``girth_mm``.
        value: the value (signed: an excess or change below zero is a loss).
        threshold: the threshold it reached (:class:`Thresholds`).
        where: :data:`WHOLE_LIMB`, ``segment A-B mm`` or ``level A mm`` (from the landmark).
        label: what the threshold marks, if it has a name (``lymphoedema``, ``subclinical``).
        context: which limbs or visits the value compares (e.g. ``left over right, scan 4``).
    """

    quantity: str
    value: float
    threshold: float
    where: str = WHOLE_LIMB
    label: str = ""
    context: str = ""

    @property
    def unit(self) -> str:
        """Return the unit of the value and the threshold."""
        return _FLAG_WORDS[self.quantity][1]

    @property
    def text(self) -> str:
        """Return the flag in one line: where, what, the value and the threshold it reached."""
        name, unit = _FLAG_WORDS[self.quantity]
        digits = 0 if unit == "mL" else 1
        place = ", ".join(part for part in (self.where, self.context) if part)
        label = f" ({self.label})" if self.label else ""
        return (
            f"{place}: {name} {self.value:+.{digits}f} {unit} reaches the "
            f"{self.threshold:g} {unit} threshold{label}"
        )

    def __str__(self) -> str:
        return self.text

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form (with the line of text)."""
        return {
            "quantity": self.quantity,
            "value": self.value,
            "threshold": self.threshold,
            "where": self.where,
            "label": self.label,
            "context": self.context,
            "text": self.text,
        }


def reached(
    quantity: str, value: float, threshold: float, where: str = WHOLE_LIMB, context: str = "",
    signed: bool = False,
) -> list[Flag]:  # fmt: skip
    """Return the flag of ``value`` if its size (its value, if ``signed``) reaches ``threshold``.

    A value that is not a number (not measured) is never flagged.
    """
    size = value if signed else abs(value)
    if not math.isfinite(value) or size < threshold:
        return []
    return [Flag(quantity, value, threshold, where, "", context)]


def segment_place(offset_lo_mm: float, offset_hi_mm: float) -> str:
    """Return where a segment lies, in the words of a flag (``segment 40-80 mm``)."""
    return f"segment {offset_lo_mm:g}-{offset_hi_mm:g} mm"


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
    c = np.array(
        [centroid_or_mean(s.efd.evaluate(OUTLINE_SAMPLES)) for s in closed if s.efd is not None]
    )
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
    direction: float = 1.0
    """+1 when the distance from the landmark grows along the axis, -1 when against it."""

    @property
    def offset_range_mm(self) -> tuple[float, float]:
        """Return the distances from the landmark the measured range spans (lowest, highest)."""
        start = float(self.axis.position_mm(self.landmark_z_mm))
        ends = [
            self.direction * (float(self.axis.position_mm(z)) - start) for z in self.coverage_mm
        ]
        return min(ends), max(ends)

    def z_at_offset(self, offset_mm: float) -> float:
        """Return the height of the level ``offset_mm`` from the landmark (inside the range)."""
        start = float(self.axis.position_mm(self.landmark_z_mm))
        z = self.axis.height_mm(start + self.direction * offset_mm)
        return min(max(z, self.coverage_mm[0]), self.coverage_mm[1])

    def volume_between_mm3(self, offset_a_mm: float, offset_b_mm: float) -> float:
        """Return the exact volume between two distances from the landmark (in the range)."""
        za, zb = sorted((self.z_at_offset(offset_a_mm), self.z_at_offset(offset_b_mm)))
        if abs(za - self.coverage_mm[0]) + abs(zb - self.coverage_mm[1]) < _LEVEL_TOLERANCE_MM:
            return self.volume_mm3  # the whole range, integrated once already
        return stack_volume_mm3(self.stack, za, zb)

    def circumference_at(self, offset_mm: float) -> float:
        """Return the circumference (girth) ``offset_mm`` from the landmark."""
        z = self.z_at_offset(offset_mm)
        return _circumference(self.stack.section(z), z, self.axis)

    def segment_volume_mm3(self, offset_lo_mm: float, offset_hi_mm: float) -> float:
        """Return the exact volume of the segment between two levels (NaN if not measured)."""
        key = (round(offset_lo_mm, 6), round(offset_hi_mm, 6))
        for s in self.segments:
            if (round(s.offset_lo_mm, 6), round(s.offset_hi_mm, 6)) == key:
                return s.volume_mm3
        return math.nan

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
    a, b = edges[:-1, None], edges[1:, None]
    z = 0.5 * (a + b) + 0.5 * (b - a) * nodes  # (slabs, nodes)
    area = np.array([abs(efd_area(e)) for e in stack.sections(z.ravel())]).reshape(z.shape)
    return float(np.sum(0.5 * (b[:, 0] - a[:, 0]) * (area @ weights)))


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
        direction=sign,
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

    @property
    def difference_percent(self) -> float:
        """Return the difference as a percentage of the reference's circumference."""
        return 100.0 * self.difference_mm / self.reference_mm if self.reference_mm else math.nan


@dataclass(frozen=True)
class SegmentDifference:
    """One segment (between two levels) of a comparison: its volume against the reference's."""

    offset_lo_mm: float
    offset_hi_mm: float
    volume_mm3: float
    reference_mm3: float

    @property
    def difference_ml(self) -> float:
        """Return this limb's segment volume minus the reference's, in mL."""
        return (self.volume_mm3 - self.reference_mm3) / 1000.0

    @property
    def difference_percent(self) -> float:
        """Return the difference as a percentage of the reference's segment volume."""
        return percent_over(self.volume_mm3, self.reference_mm3)


def percent_over(value: float, reference: float) -> float:
    """Return how much ``value`` is above ``reference``, in % of it (NaN without a reference)."""
    if not (math.isfinite(value) and math.isfinite(reference)) or reference <= 0:
        return math.nan
    return 100.0 * (value - reference) / reference


COMPARISONS = ("limbs", "visits")
"""``limbs``: affected against other limb (excess); ``visits``: visit against baseline."""

MIN_COMMON_MM = 10.0
"""Two scans are compared over the stretch of limb both measured; less than a centimetre
says nothing about a limb's volume, so it is refused."""


@dataclass(frozen=True)
class Comparison:
    """Two scans aligned by their landmarks: over the range both measured, and level by level.

    The volumes are those of the whole common range (``span_mm``, distances from each
    scan's landmark), so the excess or change does not depend on the level spacing; the
    levels and segments are those both scans have.
    """

    kind: str
    levels: tuple[LevelDifference, ...]
    volume_mm3: float
    reference_volume_mm3: float
    span_mm: tuple[float, float]
    segments: tuple[SegmentDifference, ...] = ()
    alerts: tuple[Flag, ...] = field(default=())

    @property
    def difference_ml(self) -> float:
        """Return the excess (limbs) or change (visits) in mL over the common range."""
        return (self.volume_mm3 - self.reference_volume_mm3) / 1000.0

    @property
    def difference_percent(self) -> float:
        """Return the excess or change as a percentage of the reference volume."""
        return percent_over(self.volume_mm3, self.reference_volume_mm3)

    @property
    def flags(self) -> tuple[str, ...]:
        """Return each flag as one line of text."""
        return tuple(f.text for f in self.alerts)

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
                    "difference_percent": d.difference_percent,
                    "flagged": d.flagged,
                }
                for d in self.levels
            ],
            "segments": [
                {
                    "offset_lo_mm": s.offset_lo_mm,
                    "offset_hi_mm": s.offset_hi_mm,
                    "volume_ml": s.volume_mm3 / 1000.0,
                    "reference_volume_ml": s.reference_mm3 / 1000.0,
                    "difference_ml": s.difference_ml,
                    "difference_percent": s.difference_percent,
                }
                for s in self.segments
            ],
            "flags": [f.to_dict() for f in self.alerts],
        }


def common_span_mm(measurements: Sequence[LimbMeasurement]) -> tuple[float, float]:
    """Return the distances from the landmark that every measurement covers (low, high).

    Raises:
        ClinicalError: they share less than :data:`MIN_COMMON_MM` of limb.
    """
    ranges = [m.offset_range_mm for m in measurements]
    lo, hi = max(r[0] for r in ranges), min(r[1] for r in ranges)
    if hi - lo < MIN_COMMON_MM:
        raise ClinicalError(
            f"the scans share {max(hi - lo, 0.0):.0f} mm of limb from their landmarks (at least "
            f"{MIN_COMMON_MM:g} mm needed): scan the same stretch of the limb, or choose a "
            "landmark both scans reach"
        )
    return lo, hi


def _common_levels(measurements: Sequence[LimbMeasurement]) -> list[float]:
    """Return the level offsets every measurement has, in order."""
    keys = [{round(lv.offset_mm, 6) for lv in m.levels} for m in measurements]
    return [lv.offset_mm for lv in measurements[0].levels if all(round(lv.offset_mm, 6) in k
                                                                 for k in keys)]  # fmt: skip


def _common_segments(measurements: Sequence[LimbMeasurement]) -> list[tuple[float, float]]:
    """Return the (low, high) offsets of the segments every measurement has, in order."""
    return [
        (s.offset_lo_mm, s.offset_hi_mm)
        for s in measurements[0].segments
        if all(math.isfinite(m.segment_volume_mm3(s.offset_lo_mm, s.offset_hi_mm))
               for m in measurements)
    ]  # fmt: skip


def _check_spacing(measurements: Sequence[LimbMeasurement]) -> None:
    spacings = {round(m.spacing_mm, 6) for m in measurements}
    if len(spacings) > 1:
        raise ClinicalError("compare scans measured at the same level spacing")


def compare(
    scan: LimbMeasurement,
    reference: LimbMeasurement,
    kind: str = COMPARISONS[0],
    thresholds: Thresholds | None = None,
) -> Comparison:
    """Compare a limb with a reference (other limb or baseline visit).

    Both are aligned by their landmarks: distances are from each scan's own landmark. The
    volumes are those of the whole range both measured (independent of the level
    spacing); levels and segments are those both have. Flags follow ``thresholds``.

    Raises:
        ClinicalError: an unknown kind, different spacings, or too little common range.
    """
    if kind not in COMPARISONS:
        raise ClinicalError(f"comparison {kind!r} must be one of {', '.join(COMPARISONS)}")
    limits = thresholds or Thresholds()
    _check_spacing([scan, reference])
    lo, hi = common_span_mm([scan, reference])
    girth_a = {round(lv.offset_mm, 6): lv.circumference_mm for lv in scan.levels}
    girth_b = {round(lv.offset_mm, 6): lv.circumference_mm for lv in reference.levels}
    levels = []
    for off in _common_levels([scan, reference]):
        ca, cb = girth_a[round(off, 6)], girth_b[round(off, 6)]
        levels.append(LevelDifference(off, ca, cb, abs(ca - cb) >= limits.circumference_mm))
    segments = tuple(
        SegmentDifference(a, b, scan.segment_volume_mm3(a, b), reference.segment_volume_mm3(a, b))
        for a, b in _common_segments([scan, reference])
    )
    c = Comparison(
        kind, tuple(levels), scan.volume_between_mm3(lo, hi), reference.volume_between_mm3(lo, hi),
        (lo, hi), segments,
    )  # fmt: skip
    return replace(c, alerts=tuple(_comparison_flags(c, limits)))


def _comparison_flags(c: Comparison, limits: Thresholds) -> list[Flag]:
    """Return one flag per value of the comparison that reaches its threshold."""
    flags = []
    if c.kind == "limbs":
        flags += reached("excess_ml", c.difference_ml, limits.limb_difference_ml)
        flags += reached("excess_percent", c.difference_percent, limits.limb_difference_percent)
        quantity, limit = "excess_percent", limits.limb_difference_percent
    else:
        flags += reached("change_percent", c.difference_percent, limits.change_percent)
        quantity, limit = "change_percent", limits.change_percent
    for s in c.segments:
        flags += reached(
            quantity, s.difference_percent, limit, segment_place(s.offset_lo_mm, s.offset_hi_mm)
        )
    for d in c.levels:
        if d.flagged:
            flags += [Flag("girth_mm", d.difference_mm, limits.circumference_mm,
                           f"level {d.offset_mm:g} mm")]  # fmt: skip
    return flags


def rvc_percent(
    affected_before: float, other_before: float, affected: float, other: float
) -> float:
    """Return the relative volume change in %: 100 ((A2 x U1) / (U2 x A1) - 1).

    A is the affected limb, U the other, 1 the earlier visit and 2 the later (any one
    volume unit). The other limb's change (growth, weight) is divided out, so only the
    affected limb's change relative to it remains. NaN when a volume is not positive.
    """
    volumes = (affected_before, other_before, affected, other)
    if not all(math.isfinite(v) and v > 0 for v in volumes):
        return math.nan
    return 100.0 * ((affected * other_before) / (other * affected_before) - 1.0)


@dataclass(frozen=True)
class VolumeChange:
    """One stretch of both limbs at two visits: the clinic's figures for it (mm^3 inside).

    ``offset_*_mm`` are distances from the landmarks; A is the affected limb, U the other,
    ``before`` the earlier (baseline) visit.
    """

    offset_lo_mm: float
    offset_hi_mm: float
    affected_before_mm3: float
    other_before_mm3: float
    affected_mm3: float
    other_mm3: float

    @property
    def rvc_percent(self) -> float:
        """Return the relative volume change, (A2 x U1) / (U2 x A1) - 1, in %."""
        return rvc_percent(
            self.affected_before_mm3, self.other_before_mm3, self.affected_mm3, self.other_mm3
        )

    @property
    def excess_ml(self) -> float:
        """Return the affected limb's excess over the other at the later visit, in mL."""
        return (self.affected_mm3 - self.other_mm3) / 1000.0

    @property
    def excess_percent(self) -> float:
        """Return that excess in % of the other limb."""
        return percent_over(self.affected_mm3, self.other_mm3)

    @property
    def baseline_excess_percent(self) -> float:
        """Return the excess at the earlier visit, in % of the other limb."""
        return percent_over(self.affected_before_mm3, self.other_before_mm3)

    @property
    def change_ml(self) -> float:
        """Return the affected limb's change from the earlier visit, in mL."""
        return (self.affected_mm3 - self.affected_before_mm3) / 1000.0

    @property
    def change_percent(self) -> float:
        """Return that change in % of the earlier volume."""
        return percent_over(self.affected_mm3, self.affected_before_mm3)

    @property
    def other_change_percent(self) -> float:
        """Return the other limb's change from the earlier visit, in %."""
        return percent_over(self.other_mm3, self.other_before_mm3)


@dataclass(frozen=True)
class LimbChange:
    """The relative volume change of an affected limb between two visits, whole and by segment."""

    whole: VolumeChange
    segments: tuple[VolumeChange, ...]
    alerts: tuple[Flag, ...] = ()

    @property
    def flags(self) -> tuple[str, ...]:
        """Return each flag as one line of text."""
        return tuple(f.text for f in self.alerts)


def rvc_flags(
    value: float, limits: Thresholds, where: str = WHOLE_LIMB, context: str = ""
) -> list[Flag]:
    """Return the flag of an RVC: the lymphoedema threshold, else the subclinical one.

    Only an increase is flagged (a limb that shrank relative to the other is the other
    limb's increase).
    """
    for threshold, label in (
        (limits.rvc_percent, "lymphoedema"),
        (limits.subclinical_percent, "subclinical"),
    ):
        if math.isfinite(value) and value >= threshold:
            return [Flag("rvc_percent", value, threshold, where, label, context)]
    return []


def relative_volume_change(
    affected_before: LimbMeasurement,
    other_before: LimbMeasurement,
    affected: LimbMeasurement,
    other: LimbMeasurement,
    thresholds: Thresholds | None = None,
    span_mm: tuple[float, float] | None = None,
) -> LimbChange:
    """Return the RVC, excess and change of an affected limb between two visits.

    RVC = (A2 x U1) / (U2 x A1) - 1 over the range all four scans measured (or ``span_mm``,
    distances from the landmarks, which all four must cover), and for each segment all
    four have. Flags: the RVC (lymphoedema, else subclinical threshold), the excess at the
    later visit (mL and %) and the affected limb's change from the earlier one.

    Raises:
        ClinicalError: different spacings, too little common range, or a ``span_mm`` one of
            the scans does not cover.
    """
    limits = thresholds or Thresholds()
    scans = (affected_before, other_before, affected, other)
    _check_spacing(scans)
    common = common_span_mm(scans)
    lo, hi = span_mm or common
    if lo < common[0] - 1e-6 or hi > common[1] + 1e-6:
        raise ClinicalError(
            f"the range {lo:g}..{hi:g} mm from the landmark is not measured in all four scans "
            f"(they share {common[0]:g}..{common[1]:g} mm)"
        )
    whole = VolumeChange(lo, hi, *(m.volume_between_mm3(lo, hi) for m in scans))
    segments = tuple(
        VolumeChange(a, b, *(m.segment_volume_mm3(a, b) for m in scans))
        for a, b in _common_segments(scans)
    )
    flags = rvc_flags(whole.rvc_percent, limits)
    flags += reached("excess_ml", whole.excess_ml, limits.limb_difference_ml, signed=True)
    flags += reached(
        "excess_percent", whole.excess_percent, limits.limb_difference_percent, signed=True
    )
    flags += reached("change_percent", whole.change_percent, limits.change_percent)
    for s in segments:
        flags += rvc_flags(s.rvc_percent, limits, segment_place(s.offset_lo_mm, s.offset_hi_mm))
    return LimbChange(whole, segments, tuple(flags))


SIDES = ("none", "left", "right")
"""The limb side a scan records (as :data:`lamina_host.store.library.SIDES`)."""

_OTHER_SIDE = {"left": "right", "right": "left"}

PAIR_WINDOW_H = 24.0
"""Scans of the two sides this close in time are one visit (both limbs measured together):
their excess and RVC compare them; scans further apart are not paired."""


@dataclass(frozen=True)
class Visit:
    """One scan in a subject's trend: its volume, change, excess over the other limb and RVC.

    All figures but ``whole_volume_ml`` are over the trend's range (:attr:`Trend.span_mm`,
    the stretch every visit measured), so they can be compared and recomputed from each
    other. ``change_*`` is against the first scan of the same side (``baseline_id``);
    ``excess_*`` is this limb over the other side's scan of the same visit
    (``excess_over``, within :data:`PAIR_WINDOW_H`); ``rvc_percent`` is this side's RVC
    since the first visit with both limbs (``rvc_scans``: that visit's scans of this side
    and of the other), as if this side were the affected one. NaN where a figure cannot be
    had (and ``flags`` says why).
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
    rvc_percent: float = math.nan
    baseline_id: int | None = None
    rvc_scans: tuple[int, int] | None = None
    whole_volume_ml: float = math.nan
    alerts: tuple[Flag, ...] = ()


@dataclass(frozen=True)
class Trend:
    """A subject's visits in time order, per side, with the thresholds they are judged by.

    ``span_mm`` is the stretch of limb (distances from the landmark) every visit measured,
    over which every figure is taken; None when the visits share too little of it (then
    only each scan's own volume is given, and ``notes`` says which scan is short).
    """

    visits: tuple[Visit, ...]
    span_mm: tuple[float, float] | None
    thresholds: Thresholds = field(default_factory=Thresholds)
    notes: tuple[str, ...] = ()

    def side(self, side: str) -> list[Visit]:
        """Return the visits of one side, in time order."""
        return [v for v in self.visits if v.side == side]

    def visit(self, scan_id: int) -> Visit | None:
        """Return the visit of scan ``scan_id`` (None if it is not in the trend)."""
        return next((v for v in self.visits if v.scan_id == scan_id), None)

    @property
    def flags(self) -> tuple[Flag, ...]:
        """Return every visit's flags."""
        return tuple(f for v in self.visits for f in v.alerts)


def _days(created: str) -> float:
    """Return an ISO 8601 time as days since the epoch (NaN if it cannot be read)."""
    try:
        stamp = datetime.fromisoformat(created)
    except ValueError:
        return math.nan
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=UTC)
    return stamp.timestamp() / 86400.0


def _trend_span(
    scans: Sequence[tuple[int, str, LimbMeasurement]],
) -> tuple[tuple[float, float] | None, list[str]]:
    """Return the range every scan covers (None if too short) and a note naming the shortest."""
    if not scans:
        return None, []
    try:
        span = common_span_mm([m for _, _, m in scans])
    except ClinicalError:
        span = None
    shortest_id, _, shortest = min(
        scans, key=lambda s: s[2].offset_range_mm[1] - s[2].offset_range_mm[0]
    )
    lo, hi = shortest.offset_range_mm
    widest = max(m.offset_range_mm[1] - m.offset_range_mm[0] for _, _, m in scans)
    if span is None or span[1] - span[0] < 0.8 * widest:
        reach = f"scan {shortest_id} covers only {lo:.0f}..{hi:.0f} mm from the landmark"
        what = "the visits share too little of the limb for a trend" if span is None else (
            f"the trend is taken over {span[0]:.0f}..{span[1]:.0f} mm, the range every visit "
            "measured")  # fmt: skip
        return span, [f"{what}; {reach}: if it is not a visit, mark it as a test scan"]
    return span, []


def _pairs(
    ordered: Sequence[tuple[int, str, LimbMeasurement]], side_of: Mapping[int, str],
    window_h: float,
) -> dict[int, int]:  # fmt: skip
    """Return each left or right scan's partner: the other side's scan nearest in time within
    ``window_h`` hours (one visit), if there is one."""
    pairs = {}
    for scan_id, created, _ in ordered:
        other = _OTHER_SIDE.get(side_of[scan_id])
        when = _days(created)
        near = [
            (abs(_days(c) - when) * 24.0, c, i) for i, c, _ in ordered
            if side_of[i] == other and abs(_days(c) - when) * 24.0 <= window_h
        ]  # fmt: skip
        if near:
            pairs[scan_id] = min(near)[2]
    return pairs


def trend(
    scans: Sequence[tuple[int, str, LimbMeasurement]],
    thresholds: Thresholds | None = None,
    sides: Mapping[int, str] | None = None,
    pair_window_h: float = PAIR_WINDOW_H,
) -> Trend:
    """Return a subject's trend: every scan's volume, change, excess and RVC, in time order.

    Args:
        scans: (scan id, creation time ISO 8601, measurement) of one subject's scans.
        thresholds: when a change, an excess or an RVC is flagged.
        sides: each scan's limb side (:data:`SIDES`; a scan not named is ``none``).
        pair_window_h: scans of the two sides this close in time are one visit.

    Every figure is taken over the stretch of limb every scan measured (the trend's span).
    Left and right are followed apart, each from its own first scan (its baseline). A left
    or right scan paired with the other side's scan of the same visit gets its excess over
    it; and, once a visit with both limbs exists, its RVC since the first such visit.
    Flags: the change from baseline (either way), an excess (on the larger limb), and an
    RVC increase (the lymphoedema threshold, else the subclinical one).
    """
    limits = thresholds or Thresholds()
    side_of = {scan_id: (sides or {}).get(scan_id, SIDES[0]) for scan_id, _, _ in scans}
    ordered = sorted(scans, key=lambda item: (item[1], item[0]))
    span, notes = _trend_span(ordered)
    volume = {
        i: (m.volume_between_mm3(*span) if span else m.volume_mm3) / 1000.0 for i, _, m in ordered
    }
    baseline: dict[str, int] = {}
    for scan_id, _, _ in ordered:
        baseline.setdefault(side_of[scan_id], scan_id)
    pairs = _pairs(ordered, side_of, pair_window_h)
    first_pair = next(((i, pairs[i]) for i, _, _ in ordered if i in pairs), None)
    by_side = {side_of[i]: i for i in first_pair} if first_pair else {}
    visits = []
    for scan_id, created, m in ordered:
        side = side_of[scan_id]
        base = baseline[side]
        known = span is not None or scan_id == base
        change_ml = volume[scan_id] - volume[base] if known else math.nan
        visit = Visit(
            scan_id, created, volume[scan_id], change_ml,
            percent_over(volume[scan_id], volume[base]) if known else math.nan,
            side=side, baseline_id=base, whole_volume_ml=m.volume_mm3 / 1000.0,
        )  # fmt: skip
        partner = pairs.get(scan_id)
        if partner is not None and span is not None:
            a1, u1 = by_side.get(side), by_side.get(_OTHER_SIDE[side])
            visit = replace(
                visit,
                excess_ml=volume[scan_id] - volume[partner],
                excess_percent=percent_over(volume[scan_id], volume[partner]),
                excess_over=partner,
            )
            if a1 is not None and u1 is not None:
                rvc = rvc_percent(volume[a1], volume[u1], volume[scan_id], volume[partner])
                visit = replace(visit, rvc_percent=rvc, rvc_scans=(a1, u1))
        visits.append(_with_flags(visit, limits, span is not None))
    return Trend(tuple(visits), span, limits, tuple(notes))


def _with_flags(visit: Visit, limits: Thresholds, measured: bool) -> Visit:
    """Return the visit with its flags (and a line saying why a figure is missing)."""
    side = f"{visit.side} " if visit.side != SIDES[0] else ""
    alerts = reached(
        "change_percent", visit.change_percent, limits.change_percent,
        context=f"{side}since scan {visit.baseline_id}",
    )  # fmt: skip
    if visit.excess_over is not None:
        over = f"{visit.side} over {_OTHER_SIDE[visit.side]} (scan {visit.excess_over})"
        alerts += reached("excess_ml", visit.excess_ml, limits.limb_difference_ml,
                          context=over, signed=True)  # fmt: skip
        alerts += reached("excess_percent", visit.excess_percent, limits.limb_difference_percent,
                          context=over, signed=True)  # fmt: skip
    if visit.rvc_scans is not None:
        alerts += rvc_flags(
            visit.rvc_percent, limits, context=f"{visit.side} since scan {visit.rvc_scans[0]}"
        )
    notes = []
    if not measured:
        notes.append("no trend figures: the visits share too little of the limb")
    elif visit.side in _OTHER_SIDE and visit.excess_over is None:
        notes.append(
            f"no {_OTHER_SIDE[visit.side]} scan within {PAIR_WINDOW_H:g} h: no excess or RVC"
        )
    return replace(visit, alerts=tuple(alerts), flags=tuple(f.text for f in alerts) + tuple(notes))


def history(
    scans: Sequence[tuple[int, str, LimbMeasurement]],
    thresholds: Thresholds | None = None,
    sides: Mapping[int, str] | None = None,
) -> list[Visit]:
    """Return the visits of :func:`trend` alone, in time order."""
    return list(trend(scans, thresholds, sides).visits)
