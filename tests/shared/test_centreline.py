"""The host's fit along the stripe: less scatter, no bias on curves, chains kept apart."""

from __future__ import annotations

import numpy as np
import pytest

from lamina_shared.centreline import chain_starts, refine_rows


def _arc(radius_px: float, columns: int = 200) -> tuple[np.ndarray, np.ndarray]:
    """Return (cols, true rows) of a circular arc spanning +-50 degrees of slope."""
    half = min(radius_px * np.sin(np.radians(50.0)), columns / 2 - 1)
    cols = np.arange(columns)
    x = cols - columns / 2
    inside = np.abs(x) <= half
    rows = 100.0 - np.sqrt(radius_px**2 - x[inside] ** 2)
    return cols[inside], rows


@pytest.mark.parametrize("radius_px", [20.0, 50.0, 500.0])
def test_fit_removes_scatter_without_pulling_a_curve(radius_px):
    cols, truth = _arc(radius_px)
    width = np.full(cols.size, 4, np.uint8)
    exact = refine_rows(cols, truth, width)
    inner = slice(3, -3)  # the ends have no neighbours on one side
    # A parabola follows a circle: the noise-free fit stays on it.
    assert np.max(np.abs(exact - truth)[inner]) < 0.02
    rng = np.random.default_rng(1)
    noisy = truth + rng.normal(0.0, 0.3, truth.size)
    fitted = refine_rows(cols, noisy, width)
    before = np.sqrt(np.mean((noisy - truth)[inner] ** 2))
    after = np.sqrt(np.mean((fitted - truth)[inner] ** 2))
    assert after < 0.75 * before


def test_fit_never_reaches_across_a_chain_break():
    cols = np.concatenate([np.arange(0, 60), np.arange(60, 120), np.arange(124, 180)])
    truth = np.concatenate([np.full(60, 40.0), np.full(60, 70.0), np.full(56, 40.0)])
    width = np.full(cols.size, 3, np.uint8)
    assert chain_starts(cols, truth, width, 4.0).tolist() == [0, 60, 120]
    fitted = refine_rows(cols, truth, width)
    # A jump to another surface and a gap of four columns: each chain keeps its own row.
    np.testing.assert_allclose(fitted, truth, atol=1e-9)


def test_a_dropout_far_off_the_stripe_does_not_pull_its_neighbours():
    cols = np.arange(100)
    truth = 50.0 + 0.05 * cols
    rows = truth.copy()
    rows[50] += 3.0  # within the row jump: the same chain, but no stripe point
    fitted = refine_rows(cols, rows, np.full(100, 4, np.uint8))
    assert np.max(np.abs(fitted - truth)) < 0.01


def test_short_chains_and_fixed_reach():
    cols, rows, width = np.array([5, 6]), np.array([10.0, 11.0]), np.array([3, 3], np.uint8)
    np.testing.assert_allclose(refine_rows(cols, rows, width), rows)
    one = refine_rows(np.array([3]), np.array([7.25]), np.array([2], np.uint8))
    assert one.tolist() == [7.25]
    line = 20.0 + 0.3 * np.arange(50)
    np.testing.assert_allclose(
        refine_rows(np.arange(50), line, np.full(50, 3, np.uint8), sigma_px=4.0), line, atol=1e-9
    )
    assert refine_rows(np.arange(50), line, np.full(50, 3), sigma_px=0.0) is not line


def test_a_segment_is_fitted_in_its_own_point_order():
    from lamina_shared.centreline import refined_uv
    from lamina_shared.types import Segment

    rng = np.random.default_rng(2)
    cols = np.arange(100, 200, dtype=np.uint16)
    truth = 80.0 + 0.2 * np.arange(100)
    rows = (truth + rng.normal(0.0, 0.3, 100)).astype(np.float32)
    order = rng.permutation(100)  # a segment need not list its points by column
    segment = Segment(
        "object", 0, 0, 0.0, 0.0, cols[order], rows[order],
        np.full(100, 150, np.uint8), np.full(100, 4, np.uint8),
    )  # fmt: skip
    uv = refined_uv(segment)
    assert np.array_equal(uv[:, 0], cols[order])
    assert np.sqrt(np.mean((uv[:, 1] - truth[order]) ** 2)) < 0.5 * 0.3
    doubled = Segment(
        "object", 0, 0, 0.0, 0.0, np.array([5, 5, 6], np.uint16),
        np.array([1.0, 9.0, 1.0], np.float32), np.full(3, 99, np.uint8), np.full(3, 2, np.uint8),
    )  # fmt: skip
    np.testing.assert_array_equal(refined_uv(doubled), doubled.uv)  # not one point per column
