"""Ground truth: exact distances to known geometry, the lit-and-seen surface, the alignment."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lamina_device.sim import Mechanics, NoiseModel, Rig, SimScene, TriangleMesh, parse_object
from lamina_device.sim.phantoms import phantom
from lamina_device.sim.truth import (
    Alignment,
    TrueSurface,
    align_about_axis,
    coverage,
    lit_and_seen_points,
    scan_accuracy,
    surface_distance_mm,
)

RNG_SEED = 7


def test_cylinder_distances_are_exact_for_points_offset_by_known_amounts():
    """Radially offset points beside the wall, and points above the cap, by known distances."""
    rng = np.random.default_rng(RNG_SEED)
    cyl = parse_object("cylinder:d=19.05,x=1,y=-2")  # wall r 9.525, z -5..35
    phi, z = rng.uniform(0, 2 * np.pi, 500), rng.uniform(0.0, 30.0, 500)
    offset = rng.uniform(-3.0, 3.0, 500)
    r = 9.525 + offset
    side = np.column_stack([1 + r * np.cos(phi), -2 + r * np.sin(phi), z])
    np.testing.assert_allclose(surface_distance_mm(cyl, side), np.abs(offset), atol=1e-9)
    above = np.column_stack([1 + 4.0 * np.cos(phi), -2 + 4.0 * np.sin(phi), 35.0 + np.abs(offset)])
    np.testing.assert_allclose(surface_distance_mm(cyl, above), np.abs(offset), atol=1e-9)
    corner = np.array([[1 + 9.525 + 3.0, -2.0, 39.0]])  # beyond the rim: to the edge circle
    np.testing.assert_allclose(surface_distance_mm(cyl, corner), [5.0], atol=1e-9)


def test_ellipsoid_distances_match_a_dense_brute_force():
    """Inside, outside and on-axis points against 8 million surface samples (< 5 um)."""
    from scipy.spatial import cKDTree

    ell = parse_object("ellipsoid:a=10,b=6.5,c=20,x=1,yaw=30")
    u, v = np.meshgrid(np.linspace(0, np.pi, 2000), np.linspace(0, 2 * np.pi, 4000))
    local = np.stack(
        [10 * np.sin(u) * np.cos(v), 6.5 * np.sin(u) * np.sin(v), 20 * np.cos(u)], axis=-1
    ).reshape(-1, 3)
    c, s = math.cos(math.radians(30)), math.sin(math.radians(30))
    surface = local @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]]).T + [1, 0, 0]
    rng = np.random.default_rng(RNG_SEED)
    probe = np.vstack(
        [rng.uniform(-15, 15, (40, 3)) * [1, 1, 2], [[1, 0, 0], [1, 0, 10], [1, 0, 25]]]
    )
    brute, _ = cKDTree(surface).query(probe)
    exact = surface_distance_mm(ell, probe)
    assert np.all(exact <= brute + 1e-9)  # samples lie on the surface: never nearer
    np.testing.assert_allclose(exact, brute, atol=0.005)
    assert exact[-3] == pytest.approx(6.5, abs=1e-6)  # the centre: the shortest semi-axis


def test_mesh_distances_are_exact_for_a_cube_and_match_brute_force_on_a_phantom():
    """A 10 mm cube's faces, edges and corners; then every triangle of the bust, brute force."""
    corners = np.array([[x, y, z] for x in (0, 10) for y in (0, 10) for z in (0, 10)], float)
    quads = [[0, 1, 3, 2], [4, 6, 7, 5], [0, 4, 5, 1], [2, 3, 7, 6], [0, 2, 6, 4], [1, 5, 7, 3]]
    tris = np.array(
        [[corners[q[0]], corners[q[k]], corners[q[k + 1]]] for q in quads for k in (1, 2)]
    )
    cube = TriangleMesh.from_triangles(tris)
    probe = np.array([[5, 5, 12.5], [5, 5, 9.2], [13, 5, 13], [-3, -4, 5], [12, 12, 12], [5, 5, 5]])
    expected = [2.5, 0.8, math.hypot(3, 3), 5.0, math.sqrt(12), 5.0]
    np.testing.assert_allclose(surface_distance_mm(cube, probe), expected, atol=1e-12)

    bust = phantom("bust")
    rng = np.random.default_rng(RNG_SEED)
    tri = bust.triangles
    pick = rng.integers(0, len(tri), 150)
    on = np.einsum("ij,ijk->ik", rng.dirichlet([1, 1, 1], 150), tri[pick])
    probe = on + rng.normal(0.0, 1.0, (150, 3)) * rng.choice([0.05, 0.5, 5.0], (150, 1))
    fast = surface_distance_mm(bust, probe)
    # Brute force over every triangle: the closest point of each, exactly, then the minimum.
    from lamina_device.sim.truth import _closest_on_triangles

    pairs_p = np.repeat(probe, len(tri), axis=0)
    pairs_t = np.tile(tri, (len(probe), 1, 1))
    brute = np.linalg.norm(_closest_on_triangles(pairs_p, pairs_t) - pairs_p, axis=1)
    np.testing.assert_allclose(fast, brute.reshape(len(probe), -1).min(axis=1), atol=1e-9)


def test_lit_and_seen_arc_of_a_cylinder_is_the_arc_facing_laser_and_camera():
    """On a cylinder wall both tests reduce to the 2D normal facing the source and the camera."""
    rig = Rig()
    scene = SimScene(rig, parse_object("cylinder:d=19.05"), NoiseModel.thesis())
    mechanics = Mechanics.ideal()
    pts = lit_and_seen_points(scene, [(4.0, 30.0)], mechanics, spacing_mm=0.01)
    assert np.allclose(pts[:, 2], 4.0) and np.allclose(np.hypot(pts[:, 0], pts[:, 1]), 9.525)
    phi = np.linspace(0, 2 * np.pi, 200_000, endpoint=False)
    ring = 9.525 * np.column_stack([np.cos(phi), np.sin(phi)])
    world = rig.object_to_world(ring, 30.0, 4.0)[:, :2]
    normal = world - np.asarray(rig.axis_xy_mm)
    seen = np.sum(normal * (rig.camera_centre_mm[:2] - world), axis=1) > 0
    lit = np.sum(normal * (np.asarray(rig.laser_source_xy_mm) - world), axis=1) > 0
    arc_mm = np.mean(seen & lit) * 2 * np.pi * 9.525
    got = np.arctan2(pts[:, 1], pts[:, 0])
    bins = np.unique(np.floor((got % (2 * np.pi)) / (2 * np.pi) * 2000).astype(int))
    assert len(bins) / 2000 * 2 * np.pi * 9.525 == pytest.approx(arc_mm, rel=0.01)
    inside = np.interp(got % (2 * np.pi), phi, (seen & lit).astype(float))
    assert np.mean(inside > 0.5) > 0.995


def _posts(rig: Rig) -> tuple[TriangleMesh, np.ndarray, np.ndarray]:
    """Two 6 mm posts, the second 9 mm behind the first on the laser's line through it."""
    from lamina_device.sim.phantoms import _loft

    source = np.asarray(rig.laser_source_xy_mm) - np.asarray(rig.axis_xy_mm)
    near = np.array([0.0, -6.0])
    far = near + 9.0 * (near - source) / np.linalg.norm(near - source)
    z = np.linspace(-5.0, 20.0, 6)
    parts = [
        _loft(z, np.ones(6), lambda phi, z: np.full_like(phi, 3.0), lambda z, c=c: tuple(c))
        for c in (near, far)
    ]
    return TriangleMesh.from_triangles(np.concatenate(parts)), near, far


def test_lit_and_seen_points_follow_the_true_mechanics_and_skip_shadows():
    """The eccentric gear moves the lit arc; a post in the shadow of another adds nothing."""
    rig = Rig()
    posts, near, far = _posts(rig)
    scene = SimScene(rig, posts, NoiseModel.thesis())
    ideal = lit_and_seen_points(scene, [(6.0, 0.0)], Mechanics.ideal())
    harsh = lit_and_seen_points(scene, [(6.0, 0.0)], Mechanics.harsh())
    assert np.abs(surface_distance_mm(posts, ideal)).max() < 1e-9
    assert len(ideal) > 100 and not np.array_equal(ideal, harsh)
    on_near = np.linalg.norm(ideal[:, :2] - near, axis=1) < 3.01
    on_far = np.linalg.norm(ideal[:, :2] - far, axis=1) < 3.01
    assert np.all(on_near | on_far)
    assert on_far.sum() < 0.05 * on_near.sum()


def test_coverage_counts_truth_points_within_the_tolerance():
    """A scan 0.2 mm off covers everything at 0.25 mm, one 0.3 mm off nothing."""
    truth = np.column_stack([np.linspace(0, 10, 101), np.zeros(101), np.zeros(101)])
    assert coverage(truth, truth + np.array([0, 0.2, 0])) == 1.0
    assert coverage(truth, truth + np.array([0, 0.3, 0])) == 0.0
    assert coverage(truth, truth[:50] + np.array([0, 0.1, 0])) == pytest.approx(
        50 / 101 + 0.01, abs=0.011
    )
    with pytest.raises(ValueError, match="no lit-and-seen"):
        coverage(np.empty((0, 3)), truth)


def test_alignment_recovers_a_known_frame_error_and_spares_shape_error():
    """Points turned 0.5 deg and shifted are put back; a 0.1 mm swelling stays in the figures."""
    obj = phantom("bust")
    scene = SimScene(Rig(), obj, NoiseModel.thesis())
    views = [(z, a) for z in (2.0, 6.0, 10.0) for a in range(0, 360, 45)]
    truth = lit_and_seen_points(scene, views, Mechanics.ideal(), spacing_mm=0.2)
    frame = Alignment(0.5, (0.3, -0.2))
    moved = frame.apply(truth)
    back = align_about_axis(TrueSurface(obj), moved)
    assert back.angle_deg == pytest.approx(-0.5, abs=2e-3)
    np.testing.assert_allclose(back.apply(moved), truth, atol=2e-3)
    acc = scan_accuracy(obj, moved, moved, truth)
    assert acc.direct.mean_distance_mm > 0.05 and acc.aligned.mean_distance_mm < 0.002
    assert acc.direct.coverage_percent < 60.0 and acc.aligned.coverage_percent == 100.0
    swollen = truth.copy()
    swollen[:, :2] *= 1.0 + 0.1 / 10.0  # ~0.1 mm bigger at the bust's ~10 mm radius
    acc = scan_accuracy(obj, swollen, swollen, truth)
    assert acc.aligned.mean_distance_mm > 0.05
    assert acc.aligned.outlier_percent == 0.0
