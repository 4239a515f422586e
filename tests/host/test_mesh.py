"""Tests for reconstruct.mesh: normals, ball pivoting and PLY output (thesis chapter 7)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pymeshlab
import pytest

from lamina_host.reconstruct.mesh import (
    ball_pivoting,
    contour_normals,
    obj_bytes,
    save_ply,
    screened_poisson,
    signed_volume,
    topology,
    tube_mesh,
)
from tests.helpers.shapes import circle

R = 9.525


def test_contour_normals_point_outward_either_orientation() -> None:
    """Normals of a circle are radial whichever way it runs."""
    c = circle((0.0, 0.0), R, 120)
    radial = c / np.linalg.norm(c, axis=1, keepdims=True)
    assert np.allclose(contour_normals(c), radial, atol=1e-12)
    assert np.allclose(contour_normals(c[::-1]), radial[::-1], atol=1e-12)


def stacked_cylinder() -> tuple[np.ndarray, np.ndarray]:
    """Four rings 2 mm apart (thesis Prototype II test cylinder) with xy normals."""
    c = circle((0.0, 0.0), R, 120)
    pts = np.concatenate([np.column_stack([c, np.full(len(c), 2.0 * k)]) for k in range(4)])
    nrm = np.concatenate([contour_normals(c)] * 4)
    return pts, nrm


def test_ball_pivoting_makes_faces() -> None:
    """Four rings 2 mm apart mesh with a 2 mm ball."""
    pts, nrm = stacked_cylinder()
    verts, faces = ball_pivoting(pts, nrm, 2.0)
    topo = topology(verts, faces)
    print(f"ball pivoting: {len(verts)} vertices, {len(faces)} faces, {topo}")
    assert len(faces) > 0 and faces.shape[1] == 3 and faces.max() < len(verts)
    assert topo["faces"] == len(faces) and topo["vertices"] == len(verts)
    # An open tube: two boundary rings, so not watertight.
    assert not topo["watertight"]


def test_save_ply_round_trip(tmp_path: Path) -> None:
    """PLY files written with numpy load back in MeshLab unchanged."""
    pts, nrm = stacked_cylinder()
    cloud = tmp_path / "cloud.ply"
    save_ply(cloud, pts, normals=nrm)
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(cloud))
    m = ms.current_mesh()
    assert m.vertex_number() == len(pts)
    assert np.allclose(m.vertex_matrix(), pts, atol=1e-5)
    assert np.allclose(m.vertex_normal_matrix()[:, :2], nrm, atol=1e-5)

    verts, faces = ball_pivoting(pts, nrm, 2.0)
    mesh = tmp_path / "mesh.ply"
    save_ply(mesh, verts, faces)
    ms.load_new_mesh(str(mesh))
    m = ms.current_mesh()
    assert m.vertex_number() == len(verts) and m.face_number() == len(faces)
    assert np.array_equal(m.face_matrix(), faces)


def test_tube_mesh_is_closed_manifold_and_outward() -> None:
    """Rings joined and capped: watertight, 2-manifold, genus 0, the cylinder's volume."""
    rings = np.stack([circle((0.0, 0.0), R, 200)] * 4)
    verts, faces = tube_mesh(rings, np.array([0.0, 2.0, 4.0, 6.0]))
    topo = topology(verts, faces)
    print(f"tube mesh: {topo}")
    assert topo["watertight"] and topo["two_manifold"] and topo["genus"] == 0
    assert topo["components"] == 1 and topo["non_manifold_edges"] == 0
    # Positive volume means every face points outward; 200-gon area is 0.05 % under pi R^2.
    assert topo["volume_mm3"] == pytest.approx(np.pi * R**2 * 6.0, rel=1e-3)
    assert signed_volume(verts, faces[:, ::-1]) < 0


def test_screened_poisson_closes_the_stack() -> None:
    """Screened Poisson turns the four rings into a closed surface near the cylinder."""
    pts, nrm = stacked_cylinder()
    verts, faces = screened_poisson(pts, nrm, depth=6)
    assert len(faces) > 100
    radial = np.hypot(verts[:, 0], verts[:, 1])
    mid = (verts[:, 2] > 1.0) & (verts[:, 2] < 5.0)
    assert np.abs(radial[mid] - R).max() < 0.5


def meshlab_topology(verts: np.ndarray, faces: np.ndarray) -> dict[str, int | bool]:
    """Return MeshLab's own topological measures, in topology()'s keys."""
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=verts, face_matrix=np.asarray(faces, np.int32)))
    m = ms.get_topological_measures()
    return {
        "watertight": int(m["boundary_edges"]) == 0,
        "two_manifold": bool(m["is_mesh_two_manifold"]),
        "components": int(m["connected_components_number"]),
        "faces": int(m["faces_number"]),
        "vertices": int(m["vertices_number"]),
        "boundary_edges": int(m["boundary_edges"]),
        "non_manifold_edges": int(m["non_two_manifold_edges"]),
        "non_manifold_vertices": int(m["non_two_manifold_vertices"]),
        "genus": int(m["genus"]),
    }


def topology_cases() -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Closed, open, two-part, pinched (shared vertex) and finned (3-face edge) meshes."""
    rings = np.stack([circle((0.0, 0.0), R, 40)] * 5)
    v, f = tube_mesh(rings, np.arange(5.0) * 2.0)
    pts, nrm = stacked_cylinder()
    both_v = np.concatenate([v, v + np.array([30.0, 0.0, 0.0])])
    both_f = np.concatenate([f, f + len(v)])
    pinched = both_f.copy()
    pinched[pinched == len(v)] = 0
    return {
        "tube": (v, f),
        "open tube": (v, f[:-30]),
        "ball pivoting": ball_pivoting(pts, nrm, 2.0),
        "two tubes": (both_v, both_f),
        "pinched": (both_v, pinched),
        "fin": (both_v, np.concatenate([f, [[0, 1, len(v) + 5]]])),
    }


@pytest.mark.parametrize("name", list(topology_cases()))
def test_topology_matches_meshlab(name: str) -> None:
    """The numpy topology (no pymeshlab needed) gives MeshLab's own figures."""
    verts, faces = topology_cases()[name]
    ours = topology(verts, faces)
    ours.pop("volume_mm3")
    assert ours == meshlab_topology(verts, faces)


def test_obj_bytes_load_in_meshlab(tmp_path: Path) -> None:
    """An OBJ written with numpy loads in MeshLab with the same vertices and faces."""
    verts, faces = tube_mesh(np.stack([circle((0.0, 0.0), R, 40)] * 3), np.array([0.0, 2.0, 4.0]))
    path = tmp_path / "tube.obj"
    path.write_bytes(obj_bytes(verts, faces))
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(str(path))
    m = ms.current_mesh()
    assert np.allclose(m.vertex_matrix(), verts, atol=1e-4)
    assert np.array_equal(m.face_matrix(), faces)
