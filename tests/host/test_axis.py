"""Tests for lamina_host.reconstruct.axis: circle fitting and the turntable axis (thesis 6.2)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from lamina_host.reconstruct.assembly import trim
from lamina_host.reconstruct.axis import (
    find_axis,
    find_axis_joint,
    fit_circle,
    gear_advice,
    gear_ratio_factor,
)
from lamina_host.reconstruct.calibration import CalibrationError

R_CYL = 9.525  # thesis test cylinder, 19.05 mm diameter


def arc(
    centre: tuple[float, float],
    r: float,
    start_deg: float,
    span_deg: float,
    n: int,
    sigma: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Points on a circular arc with isotropic Gaussian noise."""
    t = np.deg2rad(start_deg + np.linspace(0.0, span_deg, n))
    pts = np.stack([centre[0] + r * np.cos(t), centre[1] + r * np.sin(t)], axis=1)
    return pts + rng.normal(0.0, sigma, pts.shape)


def kasa(pts: np.ndarray) -> tuple[float, float, float]:
    """Kasa's algebraic fit, for comparison: biased towards small circles on short arcs."""
    x, y = pts.T
    a = np.stack([x, y, np.ones_like(x)], axis=1)
    sol, *_ = np.linalg.lstsq(a, x * x + y * y, rcond=None)
    cx, cy = sol[0] / 2, sol[1] / 2
    return cx, cy, float(np.sqrt(sol[2] + cx * cx + cy * cy))


def test_fit_circle_exact() -> None:
    """Noise-free arc points give the circle exactly."""
    pts = arc((3.0, -2.0), 5.0, 10.0, 100.0, 20, 0.0, np.random.default_rng(0))
    c = fit_circle(pts)
    assert c.cx == pytest.approx(3.0, abs=1e-9) and c.cy == pytest.approx(-2.0, abs=1e-9)
    assert c.r == pytest.approx(5.0, abs=1e-9) and c.rms_mm < 1e-9


def test_fit_circle_short_arc_unbiased() -> None:
    """On a noisy 60 deg arc the radius is unbiased, unlike Kasa's fit."""
    rng = np.random.default_rng(3)
    ours, theirs = [], []
    for _ in range(100):
        pts = arc((1.0, 2.0), R_CYL, -120.0, 60.0, 500, 0.02, rng)
        c = fit_circle(pts)
        ours.append((c.r - R_CYL, np.hypot(c.cx - 1.0, c.cy - 2.0)))
        k = kasa(pts)
        theirs.append((k[2] - R_CYL, np.hypot(k[0] - 1.0, k[1] - 2.0)))
    ours_a, theirs_a = np.array(ours), np.array(theirs)
    print(
        f"60 deg arc, sigma 0.02: radius error mean {ours_a[:, 0].mean():+.4f} "
        f"max |{np.abs(ours_a[:, 0]).max():.4f}| (Kasa mean {theirs_a[:, 0].mean():+.4f}); "
        f"centre error mean {ours_a[:, 1].mean():.4f} (Kasa {theirs_a[:, 1].mean():.4f})"
    )
    # A single 60 deg arc cannot pin the radius to 0.02 mm (its spread is ~0.02 mm at
    # K = 500), so the bias is judged on the mean of 100 fits (standard error ~0.002 mm).
    assert abs(ours_a[:, 0].mean()) < 0.006
    assert np.sqrt(np.mean(ours_a[:, 0] ** 2)) < 0.03
    assert theirs_a[:, 0].mean() < -0.02  # Kasa shrinks the circle on short arcs
    assert ours_a[:, 1].mean() < theirs_a[:, 1].mean()


def test_fit_circle_errors() -> None:
    """Too few or collinear points raise CalibrationError."""
    with pytest.raises(CalibrationError):
        fit_circle(np.array([[0.0, 0.0], [1.0, 1.0]]))
    with pytest.raises(CalibrationError):
        fit_circle(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]))


def cylinder_arcs(
    axis: tuple[float, float], offset: float, r: float, scale: float, rng: np.random.Generator
) -> list[np.ndarray]:
    """8 camera-facing 160 deg arcs of a cylinder offset from the axis, at 45 deg steps."""
    arcs = []
    for k in range(8):
        th = np.deg2rad(45.0 * k + 20.0)
        centre = (axis[0] + offset * np.cos(th), axis[1] + offset * np.sin(th))
        # The camera looks along +y, so it sees the side facing -y: angles -170..-10 deg.
        pts = arc(centre, r, -170.0, 160.0, 300, 0.01, rng)
        pts = np.asarray(axis) + scale * (pts - np.asarray(axis))
        arcs.append(trim(pts))
    return arcs


def test_find_axis_recovers_axis_and_scale() -> None:
    """8 arcs of an off-centre cylinder give the axis and C_f ~ 1."""
    axis = (-3.2, 41.7)
    cal = find_axis(cylinder_arcs(axis, 1.5, R_CYL, 1.0, np.random.default_rng(4)), 2 * R_CYL)
    err = np.hypot(cal.axis_xy_mm[0] - axis[0], cal.axis_xy_mm[1] - axis[1])
    print(f"find_axis: axis error {err:.5f} mm, C_f {cal.correction_factor:.6f}")
    assert err < 0.01
    assert abs(cal.correction_factor - 1.0) < 1e-3
    assert cal.warnings == ()
    assert cal.arc_centres_mm.shape == (8, 2) and cal.arc_radii_mm.shape == (8,)
    assert np.allclose(np.hypot(*(cal.arc_centres_mm - axis).T), 1.5, atol=0.02)
    assert cal.to_dict()["axis_xy_mm"] == list(cal.axis_xy_mm)


def test_find_axis_warns_on_scale_error() -> None:
    """A 7 % scale error gives C_f ~ 1/1.07 and a warning."""
    arcs = cylinder_arcs((0.0, 40.0), 1.5, R_CYL, 1.07, np.random.default_rng(5))
    cal = find_axis(arcs, 2 * R_CYL)
    assert cal.correction_factor == pytest.approx(1 / 1.07, abs=2e-3)
    assert len(cal.warnings) == 1 and "correction factor" in cal.warnings[0]


def test_find_axis_needs_three_arcs() -> None:
    """Fewer than 3 arcs or a bad diameter raise CalibrationError."""
    arcs = cylinder_arcs((0.0, 40.0), 1.5, R_CYL, 1.0, np.random.default_rng(6))
    with pytest.raises(CalibrationError, match="at least 3"):
        find_axis(arcs[:2], 2 * R_CYL)
    with pytest.raises(CalibrationError, match="diameter"):
        find_axis(arcs, -1.0)


def turned_centres(
    axis: tuple[float, float], offset: tuple[float, float], angles_deg: list[float], scale: float
) -> list[tuple[float, float]]:
    """Return where a cylinder at object-frame ``offset`` stands at each commanded angle.

    The turntable really turns ``scale`` x the commanded angle (undershoot when < 1).
    """
    centres = []
    for angle in angles_deg:
        th = np.deg2rad(scale * angle)
        rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
        x, y = np.asarray(axis) + rot @ np.asarray(offset)
        centres.append((float(x), float(y)))
    return centres


def world_arcs(
    axis: tuple[float, float],
    offset: tuple[float, float],
    r: float,
    angles_deg: list[float],
    scale: float,
    rng: np.random.Generator,
) -> list[np.ndarray]:
    """Camera-facing arcs of a cylinder at object-frame ``offset``, turned to each angle."""
    centres = turned_centres(axis, offset, angles_deg, scale)
    return [trim(arc(c, r, -170.0, 160.0, 300, 0.02, rng)) for c in centres]


def test_a_gear_fitted_over_three_turns_places_a_view_forty_turns_on() -> None:
    """The cylinder seen at 8 angles on each of three turns (the default plan's counts) of
    a table 0.2 degrees short per 45 with an off-centre gear's 0.15 degree once-per-turn
    error: the fit's scale and once-per-turn term put a view forty turns on (a leg's top
    section) within 0.15 degrees of where the table really is (corrected within the turn
    it would stand 64 degrees off). What is left is the scale's own precision over three
    turns, some 5e-6 at this stripe noise, times forty turns."""
    axis, offset = (0.6, -0.4), (6.0, -3.0)
    scale = 1.0 - 0.2 / 45.0

    def true_deg(count: np.ndarray) -> np.ndarray:
        return scale * count + 0.15 * np.sin(np.deg2rad(count + 40.0))

    counts = np.array([360.0 * turn + 45.0 * k for turn in range(3) for k in range(8)])
    centres = turned_centres(axis, offset, list(true_deg(counts)), 1.0)
    rng = np.random.default_rng(11)
    arcs = [trim(arc(c, R_CYL, -170.0, 160.0, 300, 0.02, rng)) for c in centres]
    cal = find_axis_joint(arcs, list(counts), 2 * R_CYL, fit_angle_scale=True, fit_radius=False)
    far = 360.0 * 40 + np.array([0.0, 45.0, 135.0, 270.0])
    # The frame starts at count 0: compare the turn since then.
    error_deg = (cal.true_angle_deg(far) - cal.true_angle_deg(0.0)) - (
        true_deg(far) - true_deg(0.0)
    )
    print(f"scale {cal.angle_scale - scale:+.2e} off, wave {cal.angle_wave_deg}, "
          f"forty turns on {np.round(error_deg, 4)} deg")  # fmt: skip
    assert np.abs(error_deg).max() < 0.15
    assert cal.angle_scale == pytest.approx(scale, abs=1e-5)
    a, b = cal.angle_wave_deg  # the gear's 0.15 sin(count + 40): a = 0.115, b = 0.096
    assert a == pytest.approx(0.15 * np.cos(np.deg2rad(40.0)), abs=0.02)
    assert b == pytest.approx(0.15 * np.sin(np.deg2rad(40.0)), abs=0.02)


def test_a_scale_the_cylinder_cannot_tell_from_one_is_held_at_one() -> None:
    """A tooth-exact belt has no shortfall: the fitted scale's noise would be multiplied
    by every turn of a long scan, so within three standard errors of 1 it is exactly 1;
    the thesis motor's 0.2 per 45 stands hundreds of them off and is kept."""
    axis, offset = (0.6, -0.4), (6.0, -3.0)
    counts = [360.0 * turn + 45.0 * k for turn in range(3) for k in range(8)]
    fits = {}
    for scale in (1.0, 1.0 - 0.2 / 45.0):
        centres = turned_centres(axis, offset, counts, scale)
        rng = np.random.default_rng(5)
        arcs = [trim(arc(c, R_CYL, -170.0, 160.0, 300, 0.02, rng)) for c in centres]
        fits[scale] = find_axis_joint(
            arcs, counts, 2 * R_CYL, fit_angle_scale=True, fit_radius=False
        )
    exact, short = fits[1.0], fits[1.0 - 0.2 / 45.0]
    assert exact.angle_scale == 1.0 and 0.0 < exact.angle_scale_sd < 3e-5
    assert exact.to_dict()["angle_scale_sd"] == exact.angle_scale_sd
    assert abs(short.angle_scale - 1.0) > 100 * short.angle_scale_sd
    assert short.angle_scale == pytest.approx(1.0 - 0.2 / 45.0, abs=3 * short.angle_scale_sd)


def test_a_table_short_of_its_count_is_named_with_the_gear_ratio_that_mends_it() -> None:
    """The calibration names the ``gear_ratio`` factor (1 / scale) where a turn misses its
    count by more than 0.05 degrees (what a laser-off frame a turn later may), in
    ``report.json`` and as a line for the technician; a scale held at 1, or one whose turn
    misses by less, needs nothing."""
    axis, offset = (0.6, -0.4), (6.0, -3.0)
    counts = [360.0 * turn + 45.0 * k for turn in range(3) for k in range(8)]
    fits = {}
    for scale in (1.0, 1.0 - 0.2 / 45.0, 1.0 + 0.1 / 45.0):
        centres = turned_centres(axis, offset, counts, scale)
        rng = np.random.default_rng(5)
        arcs = [trim(arc(c, R_CYL, -170.0, 160.0, 300, 0.02, rng)) for c in centres]
        fits[scale] = find_axis_joint(
            arcs, counts, 2 * R_CYL, fit_angle_scale=True, fit_radius=False
        )
    exact, short, long = fits.values()
    assert gear_ratio_factor(exact) is None and gear_advice(exact) is None
    assert exact.to_dict()["gear_ratio_factor"] is None
    factor = gear_ratio_factor(short)
    assert factor == pytest.approx(1.0 / short.angle_scale) and factor > 1.0
    assert factor == pytest.approx(45.0 / 44.8, abs=3e-5)
    assert short.to_dict()["gear_ratio_factor"] == factor
    line = gear_advice(short)
    miss_deg = 360.0 * (1.0 - short.angle_scale)
    assert miss_deg == pytest.approx(1.6, abs=0.02)
    assert line is not None and f"{miss_deg:.2f} degrees short of its step count" in line
    assert f"gear_ratio in the box's configuration by {factor:.5f}" in line
    advice = gear_advice(long)
    assert advice is not None and "degrees beyond its step count" in advice
    assert 360.0 * (long.angle_scale - 1.0) == pytest.approx(0.8, abs=0.02)
    # A miss within the tolerance, or a scale that is no number, names nothing; nor does
    # one the cylinder cannot tell from the tolerance (within three standard errors).
    exact_sd = replace(short, angle_scale_sd=0.0)
    for scale in (1.0 + 0.049 / 360.0, 1.0 - 0.049 / 360.0, float("nan"), 0.0):
        assert gear_ratio_factor(replace(exact_sd, angle_scale=scale)) is None
    assert gear_ratio_factor(replace(exact_sd, angle_scale=1.0 + 0.051 / 360.0)) is not None
    unsure = replace(short, angle_scale=1.0 + 0.06 / 360.0, angle_scale_sd=0.01 / 360.0)
    assert gear_ratio_factor(unsure) is None
    assert gear_ratio_factor(replace(unsure, angle_scale_sd=0.003 / 360.0)) is not None


def test_joint_fit_beats_centroid_on_uneven_views() -> None:
    """Five views over half a turn: the centroid of arc centres is off, the joint fit is not."""
    axis, offset = (-3.2, 41.7), (1.5, -0.8)
    angles = [0.0, 45.0, 90.0, 135.0, 180.0]
    arcs = world_arcs(axis, offset, R_CYL, angles, 1.0, np.random.default_rng(7))
    joint = find_axis_joint(arcs, angles, 2 * R_CYL)
    thesis = find_axis(arcs, 2 * R_CYL)
    err_joint = np.hypot(*(np.asarray(joint.axis_xy_mm) - axis))
    err_thesis = np.hypot(*(np.asarray(thesis.axis_xy_mm) - axis))
    print(f"uneven views: joint axis error {err_joint:.4f} mm, centroid {err_thesis:.4f} mm")
    assert err_joint < 0.01 < 0.5 < err_thesis
    assert np.allclose(joint.cylinder_offset_mm, offset, atol=0.01)
    assert joint.correction_factor == pytest.approx(1.0, abs=5e-4)
    assert joint.method == "joint" and joint.to_dict()["method"] == "joint"


def test_joint_fit_recovers_turntable_undershoot() -> None:
    """0.2 degrees undershoot per 45 degrees is measured from an off-centre cylinder."""
    axis, offset = (0.6, -0.4), (3.0, -1.5)
    angles = [45.0 * k for k in range(8)]
    scale = 1.0 - 0.2 / 45.0
    arcs = world_arcs(axis, offset, R_CYL, angles, scale, np.random.default_rng(8))
    cal = find_axis_joint(arcs, angles, 2 * R_CYL, fit_angle_scale=True)
    undershoot = cal.to_dict()["undershoot_deg_per_45"]
    print(f"undershoot {undershoot:.4f} deg per 45 deg (true 0.2)")
    assert undershoot == pytest.approx(0.2, abs=0.03)
    # No periodic error to find: the once-per-turn term stays near zero.
    assert np.hypot(*cal.angle_wave_deg) < 0.03
    a, b = np.deg2rad(cal.angle_wave_deg)
    wave_deg = np.rad2deg(a * np.sin(np.deg2rad(315.0)) + b * (np.cos(np.deg2rad(315.0)) - 1))
    assert cal.true_angle_deg(315.0) == pytest.approx(315.0 * cal.angle_scale + wave_deg)
    assert np.hypot(*(np.asarray(cal.axis_xy_mm) - axis)) < 0.01
    # A centred cylinder cannot show the angle: the scale is left at 1 with a warning.
    centred = world_arcs(axis, (0.1, 0.0), R_CYL, angles, scale, np.random.default_rng(9))
    cal = find_axis_joint(centred, angles, 2 * R_CYL, fit_angle_scale=True)
    assert cal.angle_scale == 1.0 and any("off-centre" in w for w in cal.warnings)
    with pytest.raises(CalibrationError, match="one turntable angle per"):
        find_axis_joint(arcs, angles[:-1], 2 * R_CYL)


def test_known_radius_keeps_stripe_noise_out_of_the_axis() -> None:
    """Front-only arcs: a free radius drags the axis along y; the known radius does not.

    Limb scale: a 60 mm cylinder 11.7 mm off the axis, 0.18 mm of noise per point. The
    free radius and the axis's y move together (each error ~0.05 mm); with the radius
    held at the known value the axis is found to ~0.01 mm, and C_f is 1.
    """
    axis, offset, r = (2.0, -1.5), (10.0, -6.0), 30.0
    angles = [45.0 * k for k in range(8)]
    free_err, held_err, radius_err = [], [], []
    for seed in range(12):
        rng = np.random.default_rng(100 + seed)
        # Arcs of +-50 degrees on the side facing the camera (-y), as the rig sees them.
        centres = turned_centres(axis, offset, angles, 1.0)
        arcs = [arc(c, r, -140.0, 100.0, 250, 0.18, rng) for c in centres]
        free = find_axis_joint(arcs, angles, 2 * r, fit_angle_scale=True)
        held = find_axis_joint(arcs, angles, 2 * r, fit_angle_scale=True, fit_radius=False)
        free_err.append(free.axis_xy_mm[1] - axis[1])
        held_err.append(held.axis_xy_mm[1] - axis[1])
        radius_err.append(free.estimated_diameter_mm / 2 - r)
        assert held.correction_factor == 1.0
        assert held.estimated_diameter_mm == free.estimated_diameter_mm
        assert np.allclose(held.cylinder_offset_mm, offset, atol=0.05)
    rms_free, rms_held = (
        np.sqrt(np.mean(np.square(free_err))),
        np.sqrt(np.mean(np.square(held_err))),
    )
    print(f"axis y error RMS: free radius {rms_free:.4f} mm, known radius {rms_held:.4f} mm")
    # The free fit's radius and axis errors are the same error, seen twice.
    assert np.corrcoef(free_err, radius_err)[0, 1] > 0.9
    assert rms_held < 0.015 and rms_free > 3.0 * rms_held


def test_known_radius_still_warns_about_a_wrong_diameter() -> None:
    """Holding the radius does not hide a cylinder 7 % bigger than the one configured."""
    angles = [45.0 * k for k in range(8)]
    arcs = world_arcs((0.6, -0.4), (3.0, -1.5), 1.07 * R_CYL, angles, 1.0, np.random.default_rng(3))
    cal = find_axis_joint(arcs, angles, 2 * R_CYL, fit_radius=False)
    assert cal.estimated_diameter_mm == pytest.approx(2 * 1.07 * R_CYL, abs=0.01)
    assert any("5%" in w for w in cal.warnings), cal.warnings
