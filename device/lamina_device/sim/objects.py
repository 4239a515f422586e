"""Things that stand on the simulated turntable, with exact ray casts and true sections.

Every object lives in the *object frame* of ``docs/capture-format.md``: origin on
the turntable axis at the first section's laser height, ``z`` up, mm. Objects answer two
questions: where does a ray first meet me (for rendering) and what is my exact
cross-section at height ``z`` (for the laser-visibility test and as ground truth).
"""

from __future__ import annotations

import itertools
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = [
    "Cylinder",
    "Ellipsoid",
    "Revolved",
    "SceneObject",
    "SectionCurve",
    "TriangleMesh",
    "cylinder",
    "ellipsoid",
    "grooved_cylinder",
    "load_mesh",
    "section_curves",
    "section_edges",
    "sphere",
    "tilt_matrix",
]

OUTLINE_VERTICES = 4096
_EPS_T_MM = 1e-9  # hits closer than this to the origin are the origin's own surface
_INSIDE_EPS = 1e-12  # generous 2D inside test: the exact 3D test decides, this only culls
_PAIRS_PER_CHUNK = 250_000  # (ray, face) pairs tested at once: bounded memory, warm cache


@runtime_checkable
class SceneObject(Protocol):
    """A solid in the object frame that can be ray cast and sliced."""

    @property
    def name(self) -> str:
        """Return the object's short name (``cylinder``, ``mesh:hand``...)."""
        ...

    def raycast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the first hit distance t (N,) (inf on a miss) and outward unit normals (N, 3)."""
        ...

    def section_outline(self, z_mm: float) -> list[np.ndarray]:
        """Return the closed CCW cross-section polygons (K, 2) at height ``z_mm``."""
        ...


def _as_rays(origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Broadcast ray origins and directions to two (N, 3) float arrays."""
    d = np.atleast_2d(np.asarray(dirs, dtype=float))
    o = np.broadcast_to(np.asarray(origins, dtype=float), d.shape)
    return o, d


def _yaw_matrix(yaw_deg: float) -> np.ndarray:
    """Return the 3x3 rotation about +z by ``yaw_deg``."""
    c, s = math.cos(math.radians(yaw_deg)), math.sin(math.radians(yaw_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def tilt_matrix(tilt_deg: float, toward_deg: float) -> np.ndarray:
    """Return the 3x3 rotation that leans +z by ``tilt_deg`` towards azimuth ``toward_deg``.

    The rotation is about the horizontal axis at right angles to the azimuth, so a point
    on +z moves towards ``(cos toward, sin toward)`` and nothing turns about z.
    """
    t, d = math.radians(tilt_deg), math.radians(toward_deg)
    k = np.array([-math.sin(d), math.cos(d), 0.0])  # z x (cos d, sin d, 0)
    cross = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + math.sin(t) * cross + (1.0 - math.cos(t)) * (cross @ cross)


@dataclass(frozen=True)
class Placement:
    """Where a mesh object stands: scaled about its origin, yawed, tilted, then shifted.

    ``yaw_deg`` turns the object about its own vertical axis; ``tilt_deg`` then leans that
    axis towards azimuth ``tilt_dir_deg`` about the point of the axis ``pivot_mm`` above
    the origin (scaled mm: where a limb put back on the turntable not quite upright is
    held); ``shift_mm`` moves it last.
    """

    scale: float = 1.0
    yaw_deg: float = 0.0
    shift_mm: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tilt_deg: float = 0.0
    tilt_dir_deg: float = 0.0
    pivot_mm: float = 0.0

    @property
    def rotation(self) -> np.ndarray:
        """Return the 3x3 rotation of the placement (yaw, then tilt)."""
        return tilt_matrix(self.tilt_deg, self.tilt_dir_deg) @ _yaw_matrix(self.yaw_deg)

    @property
    def offset_mm(self) -> np.ndarray:
        """Return where the object's origin lands: the shift, and the pivot's lean."""
        pivot = np.array([0.0, 0.0, self.pivot_mm])
        return pivot - self.rotation @ pivot + np.asarray(self.shift_mm)

    def apply(self, tris: np.ndarray) -> np.ndarray:
        """Return triangles (F, 3, 3) (or points (..., 3)) given in the object's own frame,
        placed."""
        return (np.asarray(tris) * self.scale) @ self.rotation.T + self.offset_mm

    def own_frame(self, points_mm: np.ndarray) -> np.ndarray:
        """Return placed points (..., 3) in the object's own frame (the inverse of apply)."""
        moved = np.asarray(points_mm, dtype=float) - self.offset_mm
        return moved @ self.rotation / self.scale


AS_BUILT = Placement()
"""No scale, yaw or shift: the object where its own frame puts it."""


def _near_axis(o: np.ndarray, d: np.ndarray, x: float, y: float, radius: float) -> np.ndarray:
    """Return the indices of the rays whose line passes within ``radius`` of the vertical line
    through ``(x, y)``: the only ones that can meet a solid of revolution that wide (most of
    a camera's rays do not)."""
    rx, ry = o[:, 0] - x, o[:, 1] - y
    dxy = d[:, 0] ** 2 + d[:, 1] ** 2
    return np.flatnonzero((rx * d[:, 1] - ry * d[:, 0]) ** 2 <= radius * radius * dxy)


def _smallest_positive(*candidates: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return the smallest candidate t > eps per ray and which candidate it was."""
    stack = np.stack([np.where(c > _EPS_T_MM, c, np.inf) for c in candidates])
    which = np.argmin(stack, axis=0)
    return np.take_along_axis(stack, which[None], axis=0)[0], which


@dataclass(frozen=True)
class Cylinder:
    """A closed upright circular cylinder: base centre ``(x, y, z)``, diameter and height."""

    diameter_mm: float
    height_mm: float = 40.0
    x_mm: float = 0.0
    y_mm: float = 0.0
    z_mm: float = -5.0
    name: str = "cylinder"

    def raycast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the first hit t (N,) and outward normals (N, 3) of the wall and both caps."""
        o, d = _as_rays(origins, dirs)
        near = _near_axis(o, d, self.x_mm, self.y_mm, self.diameter_mm / 2.0)
        best, normal = np.full(len(d), np.inf), np.zeros_like(d)
        if near.size:
            best[near], normal[near] = self._cast(o[near], d[near])
        return best, normal

    def _cast(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the first hit t and outward normals of rays (N, 3) that may meet it."""
        r = self.diameter_mm / 2.0
        z0, z1 = self.z_mm, self.z_mm + self.height_mm
        ox, oy = o[:, 0] - self.x_mm, o[:, 1] - self.y_mm
        a = d[:, 0] ** 2 + d[:, 1] ** 2
        b = 2.0 * (ox * d[:, 0] + oy * d[:, 1])
        c = ox**2 + oy**2 - r * r
        disc = b * b - 4.0 * a * c
        with np.errstate(invalid="ignore", divide="ignore"):
            root = np.sqrt(np.where(disc >= 0, disc, np.nan))
            walls = []
            for t in ((-b - root) / (2.0 * a), (-b + root) / (2.0 * a)):
                z = o[:, 2] + t * d[:, 2]
                walls.append(np.where((z >= z0) & (z <= z1), t, np.inf))
            caps = []
            for zc in (z0, z1):
                t = (zc - o[:, 2]) / d[:, 2]
                px, py = ox + t * d[:, 0], oy + t * d[:, 1]
                caps.append(np.where(px * px + py * py <= r * r, t, np.inf))
        t, which = _smallest_positive(*walls, *caps)
        t_hit = np.where(np.isfinite(t), t, 0.0)
        hx, hy = ox + t_hit * d[:, 0], oy + t_hit * d[:, 1]
        on_wall = which < 2
        n = np.zeros_like(d)
        on_wall &= np.isfinite(t)
        n[:, 0] = np.where(on_wall, hx / r, 0.0)
        n[:, 1] = np.where(on_wall, hy / r, 0.0)
        n[:, 2] = np.where(which == 2, -1.0, np.where(which == 3, 1.0, 0.0))
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        return t, n

    def section_outline(self, z_mm: float) -> list[np.ndarray]:
        """Return the circle at height ``z_mm`` as one CCW polygon, or [] above or below."""
        if not self.z_mm <= z_mm <= self.z_mm + self.height_mm:
            return []
        phi = np.linspace(0.0, 2.0 * np.pi, OUTLINE_VERTICES, endpoint=False)
        r = self.diameter_mm / 2.0
        return [np.stack([self.x_mm + r * np.cos(phi), self.y_mm + r * np.sin(phi)], axis=1)]


@dataclass(frozen=True)
class Ellipsoid:
    """An ellipsoid with semi-axes ``(a, b, c)`` along x, y, z, centre ``(x, y, z)``, yaw."""

    semi_axes_mm: tuple[float, float, float]
    x_mm: float = 0.0
    y_mm: float = 0.0
    z_mm: float = 0.0
    yaw_deg: float = 0.0
    name: str = "ellipsoid"

    def _to_local(self, p: np.ndarray) -> np.ndarray:
        """Rotate object-frame vectors (N, 3) into the ellipsoid's own axes."""
        return p @ _yaw_matrix(self.yaw_deg)  # row vectors: p R == R^T p

    def raycast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the first hit t (N,) and outward normals (N, 3) via a unit-sphere quadratic."""
        o, d = _as_rays(origins, dirs)
        axes = np.asarray(self.semi_axes_mm, dtype=float)
        centre = np.array([self.x_mm, self.y_mm, self.z_mm])
        # Scaling space by 1/axes maps the ellipsoid to the unit sphere; t is unchanged.
        lo = self._to_local(o - centre) / axes
        ld = self._to_local(d) / axes
        a = np.einsum("ij,ij->i", ld, ld)
        b = 2.0 * np.einsum("ij,ij->i", lo, ld)
        c = np.einsum("ij,ij->i", lo, lo) - 1.0
        disc = b * b - 4.0 * a * c
        with np.errstate(invalid="ignore"):
            root = np.sqrt(np.where(disc >= 0, disc, np.nan))
            t, _ = _smallest_positive((-b - root) / (2 * a), (-b + root) / (2 * a))
        hit_local = (lo + np.where(np.isfinite(t), t, 0.0)[:, None] * ld) * axes
        n = self._to_local_inverse(hit_local / axes**2)
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
        return t, n

    def _to_local_inverse(self, v: np.ndarray) -> np.ndarray:
        """Rotate vectors from the ellipsoid's own axes back to the object frame."""
        return v @ _yaw_matrix(self.yaw_deg).T

    def section_outline(self, z_mm: float) -> list[np.ndarray]:
        """Return the ellipse cut at height ``z_mm`` as one CCW polygon, or [] if missed."""
        a, b, c = self.semi_axes_mm
        frac = 1.0 - ((z_mm - self.z_mm) / c) ** 2
        if frac <= 0.0:
            return []
        phi = np.linspace(0.0, 2.0 * np.pi, OUTLINE_VERTICES, endpoint=False)
        s = math.sqrt(frac)
        local = np.stack([a * s * np.cos(phi), b * s * np.sin(phi)], axis=1)
        rot = _yaw_matrix(self.yaw_deg)[:2, :2]
        return [local @ rot.T + np.array([self.x_mm, self.y_mm])]


# ----------------------------------------------------------------------------- meshes


def _moller_trumbore(
    o: np.ndarray, d: np.ndarray, v0: np.ndarray, e1: np.ndarray, e2: np.ndarray
) -> np.ndarray:
    """Return t for paired rays and triangles (all (P, 3)), inf where they miss."""
    p = np.cross(d, e2)
    det = np.einsum("ij,ij->i", e1, p)
    ok = np.abs(det) > 1e-12
    inv = 1.0 / np.where(ok, det, 1.0)
    s = o - v0
    u = np.einsum("ij,ij->i", s, p) * inv
    q = np.cross(s, e1)
    v = np.einsum("ij,ij->i", d, q) * inv
    t = np.einsum("ij,ij->i", e2, q) * inv
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > _EPS_T_MM)
    return np.where(hit, t, np.inf)


def _expand_ranges(starts: np.ndarray, counts: np.ndarray) -> np.ndarray:
    """Return ``starts[k] + 0..counts[k]-1`` for every k, concatenated."""
    # One repeat: each range's values are the running index shifted by its start.
    shift = starts - (np.cumsum(counts) - counts)
    return np.arange(int(counts.sum())) + np.repeat(shift, counts)


_UNCLAIMED = np.iinfo(np.int64).max


class _Nearest:
    """Per-ray nearest hit (t, face) fed with candidates in pairing order."""

    def __init__(self, n_rays: int) -> None:
        """Start with every ray missing."""
        self.t = np.full(n_rays, np.inf)
        self.face = np.full(n_rays, -1)
        # Scratch for exact ties, kept at _UNCLAIMED between offers so no offer allocates it.
        self._claim = np.full(n_rays, _UNCLAIMED, dtype=np.int64)

    def offer(self, ray: np.ndarray, t: np.ndarray, face: np.ndarray) -> None:
        """Keep each ray's nearest candidate (ray, t, face); an exact tie keeps the earlier.

        Candidates come in pairing order (faces in a fixed order, chunk after chunk), so
        "earlier" makes the result independent of how the pairs were chunked or bucketed.
        """
        hit = np.flatnonzero(np.isfinite(t))
        ray, t, face = ray[hit], t[hit], face[hit]
        before = self.t[ray]
        np.minimum.at(self.t, ray, t)
        win = np.flatnonzero((t < before) & (t == self.t[ray]))
        ray, face = ray[win], face[win]
        np.minimum.at(self._claim, ray, win)
        first = self._claim[ray] == win
        self.face[ray[first]] = face[first]
        self._claim[ray] = _UNCLAIMED


@dataclass(frozen=True, eq=False)
class _RayBuckets:
    """2D ray positions sorted into a uniform grid, with an integral image of counts."""

    lo: np.ndarray
    cell: np.ndarray
    n: int
    order: np.ndarray
    edge: np.ndarray  # (n * n + 1,) first sorted slot of each cell, then the total
    integral: np.ndarray

    @classmethod
    def build(cls, x: np.ndarray, y: np.ndarray, rays_per_cell: float = 8.0) -> _RayBuckets:
        """Bucket N points (x, y) into about N / rays_per_cell square-ish cells."""
        n = max(1, int(math.sqrt(len(x) / rays_per_cell)))
        lo = np.array([x.min(), y.min()])
        cell = np.maximum((np.array([x.max(), y.max()]) - lo) / n, 1e-12)
        i = np.minimum(((x - lo[0]) / cell[0]).astype(np.int64), n - 1)
        j = np.minimum(((y - lo[1]) / cell[1]).astype(np.int64), n - 1)
        flat = j * n + i
        count = np.bincount(flat, minlength=n * n)
        integral = np.zeros((n + 1, n + 1), dtype=np.int64)
        integral[1:, 1:] = count.reshape(n, n).cumsum(0).cumsum(1)
        order = np.argsort(flat, kind="stable")
        edge = np.concatenate([[0], np.cumsum(count)])
        return cls(lo, cell, n, order, edge, integral)

    def cell_range(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return inclusive (M, 2) cell index ranges covering boxes [lo, hi]."""
        pad = 1e-9 * self.cell
        c0 = np.floor((lo - pad - self.lo) / self.cell)
        c1 = np.floor((hi + pad - self.lo) / self.cell)
        return (
            np.clip(c0, 0, self.n - 1).astype(np.int64),
            np.clip(c1, 0, self.n - 1).astype(np.int64),
        )

    def count_in(self, c0: np.ndarray, c1: np.ndarray) -> np.ndarray:
        """Return how many points fall in each inclusive cell range."""
        s = self.integral
        return (
            s[c1[:, 1] + 1, c1[:, 0] + 1]
            - s[c0[:, 1], c1[:, 0] + 1]
            - s[c1[:, 1] + 1, c0[:, 0]]
            + s[c0[:, 1], c0[:, 0]]
        )

    def slots(self, c0: np.ndarray, c1: np.ndarray) -> np.ndarray:
        """Return the sorted slots (positions in ``order``) of the points in each cell range.

        Box after box, row after row: a row of a box is one run of consecutive slots, so
        the ranges are enumerated by rows, not cell by cell.
        """
        rows = c1[:, 1] - c0[:, 1] + 1
        y = _expand_ranges(c0[:, 1], rows)
        first = y * self.n + np.repeat(c0[:, 0], rows)
        last = y * self.n + np.repeat(c1[:, 0], rows)
        start = self.edge[first]
        return _expand_ranges(start, self.edge[last + 1] - start)


@dataclass(frozen=True, eq=False)
class _PinholeFaces:
    """Per-face terms of a pinhole cast, so a (ray, face) pair costs no face arithmetic.

    The 2D edges give each pair's inside test with exactly the rounding of the full
    cross product; the 3D terms are Möller–Trumbore's, which for a shared origin depend
    on the face alone except for the ray's cross product.
    """

    qx: np.ndarray  # (3, M) first corner of each projected edge
    qy: np.ndarray
    ex: np.ndarray  # (3, M) projected edge vectors, negated on clockwise faces
    ey: np.ndarray
    two_sided: np.ndarray  # (M,) orientation within rounding: test both signs
    e1: np.ndarray  # (M, 3) Möller–Trumbore edges, origin offset and its cross product
    e2: np.ndarray
    s: np.ndarray
    q: np.ndarray
    tq: np.ndarray  # (M,) e2 . q: t before dividing by the pair's determinant

    @classmethod
    def build(
        cls,
        origin: np.ndarray,
        tri: np.ndarray,
        tri_xy: np.ndarray,
        exact_2d: np.ndarray,
        reach: float,
    ) -> _PinholeFaces:
        """Precompute the terms of faces ``tri`` (M, 3, 3) projected to ``tri_xy`` (M, 3, 2).

        Faces not ``exact_2d`` (crossing the origin's plane) get null edges, so every
        ray paired with them passes the 2D test and the 3D test alone decides. ``reach``
        bounds the rays' projected coordinates.
        """
        nxt = tri_xy[:, [1, 2, 0]]
        q = np.where(exact_2d[:, None, None], tri_xy, 0.0)
        e = np.where(exact_2d[:, None, None], nxt - tri_xy, 0.0)
        a, b, c = tri_xy[:, 0], tri_xy[:, 1], tri_xy[:, 2]
        area2 = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (b[:, 1] - a[:, 1]) * (
            c[:, 0] - a[:, 0]
        )
        # The three edge tests of a point sum to twice the area up to rounding (about
        # 1e-15 of the squared coordinates), so past this margin a point can pass the
        # old test's clockwise branch only on a clockwise face: one branch per face.
        size = np.abs(tri_xy).max(axis=(1, 2))
        margin = 4 * _INSIDE_EPS + 1e-12 * (size + reach + 1.0) ** 2
        flip = area2 < -margin
        e[flip] = -e[flip]  # negation is exact: a clockwise face's tests change sign only
        v0 = tri[:, 0]
        e1, e2 = tri[:, 1] - v0, tri[:, 2] - v0
        s = origin[None] - v0
        qm = np.cross(s, e1)
        return cls(
            np.ascontiguousarray(q[..., 0].T),
            np.ascontiguousarray(q[..., 1].T),
            np.ascontiguousarray(e[..., 0].T),
            np.ascontiguousarray(e[..., 1].T),
            exact_2d & (np.abs(area2) <= margin),
            e1,
            e2,
            s,
            qm,
            np.einsum("ij,ij->i", e2, qm),
        )

    def inside_2d(self, owner: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
        """Return True where points (P,) lie in (or within rounding of) faces ``owner``."""
        sides = []
        for k in range(3):
            s = py - self.qy[k][owner]
            s *= self.ex[k][owner]
            r = px - self.qx[k][owner]
            r *= self.ey[k][owner]
            s -= r
            sides.append(s)
        keep = (sides[0] >= -_INSIDE_EPS) & (sides[1] >= -_INSIDE_EPS) & (sides[2] >= -_INSIDE_EPS)
        both = np.flatnonzero(self.two_sided[owner])
        if both.size:
            keep[both] |= np.all([s[both] <= _INSIDE_EPS for s in sides], axis=0)
        return keep

    def hit_t(self, d: np.ndarray, f: np.ndarray) -> np.ndarray:
        """Return t for rays ``d`` (P, 3) from the origin against faces ``f``, inf on a miss.

        Möller–Trumbore with the face-only terms looked up, bit for bit its result.
        """
        e2 = self.e2[f]
        p = np.cross(d, e2)
        det = np.einsum("ij,ij->i", self.e1[f], p)
        ok = np.abs(det) > 1e-12
        inv = 1.0 / np.where(ok, det, 1.0)
        u = np.einsum("ij,ij->i", self.s[f], p) * inv
        v = np.einsum("ij,ij->i", d, self.q[f]) * inv
        t = self.tq[f] * inv
        hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > _EPS_T_MM)
        return np.where(hit, t, np.inf)


def _straddle_boxes(rel: np.ndarray, eps: float) -> tuple[np.ndarray, np.ndarray]:
    """Return the projected 2D boxes of the parts of triangles in front of ``z = eps``.

    ``rel`` holds triangles (M, 3, 3) in the projection frame, each with some vertex in
    front and some not. A ray ahead that hits one hits its front part, whose projection
    lies in the box of the front vertices and the points where its edges cross the plane.
    """
    z = rel[..., 2]
    points = []
    for k in range(3):
        ahead = (z[:, k] > eps)[:, None]
        points.append(np.where(ahead, rel[:, k, :2] / np.maximum(z[:, k, None], eps), np.nan))
    for a, b in ((0, 1), (1, 2), (2, 0)):
        crosses = (z[:, a] - eps) * (z[:, b] - eps) < 0
        w = np.where(crosses, (eps - z[:, a]) / np.where(crosses, z[:, b] - z[:, a], 1.0), 0.0)
        cut = rel[:, a, :2] + w[:, None] * (rel[:, b, :2] - rel[:, a, :2])
        points.append(np.where(crosses[:, None], cut / eps, np.nan))
    stacked = np.stack(points, axis=1)
    return np.nanmin(stacked, axis=1), np.nanmax(stacked, axis=1)


def _cast_pinhole(
    origin: np.ndarray, d: np.ndarray, tri: np.ndarray, best: _Nearest
) -> tuple[np.ndarray, np.ndarray]:
    """Cast rays sharing one origin via a 2D bucket grid; return (faces, rays) left over.

    What is left for brute force is only the rays that do not point ahead of the mean
    ray (none, for a camera), against every face not wholly ahead.
    """
    # Gnomonic projection about the mean ray maps straight lines to straight lines, so a
    # triangle wholly in front of the origin projects to a triangle holding exactly the rays
    # that hit it. Buckets pair each triangle with nearby rays, a cheap 2D test culls most
    # pairs, and Möller–Trumbore in 3D decides the rest exactly. A triangle that crosses
    # the origin's plane (an object taller than the camera is high) is paired by the box
    # of its front part, without the 2D test; one wholly behind meets no ray ahead.
    eps = 1e-6
    axis = d.mean(axis=0)
    axis /= np.linalg.norm(axis)
    side = np.cross(axis, [0.0, 0.0, 1.0] if abs(axis[2]) < 0.9 else [1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    frame = np.stack([side, np.cross(axis, side), axis])
    rel = (tri - origin) @ frame.T
    front = np.all(rel[..., 2] > eps, axis=1)
    straddle = ~front & np.any(rel[..., 2] > eps, axis=1)
    # A contiguous right operand keeps BLAS on its fast path: the same sums, 4x faster.
    # (Rays through a vertex at the edge of the mesh's box are kept or not on the last
    # bit of this projection, so it is left as it was, bit for bit.)
    rd = d @ np.ascontiguousarray(frame.T)
    rx, ry, rz = rd[:, 0], rd[:, 1], rd[:, 2]
    ahead = rz > eps
    left = (np.flatnonzero(~front), np.flatnonzero(~ahead))
    fidx = np.concatenate([np.flatnonzero(front), np.flatnonzero(straddle)])
    exact_2d = np.arange(fidx.size) < np.count_nonzero(front)
    lo = np.empty((fidx.size, 2))
    hi = np.empty((fidx.size, 2))
    tri_xy = np.zeros((fidx.size, 3, 2))
    tri_xy[exact_2d] = rel[front, :, :2] / rel[front, :, 2:3]
    lo[exact_2d], hi[exact_2d] = tri_xy[exact_2d].min(axis=1), tri_xy[exact_2d].max(axis=1)
    if straddle.any():
        lo[~exact_2d], hi[~exact_2d] = _straddle_boxes(rel[straddle], eps)
    live = np.flatnonzero(ahead)
    if live.size < len(d):
        rx, ry, rz = rx[live], ry[live], rz[live]
    x, y = rx / rz, ry / rz
    if fidx.size and live.size:
        (x0, y0), (x1, y1) = lo.min(0), hi.max(0)
        inside = np.flatnonzero((x >= x0) & (x <= x1) & (y >= y0) & (y <= y1))
        live, x, y = live[inside], x[inside], y[inside]
        if live.size:
            # A triangle whose box misses every ray's box holds no ray: drop it (a few
            # rays, as the truth's visibility test casts, then skip most of the mesh).
            near = np.all((hi >= [x.min(), y.min()]) & (lo <= [x.max(), y.max()]), axis=1)
            fidx, tri_xy, lo, hi = fidx[near], tri_xy[near], lo[near], hi[near]
            exact_2d = exact_2d[near]
    if not (fidx.size and live.size):
        return left
    _pair_in_chunks(origin, d, tri, fidx, tri_xy, exact_2d, lo, hi, live, x, y, best)
    return left


def _pair_in_chunks(
    origin: np.ndarray,
    d: np.ndarray,
    tri: np.ndarray,
    fidx: np.ndarray,
    tri_xy: np.ndarray,
    exact_2d: np.ndarray,
    lo: np.ndarray,
    hi: np.ndarray,
    live: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    best: _Nearest,
) -> None:
    """Test faces ``fidx`` (boxes lo..hi) against the live rays (at x, y) near them, in chunks.

    Chunks hold whole faces in order, about ``_PAIRS_PER_CHUNK`` pairs each: memory stays
    bounded, and the arrays of a chunk stay in cache.
    """
    buckets = _RayBuckets.build(x, y)
    # Rays in slot order: each face's rays are runs of consecutive slots, read in order.
    px, py, ray_of_slot = x[buckets.order], y[buckets.order], live[buckets.order]
    reach = float(np.abs([x.min(), x.max(), y.min(), y.max()]).max())
    faces = _PinholeFaces.build(origin, tri[fidx], tri_xy, exact_2d, reach)
    c0, c1 = buckets.cell_range(lo, hi)
    count = buckets.count_in(c0, c1)
    load = np.cumsum(count)
    bounds = np.searchsorted(
        load, np.arange(1, load[-1] // _PAIRS_PER_CHUNK + 1) * _PAIRS_PER_CHUNK
    )
    for a, b in itertools.pairwise([0, *bounds.tolist(), fidx.size]):
        if b <= a:
            continue
        slot = buckets.slots(c0[a:b], c1[a:b])
        owner = np.repeat(np.arange(a, b), count[a:b])
        keep = np.flatnonzero(faces.inside_2d(owner, px[slot], py[slot]))
        f, ray = owner[keep], ray_of_slot[slot[keep]]
        best.offer(ray, faces.hit_t(d[ray], f), fidx[f])


@dataclass(frozen=True, eq=False)
class TriangleMesh:
    """A triangle mesh (vertices (V, 3), faces (F, 3) indices) placed in the object frame."""

    vertices: np.ndarray = field(repr=False)
    faces: np.ndarray = field(repr=False)
    name: str = "mesh"

    @classmethod
    def from_triangles(cls, tris: np.ndarray, name: str = "mesh") -> TriangleMesh:
        """Build an indexed mesh from a triangle soup (F, 3, 3), welding equal vertices."""
        flat = np.asarray(tris, dtype=float).reshape(-1, 3)
        # Weld on a 1e-6 mm lattice so STL soups share edges and sections chain up.
        keys = np.round(flat * 1e6).astype(np.int64)
        _, first, inverse = np.unique(keys, axis=0, return_index=True, return_inverse=True)
        faces = inverse.reshape(-1, 3)
        good = (
            (faces[:, 0] != faces[:, 1])
            & (faces[:, 1] != faces[:, 2])
            & (faces[:, 2] != faces[:, 0])
        )
        return cls(flat[first], faces[good], name)

    @property
    def triangles(self) -> np.ndarray:
        """Return the (F, 3, 3) corner coordinates."""
        return self.vertices[self.faces]

    def raycast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the nearest hit t (N,) and unit normals facing the ray (N, 3), Möller–Trumbore."""
        o, d = _as_rays(origins, dirs)
        best = _Nearest(len(d))
        if len(d) == 0:  # no ray to cast (a view where nothing is lit): nothing hit
            return best.t, np.zeros((0, 3))
        tri = self.triangles
        if o.strides[0] == 0 or np.all(o == o[0]):  # one origin, broadcast or repeated
            faces, rays = _cast_pinhole(o[0], d, tri, best)
        else:
            faces, rays = np.arange(len(tri)), np.arange(len(d))
        if faces.size and rays.size:
            sub = _Nearest(rays.size)
            sub.t[:], sub.face[:] = best.t[rays], best.face[rays]
            self._cast_brute(o[rays], d[rays], tri, faces, sub)
            best.t[rays], best.face[rays] = sub.t, sub.face
        best_t, best_f = best.t, best.face
        n = np.zeros_like(d)
        hit = best_f >= 0
        t3 = tri[best_f[hit]]
        fn = np.cross(t3[:, 1] - t3[:, 0], t3[:, 2] - t3[:, 0])
        fn /= np.linalg.norm(fn, axis=1, keepdims=True)
        # The first hit from outside is a front face, so facing the ray means outward even
        # when a file's winding is inconsistent.
        flip = np.einsum("ij,ij->i", fn, d[hit]) > 0
        n[hit] = np.where(flip[:, None], -fn, fn)
        return best_t, n

    @staticmethod
    def _cast_brute(
        o: np.ndarray,
        d: np.ndarray,
        tri: np.ndarray,
        faces: np.ndarray,
        best: _Nearest,
    ) -> None:
        """Test every ray against the given faces in bounded-memory chunks."""
        if faces.size == 0 or len(d) == 0:
            return
        per_chunk = max(1, 2_000_000 // len(d))
        for start in range(0, faces.size, per_chunk):
            f = faces[start : start + per_chunk]
            ray = np.tile(np.arange(len(d)), f.size)
            face = np.repeat(f, len(d))
            v0 = tri[face, 0]
            t = _moller_trumbore(o[ray], d[ray], v0, tri[face, 1] - v0, tri[face, 2] - v0)
            best.offer(ray, t, face)

    def section_outline(self, z_mm: float) -> list[np.ndarray]:
        """Slice the mesh at ``z_mm`` and chain the segments into closed CCW polygons.

        An open mesh (a shell, a tube cut off at a rim) may also give open chains; they
        are returned whole, unclosed; :meth:`section_curves` says which is which.
        """
        return [c.points for c in self.section_curves(z_mm)]

    def section_curves(self, z_mm: float) -> list[SectionCurve]:
        """Slice the mesh at ``z_mm``: closed CCW polygons and open chains, each flagged."""
        key, pts = self._slice(z_mm)
        return _chain_segments(key, pts) if len(key) else []

    def section_edges(self, z_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """Return the section's segments at ``z_mm`` as start and end points (S, 2) each.

        The same edges as :meth:`section_curves`, unchained: all the laser's shadow test
        needs, without the chaining's cost on a finely meshed object.
        """
        _, pts = self._slice(z_mm)
        return pts[:, 0], pts[:, 1]

    def _slice(self, z_mm: float) -> tuple[np.ndarray, np.ndarray]:
        """Return the edge keys (S, 2) and end points (S, 2, 2) of the cut at ``z_mm``."""
        above = self.vertices[:, 2] >= z_mm  # on-plane vertices count as above: no degeneracy
        f = self.faces
        n_above = above[f].sum(axis=1)
        cut = f[(n_above == 1) | (n_above == 2)]
        if cut.size == 0:
            return np.empty((0, 2), np.int64), np.empty((0, 2, 2))
        edges = np.stack([cut[:, [0, 1]], cut[:, [1, 2]], cut[:, [2, 0]]], axis=1)
        crosses = above[edges[..., 0]] != above[edges[..., 1]]
        seg_edges = edges[crosses].reshape(-1, 2, 2)  # two crossing edges per cut face
        a, b = np.sort(seg_edges, axis=2)[..., 0], np.sort(seg_edges, axis=2)[..., 1]
        key = a * len(self.vertices) + b
        za, zb = self.vertices[a, 2], self.vertices[b, 2]
        w = ((z_mm - za) / (zb - za))[..., None]
        pts = self.vertices[a, :2] + w * (self.vertices[b, :2] - self.vertices[a, :2])
        return key, pts


@dataclass(frozen=True, eq=False)
class SectionCurve:
    """One curve of a true section: a closed CCW polygon or an open chain (K, 2), mm."""

    points: np.ndarray
    closed: bool = True


def section_curves(obj: SceneObject, z_mm: float) -> list[SectionCurve]:
    """Return ``obj``'s true section at ``z_mm`` with each curve flagged closed or open.

    Args:
        obj: any scene object; one without open curves (the solids) gives closed ones.
        z_mm: the height of the section in the object frame.

    Returns:
        The section's curves; an open mesh's open chains have ``closed`` False.
    """
    curves = getattr(obj, "section_curves", None)
    if curves is not None:
        return list(curves(z_mm))
    return [SectionCurve(p) for p in obj.section_outline(z_mm)]


def section_edges(obj: SceneObject, z_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """Return the edges of ``obj``'s true section at ``z_mm``: start and end points (S, 2).

    Args:
        obj: any scene object; a closed curve gives every edge, its closing one too, an
            open chain all but that one.
        z_mm: the height of the section in the object frame.

    Returns:
        The edges' start and end points.
    """
    edges = getattr(obj, "section_edges", None)
    if edges is not None:
        a, b = edges(z_mm)
        return np.asarray(a), np.asarray(b)
    curves = section_curves(obj, z_mm)
    if not curves:
        return np.empty((0, 2)), np.empty((0, 2))
    a = np.concatenate([c.points if c.closed else c.points[:-1] for c in curves])
    b = np.concatenate(
        [np.roll(c.points, -1, axis=0) if c.closed else c.points[1:] for c in curves]
    )
    return a, b


def _chain_segments(key: np.ndarray, pts: np.ndarray) -> list[SectionCurve]:
    """Join segments (S, 2) that share edge keys into closed CCW polygons and open chains."""
    point_of = {int(k): p for k, p in zip(key.ravel(), pts.reshape(-1, 2), strict=True)}
    touching: dict[int, list[int]] = {}
    for s, (k0, k1) in enumerate(key.tolist()):
        touching.setdefault(k0, []).append(s)
        touching.setdefault(k1, []).append(s)
    used = np.zeros(len(key), dtype=bool)
    polygons = []
    for start in range(len(key)):
        if used[start]:
            continue
        used[start] = True
        ring = [int(key[start, 0])]
        cur = int(key[start, 1])
        closed = _walk(ring, cur, key, touching, used)
        if not closed:
            # An open mesh's chain (a rim, a shell's edge): walk back from the start too,
            # so the whole curve is one chain and not two falsely closed pieces.
            back = [int(key[start, 1])]
            _walk(back, int(key[start, 0]), key, touching, used)
            ring = back[::-1] + ring[2:]  # back ends [.., k0, k1], ring starts [k0, k1]
        poly = np.array([point_of[k] for k in ring])
        if not closed and len(poly) >= 2:
            polygons.append(SectionCurve(poly, closed=False))
        elif len(poly) >= 3:
            area = 0.5 * np.sum(
                poly[:, 0] * np.roll(poly[:, 1], -1) - np.roll(poly[:, 0], -1) * poly[:, 1]
            )
            polygons.append(SectionCurve(poly if area > 0 else poly[::-1]))
    return polygons


def _walk(
    chain: list[int],
    cur: int,
    key: np.ndarray,
    touching: dict[int, list[int]],
    used: np.ndarray,
) -> bool:
    """Extend ``chain`` from key ``cur`` through unused segments; return True if it closed."""
    while cur != chain[0]:
        chain.append(cur)
        nxt = [s for s in touching[cur] if not used[s]]
        if not nxt:
            return False  # the end of an open chain
        used[nxt[0]] = True
        k0, k1 = key[nxt[0]]
        cur = int(k1 if k0 == cur else k0)
    return True


# ----------------------------------------------------------------------------- loading


def _read_stl(data: bytes) -> np.ndarray:
    """Return the (F, 3, 3) triangles of a binary or ASCII STL file."""
    if len(data) >= 84:
        (count,) = struct.unpack_from("<I", data, 80)
        if len(data) == 84 + 50 * count:  # binary files may also start with "solid"
            rec = np.dtype([("n", "<f4", 3), ("v", "<f4", (3, 3)), ("attr", "<u2")])
            return np.frombuffer(data, rec, count, 84)["v"].astype(float)
    words = data.decode("ascii", errors="replace").split()
    idx = [i for i, w in enumerate(words) if w == "vertex"]
    if not idx or len(idx) % 3:
        raise ValueError("mesh: not a valid STL file (no complete 'vertex' triples)")
    return np.array([[float(words[i + k]) for k in (1, 2, 3)] for i in idx]).reshape(-1, 3, 3)


def _fan(polys: list[list[int]]) -> np.ndarray:
    """Triangulate polygons given as vertex index lists by fanning from the first vertex."""
    tris = [(p[0], p[k], p[k + 1]) for p in polys for k in range(1, len(p) - 1)]
    return np.array(tris, dtype=np.int64).reshape(-1, 3)


def _read_ply(text: str) -> np.ndarray:
    """Return the (F, 3, 3) triangles of an ASCII PLY file."""
    lines = text.splitlines()
    if not lines or lines[0].strip() != "ply":
        raise ValueError("mesh: not a PLY file")
    counts: dict[str, int] = {}
    props: list[str] = []
    current = ""
    body = 0
    for i, line in enumerate(lines):
        parts = line.split()
        if parts[:1] == ["format"] and parts[1] != "ascii":
            raise ValueError("mesh: only ASCII PLY is supported, this file is " + parts[1])
        if parts[:1] == ["element"]:
            current, counts[parts[1]] = parts[1], int(parts[2])
        elif parts[:1] == ["property"] and current == "vertex":
            props.append(parts[-1])
        elif parts[:1] == ["end_header"]:
            body = i + 1
            break
    nv, nf = counts.get("vertex", 0), counts.get("face", 0)
    cols = [props.index(c) for c in ("x", "y", "z")]
    verts = np.array([[float(lines[body + i].split()[c]) for c in cols] for i in range(nv)])
    polys = [[int(x) for x in lines[body + nv + i].split()[1:]] for i in range(nf)]
    return verts[_fan(polys)]


def _read_obj(text: str) -> np.ndarray:
    """Return the (F, 3, 3) triangles of an OBJ file's ``v`` and ``f`` lines."""
    verts: list[list[float]] = []
    polys: list[list[int]] = []
    for line in text.splitlines():
        parts = line.split()
        if parts[:1] == ["v"]:
            verts.append([float(x) for x in parts[1:4]])
        elif parts[:1] == ["f"]:
            # "f 1/2/3 ..." is vertex/texture/normal; negative indices count from the end.
            idx = [int(p.split("/")[0]) for p in parts[1:]]
            polys.append([i - 1 if i > 0 else len(verts) + i for i in idx])
    return np.array(verts)[_fan(polys)]


def load_mesh(path: str | Path, placement: Placement = AS_BUILT) -> TriangleMesh:
    """Load an STL, ASCII PLY or OBJ file and place it (scale, yaw, then move its origin)."""
    p = Path(path)
    if not p.is_file():
        raise ValueError(f"mesh: file not found: {p}")
    data = p.read_bytes()
    suffix = p.suffix.lower()
    if suffix == ".stl":
        tris = _read_stl(data)
    elif suffix == ".ply":
        tris = _read_ply(data.decode("ascii", errors="replace"))
    elif suffix == ".obj":
        tris = _read_obj(data.decode("ascii", errors="replace"))
    else:
        raise ValueError(f"mesh: unknown file type {suffix!r}; expected .stl, .ply or .obj")
    if tris.size == 0:
        raise ValueError(f"mesh: {p} holds no triangles")
    return TriangleMesh.from_triangles(placement.apply(tris), name=f"mesh:{p.name}")


# ----------------------------------------------------------------------------- builders


def cylinder(
    diameter_mm: float, height_mm: float = 40.0, x: float = 0.0, y: float = 0.0, z: float = -5.0
) -> Cylinder:
    """Return an upright cylinder whose base centre sits at ``(x, y, z)``."""
    return Cylinder(diameter_mm, height_mm, x, y, z)


@dataclass(frozen=True)
class Revolved:
    """A solid of revolution about the vertical line through ``(x, y)``: flat end faces at
    the first and last heights of ``profile``, a wall of cylinders and cones between them.

    ``profile`` holds (z, r) pairs, z rising strictly; the radius runs linearly between
    them. Ray casts and sections are exact (no facets).
    """

    profile: tuple[tuple[float, float], ...]
    x_mm: float = 0.0
    y_mm: float = 0.0
    name: str = "revolved"

    def radius_at(self, z_mm: float) -> float:
        """Return the wall's radius at height ``z_mm`` (NaN above or below the solid)."""
        z = [p[0] for p in self.profile]
        if not z[0] <= z_mm <= z[-1]:
            return math.nan
        return float(np.interp(z_mm, z, [p[1] for p in self.profile]))

    def raycast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the first hit t (N,) and outward normals (N, 3) of the wall and end faces."""
        o, d = _as_rays(origins, dirs)
        best = np.full(len(d), np.inf)
        normal = np.zeros_like(d)
        near = _near_axis(o, d, self.x_mm, self.y_mm, max(r for _, r in self.profile))
        if near.size:
            t, n = self._cast(o[near], d[near])
            best[near], normal[near] = t, n
        return best, normal

    def _cast(self, o: np.ndarray, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the first hit t and unit outward normals of rays (N, 3) near the solid."""
        ox, oy, oz = o[:, 0] - self.x_mm, o[:, 1] - self.y_mm, o[:, 2]
        best = np.full(len(d), np.inf)
        normal = np.zeros_like(d)
        with np.errstate(invalid="ignore", divide="ignore"):
            for (z0, r0), (z1, r1) in itertools.pairwise(self.profile):
                s = (r1 - r0) / (z1 - z0)  # dr/dz of this piece
                k = r0 - s * z0 + s * oz  # the piece's radius at the ray's origin height
                a = d[:, 0] ** 2 + d[:, 1] ** 2 - (s * d[:, 2]) ** 2
                b = 2.0 * (ox * d[:, 0] + oy * d[:, 1] - s * d[:, 2] * k)
                c = ox**2 + oy**2 - k * k
                root = np.sqrt(np.where(b * b - 4.0 * a * c >= 0.0, b * b - 4.0 * a * c, np.nan))
                for t in ((-b - root) / (2.0 * a), (-b + root) / (2.0 * a)):
                    z = oz + t * d[:, 2]
                    ok = (t > _EPS_T_MM) & (z >= z0) & (z <= z1) & (k + s * t * d[:, 2] >= 0.0)
                    closer = ok & (t < best)
                    best = np.where(closer, t, best)
                    hx, hy = ox + t * d[:, 0], oy + t * d[:, 1]
                    wall = np.stack([hx, hy, -s * (k + s * t * d[:, 2])], axis=1)
                    normal = np.where(closer[:, None], wall, normal)
            for zc, rc, up in ((*self.profile[0], -1.0), (*self.profile[-1], 1.0)):
                t = (zc - oz) / d[:, 2]
                px, py = ox + t * d[:, 0], oy + t * d[:, 1]
                closer = (t > _EPS_T_MM) & (px * px + py * py <= rc * rc) & (t < best)
                best = np.where(closer, t, best)
                normal = np.where(closer[:, None], np.array([0.0, 0.0, up]), normal)
        normal /= np.maximum(np.linalg.norm(normal, axis=1, keepdims=True), 1e-300)
        return best, normal

    def section_outline(self, z_mm: float) -> list[np.ndarray]:
        """Return the circle at height ``z_mm`` as one CCW polygon, or [] above or below."""
        r = self.radius_at(z_mm)
        if not r > 0.0:
            return []
        phi = np.linspace(0.0, 2.0 * np.pi, OUTLINE_VERTICES, endpoint=False)
        return [np.stack([self.x_mm + r * np.cos(phi), self.y_mm + r * np.sin(phi)], axis=1)]


def grooved_cylinder(
    diameter_mm: float,
    height_mm: float,
    x: float,
    y: float,
    z: float,
    grooves_mm: tuple[float, ...],
    depth_mm: float,
) -> Revolved:
    """Return an upright cylinder (base centre ``(x, y, z)``) with 90 degree V-grooves.

    Each groove is centred at a height in ``grooves_mm`` (object frame), ``depth_mm`` deep
    and twice as wide: its flanks are 45 degree cones.
    """
    r = diameter_mm / 2.0
    profile = [(z, r)]
    for g in sorted(grooves_mm):
        profile += [(g - depth_mm, r), (g, r - depth_mm), (g + depth_mm, r)]
    profile.append((z + height_mm, r))
    return Revolved(tuple(profile), x, y, name="grooved cylinder")


def sphere(diameter_mm: float, x: float = 0.0, y: float = 0.0, z: float = 0.0) -> Ellipsoid:
    """Return a sphere centred at ``(x, y, z)``."""
    r = diameter_mm / 2.0
    return Ellipsoid((r, r, r), x, y, z, 0.0, name="sphere")


def ellipsoid(
    a: float, b: float, c: float, x: float = 0.0, y: float = 0.0, z: float = 0.0, yaw: float = 0.0
) -> Ellipsoid:
    """Return an ellipsoid with semi-axes a, b, c (x, y, z) centred at ``(x, y, z)``, yawed."""
    return Ellipsoid((a, b, c), x, y, z, yaw)
