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

The same pairs tell whether the subject moved (:func:`views_disagreement_mm`): a move
shifts a whole view, so a pair's median stands off zero. So does an error of the
turntable's angle where the outline runs slantwise to its frame; each pair is therefore
compared again with its earlier view turned by :data:`TURN_TOLERANCE_DEG`, and only what
lies beyond that counts.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

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


@dataclass(frozen=True)
class ViewPair:
    """Two views of one outline compared where they overlap.

    ``differences_mm``: the earlier view's offsets minus the later view's outline there,
    one per point of the earlier view inside the later view's cover. ``earlier`` and
    ``later``: the two views' places among the views with two points or more.
    """

    differences_mm: np.ndarray
    earlier: int = 0
    later: int = 0


TURN_TOLERANCE_DEG = 0.2
"""The error of the turntable's angle between two views that a pair's offset may come
from: a cheap printed or cast gear's eccentricity errs by 0.1-0.2 degrees once per turn
(the harsh preset's 0.15 degree gear, plus its runout and jitter), and the cylinder's
per-view offsets, where they are measured well enough to be used, leave about 0.03."""


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
    return np.concatenate([p.differences_mm for p in pairs]) if pairs else np.zeros(0)


def pair_differences(
    views: list[np.ndarray],
    frame: OutlineFrame | None = None,
    turn_deg: float = 0.0,
    only: set[tuple[int, int]] | None = None,
) -> list[ViewPair]:
    """Return :func:`overlap_differences` pair by pair (pairs without overlap left out).

    Each later view is compared with all the earlier ones at once (their points laid one
    after the other, once for every later view), then the differences are parted by the
    earlier view: pairs come out grouped by their later view.

    Args:
        views: each view's (K, 2) object-frame points of one outline, in mm.
        frame: the outline's frame; None: polar about the views' centroid.
        turn_deg: the earlier view of every pair turned by this about the turntable
            axis (the object frame's origin) first: what an angle error makes of a pair.
        only: the ``(earlier, later)`` pairs to compare (places among the views with two
            points or more); None: every pair. A pair's differences do not depend on
            which others are compared.

    Returns:
        One :class:`ViewPair` per pair of views that overlap.
    """
    usable = [v for v in views if len(v) >= 2]
    if len(usable) < 2:
        return []
    frame = frame or OutlineFrame(np.concatenate(usable).mean(axis=0))
    wanted = only if only is not None else {(k, n) for n in range(len(usable)) for k in range(n)}
    later = sorted({n for _, n in wanted})
    earlier = sorted({k for k, _ in wanted})
    local = {n: _local_sorted(usable[n], frame) for n in {*later, *(() if turn_deg else earlier)}}
    turned = local
    if turn_deg:
        c, s = math.cos(math.radians(turn_deg)), math.sin(math.radians(turn_deg))
        rotation = np.array([[c, s], [-s, c]])  # rows times it: turned counter-clockwise
        turned = {k: _local_sorted(usable[k] @ rotation, frame) for k in earlier}
    # The earlier views laid out once, in order: view n's predecessors are a prefix.
    laid = _Laid.of([(k, turned[k]) for k in earlier])
    return [
        ViewPair(d, k, n)
        for n in later
        for k, d in _against_view(laid.before(n), local[n])
        if (k, n) in wanted
    ]


@dataclass(frozen=True)
class _Laid:
    """Views' positions and offsets along the outline laid one after the other."""

    angles: np.ndarray
    offsets: np.ndarray
    owner: np.ndarray

    @classmethod
    def of(cls, views: list[tuple[int, tuple[np.ndarray, np.ndarray]]]) -> _Laid:
        """Lay out ``(view, (positions, offsets))`` in ascending view order."""
        if not views:
            return cls(np.zeros(0), np.zeros(0), np.zeros(0, int))
        return cls(
            np.concatenate([a for _, (a, _) in views]),
            np.concatenate([r for _, (_, r) in views]),
            np.repeat([k for k, _ in views], [len(a) for _, (a, _) in views]),
        )

    def before(self, n: int) -> _Laid:
        """Return the points of the views before view ``n``."""
        end = int(np.searchsorted(self.owner, n))
        return _Laid(self.angles[:end], self.offsets[:end], self.owner[:end])


def _against_view(
    earlier: _Laid, later: tuple[np.ndarray, np.ndarray]
) -> list[tuple[int, np.ndarray]]:
    """Return the differences of the ``earlier`` views to the ``later`` one, by view.

    Args:
        earlier: the earlier views' positions and offsets along the outline
            (``_local_sorted``), laid out.
        later: the later view's.

    Returns:
        ``(earlier view, differences)`` for each earlier view with points inside the
        later view's cover, where the later view has no gap about them.
    """
    angle_n, radius_n = later
    if not earlier.angles.size:
        return []
    spacing = _median(angle_n[1:] - angle_n[:-1]) if len(angle_n) > 2 else math.inf
    # The earlier views' positions shifted into view n's turn, so the wrap hides no cover.
    shifted = angle_n[0] + np.mod(earlier.angles - angle_n[0], 2 * math.pi)
    inside = np.flatnonzero(shifted <= angle_n[-1])
    if not inside.size:
        return []
    x = shifted[inside]
    at = np.minimum(np.maximum(np.searchsorted(angle_n, x), 1), len(angle_n) - 1)
    whole = angle_n[at] - angle_n[at - 1] <= _MAX_GAP_SPACINGS * max(spacing, 1e-12)
    difference = (earlier.offsets[inside] - np.interp(x, angle_n, radius_n))[whole]
    if not difference.size:
        return []
    by = earlier.owner[inside][whole]
    cuts = np.flatnonzero(np.diff(by)) + 1
    first = by[np.concatenate(([0], cuts))].tolist()
    return list(zip(first, np.split(difference, cuts), strict=True))


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


def precision_of(pairs: list[ViewPair]) -> float | None:
    """Return :func:`section_precision_mm` from the pairs of :func:`pair_differences`."""
    d = np.concatenate([p.differences_mm for p in pairs]) if pairs else np.zeros(0)
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
it (0.19-2.95 mm): continuous sway's smeared views disagree little more than that. What
the turntable's own angle error can make of a pair (:data:`TURN_TOLERANCE_DEG`) is taken
off each offset first: of the campaign's 30 still limb shapes (2 sections, 6 views) it
left 2 warned of 7, with every swaying section still warned."""

_MOTION_SIGMAS = 4.0  # an offset counts only beyond this many standard errors
_COHERENT_SPREADS = 4.0
"""A pair of views scattering more than this many times the outline's median pair scatter
compared different stretches of surface: it shows no motion (``disagreement_of``)."""


def views_disagreement_mm(views: list[np.ndarray], frame: OutlineFrame | None = None) -> float:
    """Return how far apart a section's overlapping views stand, beyond their noise (mm).

    Noise scatters two views' differences about zero; a subject who moved between them
    shifts one view's whole stretch, so the median of a pair's differences moves off
    zero. Only offsets beyond :data:`_MOTION_SIGMAS` standard errors and beyond what a
    turntable angle error of :data:`TURN_TOLERANCE_DEG` makes of the pair count, and
    only where two pairs or more show one: the figure is the second largest offset.

    Args:
        views: each view's (K, 2) object-frame points of one outline, in mm.
        frame: the outline's frame; None: polar about the views' centroid.

    Returns:
        The second largest such offset (0.0 where fewer than two pairs stand out).
    """
    return disagreement_of(pair_differences(views, frame), views, frame)


def disagreement_of(
    pairs: list[ViewPair],
    views: list[np.ndarray] | None = None,
    frame: OutlineFrame | None = None,
) -> float:
    """Return :func:`views_disagreement_mm` from the pairs of :func:`pair_differences`.

    Args:
        pairs: the outline's view pairs.
        views: the views they came from, to allow for the turntable's angle error and
            to leave out pairs whose later view has fewer than :data:`MIN_OVERLAP_POINTS`
            points; None: neither.
        frame: the frame the pairs were taken in.

    Returns:
        The second largest offset beyond noise and the allowance (0.0: fewer than two);
        the allowance is taken only where the figure would otherwise pass
        :data:`MOTION_WARN_MM` (below it, it could only lower a figure that warns of
        nothing).
    """
    # A later view of a dozen points (a stretch the stripe grazed) is compared as a
    # curve through them, its grazing bias and all: no measure of a whole view's shift.
    # On the still arm, continuous, a 14-point piece stood 0.3-0.5 mm off three views.
    pieces = [len(v) for v in views if len(v) >= 2] if views is not None else None
    pairs = [
        p
        for p in pairs
        if p.differences_mm.size >= MIN_OVERLAP_POINTS
        and (pieces is None or pieces[p.later] >= MIN_OVERLAP_POINTS)
    ]
    if not pairs:
        return 0.0
    sizes = np.array([p.differences_mm.size for p in pairs])
    group = np.repeat(np.arange(len(pairs)), sizes)
    values = np.concatenate([p.differences_mm for p in pairs])
    centre = _group_medians(values, group, sizes)
    spread = _MAD_SIGMAS * _group_medians(np.abs(values - centre[group]), group, sizes)
    # A pair that laid one view's stripe against another stretch of surface (the far face
    # of a thin part, the other branch of a bent outline) scatters far beyond the noise
    # of the others: its median is no offset (a still bent limb gave 30 mm). A subject's
    # move shifts a view whole, its pairs' scatter staying at the noise.
    coherent = spread <= _COHERENT_SPREADS * float(np.median(spread))
    # The median's standard error is about 1.25 sigma / sqrt(n) for Gaussian noise.
    noise = _MOTION_SIGMAS * 1.25 * spread / np.sqrt(sizes)
    beyond = np.abs(centre)
    moved = coherent & (beyond > noise)
    # A subject who moves between two views stands apart in at least two pairs: round a
    # closed outline the views before and after the move meet at two places. A lone
    # offset pair is the shape's (a thin part's edge, a shell's far face): of the 48
    # outlines of 30 still limb shapes the largest offset warned of, 43 had one pair
    # alone beyond the warning's 0.15 mm.
    figure = _second_largest(beyond[moved])
    # The allowance only lowers the figure, so it is taken only where the figure would
    # warn: comparing the views again costs a sixth of a still section's processing.
    if views is not None and figure > MOTION_WARN_MM:
        beyond = beyond - _turn_allowances(pairs, centre, moved, views, frame)
        figure = _second_largest(beyond[coherent & (beyond > noise)])
    return figure


def _second_largest(values: np.ndarray) -> float:
    """Return the second largest of ``values``, 0.0 when there are fewer than two."""
    return float(np.partition(values, -2)[-2]) if values.size >= 2 else 0.0


def _turn_allowances(
    pairs: list[ViewPair],
    centre: np.ndarray,
    standing: np.ndarray,
    views: list[np.ndarray],
    frame: OutlineFrame | None,
) -> np.ndarray:
    """Return how far each standing pair's median moves with its earlier view turned (mm).

    A gear's angle error turns one view against another by a tenth of a degree or two;
    where an outline runs slantwise to its frame that shifts a pair as a move would
    (on the limb rig, 4 of 6 still random shapes warned of motion went with the gear
    error). Taken only where a warning is in question, and only for the pairs that
    stand out (``standing``; the others get 0, an allowance could not make them count):
    it compares those views again.
    """
    asked = {(p.earlier, p.later) for p, up in zip(pairs, standing, strict=True) if up}
    turned = {
        (p.earlier, p.later): _median(p.differences_mm)
        for p in pair_differences(views, frame, TURN_TOLERANCE_DEG, only=asked)
    }
    return np.array(
        [
            abs(turned[(p.earlier, p.later)] - c) if (p.earlier, p.later) in turned else 0.0
            for p, c in zip(pairs, centre, strict=True)
        ]
    )


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
