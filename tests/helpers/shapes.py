"""Known outlines, solids and synthetic stripes for the host tests and the benches.

Everything here is exact by construction (mm, object frame), so a test can compare
what the pipeline recovers with the truth it was built from.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path

import numpy as np

from lamina_device.sim import Rig
from lamina_host.reconstruct.mesh import stl_bytes
from lamina_shared.types import Segment

Outline = np.ndarray
"""(M, 2) counter-clockwise object-frame points of one convex outline, in mm."""


def circle(centre: tuple[float, float], radius_mm: float, n: int = 4000) -> Outline:
    """Return a dense counter-clockwise circle."""
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.asarray(centre) + radius_mm * np.stack([np.cos(t), np.sin(t)], axis=1)


def ellipse(centre: tuple[float, float], a_mm: float, b_mm: float, n: int = 4000) -> Outline:
    """Return a dense counter-clockwise ellipse with semi-axes a (x) and b (y)."""
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return np.asarray(centre) + np.stack([a_mm * np.cos(t), b_mm * np.sin(t)], axis=1)


def regular_polygon(sides: int, area_mm2: float, pts_per_side: int = 40) -> Outline:
    """Return a regular polygon of the given area, sampled densely along its edges."""
    circumradius = np.sqrt(2 * area_mm2 / (sides * np.sin(2 * np.pi / sides)))
    ang = 2 * np.pi * np.arange(sides) / sides + np.pi / sides
    v = circumradius * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    s = np.linspace(0.0, 1.0, pts_per_side, endpoint=False)[:, None]
    return np.concatenate([v[k] + (v[(k + 1) % sides] - v[k]) * s for k in range(sides)])


def posts_stl(path: Path, posts: Iterable[tuple[float, float, float]]) -> None:
    """Write a binary STL of closed vertical 96-gon posts ``(x, y, radius)`` mm, z -5..15 mm."""
    t = np.linspace(0.0, 2.0 * np.pi, 96, endpoint=False)
    tris = []
    for cx, cy, r in posts:
        ring = np.stack([cx + r * np.cos(t), cy + r * np.sin(t)], axis=1)
        for k in range(len(t)):
            a, b = ring[k], ring[(k + 1) % len(t)]
            a0, b0, a1, b1 = [*a, -5.0], [*b, -5.0], [*a, 15.0], [*b, 15.0]
            bottom, top = [cx, cy, -5.0], [cx, cy, 15.0]
            tris += [[a0, b0, b1], [a0, b1, a1], [bottom, b0, a0], [top, a1, b1]]
    vertices = np.asarray(tris, dtype=float).reshape(-1, 3)
    path.write_bytes(stl_bytes(vertices, np.arange(len(vertices)).reshape(-1, 3)))


def view_segment(
    rig: Rig, target: str, section: int, view: int, z_mm: float, commanded_deg: float,
    true_deg: float, outline: Outline, rng: np.random.Generator, noise_px: float,
) -> Segment | None:  # fmt: skip
    """Return what the camera sees of an outline turned to ``true_deg``.

    The stripe is the outline points both the camera and the laser face, projected
    and resampled at whole columns with ``noise_px`` of row noise; None when it is short.
    """
    tangent = np.roll(outline, -1, axis=0) - np.roll(outline, 1, axis=0)
    normal = np.stack([tangent[:, 1], -tangent[:, 0]], axis=1)
    world = rig.object_to_world(outline, true_deg, 0.0)
    th = np.deg2rad(true_deg)
    n_world = normal @ np.array([[np.cos(th), -np.sin(th)], [np.sin(th), np.cos(th)]]).T
    to_cam = rig.camera_centre_mm[:2] - world[:, :2]
    to_laser = rig.laser_source_mm[:2] - world[:, :2]
    keep = (np.sum(n_world * to_cam, 1) > 0) & (np.sum(n_world * to_laser, 1) > 0)
    if keep.sum() < 20:
        return None
    # From the start of a run, every point both face: one run on a convex outline, several
    # on one with shallow relief (what the relief hides from the camera is not removed).
    start = int(np.flatnonzero(keep & ~np.roll(keep, 1))[0])
    idx = np.roll(np.arange(len(outline)), -start)
    idx = idx[keep[idx]]
    uv = rig.project(world[idx])
    order = np.argsort(uv[:, 0])
    u, v = uv[order, 0], uv[order, 1]
    cols = np.arange(int(np.ceil(u[0])), int(np.floor(u[-1])) + 1)
    cols = cols[(cols >= 0) & (cols < rig.image_size[0])]
    rows = np.interp(cols, u, v) + rng.normal(0.0, noise_px, len(cols))
    return Segment(target, section, view, z_mm, commanded_deg, cols.astype(np.uint16),
                   rows.astype(np.float32), np.full(len(cols), 200, np.uint8),
                   np.full(len(cols), 1, np.uint8))  # fmt: skip
