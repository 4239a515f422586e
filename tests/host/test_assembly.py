"""Tests for reconstruct.assembly: trimming, object frame and overlap averaging (6.1-6.3)."""

from __future__ import annotations

import numpy as np
import pytest

from lamina_host.reconstruct.assembly import average_overlaps, split_outlines, to_object_frame, trim

R = 9.525


def test_trim_drops_ten_percent_each_end() -> None:
    """trim removes floor(10 %) of the points from each end."""
    pts = np.arange(40.0).reshape(20, 2)
    out = trim(pts)
    assert np.array_equal(out, pts[2:18])
    assert len(trim(pts, 0.25)) == 10
    with pytest.raises(ValueError):
        trim(pts, 0.5)


def test_to_object_frame_known_rotation_and_round_trip() -> None:
    """to_object_frame inverts p = a + Rz(theta) q / C_f."""
    axis = (2.0, 30.0)
    # A point 1 mm along +x from the axis, seen after the table turned +90 deg, was at
    # the object's -y... i.e. q = Rz(-90)(1, 0) = (0, -1).
    q = to_object_frame(np.array([[3.0, 30.0]]), 90.0, axis, 1.0)
    assert np.allclose(q, [[0.0, -1.0]])
    rng = np.random.default_rng(0)
    obj = rng.uniform(-10, 10, (50, 2))
    th = np.deg2rad(135.0)
    rot = np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]])
    cf = 1.02
    world = obj / cf @ rot.T + axis  # forward model: p = a + Rz(theta) q / C_f
    assert np.allclose(to_object_frame(world, 135.0, axis, cf), obj, atol=1e-12)


def noisy_arcs(rng: np.random.Generator, sigma: float) -> tuple[list[np.ndarray], np.ndarray]:
    """8 object-frame arcs of 128 deg (160 deg trimmed) at 45 deg steps; some run clockwise."""
    centre = np.array([0.3, -0.2])
    segs = []
    for k in range(8):
        t = np.deg2rad(45.0 * k - 64.0 + np.linspace(0.0, 128.0, 120))
        if k % 2:
            t = t[::-1]  # stripe order may run either way in angle
        r = R + rng.normal(0.0, sigma, t.shape)
        segs.append(centre + np.stack([r * np.cos(t), r * np.sin(t)], axis=1))
    return segs, centre


def test_average_overlaps_orders_and_reduces_noise() -> None:
    """Averaging 8 overlapping noisy arcs sorts by angle and lowers radial noise."""
    rng = np.random.default_rng(1)
    segs, centre = noisy_arcs(rng, 0.05)
    out = average_overlaps(segs)
    assert out.shape == (8 * 120, 2)
    c = np.concatenate(segs).mean(axis=0)  # the polar centre average_overlaps uses
    ang = np.arctan2(out[:, 1] - c[1], out[:, 0] - c[0])
    assert np.all(np.diff(ang) >= 0)
    before = np.std(np.hypot(*(np.concatenate(segs) - centre).T) - R)
    after = np.std(np.hypot(*(out - centre).T) - R)
    print(f"average_overlaps: radial noise {before:.4f} -> {after:.4f} mm")
    assert after < 0.7 * before
    assert abs(np.mean(np.hypot(*(out - centre).T)) - R) < 0.01


def test_average_overlaps_wrap_matches_unwrapped_case() -> None:
    """Overlaps across +-pi average exactly as the same data turned 180 deg."""
    # Overlaps straddling +-pi must be averaged exactly as the same data turned 180 deg,
    # where nothing wraps: the method is rotation-equivariant.
    rng = np.random.default_rng(2)
    segs, _ = noisy_arcs(rng, 0.05)
    rot = np.array([[-1.0, 0.0], [0.0, -1.0]])
    direct = average_overlaps(segs)
    turned = average_overlaps([s @ rot.T for s in segs]) @ rot.T

    def key(p: np.ndarray) -> np.ndarray:
        c = p.mean(axis=0)
        return p[np.argsort(np.arctan2(p[:, 1] - c[1], p[:, 0] - c[0]))]

    assert np.allclose(key(direct), key(turned), atol=1e-9)


def test_average_overlaps_two_arcs_blend_without_a_step() -> None:
    """Arcs of radii 5.0 and 5.2: 5.1 mid-overlap, each its own radius outside, no step.

    The plain mean of the thesis jumps by 0.1 mm where one arc ends (a view seam); the
    blending weights fall to zero at each arc's end, so the radius ramps across the
    20-degree overlap with no step larger than the ramp's own slope gives.
    """
    t1 = np.deg2rad(np.linspace(-100.0, 100.0, 201))
    t2 = np.deg2rad(np.linspace(80.0, 280.0, 201))
    a = 5.0 * np.stack([np.cos(t1), np.sin(t1)], axis=1)
    b = 5.2 * np.stack([np.cos(t2), np.sin(t2)], axis=1)
    out = average_overlaps([a, b])
    # Blended about the points' mean, a little off the arcs' centre: judged about both.
    c = np.concatenate([a, b]).mean(axis=0)
    rad = np.hypot(*(out - c).T)
    ang = np.degrees(np.arctan2(out[:, 1], out[:, 0]))
    true_rad = np.hypot(*out.T)
    middle = np.abs(np.abs(ang) - 90.0) < 0.6
    assert middle.sum() >= 2 and np.allclose(true_rad[middle], 5.1, atol=0.03)
    assert np.allclose(true_rad[np.abs(ang) < 75.0], 5.0, atol=1e-9)
    assert np.allclose(true_rad[np.abs(ang) > 105.0], 5.2, atol=1e-9)
    # Points 1 degree apart: the steepest step is that of a 0.2 mm ramp over the overlap.
    steps = np.abs(np.diff(rad))
    print(f"largest radius step {steps.max():.4f} mm (plain mean: 0.1 mm)")
    assert steps.max() < 0.03
    single = average_overlaps([a])
    assert np.allclose(
        np.sort(np.hypot(*(single - a.mean(0)).T)), np.sort(np.hypot(*(a - a.mean(0)).T))
    )


def test_views_of_two_surfaces_at_one_angle_are_not_averaged() -> None:
    """A blended point stays on the surface its view saw, not midway to another one.

    Three views of one outline the rejection kept together: a long arc about the origin,
    and a small ring off to one side seen by two views, its near half by one and its far
    half by the other. About the points' mean, both halves of the ring lie at the same
    angles, 4 mm apart in radius; averaged, they drew a chord through the ring's inside
    (a random two-part section kept such a chord as measured points 1.5 mm off).
    """
    t = np.linspace(np.deg2rad(100.0), np.deg2rad(260.0), 160)
    arc = 12.0 * np.column_stack([np.cos(t), np.sin(t)])
    ring_centre = np.array([12.0, 0.0])
    near_t = np.linspace(np.pi / 2, 3 * np.pi / 2, 60)  # the half facing the origin
    far_t = near_t + np.pi
    near = ring_centre + 2.0 * np.column_stack([np.cos(near_t), np.sin(near_t)])
    far = ring_centre + 2.0 * np.column_stack([np.cos(far_t), np.sin(far_t)])
    blended = average_overlaps([arc, near, far])
    on_arc = np.abs(np.hypot(blended[:, 0], blended[:, 1]) - 12.0)
    on_ring = np.abs(np.linalg.norm(blended - ring_centre, axis=1) - 2.0)
    assert len(blended) == len(arc) + len(near) + len(far)
    assert np.max(np.minimum(on_arc, on_ring)) < 0.05


def test_split_outlines_separates_two_legs() -> None:
    """Two circles 6 mm apart split into two outlines; each piece keeps its own segment."""
    t = np.deg2rad(np.linspace(-80.0, 80.0, 200))
    left = np.stack([-10.0 + 7.0 * np.cos(t + np.pi), 7.0 * np.sin(t + np.pi)], axis=1)
    right = np.stack([10.0 + 7.0 * np.cos(t), 7.0 * np.sin(t)], axis=1)
    across = np.concatenate([left[:50], right[:50]])  # one stripe crossing both legs
    outlines = split_outlines([left, right, across], gap_mm=2.0)
    assert len(outlines) == 2
    sizes = sorted(sum(len(p) for p in pieces) for pieces in outlines)
    assert sizes == [250, 250]
    for pieces in outlines:
        xs = np.concatenate(pieces)[:, 0]
        assert np.all(np.sign(xs) == np.sign(xs[0]))  # never mixes the legs
        assert len(pieces) == 2
    # One closed outline stays whole; stray points are dropped.
    ring = 9.0 * np.stack([np.cos(t * 2), np.sin(t * 2)], axis=1)
    stray = np.array([[40.0, 40.0], [40.1, 40.0]])
    assert [len(o) for o in split_outlines([ring, stray], gap_mm=2.0)] == [1]
    with pytest.raises(ValueError):
        split_outlines([ring], gap_mm=0.0)
