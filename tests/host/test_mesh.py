"""Tests for lamina_host.mesh: normals, ball pivoting and PLY output (thesis chapter 7)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pymeshlab

from lamina_host.mesh import ball_pivoting, contour_normals, save_ply, topology

R = 9.525


def ring(n: int = 120) -> np.ndarray:
    """Counter-clockwise circle of radius R."""
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return R * np.stack([np.cos(t), np.sin(t)], axis=1)


def test_contour_normals_point_outward_either_orientation() -> None:
    """Normals of a circle are radial whichever way it runs."""
    c = ring()
    radial = c / np.linalg.norm(c, axis=1, keepdims=True)
    assert np.allclose(contour_normals(c), radial, atol=1e-12)
    assert np.allclose(contour_normals(c[::-1]), radial[::-1], atol=1e-12)


def stacked_cylinder() -> tuple[np.ndarray, np.ndarray]:
    """Four rings 2 mm apart (thesis Prototype II test cylinder) with xy normals."""
    c = ring()
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
