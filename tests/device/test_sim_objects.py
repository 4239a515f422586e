"""Simulated objects: spec parsing, exact ray casts, true sections, mesh loaders, laser reach."""

from __future__ import annotations

import numpy as np
import pytest

from lamina_device.sim import Cylinder, parse_object, sphere
from lamina_device.sim.render import laser_reaches


@pytest.mark.parametrize(
    ("spec", "words"),
    [
        ("teapot:d=3", ["unknown object kind", "'teapot'", "cylinder:d=19.05,h=40"]),
        ("cylinder:d=", ["'d' has no value", "cylinder:d=19.05,h=40"]),
        ("cylinder:h=40", ["missing d=", "cylinder:d=19.05,h=40"]),
        ("sphere:d=abc", ["d='abc' is not a number", "sphere:d=25"]),
        ("sphere:d=-4", ["must be a positive number"]),
        ("ellipsoid:a=1,b=2,c=3,q=4", ["unknown key 'q'", "yaw"]),
        ("ellipsoid:a=1,b=2,c", ["'c' is not key=value"]),
        ("mesh:path=/no/such/file.stl", ["file not found", "/no/such/file.stl"]),
    ],
)
def test_parse_object_errors_name_the_bad_part(spec, words):
    """Every malformed spec is a one-line ValueError naming the culprit and the right form."""
    with pytest.raises(ValueError) as err:
        parse_object(spec)
    message = str(err.value)
    assert "\n" not in message
    for word in words:
        assert word in message


def test_parse_object_builds_placed_shapes():
    """Kinds, defaults and placement keys land where the grammar says."""
    cyl = parse_object("cylinder:d=19.05")
    assert isinstance(cyl, Cylinder) and (cyl.height_mm, cyl.z_mm) == (40.0, -5.0)
    ball = parse_object("sphere:d=25,x=1,y=-2,z=3")
    (ring,) = ball.section_outline(3.0)
    np.testing.assert_allclose(ring.mean(axis=0), [1.0, -2.0], atol=1e-9)
    np.testing.assert_allclose(np.hypot(ring[:, 0] - 1, ring[:, 1] + 2), 12.5)
    egg = parse_object("ellipsoid:a=10,b=6.5,c=20,yaw=90")
    (ring,) = egg.section_outline(0.0)
    np.testing.assert_allclose(np.abs(ring).max(axis=0), [6.5, 10.0], atol=1e-6)


def test_outlines_are_dense_closed_ccw_and_empty_off_the_object():
    """Analytic sections: >= 2048 CCW vertices; nothing above the top or below the base."""
    for obj, z in ((parse_object("cylinder:d=10"), 7.0), (sphere(25.0), 4.0)):
        (ring,) = obj.section_outline(z)
        assert len(ring) >= 2048
        area = 0.5 * np.sum(
            ring[:, 0] * np.roll(ring[:, 1], -1) - np.roll(ring[:, 0], -1) * ring[:, 1]
        )
        assert area > 0
    assert parse_object("cylinder:d=10").section_outline(35.5) == []
    assert sphere(25.0).section_outline(-12.6) == []


def test_analytic_raycasts_hit_known_points_with_outward_normals():
    """Rays at a cylinder's wall and cap, and at a sphere, meet them where geometry says."""
    cyl = Cylinder(10.0, 40.0, 0.0, 0.0, -5.0)
    origins = np.array([[-20.0, 0.0, 3.0], [0.0, 0.0, 60.0], [20.0, 20.0, 0.0]])
    dirs = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
    t, n = cyl.raycast(origins, dirs)
    np.testing.assert_allclose(t[:2], [15.0, 25.0])
    assert np.isinf(t[2])
    np.testing.assert_allclose(n[:2], [[-1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], atol=1e-12)
    d = np.array([[0.0, 1.0, 1.0]]) / np.sqrt(2.0)
    t, n = sphere(10.0, z=2.0).raycast(np.array([0.0, -30.0, -28.0]), d)
    hit = np.array([0.0, -30.0, -28.0]) + t[0] * d[0]
    assert abs(np.linalg.norm(hit - [0.0, 0.0, 2.0]) - 5.0) < 1e-9
    np.testing.assert_allclose(n[0], (hit - [0.0, 0.0, 2.0]) / 5.0, atol=1e-12)


def _cube_files(tmp_path):
    """Write the same 10 mm cube (base at z = 0) as ASCII STL, ASCII PLY and OBJ."""
    v = np.array([[x, y, z] for z in (0, 10) for y in (0, 10) for x in (0, 10)], dtype=float)
    quads = [[0, 2, 3, 1], [4, 5, 7, 6], [0, 1, 5, 4], [2, 6, 7, 3], [0, 4, 6, 2], [1, 3, 7, 5]]
    obj = tmp_path / "cube.obj"
    obj.write_text(
        "".join(f"v {a} {b} {c}\n" for a, b, c in v)
        + "".join("f " + " ".join(f"{i + 1}/1/1" for i in q) + "\n" for q in quads)
    )
    ply = tmp_path / "cube.ply"
    ply.write_text(
        "ply\nformat ascii 1.0\nelement vertex 8\nproperty float x\nproperty float y\n"
        "property float z\nelement face 6\nproperty list uchar int vertex_indices\nend_header\n"
        + "".join(f"{a} {b} {c}\n" for a, b, c in v)
        + "".join("4 " + " ".join(map(str, q)) + "\n" for q in quads)
    )
    tris = [(v[q[0]], v[q[k]], v[q[k + 1]]) for q in quads for k in (1, 2)]
    stl = tmp_path / "cube.stl"
    body = "".join(
        "facet normal 0 0 0\nouter loop\n"
        + "".join(f"vertex {p[0]} {p[1]} {p[2]}\n" for p in t)
        + "endloop\nendfacet\n"
        for t in tris
    )
    stl.write_text("solid cube\n" + body + "endsolid cube\n")
    return [stl, ply, obj]


def test_mesh_loaders_agree_on_a_cube(tmp_path):
    """ASCII STL, PLY and OBJ give the same placed cube, its section and its ray hits."""
    for path in _cube_files(tmp_path):
        mesh = parse_object(f"mesh:path={path},x=-5,y=-5,z=-2,scale=1")
        (square,) = mesh.section_outline(3.0)
        assert len(square) == 4 or len(square) == 8  # corners, maybe split by diagonals
        np.testing.assert_allclose(square.min(axis=0), [-5.0, -5.0])
        np.testing.assert_allclose(square.max(axis=0), [5.0, 5.0])
        assert mesh.section_outline(8.5) == []
        dirs = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])
        t, n = mesh.raycast(
            np.array([[1.0, -30.0, 0.0], [1.0, 2.0, 40.0], [-30.0, 30.0, 0.0]]), dirs
        )
        np.testing.assert_allclose(t[:2], [25.0, 32.0])
        assert np.isinf(t[2])
        np.testing.assert_allclose(n[:2], [[0.0, -1.0, 0.0], [0.0, 0.0, 1.0]], atol=1e-12)
        # A pinhole bundle (shared origin) takes the bucketed path: same answers.
        t2, _ = mesh.raycast(
            np.array([1.0, -30.0, 0.0]), np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])
        )
        np.testing.assert_allclose(t2, [25.0, np.inf])


def test_laser_reaches_exactly_the_arc_facing_the_source():
    """For a convex outline the lit set is where the outward normal faces the source."""
    (ring,) = Cylinder(19.05).section_outline(0.0)
    src = np.array([15.0, -85.0])
    tangent = np.roll(ring, -1, axis=0) - np.roll(ring, 1, axis=0)
    normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
    facing = np.einsum("ij,ij->i", normal, src - ring)
    lit = laser_reaches(src, ring, [ring], np.full(len(ring), 1e-3))
    clear = np.abs(facing) > 1e-3 * np.abs(facing).max()  # skip the two tangent points
    assert np.array_equal(lit[clear], facing[clear] > 0)


def test_limb_phantoms_take_skin_relief_of_the_asked_height_and_wavelength():
    """arm:scale=5,relief=0.3,wave=8: the outline departs from the smooth arm's by up to
    about 0.3 mm, in folds whose strongest period round the outline is ~8 mm; the other
    phantoms refuse relief in one line."""
    smooth = parse_object("arm:scale=5").section_outline(40.0)[0]
    relief = parse_object("arm:scale=5,relief=0.3,wave=8").section_outline(40.0)[0]

    def radius(outline: np.ndarray, phi: np.ndarray) -> np.ndarray:
        ang = np.arctan2(outline[:, 1], outline[:, 0])
        order = np.argsort(ang)
        return np.interp(phi, ang[order], np.hypot(*outline[order, :2].T), period=2 * np.pi)

    phi = np.linspace(-np.pi, np.pi, 4096, endpoint=False)
    bumps = radius(relief, phi) - radius(smooth, phi)
    assert 0.2 < np.abs(bumps).max() < 0.35
    spectrum = np.abs(np.fft.rfft(bumps))
    waves = int(np.argmax(spectrum[1:]) + 1)
    perimeter = float(np.sum(np.linalg.norm(np.diff(smooth[:, :2], axis=0), axis=1)))
    assert perimeter / waves == pytest.approx(8.0, rel=0.1)
    with pytest.raises(ValueError, match=r"unknown key .relief."):
        parse_object("hand:relief=0.3")
    with pytest.raises(ValueError, match="wave= needs relief="):
        parse_object("stump:wave=5")


def test_a_mesh_reaching_behind_the_camera_casts_as_brute_force_does():
    """Faces crossing the camera's plane (an object taller than the camera is high) and
    faces behind it are culled or boxed, never tested against every pixel; the hits are
    those of testing every ray against every face."""
    from lamina_device.sim import Rig
    from lamina_device.sim.objects import TriangleMesh, _Nearest

    centre, dirs = Rig().pixel_rays()
    rays = dirs.reshape(-1, 3)[::211]
    # A tall tube around the camera's position: faces in front, crossing and behind it.
    phi = np.linspace(0.0, 2 * np.pi, 40, endpoint=False)
    rings = [np.c_[centre[0] + 30 * np.cos(phi), centre[1] + 30 * np.sin(phi), np.full(40, z)]
             for z in np.linspace(-20.0, centre[2] + 60.0, 12)]  # fmt: skip
    vertices = np.concatenate(rings)
    faces = [(r * 40 + k, r * 40 + (k + 1) % 40, (r + 1) * 40 + k) for r in range(11)
             for k in range(40)]  # fmt: skip
    tube = TriangleMesh.from_triangles(vertices[np.array(faces)])
    t, _ = tube.raycast(centre, rays)
    brute = _Nearest(len(rays))
    origins = np.repeat(centre[None], len(rays), axis=0)
    TriangleMesh._cast_brute(origins, rays, tube.triangles, np.arange(len(tube.triangles)), brute)
    best_t = brute.t
    assert np.isfinite(best_t).sum() > 100  # the tube surrounds the camera: most rays hit
    np.testing.assert_array_equal(np.isfinite(t), np.isfinite(best_t))
    np.testing.assert_allclose(t[np.isfinite(t)], best_t[np.isfinite(best_t)], atol=1e-9)


def test_no_rays_cast_hit_nothing():
    """A truth query with no point to test (nothing lit in a view) is empty, not an error."""
    mesh = parse_object("stump:scale=1")
    t, normals = mesh.raycast(np.zeros(3), np.zeros((0, 3)))
    assert t.shape == (0,) and normals.shape == (0, 3)
    t, normals = mesh.raycast(np.zeros((0, 3)), np.zeros((0, 3)))
    assert t.shape == (0,) and normals.shape == (0, 3)
