"""EFD benchmarks: harmonic-count rules and coefficient interpolation on known outlines.

Thesis fig. 6.8 (noisy circle), fig. 6.11 (HN of polygons), the harmonic rules on other
outlines, and interpolation of coefficients along z (thesis ref. [86]).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from lamina_host.reconstruct.efd import (
    HARMONIC_RULES,
    EfdStack,
    choose_harmonics,
    efd_fit,
    harmonics_thesis,
)
from tests.helpers.shapes import regular_polygon

TITLE = "elliptic Fourier descriptors: thesis figs. 6.8 and 6.11, harmonic rules, z interpolation"
R_MM = 9.525
NOISE_VAR_MM2 = 3.9e-3  # thesis 6.4.2
POINTS = 500  # the thesis' outline size (Table 8.2); the fig. 6.8 count is not stated
TRIALS = 20


def _circle(n: int, r: float = R_MM) -> np.ndarray:
    t = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    return r * np.stack([np.cos(t), np.sin(t)], axis=1)


def _shapes() -> dict[str, np.ndarray]:
    """Dense true outlines (4000 points): ellipse, blob and a limb-sized lobed section."""
    t = np.linspace(0.0, 2.0 * np.pi, 4000, endpoint=False)
    blob_r = 8.0 + 1.5 * np.cos(3 * t) + 0.7 * np.sin(2 * t + 0.3)
    limb_r = 55.0 + 4.0 * np.cos(2 * t) + 2.0 * np.sin(3 * t + 0.5) + 0.8 * np.cos(5 * t)
    return {
        "ellipse 10x6.5": np.stack([10.0 * np.cos(t), 6.5 * np.sin(t)], axis=1),
        "blob": np.stack([blob_r * np.cos(t), 1.3 * blob_r * np.sin(t)], axis=1),
        "limb 110 mm": np.stack([limb_r * np.cos(t), limb_r * np.sin(t)], axis=1),
    }


def _distance_rms(points: np.ndarray, truth: np.ndarray) -> float:
    """RMS distance from points to a closed true polyline (its two edges at the nearest vertex)."""
    _, k = cKDTree(truth).query(points)
    best = np.full(len(points), np.inf)
    for step in (-1, 1):
        a, b = truth[k], truth[(k + step) % len(truth)]
        ab = b - a
        u = np.clip(np.sum((points - a) * ab, axis=1) / np.sum(ab * ab, axis=1), 0.0, 1.0)
        best = np.minimum(best, np.linalg.norm(points - (a + u[:, None] * ab), axis=1))
    return float(np.sqrt(np.mean(best**2)))


def circle_study(seed: int = 0) -> dict[str, Any]:
    """Fig. 6.8: each rule and parameterisation on the noisy circle; RMS and max error."""
    rng = np.random.default_rng(seed)
    sets = [
        _circle(POINTS) + rng.normal(0, np.sqrt(NOISE_VAR_MM2), (POINTS, 2)) for _ in range(TRIALS)
    ]
    out: dict[str, Any] = {}
    for parameter in ("smoothed", "chord"):
        for rule in HARMONIC_RULES:
            orders, rms, worst = [], [], []
            for noisy in sets:
                order = choose_harmonics(noisy, rule, parameter)
                err = np.hypot(*efd_fit(noisy, order, parameter).evaluate(POINTS).T) - R_MM
                orders.append(order)
                rms.append(float(np.sqrt(np.mean(err**2))))
                worst.append(float(np.abs(err).max()))
            out[f"{rule}/{parameter}"] = {
                "harmonics_mean": float(np.mean(orders)),
                "rms_mm": float(np.mean(rms)),
                "max_mm": float(np.max(worst)),
            }
    raw = [np.hypot(*s.T) - R_MM for s in sets]
    out["raw data"] = {
        "harmonics_mean": 0.0,
        "rms_mm": float(np.mean([np.sqrt(np.mean(e**2)) for e in raw])),
        "max_mm": float(np.max([np.abs(e).max() for e in raw])),
    }
    return out


def polygon_study() -> dict[str, int]:
    """Fig. 6.11: HN of an equal-area square, pentagon and octagon (thesis: 6, 5, 5)."""
    area = 17.6**2  # HN = perimeter / 4 pi, so the area sets the scale; see test_efd
    return {name: harmonics_thesis(regular_polygon(k, area)) for name, k in
            (("square", 4), ("pentagon", 5), ("octagon", 8))}  # fmt: skip


def shape_study(sigma_mm: float = 0.05, seed: int = 1) -> dict[str, Any]:
    """Each rule (smoothed parameter) on noisy samples of other outlines: RMS error to truth."""
    rng = np.random.default_rng(seed)
    out: dict[str, Any] = {}
    for name, truth in _shapes().items():
        samples = truth[:: 4000 // 1000]
        noisy = samples + rng.normal(0.0, sigma_mm, samples.shape)
        for rule in HARMONIC_RULES:
            order = choose_harmonics(noisy, rule)
            fit = efd_fit(noisy, order, "smoothed").evaluate(1000)
            out[f"{name}/{rule}"] = {"harmonics": order, "rms_mm": _distance_rms(fit, truth)}
    return out


def interpolation_study() -> dict[str, float]:
    """Sections of an ellipsoid every 2 mm; contours interpolated half-way vs the truth."""
    a, b, c = 10.0, 6.5, 20.0
    t = np.linspace(0.0, 2.0 * np.pi, 400, endpoint=False)

    def section(z: float, n: int = 400) -> np.ndarray:
        s = np.sqrt(1.0 - (z / c) ** 2)
        tt = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False) + 0.7  # start anywhere
        return np.stack([a * s * np.cos(tt), b * s * np.sin(tt)], axis=1)

    heights = np.arange(-16.0, 16.1, 2.0)
    efds = [efd_fit(section(z)[::-1] if k % 2 else section(z), 6) for k, z in enumerate(heights)]
    out = {}
    for kind in ("linear", "pchip"):
        stack = EfdStack.from_sections(list(heights), efds, kind)
        mids = heights[:-1] + 1.0
        errs = []
        for z in mids:
            truth = section(z, 4000)
            errs.append(_distance_rms(stack.section(z).evaluate(len(t)), truth))
        out[f"{kind}_rms_mm"] = float(np.mean(errs))
        out[f"{kind}_max_mm"] = float(np.max(errs))
    return out


def run() -> dict[str, Any]:
    """Run every EFD study."""
    return {
        "circle_fig_6_8": circle_study(),
        "polygons_fig_6_11": polygon_study(),
        "shapes": shape_study(),
        "interpolation": interpolation_study(),
    }


def report(results: dict[str, Any]) -> list[str]:
    """Return the tables."""
    lines = [f"  fig 6.8: circle r {R_MM} mm, noise {NOISE_VAR_MM2} mm^2, {POINTS} points"]
    lines.append("  rule/parameter         harmonics   RMS mm    max mm")
    for name, row in results["circle_fig_6_8"].items():
        lines.append(
            f"  {name:<22} {row['harmonics_mean']:9.2f} {row['rms_mm']:9.4f} {row['max_mm']:9.4f}"
        )
    poly = results["polygons_fig_6_11"]
    lines.append(
        f"  fig 6.11 HN: square {poly['square']}, pentagon {poly['pentagon']}, "
        f"octagon {poly['octagon']} (thesis 6, 5, 5)"
    )
    lines.append("  other outlines, noise 0.05 mm, 1000 points: harmonics / RMS mm per rule")
    for name, row in results["shapes"].items():
        lines.append(f"  {name:<26} {row['harmonics']:5d} {row['rms_mm']:9.4f}")
    interp = results["interpolation"]
    lines.append(
        f"  z interpolation half-way between 2 mm sections of an ellipsoid: linear "
        f"{interp['linear_rms_mm']:.4f} mm RMS (max {interp['linear_max_mm']:.4f}), pchip "
        f"{interp['pchip_rms_mm']:.4f} mm (max {interp['pchip_max_mm']:.4f})"
    )
    return lines
