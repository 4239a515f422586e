"""Each section against its neighbours: where the stack jumps, the subject moved (issue 22).

A limb's outline changes slowly along its length: its centre follows a straight or gently
curved line (leant by a few degrees at most) and its size tapers and swells over
centimetres. A patient's sway moves the limb between sections, and within a continuous
turn (one section a second) it moves it the same way under every view, so the views of
a section agree while the whole section stands off: shifted, or grown or shrunk by the
part of the motion along the camera's line of sight (each view sees the side facing the
camera). The overlapping views cannot show that (:mod:`.precision`); its neighbours can.

For every outline with a measured outline below and above it (one vertical chain of
outlines, :func:`~lamina_host.reconstruct.pipeline.chain_outlines`), its area centroid and
its equivalent radius (that of the circle of its area) are compared with the values
interpolated linearly in z from the two neighbours (a second difference). The limit a
jump must pass is :data:`JUMP_WARN_MM` plus an allowance for the shape's own curvature,
which grows with the square of the section spacing and shrinks with the outline's size
(:data:`CURVATURE_ALLOWANCE`), plus :data:`NOISE_SIGMAS` standard errors of the figures
from each outline's measured precision.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from lamina_host.reconstruct.calibration import CalibrationError
from lamina_host.reconstruct.measure import centroid, polygon_area
from lamina_host.reconstruct.pipeline import Section, chain_outlines
from lamina_host.reconstruct.status import OutlineStatus

JUMP_WARN_MM = 0.5
"""A section whose centre or equivalent radius stands further than this (beyond the
allowances) off the line of its neighbours is taken to show the subject moving. The
simulator's limb phantoms (arm, stump, leg; upright and leant 3 degrees) stand within
0.05 mm of it at 2 mm spacing, true shape and still scans alike; its random limb-scale
shapes leant 3 degrees or less within it everywhere at 2 mm (713 sections of 22 shapes).
Half a millimetre of radius is 3 mm of circumference, what a clinic begins to read."""
CURVATURE_ALLOWANCE = 0.4
"""The shape's own curvature allowed for, as this times ``dz_below * dz_above / radius``
(mm): a shape that changes over lengths in proportion to its size bends its centre and
radius in proportion to the spacing squared over its size. 0.4 leaves 1.0 mm at 10 mm
spacing on a 40 mm radius and 0.04 mm at the default 2 mm spacing. At 10 mm spacing the
phantoms' own curvature reaches 0.53 mm (arm) and 1.17 mm (the stump near its rounded
end: 0.84 of its limit); of the random limb-scale shapes leant 3 degrees or less, 8 of
363 sections (6 of 65 shapes) pass the limit, as 18 of 547 of all of them (tilts to 20
degrees, shells, thin parts): at that spacing a jump must be large to be told from
shape."""
MAX_SLOPE = 0.5
"""Outlines where the radius or the centre changes faster than this per mm of height
(the surface leaning more than about 27 degrees from upright on some side: a dome, a
tip, a rounded end, upright or leant; a limb leant 3 degrees moves its centre 0.05 mm
per mm) are not
judged: a section's size there follows its height (a lift error) more than its outline,
and the surface is seen at a grazing angle."""
NOISE_SIGMAS = 4.0
"""A jump counts only beyond this many standard errors of its figures."""


@dataclass(frozen=True)
class OutlineShape:
    """What the check needs of one outline: where it is, its centre, size and noise."""

    index: int
    part: int
    z_mm: float
    centre_mm: tuple[float, float]
    radius_mm: float
    """The equivalent radius: that of the circle of the outline's area."""
    error_mm: float
    """The standard error of the centre and radius (0: unknown)."""


@dataclass(frozen=True)
class SectionJump:
    """How far one outline stands off the line of its neighbours, and the limit.

    ``centre_mm``: the distance of its centre from the neighbours' interpolated centre;
    ``size_mm``: its equivalent radius over the interpolated one (signed: + larger).
    """

    index: int
    part: int
    z_mm: float
    centre_mm: float
    size_mm: float
    limit_mm: float

    @property
    def jump_mm(self) -> float:
        """Return the larger of the centre's and the size's offsets."""
        return max(self.centre_mm, abs(self.size_mm))

    @property
    def flagged(self) -> bool:
        """Return whether the jump passes its limit (the subject probably moved)."""
        return self.jump_mm > self.limit_mm


def outline_shape(
    index: int,
    part: int,
    z_mm: float,
    contour: np.ndarray,
    precision_mm: float | None = None,
    points: int = 0,
) -> OutlineShape | None:
    """Return the centre and equivalent radius of a closed contour (None: no area).

    Args:
        index: the section's index.
        part: the outline's place among its section's outlines.
        z_mm: the section's height.
        contour: (N, 2) samples of the closed outline, mm.
        precision_mm: the precision of one measured point (None: unknown).
        points: the measured points behind the outline (their noise averages down).

    Returns:
        The outline's shape; None when the contour encloses no area.
    """
    try:
        centre = centroid(contour)
    except CalibrationError:
        return None
    radius = math.sqrt(polygon_area(contour) / math.pi)
    # A centre or mean radius from n independent points errs by about sigma / sqrt(n / 2).
    error = precision_mm * math.sqrt(2.0 / points) if precision_mm and points > 0 else 0.0
    return OutlineShape(index, part, z_mm, (float(centre[0]), float(centre[1])), radius, error)


def section_jumps(chain: Sequence[OutlineShape]) -> list[SectionJump]:
    """Return each inner outline's offset from the line of its neighbours in ``chain``.

    Args:
        chain: one vertical chain of measured outlines (one per section), any order;
            outlines estimated from their neighbours or not closed must be left out.

    Returns:
        One jump per outline with a neighbour below and above, bottom to top, save where
        the surface leans more than :data:`MAX_SLOPE` (a rounded end); empty for fewer
        than three outlines.
    """
    ordered = sorted(chain, key=lambda s: s.z_mm)
    jumps = []
    for below, here, above in zip(ordered, ordered[1:], ordered[2:], strict=False):
        dz_below, dz_above = here.z_mm - below.z_mm, above.z_mm - here.z_mm
        if dz_below <= 0.0 or dz_above <= 0.0 or here.radius_mm <= 0.0:
            continue
        if _leaning(below, above, MAX_SLOPE * (dz_below + dz_above)):
            continue
        jumps.append(_jump(below, here, above, dz_below, dz_above))
    return jumps


def _leaning(below: OutlineShape, above: OutlineShape, limit_mm: float) -> bool:
    """Return whether the radius or the centre changes by more than ``limit_mm`` from
    ``below`` to ``above`` (a rounded end, upright or leant: one side flattens)."""
    shift = math.dist(below.centre_mm, above.centre_mm)
    return abs(above.radius_mm - below.radius_mm) > limit_mm or shift > limit_mm


def _jump(
    below: OutlineShape, here: OutlineShape, above: OutlineShape, dz_below: float, dz_above: float
) -> SectionJump:
    """Return ``here``'s offset from the line through ``below`` and ``above``, and its limit."""
    w = dz_below / (dz_below + dz_above)  # the weight of the outline above
    centre = (1.0 - w) * np.asarray(below.centre_mm) + w * np.asarray(above.centre_mm)
    radius = (1.0 - w) * below.radius_mm + w * above.radius_mm
    error = math.sqrt(
        here.error_mm**2 + ((1.0 - w) * below.error_mm) ** 2 + (w * above.error_mm) ** 2
    )
    curvature = CURVATURE_ALLOWANCE * dz_below * dz_above / here.radius_mm
    return SectionJump(
        index=here.index,
        part=here.part,
        z_mm=here.z_mm,
        centre_mm=float(np.linalg.norm(np.asarray(here.centre_mm) - centre)),
        size_mm=here.radius_mm - radius,
        limit_mm=JUMP_WARN_MM + curvature + NOISE_SIGMAS * error,
    )


def outline_jumps(sections: list[Section]) -> list[SectionJump]:
    """Return how far each measured outline stands off the line of its neighbours.

    Outlines are followed up the scan (``chain_outlines``); only those closed from their
    own data (measured, or bridged across small gaps) are judged or judge: one filled
    from its neighbours would agree with them by construction.
    """
    jumps = []
    for chain in chain_outlines(sections):
        shapes = [
            outline_shape(s.index, s.part, s.z_mm, s.contour, s.precision_mm, len(s.raw))
            for s in chain
            if s.status in (OutlineStatus.MEASURED, OutlineStatus.BRIDGED)
        ]
        jumps += section_jumps([shape for shape in shapes if shape is not None])
    return sorted(jumps, key=lambda j: (j.index, j.part))
