"""Tests for reconstruct.efd: Kuhl-Giardina coefficients and harmonic choice (thesis 6.4)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pyefd
import pytest

from lamina_host.reconstruct.efd import (
    HARMONIC_RULES,
    MAX_TESTED_HARMONICS,
    EfdStack,
    MeasuredPoints,
    align,
    choose_harmonics,
    efd_area,
    efd_fit,
    harmonics_residual,
    harmonics_thesis,
    highest_tested_order,
    nyquist_max,
    shift_start,
)
from lamina_host.reconstruct.measure import signed_area
from lamina_host.reconstruct.outline_frame import OutlineFrame
from tests.helpers.shapes import regular_polygon

R = 9.525


def blob(n: int = 200) -> np.ndarray:
    """A smooth, non-symmetric closed outline, counter-clockwise, off the origin."""
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    r = 8.0 + 1.5 * np.cos(3 * t) + 0.7 * np.sin(2 * t + 0.3)
    return np.stack([3.0 + r * np.cos(t), -2.0 + 1.3 * r * np.sin(t)], axis=1)


def nearest_mm(points: np.ndarray, dense: np.ndarray) -> np.ndarray:
    """Distance from each point to the nearest of a dense sampling of a curve."""
    from scipy.spatial import cKDTree

    return cKDTree(dense).query(points)[0]


@pytest.mark.parametrize("order", [1, 5, 12])
def test_efd_matches_pyefd(order: int) -> None:
    """Coefficients and DC terms agree with pyefd, closing point or not."""
    contour = blob()
    ours = efd_fit(contour, order)
    ref = pyefd.elliptic_fourier_descriptors(contour, order=order, normalize=False)
    a0, c0 = pyefd.calculate_dc_coefficients(contour)
    assert ours.order == order
    assert np.allclose(ours.coeffs, ref, rtol=1e-10, atol=1e-12)
    assert ours.a0 == pytest.approx(a0, abs=1e-10) and ours.c0 == pytest.approx(c0, abs=1e-10)
    # An explicit closing point and repeated points change nothing.
    messy = np.concatenate([contour[:5], contour[4:5], contour[5:], contour[:1]])
    again = efd_fit(messy, order)
    assert np.allclose(again.coeffs, ours.coeffs) and again.a0 == pytest.approx(ours.a0)
    recon = pyefd.reconstruct_contour(ref, locus=(a0, c0), num_points=301)[:-1]
    assert np.allclose(ours.evaluate(300), recon, atol=1e-10)


def test_evaluate_starts_at_first_point_same_orientation() -> None:
    """evaluate starts at the first input point and keeps its orientation."""
    contour = blob(400)
    for c in (contour, contour[::-1]):
        fit = efd_fit(c, 40)
        pts = fit.evaluate(400)
        assert np.linalg.norm(pts[0] - c[0]) < 0.05
        assert np.sign(signed_area(pts)) == np.sign(signed_area(c))


@pytest.mark.parametrize(
    ("rule", "parameter", "max_rms_mm", "max_err_mm"),
    [("noise", "smoothed", 0.01, 0.05), ("thesis", "chord", 0.05, 0.1)],
)
def test_noisy_circle_reconstruction_thesis_642(
    rule: str, parameter: str, max_rms_mm: float, max_err_mm: float
) -> None:
    """The thesis 6.4.2 noisy circle: within 0.1 mm the thesis' way, 0.01 mm RMS Lamina's."""
    # Thesis 6.4.2: r = 9.525 mm with white noise of variance 3.9e-3 mm^2.
    rng = np.random.default_rng(7)
    t = np.linspace(0.0, 2 * np.pi, 500, endpoint=False)
    clean = R * np.stack([np.cos(t), np.sin(t)], axis=1)
    noisy = clean + rng.normal(0.0, np.sqrt(3.9e-3), clean.shape)
    order = choose_harmonics(noisy, rule, parameter)
    recon = efd_fit(noisy, order, parameter).evaluate(500)
    err = np.abs(np.hypot(*recon.T) - R)
    raw = np.abs(np.hypot(*noisy.T) - R)
    rms = float(np.sqrt(np.mean(err**2)))
    print(f"noisy circle {rule}/{parameter}: {order} harmonics, RMS {rms:.4f}, max {err.max():.4f}")
    assert 1 <= order <= 6
    assert rms < max_rms_mm and err.max() < max_err_mm
    assert err.max() < 0.5 * raw.max()


def test_harmonics_thesis_polygons_fig_6_11() -> None:
    """HN gives 6, 5, 5 for an equal-area square, pentagon and octagon."""
    # HN = 1/(PA*RF) reduces to perimeter / (4 pi). At equal area the square has the
    # longest perimeter, so area ~310 mm^2 (side 17.6 mm) gives the thesis' 6, 5, 5.
    area = 17.6**2
    assert harmonics_thesis(regular_polygon(4, area)) == 6
    assert harmonics_thesis(regular_polygon(5, area)) == 5
    assert harmonics_thesis(regular_polygon(8, area)) == 5
    circle = R * np.stack(
        [
            np.cos(np.linspace(0, 2 * np.pi, 720, endpoint=False)),
            np.sin(np.linspace(0, 2 * np.pi, 720, endpoint=False)),
        ],
        axis=1,
    )
    assert harmonics_thesis(circle) == round(2 * np.pi * R / (4 * np.pi))  # = 5
    tiny = np.array([[0.0, 0.0], [1.0, 0.0], [0.0, 1.0]])
    assert harmonics_thesis(tiny) == 1


def test_nyquist_and_cap() -> None:
    """The Nyquist cap is n // 2 and limits choose_harmonics."""
    assert nyquist_max(500) == 250 and nyquist_max(501) == 250 and nyquist_max(7) == 3
    few = regular_polygon(8, 40.0**2, pts_per_side=1)  # 8 points, HN would be ~11
    assert choose_harmonics(few) == 4


def test_harmonic_rules_selectable_and_noise_rule_finds_the_shape() -> None:
    """Every rule runs; the noise rule keeps 1 harmonic for a circle, more for a lobed blob."""
    rng = np.random.default_rng(3)
    t = np.linspace(0.0, 2 * np.pi, 1000, endpoint=False)
    circle = R * np.stack([np.cos(t), np.sin(t)], axis=1) + rng.normal(0, 0.05, (1000, 2))
    shape = blob(1000) + rng.normal(0, 0.05, (1000, 2))
    for rule in HARMONIC_RULES:
        assert choose_harmonics(circle, rule) >= 1
    assert choose_harmonics(circle, "noise") == 1
    assert choose_harmonics(circle, "nyquist") == 500
    lobed = choose_harmonics(shape, "noise")
    assert 4 <= lobed <= 20
    # The smoothed parameter and the chosen order reproduce the blob closely.
    fit = efd_fit(shape, lobed, "smoothed").evaluate(1000)
    assert np.sqrt(np.mean(nearest_mm(fit, blob(20000)) ** 2)) < 0.03
    with pytest.raises(ValueError, match="unknown harmonic rule"):
        choose_harmonics(circle, "magic")


def order_and_error(
    blend: np.ndarray,
    measured: MeasuredPoints,
    true_radius_mm: Callable[[np.ndarray], np.ndarray],
    samples: int,
) -> tuple[int, float]:
    """Return the residual rule's order for ``blend`` and its fit's RMS radial error (mm)
    from the true star-shaped outline ``true_radius_mm(angle)``."""
    order = harmonics_residual(blend, measured)
    fit = efd_fit(blend, order, "smoothed").evaluate(samples)
    truth = true_radius_mm(np.arctan2(fit[:, 1], fit[:, 0]))
    rms_mm = float(np.sqrt(np.mean((np.hypot(fit[:, 0], fit[:, 1]) - truth) ** 2)))
    print(f"order {order}, {rms_mm:.4f} mm RMS from the truth")
    return order, rms_mm


def limb_radius_mm(angle_rad: np.ndarray, relief_mm: float) -> np.ndarray:
    """A 45 mm limb outline, slightly oval, with skin relief at 54 waves round (5.2 mm)."""
    return 45.0 + 2.0 * np.cos(2 * angle_rad) + relief_mm * np.cos(54 * angle_rad)


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize(
    ("blend_relief_mm", "points_relief_mm", "keeps_relief"),
    [(0.12, 0.12, True), (0.0, 0.0, False), (0.12, 0.0, False)],
)
def test_the_residual_rule_keeps_relief_each_points_noise_hides(
    seed: int, blend_relief_mm: float, points_relief_mm: float, keeps_relief: bool
) -> None:
    """Relief below each point's noise, where the overlaps' noise estimate sits above the
    residual's floor (as on a limb), is kept: the residual reaches that estimate at the
    oval's order, but the relief stands out of the blend's spectrum and the points confirm
    it. Without relief, or with a peak in the blend that the points do not share (a seam),
    the order stays at the oval's."""
    rng = np.random.default_rng(seed)
    sigma_mm = 0.15
    t = np.linspace(-np.pi, np.pi, 2600, endpoint=False)
    r = limb_radius_mm(t, blend_relief_mm) + rng.normal(0.0, 0.03, t.size)
    blend = np.stack([r * np.cos(t), r * np.sin(t)], axis=1)
    angle = rng.uniform(-np.pi, np.pi, 600)
    radius = limb_radius_mm(angle, points_relief_mm) + rng.normal(0.0, sigma_mm, angle.size)
    measured = MeasuredPoints(OutlineFrame(np.zeros(2)), angle, radius, 1.2 * sigma_mm)
    order, rms_mm = order_and_error(
        blend, measured, lambda a: limb_radius_mm(a, blend_relief_mm), 4000
    )
    if keeps_relief:
        assert 54 <= order <= 64 and rms_mm < 0.015  # 0.085 mm with the relief cut
    else:
        assert order <= 4


def wide_radius_mm(angle_rad: np.ndarray, relief_mm: float) -> np.ndarray:
    """An 85 mm wide outline (534 mm round), oval, with relief at 140 waves round (3.8 mm)."""
    return 85.0 + 3.0 * np.cos(2 * angle_rad) + relief_mm * np.cos(140 * angle_rad)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("relief_mm", [0.3, 0.0])
def test_the_residual_rule_looks_past_harmonic_128_round_a_long_outline(
    seed: int, relief_mm: float
) -> None:
    """Skin relief at 3.8 mm round a 534 mm outline is harmonic 140: the rule tests orders
    to a 2.7 mm wavelength there (197), so it keeps the relief (it stopped at 128 and
    lost it); without relief the order stays at the oval's."""
    rng = np.random.default_rng(seed)
    sigma_mm = 0.1
    t = np.linspace(-np.pi, np.pi, 3700, endpoint=False)
    r = wide_radius_mm(t, relief_mm) + rng.normal(0.0, 0.02, t.size)
    blend = np.stack([r * np.cos(t), r * np.sin(t)], axis=1)
    assert 197 <= highest_tested_order(blend) <= 215  # 534 mm, and what relief adds to it
    assert highest_tested_order(blend * (300.0 / 534.0)) == MAX_TESTED_HARMONICS
    angle = rng.uniform(-np.pi, np.pi, 3000)
    radius = wide_radius_mm(angle, relief_mm) + rng.normal(0.0, sigma_mm, angle.size)
    measured = MeasuredPoints(OutlineFrame(np.zeros(2)), angle, radius, sigma_mm)
    order, rms_mm = order_and_error(blend, measured, lambda a: wide_radius_mm(a, relief_mm), 8000)
    if relief_mm:
        assert 140 <= order <= 215 and rms_mm < 0.03  # 0.21 mm with the relief cut
    else:
        assert order <= 4 and rms_mm < 0.03


def test_shift_start_and_align_keep_the_curve() -> None:
    """Shifting the start or aligning changes the parameterisation, never the curve."""
    fit = efd_fit(blob(400)[::-1], 12)  # clockwise input
    assert efd_area(fit) < 0
    shifted = shift_start(fit, 0.3)
    assert np.allclose(shifted.evaluate(100), np.roll(fit.evaluate(100), -30, axis=0), atol=1e-9)
    aligned = align(fit)
    assert efd_area(aligned) > 0
    assert efd_area(aligned) == pytest.approx(-efd_area(fit))
    start = aligned.evaluate(8)[0] - [aligned.a0, aligned.c0]
    assert abs(start[1]) < 1e-3 and start[0] > 0  # starts on the +x ray from the centre
    assert nearest_mm(aligned.evaluate(500), fit.evaluate(20000)).max() < 0.005


def test_efd_stack_interpolates_along_z() -> None:
    """Sections come back at their own heights; half-way lies between them."""
    t = np.linspace(0.0, 2 * np.pi, 300, endpoint=False)
    rings = [r * np.stack([np.cos(t + k), np.sin(t + k)], axis=1) for k, r in enumerate((8, 10))]
    efds = [efd_fit(rings[0], 3), efd_fit(rings[1][::-1], 3)]  # different starts and directions
    stack = EfdStack.from_sections([0.0, 2.0], efds)
    assert np.allclose(np.hypot(*stack.section(0.0).evaluate(50).T), 8.0, atol=1e-3)
    assert np.allclose(np.hypot(*stack.section(1.0).evaluate(50).T), 9.0, atol=1e-3)
    sampled = stack.sample(64)
    assert sampled.shape == (2, 64, 2)
    # Aligned: both rings start on +x and run counter-clockwise.
    assert np.allclose(sampled[:, 0, 1], 0.0, atol=1e-3) and np.all(sampled[:, 0, 0] > 0)
    a, b = sampled[:, 1], sampled[:, 2]
    assert np.all(a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0] > 0)
    pchip = EfdStack.from_sections([0.0, 2.0, 4.0], [*efds, efd_fit(rings[0], 3)], "pchip")
    assert np.allclose(np.hypot(*pchip.section(4.0).evaluate(50).T), 8.0, atol=1e-3)
