"""Contour measurements and the radial error table of the thesis (8.2.1, Table 8.3)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from lamina_host.reconstruct.calibration import CalibrationError


def _closed_xy(contour: np.ndarray) -> np.ndarray:
    """Return a validated (N, 2) float array of a closed contour (N >= 3)."""
    pts = np.asarray(contour, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 3:
        raise CalibrationError(
            f"a closed contour needs at least 3 points in an (N, 2) array, got {pts.shape}; "
            "check the section produced data"
        )
    return pts


def _next(values: np.ndarray) -> np.ndarray:
    """Return ``values`` shifted one place back along the last axis (the first comes last):
    each point's successor round a closed contour (``np.roll(values, -1, axis=-1)``, with
    fewer copies)."""
    return np.concatenate([values[..., 1:], values[..., :1]], axis=-1)


def signed_areas(contours: np.ndarray) -> np.ndarray:
    """Return the shoelace areas in mm^2 of closed contours, positive counter-clockwise.

    Args:
        contours: (..., N, 2) points, N >= 3 (not checked: :func:`signed_area` checks one).

    Returns:
        (...) areas; a 0-d array for one (N, 2) contour. Each area is summed along its
        own contour, so a contour's area is the same alone or in a batch.
    """
    x, y = contours[..., 0], contours[..., 1]
    return 0.5 * np.sum(x * _next(y) - _next(x) * y, axis=-1)


def signed_area(contour: np.ndarray) -> float:
    """Return the shoelace area in mm^2, positive when the contour runs counter-clockwise."""
    return float(signed_areas(_closed_xy(contour)))


def polygon_area(contour: np.ndarray) -> float:
    """Return the enclosed area in mm^2 of a closed contour (last point joins the first)."""
    return abs(signed_area(contour))


def perimeters(contours: np.ndarray) -> np.ndarray:
    """Return the lengths in mm of closed contours (..., N, 2), closing edges included.

    Returns:
        (...) lengths, each summed along its own contour as :func:`perimeter` sums it.
    """
    step = np.concatenate([contours[..., 1:, :], contours[..., :1, :]], axis=-2) - contours
    return np.linalg.norm(step, axis=-1).sum(axis=-1)


def perimeter(contour: np.ndarray) -> float:
    """Return the length in mm of a closed contour, including the closing edge."""
    return float(perimeters(_closed_xy(contour)))


def centroid(contour: np.ndarray) -> np.ndarray:
    """Return the (2,) area centroid in mm of a closed contour.

    Raises:
        CalibrationError: the contour encloses no area.
    """
    pts = _closed_xy(contour)
    x, y = pts.T
    xn, yn = _next(x), _next(y)
    cross = x * yn - xn * y
    area = 0.5 * cross.sum()
    scale = float(np.ptp(pts, axis=0).max())
    if abs(area) <= 1e-12 * max(scale * scale, 1e-300):
        raise CalibrationError("the contour encloses no area, so it has no centroid")
    cx = np.sum((x + xn) * cross) / (6.0 * area)
    cy = np.sum((y + yn) * cross) / (6.0 * area)
    return np.array([cx, cy])


RadiusModel = Callable[[np.ndarray, float], np.ndarray]
"""True outline radius at polar angles ``phi`` (rad) of the section at height ``z`` (mm)."""


@dataclass(frozen=True)
class RadialErrorRow:
    """One section of Table 8.3: RMS radial error about its own and the mean centroid."""

    section: int
    z_mm: float
    rms_own_mm: float
    rms_mean_mm: float
    mean_radius_mm: float
    centroid_mm: tuple[float, float]

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form (the fields, the centroid as a list)."""
        return {**asdict(self), "centroid_mm": list(self.centroid_mm)}


@dataclass(frozen=True)
class RadialErrorTable:
    """Table 8.3: per-section RMS radial errors and their means over sections."""

    rows: tuple[RadialErrorRow, ...]
    mean_own_mm: float
    mean_mean_mm: float
    mean_centroid_mm: tuple[float, float]

    @property
    def max_mean_mm(self) -> float:
        """Return the worst section's RMS error about the mean centroid."""
        return max(row.rms_mean_mm for row in self.rows)

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form."""
        return {
            "rows": [row.to_dict() for row in self.rows],
            "mean_own_mm": self.mean_own_mm,
            "mean_mean_mm": self.mean_mean_mm,
            "max_mean_mm": self.max_mean_mm,
            "mean_centroid_mm": list(self.mean_centroid_mm),
        }


def centroid_or_mean(contour: np.ndarray) -> np.ndarray:
    """Return a contour's area centroid, or its samples' mean where it encloses no area.

    For where an outline only has to be placed (chaining outlines up a scan, a limb's
    centre line): a flat outline (a stripe seen edge-on) still has a place.
    """
    try:
        return centroid(contour)
    except CalibrationError:
        return np.asarray(contour, dtype=float).reshape(-1, 2).mean(axis=0)


def _radial_rms(points: np.ndarray, centre: np.ndarray, z_mm: float, radius: RadiusModel) -> float:
    rel = points - centre
    error = np.hypot(rel[:, 0], rel[:, 1]) - radius(np.arctan2(rel[:, 1], rel[:, 0]), z_mm)
    return float(np.sqrt(np.mean(error**2)))


def radial_error_table(
    contours: dict[int, np.ndarray], z_mm: dict[int, float], radius_mm: float | RadiusModel
) -> RadialErrorTable:
    """Compute the RMS radial error of each section of a scanned object (thesis 8.2.1).

    The error of a point is ``|point - centre| - r``, with ``r`` the true radius in the
    point's direction (a constant for a cylinder, see :class:`RadiusModel`). Column one uses each
    section's own area centroid as the centre (xy accuracy only); column two uses the mean
    of all sections' centroids, so section-to-section misalignment is included. The
    "mean" entries average the per-section RMS values, as in Table 8.3.

    Args:
        contours: section index -> (N, 2) closed contour in mm (object frame).
        z_mm: section index -> height in mm.
        radius_mm: the cylinder's true radius, or the true radius as a function of angle
            and height for other shapes.

    Returns:
        RadialErrorTable with rows in ascending section order.

    Raises:
        CalibrationError: no contours, a section without a height or without points.
    """
    if not contours:
        raise CalibrationError("no sections to measure; the scan produced no contours")
    missing = sorted(set(contours) - set(z_mm))
    if missing:
        raise CalibrationError(f"sections {missing} have no z_mm; pass a height for each")
    radius: RadiusModel = (
        radius_mm if callable(radius_mm) else (lambda phi, z: np.full(len(phi), radius_mm))
    )
    sections = sorted(contours)
    pts = [np.asarray(contours[s], dtype=float).reshape(-1, 2) for s in sections]
    empty = [s for s, p in zip(sections, pts, strict=True) if len(p) == 0]
    if empty:
        raise CalibrationError(f"sections {empty} have no contour points; nothing to measure")
    # A flat outline (a stripe seen edge-on) still gets a row, about its points' mean.
    centres = np.array([centroid_or_mean(p) for p in pts])
    mean_centre = centres.mean(axis=0)
    rows = []
    for s, p, c in zip(sections, pts, centres, strict=True):
        rows.append(
            RadialErrorRow(
                section=s,
                z_mm=float(z_mm[s]),
                rms_own_mm=_radial_rms(p, c, z_mm[s], radius),
                rms_mean_mm=_radial_rms(p, mean_centre, z_mm[s], radius),
                mean_radius_mm=float(np.linalg.norm(p - c, axis=1).mean()),
                centroid_mm=(float(c[0]), float(c[1])),
            )
        )
    return RadialErrorTable(
        rows=tuple(rows),
        mean_own_mm=float(np.mean([r.rms_own_mm for r in rows])),
        mean_mean_mm=float(np.mean([r.rms_mean_mm for r in rows])),
        mean_centroid_mm=(float(mean_centre[0]), float(mean_centre[1])),
    )


@dataclass(frozen=True)
class SphereProbing:
    """Probing errors of a scanned sphere, after VDI/VDE 2634 part 2.

    ``form_mm`` (P_F) is the range of the points' radial distances from the least-squares
    sphere; ``size_mm`` (P_S) is the fitted diameter minus the true diameter.
    """

    form_mm: float
    size_mm: float
    fitted_diameter_mm: float
    centre_mm: tuple[float, float, float]
    rms_mm: float
    points: int

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form."""
        return {
            "probing_error_form_mm": self.form_mm,
            "probing_error_size_mm": self.size_mm,
            "fitted_diameter_mm": self.fitted_diameter_mm,
            "centre_mm": list(self.centre_mm),
            "rms_mm": self.rms_mm,
            "points": self.points,
        }


def sphere_probing(points: np.ndarray, true_diameter_mm: float) -> SphereProbing:
    """Fit a sphere by orthogonal distance and return the VDI/VDE 2634-2 probing errors.

    The algebraic fit ``|p|^2 = 2 c.p + k`` starts Levenberg-Marquardt on ``|p - c| - r``.

    Args:
        points: (N, 3) measured surface points in mm, N >= 4.
        true_diameter_mm: the calibrated sphere's diameter.

    Raises:
        CalibrationError: too few or degenerate points.
    """
    from scipy.optimize import least_squares  # deferred: only sphere reports need it

    p = np.asarray(points, dtype=float)
    if p.ndim != 2 or p.shape[1] != 3 or len(p) < 4 or not np.isfinite(p).all():
        raise CalibrationError(f"a sphere fit needs at least 4 finite (N, 3) points, got {p.shape}")
    a = np.column_stack([2.0 * p, np.ones(len(p))])
    sol, *_ = np.linalg.lstsq(a, np.sum(p * p, axis=1), rcond=None)
    centre0 = sol[:3]
    r0 = float(np.sqrt(max(sol[3] + centre0 @ centre0, 1e-12)))

    def residuals(x: np.ndarray) -> np.ndarray:
        return np.linalg.norm(p - x[:3], axis=1) - x[3]

    fit = least_squares(residuals, np.append(centre0, r0), method="lm")
    dist = fit.fun
    diameter = float(2.0 * abs(fit.x[3]))
    return SphereProbing(
        form_mm=float(dist.max() - dist.min()),
        size_mm=diameter - float(true_diameter_mm),
        fitted_diameter_mm=diameter,
        centre_mm=(float(fit.x[0]), float(fit.x[1]), float(fit.x[2])),
        rms_mm=float(np.sqrt(np.mean(dist**2))),
        points=len(p),
    )
