"""Outlier rejection before assembly: what the views do not agree on is not surface (issue #10).

A real camera's stripe finder reports points that are not on the object: reflections,
stray light and noise columns. The thesis assembles every point (6.3), so each such point
becomes a phantom outline or a bump. Five steps, cheapest first, each vectorised:

1. **Spikes**: a point far from the coordinate-wise median of its neighbours along its own
   stripe is a noise column (the median of a locally monotone curve is its middle point,
   and a step, such as an occlusion edge, survives a median filter).
2. **Working volume**: a point further from the turntable axis than the disc the camera
   sees at every turntable angle is not on the object unless other views confirm most of
   its stretch of stripe: an object wider than that disc, or standing off the axis, keeps
   what two views agree on beyond it.
3. **View consensus** (polar coordinates about the axis): the views overlap, so a surface
   point is normally seen by more than one view. A point no other view confirms nearby,
   in an angular sector where other views agree on surfaces only at radii far from it,
   is an outlier, unless it continues a stretch of its own stripe that other
   views do confirm (the far side of a thin part, which one view sees, continues into
   its confirmed sides; a reflection is a stretch of its own) or its stretch is the arc
   of a thin part close beside a confirmed surface (which shadows it from the other
   views). A point in a sector no other view covers is kept.
4. **Outline support**: the points are grouped into clusters (points closer than the
   outline gap join); a cluster is an outline with enough points, enough views,
   enough size and enough angular extent about its fitted circle's centre. Phantom
   clusters come from one view (a reflection moves with the turntable, so it lands
   elsewhere in each view), and two that meet by chance form a stroke, not an arc.
   A cluster whose points other views mostly confirm is an outline at any angle (two
   views agree along it: a shallow arc of a wide or flat object, not a chance stroke).
   A smaller cluster, or one seen by one view, that nothing contradicted (step 3) is
   still kept when its view's stripe continues into it from a supported cluster, or
   when it is the arc of a thin part (2-6 mm thick): it is rejected only on evidence.
5. **Stray stretches**: what is left of a view's stripe in runs of fewer than
   ``MIN_RUN_POINTS`` points (between rejected points, or apart from the stripe) goes;
   each remaining run is one piece for overlap averaging, which interpolates a piece
   between its points and so must not bridge a hole.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

from lamina_host.reconstruct.axis import taubin_circle
from lamina_host.reconstruct.calibration import CalibrationError

SPIKE_WINDOW = 5
"""Points in the median window along the stripe: removes spikes of up to 2 points."""

SECTOR_DEG = 2.0
"""Angular sectors about the axis in which the views' radii are compared."""

MAX_EXTENT_POINTS = 2000
"""An outline's angular extent is measured on at most about this many of its points."""

SECTOR_KEY_MM = 1.0e5
"""Sector stride of the sorted (sector, radius) key: larger than any radius in mm."""

EXTENT_BIN_DEG = 10.0
"""Angular bins about a cluster's fitted circle centre when measuring its angular extent."""

MIN_RUN_POINTS = 5
"""A run of fewer points, left between rejected ones or apart from its stripe, is stray."""

MIN_RUN_CONFIRMED = 0.5
"""A stretch of one view's stripe with at least this share of points confirmed by other
views is surface: its unconfirmed points are kept even where other views disagree."""

OUTSIDE_RUN_CONFIRMED = 0.2
"""Beyond the working radius, a stretch of one view's stripe with at least this share
confirmed by other views is surface. Fewer views see an object out there, so its
stretches are confirmed only in part: 25-40 % on random thesis-scale shapes 60 and 62,
whose points there lay within 0.1 mm of the true surface (80-97 %) and none beyond 1 mm,
yet half the share threw away a fifth of their sections. Reflections of two views cross
at a point or two: a few % of a stretch."""


ALONG_DEG = 30.0
"""Beyond the disc every view sees, another view's point confirms a point only where the
two stripes run within this angle of each other: two views of one surface run along it
together, two stray strokes cross."""


@dataclass(frozen=True)
class OutlierRules:
    """Thresholds of the outlier tests (module docstring); the defaults suit both rigs."""

    working_radius_mm: float | None = None
    """Furthest a point may be from the axis; None: no limit."""
    spike_mm: float = 1.0
    """Distance from the stripe's local median that makes a point a spike."""
    consensus_mm: float = 1.0
    """Another view's point this close confirms a point; a point this far from every
    confirmed radius of its sector contradicts them."""
    min_points: int = 30
    """Fewest points of an outline."""
    min_views: int = 2
    """Fewest views that must each see ``min_view_points`` of an outline."""
    min_view_points: int = 5
    """Points a view must contribute to count as seeing an outline."""
    min_extent_mm: float = 2.0
    """Smallest bounding-box diagonal of an outline."""
    min_angle_deg: float = 60.0
    """Smallest angle an outline subtends about its fitted circle's centre, unless
    ``min_confirmed_share`` of its points are confirmed."""
    min_confirmed_share: float = 0.5
    """A cluster with enough points and views, at least ``confirmed_extent_mm`` across, is
    an outline whatever its angle when this share of its points is confirmed by another
    view: two views agreeing along a stretch see a surface (a shallow arc of a wide or
    flat object), where chance strokes of two views meet at a crossing. On random
    thesis-scale shape 43 the angle rule alone threw away 711 such points (85-92 %
    confirmed, 0.01-0.03 mm from the true surface) and a section's outline with them."""
    confirmed_extent_mm: float = 5.0
    """Smallest bounding-box diagonal of a cluster kept by ``min_confirmed_share``: short
    random strokes of three views that cross (3.9 mm across, 63 points, in the phantom
    test of two posts) agree all along by chance."""
    min_thin_points: int = 10
    """Fewest points of a cluster kept without the support above (``cluster_support``)."""
    continue_mm: float = 5.0
    """Longest step along one view's stripe that continues a supported cluster."""
    thin_radius_mm: tuple[float, float] = (1.0, 3.0)
    """Radii of the circle a thin part's arc fits (2-6 mm thick)."""
    thin_fit_mm: float = 0.1
    """Largest RMS distance of a thin part's points from their circle."""
    thin_reach_mm: float = 6.0
    """A thin part one view saw beside a confirmed surface lies at most this far from it."""


@dataclass
class Rejected:
    """How many points each test removed (all sections); ``clusters`` counts the clusters
    (not points) that were not outlines."""

    outside_volume: int = 0
    """Points further from the axis than the working radius that no other view supports."""
    spikes: int = 0
    """Points too far from their stripe's local median."""
    view_consensus: int = 0
    """Points the other views of their section contradict."""
    unsupported_clusters: int = 0
    """Points of clusters too small, too few views or too narrow to be an outline."""
    clusters: int = 0
    """Clusters (not points) that were not outlines."""
    short_runs: int = 0
    """Points of one view's stripe runs shorter than ``MIN_RUN_POINTS`` (stray pieces)."""

    @property
    def points(self) -> int:
        """Return the total number of points removed."""
        return (
            self.outside_volume
            + self.spikes
            + self.view_consensus
            + self.unsupported_clusters
            + self.short_runs
        )

    @property
    def one_view(self) -> int:
        """Return the points removed for want of a second view: beyond the working radius
        unconfirmed, or in clusters too small or seen by too few views."""
        return self.outside_volume + self.unsupported_clusters

    def add(self, other: Rejected) -> None:
        """Add another count to this one."""
        for name in self.__dataclass_fields__:
            setattr(self, name, getattr(self, name) + getattr(other, name))

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form."""
        return {**self.__dict__, "points": self.points}


def spike_mask(points: np.ndarray, lengths: list[int], spike_mm: float) -> np.ndarray:
    """Return True for points further than ``spike_mm`` from their stripe's local median.

    The median is coordinate-wise over ``SPIKE_WINDOW`` (5) points, the stripe's ends
    repeated.

    Args:
        points: (N, 2) points of several stripes, one after the other, each in order.
        lengths: the number of points of each stripe (summing to N).
        spike_mm: the distance that makes a point a spike.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    first = np.repeat(np.cumsum([0, *lengths[:-1]]), lengths)
    last = first + np.repeat(lengths, lengths) - 1
    at = np.arange(len(pts))
    half = SPIKE_WINDOW // 2
    med = _median5([pts[np.clip(at + k, first, last)] for k in range(-half, half + 1)])
    return np.hypot(*(pts - med).T) > spike_mm


def _median5(p: list[np.ndarray]) -> np.ndarray:
    """Return the element-wise median of five arrays (Devillard's 7-exchange network)."""
    p = list(p)
    for i, j in ((0, 1), (3, 4), (0, 3), (1, 4), (1, 2), (2, 3), (1, 2)):
        p[i], p[j] = np.minimum(p[i], p[j]), np.maximum(p[i], p[j])
    return p[2]


def group_range(
    values: np.ndarray, groups: np.ndarray, count: int
) -> tuple[np.ndarray, np.ndarray]:
    """Return the smallest and largest value of each group 0..count-1 (inf, -inf if empty)."""
    lo = np.full(count, np.inf)
    hi = np.full(count, -np.inf)
    if len(values):
        order = np.argsort(groups, kind="stable")
        g = groups[order]
        start = np.flatnonzero(np.diff(g, prepend=-1))
        lo[g[start]] = np.minimum.reduceat(values[order], start)
        hi[g[start]] = np.maximum.reduceat(values[order], start)
    return lo, hi


def _neighbour_offsets() -> np.ndarray:
    """Return the 9 cell offsets of a 3 x 3 neighbourhood."""
    d = np.arange(-1, 2)
    return np.stack(np.meshgrid(d, d, indexing="ij"), -1).reshape(-1, 2)


def confirmed_by_other_views(points: np.ndarray, views: np.ndarray, radius_mm: float) -> np.ndarray:
    """Return True for points with a point of another view within about ``radius_mm``.

    Points are hashed into cells of ``radius_mm / 2``; a point is confirmed when one of the
    9 cells around it holds a point of another view (so "near" means between
    ``radius_mm / 2`` and ``1.4 radius_mm``). Each cell keeps its smallest and largest
    view number: another view is present unless both equal the point's own view.
    """
    if len(points) == 0:
        return np.zeros(0, dtype=bool)
    cell = np.floor(points / (0.5 * radius_mm)).astype(np.int64)
    cell -= cell.min(axis=0) - 1
    height = int(cell[:, 1].max()) + 2
    n_views = int(views.max()) + 1
    # Work on the distinct (cell, view) pairs, far fewer than the points.
    pairs, inverse = np.unique((cell[:, 0] * height + cell[:, 1]) * n_views + views,
                               return_inverse=True)  # fmt: skip
    pair_cell, pair_view = pairs // n_views, pairs % n_views
    cells, first = np.unique(pair_cell, return_index=True)
    last = np.append(first[1:], len(pairs)) - 1
    lo, hi = pair_view[first], pair_view[last]  # pairs are sorted: views ascend per cell
    confirmed = np.zeros(len(pairs), dtype=bool)
    for step in _neighbour_offsets() @ np.array([height, 1]):
        probe = pair_cell + step
        at = np.minimum(np.searchsorted(cells, probe), len(cells) - 1)
        confirmed |= (cells[at] == probe) & ((lo[at] != pair_view) | (hi[at] != pair_view))
    return confirmed[inverse.ravel()]


DIRECTION_SPAN = 4
"""A stripe's direction at a point is taken over this many points either side of it
(fewer at the stripe's ends): one pixel's step is mostly noise."""


def stripe_directions(points: np.ndarray, views: np.ndarray) -> np.ndarray:
    """Return each point's unit direction along its own view's stripe (points in stripe
    order, view after view): from ``DIRECTION_SPAN`` points before it to as many after,
    within its view."""
    n = len(points)
    at = np.arange(n)
    first = np.searchsorted(views, views, side="left")  # views run in blocks, ascending
    last = np.searchsorted(views, views, side="right") - 1
    ahead = points[np.minimum(at + DIRECTION_SPAN, last)]
    step = ahead - points[np.maximum(at - DIRECTION_SPAN, first)]
    length = np.hypot(step[:, 0], step[:, 1])
    return step / np.maximum(length, 1e-12)[:, None]


def confirmed_along(
    points: np.ndarray, views: np.ndarray, asked: np.ndarray, radius_mm: float
) -> np.ndarray:
    """Return True for the ``asked`` points that another view's stripe runs along.

    A point is confirmed when a point of another view lies within ``radius_mm`` and that
    view's stripe runs within ``ALONG_DEG`` of its own there (either way round).

    Args:
        points: (N, 2) points in stripe order, view after view.
        views: (N,) each point's view.
        asked: (N,) the points to test; the others are returned False.
        radius_mm: the distance within which another view's point confirms.
    """
    out = np.zeros(len(points), dtype=bool)
    asked_at = np.flatnonzero(asked)
    if len(asked_at) == 0:
        return out
    from scipy.spatial import cKDTree  # deferred: only objects wider than the view need it

    direction = stripe_directions(points, views)
    cos_limit = np.cos(np.deg2rad(ALONG_DEG))
    near = cKDTree(points).query_ball_point(points[asked_at], radius_mm)
    for i, found in zip(asked_at, near, strict=True):
        found = np.asarray(found, dtype=np.int64)
        found = found[views[found] != views[i]]
        out[i] = bool(np.any(np.abs(direction[found] @ direction[i]) >= cos_limit))
    return out


def contradicted(points: np.ndarray, confirmed: np.ndarray, consensus_mm: float) -> np.ndarray:
    """Return True for unconfirmed points far from every confirmed surface in their sector.

    Sectors of ``SECTOR_DEG`` about the axis (the object frame's origin). Confirmed points
    are where two or more views agree on a surface. An unconfirmed point whose sector
    holds confirmed points, none within ``consensus_mm`` of its radius, contradicts them.
    A sector may hold several surfaces (both sides of an off-axis part): each counts.
    """
    out = np.zeros(len(points), dtype=bool)
    if confirmed.all() or not confirmed.any():
        return out
    n_sectors = int(360.0 / SECTOR_DEG)
    ang = np.degrees(np.arctan2(points[:, 1], points[:, 0])) + 180.0
    sector = np.minimum((ang / SECTOR_DEG).astype(np.int64), n_sectors - 1)
    # One sorted key: sector first, radius within it (radii are far below SECTOR_KEY).
    key = sector * SECTOR_KEY_MM + np.hypot(points[:, 0], points[:, 1])
    keys = np.sort(key[confirmed])
    ask, sec = key[~confirmed], sector[~confirmed]
    at = np.searchsorted(keys, ask)
    below = keys[np.maximum(at - 1, 0)]
    above = keys[np.minimum(at, len(keys) - 1)]
    near = (np.abs(below - ask) <= consensus_mm) | (np.abs(above - ask) <= consensus_mm)
    lo, hi = sec * SECTOR_KEY_MM, (sec + 1) * SECTOR_KEY_MM
    occupied = ((below >= lo) & (below < hi)) | ((above >= lo) & (above < hi))
    out[~confirmed] = occupied & ~near
    return out


def run_confirmed_share(
    points: np.ndarray, views: np.ndarray, confirmed: np.ndarray, gap_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Return each point's run's share of confirmed points, and its run number.

    A run is a stretch of one view's stripe (points in stripe order) without a jump
    wider than ``gap_mm``. The far side of a thin part, seen by one view only, continues
    a run the other views confirm; a reflection is a run of its own.
    """
    if len(points) == 0:
        # np.diff of nothing is nothing, but the leading break would still make one run.
        return np.zeros(0), np.zeros(0, dtype=np.int64)
    step = np.hypot(*np.diff(points, axis=0).T)
    breaks = np.concatenate([[True], (np.diff(views) != 0) | (step > gap_mm)])
    run = np.cumsum(breaks) - 1
    share = np.bincount(run, confirmed.astype(float)) / np.bincount(run)
    return share[run], run


def thin_runs(
    points: np.ndarray,
    run: np.ndarray,
    suspect: np.ndarray,
    confirmed: np.ndarray,
    rules: OutlierRules,
) -> np.ndarray:
    """Return True for the points of suspect runs that are a thin part beside the surface.

    A thin part (2-6 mm thick) near a larger one is often seen by one view, the others
    shadowed by the larger part; other views confirming that larger part in the same
    sector do not contradict it. A run (one view's stretch, :func:`run_confirmed_share`)
    holding ``suspect`` points is kept when it is :func:`thin_part`'s arc and lies within
    ``rules.thin_reach_mm`` of a confirmed point. Further out, where the other views
    would have seen it too, it stays contradicted (a reflection).
    """
    out = np.zeros(len(points), dtype=bool)
    runs = np.unique(run[suspect])
    if len(runs) == 0 or not confirmed.any():
        return out
    from scipy.spatial import cKDTree  # deferred: only sections with suspects need it

    tree = cKDTree(points[confirmed])
    for r in runs:
        mine = run == r
        if mine.sum() < rules.min_thin_points or not thin_part(points[mine], rules):
            continue
        if tree.query(points[mine], distance_upper_bound=rules.thin_reach_mm)[0].min() < np.inf:
            out |= mine
    return out


def label_clusters(points: np.ndarray, gap_mm: float) -> tuple[np.ndarray, int]:
    """Return each point's cluster label (0..count-1) and the count.

    Points are binned on a grid of ``gap_mm / 2`` cells and 8-connected occupied cells
    join, so clusters more than ``sqrt(2) gap_mm`` apart are always separate and points
    closer than ``gap_mm / 2`` always join.
    """
    if not gap_mm > 0:
        raise ValueError(f"the outline gap must be a positive number of mm, not {gap_mm}")
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64), 0
    cell = np.floor((points - points.min(axis=0)) / (0.5 * gap_mm)).astype(np.int64)
    grid = np.zeros(cell.max(axis=0) + 1, dtype=bool)
    grid[cell[:, 0], cell[:, 1]] = True
    labels, count = ndimage.label(grid, structure=np.ones((3, 3), dtype=int))
    return labels[cell[:, 0], cell[:, 1]] - 1, int(count)


def cluster_support(
    points: np.ndarray,
    views: np.ndarray,
    labels: np.ndarray,
    count: int,
    rules: OutlierRules,
    confirmed: np.ndarray | None = None,
) -> np.ndarray:
    """Return True for each cluster that is well enough supported to be an outline.

    A cluster is an outline with enough points, views, size and angle (module docstring,
    step 4). One that falls short is still kept, as nothing rejected it on evidence (the
    views' consensus, step 3, comes first), when it holds ``rules.min_thin_points`` and
    either continues a supported cluster along its own view's stripe (the stripe steps
    less than ``rules.continue_mm`` from one to the other: the far side of a part, an
    occlusion edge) or is plausibly a thin part (:func:`thin_part`). ``confirmed`` (per
    point, True where another view confirms it) lets a confirmed cluster pass without
    the angle (``rules.min_confirmed_share``); None: every cluster needs the angle.
    """
    return support_and_joins(points, views, labels, count, rules, confirmed)[0]


def support_and_joins(
    points: np.ndarray,
    views: np.ndarray,
    labels: np.ndarray,
    count: int,
    rules: OutlierRules,
    confirmed: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Return :func:`cluster_support`'s verdict and, per cluster, the one it continues.

    Returns:
        (count,) True for kept clusters, and (count,) the label of the supported cluster
        a cluster was kept for continuing (-1 for the others): it belongs to that outline.
    """
    n_views = int(views.max()) + 1 if len(views) else 1
    sizes = np.bincount(labels, minlength=count)
    per_view = np.bincount(labels * n_views + views, minlength=count * n_views)
    seen_by = (per_view.reshape(count, n_views) >= rules.min_view_points).sum(axis=1)
    ranges = [group_range(points[:, k], labels, count) for k in (0, 1)]
    extent = np.hypot(*(hi - lo for lo, hi in ranges))
    good = (
        (sizes >= rules.min_points) & (seen_by >= rules.min_views) & (extent >= rules.min_extent_mm)
    )
    if confirmed is not None:
        share = np.bincount(labels, weights=confirmed, minlength=count) / np.maximum(sizes, 1)
        agreed = (share >= rules.min_confirmed_share) & (extent >= rules.confirmed_extent_mm)
    else:
        agreed = np.zeros(count, dtype=bool)
    for label in np.flatnonzero(good & ~agreed):
        good[label] = angular_extent_deg(points[labels == label]) >= rules.min_angle_deg
    joins = np.full(count, -1, dtype=np.int64)
    candidates = ~good & (sizes >= rules.min_thin_points)
    for _ in range(count):  # a chain of pieces along one stripe joins one at a time
        if not candidates.any() or not good.any():
            break
        target = _continues(points, views, labels, count, good, rules.continue_mm)
        joined = candidates & (target >= 0)
        if not joined.any():
            break
        owner = target[joined]
        joins[joined] = np.where(joins[owner] >= 0, joins[owner], owner)
        good |= joined
        candidates &= ~joined
    if candidates.any():
        good |= candidates & _thin_parts(points, labels, count, rules)
    return good, joins


def _continues(
    points: np.ndarray,
    views: np.ndarray,
    labels: np.ndarray,
    count: int,
    good: np.ndarray,
    reach_mm: float,
) -> np.ndarray:
    """Return, per cluster, a ``good`` cluster its view's stripe steps to it from (or -1).

    ``points`` are in stripe order, view after view; a step joins two clusters when it
    stays in one view and is at most ``reach_mm`` long.
    """
    out = np.full(count, -1, dtype=np.int64)
    if len(points) < 2:
        return out
    step = np.hypot(*np.diff(points, axis=0).T)
    link = (np.diff(views) == 0) & (step <= reach_mm) & (labels[1:] != labels[:-1])
    a, b = labels[:-1][link], labels[1:][link]
    forward, backward = good[a] & ~good[b], good[b] & ~good[a]
    out[b[forward]] = a[forward]
    out[a[backward]] = b[backward]
    return out


def _thin_parts(
    points: np.ndarray, labels: np.ndarray, count: int, rules: OutlierRules
) -> np.ndarray:
    """Return True for each cluster that :func:`thin_part` finds plausible."""
    out = np.zeros(count, dtype=bool)
    for label in range(count):
        mine = points[labels == label]
        if len(mine) >= rules.min_thin_points:
            out[label] = thin_part(mine, rules)
    return out


def thin_part(points: np.ndarray, rules: OutlierRules) -> bool:
    """Return whether one view's points are plausibly the side of a thin part.

    A thin part (a finger, a tendon, a strap 2-6 mm thick) shows a view an arc of a small
    outline: the points fit a circle of ``rules.thin_radius_mm`` (1-3 mm) closely (RMS
    within ``rules.thin_fit_mm``) and cover ``rules.min_angle_deg`` of it. A reflection
    is a stroke (a huge circle) and stray light a scatter, neither an arc.
    """
    try:
        cx, cy, r = taubin_circle(points)
    except CalibrationError:
        return False
    lo, hi = rules.thin_radius_mm
    if not lo <= r <= hi:
        return False
    rms = float(np.sqrt(np.mean((np.hypot(*(points - [cx, cy]).T) - r) ** 2)))
    return rms <= rules.thin_fit_mm and angular_extent_deg(points) >= rules.min_angle_deg


def angular_extent_deg(points: np.ndarray) -> float:
    """Return the angle an outline's points subtend about their fitted circle's centre.

    An outline seen all round subtends 360 degrees, a 60-degree arc 60; a straight stroke
    (a reflection) fits a huge circle and subtends almost nothing. The mean of the
    points would not do: a shallow arc about its own mean looks like a line.
    """
    points = points[:: max(1, len(points) // MAX_EXTENT_POINTS)]
    try:
        cx, cy, _ = taubin_circle(points)
    except CalibrationError:
        return 0.0
    d = points - np.array([cx, cy])
    n_bins = int(360.0 / EXTENT_BIN_DEG)
    angle_bin = ((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / (2 * np.pi) * n_bins).astype(np.int64)
    return float(len(np.unique(np.minimum(angle_bin, n_bins - 1))) * EXTENT_BIN_DEG)


def _outside_unconfirmed(
    points: np.ndarray, run_share: np.ndarray, radius_mm: float | None
) -> np.ndarray:
    """Return True for points beyond the working radius that no other view supports.

    The working radius is the disc the camera sees at every turntable angle. An object
    wider than it (or standing off the axis) is still surface where a stretch of one
    view's stripe is partly confirmed by the others (``OUTSIDE_RUN_CONFIRMED``), beyond
    the disc or running on into it. A point merely confirmed is not enough out there: two
    views' reflections cross at a point or two, while two views of one surface agree
    along their whole overlap.
    """
    if radius_mm is None:
        return np.zeros(len(points), dtype=bool)
    outside = np.hypot(points[:, 0], points[:, 1]) > radius_mm
    return outside & (run_share < OUTSIDE_RUN_CONFIRMED)


def clean_section(
    pieces: list[np.ndarray], gap_mm: float, rules: OutlierRules
) -> tuple[list[list[np.ndarray]], Rejected]:
    """Reject a section's outliers and group what is left into well-supported outlines.

    Args:
        pieces: object-frame (K, 2) stripe points in mm, one array per view, each ordered
            along its stripe.
        gap_mm: outlines further apart than this are separate.
        rules: the thresholds.

    Returns:
        One list of pieces per outline (most points first): runs of one view's stripe,
        in stripe order, of ``MIN_RUN_POINTS`` or more; and the counts of points rejected.
    """
    rejected = Rejected()
    segs = [np.asarray(p, dtype=float).reshape(-1, 2) for p in pieces]
    segs = [s for s in segs if len(s)]
    if not segs:
        return [], rejected
    pts = np.concatenate(segs)
    views = np.repeat(np.arange(len(segs)), [len(s) for s in segs])
    spikes = spike_mask(pts, [len(s) for s in segs], rules.spike_mm)
    rejected.spikes = int(spikes.sum())
    pts, views = pts[~spikes], views[~spikes]
    # A stretch may step a little (an occlusion edge) and still be one stretch here.
    run_gap_mm = max(gap_mm, rules.continue_mm)
    if rules.working_radius_mm is not None:
        confirmed = confirmed_by_other_views(pts, views, rules.consensus_mm)
        beyond = np.hypot(pts[:, 0], pts[:, 1]) > rules.working_radius_mm
        if beyond.any():
            along = confirmed_along(pts, views, beyond & confirmed, rules.consensus_mm)
            confirmed = np.where(beyond, along, confirmed)
        share, _ = run_confirmed_share(pts, views, confirmed, run_gap_mm)
        far = _outside_unconfirmed(pts, share, rules.working_radius_mm)
        rejected.outside_volume = int(far.sum())
        # What is rejected out there confirms nothing inside (two reflections may cross).
        pts, views = pts[~far], views[~far]
    confirmed = confirmed_by_other_views(pts, views, rules.consensus_mm)
    bad = contradicted(pts, confirmed, rules.consensus_mm)
    share, run = run_confirmed_share(pts, views, confirmed, run_gap_mm)
    bad &= share < MIN_RUN_CONFIRMED
    bad &= ~thin_runs(pts, run, bad, confirmed, rules)
    rejected.view_consensus = int(bad.sum())
    pts, views = pts[~bad], views[~bad]
    labels, count = label_clusters(pts, gap_mm)
    if count == 0:
        return [], rejected
    good, joins = support_and_joins(pts, views, labels, count, rules, confirmed[~bad])
    rejected.clusters = int((~good).sum())
    rejected.unsupported_clusters = int((~good[labels]).sum())
    # A cluster kept for continuing an outline along a stripe is part of that outline.
    labels = np.where(joins[labels] >= 0, joins[labels], labels)
    good &= joins < 0
    sizes = np.bincount(labels, minlength=count)
    pts, views, labels = pts[good[labels]], views[good[labels]], labels[good[labels]]
    # Pieces are runs of one view's stripe: overlap averaging interpolates each piece
    # between its points, which must not happen across a hole left by a rejection.
    _, run = run_confirmed_share(pts, views, np.ones(len(pts), dtype=bool), gap_mm)
    run_size = np.bincount(run)
    short = run_size[run] < MIN_RUN_POINTS
    rejected.short_runs = int(short.sum())
    outlines = []
    for label in np.argsort(-sizes, kind="stable"):
        if not good[label]:
            continue
        mine = (labels == label) & ~short
        bounds = np.flatnonzero(np.diff(run[mine])) + 1
        outlines.append(np.split(pts[mine], bounds))
    return outlines, rejected
