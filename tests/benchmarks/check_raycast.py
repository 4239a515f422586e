"""Check that the mesh ray caster gives bit-identical results to main's (not a test).

The ray caster of ``lamina_device.sim.objects.TriangleMesh`` was rewritten for speed;
its old implementation is kept below, verbatim apart from names, and both cast the
renderer's camera rays (every pixel, a band, a sparse subset), the truth's visibility
rays and a few rays from scattered origins at random shapes (seeds 0-9, thesis and limb)
and the built-in phantoms. Run ``python tests/benchmarks/check_raycast.py``; it prints
one line per mesh and exits non-zero when any t or normal differs.
"""

from __future__ import annotations

import math
import sys
import time
from dataclasses import dataclass

import numpy as np

from lamina_device.sim import NoiseModel, Rig, SimScene
from lamina_device.sim.objects import TriangleMesh, _as_rays
from lamina_device.sim.phantoms import PHANTOMS, phantom
from lamina_device.sim.random_shapes import random_shape
from lamina_device.sim.render import _rz

EPS_T_MM = 1e-9

# ---------------------------------------------------------------- main's implementation


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
    hit = ok & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > EPS_T_MM)
    return np.where(hit, t, np.inf)


def _expand_ranges(starts: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (owner, index) pairs enumerating ``starts[k] + 0..counts[k]-1`` for every k."""
    owner = np.repeat(np.arange(len(counts)), counts)
    first = np.cumsum(counts) - counts
    local = np.arange(owner.size) - np.repeat(first, counts)
    return owner, np.repeat(starts, counts) + local


def _keep_nearest(
    best_t: np.ndarray, best_f: np.ndarray, ray: np.ndarray, t: np.ndarray, face: np.ndarray
) -> None:
    """Update per-ray nearest hit arrays in place from candidate (ray, t, face) triples."""
    hit = np.isfinite(t)
    ray, t, face = ray[hit], t[hit], face[hit]
    order = np.lexsort((t, ray))
    ray, t, face = ray[order], t[order], face[order]
    first = np.ones(ray.size, dtype=bool)
    first[1:] = ray[1:] != ray[:-1]
    ray, t, face = ray[first], t[first], face[first]
    better = t < best_t[ray]
    best_t[ray[better]] = t[better]
    best_f[ray[better]] = face[better]


@dataclass(frozen=True, eq=False)
class _RayBuckets:
    """2D ray positions sorted into a uniform grid, with an integral image of counts."""

    lo: np.ndarray
    cell: np.ndarray
    n: int
    order: np.ndarray
    start: np.ndarray
    count: np.ndarray
    integral: np.ndarray

    @classmethod
    def build(cls, xy: np.ndarray, rays_per_cell: float = 8.0) -> _RayBuckets:
        """Bucket (N, 2) points into about N / rays_per_cell square-ish cells."""
        n = max(1, int(math.sqrt(len(xy) / rays_per_cell)))
        lo, hi = xy.min(axis=0), xy.max(axis=0)
        cell = np.maximum((hi - lo) / n, 1e-12)
        ij = np.minimum(((xy - lo) / cell).astype(np.int64), n - 1)
        flat = ij[:, 1] * n + ij[:, 0]
        count = np.bincount(flat, minlength=n * n)
        integral = np.zeros((n + 1, n + 1), dtype=np.int64)
        integral[1:, 1:] = count.reshape(n, n).cumsum(0).cumsum(1)
        order = np.argsort(flat, kind="stable")
        return cls(lo, cell, n, order, np.cumsum(count) - count, count, integral)

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

    def pairs(self, c0: np.ndarray, c1: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return (box index, point index) for every point in every box's cell range."""
        span = c1 - c0 + 1
        owner, k = _expand_ranges(np.zeros(len(c0), np.int64), span[:, 0] * span[:, 1])
        cells = (c0[owner, 1] + k // span[owner, 0]) * self.n + c0[owner, 0] + k % span[owner, 0]
        which, slot = _expand_ranges(self.start[cells], self.count[cells])
        return owner[which], self.order[slot]


def _inside_2d(tri: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Return True where points (P, 2) lie in (or within rounding of) triangles (P, 3, 2)."""
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]

    def side(q: np.ndarray, r: np.ndarray) -> np.ndarray:
        """Return the 2D cross product telling which side of edge q->r each point is on."""
        return (r[:, 0] - q[:, 0]) * (p[:, 1] - q[:, 1]) - (r[:, 1] - q[:, 1]) * (p[:, 0] - q[:, 0])

    s0, s1, s2 = side(a, b), side(b, c), side(c, a)
    eps = 1e-12  # generous: the exact 3D test decides, this only culls
    return ((s0 >= -eps) & (s1 >= -eps) & (s2 >= -eps)) | ((s0 <= eps) & (s1 <= eps) & (s2 <= eps))


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
    origin: np.ndarray, d: np.ndarray, tri: np.ndarray, best_t: np.ndarray, best_f: np.ndarray
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
    rd = d @ frame.T
    ahead = rd[:, 2] > eps
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
    ray_xy = rd[live, :2] / rd[live, 2:3]
    if fidx.size and live.size:
        inside = np.all((ray_xy >= lo.min(0)) & (ray_xy <= hi.max(0)), axis=1)
        live, ray_xy = live[inside], ray_xy[inside]
        if live.size:
            # A triangle whose box misses every ray's box holds no ray: drop it (a few
            # rays, as the truth's visibility test casts, then skip most of the mesh).
            near = np.all((hi >= ray_xy.min(0)) & (lo <= ray_xy.max(0)), axis=1)
            fidx, tri_xy, lo, hi = fidx[near], tri_xy[near], lo[near], hi[near]
            exact_2d = exact_2d[near]
    if not (fidx.size and live.size):
        return left
    buckets = _RayBuckets.build(ray_xy)
    c0, c1 = buckets.cell_range(lo, hi)
    load = np.cumsum(buckets.count_in(c0, c1))
    bounds = np.searchsorted(load, np.arange(1, load[-1] // 1_000_000 + 1) * 1_000_000)
    for chunk in np.split(np.arange(fidx.size), bounds):  # ~1e6 candidate pairs per chunk
        if chunk.size == 0:
            continue
        owner, ray = buckets.pairs(c0[chunk], c1[chunk])
        keep = ~exact_2d[chunk][owner]
        keep[~keep] = _inside_2d(tri_xy[chunk][owner[~keep]], ray_xy[ray[~keep]])
        face, ray = fidx[chunk][owner[keep]], live[ray[keep]]
        v0 = tri[face, 0]
        t = _moller_trumbore(origin[None], d[ray], v0, tri[face, 1] - v0, tri[face, 2] - v0)
        _keep_nearest(best_t, best_f, ray, t, face)
    return left


def old_raycast(
    mesh: TriangleMesh, origins: np.ndarray, dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Return ``TriangleMesh.raycast`` as main had it: nearest t (N,) and normals (N, 3)."""
    o, d = _as_rays(origins, dirs)
    best_t = np.full(len(d), np.inf)
    best_f = np.full(len(d), -1)
    if len(d) == 0:  # no ray to cast (a view where nothing is lit): nothing hit
        return best_t, np.zeros((0, 3))
    tri = mesh.triangles
    if np.all(o == o[0]):
        faces, rays = _cast_pinhole(o[0], d, tri, best_t, best_f)
    else:
        faces, rays = np.arange(len(tri)), np.arange(len(d))
    if faces.size and rays.size:
        sub_t, sub_f = best_t[rays], best_f[rays]
        _cast_brute(o[rays], d[rays], tri, faces, sub_t, sub_f)
        best_t[rays], best_f[rays] = sub_t, sub_f
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


def _cast_brute(
    o: np.ndarray,
    d: np.ndarray,
    tri: np.ndarray,
    faces: np.ndarray,
    best_t: np.ndarray,
    best_f: np.ndarray,
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
        _keep_nearest(best_t, best_f, ray, t, face)


# ---------------------------------------------------------------------------- the check


@dataclass
class Tally:
    """Rays cast and rays whose result differs, over every case of one mesh."""

    rays: int = 0
    hits: int = 0
    t_differ: int = 0  # finite in both, different value
    hit_differ: int = 0  # hit in one, missed in the other
    normal_differ: int = 0
    old_s: float = 0.0
    new_s: float = 0.0


def compare(tally: Tally, mesh: TriangleMesh, origins: np.ndarray, dirs: np.ndarray) -> None:
    """Cast with both implementations and add the differences to ``tally``."""
    t0 = time.process_time()
    t_old, n_old = old_raycast(mesh, origins, dirs)
    t1 = time.process_time()
    t_new, n_new = mesh.raycast(origins, dirs)
    t2 = time.process_time()
    tally.old_s += t1 - t0
    tally.new_s += t2 - t1
    both = np.isfinite(t_old) & np.isfinite(t_new)
    tally.rays += len(t_old)
    tally.hits += int(np.isfinite(t_old).sum())
    tally.hit_differ += int((np.isfinite(t_old) != np.isfinite(t_new)).sum())
    tally.t_differ += int((t_old[both] != t_new[both]).sum())
    tally.normal_differ += int(np.any(n_old != n_new, axis=1).sum())


def camera_cases(scene: SimScene, obj: TriangleMesh, rng: np.random.Generator) -> list:
    """Return (origins, dirs) the renderer casts: whole views, a band, a sparse subset."""
    axis = np.array([*scene.rig.axis_xy_mm, 0.0])
    cases = []
    h, w = scene._shape
    for angle, z in ((0.0, 0.0), (137.0, float(rng.uniform(0.0, 60.0)))):
        to_obj = _rz(-angle)
        origin = to_obj @ (scene._centre - axis) + np.array([0.0, 0.0, z])
        cases.append((origin, scene._dirs @ to_obj.T))
        band = slice((h // 3) * w, (h // 3 + 24) * w)
        cases.append((origin, scene._dirs[band] @ to_obj.T))
        pick = rng.choice(h * w, size=500, replace=False)
        cases.append((origin, scene._dirs[pick] @ to_obj.T))
    # The truth's visibility test: rays from the camera to points on a section.
    zs = obj.vertices[:, 2]
    z = float(np.quantile(zs, 0.4))
    for curve in obj.section_curves(z)[:3]:
        q3 = np.column_stack([curve.points, np.full(len(curve.points), z)])
        ray = q3 - scene._centre
        cases.append((scene._centre, ray / np.linalg.norm(ray, axis=1)[:, None]))
    # Scattered origins (not a pinhole): the brute-force path.
    o = scene._centre + rng.normal(0.0, 5.0, (200, 3))
    d = obj.vertices[rng.integers(0, len(obj.vertices), 200)] - o
    cases.append((o, d / np.linalg.norm(d, axis=1)[:, None]))
    return cases


def check(name: str, obj: TriangleMesh, scale: str, rng: np.random.Generator) -> Tally:
    """Compare both ray casters on every case of ``obj`` seen by the ``scale`` rig."""
    scene = SimScene(Rig.preset(scale), obj, NoiseModel.preset("harsh"))
    tally = Tally()
    for origins, dirs in camera_cases(scene, obj, rng):
        compare(tally, obj, origins, dirs)
    print(
        f"{name:24s} {scale:6s} faces {len(obj.faces):6d} rays {tally.rays:8d} "
        f"hits {tally.hits:8d} | differ: t {tally.t_differ} hit/miss {tally.hit_differ} "
        f"normal {tally.normal_differ} | cpu old {tally.old_s:6.2f} s new {tally.new_s:6.2f} s",
        flush=True,
    )
    return tally


def main() -> int:
    """Check every mesh; return 1 when any result differs."""
    rng = np.random.default_rng(7)
    total = Tally()
    meshes = [
        (f"random:seed={seed}", random_shape(seed, scale), scale)
        for scale in ("thesis", "limb")
        for seed in range(10)
    ]
    meshes += [(f"phantom:{name}", phantom(name), "limb") for name in PHANTOMS]
    meshes += [(f"phantom:{name}", phantom(name), "thesis") for name in PHANTOMS]
    for name, obj, scale in meshes:
        tally = check(name, obj, scale, rng)
        for key in vars(total):
            setattr(total, key, getattr(total, key) + getattr(tally, key))
    print(f"total: {total}")
    return int(bool(total.t_differ or total.hit_differ or total.normal_differ))


if __name__ == "__main__":
    sys.exit(main())
