"""Tests for reconstruct.calibration: corner detection, DLT homography, grid calibration."""

from __future__ import annotations

from dataclasses import replace

import cv2
import numpy as np
import pytest

from lamina_device.sim import NoiseModel, Rig, SimScene
from lamina_host.reconstruct.calibration import (
    CalibrationError,
    GridCalibration,
    Homography,
    analytical_homography,
    calibrate_grid,
    dlt_homography,
    find_corners,
    fit_plane_map,
    ml_homography,
    outer_corners,
    reprojection_px,
)
from lamina_shared.types import BoardSpec

IMAGE_SIZE = (480, 360)  # (W, H)


def render_board(
    board: BoardSpec, world_to_image: np.ndarray, flip_colour: bool = False, ss: int = 8
) -> np.ndarray:
    """Render an anti-aliased chessboard: ss x ss stratified-jittered samples per pixel.

    Pixel (col, row) covers [col - 0.5, col + 0.5] x [row - 0.5, row + 0.5] so its centre
    is at integer coordinates. Jitter avoids quantising edge positions to 1/ss pixel.
    ``flip_colour`` swaps black and white, which is the board turned 180 degrees.
    """
    nx, ny = board.inner_corners
    sq = board.square_mm
    ox, oy = board.origin_mm
    width, height = IMAGE_SIZE
    inv = np.linalg.inv(world_to_image)
    rng = np.random.default_rng(0)
    base = np.arange(ss) / ss - 0.5
    bu, bv = (g.ravel() for g in np.meshgrid(base, base))
    out = np.empty((height, width))
    for r0 in range(0, height, 40):
        rows = np.arange(r0, min(height, r0 + 40))
        vv, uu = np.meshgrid(rows, np.arange(width), indexing="ij")
        jitter = rng.uniform(0.0, 1.0 / ss, (2, len(rows), width, ss * ss))
        u = uu[..., None] + bu + jitter[0]
        v = vv[..., None] + bv + jitter[1]
        w = inv[2, 0] * u + inv[2, 1] * v + inv[2, 2]
        x = (inv[0, 0] * u + inv[0, 1] * v + inv[0, 2]) / w
        y = (inv[1, 0] * u + inv[1, 1] * v + inv[1, 2]) / w
        a = np.floor((x - ox) / sq)
        b = np.floor((y - oy) / sq)
        inside = (a >= -1) & (a <= nx - 1) & (b >= -1) & (b <= ny - 1)
        black = ((a + b) % 2 == 0) ^ flip_colour
        out[rows] = np.where(inside & black, 30.0, 220.0).mean(axis=-1)
    return np.clip(np.round(out), 0, 255).astype(np.uint8)


def camera_homography(board: BoardSpec) -> np.ndarray:
    """World -> image H of a camera ~30 deg above the plane: far edge narrower and higher."""
    nx, ny = board.inner_corners
    sq = board.square_mm
    ox, oy = board.origin_mm
    x0, x1 = ox - 2 * sq, ox + (nx + 1) * sq
    y0, y1 = oy - 2 * sq, oy + (ny + 1) * sq
    src = np.float32([[x0, y0], [x1, y0], [x1, y1], [x0, y1]])
    dst = np.float32([[55, 335], [425, 322], [362, 78], [112, 86]])
    return cv2.getPerspectiveTransform(src, dst).astype(float)


def project(h: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Apply a 3x3 homography to (N, 2) points."""
    hom = pts @ h[:, :2].T + h[:, 2]
    return hom[:, :2] / hom[:, 2:3]


BOARD = BoardSpec((9, 7), 2.5, (-10.0, 20.0))


@pytest.mark.parametrize("board", [BOARD, BoardSpec((7, 7), 2.5, (-8.0, 20.0))])
@pytest.mark.parametrize("flip_colour", [False, True])
def test_find_corners_subpixel_and_ordered(board: BoardSpec, flip_colour: bool) -> None:
    """Rendered boards give sub-pixel corners in world_corners() order."""
    h = camera_homography(board)
    truth = project(h, board.world_corners())
    image = render_board(board, h, flip_colour=flip_colour)
    nx, ny = board.inner_corners
    found, raw = cv2.findChessboardCornersSB(image, (nx, ny))
    assert found
    # OpenCV's own order does not start at corner (0, 0), so reordering is exercised.
    assert np.linalg.norm(raw.reshape(-1, 2)[0] - truth[0]) > 5.0

    corners = find_corners(image, board)
    err = np.linalg.norm(corners - truth, axis=1)
    rms = float(np.sqrt(np.mean(err**2)))
    print(f"find_corners {nx}x{ny} flip={flip_colour}: rms {rms:.4f} px, max {err.max():.4f}")
    assert corners.shape == (nx * ny, 2) and corners.dtype == np.float64
    assert rms < 0.05
    assert err.max() < 0.15  # every corner matched to its own truth, so order is right


def test_find_corners_without_board_raises() -> None:
    """An image without a board raises CalibrationError naming the board."""
    rng = np.random.default_rng(1)
    image = rng.integers(100, 140, size=(360, 480), dtype=np.uint8)
    with pytest.raises(CalibrationError, match="no chessboard with 9x7 inner corners"):
        find_corners(image, BOARD)


def test_find_corners_rejects_tiny_board_and_odd_images() -> None:
    """Boards under 4 corners and images that are not pictures are refused."""
    image = np.zeros((360, 480), np.uint8)
    with pytest.raises(CalibrationError, match="at least 4 corners"):
        find_corners(image, BoardSpec((1, 3), 2.5, (0.0, 0.0)))
    with pytest.raises(CalibrationError, match="grayscale"):
        find_corners(np.zeros((360, 480), np.float32), BOARD)
    with pytest.raises(CalibrationError, match="no chessboard"):
        find_corners(np.zeros((360, 480, 3), np.uint8), BOARD)


# Image -> world homography typical of a camera ~30 deg above the plane.
H_TRUE = np.array([[0.085, 0.004, -21.0], [0.001, -0.16, 58.0], [0.00002, -0.0011, 1.0]])


def _grid_points() -> tuple[np.ndarray, np.ndarray]:
    world = BOARD.world_corners()
    image = project(np.linalg.inv(H_TRUE), world)
    return image, world


def test_dlt_recovers_exact_homography() -> None:
    """Noise-free points recover the known H to rounding error."""
    image, world = _grid_points()
    h = dlt_homography(image, world)
    assert np.allclose(h.matrix, H_TRUE, rtol=1e-9, atol=1e-12)
    assert np.allclose(h.apply(image), world, atol=1e-9)


def test_dlt_four_point_exact() -> None:
    """Four points in general position determine H exactly."""
    image, world = _grid_points()
    idx = [0, 8, 62, 54]
    h = dlt_homography(image[idx], world[idx])
    assert np.allclose(h.matrix, H_TRUE, rtol=1e-8, atol=1e-11)


def test_dlt_with_noise_63_points() -> None:
    """With 0.5 px noise the 63-point fit is much closer to the truth than the points."""
    image, world = _grid_points()
    rng = np.random.default_rng(2)
    noisy = image + rng.normal(0.0, 0.5, image.shape)
    h = dlt_homography(noisy, world)
    fit_rms = float(np.sqrt(np.mean(np.sum((h.apply(noisy) - world) ** 2, axis=1))))
    true_rms = float(np.sqrt(np.mean(np.sum((h.apply(image) - world) ** 2, axis=1))))
    # What 0.5 px of noise is worth in mm when mapped through the true H.
    noise_rms = float(np.sqrt(np.mean(np.sum((project(H_TRUE, noisy) - world) ** 2, axis=1))))
    print(
        f"DLT 0.5 px noise, 63 pts: input noise {noise_rms:.4f} mm, residual rms "
        f"{fit_rms:.4f} mm, fitted-vs-true map {true_rms:.4f} mm"
    )
    # The least-squares residual cannot beat the noise by much (8 of 126 dof absorbed)...
    assert 0.85 * noise_rms < fit_rms <= noise_rms
    # ...while the fitted map itself is far closer to the truth than any single point.
    assert true_rms < 0.3 * noise_rms


@pytest.mark.parametrize(
    "image",
    [
        np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0], [4.0, 4.0]]),
        np.array([[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [0.0, 1.0]]),
        np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]]),
    ],
    ids=["all-collinear", "three-collinear", "too-few"],
)
def test_dlt_degenerate_raises(image: np.ndarray) -> None:
    """Collinear or too few points raise CalibrationError."""
    world = image * 2.0 + 1.0
    with pytest.raises(CalibrationError):
        dlt_homography(image, world)


def test_homography_apply_vectorised() -> None:
    """apply on many points equals apply point by point."""
    h = Homography(H_TRUE)
    pts = np.array([[100.0, 200.0], [300.0, 50.0]])
    one = np.vstack([h.apply(p[None]) for p in pts])
    assert np.allclose(h.apply(pts), one)


def test_calibrate_grid_end_to_end() -> None:
    """A rendered board calibrates to micrometre residuals without warnings."""
    h = camera_homography(BOARD)
    cal = calibrate_grid(render_board(BOARD, h), BOARD)
    print(f"calibrate_grid: rms {cal.rms_mm:.5f} mm, max {cal.max_mm:.5f} mm")
    assert cal.n_corners == 63 and cal.warnings == ()
    assert cal.rms_mm < 0.01
    assert np.allclose(
        cal.residuals_mm,
        np.linalg.norm(cal.homography.apply(cal.image_pts) - cal.world_pts, axis=1),
    )
    # The recovered map agrees with the true image -> world map across the board.
    truth_h = np.linalg.inv(h)
    probe = project(h, BOARD.world_corners())
    assert np.abs(cal.homography.apply(probe) - project(truth_h, probe)).max() < 0.01
    d = cal.to_dict()
    assert d["n_corners"] == 63 and len(d["residuals_mm"]) == 63 and len(d["matrix"]) == 3


def test_calibrate_grid_warns_on_few_corners() -> None:
    """A 12-corner board calibrates with the thesis' 20-point warning."""
    board = BoardSpec((4, 3), 5.0, (-10.0, 20.0))
    cal = calibrate_grid(render_board(board, camera_homography(board)), board)
    assert cal.n_corners == 12
    assert any("at least 20" in w for w in cal.warnings)


def test_pixel_centre_convention_on_the_simulators_board() -> None:
    """Corners found on the simulator's rendered board sit where Rig.project puts them.

    Pixel (col, row) has its centre at u = col, v = row in both the renderer and OpenCV's
    corner detector; a half-pixel convention slip would show as a 0.5 px mean offset.
    """
    rig = Rig()
    image = SimScene(rig).render("grid", 0.0, 0.0, False)
    found = find_corners(image, rig.board)
    world = rig.board.world_corners()
    truth = rig.project(np.column_stack([world, np.zeros(len(world))]))
    offset = (found - truth).mean(axis=0)
    rms = float(np.sqrt(np.mean(np.sum((found - truth) ** 2, axis=1))))
    print(f"sim board: mean offset {offset} px, rms {rms:.4f} px")
    assert np.all(np.abs(offset) < 0.02)
    assert rms < 0.1
    cal = calibrate_grid(image, rig.board)
    # The fitted map agrees with the true back-projection to a few micrometres.
    probe = truth + np.array([3.0, -2.0])
    assert np.abs(cal.homography.apply(probe) - rig.backproject_to_plane(probe)).max() < 0.005
    assert cal.method == "ml" and cal.rejected == [] and cal.warnings == ()


def test_analytical_four_points_exact_and_refuses_other_counts() -> None:
    """The thesis' 4-point method reproduces H exactly and takes exactly 4 pairs."""
    image, world = _grid_points()
    idx = outer_corners(world)
    assert sorted(idx.tolist()) == [0, 8, 54, 62]
    h = analytical_homography(image[idx], world[idx])
    assert np.allclose(h.matrix, H_TRUE, rtol=1e-8, atol=1e-11)
    with pytest.raises(CalibrationError, match="exactly 4"):
        analytical_homography(image[:5], world[:5])
    with pytest.raises(CalibrationError, match="collinear"):
        analytical_homography(image[[0, 1, 2, 62]], world[[0, 1, 2, 62]])


def test_ml_exact_and_beats_dlt_on_average() -> None:
    """ML is exact without noise and, on the same noisy corners, closer to truth than the DLT."""
    image, world = _grid_points()
    assert np.allclose(ml_homography(image, world).matrix, H_TRUE, rtol=1e-8, atol=1e-11)
    rng = np.random.default_rng(11)
    probe = image[outer_corners(world)]
    truth = world[outer_corners(world)]
    dlt_err, ml_err = [], []
    for _ in range(100):
        noisy = image + rng.normal(0.0, 1.5, image.shape)
        dlt_err.append(np.linalg.norm(dlt_homography(noisy, world).apply(probe) - truth, axis=1))
        ml_err.append(np.linalg.norm(ml_homography(noisy, world).apply(probe) - truth, axis=1))
    print(f"1.5 px noise: DLT {np.mean(dlt_err):.4f} mm, ML {np.mean(ml_err):.4f} mm")
    assert np.mean(ml_err) < np.mean(dlt_err)
    # ML minimises reprojection error, so its image residuals are never larger.
    noisy = image + rng.normal(0.0, 1.5, image.shape)
    ml_rms = np.sqrt(np.mean(reprojection_px(ml_homography(noisy, world), noisy, world) ** 2))
    dlt_rms = np.sqrt(np.mean(reprojection_px(dlt_homography(noisy, world), noisy, world) ** 2))
    assert ml_rms <= dlt_rms + 1e-9


def test_misdetected_corners_are_rejected() -> None:
    """Three corners moved by several pixels are rejected; the fit ignores them."""
    image, world = _grid_points()
    rng = np.random.default_rng(12)
    noisy = image + rng.normal(0.0, 0.05, image.shape)
    bad = [5, 30, 47]
    noisy[bad] += np.array([[6.0, -4.0], [-3.0, 9.0], [12.0, 0.0]])
    h, used = fit_plane_map(noisy, world, "ml")
    assert np.flatnonzero(~used).tolist() == bad
    probe = image[outer_corners(world)]
    err = np.linalg.norm(h.apply(probe) - world[outer_corners(world)], axis=1).max()
    naive = np.linalg.norm(
        dlt_homography(noisy, world).apply(probe) - world[outer_corners(world)], axis=1
    ).max()
    print(f"with 3 outliers: robust ML {err:.4f} mm, plain DLT {naive:.4f} mm")
    assert err < 0.01 < naive
    # Without outliers nothing is rejected, even with realistic detector noise.
    _, used = fit_plane_map(image + rng.normal(0.0, 0.05, image.shape), world, "ml")
    assert used.all()


def test_division_distortion_estimated_jointly() -> None:
    """Corners seen through a division-model lens give back k, and the map undoes it."""
    rig = Rig()
    world = rig.board.world_corners()
    ideal = rig.project(np.column_stack([world, np.zeros(len(world))]))
    centre = np.array(rig.principal_point_px)
    radius = float(np.linalg.norm(ideal - centre, axis=1).max())
    k_true = -0.01  # barrel: about 3 px at the board's far corner
    # Distort by inverting u = c + d / (1 + k |d|^2 / R^2) with a fixed-point iteration.
    distorted = ideal.copy()
    for _ in range(50):
        d = distorted - centre
        distorted = centre + (ideal - centre) * (
            1.0 + k_true * np.sum(d * d, 1, keepdims=True) / radius**2
        )
    rng = np.random.default_rng(13)
    noisy = distorted + rng.normal(0.0, 0.03, distorted.shape)
    plain, _ = fit_plane_map(noisy, world, "ml", centre_px=tuple(centre))
    lens, used = fit_plane_map(noisy, world, "ml", distortion=True, centre_px=tuple(centre))
    assert used.all()
    k = lens.division_k * (radius / lens.radius_px) ** 2
    err_plain = np.linalg.norm(plain.apply(distorted) - world, axis=1).max()
    err_lens = np.linalg.norm(lens.apply(distorted) - world, axis=1).max()
    print(f"division k {k:.5f} (true {k_true}); max error {err_plain:.4f} -> {err_lens:.4f} mm")
    assert k == pytest.approx(k_true, rel=0.05)
    assert err_lens < 0.005 < err_plain


def test_calibrate_grid_methods_and_bad_method() -> None:
    """Every method calibrates the rendered board; an unknown method is one clear error."""
    h = camera_homography(BOARD)
    image = render_board(BOARD, h)
    results = {m: calibrate_grid(image, BOARD, method=m) for m in ("ml", "dlt", "analytical")}
    assert results["analytical"].n_corners == 4
    assert any("at least 20" in w for w in results["analytical"].warnings)
    for m, cal in results.items():
        assert cal.to_dict()["method"] == m and cal.rms_mm < 0.02, m
    with pytest.raises(CalibrationError, match="unknown calibration method"):
        calibrate_grid(image, BOARD, method="magic")


def _field_error_mm(rig: Rig, cal: GridCalibration, reach_mm: float) -> float:
    """Return the plane map's largest error in mm over a disc about the axis (the stripes)."""
    phi, radius = np.meshgrid(np.linspace(0, 2 * np.pi, 90), np.linspace(0.1, 1.0, 8) * reach_mm)
    xy = np.asarray(rig.axis_xy_mm) + np.column_stack(
        [(radius * np.cos(phi)).ravel(), (radius * np.sin(phi)).ravel()]
    )
    uv = rig.project(np.column_stack([xy, np.zeros(len(xy))]))
    return float(np.linalg.norm(cal.homography.apply(uv) - xy, axis=1).max())


@pytest.mark.parametrize("lens_k", [-0.02, -0.1])
def test_lens_distortion_is_found_on_the_board_by_default(lens_k: float) -> None:
    """A barrel lens (the harsh preset's, 4 px at the image corners; a wide lens's, 20 px):
    the default calibration keeps a coefficient, the corners' residual falls to their noise
    and the map is right over the field; --distortion off keeps the bend (and says so).
    The limb camera's figures are in ``bench_calibration``."""
    rig_name, reach_mm = "thesis", 15.0
    noise = replace(NoiseModel.harsh(), lens_division_k=lens_k)
    scene = SimScene(Rig.preset(rig_name), None, noise)
    rig, image = scene.rig, scene.render("grid", 0.0, 0.0, False)
    auto = calibrate_grid(image, rig.board)
    test = auto.distortion
    assert test is not None and test.mode == "auto" and test.significant and test.applied
    assert auto.homography.division_k == test.division_k < 0.0  # barrel
    assert test.rms_px_with < 0.08 < 2.0 * test.rms_px_with < test.rms_px_without
    assert test.rms_mm_with < test.rms_mm_without
    reported = auto.to_dict()["distortion"]
    assert reported["division_k"] == test.division_k and reported["applied"]
    assert {"rms_px_without", "rms_px_with", "rms_mm_without", "rms_mm_with"} <= set(reported)
    off = calibrate_grid(image, rig.board, distortion="off")
    assert off.homography.division_k == 0.0 and off.distortion.significant
    assert any("shows lens distortion" in w for w in off.warnings)
    errors = (_field_error_mm(rig, auto, reach_mm), _field_error_mm(rig, off, reach_mm))
    print(f"{rig_name} k {lens_k}: F {test.f_statistic:.0f}, field error {errors} mm")
    assert errors[0] < 0.015 < 4 * errors[0] < errors[1]


def test_a_pinhole_camera_gets_no_distortion() -> None:
    """No lens distortion: the F test finds none to keep (noisy and noise-free boards, the
    harsh preset's light through a pinhole); --distortion on still fits it, next to nothing."""
    for noise in (NoiseModel.thesis(), NoiseModel.none(), NoiseModel.harsh()):
        scene = SimScene(Rig(), None, replace(noise, lens_division_k=0.0))
        image = scene.render("grid", 0.0, 0.0, False)
        cal = calibrate_grid(image, scene.rig.board)
        assert cal.distortion is not None and not cal.distortion.significant
        assert not cal.distortion.applied and cal.homography.division_k == 0.0
        assert cal.distortion.f_statistic < cal.distortion.f_critical / 3
        on = calibrate_grid(image, scene.rig.board, distortion="on")
        assert on.distortion.applied and abs(on.homography.division_k) < 1e-3
    with pytest.raises(CalibrationError, match="only estimated by the 'ml' method"):
        calibrate_grid(image, scene.rig.board, "dlt", "on")
    assert calibrate_grid(image, scene.rig.board, "dlt").distortion is None
