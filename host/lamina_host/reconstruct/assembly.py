"""Reassemble stripe segments into one contour per section (thesis 6.1-6.3)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lamina_host.reconstruct.axis import taubin_circle
from lamina_host.reconstruct.calibration import CalibrationError
from lamina_host.reconstruct.outliers import (
    EXTENT_BIN_DEG,
    MAX_EXTENT_POINTS,
    angular_extent_deg,
    label_clusters,
)
from lamina_host.reconstruct.outline_frame import OutlineFrame, outline_frame, unwrap_angles

TWO_PI = 2.0 * np.pi


TRIM_RANGE = (0.0, 0.5)
"""The share of each segment's points :func:`trim` may drop at each end: from the first
(included) to below the second (half of each end would leave nothing)."""

THESIS_TRIM_FRACTION = 0.10
"""The thesis' share dropped at each end (6.1)."""

DEFAULT_TRIM_FRACTION = 0.0
"""Lamina's share dropped at each end: none. The thesis drops a tenth (6.1) because the
stripe is weakest where it grazes the surface; here the device's noise gate already
refuses what the noise hides, and the overlap blending weighs a segment's points less
towards its ends (:func:`blend_weight`), so a view's grazing end counts where nothing
better saw that stretch and little where another view did. Dropping the ends cost the
random-shape campaign 9 % of the surface it could have measured (median coverage 0.89
against 0.98, harsh preset, thesis scale) and a thin part's short stripes most of it."""


def trim_problem(fraction: object, name: str = "trim fraction") -> str | None:
    """Return why ``fraction`` is no share :func:`trim` can drop, or None if it is one.

    Args:
        fraction: the share asked for (anything a user or a stored record may hold).
        name: how the asking front end names the option (``--trim``).
    """
    low, high = TRIM_RANGE
    if (
        isinstance(fraction, int | float)
        and not isinstance(fraction, bool)
        and low <= fraction < high  # NaN fails this
    ):
        return None
    return f"{name} {fraction} must be at least {low:g} and below {high:g}"


def trim(points: np.ndarray, fraction: float = THESIS_TRIM_FRACTION) -> np.ndarray:
    """Drop the first and last ``fraction`` of a segment's points (thesis 6.1).

    The stripe is weakest and noisiest where it grazes the object's edges, so the thesis
    discards 10 % at each end (Lamina's default drops none: ``DEFAULT_TRIM_FRACTION``).

    Args:
        points: (K, ...) points ordered along the segment (by image column).
        fraction: share of the points dropped at each end, within :data:`TRIM_RANGE`.

    Returns:
        The middle points; ``floor(K * fraction)`` are removed from each end.
    """
    if problem := trim_problem(fraction):
        raise ValueError(problem)
    pts = np.asarray(points)
    k = int(np.floor(len(pts) * fraction + 1e-9))
    return pts[k : len(pts) - k]


def to_object_frame(
    points_world: np.ndarray,
    angle_deg: float | np.ndarray,
    axis_xy_mm: tuple[float, float],
    correction_factor: float,
) -> np.ndarray:
    """Move laser-plane points into the object's frame: ``q = C_f Rz(-angle)(p - a)``.

    Capture-spec convention; thesis 6.2.3 (translate to the axis, rotate, eq. 6.2) and
    6.2.4 (scale by the correction factor about the axis).

    Args:
        points_world: (N, 2) world points in mm.
        angle_deg: turntable angle of the view, counter-clockwise seen from above; or
            (N,) angles, one per point (a continuous view's rows, each exposed at its own).
        axis_xy_mm: turntable axis ``a`` in world mm.
        correction_factor: ``C_f`` from the calibration cylinder.

    Returns:
        (N, 2) object-frame points in mm.
    """
    p = np.asarray(points_world, dtype=float).reshape(-1, 2) - np.asarray(axis_xy_mm, float)
    th = np.deg2rad(angle_deg)
    c, s = np.cos(th), np.sin(th)
    if np.ndim(th):
        x, y = p[:, 0], p[:, 1]
        return correction_factor * np.stack([x * c + y * s, y * c - x * s], axis=1)
    # Rz(-theta) = [[c, s], [-s, c]]; applied to row vectors as p @ Rz(-theta).T.
    rot_t = np.array([[c, -s], [s, c]])
    return correction_factor * (p @ rot_t)


def _polar(points: np.ndarray, centre: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (angle in (-pi, pi], radius) of points about centre."""
    d = points - centre
    return np.arctan2(d[:, 1], d[:, 0]), np.hypot(d[:, 0], d[:, 1])


@dataclass(frozen=True, eq=False)
class Blend:
    """One outline's overlap-blended contour and what its measured points say of their noise.

    ``points`` is the blended contour (one point per measured point, in order along the
    outline: by position ``t`` in ``frame``); ``angle_rad`` and ``radius_mm`` are the
    measured points' own frame coordinates (position, outward offset) before blending,
    each view's averaged over runs ``RESOLUTION_RAD`` long (:func:`run_means`).
    ``noise_mm`` is the RMS distance of those from the surface, estimated where two views
    saw the same surface (:func:`overlap_noise`); None when no two views overlap.
    """

    points: np.ndarray
    frame: OutlineFrame
    angle_rad: np.ndarray
    radius_mm: np.ndarray
    noise_mm: float | None
    overlap_pairs: int

    @property
    def centre_mm(self) -> np.ndarray:
        """Return the centre of the outline's frame (the mean of its points)."""
        return self.frame.centre_mm


MIN_NOISE_PAIRS = 20
"""Fewest overlap pairs from which an outline's noise is estimated."""

FOLD_MM = 1.0
"""Two views' radii at one polar angle further apart than this are two surfaces, not one
seen twice: the outline is not star-shaped about its centre."""

FOLD_SHARE = 0.02
"""Share of the overlap pairs that must stand ``FOLD_MM`` apart (a stray pair is noise)."""

FOLD_DRAWDOWN_RAD = np.deg2rad(2.0)
"""A view's stripe (averaged in runs) whose polar angle runs back by more than this
folds: the outline is not star-shaped about its centre."""

STEEP_RATIO = 3.0
"""A stretch of stripe whose radius changes this many times faster than its arc about
the centre runs within 18 degrees of a ray from the centre: one radius per angle is
ill-conditioned there (a deep dent, the inner side of a bend)."""

STEEP_MM = 0.5
"""Radial travel over such steep stretches that makes polar coordinates unfit."""


def blend_overlaps(segments: list[np.ndarray], link_mm: float = 3.0) -> Blend:
    """Blend overlapping segments into one closed contour and estimate their noise.

    Thesis 6.3, generalised from pairs to any number of overlapping segments: polar
    coordinates are taken about the mean of all the section's points; every point's radius
    is replaced by the weighted mean of its own radius and the radius of each *other*
    segment whose angular range covers the point's angle, linearly interpolated there
    (6.3 steps 3-4). The thesis takes the plain mean, which jumps where a segment ends
    and leaves a seam the EFD would have to follow; here each segment's weight falls to
    zero at its ends (:func:`blend_weight`), so overlapping views blend without a step.
    Angles are unwrapped along each segment, so segments crossing +-pi and segments running
    clockwise are handled. Polar coordinates need one radius per angle (a star-shaped
    outline); where a view's stripe folds back in angle or two views stand at far
    different radii at one angle, the outline is blended along a reference curve through
    its points instead (:mod:`.outline_frame`), its position along the curve and its
    offset from it taking the place of angle and radius.

    Args:
        segments: object-frame (K, 2) arrays in mm, each ordered along its stripe.
        link_mm: the widest step between points of one outline (for the reference curve).

    Returns:
        The blended contour, the measured points' frame coordinates and their noise.

    Raises:
        CalibrationError: no points at all.
    """
    segs = [np.asarray(s, dtype=float).reshape(-1, 2) for s in segments]
    segs = [s for s in segs if len(s) > 0]
    if not segs:
        raise CalibrationError("the section has no stripe points; check the scan views")
    coords = _frame_coordinates(segs, link_mm)
    polar, local = coords.polar, coords.local
    ang, rad = _overlap_means(polar, [r[:, None] for _, r in polar])
    noise, pairs = overlap_noise(*coords.overlaps)
    return Blend(
        coords.frame.to_xy(ang, rad[:, 0]),
        coords.frame,
        np.concatenate([a for a, _ in local]),
        np.concatenate([r for _, r in local]),
        noise,
        pairs,
    )


@dataclass(frozen=True, eq=False)
class _FrameCoordinates:
    """An outline's frame and its views' coordinates in it (:func:`_frame_coordinates`).

    ``fits`` is False when polar coordinates fold and no reference curve could be drawn
    either: the polar frame is kept, but no one frame orders the points.
    """

    frame: OutlineFrame
    polar: list[tuple[np.ndarray, np.ndarray]]
    local: list[tuple[np.ndarray, np.ndarray]]
    overlaps: tuple[np.ndarray, np.ndarray]
    fits: bool


def _frame_coordinates(segs: list[np.ndarray], link_mm: float) -> _FrameCoordinates:
    """Choose an outline's frame (polar, else a reference curve) and place its views in it.

    Args:
        segs: the outline's non-empty (K, 2) pieces in mm, each ordered along its stripe.
        link_mm: the widest step between points of one outline (for the reference curve).
    """
    frame = OutlineFrame(np.concatenate(segs).mean(axis=0))
    polar = [frame.to_local(s) for s in segs]
    local = [run_means(a, r, RESOLUTION_RAD) for a, r in polar]
    overlaps = _overlap_differences(local)
    if not _folds(local, overlaps[0]):
        return _FrameCoordinates(frame, polar, local, overlaps, True)
    curve = outline_frame(np.concatenate(segs), link_mm)
    if curve.polar:
        return _FrameCoordinates(frame, polar, local, overlaps, False)
    polar = [curve.to_local(s) for s in segs]
    local = [run_means(a, r, RESOLUTION_RAD) for a, r in polar]
    return _FrameCoordinates(curve, polar, local, _overlap_differences(local), True)


def _folds(local: list[tuple[np.ndarray, np.ndarray]], d: np.ndarray) -> bool:
    """Return whether polar coordinates fail an outline (:func:`blend_overlaps`).

    Args:
        local: each view's run means (unwrapped angles along its stripe, radii).
        d: their radius differences where they overlap (:func:`_overlap_differences`).
    """
    for ang, rad in local:
        if len(ang) > 2:
            a = ang if ang[-1] >= ang[0] else -ang
            if float(np.max(np.maximum.accumulate(a) - a)) > FOLD_DRAWDOWN_RAD:
                return True
            d_rad = np.abs(np.diff(rad))
            steep = d_rad > STEEP_RATIO * rad[1:] * np.abs(np.diff(ang))
            if float(d_rad[steep].sum()) > STEEP_MM:
                return True
    return len(d) >= MIN_NOISE_PAIRS and float(np.mean(np.abs(d) > FOLD_MM)) > FOLD_SHARE


RESOLUTION_RAD = 2.0 * np.pi / 256.0
"""The finest detail the outline's order is judged at: half a wavelength of harmonic 128
(``efd.MAX_TESTED_HARMONICS``), which averaging over it attenuates by a third."""


def run_means(
    angle_rad: np.ndarray, radius_mm: np.ndarray, resolution_rad: float
) -> tuple[np.ndarray, np.ndarray]:
    """Return a stripe's points averaged in runs of consecutive points ``resolution_rad`` long.

    Stripe noise at a pixel's scale is far finer than any harmonic the EFD keeps; a mean
    over a few neighbours along the stripe keeps what an outline's order can show (its
    shape, the views' disagreement) and lowers the rest, in the residual and in the noise
    alike. Runs hold ``floor(points * resolution / angular span)`` points (at least one).

    Args:
        angle_rad: the stripe's points' polar angles, in stripe order.
        radius_mm: their radii.
        resolution_rad: the angular length of a run.

    Returns:
        The runs' mean angles (unwrapped along the stripe) and mean radii.
    """
    unwrapped = unwrap_angles(angle_rad)
    radius = np.asarray(radius_mm, dtype=float)
    span = float(np.ptp(unwrapped)) if len(unwrapped) else 0.0
    k = max(1, int(len(unwrapped) * resolution_rad / span)) if span > 0 else 1
    if k == 1:
        return unwrapped, radius
    # A run does not reach across a hole in the stripe (a shadow, a rejected stretch).
    step = np.abs(np.diff(unwrapped))
    hole = np.concatenate([[True], step > RUN_HOLE_STEPS * span / (len(unwrapped) - 1)])
    piece = np.cumsum(hole) - 1
    first = np.flatnonzero(hole)[piece]
    run = piece * len(unwrapped) + (np.arange(len(unwrapped)) - first) // k
    starts = np.flatnonzero(np.concatenate([[True], np.diff(run) != 0]))
    counts = np.diff(np.append(starts, len(unwrapped)))
    return (
        np.add.reduceat(unwrapped, starts) / counts,
        np.add.reduceat(radius, starts) / counts,
    )


RUN_HOLE_STEPS = 4.0
"""A step along a stripe this many times its mean step is a hole runs do not cross."""


def average_overlaps(segments: list[np.ndarray]) -> np.ndarray:
    """Return the blended contour of :func:`blend_overlaps` alone.

    Args:
        segments: object-frame (K, 2) arrays in mm, each ordered along its stripe.

    Returns:
        (N, 2) closed contour of all points, sorted by polar angle in (-pi, pi].
    """
    return blend_overlaps(segments).points


def overlap_noise(d: np.ndarray, f: np.ndarray) -> tuple[float | None, int]:
    """Return the measured points' RMS noise in mm from where views overlap, and the pairs.

    Where segment m covers a point of another segment, both saw the same surface: the
    point's radius less m's radius there (linearly interpolated between m's neighbouring
    points at fractions t, 1 - t) is the difference of two measurements' errors, of
    variance sigma^2 (1 + t^2 + (1 - t)^2) when the noise is independent. So
    sigma^2 = sum(d^2) / sum(1 + t^2 + (1 - t)^2). What views disagree on (a residual of
    calibration or turntable angle, a seam) counts as noise: the EFD must not follow it.
    The largest 1 % of differences are left out (a stray point the rejection let by).

    Args:
        d: the radius differences where segments overlap (:func:`_overlap_differences`).
        f: the variance factor ``1 + t^2 + (1 - t)^2`` of each.

    Returns:
        (noise in mm, number of pairs); noise None with fewer than ``MIN_NOISE_PAIRS``.
    """
    if len(d) < MIN_NOISE_PAIRS:
        return None, len(d)
    keep = np.abs(d) <= np.quantile(np.abs(d), 0.99)
    return float(np.sqrt(np.sum(d[keep] ** 2) / np.sum(f[keep]))), len(d)


def _overlap_differences(
    polar: list[tuple[np.ndarray, np.ndarray]],
) -> tuple[np.ndarray, np.ndarray]:
    """Return :func:`overlap_noise`'s radius differences where segments overlap and the
    variance factor ``1 + t^2 + (1 - t)^2`` of each.

    Args:
        polar: each segment's angles, unwrapped along it (:func:`run_means`), and radii.
    """
    diffs, factors = [], []
    ang_all = np.concatenate([a for a, _ in polar])
    rad_all = np.concatenate([r for _, r in polar])
    owner = np.repeat(np.arange(len(polar)), [len(a) for a, _ in polar])
    for m, (xp, rad_m) in enumerate(polar):
        order = np.argsort(xp, kind="stable")
        xp, fp = xp[order], rad_m[order]
        inside, x = _covered(xp, ang_all, owner, m)
        if not inside.size:
            continue
        j = np.clip(np.searchsorted(xp, x) - 1, 0, len(xp) - 2)
        t = (x - xp[j]) / np.maximum(xp[j + 1] - xp[j], 1e-300)
        diffs.append(rad_all[inside] - np.interp(x, xp, fp))
        factors.append(1.0 + t**2 + (1.0 - t) ** 2)
    if not diffs:
        return np.zeros(0), np.zeros(0)
    return np.concatenate(diffs), np.concatenate(factors)


def _covered(
    xp: np.ndarray, ang: np.ndarray, owner: np.ndarray, m: int
) -> tuple[np.ndarray, np.ndarray]:
    """Return the points of other segments that segment ``m``'s angular span covers.

    One rule for the blend and the noise estimate: a segment spans its sorted angles
    ``xp`` from first to last; one of fewer than two points, or all at one angle, spans
    nothing (it would weigh a point at its angle by 0 / 0).

    Args:
        xp: segment ``m``'s angles, sorted ascending.
        ang: every segment's points' angles, one after another.
        owner: the segment each of those points belongs to.
        m: the covering segment.

    Returns:
        The covered points' indices into ``ang`` and their angles shifted into
        ``[xp[0], xp[0] + 2 pi)``, so the wrap at +-pi hides no cover.
    """
    if len(xp) < 2 or xp[-1] <= xp[0]:
        return np.zeros(0, np.intp), np.zeros(0)
    shifted = xp[0] + np.mod(ang - xp[0], TWO_PI)
    covered = np.flatnonzero((shifted <= xp[-1]) & (owner != m))
    return covered, shifted[covered]


def average_overlap_colours(
    segments: list[np.ndarray], colours: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Give every point the mean colour of all the segments that cover its angle.

    The colour counterpart of :func:`average_overlaps` (same polar centre, same cover
    test, same interpolation and blending weights): a point seen in two views gets the
    blend of its own colour and the other view's there, so colour has no seam either.

    Args:
        segments: object-frame (K, 2) arrays in mm, each ordered along its stripe.
        colours: (K, 3) colours of those points (any numeric scale).

    Returns:
        The (N, 2) points, sorted by polar angle in (-pi, pi], and their (N, 3) float colours.
    """
    pairs = [
        (np.asarray(s, float).reshape(-1, 2), np.asarray(c, float).reshape(-1, 3))
        for s, c in zip(segments, colours, strict=True)
    ]
    pairs = [(s, c) for s, c in pairs if len(s)]
    if not pairs:
        return np.empty((0, 2)), np.empty((0, 3))
    pts = np.concatenate([s for s, _ in pairs])
    centre = pts.mean(axis=0)
    polar = [_polar(s, centre) for s, _ in pairs]
    _, mean = _overlap_means(polar, [c for _, c in pairs])
    order = np.argsort(np.concatenate([a for a, _ in polar]), kind="stable")
    return pts[order], mean


def blend_weight(position: np.ndarray) -> np.ndarray:
    """Return a segment's blending weight at ``position`` along it (0 and 1 are its ends).

    A Hann window, sin^2(pi s): one at the segment's middle, falling smoothly to zero at
    both ends, where its stripe grazes the surface. Overlapping segments blended with it
    hand over gradually, so a small disagreement between two views (a residual of the
    calibration, the turntable or the stripe) becomes a smooth ramp across their overlap
    instead of a step where one segment ends. A floor keeps a point that no other segment
    covers at its own value.
    """
    s = np.clip(np.asarray(position, dtype=float), 0.0, 1.0)
    return np.maximum(np.sin(np.pi * s) ** 2, BLEND_FLOOR)


BLEND_FLOOR = 1e-6
"""Smallest blending weight, so a point at its segment's very end still has one."""


def _overlap_means(
    polar: list[tuple[np.ndarray, np.ndarray]], values: list[np.ndarray]
) -> tuple[np.ndarray, np.ndarray]:
    """Return every point's angle and the blend of its values with the covering segments'.

    ``polar`` holds each segment's (angles, radii); ``values`` its (K, D) per-point values.
    Each segment covering a point's angle contributes its value there (linearly
    interpolated, thesis 6.3 steps 3-4) weighted by :func:`blend_weight` of where that
    angle lies along the segment; the point's own value is weighted the same way. Angles
    are unwrapped along each segment so segments crossing +-pi and segments running
    clockwise are handled; the result is sorted by angle.

    A segment whose radius at the point's angle stands more than ``FOLD_MM`` from the
    point's own saw another surface there (the far side of a bend, a second outline the
    rejection joined to this one) and contributes nothing: the mean of two surfaces lies
    on neither, and would be kept as a measured point (a random two-part section was
    blended into a chord 1.5 mm inside its outline so).
    """
    tables, own_weight = [], []
    for (ang_m, rad_m), val in zip(polar, values, strict=True):
        unwrapped = unwrap_angles(ang_m)
        order = np.argsort(unwrapped, kind="stable")
        tables.append((unwrapped[order], rad_m[order], val[order]))
        lo, hi = unwrapped[order[0]], unwrapped[order[-1]]
        span = hi - lo if hi > lo else 1.0
        own_weight.append(blend_weight((unwrapped - lo) / span))
    ang = np.concatenate([a for a, _ in polar])
    rad = np.concatenate([r for _, r in polar])
    weight = np.concatenate(own_weight)
    total = np.concatenate(values).astype(float) * weight[:, None]
    owner = np.repeat(np.arange(len(polar)), [len(a) for a, _ in polar])
    for m, (xp, rp, fp) in enumerate(tables):
        covered, x = _covered(xp, ang, owner, m)
        if not covered.size:
            continue
        same = np.abs(np.interp(x, xp, rp) - rad[covered]) <= FOLD_MM
        covered, x = covered[same], x[same]
        w = blend_weight((x - xp[0]) / (xp[-1] - xp[0]))
        for d in range(total.shape[1]):
            total[covered, d] += w * np.interp(x, xp, fp[:, d])
        weight[covered] += w
    mean = total / weight[:, None]
    order = np.argsort(ang, kind="stable")
    return ang[order], mean[order]


MIN_OUTLINE_POINTS = 30
"""The fewest points an outline holds: a smaller cluster is stray (:func:`split_outlines`),
and a part of it no body of its own (:func:`separate_bodies`)."""


def split_outlines(
    segments: list[np.ndarray], gap_mm: float, min_points: int = MIN_OUTLINE_POINTS
) -> list[list[np.ndarray]]:
    """Split a section's segments into separate outlines (fingers, two legs; thesis 9.2).

    Points are binned on a grid of ``gap_mm / 2`` cells and 8-connected occupied cells
    are joined, so outlines more than ``sqrt(2) gap_mm`` apart are always separate and
    points closer than ``gap_mm / 2`` (a stripe's neighbouring points) always join. Each
    segment is cut into its pieces per outline, so each outline can be overlap-averaged
    and fitted on its own.

    Args:
        segments: object-frame (K, 2) arrays in mm.
        gap_mm: the smallest gap that separates two outlines.
        min_points: outlines with fewer points are stray and dropped.

    Returns:
        One list of segment pieces per outline, the outline with most points first.
    """
    if not gap_mm > 0:
        raise ValueError(f"the outline gap must be a positive number of mm, not {gap_mm}")
    segs = [np.asarray(s, dtype=float).reshape(-1, 2) for s in segments]
    segs = [s for s in segs if len(s)]
    if not segs:
        return []
    pts = np.concatenate(segs)
    point_label, count = label_clusters(pts, gap_mm)
    sizes = np.bincount(point_label, minlength=count)
    owner = np.repeat(np.arange(len(segs)), [len(s) for s in segs])
    outlines = []
    for label in np.argsort(-sizes, kind="stable"):
        if sizes[label] < min_points:
            break
        mine = point_label == label
        pieces = [pts[mine & (owner == k)] for k in range(len(segs))]
        outlines.append([p for p in pieces if len(p)])
    return outlines


ARC_COVERAGE = 0.75
"""A cluster covering less of its own outline than this (about its fitted circle's
centre) is an arc, which :func:`join_arcs` may join to another."""

ARC_RADIUS_RATIO = 2.0
"""Two arcs are one outline only if each arc's own circle is within this factor of the
radius of the circle fitted to both: arcs of one body bend as the body does, while two
fingers' arcs bend much tighter than a circle round both."""

ARC_OVERLAP_BINS = 1
"""Two arcs of one outline lie in different directions from their joint centre: they may
share at most this many ``EXTENT_BIN_DEG`` bins (concentric arcs, a ring's inner and
outer side, share many)."""


def join_arcs(outlines: list[list[np.ndarray]]) -> list[list[np.ndarray]]:
    """Join the clusters that are arcs of one outline, split apart by unseen stretches.

    A body no view saw all round (a limb's side in shadow, a stretch the stripe grazed)
    falls apart into arcs further apart than the outline gap, and each would be fitted
    as an outline of its own, open, where one outline was seen in pieces. Two arcs
    (:data:`ARC_COVERAGE`) join when they bend like one circle (:data:`ARC_RADIUS_RATIO`)
    and lie on different sides of it (:data:`ARC_OVERLAP_BINS`); pairs join closest ends
    first, until no pair qualifies.

    Args:
        outlines: each outline's pieces (per-view runs, in stripe order).

    Returns:
        The outlines, joined ones as one, most points first.
    """
    groups = [list(o) for o in outlines]
    while len(groups) > 1:
        arcs = [_arc_circle(np.concatenate(g)) for g in groups]
        best: tuple[float, int, int] | None = None
        for i in range(len(groups)):
            for j in range(i + 1, len(groups)):
                gap = _one_outline_gap(groups[i], groups[j], arcs[i], arcs[j])
                if gap is not None and (best is None or gap < best[0]):
                    best = (gap, i, j)
        if best is None:
            break
        _, i, j = best
        groups[i] = groups[i] + groups[j]
        del groups[j]
    return sorted(groups, key=lambda g: -sum(len(p) for p in g))


def separate_bodies(
    outline: list[np.ndarray], gap_mm: float, link_mm: float = 3.0
) -> list[list[np.ndarray]]:
    """Split an outline into its separate clusters when no one frame can order them.

    The outlier tests keep a cluster that continues an outline along its view's stripe as
    part of that outline (the far side of a part, an occlusion edge). Where the cluster
    is another body (a second ring beside the first, its stripe a step away), the two
    fold in polar coordinates, no reference curve links them, and taken in angle about
    their mean the points zigzag from one body to the other (a path more than
    ``BODIES_PATH_RATIO`` times the views' own): one EFD through both loops between
    them. Each cluster is then an outline of its own. Bodies closer than the gap are one
    cluster, which a reference curve through the passage between them may order: where
    their points zigzag, the outline is split at half the gap if every part is then a
    body seen all round. A thin part's near and far sides, which fold and do not link
    either, are taken round in angle without a zigzag and stay one outline.

    Args:
        outline: one outline's pieces (runs of one view's stripe, in stripe order).
        gap_mm: the outline gap of :func:`split_outlines`.
        link_mm: the widest step between points of one outline (as :func:`blend_overlaps`).

    Returns:
        ``[outline]`` unchanged, or its clusters, most points first.
    """
    segs = [np.asarray(p, dtype=float).reshape(-1, 2) for p in outline]
    segs = [p for p in segs if len(p)]
    if not segs:
        return [outline]
    if not _zigzags(segs):
        return [outline]
    clusters = split_outlines(segs, gap_mm, min_points=1)
    if len(clusters) >= 2:
        return [outline] if _frame_coordinates(segs, link_mm).fits else clusters
    # Bodies closer than the outline gap (two fingers a millimetre apart) are one cluster
    # at that gap, and a reference curve through the narrow passage between them orders
    # them as one outline: the EFD then runs a figure of eight through both (random
    # thesis shape 91023: 0.095 mm, coverage 0.74). At half the gap they part. Taken only
    # where every part is a body seen all round, not an arc (as :func:`join_arcs` tells
    # them): one crescent's outer and inner arcs, apart where its horn hides a stretch,
    # part there too (random thesis shape 27: 210 and 40 degrees), and stray points
    # between two bodies never become outlines of their own.
    close = split_outlines(segs, gap_mm / 2, min_points=1)
    if len(close) >= 2 and all(_whole_body(np.concatenate(c)) for c in close):
        return close
    return [outline]


def _whole_body(points: np.ndarray) -> bool:
    """Return whether points are a body seen all round: an outline's worth, and no arc."""
    enough = len(points) >= MIN_OUTLINE_POINTS
    return enough and angular_extent_deg(points) >= ARC_COVERAGE * 360.0


BODIES_PATH_RATIO = 2.0
"""An outline whose points, taken in angle about their mean, run a path more than this
many times the length of its views' own stripes zigzags between bodies. One body's
outline runs about once round (overlapping views count twice in their own length); two
bodies side by side ran 2.5-20 times (random shapes 857833, 26, 26322), a thin part's
two sides 1.2-1.8 times."""


def _zigzags(segs: list[np.ndarray]) -> bool:
    """Return whether an outline's points zigzag taken in angle about their mean.

    Args:
        segs: the outline's non-empty (K, 2) pieces, each ordered along its stripe.
    """
    points = np.concatenate(segs)
    angle, _ = _polar(points, points.mean(axis=0))
    in_angle = points[np.argsort(angle, kind="stable")]
    path_mm = float(np.hypot(*np.diff(in_angle, axis=0).T).sum())
    own_mm = sum(float(np.hypot(*np.diff(s, axis=0).T).sum()) for s in segs)
    return path_mm > BODIES_PATH_RATIO * own_mm


def _arc_circle(points: np.ndarray) -> float | None:
    """Return the radius of an arc's own fitted circle, or None when it is no arc."""
    if len(points) < 10:
        return None
    try:
        _, _, r = taubin_circle(points[:: max(1, len(points) // MAX_EXTENT_POINTS)])
    except CalibrationError:
        return None
    if angular_extent_deg(points) >= ARC_COVERAGE * 360.0 or not np.isfinite(r):
        return None
    return r


def _one_outline_gap(
    a: list[np.ndarray], b: list[np.ndarray], r_a: float | None, r_b: float | None
) -> float | None:
    """Return the distance between two arcs' nearest points if they are one outline's."""
    if r_a is None or r_b is None:
        return None
    pa, pb = np.concatenate(a), np.concatenate(b)
    both = np.concatenate([pa, pb])
    try:
        cx, cy, r = taubin_circle(both[:: max(1, len(both) // MAX_EXTENT_POINTS)])
    except CalibrationError:
        return None
    if not all(1.0 / ARC_RADIUS_RATIO <= own / r <= ARC_RADIUS_RATIO for own in (r_a, r_b)):
        return None
    n_bins = int(360.0 / EXTENT_BIN_DEG)

    def bins(p: np.ndarray) -> set[int]:
        ang = np.arctan2(p[:, 1] - cy, p[:, 0] - cx)
        return set(np.minimum(((ang + np.pi) / (2 * np.pi) * n_bins).astype(int), n_bins - 1))

    if len(bins(pa) & bins(pb)) > ARC_OVERLAP_BINS:
        return None
    from scipy.spatial import cKDTree  # deferred: only sections of several arcs need it

    return float(cKDTree(pa).query(pb)[0].min())
