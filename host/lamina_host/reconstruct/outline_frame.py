"""Where along an outline a point lies and how far out: the coordinates views are blended in.

The thesis blends overlapping views radially about the section's centre (6.3): a point's
polar angle says where along the outline it lies, its radius how far out. That holds for
an outline that every ray from the centre crosses once (star-shaped): a cylinder, most
limbs. A kidney, a C, a bent flap or the web between two digits is crossed twice by some
rays, and polar blending averages two surfaces into one, so their EFD is drawn through
points taken from both sides in the wrong order.

Such an outline gets a reference curve instead: a smooth line through its points (the
longest path of the minimum spanning tree of its points binned into cells), closed by a
chord across an unseen gap. A point's position is then its arc length along that curve,
its offset the signed distance from it. Both kinds of :class:`OutlineFrame` give the same
two numbers, ``t`` in radians (one turn round the outline, counter-clockwise) and an
offset in mm that grows outwards, so the overlap blending, coverage, gap bridging and the
EFD order rule work on either unchanged; star-shaped outlines keep the polar frame, so
what they give is the thesis' method as it was.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy import sparse
from scipy.sparse import csgraph
from scipy.spatial import cKDTree

from lamina_host.reconstruct.measure import signed_area

TWO_PI = 2.0 * math.pi

CELLS_ACROSS = 100
"""The reference curve bins an outline's points into cells this many times smaller than
the outline's bounding-box diagonal (within ``CELL_RANGE_MM``): fine enough to follow a
thin part's tip, coarse enough that the stripe's scatter stays within a cell or two."""

CELL_RANGE_MM = (0.15, 1.5)
"""Smallest and largest cell of the reference curve's binning, mm."""

SMOOTHING_CELLS = 7
"""The reference path is smoothed twice by a moving mean over this many cells."""


@dataclass(frozen=True, eq=False)
class OutlineFrame:
    """Coordinates along one outline: polar about ``centre_mm``, or along ``reference``.

    ``reference`` is None for the polar frame; otherwise a closed counter-clockwise
    polyline (M, 2), uniformly sampled, its last point joined to its first.
    """

    centre_mm: np.ndarray
    reference: np.ndarray | None = None
    _curve: _Curve | None = field(default=None, init=False, repr=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "centre_mm", np.asarray(self.centre_mm, dtype=float))
        if self.reference is not None:
            object.__setattr__(self, "_curve", _Curve(np.asarray(self.reference, dtype=float)))

    @property
    def polar(self) -> bool:
        """Return True for the polar frame (a star-shaped outline)."""
        return self._curve is None

    def to_local(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return each (N, 2) point's position ``t`` in [-pi, pi] and outward offset in mm.

        Polar: the angle and radius about the centre. Along the reference: ``t`` is
        ``-pi + 2 pi s / L`` of the arc length ``s`` of the nearest point on the curve of
        length ``L``, the offset the signed distance from it plus ``L / 2 pi`` (so a
        circle's reference gives about its radius).
        """
        pts = np.asarray(points, dtype=float).reshape(-1, 2)
        if self._curve is None:
            d = pts - self.centre_mm
            return np.arctan2(d[:, 1], d[:, 0]), np.hypot(d[:, 0], d[:, 1])
        return self._curve.to_local(pts)

    def to_xy(self, t: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """Return the (N, 2) points at positions ``t`` (radians) and offsets (mm)."""
        t, offset = np.asarray(t, dtype=float), np.asarray(offset, dtype=float)
        if self._curve is None:
            return self.centre_mm + np.stack([offset * np.cos(t), offset * np.sin(t)], axis=1)
        return self._curve.to_xy(t, offset)


class _Curve:
    """A closed polyline's arc length, its segments' outward normals and nearest points."""

    def __init__(self, points: np.ndarray) -> None:
        self.points = points
        step = np.roll(points, -1, axis=0) - points  # segment k: point k to point k + 1
        self.seg_len = np.maximum(np.hypot(step[:, 0], step[:, 1]), 1e-12)
        self.seg_normal = np.stack([step[:, 1], -step[:, 0]], axis=1) / self.seg_len[:, None]
        self.start = np.concatenate([[0.0], np.cumsum(self.seg_len)])  # (M + 1,)
        self.length = float(self.start[-1])
        self.base = self.length / TWO_PI
        self.tree = cKDTree(points)

    def to_local(self, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return positions and offsets of ``pts`` (see :meth:`OutlineFrame.to_local`)."""
        m = len(self.points)
        _, k = self.tree.query(pts)
        best_s = np.zeros(len(pts))
        best_n = np.zeros(len(pts))
        best_d = np.full(len(pts), np.inf)
        for seg in ((k - 1) % m, k):  # the segments either side of the nearest vertex
            a = self.points[seg]
            b = self.points[(seg + 1) % m]
            ab = b - a
            u = np.clip(np.einsum("ij,ij->i", pts - a, ab) / self.seg_len[seg] ** 2, 0.0, 1.0)
            foot = a + u[:, None] * ab
            d = np.hypot(*(pts - foot).T)
            closer = d < best_d
            best_d[closer] = d[closer]
            best_s[closer] = (self.start[seg] + u * self.seg_len[seg])[closer]
            best_n[closer] = np.einsum("ij,ij->i", pts - foot, self.seg_normal[seg])[closer]
        return -math.pi + TWO_PI * best_s / self.length, best_n + self.base

    def to_xy(self, t: np.ndarray, offset: np.ndarray) -> np.ndarray:
        """Return the points at positions ``t`` and offsets (see :meth:`OutlineFrame.to_xy`).

        Along the segment's own normal, as :meth:`to_local` measures the offset, so the
        two are each other's inverse wherever a point's nearest foot lies inside a segment.
        """
        s = np.mod((t + math.pi) / TWO_PI * self.length, self.length)
        seg = np.clip(np.searchsorted(self.start, s, side="right") - 1, 0, len(self.points) - 1)
        u = (s - self.start[seg]) / self.seg_len[seg]
        nxt = (seg + 1) % len(self.points)
        pos = self.points[seg] + u[:, None] * (self.points[nxt] - self.points[seg])
        return pos + (offset - self.base)[:, None] * self.seg_normal[seg]


def unwrap_angles(angle_rad: np.ndarray) -> np.ndarray:
    """Return angles along a stripe unwrapped (no step over pi), as ``np.unwrap`` but leaner.

    Called for every stripe of every section, where ``np.unwrap``'s generality costs more
    than the work.
    """
    a = np.asarray(angle_rad, dtype=float)
    if len(a) < 2:
        return a.copy()
    step = a[1:] - a[:-1]
    step -= TWO_PI * np.rint(step / TWO_PI)
    out = np.empty_like(a)
    out[0] = a[0]
    np.cumsum(step, out=out[1:])
    out[1:] += a[0]
    return out


def outline_frame(points: np.ndarray, link_mm: float) -> OutlineFrame:
    """Return the frame along a reference curve through an outline's points.

    For an outline that polar coordinates about its centre do not fit (the caller tells:
    a view's stripe folds back in angle or runs along a ray). The polar frame about the
    mean of the points is returned where no reference curve can be drawn (the points do
    not link into one tree, or too few).

    Args:
        points: (N, 2) points of one outline in mm, from any number of views.
        link_mm: the widest step between points of one outline (its points are all linked
            by steps no longer than this; wider unseen gaps close by a chord).

    Returns:
        The frame.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    centre = pts.mean(axis=0) if len(pts) else np.zeros(2)
    if len(pts) < 8 or not np.isfinite(pts).all():
        return OutlineFrame(centre)
    return OutlineFrame(centre, reference_curve(pts, link_mm))


def reference_curve(points: np.ndarray, link_mm: float) -> np.ndarray | None:
    """Return a smooth closed counter-clockwise curve through an outline's points, or None.

    The points are binned into cells (``CELLS_ACROSS``), the cells' means linked within
    ``link_mm`` (at least three cells), and the longest path of the minimum spanning tree
    of those links, smoothed over ``SMOOTHING_CELLS`` cells, is the curve: an outline seen
    all round is a loop that the tree breaks once, so the path runs round it; one seen in
    part is an arc, closed here by the chord across its gap. None when the points do not
    link into one tree (nothing to order them by).

    Args:
        points: (N, 2) points in mm.
        link_mm: the widest step between points of the outline.

    Returns:
        (M, 2) points sampled every quarter cell, or None.
    """
    diagonal = float(np.hypot(*np.ptp(points, axis=0)))
    cell = float(np.clip(diagonal / CELLS_ACROSS, *CELL_RANGE_MM))
    keys = np.floor((points - points.min(axis=0)) / cell).astype(np.int64)
    _, inverse, counts = np.unique(
        keys[:, 0] * (int(keys[:, 1].max()) + 1) + keys[:, 1],
        return_inverse=True,
        return_counts=True,
    )
    means = np.stack([np.bincount(inverse, points[:, k]) / counts for k in (0, 1)], axis=1)
    if len(means) < 4:
        return None
    tree = cKDTree(means)
    spanning = _spanning_tree(means, tree.query_pairs(3.0 * cell, output_type="ndarray"))
    reach = max(link_mm, 3.0 * cell)
    groups, label = csgraph.connected_components(spanning, directed=False)
    if groups > 1:  # unseen stretches: link across them, within reach
        wide = tree.query_pairs(reach, output_type="ndarray")
        wide = wide[label[wide[:, 0]] != label[wide[:, 1]]]
        spanning = _spanning_tree(means, np.vstack([_edges(spanning), wide]))
        if csgraph.connected_components(spanning, directed=False)[0] > 1:
            return None
    path = _longest_path(spanning)
    if len(path) < 4:
        return None
    closed = _closes(means[path], reach)
    xy = _smooth(_smooth(means[path], SMOOTHING_CELLS, closed), SMOOTHING_CELLS, closed)
    if signed_area(xy) < 0.0:  # clockwise
        xy = xy[::-1]
    return _resample_closed(xy, cell / 4.0)


def _spanning_tree(means: np.ndarray, pairs: np.ndarray) -> sparse.csr_array:
    """Return the minimum spanning tree (forest) of the cell means linked by ``pairs``."""
    n = len(means)
    weight = np.maximum(np.hypot(*(means[pairs[:, 0]] - means[pairs[:, 1]]).T), 1e-9)
    links = sparse.coo_array((weight, (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    return csgraph.minimum_spanning_tree(links.tocsr())


def _edges(spanning: sparse.csr_array) -> np.ndarray:
    """Return a sparse graph's (E, 2) node pairs."""
    coo = sparse.coo_array(spanning)
    return np.stack([coo.row, coo.col], axis=1).astype(np.int64)


def _longest_path(spanning: sparse.csr_array) -> np.ndarray:
    """Return the node indices of a tree's longest path (two farthest-node searches)."""
    far = csgraph.shortest_path(spanning, directed=False, indices=0)
    a = int(np.argmax(np.where(np.isfinite(far), far, -1.0)))
    dist, pred = csgraph.shortest_path(
        spanning, directed=False, indices=a, return_predecessors=True
    )
    b = int(np.argmax(np.where(np.isfinite(dist), dist, -1.0)))
    path = [b]
    while path[-1] != a:
        path.append(int(pred[path[-1]]))
    return np.asarray(path[::-1])


def _closes(path: np.ndarray, reach_mm: float) -> bool:
    """Return whether a path's ends lie within ``reach_mm`` (it runs round a loop)."""
    return bool(np.hypot(*(path[0] - path[-1])) <= reach_mm)


def _smooth(xy: np.ndarray, window: int, closed: bool) -> np.ndarray:
    """Return a path smoothed by a moving mean (wrapping round if ``closed``)."""
    if len(xy) <= window:
        return xy
    half = window // 2
    if closed:
        padded = np.vstack([xy[-half:], xy, xy[:half]])
    else:
        padded = np.vstack([np.repeat(xy[:1], half, 0), xy, np.repeat(xy[-1:], half, 0)])
    kernel = np.ones(window) / window
    out = np.stack([np.convolve(padded[:, k], kernel, mode="valid") for k in (0, 1)], axis=1)
    if not closed:
        out[0], out[-1] = xy[0], xy[-1]  # an arc keeps its ends where they were seen
    return out


def _resample_closed(xy: np.ndarray, spacing_mm: float) -> np.ndarray:
    """Return a closed polyline resampled every ``spacing_mm`` along its length."""
    loop = np.vstack([xy, xy[:1]])
    step = np.hypot(*np.diff(loop, axis=0).T)
    s = np.concatenate([[0.0], np.cumsum(step)])
    count = max(16, math.ceil(s[-1] / spacing_mm))
    at = np.arange(count) * (s[-1] / count)
    return np.stack([np.interp(at, s, loop[:, k]) for k in (0, 1)], axis=1)
