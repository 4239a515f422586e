"""Tests for lamina_host.reconstruct.measure: polygon measures and the Table 8.3 radial errors."""

from __future__ import annotations

import numpy as np
import pytest

from lamina_host.reconstruct.calibration import CalibrationError
from lamina_host.reconstruct.measure import (
    centroid,
    centroid_or_mean,
    perimeter,
    perimeters,
    polygon_area,
    radial_error_table,
    signed_area,
    signed_areas,
)

R = 9.525


def circle(centre: tuple[float, float], r: float = R, n: int = 500) -> np.ndarray:
    """Regular n-gon inscribed in a circle, counter-clockwise."""
    t = np.linspace(0.0, 2 * np.pi, n, endpoint=False)
    return np.stack([centre[0] + r * np.cos(t), centre[1] + r * np.sin(t)], axis=1)


def test_polygon_measures() -> None:
    """Area, perimeter and area centroid of simple polygons."""
    square = np.array([[1.0, 1.0], [4.0, 1.0], [4.0, 3.0], [1.0, 3.0]])
    assert polygon_area(square) == pytest.approx(6.0)
    assert signed_area(square[::-1]) == pytest.approx(-6.0)
    assert perimeter(square) == pytest.approx(10.0)
    assert np.allclose(centroid(square), [2.5, 2.0])
    # Area centroid, not point mean: extra points on one edge must not move it.
    dense = np.array([[0.0, 0.0], [1, 0], [2, 0], [3, 0], [4.0, 0.0], [4.0, 4.0], [0.0, 4.0]])
    assert np.allclose(centroid(dense), [2.0, 2.0])
    with pytest.raises(CalibrationError):
        centroid(np.array([[0.0, 0.0], [1.0, 1.0], [2.0, 2.0]]))


def test_a_batch_of_contours_measures_as_each_alone() -> None:
    """Areas and perimeters of stacked contours: the truth, and each alone bit for bit.

    The contour mesh's ring spacing measures hundreds of probe contours at once; a batch
    must round as the plain formula over one contour does, as the single measures do.
    """
    square = np.array([[1.0, 1.0], [4.0, 1.0], [4.0, 3.0], [1.0, 3.0]])
    batch = np.stack([square, square[::-1], square * 2.0])
    assert signed_areas(batch) == pytest.approx([6.0, -6.0, 24.0])
    assert perimeters(batch) == pytest.approx([10.0, 10.0, 20.0])
    rng = np.random.default_rng(5)
    many = rng.normal(size=(40, 64, 2)) * rng.uniform(0.1, 60.0, (40, 1, 1))
    areas, lengths = signed_areas(many), perimeters(many)
    # The shoelace and the edge lengths written out for one contour at a time.
    alone = [0.5 * np.sum(c[:, 0] * np.roll(c[:, 1], -1) - np.roll(c[:, 0], -1) * c[:, 1])
             for c in many]  # fmt: skip
    assert areas.tolist() == alone == [signed_area(c) for c in many]
    edges = [np.linalg.norm(np.roll(c, -1, axis=0) - c, axis=1).sum() for c in many]
    assert lengths.tolist() == edges == [perimeter(c) for c in many]


def test_a_flat_outline_is_placed_at_its_mean() -> None:
    """An outline without area has no centroid, but still a place (chains, centre lines)."""
    flat = np.column_stack([np.linspace(-3.0, 5.0, 9), np.full(9, 2.0)])
    with pytest.raises(CalibrationError):
        centroid(flat)
    np.testing.assert_allclose(centroid_or_mean(flat), [1.0, 2.0])
    phi = np.linspace(0.0, 2.0 * np.pi, 7, endpoint=False)
    lopsided = np.column_stack([1.0 + np.cos(phi) ** 3, -2.0 + np.sin(phi)])
    np.testing.assert_array_equal(centroid_or_mean(lopsided), centroid(lopsided))


def test_radial_error_perfect_circles() -> None:
    """Perfect concentric circles have zero radial error."""
    contours = {s: circle((0.5, -0.25)) for s in range(4)}
    table = radial_error_table(contours, {s: 2.0 * s for s in range(4)}, R)
    assert table.mean_own_mm < 1e-9 and table.mean_mean_mm < 1e-9
    assert [r.section for r in table.rows] == [0, 1, 2, 3]
    assert table.rows[2].z_mm == 4.0
    assert table.rows[0].mean_radius_mm == pytest.approx(R, abs=1e-3)


def test_radial_error_shifted_centres() -> None:
    """Shifted circles give e / sqrt(2) about the mean centroid, 0 about their own."""
    shifts = np.array([[0.1, 0.0], [-0.1, 0.0], [0.0, 0.2], [0.0, -0.2]])
    contours = {s: circle(tuple(d)) for s, d in enumerate(shifts)}
    table = radial_error_table(contours, dict.fromkeys(range(4), 0.0), R)
    assert np.allclose(table.mean_centroid_mm, (0.0, 0.0), atol=1e-12)
    # A circle shifted by e from the centre has radial error ~ e cos(phi): RMS e / sqrt(2).
    expected = np.hypot(*shifts.T) / np.sqrt(2.0)
    got = np.array([r.rms_mean_mm for r in table.rows])
    assert np.allclose(got, expected, rtol=0.01)
    assert np.allclose([r.rms_own_mm for r in table.rows], 0.0, atol=1e-9)
    assert table.mean_mean_mm == pytest.approx(expected.mean(), rel=0.01)
    assert table.to_dict()["rows"][3]["section"] == 3


def test_radial_error_table_takes_a_flat_section() -> None:
    """A flat outline (no area) gets a row about its points' mean, not an exception."""
    flat = np.column_stack([np.linspace(-R, R, 50), np.zeros(50)])
    table = radial_error_table({0: circle((0.0, 0.0)), 1: flat}, {0: 0.0, 1: 2.0}, R)
    assert table.rows[0].rms_own_mm == pytest.approx(0.0, abs=1e-9)
    # Points spread evenly over [-R, R] about 0: radial error |x| - R, RMS R / sqrt(3).
    assert table.rows[1].rms_own_mm == pytest.approx(R / np.sqrt(3.0), rel=0.05)


def test_radial_error_needs_heights() -> None:
    """A section without a height raises CalibrationError."""
    with pytest.raises(CalibrationError, match="z_mm"):
        radial_error_table({0: circle((0.0, 0.0))}, {}, R)


def test_radial_error_table_with_a_radius_model_for_ellipses():
    a, b = 10.0, 6.5
    t = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    ellipse = np.c_[a * np.cos(t), b * np.sin(t)]

    def radius(phi, z):
        return a * b / np.sqrt((b * np.cos(phi)) ** 2 + (a * np.sin(phi)) ** 2)

    exact = radial_error_table({0: ellipse, 1: ellipse}, {0: 0.0, 1: 2.0}, radius)
    assert exact.max_mean_mm < 1e-9
    bigger = radial_error_table({0: ellipse * 1.01}, {0: 0.0}, radius)
    # Every point is 1% too far out: RMS equals 1% of the RMS radius.
    expected = 0.01 * np.sqrt(np.mean(radius(t, 0.0) ** 2))
    assert bigger.rows[0].rms_own_mm == pytest.approx(expected, rel=0.05)
