"""The simulated camera against geometric truth: board corners, stripe rows, occlusion, noise."""

from __future__ import annotations

import struct
import time
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest

from lamina_device.sim import NoiseModel, Rig, SimScene, parse_object

RIG = Rig()


def stripe_centroids(
    on: np.ndarray, off: np.ndarray, frac: float = 0.2, min_peak_dn: float = 20.0
) -> dict[int, float]:
    """Return {column: row} by centre of gravity of the run above ``frac`` of the column peak.

    Weights are (difference - threshold) so a pixel entering or leaving the run does not
    jump the centroid; that keeps the estimator itself unbiased to ~0.01 px.
    """
    diff = on.astype(float) - off.astype(float)
    out = {}
    for u in range(diff.shape[1]):
        col = diff[:, u]
        k = int(np.argmax(col))
        if col[k] < min_peak_dn:
            continue
        thr = frac * col[k]
        lo, hi = k, k
        while lo > 0 and col[lo - 1] > thr:
            lo -= 1
        while hi < len(col) - 1 and col[hi + 1] > thr:
            hi += 1
        w = col[lo : hi + 1] - thr
        out[u] = float(np.sum(np.arange(lo, hi + 1) * w) / np.sum(w))
    return out


def outline_truth(
    scene: SimScene, target: str, angle_deg: float, z_mm: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return projected truth outline (K, 2) px and camera-visible / laser-lit masks.

    The visibility masks use the 2D normal test, exact for a convex body whose normals are
    horizontal at the section (a cylinder wall, an ellipsoid's equator).
    """
    (poly,) = scene.truth_outline(target, z_mm)
    world = RIG.object_to_world(poly, angle_deg, z_mm)
    xy = world[:, :2]
    tangent = np.roll(xy, -1, axis=0) - np.roll(xy, 1, axis=0)
    normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)  # outward for a CCW polygon
    seen = np.einsum("ij,ij->i", normal, RIG.camera_centre_mm[:2] - xy) > 0
    lit = np.einsum("ij,ij->i", normal, np.asarray(RIG.laser_source_xy_mm) - xy) > 0
    return RIG.project(world), seen, lit


def view_pair(scene: SimScene, target: str, angle_deg: float, z_mm: float, key=()):
    """Return the laser-on and laser-off frames of one view."""
    return (
        scene.render(target, angle_deg, z_mm, True, key),
        scene.render(target, angle_deg, z_mm, False, key),
    )


def write_binary_stl(path: Path, tris: np.ndarray) -> None:
    """Write (F, 3, 3) triangles as a binary STL file."""
    with open(path, "wb") as f:
        f.write(b"solid lamina test".ljust(80, b" "))
        f.write(struct.pack("<I", len(tris)))
        for t in tris.astype(np.float32):
            n = np.cross(t[1] - t[0], t[2] - t[0])
            n = n / np.linalg.norm(n)
            f.write(struct.pack("<12fH", *n, *t.ravel(), 0))


def tessellated_cylinder(diameter_mm: float, height_mm: float, sides: int) -> np.ndarray:
    """Return the outward-wound (F, 3, 3) triangles of a closed prism, base at z = 0."""
    phi = np.linspace(0.0, 2.0 * np.pi, sides, endpoint=False)
    ring = np.stack([np.cos(phi), np.sin(phi)], 1) * diameter_mm / 2.0
    nxt = np.roll(ring, -1, axis=0)
    lo = lambda p: np.column_stack([p, np.zeros(len(p))])  # noqa: E731
    hi = lambda p: np.column_stack([p, np.full(len(p), height_mm)])  # noqa: E731
    zero = np.zeros((sides, 3))
    top = np.array([0.0, 0.0, height_mm]) + zero
    return np.concatenate(
        [
            np.stack([lo(ring), lo(nxt), hi(nxt)], 1),
            np.stack([lo(ring), hi(nxt), hi(ring)], 1),
            np.stack([top, hi(ring), hi(nxt)], 1),
            np.stack([zero, lo(nxt), lo(ring)], 1),
        ]
    )


# ----------------------------------------------------------------------------- tests


def test_board_and_outer_squares_inside_image_with_margin():
    """Every inner corner, the outer squares and the paper margin project well inside."""
    board = RIG.board
    nx, ny = board.inner_corners
    sq = board.square_mm
    ox, oy = board.origin_mm
    corners = np.column_stack([board.world_corners(), np.zeros(board.corner_count)])
    outer = np.array(
        [
            [ox - sq, oy - sq],
            [ox + nx * sq, oy - sq],
            [ox - sq, oy + ny * sq],
            [ox + nx * sq, oy + ny * sq],
        ]
    )
    w, h = RIG.image_size
    for pts, margin_px in ((corners[:, :2], 10.0), (outer, 10.0)):
        uv = RIG.project(np.column_stack([pts, np.zeros(len(pts))]))
        assert uv[:, 0].min() >= margin_px and uv[:, 0].max() <= w - 1 - margin_px
        assert uv[:, 1].min() >= margin_px and uv[:, 1].max() <= h - 1 - margin_px
    paper_mm = NoiseModel.thesis().grid_paper_margin_mm
    paper = outer + np.array([[-1, -1], [1, -1], [-1, 1], [1, 1]]) * paper_mm
    uv = RIG.project(np.column_stack([paper, np.zeros(4)]))
    assert uv.min() >= 0 and uv[:, 0].max() <= w - 1 and uv[:, 1].max() <= h - 1


def test_rays_and_projection_agree_on_the_pixel_centre_convention():
    """A point along the ray of pixel (i, j) projects to exactly (i, j)."""
    centre, dirs = RIG.pixel_rays()
    for i, j in ((0, 0), (319, 240), (639, 479), (100, 400)):
        uv = RIG.project((centre + 123.0 * dirs[j, i])[None])
        np.testing.assert_allclose(uv[0], [i, j], atol=1e-9)
    np.testing.assert_allclose(RIG.project(np.array([[*RIG.axis_xy_mm, 0.0]])), [[319.5, 239.5]])


def test_noise_free_grid_corners_match_projection():
    """OpenCV finds the rendered board; sub-pixel corners sit on the projected truth."""
    img = SimScene(RIG, noise=NoiseModel.none()).render("grid", 0.0, 0.0, False)
    found, corners = cv2.findChessboardCorners(img, RIG.board.inner_corners)
    assert found
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 100, 1e-4)
    corners = cv2.cornerSubPix(img, corners, (7, 7), (-1, -1), criteria).reshape(-1, 2)
    board = RIG.board
    truth = RIG.project(np.column_stack([board.world_corners(), np.zeros(board.corner_count)]))
    dist = np.linalg.norm(corners[:, None] - truth[None], axis=2)
    nearest = dist.min(axis=1)
    assert len(set(dist.argmin(axis=1))) == board.corner_count
    rms = float(np.sqrt(np.mean(nearest**2)))
    print(f"grid corner RMS vs projection: {rms:.4f} px")
    assert rms < 0.1


def test_board_edges_are_rendered_exactly():
    """Square edges crossing a column sit on the projected board lines within 0.02 px."""
    flat = replace(NoiseModel.none(), ambient_gradient=(0.0, 0.0), vignette=0.0, shadow_depth=0.0)
    img = SimScene(RIG, noise=flat).render("grid", 0.0, 0.0, False).astype(float)
    board = RIG.board
    sq, (ox, oy) = board.square_mm, board.origin_mm
    errors = []
    for j in range(board.inner_corners[1]):
        for i in range(-1, board.inner_corners[0]):
            xs = np.linspace(ox + (i + 0.25) * sq, ox + (i + 0.75) * sq, 501)
            line = RIG.project(np.column_stack([xs, np.full_like(xs, oy + j * sq), 0 * xs]))
            u = round(float(line[250, 0]))
            v_true = float(np.interp(u, line[:, 0], line[:, 1]))
            r0 = int(np.floor(v_true)) - 4
            col = img[r0 : r0 + 10, u]
            # An anti-aliased step: the edge is where the summed coverage says it is.
            cover = (col - col[-1]) / (col[0] - col[-1])
            errors.append(r0 - 0.5 + cover.sum() - v_true)
    assert np.abs(errors).max() < 0.02


@pytest.mark.parametrize("angle_deg", [0.0, 37.0])
def test_noise_free_cylinder_stripe_matches_true_outline(angle_deg):
    """Per-column stripe COG equals the projected true section within 0.05 px."""
    scene = SimScene(RIG, noise=NoiseModel.none())
    rows = stripe_centroids(*view_pair(scene, "cylinder", angle_deg, 0.0))
    uv, seen, lit = outline_truth(scene, "cylinder", angle_deg, 0.0)
    arc = uv[seen & lit]
    arc = arc[np.argsort(arc[:, 0])]
    slope = np.gradient(arc[:, 1], arc[:, 0])
    cols = np.array([u for u in rows if arc[0, 0] <= u <= arc[-1, 0]])
    # Where the imaged stripe runs steeper than 1:2 a column cut mixes the intensity
    # gradient along the stripe into the COG: an estimator effect, not the renderer's.
    cols = cols[np.abs(np.interp(cols, arc[:, 0], slope)) < 0.5]
    assert len(cols) > 150
    err = np.array([rows[u] for u in cols]) - np.interp(cols, arc[:, 0], arc[:, 1])
    print(f"angle {angle_deg}: {len(cols)} columns, max |err| {np.abs(err).max():.4f} px")
    assert np.abs(err).max() < 0.05
    # No stripe outside the columns where the doubly visible arc projects.
    assert all(arc[0, 0] - 1 <= u <= arc[-1, 0] + 1 for u in rows)


def test_stripe_missing_where_laser_or_camera_cannot_reach():
    """Laser-shadowed but visible arcs are dark; laser-lit arcs hidden from the camera too."""
    obj = parse_object("ellipsoid:a=20,b=4,c=15,yaw=-83")
    scene = SimScene(RIG, obj, NoiseModel.none())
    on, off = view_pair(scene, "object", 0.0, 0.0)
    diff = on.astype(float) - off.astype(float)
    assert diff.max() > 100  # the stripe is there somewhere
    uv, seen, lit = outline_truth(scene, "object", 0.0, 0.0)
    cols = np.rint(uv[:, 0]).astype(int)
    shadowed_only = sorted(set(cols[seen & ~lit]) - set(cols[seen & lit]))
    assert len(shadowed_only) >= 10
    assert diff[:, shadowed_only].max() <= 2
    hidden = uv[~seen & lit]
    near_visible = np.linalg.norm(hidden[:, None] - uv[seen][None], axis=2).min(axis=1) < 6
    hidden = np.rint(hidden[~near_visible]).astype(int)
    assert len(hidden) >= 50
    for dv in (-1, 0, 1):
        assert diff[hidden[:, 1] + dv, hidden[:, 0]].max() <= 2


def test_frames_are_deterministic_and_thesis_noise_has_measured_scatter():
    """Same key -> same bits in any order; new key -> new noise; scatter ~0.05 mm."""
    a = SimScene(RIG, seed=7)
    b = SimScene(RIG, seed=7)
    first = a.render("cylinder", 10.0, 0.0, True, ("x", 1))
    a.render("cylinder", 20.0, 0.0, True)
    a.render("grid", 0.0, 0.0, False)
    assert np.array_equal(first, a.render("cylinder", 10.0, 0.0, True, ("x", 1)))
    assert np.array_equal(first, b.render("cylinder", 10, 0, True, ("x", 1)))
    assert not np.array_equal(first, a.render("cylinder", 10.0, 0.0, True, ("x", 2)))
    assert not np.array_equal(
        first, SimScene(RIG, seed=8).render("cylinder", 10.0, 0.0, True, ("x", 1))
    )
    off1 = a.render("cylinder", 10.0, 0.0, False, (1,))
    off2 = a.render("cylinder", 10.0, 0.0, False, (2,))
    assert not np.array_equal(off1, off2)
    assert abs(float(off1.astype(float).mean() - off2.astype(float).mean())) < 0.5

    clean = SimScene(RIG, noise=NoiseModel.none())
    ref = stripe_centroids(*view_pair(clean, "cylinder", 0.0, 0.0))
    uv, seen, lit = outline_truth(clean, "cylinder", 0.0, 0.0)
    arc = uv[seen & lit]
    arc = arc[np.argsort(arc[:, 0])]
    slope = np.gradient(arc[:, 1], arc[:, 0])
    good = [u for u in ref if abs(np.interp(u, arc[:, 0], slope)) < 0.5]
    err_px, err_mm = [], []
    for k in range(6):
        noisy = stripe_centroids(*view_pair(a, "cylinder", 0.0, 0.0, (k,)))
        for u in good:
            if u in noisy:
                # Map the row error into the laser plane, as triangulation will.
                p = RIG.backproject_to_plane(np.array([[u, ref[u]], [u, noisy[u]]]))
                err_px.append(noisy[u] - ref[u])
                err_mm.append(np.linalg.norm(p[1] - p[0]))
    rms_px = float(np.sqrt(np.mean(np.square(err_px))))
    rms_mm = float(np.sqrt(np.mean(np.square(err_mm))))
    print(f"thesis() per-point scatter: {rms_px:.3f} px RMS = {rms_mm:.4f} mm RMS in the plane")
    assert len(err_px) > 6 * 150
    assert 0.03 <= rms_mm <= 0.07
    assert abs(float(np.mean(err_px))) < 0.05  # noise must not bias the stripe


def test_mesh_cylinder_matches_analytic_cylinder(tmp_path):
    """A 128-sided binary STL cylinder gives the analytic cylinder's stripe within 0.3 px."""
    path = tmp_path / "cyl128.stl"
    write_binary_stl(path, tessellated_cylinder(RIG.cylinder_diameter_mm, 40.0, 128))
    ox, oy = RIG.cylinder_offset_mm
    mesh = parse_object(f"mesh:path={path},x={ox},y={oy},z=-5")
    scene = SimScene(RIG, mesh, NoiseModel.none())
    for angle_deg in (0.0, 101.0):
        t0 = time.perf_counter()
        mesh_rows = stripe_centroids(*view_pair(scene, "object", angle_deg, 3.0))
        elapsed = time.perf_counter() - t0
        ref_rows = stripe_centroids(*view_pair(scene, "cylinder", angle_deg, 3.0))
        common = sorted(set(mesh_rows) & set(ref_rows))
        assert len(common) > 0.95 * len(ref_rows) > 200
        err = np.array([mesh_rows[u] - ref_rows[u] for u in common])
        print(
            f"mesh vs analytic at {angle_deg} deg: max {np.abs(err).max():.3f} px, {elapsed:.2f} s"
        )
        assert np.abs(err).max() < 0.3


@pytest.mark.wall_clock
def test_two_thousand_triangle_mesh_renders_quickly(tmp_path):
    """A 2,000-triangle mesh frame renders in about a second (budget: 2 s on one core)."""
    path = tmp_path / "cyl500.stl"
    write_binary_stl(path, tessellated_cylinder(25.0, 30.0, 500))
    scene = SimScene(RIG, parse_object(f"mesh:path={path},z=-10"), NoiseModel.thesis())
    t0 = time.perf_counter()
    frame = scene.render("object", 15.0, 0.0, True)
    elapsed = time.perf_counter() - t0
    print(f"2000-triangle mesh frame: {elapsed:.2f} s")
    assert frame.dtype == np.uint8 and frame.shape == (480, 640)
    assert elapsed < 4.0


def test_object_target_needs_an_object_and_targets_are_checked():
    """Asking for an absent object or an unknown target is a clear ValueError."""
    scene = SimScene(RIG)
    with pytest.raises(ValueError, match="no object"):
        scene.render("object", 0.0, 0.0, True)
    with pytest.raises(ValueError, match="unknown target"):
        scene.render("teapot", 0.0, 0.0, True)
