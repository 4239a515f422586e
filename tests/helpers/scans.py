"""Synthetic scans on the simulated rig's true geometry, reconstructed by the host.

A known outline is turned to each view's *true* turntable angle (``Mechanics``), the arc
the camera sees and the laser reaches is projected, sampled once per image column with
stripe-centre noise (``shapes.view_segment``) and labelled with the *commanded* angle, as
the device does; so every result can be checked against the outline in mm.
"""

from __future__ import annotations

import numpy as np

from lamina_device.sim import Mechanics, Rig, SimScene
from lamina_host.reconstruct.pipeline import ProcessOptions, Reconstruction, reconstruct
from tests.helpers.shapes import Outline, circle, view_segment


def synthetic_scan(
    rig: Rig, mechanics: Mechanics, outlines: dict[int, Outline], views: int = 8,
    noise_px: float = 0.1, seed: int = 0, views_of: dict[int, list[int]] | None = None,
    pitch_mm: float = 2.0,
) -> dict:  # fmt: skip
    """Return grid image, cylinder and object segments of sections ``outlines`` (index: outline).

    The cylinder is seen at the object's commanded view angles; ``views_of`` limits the
    views of a section (a section seen over part of its circumference).
    """
    rng = np.random.default_rng(seed)
    angles = [360.0 * v / views for v in range(views)]
    cyl = circle(rig.cylinder_offset_mm, rig.cylinder_diameter_mm / 2.0)
    cylinder = [
        s for v, a in enumerate(angles)
        if (s := view_segment(rig, "cylinder", 0, v, 0.0, a, mechanics.true_angle_deg(a), cyl,
                              rng, noise_px)) is not None
    ]  # fmt: skip
    segments = []
    for k, outline in outlines.items():
        for v in (views_of or {}).get(k, range(views)):
            a = angles[v]
            s = view_segment(rig, "object", k, v, k * pitch_mm, a, mechanics.true_angle_deg(a),
                             outline, rng, noise_px)  # fmt: skip
            if s is not None:
                segments.append(s)
    return {"grid": SimScene(rig).render("grid", 0.0, 0.0, False), "board": rig.board,
            "cylinder": cylinder, "cylinder_mm": rig.cylinder_diameter_mm,
            "segments": segments}  # fmt: skip


def run(scan: dict, options: ProcessOptions | None = None, segments=None) -> Reconstruction:
    """Reconstruct a synthetic scan."""
    return reconstruct(scan["grid"], scan["board"], scan["cylinder"], scan["cylinder_mm"],
                       segments if segments is not None else scan["segments"], options)  # fmt: skip


def distance_to(points: np.ndarray, outline: Outline) -> np.ndarray:
    """Return each point's distance in mm to a dense true outline."""
    from scipy.spatial import cKDTree

    return cKDTree(outline).query(np.asarray(points).reshape(-1, 2))[0]
