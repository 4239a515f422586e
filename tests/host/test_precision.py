"""The per-point precision of a section, from where its views overlap."""

from __future__ import annotations

import numpy as np
import pytest

from lamina_host.reconstruct.precision import (
    overlap_differences,
    pair_differences,
    section_precision_mm,
)


def circle_views(noise_mm: float, views: int = 6, seed: int = 0, radius_mm: float = 20.0):
    """Return overlapping arcs of one circle, each seen with its own noise (mm)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(views):
        start = 2 * np.pi * k / views
        angle = start + np.linspace(0.0, 2 * np.pi / views * 1.8, 300)  # 80 % overlap
        r = radius_mm + rng.normal(0.0, noise_mm, angle.size)
        points = np.stack([r * np.cos(angle), r * np.sin(angle)], axis=1)
        out.append(points + np.array([3.0, -2.0]))
    return out


@pytest.mark.parametrize("noise_mm", [0.01, 0.05, 0.2])
def test_precision_matches_the_point_noise(noise_mm):
    estimate = section_precision_mm(circle_views(noise_mm))
    assert estimate == pytest.approx(noise_mm, rel=0.15)


def test_an_offset_between_views_counts_and_gaps_are_skipped():
    views = circle_views(0.02, seed=1)
    views[2] = views[2] * 1.01  # one view 0.2 mm too far out: worse than the noise alone
    assert section_precision_mm(views) > 0.02 * 1.3
    holey = circle_views(0.02, seed=2)
    holey[1] = np.delete(holey[1], range(100, 160), axis=0)  # a gap is not an overlap
    full = overlap_differences(circle_views(0.02, seed=2)).size
    assert overlap_differences(holey).size < full


def test_without_overlap_there_is_no_estimate():
    assert section_precision_mm(circle_views(0.05, views=1)) is None
    angle = np.linspace(0.0, 1.0, 50)
    apart = [np.stack([np.cos(angle + s), np.sin(angle + s)], axis=1) for s in (0.0, 3.0)]
    assert section_precision_mm(apart) is None


def kidney_views(noise_mm: float, views: int = 6, seed: int = 3):
    """Return overlapping arcs of a kidney outline (not star-shaped about its centroid)."""
    rng = np.random.default_rng(seed)
    out = []
    for k in range(views):
        start = 2 * np.pi * k / views
        s = start + np.linspace(0.0, 2 * np.pi / views * 1.8, 400)
        radius = 20.0 + 12.0 * np.cos(2 * s) ** 3  # deep waists: rays cross it twice
        xy = np.stack([radius * np.cos(s) * 1.6, radius * np.sin(s) * 0.5], axis=1)
        tangent = np.gradient(xy, axis=0)
        normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
        normal /= np.linalg.norm(normal, axis=1, keepdims=True)
        out.append(xy + normal * rng.normal(0.0, noise_mm, (len(s), 1)))
    return out


def test_precision_along_a_reference_curve_for_a_folded_outline():
    from lamina_host.reconstruct.outline_frame import outline_frame

    views = kidney_views(0.03)
    frame = outline_frame(np.concatenate(views), link_mm=2.0)
    assert not frame.polar, "the test shape should need a reference curve"
    assert section_precision_mm(views, frame) == pytest.approx(0.03, rel=0.25)


def test_comparing_some_pairs_gives_those_pairs_as_every_pair_does():
    views = circle_views(0.05, views=8, seed=4)
    views[3] = views[3] + np.array([0.3, 0.1])  # a moved view: its pairs stand out
    for turn_deg in (0.0, 0.2):
        every = {
            (p.earlier, p.later): p.differences_mm for p in pair_differences(views, None, turn_deg)
        }
        asked = {(2, 3), (3, 4), (0, 7), (1, 6)}  # (1, 6) do not overlap
        some = pair_differences(views, None, turn_deg, only=asked)
        assert (
            {(p.earlier, p.later) for p in some} == asked & every.keys() == {(2, 3), (3, 4), (0, 7)}
        )
        for p in some:
            np.testing.assert_array_equal(p.differences_mm, every[(p.earlier, p.later)])
