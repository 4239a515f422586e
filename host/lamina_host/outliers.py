"""Outlier rejection before assembly: what the views do not agree on is not surface (issue #10).

A real camera's stripe finder reports points that are not on the object: reflections,
stray light and noise columns. The thesis assembles every point (6.3), so each such point
becomes a phantom outline or a bump. Four tests, cheapest first, each vectorised:

1. **Working volume**: a point further from the turntable axis than the object can be (the
   disc the camera sees at every turntable angle) is not on the object.
2. **Spikes**: a point far from the coordinate-wise median of its neighbours along its own
   stripe is a noise column (the median of a locally monotone curve is its middle point,
   and a step, such as an occlusion edge, survives a median filter).
3. **View consensus** (polar coordinates about the axis): the views overlap, so a surface
   point is normally seen by more than one view. A point no other view confirms nearby,
   in an angular sector where the other views consistently see a surface at a radius far
   from it, is an outlier. A point in a sector no other view covers is kept: it may be a
   thin part only one view sees.
4. **Outline support**: the points are grouped into clusters (points closer than the
   outline gap join); a cluster is an outline only with enough points, enough views,
   enough size and enough angular extent about its own centre. Phantom clusters come from
   one view (a reflection moves with the turntable, so it lands elsewhere in each view).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy import ndimage

SPIKE_WINDOW = 5
"""Points in the median window along the stripe: removes spikes of up to 2 points."""

SECTOR_DEG = 2.0
"""Angular sectors about the axis in which the views' radii are compared."""

EXTENT_BIN_DEG = 10.0
"""Angular bins about a cluster's own centre when measuring its angular extent."""


@dataclass(frozen=True)
class OutlierRules:
    """Thresholds of the outlier tests (module docstring); the defaults suit both rigs.

    Attributes:
        working_radius_mm: furthest a point may be from the axis; None: no limit.
        spike_mm: distance from the stripe's local median that makes a point a spike.
        consensus_mm: another view's point this close confirms a point; a point this far
            from the other views' agreed radius contradicts them.
        agree_mm: the other views agree when their radii in a sector span at most this.
        min_points: fewest points of an outline.
        min_views: fewest views that must each see ``min_view_points`` of an outline.
        min_view_points: points a view must contribute to count as seeing an outline.
        min_extent_mm: smallest bounding-box diagonal of an outline.
        min_angle_deg: smallest angular extent of an outline about its own centre.
    """

    working_radius_mm: float | None = None
    spike_mm: float = 1.0
    consensus_mm: float = 1.0
    agree_mm: float = 1.0
    min_points: int = 30
    min_views: int = 2
    min_view_points: int = 5
    min_extent_mm: float = 2.0
    min_angle_deg: float = 60.0


@dataclass
class Rejected:
    """How many points each test removed (all sections)."""

    outside_volume: int = 0
    spikes: int = 0
    view_consensus: int = 0
    unsupported_clusters: int = 0
    clusters: int = 0

    @property
    def points(self) -> int:
        """Return the total number of points removed."""
        return self.outside_volume + self.spikes + self.view_consensus + self.unsupported_clusters

    def add(self, other: Rejected) -> None:
        """Add another count to this one."""
        for name in self.__dataclass_fields__:
            setattr(self, name, getattr(self, name) + getattr(other, name))

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form."""
        return {**self.__dict__, "points": self.points}


def spike_mask(points: np.ndarray, spike_mm: float, window: int = SPIKE_WINDOW) -> np.ndarray:
    """Return True for points further than ``spike_mm`` from their stripe's local median."""
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    if len(pts) < window:
        return np.zeros(len(pts), dtype=bool)
    med = ndimage.median_filter(pts, size=(window, 1), mode="nearest")
    return np.hypot(*(pts - med).T) > spike_mm


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
    key = cell[:, 0] * height + cell[:, 1]
    order = np.argsort(key, kind="stable")
    keys, start = np.unique(key[order], return_index=True)
    lo = np.minimum.reduceat(views[order], start)
    hi = np.maximum.reduceat(views[order], start)
    confirmed = np.zeros(len(points), dtype=bool)
    for dx, dy in _neighbour_offsets():
        probe = key + dx * height + dy
        at = np.minimum(np.searchsorted(keys, probe), len(keys) - 1)
        hit = keys[at] == probe
        confirmed |= hit & ((lo[at] != views) | (hi[at] != views))
    return confirmed


def contradicted(
    points: np.ndarray, confirmed: np.ndarray, consensus_mm: float, agree_mm: float
) -> np.ndarray:
    """Return True for unconfirmed points whose sector's confirmed points agree far away.

    Sectors of ``SECTOR_DEG`` about the axis (the object frame's origin). A sector's
    confirmed points are seen by at least two views; if their radii span at most
    ``agree_mm`` they agree, and an unconfirmed point more than ``consensus_mm`` from
    their range contradicts them.
    """
    ang = np.degrees(np.arctan2(points[:, 1], points[:, 0])) + 180.0
    sector = np.minimum((ang / SECTOR_DEG).astype(np.int64), int(360.0 / SECTOR_DEG) - 1)
    radius = np.hypot(points[:, 0], points[:, 1])
    n_sectors = int(360.0 / SECTOR_DEG)
    r_min = np.full(n_sectors, np.inf)
    r_max = np.full(n_sectors, -np.inf)
    np.minimum.at(r_min, sector[confirmed], radius[confirmed])
    np.maximum.at(r_max, sector[confirmed], radius[confirmed])
    s, r = sector, radius
    agreed = np.isfinite(r_min[s]) & (r_max[s] - r_min[s] <= agree_mm)
    far = (r < r_min[s] - consensus_mm) | (r > r_max[s] + consensus_mm)
    return ~confirmed & agreed & far


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
    points: np.ndarray, views: np.ndarray, labels: np.ndarray, count: int, rules: OutlierRules
) -> np.ndarray:
    """Return True for each cluster that is well enough supported to be an outline."""
    n_views = int(views.max()) + 1 if len(views) else 1
    sizes = np.bincount(labels, minlength=count)
    per_view = np.bincount(labels * n_views + views, minlength=count * n_views)
    seen_by = (per_view.reshape(count, n_views) >= rules.min_view_points).sum(axis=1)
    lo = np.full((count, 2), np.inf)
    hi = np.full((count, 2), -np.inf)
    np.minimum.at(lo, labels, points)
    np.maximum.at(hi, labels, points)
    extent = np.hypot(*(hi - lo).T)
    sums = np.stack([np.bincount(labels, points[:, k], count) for k in (0, 1)], 1)
    centre = sums / np.maximum(sizes, 1)[:, None]
    d = points - centre[labels]
    n_bins = int(360.0 / EXTENT_BIN_DEG)
    angle_bin = ((np.arctan2(d[:, 1], d[:, 0]) + np.pi) / (2 * np.pi) * n_bins).astype(np.int64)
    occupied = np.zeros(count * n_bins, dtype=bool)
    occupied[labels * n_bins + np.minimum(angle_bin, n_bins - 1)] = True
    angle_deg = occupied.reshape(count, n_bins).sum(axis=1) * EXTENT_BIN_DEG
    return (
        (sizes >= rules.min_points)
        & (seen_by >= rules.min_views)
        & (extent >= rules.min_extent_mm)
        & (angle_deg >= rules.min_angle_deg)
    )


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
        One list of per-view pieces per outline (most points first; pieces keep their
        stripe order), and the counts of points rejected.
    """
    rejected = Rejected()
    segs = [np.asarray(p, dtype=float).reshape(-1, 2) for p in pieces]
    segs = [s for s in segs if len(s)]
    if not segs:
        return [], rejected
    pts = np.concatenate(segs)
    views = np.repeat(np.arange(len(segs)), [len(s) for s in segs])
    keep = np.ones(len(pts), dtype=bool)
    if rules.working_radius_mm is not None:
        keep = np.hypot(pts[:, 0], pts[:, 1]) <= rules.working_radius_mm
        rejected.outside_volume = int((~keep).sum())
    spikes = np.concatenate([spike_mask(s, rules.spike_mm) for s in segs]) & keep
    rejected.spikes = int(spikes.sum())
    keep &= ~spikes
    pts, views = pts[keep], views[keep]
    confirmed = confirmed_by_other_views(pts, views, rules.consensus_mm)
    bad = contradicted(pts, confirmed, rules.consensus_mm, rules.agree_mm)
    rejected.view_consensus = int(bad.sum())
    pts, views = pts[~bad], views[~bad]
    labels, count = label_clusters(pts, gap_mm)
    if count == 0:
        return [], rejected
    good = cluster_support(pts, views, labels, count, rules)
    rejected.clusters = int((~good).sum())
    rejected.unsupported_clusters = int((~good[labels]).sum())
    sizes = np.bincount(labels, minlength=count)
    outlines = []
    for label in np.argsort(-sizes, kind="stable"):
        if not good[label]:
            continue
        mine = labels == label
        owners = views[mine]
        mine_pts = pts[mine]
        outlines.append([mine_pts[owners == v] for v in np.unique(owners)])
    return outlines, rejected
