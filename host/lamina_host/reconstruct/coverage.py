"""How much of a section's circumference the views really saw (issue #10).

EFD closes any outline (thesis 6.4), also across a stretch no view saw, where it invents a
curve. So each outline's angular coverage is measured about its own centre, and every
stretch of contour in an unseen gap is flagged as estimated. The centre is the outline's
algebraic (Taubin) circle centre, which stays near the middle of the whole outline when
only part of it was seen; the points' mean would move towards the seen side and make a
half-seen outline look two-thirds covered.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from lamina_host.reconstruct.axis import taubin_circle
from lamina_host.reconstruct.calibration import CalibrationError
from lamina_host.reconstruct.outliers import MAX_EXTENT_POINTS, group_range
from lamina_host.reconstruct.outline_frame import OutlineFrame, unwrap_angles

COVERAGE_BIN_DEG = 2.0
"""Angular bins about the outline's centre; a bin with a measured point is covered."""

MEASURED_TOLERANCE_MM = 0.2
"""A contour sample is measured when its bin is covered and its radius lies within this
of the bin's measured radii; a curve bridging a gap may cross covered bins elsewhere (a
chord across a wide gap passes near the centre)."""


@dataclass(frozen=True, eq=False)
class Coverage:
    """Which bins along an outline hold measured points of it.

    The bins are of the position ``t`` in ``frame`` (:mod:`.outline_frame`): angular bins
    about the centre of a star-shaped outline, stretches of equal length along the
    reference curve of another. ``radius_lo_mm`` and ``radius_hi_mm`` are each bin's
    smallest and largest measured offset (radius; inf and -inf where nothing was measured).
    """

    frame: OutlineFrame
    covered: np.ndarray
    radius_lo_mm: np.ndarray
    radius_hi_mm: np.ndarray

    @property
    def centre_mm(self) -> tuple[float, float]:
        """Return the centre of the outline's frame."""
        return float(self.frame.centre_mm[0]), float(self.frame.centre_mm[1])

    @property
    def bin_deg(self) -> float:
        """Return the width of one bin in degrees."""
        return 360.0 / len(self.covered)

    @property
    def fraction(self) -> float:
        """Return the covered share of the circumference (0..1)."""
        return float(self.covered.mean())

    def gaps_deg(self) -> list[tuple[float, float]]:
        """Return each unseen gap as (start angle, width) in degrees, start in [-180, 180)."""
        if self.covered.all():
            return []
        if not self.covered.any():
            return [(-180.0, 360.0)]
        n = len(self.covered)
        # Start the walk just after a covered bin so no gap is cut at the wrap.
        first = int(np.flatnonzero(self.covered)[-1]) + 1
        rolled = np.roll(self.covered, -first)
        edges = np.diff(np.concatenate([[1], rolled.astype(np.int8), [1]]))
        starts, ends = np.flatnonzero(edges == -1), np.flatnonzero(edges == 1)
        return [
            ((((s + first) % n) * self.bin_deg) - 180.0, (e - s) * self.bin_deg)
            for s, e in zip(starts, ends, strict=True)
        ]

    @property
    def largest_gap_deg(self) -> float:
        """Return the widest unseen gap in degrees (0 when fully covered)."""
        return max((w for _, w in self.gaps_deg()), default=0.0)

    def bins_of(self, points: np.ndarray) -> np.ndarray:
        """Return the bin index of each (N, 2) point along the outline."""
        return self._bins(self.frame.to_local(points)[0])

    def _bins(self, t: np.ndarray) -> np.ndarray:
        """Return the bin index of each position ``t`` (radians)."""
        n = len(self.covered)
        idx = ((np.asarray(t) + np.pi) / (2.0 * np.pi) * n).astype(np.int64)
        return np.clip(idx, 0, n - 1)

    def unseen(self, points: np.ndarray, tolerance_mm: float = MEASURED_TOLERANCE_MM) -> np.ndarray:
        """Return True for points not backed by a measurement (estimated): in an unseen gap,
        or further than ``tolerance_mm`` in radius from what was measured in their bin."""
        t, r = self.frame.to_local(points)
        b = self._bins(t)
        off = (r < self.radius_lo_mm[b] - tolerance_mm) | (r > self.radius_hi_mm[b] + tolerance_mm)
        return ~self.covered[b] | off

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form."""
        return {
            "centre_mm": list(self.centre_mm),
            "fraction": self.fraction,
            "largest_gap_deg": self.largest_gap_deg,
            "gaps_deg": [[start, width] for start, width in self.gaps_deg()],
        }


MEASURED_REACH_MM = 1.0
"""A contour sample further than this from every measured point is estimated, whatever
its bin says: a curve closing an outline may pass alongside a measured stretch it is
not (the way back across a bent strip's other face). One view's points along a stripe
lie at most ``CONTINUOUS_STEP_MM`` apart where they count as seeing the surface."""


def estimated_samples(coverage: Coverage, contour: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Return True for the contour samples no measurement backs (flagged estimated).

    Args:
        coverage: the outline's coverage (its unseen gaps and measured offsets per bin).
        contour: (K, 2) contour samples in mm.
        points: (N, 2) the outline's measured points in mm.
    """
    from scipy.spatial import cKDTree  # deferred: keeps the module's import light

    estimated = coverage.unseen(contour)
    claimed = np.flatnonzero(~estimated)
    if len(claimed) and len(points):
        reach, _ = cKDTree(points).query(contour[claimed], distance_upper_bound=MEASURED_REACH_MM)
        estimated[claimed[~np.isfinite(reach)]] = True
    return estimated


def outline_centre(points: np.ndarray) -> np.ndarray:
    """Return the centre about which an outline's coverage is measured (module docstring).

    The Taubin circle centre, unless the points are (nearly) collinear or that centre lies
    outside the points' bounding box, or the points taken in angle about it zigzag
    across the outline where about their mean they do not (``ORDER_SLACK``): an outline
    curling in on itself can draw the circle's centre next to its inner branch, about
    which the angles of the two branches interleave. The mean is used instead.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    mean = pts.mean(axis=0)
    try:
        cx, cy, _ = taubin_circle(pts[:: max(1, len(pts) // MAX_EXTENT_POINTS)])
    except CalibrationError:
        return mean
    centre = np.array([cx, cy])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    if not np.isfinite(centre).all() or np.any(centre < lo) or np.any(centre > hi):
        return mean
    if _angular_path_mm(pts, centre) > ORDER_SLACK * _angular_path_mm(pts, mean):
        return mean
    return centre


ORDER_SLACK = 1.5
"""How much longer the path through an outline's points in angle order about the circle's
centre may be than about their mean before the mean is the better centre."""


def _angular_path_mm(points: np.ndarray, centre: np.ndarray) -> float:
    """Return the length of the path through ``points`` in angle order about ``centre``."""
    d = points - centre
    ordered = points[np.argsort(np.arctan2(d[:, 1], d[:, 0]), kind="stable")]
    return float(np.hypot(*np.diff(ordered, axis=0).T).sum())


CONTINUOUS_STEP_MM = 0.75
"""Two consecutive points of one view's stripe closer than this saw the surface between
them: at a grazing end a stripe's points thin out, each column spanning more of the
outline, and the bins they skip are not a gap."""


def measure_coverage(
    points: np.ndarray,
    frame: OutlineFrame | None = None,
    pieces: list[np.ndarray] | None = None,
    bin_deg: float = COVERAGE_BIN_DEG,
) -> Coverage:
    """Return the coverage of an outline's measured points along it.

    A bin is covered when it holds a point, or when consecutive points of one view's
    stripe (``pieces``) no further apart than ``CONTINUOUS_STEP_MM`` lie either side of
    it; a single empty bin between covered ones is counted as covered (sampling, not a
    gap).

    Args:
        points: (N, 2) measured points of one outline.
        frame: the outline's frame when it is not star-shaped (a reference curve); None or
            a polar frame: angular bins about :func:`outline_centre`.
        pieces: the views' stripes the points came from, each in stripe order.
        bin_deg: the bins' width, degrees of a turn.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    if not len(pts) or not np.isfinite(pts).all():
        raise CalibrationError(
            f"an outline of {len(pts)} point(s), not all finite, has no coverage to measure"
        )
    n = round(360.0 / bin_deg)
    if frame is None or frame.polar:
        frame = OutlineFrame(outline_centre(pts))
    empty = np.zeros(n)
    probe = Coverage(frame, empty > 0, empty, empty)
    t, offset = frame.to_local(pts)
    bins = probe._bins(t)
    lo, hi = group_range(offset, bins, n)
    for piece in pieces or []:
        _cover_steps(probe, np.asarray(piece, dtype=float).reshape(-1, 2), lo, hi)
    covered = np.isfinite(lo)
    hole = ~covered & np.roll(covered, 1) & np.roll(covered, -1)
    lo[hole] = np.minimum(np.roll(lo, 1), np.roll(lo, -1))[hole]
    hi[hole] = np.maximum(np.roll(hi, 1), np.roll(hi, -1))[hole]
    return Coverage(frame, covered | hole, lo, hi)


def _cover_steps(probe: Coverage, piece: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> None:
    """Extend ``lo``/``hi`` over the bins a stripe's short steps skip (in place)."""
    if len(piece) < 2:
        return
    step = np.hypot(*np.diff(piece, axis=0).T)
    t, offset = probe.frame.to_local(piece)
    b = probe._bins(t)
    n = len(probe.covered)
    ahead = (b[1:] - b[:-1]) % n  # bins forward from one point to the next
    skip = np.minimum(ahead, n - ahead) > 1
    for k in np.flatnonzero(skip & (step <= CONTINUOUS_STEP_MM)):
        first, width = (b[k], ahead[k]) if ahead[k] <= n // 2 else (b[k + 1], n - ahead[k])
        between = (first + np.arange(1, width)) % n
        lo[between] = np.minimum(lo[between], min(offset[k], offset[k + 1]))
        hi[between] = np.maximum(hi[between], max(offset[k], offset[k + 1]))


BRIDGE_MIN_GAP_DEG = 4.0
"""Unseen gaps narrower than this (two coverage bins) are left to the EFD to close."""

BRIDGE_SIDE_DEG = 10.0
"""Each side of a gap, the measured points this far from it give the bridge's end value
and slope (a parabola fitted to them)."""

BRIDGE_STEP_DEG = 0.5
"""Angular spacing of the samples of a bridge."""

BRIDGE_SLOPE_SPAN_DEG = 1.0
"""A side whose points span less angle than this gives the bridge its value, not a slope:
points bunched at one angle (a small blob, views repeating one point) carry no slope,
and a fit to them returned slopes of 1e12 mm per radian (a random limb-scale shape)."""

BRIDGE_REACH_MM = 1.0
"""A bridge's offset stays within the measured offsets' range widened by that range (at
least this): a safeguard, as wide as a bridge between sane sides ever swings."""


def _side(ang: np.ndarray, rad: np.ndarray) -> tuple[float, float]:
    """Return the value and slope at angle 0 of a parabola fitted to (ang, rad).

    A parabola, not a line: a line's slope is that of the window's middle, which on a
    curved outline tilts the bridge (0.2 mm over 20 degrees of a 30 x 22 mm ellipse).
    """
    if len(ang) < 2 or np.ptp(ang) < np.deg2rad(BRIDGE_SLOPE_SPAN_DEG):
        return float(np.mean(rad)), 0.0
    # Least squares on angles scaled to about 1 (a Vandermonde of raw radians is badly
    # conditioned); the rank it finds is what the points can carry.
    scale = float(np.max(np.abs(ang)))
    x = ang / scale
    degree = 2 if len(ang) >= 6 else 1
    coeffs = np.linalg.lstsq(np.vander(x, degree + 1), rad, rcond=None)[0]
    return float(coeffs[-1]), float(coeffs[-2]) / scale


def bridge_gaps(points: np.ndarray, frame: OutlineFrame) -> np.ndarray:
    """Return an outline's measured points with every unseen gap bridged from its own sides.

    In the outline's frame (polar about its centre when star-shaped), each gap between
    consecutive points wider than ``BRIDGE_MIN_GAP_DEG`` is spanned by a cubic Hermite
    curve of the offset (radius) over the position (angle) whose ends take the value and
    slope of a parabola fitted to the measured points within ``BRIDGE_SIDE_DEG`` on that
    side: the outline continues smoothly as it was seen arriving at the gap and leaving
    it. A chord, which EFD would draw, cuts inside a convex outline (by 2.4 mm over 36
    degrees of a 50 mm radius).

    Args:
        points: (N, 2) measured points of one outline in mm.
        frame: the frame the gaps are measured in (``Coverage.frame``).

    Returns:
        (M, 2) points, the measured ones and the bridges', in order along the outline.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    ang, rad = frame.to_local(pts)
    order = np.argsort(ang, kind="stable")
    pts, ang, rad = pts[order], ang[order], rad[order]
    if len(pts) < 4:
        return pts
    step = np.diff(np.append(ang, ang[0] + 2.0 * np.pi))
    side = np.deg2rad(BRIDGE_SIDE_DEG)
    reach = max(float(np.ptp(rad)), BRIDGE_REACH_MM)
    extra = []
    for k in np.flatnonzero(step > np.deg2rad(BRIDGE_MIN_GAP_DEG)):
        start, width = ang[k], step[k]
        # Angles relative to the gap's start, unwrapped: left side <= 0, right >= width.
        rel = np.mod(ang - start + np.pi, 2.0 * np.pi) - np.pi
        left = (rel <= 0.0) & (rel >= -side)
        rel_r = np.mod(ang - start, 2.0 * np.pi)
        right = (rel_r >= width - 1e-12) & (rel_r <= width + side)
        r0, s0 = _side(rel[left], rad[left])
        # All points at one angle leave one gap of a whole turn, its right side empty.
        r1, s1 = _side(rel_r[right] - width, rad[right]) if right.any() else (r0, s0)
        n = max(2, int(np.ceil(np.rad2deg(width) / BRIDGE_STEP_DEG)))
        t = np.arange(1, n) / n
        h00, h10 = 2 * t**3 - 3 * t**2 + 1, t**3 - 2 * t**2 + t
        h01, h11 = -2 * t**3 + 3 * t**2, t**3 - t**2
        r = h00 * r0 + h10 * width * s0 + h01 * r1 + h11 * width * s1
        # A bridge is a guess: it must not go much further out or in than what was seen.
        r = np.clip(r, rad.min() - reach, rad.max() + reach)
        a = start + t * width
        extra.append(np.stack([a, r], axis=1))
    if not extra:
        return pts
    bridged = np.concatenate(extra)
    bridged[:, 0] = np.mod(bridged[:, 0] + np.pi, 2.0 * np.pi) - np.pi
    merged_t = np.concatenate([ang, bridged[:, 0]])
    merged = np.concatenate([pts, frame.to_xy(bridged[:, 0], bridged[:, 1])])
    return merged[np.argsort(merged_t, kind="stable")]


def match_sides(points: np.ndarray, fill: np.ndarray, frame: OutlineFrame) -> np.ndarray:
    """Return ``fill`` (curve samples inside an outline's unseen gaps) moved to meet its sides.

    A neighbouring section's outline has this one's shape across the gap but not its
    size: a limb narrows between sections. Each gap's run of fill samples is shifted
    outwards by a ramp from the difference at the gap's one side to that at the other,
    each side's offset from a parabola fitted to the measured points within
    ``BRIDGE_SIDE_DEG`` of it (as :func:`bridge_gaps`), so the filled outline keeps the
    neighbour's shape and joins its own measured stretches without a step.

    Args:
        points: (N, 2) measured points of the outline.
        fill: (M, 2) curve samples inside its gaps.
        frame: the outline's frame (``Coverage.frame``).

    Returns:
        (M, 2) the fill samples, shifted along the frame's offset.
    """
    pts = np.asarray(points, dtype=float).reshape(-1, 2)
    fill = np.asarray(fill, dtype=float).reshape(-1, 2)
    if len(pts) < 4 or len(fill) < 2:
        return fill
    ang, rad = frame.to_local(pts)
    f_ang, f_rad = frame.to_local(fill)
    order = np.argsort(f_ang, kind="stable")
    f_ang, f_rad = f_ang[order], f_rad[order]
    # Runs of fill: a step wider than the fill's own spacing is measured outline between.
    spacing = np.median(np.diff(f_ang)) if len(f_ang) > 2 else np.pi
    cut = np.flatnonzero(np.diff(f_ang) > 4.0 * max(spacing, 1e-9)) + 1
    runs = np.split(np.arange(len(f_ang)), cut)
    if len(runs) > 1 and (f_ang[0] + 2.0 * np.pi - f_ang[-1]) <= 4.0 * max(spacing, 1e-9):
        runs = [np.concatenate([runs[-1], runs[0]]), *runs[1:-1]]  # one run across +-pi
    side = np.deg2rad(BRIDGE_SIDE_DEG)
    shifted = f_rad.copy()
    for run in runs:
        t = unwrap_angles(f_ang[run])
        start, end = t[0], t[-1]
        rel = np.mod(ang - start + np.pi, 2.0 * np.pi) - np.pi  # <= 0 before the run
        before = (rel < 0.0) & (rel >= -side)
        rel_end = np.mod(ang - end + np.pi, 2.0 * np.pi) - np.pi  # >= 0 after it
        after = (rel_end > 0.0) & (rel_end <= side)
        if not before.any() or not after.any():
            continue
        d0 = _side(rel[before], rad[before])[0] - f_rad[run[0]]
        d1 = _side(rel_end[after], rad[after])[0] - f_rad[run[-1]]
        u = (t - start) / (end - start) if end > start else np.zeros(len(t))
        shifted[run] = f_rad[run] + d0 + (d1 - d0) * u
    out = np.empty_like(fill)
    out[order] = frame.to_xy(f_ang, shifted)
    return out
