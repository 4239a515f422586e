"""Surface meshes from the contour stack, and PLY output (thesis chapter 7).

``MESH_METHODS``: ``"contours"`` (default) joins neighbouring EFD contours sampled at the
same parameter values into a watertight, manifold tube whose ends are the end contours
themselves, triangulated;
``"ball-pivoting"`` (the thesis' choice, 7.2.1) and ``"poisson"`` (screened Poisson)
reconstruct from the points through MeshLab (pymeshlab, the optional extra
``lamina-host[meshlab]``). Everything else here (the contour mesh, topology, PLY/STL/OBJ)
is numpy only, so the host runs where pymeshlab cannot be installed.
"""

from __future__ import annotations

import importlib
from dataclasses import asdict, dataclass
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components

from lamina_host.reconstruct.calibration import CalibrationError
from lamina_host.reconstruct.measure import signed_area
from lamina_shared.errors import LaminaError

MESHLAB_EXTRA = "pip install 'lamina-host[meshlab]'"
"""The command that installs pymeshlab for ball pivoting and Poisson."""


class MeshlabMissing(LaminaError):
    """Ball pivoting or Poisson was asked for where pymeshlab cannot be imported."""


def meshlab(method: str) -> ModuleType:
    """Return the pymeshlab module for ``method``, or raise MeshlabMissing naming the extra."""
    try:
        return importlib.import_module("pymeshlab")
    except ImportError as exc:  # absent, or present without its GL/font libraries
        raise MeshlabMissing(
            f"--mesh {method} needs pymeshlab, which cannot be imported ({exc}); "
            f"install it with {MESHLAB_EXTRA} or use --mesh contours"
        ) from None


def contour_normals(contour: np.ndarray) -> np.ndarray:
    """Return (N, 2) outward unit normals of a closed contour in the xy plane.

    The tangent at each point is the central difference of its neighbours (wrapping round);
    the outward side follows from the contour's orientation (sign of its shoelace area).
    """
    pts = np.asarray(contour, dtype=float)
    tangent = np.roll(pts, -1, axis=0) - np.roll(pts, 1, axis=0)
    # For a counter-clockwise contour the outside is on the right of the tangent.
    normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
    if signed_area(pts) < 0:
        normal = -normal
    length = np.linalg.norm(normal, axis=1, keepdims=True)
    if np.any(length == 0):
        raise CalibrationError(
            "the contour has repeated neighbouring points, so a normal is undefined; "
            "remove duplicate points first"
        )
    return normal / length


def _normals3(normals: np.ndarray, n: int) -> np.ndarray:
    """Return normals as (n, 3), padding xy normals with z = 0."""
    nrm = np.asarray(normals, dtype=float)
    if nrm.ndim != 2 or len(nrm) != n or nrm.shape[1] not in (2, 3):
        raise ValueError(f"normals must be ({n}, 2) or ({n}, 3), got {nrm.shape}")
    if nrm.shape[1] == 2:
        nrm = np.concatenate([nrm, np.zeros((n, 1))], axis=1)
    return nrm


def _points3(points: np.ndarray) -> np.ndarray:
    """Return a validated (N, 3) float array."""
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points must be an (N, 3) array, got {pts.shape}")
    return pts


def ball_pivoting(
    points: np.ndarray, normals: np.ndarray, radius_mm: float
) -> tuple[np.ndarray, np.ndarray]:
    """Mesh a point cloud with MeshLab's ball-pivoting algorithm (thesis 7.2.1).

    Args:
        points: (N, 3) vertices in mm.
        normals: (N, 3) or (N, 2) outward normals (xy normals get z = 0).
        radius_mm: ball radius in mm (the thesis used 2 mm for 2 mm section pitch).

    Returns:
        (vertices (V, 3) float64, faces (F, 3) int64).
    """
    pymeshlab = meshlab("ball-pivoting")  # deferred: heavy import, only needed here
    pts = _points3(points)
    if len(pts) < 3:
        raise CalibrationError(f"meshing needs at least 3 points, got {len(pts)}")
    if not radius_mm > 0:
        raise ValueError(f"ball radius must be a positive number of mm, not {radius_mm}")
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=pts, v_normals_matrix=_normals3(normals, len(pts))))
    ms.generate_surface_reconstruction_ball_pivoting(ballradius=pymeshlab.PureValue(radius_mm))
    mesh = ms.current_mesh()
    return (
        np.asarray(mesh.vertex_matrix(), dtype=np.float64),
        np.asarray(mesh.face_matrix(), dtype=np.int64),
    )


MESH_METHODS = ("contours", "ball-pivoting", "poisson")
"""Selectable surface methods; the first is the default."""


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return the z component of (a - o) x (b - o) for stacked 2-D points."""
    return (a[..., 0] - o[..., 0]) * (b[..., 1] - o[..., 1]) - (a[..., 1] - o[..., 1]) * (
        b[..., 0] - o[..., 0]
    )


def _ears(pts: np.ndarray, alive: np.ndarray) -> np.ndarray:
    """Return a mask over ``alive`` of convex vertices whose triangle holds no other vertex."""
    p = pts[alive]
    prev, nxt = np.roll(p, 1, axis=0), np.roll(p, -1, axis=0)
    area = _cross(prev, p, nxt)
    scale = float(np.ptp(p, axis=0).max()) ** 2
    convex = area > 1e-12 * scale
    reflex = np.flatnonzero(~convex)
    ears = convex.copy()
    cand = np.flatnonzero(convex)
    if len(reflex) and len(cand):
        q = p[reflex][None, :, :]
        a, b, c = prev[cand][:, None], p[cand][:, None], nxt[cand][:, None]
        eps = -1e-12 * scale
        inside = (_cross(a, b, q) >= eps) & (_cross(b, c, q) >= eps) & (_cross(c, a, q) >= eps)
        n = len(p)
        own = (reflex[None, :] == (cand[:, None] - 1) % n) | (
            reflex[None, :] == (cand[:, None] + 1) % n
        )
        ears[cand] = ~np.any(inside & ~own, axis=1)
    return ears


def triangulate_polygon(ring: np.ndarray) -> np.ndarray:
    """Triangulate a simple counter-clockwise polygon by ear clipping; return (M-2, 3) indices.

    Unlike a fan from the centroid, this is right for any simple outline, star-shaped or
    not (a bent finger, a crescent), and adds no vertex. Several ears that share no
    vertex are clipped per pass (their diagonals cannot cross), so a convex outline
    takes about log2(M) vectorised passes. Should the outline not be simple (no ear
    left), the rest is closed by a fan from its first vertex.
    """
    pts = np.asarray(ring, dtype=float)
    alive = np.arange(len(pts))
    triangles = []
    while len(alive) > 3:
        ears = _ears(pts, alive)
        if not ears.any():
            rest = alive[1:]
            triangles.append(np.stack([np.full(len(rest) - 1, alive[0]), rest[:-1], rest[1:]], 1))
            alive = alive[:0]
            break
        # Ears at even positions only (odd if none): no two clipped ears are neighbours.
        n = len(alive)
        parity = np.arange(n) % 2
        if n % 2:
            parity[-1] = 2  # n - 1 and 0 are neighbours across the wrap
        pick = ears & (parity == 0)
        if not pick.any():
            pick = ears & (parity == 1)
        if not pick.any() or n - int(pick.sum()) < 3:
            pick = ears & (np.arange(n) == np.flatnonzero(ears)[0])
        k = np.flatnonzero(pick)
        triangles.append(np.stack([alive[(k - 1) % n], alive[k], alive[(k + 1) % n]], 1))
        alive = alive[~pick]
    if len(alive) == 3:
        triangles.append(alive[None, :])
    if not triangles:  # fewer than 3 points enclose nothing
        return np.empty((0, 3), dtype=np.int64)
    return np.concatenate(triangles).astype(np.int64)


def tube_mesh(rings: np.ndarray, z_mm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Join contours sampled at the same parameter values into a closed triangle mesh.

    Ring ``s`` vertex ``j`` joins ring ``s + 1`` by two triangles per quad; each end is
    closed by triangulating the end contour itself (:func:`triangulate_polygon`), so the
    caps are exactly the measured end sections, whatever their shape, with no invented
    vertex. With counter-clockwise rings in ascending z every face normal points outward.

    Args:
        rings: (S, M, 2) contours, S >= 1, M >= 3, counter-clockwise, aligned.
        z_mm: (S,) ascending heights.

    Returns:
        (vertices (S*M, 3), faces (2*M*(S-1) + 2*(M-2), 3)).
    """
    r = np.asarray(rings, dtype=float)
    z = np.asarray(z_mm, dtype=float)
    if r.ndim != 3 or r.shape[2] != 2 or r.shape[1] < 3 or len(z) != len(r):
        raise ValueError(f"rings must be (S, M>=3, 2) with one height each, got {r.shape}")
    n_rings, m = r.shape[:2]
    verts = np.concatenate([r.reshape(-1, 2), np.repeat(z, m)[:, None]], axis=1)
    j = np.arange(m)
    jn = (j + 1) % m
    base = (np.arange(n_rings - 1) * m)[:, None]
    a, b, c, d = base + j, base + jn, base + m + jn, base + m + j
    side = np.concatenate([np.stack([a, b, c], -1), np.stack([a, c, d], -1)], axis=1)
    bottom = triangulate_polygon(r[0])[:, ::-1]  # facing down
    top = triangulate_polygon(r[-1]) + (n_rings - 1) * m
    faces = np.concatenate([side.reshape(-1, 3), bottom, top]).astype(np.int64)
    return verts, faces


def open_tube_mesh(
    rings: np.ndarray, z_mm: np.ndarray, seen: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Join aligned contours like :func:`tube_mesh`, keeping only the surface that was seen.

    A quad between rings ``s`` and ``s + 1`` is kept when all four of its vertices were
    seen; an end is capped only when its whole contour was. What is left is an open
    surface whose boundary runs where nothing was seen (a face seen from the front, a
    limb whose back the views missed). Vertices no kept face uses are dropped.

    Args:
        rings: (S, M, 2) contours, S >= 1, M >= 3, counter-clockwise, aligned.
        z_mm: (S,) ascending heights.
        seen: (S, M) True where a ring's vertex lies on measured surface.

    Returns:
        (vertices (V, 3), faces (F, 3)); all seen gives :func:`tube_mesh`'s mesh.
    """
    r = np.asarray(rings, dtype=float)
    mask = np.asarray(seen, dtype=bool)
    if mask.shape != r.shape[:2]:
        raise ValueError(f"seen must be {r.shape[:2]}, one flag per ring vertex, got {mask.shape}")
    verts, faces = tube_mesh(r, z_mm)
    if mask.all():
        return verts, faces
    n_rings, m = r.shape[:2]
    n_side = 2 * m * (n_rings - 1)
    keep = np.zeros(len(faces), dtype=bool)
    quad = mask[:-1] & mask[1:] & np.roll(mask[:-1], -1, axis=1) & np.roll(mask[1:], -1, axis=1)
    keep[:n_side] = np.concatenate([quad, quad], axis=1).reshape(-1)  # (a, b, c) then (a, c, d)
    cap = (len(faces) - n_side) // 2
    keep[n_side : n_side + cap] = mask[0].all()
    keep[n_side + cap :] = mask[-1].all()
    kept = faces[keep]
    used = np.zeros(len(verts), dtype=bool)
    used[kept.reshape(-1)] = True
    index = np.cumsum(used) - 1
    return verts[used], index[kept].astype(np.int64)


MESH_KINDS = ("closed", "open surface", "non-manifold", "none")
"""What a scan's mesh is: a watertight two-manifold solid; a surface with a boundary (what
was seen of an object not seen all round); closed but with edges or vertices shared by more
than one sheet (from ball pivoting or Poisson); or no mesh at all."""


def mesh_kind(topo: dict[str, Any]) -> str:
    """Return which of ``MESH_KINDS`` a mesh with :func:`topology` ``topo`` is."""
    if not topo or not topo.get("faces"):
        return "none"
    if topo["boundary_edges"]:
        return "open surface"
    return "closed" if topo["two_manifold"] else "non-manifold"


@dataclass(frozen=True)
class MeshTopology:
    """The topological measures of a mesh with faces (:func:`topology`, MeshLab's names)."""

    watertight: bool
    two_manifold: bool
    components: int
    faces: int
    vertices: int
    boundary_edges: int
    non_manifold_edges: int
    non_manifold_vertices: int
    genus: int
    """-1 when undefined (not two-manifold)."""
    volume_mm3: float
    """The signed volume enclosed."""

    @classmethod
    def of(cls, vertices: np.ndarray, faces: np.ndarray) -> MeshTopology | None:
        """Measure a mesh; None when it has no faces (nothing to measure)."""
        if not len(faces):
            return None
        measures: dict[str, Any] = topology(vertices, faces)
        return cls(**measures)

    @classmethod
    def from_dict(cls, measures: dict[str, Any]) -> MeshTopology | None:
        """Return the measures a report recorded; None for none, or too few to read."""
        names = cls.__dataclass_fields__
        if not measures or not all(name in measures for name in names):
            return None
        return cls(**{name: measures[name] for name in names})

    @property
    def kind(self) -> str:
        """Return which of ``MESH_KINDS`` the mesh is."""
        return mesh_kind(self.to_dict())

    def to_dict(self) -> dict[str, Any]:
        """Return the measures in :func:`topology`'s keys and order (the report's form)."""
        return asdict(self)


def screened_poisson(
    points: np.ndarray, normals: np.ndarray, depth: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """Mesh oriented points by MeshLab's screened Poisson reconstruction.

    Args:
        points: (N, 3) vertices in mm.
        normals: (N, 3) or (N, 2) outward normals.
        depth: octree depth (resolution ~ object size / 2^depth).

    Returns:
        (vertices (V, 3), faces (F, 3)).
    """
    pymeshlab = meshlab("poisson")
    pts = _points3(points)
    if len(pts) < 3:
        raise CalibrationError(f"meshing needs at least 3 points, got {len(pts)}")
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=pts, v_normals_matrix=_normals3(normals, len(pts))))
    ms.generate_surface_reconstruction_screened_poisson(depth=depth, preclean=True)
    mesh = ms.current_mesh()
    return (
        np.asarray(mesh.vertex_matrix(), dtype=np.float64),
        np.asarray(mesh.face_matrix(), dtype=np.int64),
    )


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Return the enclosed volume in mm^3 (divergence theorem): positive when faces face out."""
    v = _points3(vertices)[np.asarray(faces, dtype=np.int64)]
    return float(np.einsum("ij,ij->i", v[:, 0], np.cross(v[:, 1], v[:, 2])).sum() / 6.0)


def topology(vertices: np.ndarray, faces: np.ndarray) -> dict[str, int | bool | float]:
    """Return the topological measures of a triangle mesh, as MeshLab defines them.

    Returns:
        dict with watertight (no boundary edges), two_manifold, components (joined by shared
        edges), faces, vertices, boundary_edges, non-manifold edge and vertex counts, genus
        (-1 when undefined: not two-manifold), and the signed volume in mm^3.
    """
    verts = _points3(vertices)
    tris = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    n_faces = len(tris)
    # Each face's three edges (corner k to corner k+1), as sorted vertex pairs.
    half = np.stack([tris, np.roll(tris, -1, axis=1)], axis=2).reshape(-1, 2)
    edges, edge_of, uses = _unique_pairs(np.sort(half, axis=1))
    face_of = np.repeat(np.arange(n_faces), 3)
    components = _components(n_faces + len(edges), face_of, n_faces + edge_of, n_faces)
    boundary = edges[uses == 1]
    holes = _components(len(verts), boundary[:, 0], boundary[:, 1], len(verts), np.unique(boundary))
    # MeshLab counts a non-manifold edge once per face that uses it.
    bad_edges = int(uses[uses > 2].sum())
    bad_vertices = _non_manifold_vertices(tris, half, edges, edge_of)
    manifold = bad_edges == 0 and bad_vertices == 0
    used = len(np.unique(tris))
    genus = -(used - len(edges) + n_faces + holes - 2 * components) // 2 if manifold else -1
    return {
        "watertight": len(boundary) == 0,
        "two_manifold": manifold,
        "components": components,
        "faces": n_faces,
        "vertices": len(verts),
        "boundary_edges": len(boundary),
        "non_manifold_edges": bad_edges,
        "non_manifold_vertices": bad_vertices,
        "genus": genus,
        "volume_mm3": signed_volume(verts, tris) if n_faces else 0.0,
    }


def _components(
    n_nodes: int, a: np.ndarray, b: np.ndarray, count_below: int, among: np.ndarray | None = None
) -> int:
    """Return how many connected components of the graph (a[i]-b[i] links) hold a node
    below ``count_below`` (or, with ``among``, one of those nodes)."""
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(n_nodes, n_nodes))
    labels = connected_components(graph, directed=False)[1]
    nodes = np.arange(count_below) if among is None else among
    return len(np.unique(labels[nodes]))


def _non_manifold_vertices(
    tris: np.ndarray, half: np.ndarray, edges: np.ndarray, edge_of: np.ndarray
) -> int:
    """Return how many vertices have their faces in more than one edge-joined fan."""
    n_corners = tris.size
    corner = np.arange(n_corners)
    nxt = corner - corner % 3 + (corner % 3 + 1) % 3
    # A corner joins the node (edge, end) of both face edges that meet at it.
    node_from = n_corners + 2 * edge_of + (half[:, 0] != edges[edge_of, 0])
    node_to = n_corners + 2 * edge_of + (half[:, 1] != edges[edge_of, 0])
    a = np.concatenate([corner, nxt])
    b = np.concatenate([node_from, node_to])
    graph = coo_matrix((np.ones(len(a)), (a, b)), shape=(n_corners + 2 * len(edges),) * 2)
    labels = connected_components(graph, directed=False)[1][:n_corners]
    fans = _unique_pairs(np.stack([tris.reshape(-1), labels], axis=1))[0][:, 0]
    return int((np.bincount(fans) > 1).sum())


def _unique_pairs(pairs: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return ``np.unique(pairs, axis=0)`` with the inverse and the counts, for (N, 2)
    pairs of non-negative integers.

    Each pair is one integer key (``first * base + second``): a 1-D unique is many times
    faster than the row-wise one, which sorts the rows as opaque records.
    """
    pairs = np.asarray(pairs, dtype=np.int64).reshape(-1, 2)
    base = int(pairs[:, 1].max()) + 1 if len(pairs) else 1
    keys, inverse, counts = np.unique(
        pairs[:, 0] * base + pairs[:, 1], return_inverse=True, return_counts=True
    )
    return np.stack([keys // base, keys % base], axis=1), inverse.reshape(-1), counts


def save_ply(
    path: str | Path,
    vertices: np.ndarray,
    faces: np.ndarray | None = None,
    normals: np.ndarray | None = None,
    colours: np.ndarray | None = None,
) -> None:
    """Write a binary little-endian PLY: float32 vertices, optional normals, colours and faces.

    With ``faces`` None the file is a point cloud: no face element at all.

    Args:
        path: output file.
        vertices: (V, 3) mm.
        faces: optional (F, 3) vertex indices.
        normals: optional (V, 3) or (V, 2) normals.
        colours: optional (V, 3) uint8 sRGB per vertex (``red``, ``green``, ``blue`` uchar).
    """
    verts = _points3(vertices)
    n = len(verts)
    fields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if normals is not None:
        fields += [("nx", "<f4"), ("ny", "<f4"), ("nz", "<f4")]
    if colours is not None:
        fields += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    vrec = np.empty(n, dtype=fields)
    vrec["x"], vrec["y"], vrec["z"] = verts.T
    if normals is not None:
        vrec["nx"], vrec["ny"], vrec["nz"] = _normals3(normals, n).T
    if colours is not None:
        vrec["red"], vrec["green"], vrec["blue"] = _colours3(colours, n).T
    header = ["ply", "format binary_little_endian 1.0", "comment written by Lamina"]
    header += [f"element vertex {n}"]
    header += [f"property {_PLY_TYPES[kind]} {name}" for name, kind in fields]
    body = [vrec.tobytes()]
    if faces is not None:
        f = _faces(faces, n)
        frec = np.empty(len(f), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
        frec["n"] = 3
        frec["idx"] = f
        header += [f"element face {len(f)}", "property list uchar int vertex_indices"]
        body.append(frec.tobytes())
    header.append("end_header")
    with open(path, "wb") as fh:
        fh.write(("\n".join(header) + "\n").encode("ascii"))
        for chunk in body:
            fh.write(chunk)


_PLY_TYPES = {"<f4": "float", "u1": "uchar"}
_PLY_DTYPES = {name: kind for kind, name in _PLY_TYPES.items()}


def _colours3(colours: np.ndarray, n: int) -> np.ndarray:
    """Return validated (n, 3) uint8 colours."""
    rgb = np.asarray(colours)
    if rgb.shape != (n, 3):
        raise ValueError(f"colours must be ({n}, 3), got {rgb.shape}")
    return rgb.astype(np.uint8)


def _faces(faces: np.ndarray, n: int) -> np.ndarray:
    """Return validated (F, 3) int64 indices into ``n`` vertices."""
    f = np.asarray(faces, dtype=np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or (f.size and (f.min() < 0 or f.max() >= n)):
        raise ValueError(f"faces must be (F, 3) indices into {n} vertices")
    return f


def load_ply(data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """Return the float32 vertices (V, 3) and faces (F, 3) of a PLY written by :func:`save_ply`.

    Raises:
        ValueError: the bytes are not a binary little-endian triangle PLY of that layout.
    """
    vertices, faces, _ = load_coloured_ply(data)
    return vertices, faces


def load_coloured_ply(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Return vertices, faces and the (V, 3) uint8 vertex colours (None if uncoloured).

    Reads the PLY layout :func:`save_ply` writes.

    Raises:
        ValueError: the bytes are not a binary little-endian triangle PLY of that layout.
    """
    end = data.find(b"end_header\n")
    if not data.startswith(b"ply\n") or end < 0:
        raise ValueError("not a PLY file")
    header = data[:end].decode("ascii", "replace").splitlines()
    if "format binary_little_endian 1.0" not in header:
        raise ValueError("only binary little-endian PLY files are read")
    counts = {
        words[1]: int(words[2])
        for words in (line.split() for line in header)
        if len(words) == 3 and words[0] == "element"
    }
    fields = [
        (words[2], _PLY_DTYPES[words[1]])
        for words in (line.split() for line in header)
        if len(words) == 3 and words[0] == "property" and words[1] in _PLY_DTYPES
    ]
    n_vertices, n_faces = counts.get("vertex", 0), counts.get("face", 0)
    offset = end + len(b"end_header\n")
    vrec = np.frombuffer(data, fields, n_vertices, offset)
    frec = np.frombuffer(data, [("n", "u1"), ("idx", "<i4", (3,))], n_faces, offset + vrec.nbytes)
    if n_faces and not (frec["n"] == 3).all():
        raise ValueError("only triangle meshes are read")
    vertices = np.stack([vrec["x"], vrec["y"], vrec["z"]], axis=1).astype(np.float32)
    names = vrec.dtype.names or ()
    colours = (
        np.stack([vrec["red"], vrec["green"], vrec["blue"]], axis=1).astype(np.uint8)
        if "red" in names
        else None
    )
    return vertices, frec["idx"].astype(np.int64), colours


def obj_bytes(vertices: np.ndarray, faces: np.ndarray, colours: np.ndarray | None = None) -> bytes:
    """Return a Wavefront OBJ of a triangle mesh, with vertex colours ``v x y z r g b`` if given.

    Colours are written as 0..1 fractions, the vertex-colour extension MeshLab, Blender and
    CloudCompare read; coordinates in mm with 6 decimals (well below a micrometre).
    """
    verts = _points3(vertices)
    f = _faces(faces, len(verts)) + 1  # OBJ counts vertices from 1
    if colours is not None:
        rgb = _colours3(colours, len(verts)).astype(float) / 255.0
        rows = np.column_stack([verts, rgb])
        v_lines = [
            f"v {x:.6f} {y:.6f} {z:.6f} {r:.4f} {g:.4f} {b:.4f}" for x, y, z, r, g, b in rows
        ]
    else:
        v_lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in verts]
    f_lines = [f"f {a} {b} {c}" for a, b, c in f.tolist()]
    return ("\n".join(["# written by Lamina", *v_lines, *f_lines]) + "\n").encode("ascii")


def load_obj(data: bytes) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
    """Return vertices, triangle faces and uint8 vertex colours (None if absent) of an OBJ.

    Reads what :func:`obj_bytes` writes (``v`` and triangular ``f`` lines; ``f a/b/c``
    index forms too).

    Raises:
        ValueError: a line it needs cannot be read.
    """
    verts: list[list[float]] = []
    faces: list[list[int]] = []
    for number, line in enumerate(data.decode("ascii", "replace").splitlines(), start=1):
        words = line.split()
        try:
            if words[:1] == ["v"]:
                verts.append([float(w) for w in words[1:7]])
            elif words[:1] == ["f"]:
                faces.append([int(w.split("/")[0]) - 1 for w in words[1:]])
        except ValueError:
            raise ValueError(f"OBJ line {number} cannot be read: {line[:60]!r}") from None
    if any(len(v) not in (3, 6) for v in verts) or len({len(v) for v in verts}) > 1:
        raise ValueError("OBJ vertices must all have 3 coordinates, or all 3 and a colour")
    if any(len(f) != 3 for f in faces):
        raise ValueError("only triangle OBJ meshes are read")
    table = np.array(verts, float).reshape(-1, 6 if verts and len(verts[0]) == 6 else 3)
    colours = None
    if table.shape[1] == 6:
        colours = np.clip(np.rint(table[:, 3:] * 255.0), 0, 255).astype(np.uint8)
    return table[:, :3], np.array(faces, np.int64).reshape(-1, 3), colours


STL_RECORD = np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])
"""One triangle of a binary STL file (50 bytes)."""


def stl_bytes(vertices: np.ndarray, faces: np.ndarray, title: str = "Lamina mesh") -> bytes:
    """Return a binary STL file of a triangle mesh: float32 coordinates in mm, unit normals."""
    tris = _points3(vertices).astype(np.float32)[np.asarray(faces, dtype=np.int64)]
    normals = np.cross(tris[:, 1] - tris[:, 0], tris[:, 2] - tris[:, 0]).astype(np.float64)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    records = np.zeros(len(tris), STL_RECORD)
    records["normal"] = normals
    records["v"] = tris
    # The header must not start with "solid": readers would take the file for ASCII STL.
    head = title.encode("ascii", "replace")[:80].ljust(80, b" ")
    return head + np.uint32(len(tris)).tobytes() + records.tobytes()


def stl_triangles(data: bytes) -> np.ndarray:
    """Return the (F, 3, 3) float32 triangles of a binary STL file.

    Raises:
        ValueError: the bytes are not a complete binary STL file.
    """
    if len(data) < 84:
        raise ValueError("not a binary STL file (shorter than its header)")
    count = int(np.frombuffer(data, "<u4", 1, 80)[0])
    if len(data) != 84 + count * STL_RECORD.itemsize:
        raise ValueError(f"binary STL file of {count} triangles has the wrong length")
    return np.frombuffer(data, STL_RECORD, count, 84)["v"].copy()
