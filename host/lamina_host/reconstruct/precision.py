"""Each outline's per-point precision, measured where its views overlap (issue 21).

Two views that see the same stretch of outline measure it independently, so their
difference there holds the noise of both (speckle, the stripe centre, the calibration
seen from two angles) and nothing of the true shape. For every point of one view that
lies inside another view's cover along the outline (in the outline's frame, as the
overlap blending takes it: polar about its centre when star-shaped, along its reference
curve otherwise, :mod:`.outline_frame`), the difference in offset to the other view's
outline, interpolated between its two neighbouring points, is taken; the robust sigma
of all these differences, divided by the noise of one point plus the interpolated
neighbour, is the precision of one point in mm.
"""

from __future__ import annotations

import math

import numpy as np

from lamina_host.reconstruct.outline_frame import OutlineFrame, unwrap_angles

MIN_OVERLAP_POINTS = 20
"""Fewer overlapping points than this give no estimate."""

_MAD_SIGMAS = 1.4826  # a Gaussian's sigma over its median absolute deviation
# Linear interpolation between two neighbours of the other view carries on average 2/3
# of one point's noise variance (weights t and 1 - t, t uniform), so a difference holds
# 1 + 2/3 of it.
_DIFFERENCE_VARIANCE = 1.0 + 2.0 / 3.0
_MAX_GAP_SPACINGS = 4.0  # neighbours further apart than this many median spacings: a gap


def _local_sorted(points: np.ndarray, frame: OutlineFrame) -> tuple[np.ndarray, np.ndarray]:
    """Return one view's positions along the outline (unwrapped, ascending) and offsets."""
    t, offset = frame.to_local(points)
    t = unwrap_angles(t)
    order = np.argsort(t, kind="stable")
    return t[order], offset[order]


def overlap_differences(views: list[np.ndarray], frame: OutlineFrame | None = None) -> np.ndarray:
    """Return the differences (mm) between each pair of views where they overlap.

    Args:
        views: each view's (K, 2) object-frame points of one outline, in mm.
        frame: the outline's frame; None: polar about the views' centroid.

    Returns:
        One difference per point of a view lying inside a later view's cover (each pair
        of views counted once), where the later view has no gap about that position.
    """
    pairs = pair_differences(views, frame)
    return np.concatenate(pairs) if pairs else np.zeros(0)


def pair_differences(
    views: list[np.ndarray], frame: OutlineFrame | None = None
) -> list[np.ndarray]:
    """Return :func:`overlap_differences` pair by pair (pairs without overlap left out).

    Each later view is compared with all the earlier ones at once (their points laid one
    after the other), then the differences are parted by the earlier view: pairs come
    out grouped by their later view.
    """
    usable = [v for v in views if len(v) >= 2]
    if len(usable) < 2:
        return []
    frame = frame or OutlineFrame(np.concatenate(usable).mean(axis=0))
    local = [_local_sorted(v, frame) for v in usable]
    angles = np.concatenate([a for a, _ in local])
    radii = np.concatenate([r for _, r in local])
    owner = np.repeat(np.arange(len(local)), [len(a) for a, _ in local])
    ends = np.cumsum([len(a) for a, _ in local])
    differences: list[np.ndarray] = []
    for n in range(1, len(local)):
        angle_n, radius_n = local[n]
        spacing = _median(angle_n[1:] - angle_n[:-1]) if len(angle_n) > 2 else math.inf
        # The earlier views' positions shifted into view n's turn, so the wrap hides no cover.
        shifted = angle_n[0] + np.mod(angles[: ends[n - 1]] - angle_n[0], 2 * math.pi)
        inside = np.flatnonzero(shifted <= angle_n[-1])
        if not inside.size:
            continue
        x = shifted[inside]
        at = np.minimum(np.maximum(np.searchsorted(angle_n, x), 1), len(angle_n) - 1)
        whole = angle_n[at] - angle_n[at - 1] <= _MAX_GAP_SPACINGS * max(spacing, 1e-12)
        difference = (radii[inside] - np.interp(x, angle_n, radius_n))[whole]
        by = owner[inside][whole]
        cuts = np.flatnonzero(np.diff(by)) + 1
        differences += np.split(difference, cuts) if difference.size else []
    return differences


def _median(values: np.ndarray) -> float:
    """Return the median of a non-empty 1-D array (``np.median`` without its overhead:
    this runs once per view of every section)."""
    low, high = (len(values) - 1) // 2, len(values) // 2
    part = np.partition(values, (low, high))
    return 0.5 * float(part[low] + part[high])


def section_precision_mm(
    views: list[np.ndarray], frame: OutlineFrame | None = None
) -> float | None:
    """Return the per-point precision (mm) of one outline, or None without overlaps.

    Args:
        views: each view's (K, 2) object-frame points of the outline, in mm.
        frame: the outline's frame; None: polar about the views' centroid.

    Returns:
        The robust sigma of one point, from :func:`overlap_differences`; None when fewer
        than :data:`MIN_OVERLAP_POINTS` points overlap.
    """
    return precision_of(pair_differences(views, frame))


def precision_of(pairs: list[np.ndarray]) -> float | None:
    """Return :func:`section_precision_mm` from the pairs of :func:`pair_differences`."""
    d = np.concatenate(pairs) if pairs else np.zeros(0)
    if d.size < MIN_OVERLAP_POINTS:
        return None
    spread = _MAD_SIGMAS * float(np.median(np.abs(d - np.median(d))))
    return spread / math.sqrt(_DIFFERENCE_VARIANCE)


MOTION_WARN_MM = 0.15
"""Overlapping views whose outlines stand further apart than this, beyond their noise and
in two pairs of views or more (:func:`disagreement_of`), are taken to show the subject
moving between them: on the thesis rig a scan's own mechanics and calibration leave less
(the cylinder 0.04 mm; 30 still random shapes on the harsh preset under 0.12 mm, a shell
0.21), a breath or a shift of weight more. On the limb rig (harsh, 8 views, 10 mm pitch)
the second largest pair offset of 30 still random shapes passes it on 5 outlines of 5 shapes
(0.17-0.41 mm; the largest offset had warned 48 outlines of 20 shapes), while every
section of the arm under the patient sway and the strong sway, either mode, stays above
it (0.19-2.95 mm): continuous sway's smeared views disagree little more than that."""

_MOTION_SIGMAS = 4.0  # an offset counts only beyond this many standard errors
_COHERENT_SPREADS = 4.0
"""A pair of views scattering more than this many times the outline's median pair scatter
compared different stretches of surface: it shows no motion (``disagreement_of``)."""


def views_disagreement_mm(views: list[np.ndarray], frame: OutlineFrame | None = None) -> float:
    """Return how far apart a section's overlapping views stand, beyond their noise (mm).

    Noise scatters two views' differences about zero; a subject who moved between them
    shifts one view's whole stretch, so the median of a pair's differences moves off
    zero. Only offsets beyond :data:`_MOTION_SIGMAS` standard errors count, and only
    where two pairs or more show one: the figure is the second largest offset.

    Args:
        views: each view's (K, 2) object-frame points of one outline, in mm.
        frame: the outline's frame; None: polar about the views' centroid.

    Returns:
        The second largest such offset (0.0 where fewer than two pairs stand out).
    """
    return disagreement_of(pair_differences(views, frame))


def disagreement_of(pairs: list[np.ndarray]) -> float:
    """Return :func:`views_disagreement_mm` from the pairs of :func:`pair_differences`."""
    pairs = [d for d in pairs if d.size >= MIN_OVERLAP_POINTS]
    if not pairs:
        return 0.0
    sizes = np.array([d.size for d in pairs])
    group = np.repeat(np.arange(len(pairs)), sizes)
    values = np.concatenate(pairs)
    centre = _group_medians(values, group, sizes)
    spread = _MAD_SIGMAS * _group_medians(np.abs(values - centre[group]), group, sizes)
    # A pair that laid one view's stripe against another stretch of surface (the far face
    # of a thin part, the other branch of a bent outline) scatters far beyond the noise
    # of the others: its median is no offset (a still bent limb gave 30 mm). A subject's
    # move shifts a view whole, its pairs' scatter staying at the noise.
    coherent = spread <= _COHERENT_SPREADS * float(np.median(spread))
    # The median's standard error is about 1.25 sigma / sqrt(n) for Gaussian noise.
    moved = coherent & (np.abs(centre) > _MOTION_SIGMAS * 1.25 * spread / np.sqrt(sizes))
    # A subject who moves between two views stands apart in at least two pairs: round a
    # closed outline the views before and after the move meet at two places. A lone
    # offset pair is the shape's (a thin part's edge, a shell's far face): of the 48
    # outlines of 30 still limb shapes the largest offset warned of, 43 had one pair
    # alone beyond the warning's 0.15 mm.
    offsets = np.sort(np.abs(centre[moved]))
    return float(offsets[-2]) if offsets.size >= 2 else 0.0


def _group_medians(values: np.ndarray, group: np.ndarray, sizes: np.ndarray) -> np.ndarray:
    """Return the median of each group of ``values`` (``group`` ascending, ``sizes`` each)."""
    # One float sort of the values lifted by their group (each group's band above the one
    # below it) is several times faster than a lexsort; taking the lift off again leaves
    # a rounding error of about 1e-16 of the largest lifted value (1e-13 mm here).
    low_value = float(values.min()) if values.size else 0.0
    band = float(np.ptp(values)) + 1.0 if values.size else 1.0
    ordered = np.sort(group * band + (values - low_value)) - group * band + low_value
    start = np.concatenate(([0], np.cumsum(sizes)[:-1]))
    low = ordered[start + (sizes - 1) // 2]
    high = ordered[start + sizes // 2]
    return 0.5 * (low + high)
