"""Ground truth for accuracy: distances to the true surface and the surface a scan can see.

How the host's output frame relates to the simulator's object frame. The host writes
``raw_points.ply`` and ``points.ply`` as ``q = C_f Rz(-theta)(p - a)`` with ``z`` the
commanded section height (``assembly.to_object_frame``, ``pipeline.assemble``):

- axis origin: ``a`` is the turntable axis the host estimated from the calibration
  cylinder (``axis.py``), not the rig's true axis, so the frame is shifted by that
  estimate's error;
- angle zero: ``theta`` is the host's model of the true angle (commanded angle, with the
  fitted angle scale of the joint axis fit); the simulator places the object at the
  mechanics' true angle, so the frame is turned by the true angle at the home position
  (the eccentric gear of ``Mechanics.harsh`` makes it ~0.1 degree) plus what the angle
  model misses per view;
- z origin: the host uses the commanded lift height, the simulator cuts the object at the
  true one (lift scale error and jitter), so the frame's z is off by the lift's error at
  the first section (a few micrometres) and stretched by its scale error;
- the object frame itself is the simulator's (``objects.py``): origin on the true axis
  at the first section's height, so no offset is added on either side.

So the two frames agree up to a rotation about z and a translation, which is what a
calibrated scanner cannot know (where the subject stood, where the turntable's zero was)
and not a shape error. :func:`scan_accuracy` reports every figure both ``direct`` (no
alignment: the frame error counts as error) and ``aligned`` (after the best-fit rotation
about z and shift in x and y, fitted to the inliers; z is left as it is, see
:func:`align_about_axis`). The acceptance figures of issue #10 are the ``aligned`` ones:
they measure shape, which is what a biomedical user of a turntable scanner gets; such a
rigid fit of three parameters cannot hide
per-view misregistration, noise points or a wrong scale, only where the frame starts.

Needs scipy (installed with the host and the test tools); the device never imports this.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from lamina_device.sim.axes import Mechanics
from lamina_device.sim.objects import (
    Cylinder,
    Ellipsoid,
    SceneObject,
    TriangleMesh,
    section_curves,
)
from lamina_device.sim.render import SimScene, laser_reaches
from lamina_shared.types import Segment, from_first_turn

__all__ = [
    "COVERAGE_MM",
    "OUTLIER_MM",
    "Alignment",
    "ScanAccuracy",
    "SurfaceErrors",
    "TrueSurface",
    "align_about_axis",
    "coverage",
    "lit_and_seen_points",
    "scan_accuracy",
    "surface_distance_mm",
]

OUTLIER_MM = 1.0
"""A scanned point further than this from the true surface is noise (issue #10)."""
COVERAGE_MM = 0.25
"""A lit-and-seen surface point counts as recovered within this distance of the scan."""
_SAMPLE_MM = 1.0  # spacing of the triangle samples that find candidate triangles
_SEEN_TOL_MM = 0.01  # a camera ray may stop this much short of the point it looks at


# ----------------------------------------------------------------------------- distances


def _closest_on_cylinder(c: Cylinder, p: np.ndarray) -> np.ndarray:
    """Return the closest points on a closed cylinder's wall and caps (exact)."""
    r = c.diameter_mm / 2.0
    z0, z1 = c.z_mm, c.z_mm + c.height_mm
    d = p[:, :2] - np.array([c.x_mm, c.y_mm])
    rho = np.hypot(d[:, 0], d[:, 1])
    unit = np.where(rho[:, None] > 0.0, d / np.maximum(rho, 1e-300)[:, None], [1.0, 0.0])
    centre = np.array([c.x_mm, c.y_mm])
    wall = np.column_stack([centre + r * unit, np.clip(p[:, 2], z0, z1)])
    inner = centre + np.minimum(rho, r)[:, None] * unit
    caps = [np.column_stack([inner, np.full(len(p), z)]) for z in (z0, z1)]
    candidates = np.stack([wall, *caps])
    dist = np.linalg.norm(candidates - p[None], axis=2)
    return candidates[np.argmin(dist, axis=0), np.arange(len(p))]


def _closest_on_ellipsoid(e: Ellipsoid, p: np.ndarray, iterations: int = 200) -> np.ndarray:
    """Return the closest points on an ellipsoid by bisection on the Lagrange multiplier.

    The closest point is ``x_i = a_i^2 y_i / (a_i^2 + t)`` where t solves
    ``sum (a_i y_i / (a_i^2 + t))^2 = 1``, decreasing in t above ``-min a_i^2``.
    """
    axes = np.asarray(e.semi_axes_mm, dtype=float)
    c, s = math.cos(math.radians(e.yaw_deg)), math.sin(math.radians(e.yaw_deg))
    rot = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    centre = np.array([e.x_mm, e.y_mm, e.z_mm])
    y = (p - centre) @ rot  # into the ellipsoid's own axes
    # A zero coordinate (a point inside on a symmetry plane) has no root above -min a^2;
    # a nudge of 1e-7 of the size picks the limit, which is the right closest point.
    tiny = 1e-7 * axes.max()
    y = np.where(np.abs(y) < tiny, np.where(y < 0.0, -tiny, tiny), y)
    a2 = axes**2
    lo = np.full(len(p), -a2.min() * (1.0 - 1e-12))
    hi = axes.max() * np.linalg.norm(y, axis=1) + a2.max()
    for _ in range(iterations):
        mid = 0.5 * (lo + hi)
        f = np.sum((axes * y / (a2 + mid[:, None])) ** 2, axis=1) - 1.0
        lo, hi = np.where(f > 0.0, mid, lo), np.where(f > 0.0, hi, mid)
    x = a2 * y / (a2 + (0.5 * (lo + hi))[:, None])
    return x @ rot.T + centre


def _closest_on_triangles(p: np.ndarray, tri: np.ndarray) -> np.ndarray:
    """Return the closest point of each triangle (P, 3, 3) to its paired point (P, 3).

    Ericson, Real-Time Collision Detection, 5.1.5: Voronoi regions of the vertices,
    edges and face, vectorised.
    """
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    ab, ac, ap = b - a, c - a, p - a

    def dot(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.einsum("ij,ij->i", u, v)

    d1, d2 = dot(ab, ap), dot(ac, ap)
    bp = p - b
    d3, d4 = dot(ab, bp), dot(ac, bp)
    cp = p - c
    d5, d6 = dot(ab, cp), dot(ac, cp)
    va = d3 * d6 - d5 * d4
    vb = d5 * d2 - d1 * d6
    vc = d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v_face, w_face = vb * denom, vc * denom
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    out = a + v_face[:, None] * ab + w_face[:, None] * ac
    regions = [  # later entries win: checked in reverse order of Ericson's early returns
        ((va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0), b + t_bc[:, None] * (c - b)),
        ((vb <= 0) & (d2 >= 0) & (d6 <= 0), a + t_ac[:, None] * ac),
        ((d6 >= 0) & (d5 <= d6), c),
        ((vc <= 0) & (d1 >= 0) & (d3 <= 0), a + t_ab[:, None] * ab),
        ((d3 >= 0) & (d4 <= d3), b),
        ((d1 <= 0) & (d2 <= 0), a),
    ]
    for mask, value in regions:
        out = np.where(mask[:, None], value, out)
    return out


@dataclass(frozen=True, eq=False)
class _MeshIndex:
    """Surface samples of a mesh, each tagged with its triangle, in a k-d tree.

    ``spacing_mm`` bounds how far any surface point lies from a sample of its own triangle.
    """

    tree: cKDTree
    owner: np.ndarray
    spacing_mm: float

    @classmethod
    def build(cls, tri: np.ndarray, edge_mm: float = _SAMPLE_MM) -> _MeshIndex:
        """Split every triangle into sub-triangles of edges <= ``edge_mm``; keep their centroids.

        Every point of a triangle is then within 2/3 ``edge_mm`` of one of its samples
        (a centroid is 2/3 of a median from each corner).
        """
        edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
        steps = np.maximum(1, np.ceil(edges / edge_mm).astype(int))
        samples, owner = [], []
        for n in np.unique(steps):
            faces = np.flatnonzero(steps == n)
            i, j = np.meshgrid(np.arange(n), np.arange(n), indexing="ij")
            up = np.column_stack([i[i + j <= n - 1], j[i + j <= n - 1]]) + 1.0 / 3.0
            down = np.column_stack([i[i + j <= n - 2], j[i + j <= n - 2]]) + 2.0 / 3.0
            w = np.concatenate([up, down]) / n  # barycentric weights of corners b and c
            t = tri[faces]
            pts = t[:, None, 0] + w[None, :, :1] * (t[:, None, 1] - t[:, None, 0])
            pts = pts + w[None, :, 1:] * (t[:, None, 2] - t[:, None, 0])
            samples.append(pts.reshape(-1, 3))
            owner.append(np.repeat(faces, len(w)))
        return cls(cKDTree(np.concatenate(samples)), np.concatenate(owner), 2.0 * edge_mm / 3.0)


def _closest_on_mesh(
    mesh: TriangleMesh, index: _MeshIndex, p: np.ndarray, chunk: int = 4096
) -> np.ndarray:
    """Return the exact closest points on a triangle mesh.

    The nearest surface sample gives an upper bound u on the distance; the true closest
    point has a sample of its own triangle within the sample spacing h, so every triangle
    with a sample within u + h of the point is a candidate, and the nearest candidate
    point (exact point-to-triangle) is the answer.
    """
    tri = mesh.triangles
    out = np.empty_like(p)
    for start in range(0, len(p), chunk):
        q = p[start : start + chunk]
        upper, _ = index.tree.query(q)
        near = index.tree.query_ball_point(q, upper + index.spacing_mm)
        counts = np.fromiter(map(len, near), int, len(near))
        sample = np.fromiter(itertools.chain.from_iterable(near), int, int(counts.sum()))
        point = np.repeat(np.arange(len(q)), counts)
        key = np.unique(point * len(tri) + index.owner[sample])  # sorted by point
        pt, face = key // len(tri), key % len(tri)
        cand = _closest_on_triangles(q[pt], tri[face])
        dist = np.linalg.norm(cand - q[pt], axis=1)
        order = np.lexsort((dist, pt))  # by point, nearest first
        first = np.unique(pt[order], return_index=True)[1]
        out[start : start + chunk] = cand[order[first]]
    return out


class TrueSurface:
    """A scene object's exact surface: closest points and distances (analytic or per triangle)."""

    def __init__(self, obj: SceneObject) -> None:
        """Prepare ``obj`` (a mesh gets its sample index once, here)."""
        if not isinstance(obj, Cylinder | Ellipsoid | TriangleMesh):
            raise TypeError(f"no true surface distance for {type(obj).__name__}")
        self.obj = obj
        self._index = _MeshIndex.build(obj.triangles) if isinstance(obj, TriangleMesh) else None

    def closest_points(self, points: np.ndarray) -> np.ndarray:
        """Return the closest surface point to each object-frame point (N, 3)."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        if len(p) == 0:
            return p.copy()
        if isinstance(self.obj, Cylinder):
            return _closest_on_cylinder(self.obj, p)
        if isinstance(self.obj, Ellipsoid):
            return _closest_on_ellipsoid(self.obj, p)
        assert isinstance(self.obj, TriangleMesh) and self._index is not None
        return _closest_on_mesh(self.obj, self._index, p)

    def distance_mm(self, points: np.ndarray) -> np.ndarray:
        """Return the unsigned distance (N,) of object-frame points (N, 3) to the surface."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        return np.asarray(np.linalg.norm(self.closest_points(p) - p, axis=1))


def surface_distance_mm(obj: SceneObject, points: np.ndarray) -> np.ndarray:
    """Return the unsigned distance (N,) of object-frame points (N, 3) to ``obj``'s surface."""
    return TrueSurface(obj).distance_mm(points)


# ----------------------------------------------------------------------------- alignment


def _rotate_z(points: np.ndarray, angle_rad: float) -> np.ndarray:
    """Rotate (N, 3) points about the z axis."""
    c, s = math.cos(angle_rad), math.sin(angle_rad)
    return points @ np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True)
class Alignment:
    """A rotation about z (about the turntable axis) then a shift in x and y, fitted by ICP."""

    angle_deg: float
    shift_mm: tuple[float, float]

    def apply(self, points: np.ndarray) -> np.ndarray:
        """Return ``points`` (N, 3) moved by this alignment."""
        p = np.asarray(points, dtype=float).reshape(-1, 3)
        return _rotate_z(p, math.radians(self.angle_deg)) + np.array([*self.shift_mm, 0.0])


def align_about_axis(
    surface: TrueSurface, points: np.ndarray, inlier_mm: float = OUTLIER_MM, iterations: int = 30
) -> Alignment:
    """Fit the rotation about z and the x, y shift that best lay ``points`` on the surface.

    Point-to-plane ICP (the plane through each point's closest surface point, normal
    to the offset) on the points within ``inlier_mm`` of the surface (noise points would
    pull the fit), linearised in the small angle and repeated to convergence.
    The z shift is left out: the frames' z origins differ by the lift's error at the
    first section (micrometres), while a z shift of noisy points along near-vertical
    walls is barely constrained and would slide into a false optimum.
    """
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    angle, shift = 0.0, np.zeros(3)
    for _ in range(iterations):
        moved = _rotate_z(p, angle) + shift
        target = surface.closest_points(moved)
        offset = target - moved
        dist = np.linalg.norm(offset, axis=1)
        keep = (dist < inlier_mm) & (dist > 1e-9)
        if keep.sum() < 3:
            break
        m, r = moved[keep], offset[keep]
        n = r / dist[keep, None]
        jac = np.column_stack([n[:, 1] * m[:, 0] - n[:, 0] * m[:, 1], n[:, 0], n[:, 1]])
        step = np.linalg.lstsq(jac, dist[keep], rcond=None)[0]
        angle += float(step[0])
        shift = _rotate_z(shift[None], float(step[0]))[0] + np.array([step[1], step[2], 0.0])
        if abs(step[0]) < 1e-8 and np.abs(step[1:]).max() < 1e-6:
            break
    return Alignment(math.degrees(angle), (float(shift[0]), float(shift[1])))


# ----------------------------------------------------------------------------- coverage


def _resample(
    polygon: np.ndarray, spacing_mm: float, closed: bool = True
) -> tuple[np.ndarray, np.ndarray]:
    """Return points at most ``spacing_mm`` apart along a polygon, with their normals.

    Normals point outward for counter-clockwise polygons. An open chain (``closed``
    False) is sampled from its first point to its last, without a closing edge.
    """
    a, b = polygon, np.roll(polygon, -1, axis=0)
    if not closed:
        a, b = polygon[:-1], polygon[1:]
    length = np.linalg.norm(b - a, axis=1)
    n = np.maximum(1, np.ceil(length / spacing_mm).astype(int))
    owner = np.repeat(np.arange(len(a)), n)
    t = (np.arange(owner.size) - np.repeat(np.cumsum(n) - n, n)) / np.repeat(n, n)
    pts = a[owner] + t[:, None] * (b - a)[owner]
    tangent = (b - a)[owner] / np.maximum(length[owner], 1e-300)[:, None]
    return pts, np.column_stack([tangent[:, 1], -tangent[:, 0]])


def segment_views(segments: list[Segment]) -> list[tuple[float, float]]:
    """Return each segment's commanded height and step count (its angle plus its whole
    turns, counted from the first turn among them): the views of one scan as the
    simulated table took them, for :func:`lit_and_seen_points`. The count, not the angle
    within the turn, is where the simulated gear put the object
    (:attr:`Mechanics.angle_error_accumulates`), over the turns since it was put on."""
    return [(s.z_mm, s.count_deg) for s in from_first_turn(segments)]


def lit_and_seen_points(
    scene: SimScene,
    views: Iterable[tuple[float, float]],
    mechanics: Mechanics,
    spacing_mm: float = 0.05,
) -> np.ndarray:
    """Return the object-frame surface points (M, 3) the sheet's centre lit and the camera saw.

    For each commanded ``(z_mm, angle_deg)`` view (the angle is the table's step count
    since power-up, unwrapped: :func:`segment_views`) the object is where the mechanics
    really put it; the true section there is sampled every ``spacing_mm``, and a sample counts
    when the laser reaches it within the sheet (nothing of the section in between) and
    the camera's ray to it meets nothing first, and it lies inside the image.
    """
    rig, obj = scene.rig, scene.obj
    if obj is None:
        raise ValueError("the scene has no object to measure")
    w, h = rig.image_size
    found = []
    for z_cmd, angle_cmd in views:
        z, angle = mechanics.true_z_mm(z_cmd), mechanics.true_angle_deg(angle_cmd)
        curves = section_curves(obj, z)
        if not curves:
            continue
        polygons, closed = [c.points for c in curves], [c.closed for c in curves]
        q = np.concatenate([_resample(c.points, spacing_mm, c.closed)[0] for c in curves])
        th = math.radians(angle)
        to_obj = np.array([[math.cos(th), math.sin(th)], [-math.sin(th), math.cos(th)]])
        axis = np.asarray(rig.axis_xy_mm)
        src = to_obj @ (np.asarray(rig.laser_source_xy_mm) - axis)
        lit = laser_reaches(src, q, polygons, np.full(len(q), 1e-3), closed)
        world = rig.object_to_world(q, angle, z)
        uv = rig.project(world)
        inside = (uv[:, 0] >= 0) & (uv[:, 0] <= w - 1) & (uv[:, 1] >= 0) & (uv[:, 1] <= h - 1)
        cand = np.flatnonzero(lit & inside)
        cam = rig.camera_centre_mm
        cam_obj = np.array([*(to_obj @ (cam[:2] - axis)), cam[2] + z])
        q3 = np.column_stack([q[cand], np.full(len(cand), z)])
        ray = q3 - cam_obj
        dist = np.linalg.norm(ray, axis=1)
        t, _ = obj.raycast(cam_obj, ray / dist[:, None])
        seen = t >= dist - _SEEN_TOL_MM
        found.append(q3[seen])
    return np.concatenate(found) if found else np.empty((0, 3))


def coverage(truth_points: np.ndarray, scanned: np.ndarray, tol_mm: float = COVERAGE_MM) -> float:
    """Return the fraction of ``truth_points`` with a scanned point within ``tol_mm``."""
    truth = np.asarray(truth_points, dtype=float).reshape(-1, 3)
    scan = np.asarray(scanned, dtype=float).reshape(-1, 3)
    if len(truth) == 0:
        raise ValueError("no lit-and-seen surface to cover")
    if len(scan) == 0:
        return 0.0
    d, _ = cKDTree(scan).query(truth, distance_upper_bound=tol_mm)
    return float(np.mean(np.isfinite(d)))


# ----------------------------------------------------------------------------- summary


@dataclass(frozen=True)
class SurfaceErrors:
    """Issue #10's figures for one frame (direct or aligned)."""

    outlier_percent: float  # raw points further than OUTLIER_MM from the surface
    mean_distance_mm: float  # mean distance of the contour points (points.ply)
    coverage_percent: float  # lit-and-seen surface within COVERAGE_MM of the contours


@dataclass(frozen=True)
class ScanAccuracy:
    """A scan against the truth: direct, and after the 3-parameter alignment."""

    direct: SurfaceErrors
    aligned: SurfaceErrors
    alignment: Alignment
    raw_points: int
    contour_points: int
    lit_and_seen_points: int


def _errors(
    surface: TrueSurface, raw: np.ndarray, contour: np.ndarray, lit: np.ndarray
) -> SurfaceErrors:
    """Return the three figures for point sets already in the object frame."""
    raw_d = surface.distance_mm(raw)
    contour_d = surface.distance_mm(contour)
    return SurfaceErrors(
        100.0 * float(np.mean(raw_d > OUTLIER_MM)) if len(raw_d) else math.nan,
        float(np.mean(contour_d)) if len(contour_d) else math.nan,
        100.0 * coverage(lit, contour),
    )


def scan_accuracy(
    obj: SceneObject, raw_points: np.ndarray, contour_points: np.ndarray, lit_points: np.ndarray
) -> ScanAccuracy:
    """Compare a scan's raw and contour points (host output frame) with the true surface.

    ``lit_points`` come from :func:`lit_and_seen_points`. The alignment is fitted to the
    contour points and applied to both point sets.
    """
    raw = np.asarray(raw_points, dtype=float).reshape(-1, 3)
    contour = np.asarray(contour_points, dtype=float).reshape(-1, 3)
    surface = TrueSurface(obj)
    alignment = align_about_axis(surface, contour)
    return ScanAccuracy(
        _errors(surface, raw, contour, lit_points),
        _errors(surface, alignment.apply(raw), alignment.apply(contour), lit_points),
        alignment,
        len(raw),
        len(contour),
        len(lit_points),
    )
