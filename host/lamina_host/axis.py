"""Turntable axis and scale correction from a calibration cylinder (thesis 6.2).

Each view of the cylinder gives an arc in the laser plane; a circle is fitted to every
arc (6.2.1), the axis is the centroid of the arc centres (6.2.2) and the correction
factor is ``C_f = D_a / D_e`` (6.2.4, eq. 6.3), with a warning when it is more than 5 %
from one.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.optimize import least_squares

from lamina_host.calibration import CalibrationError

CF_WARNING = 0.05
"""Thesis 6.2.4: warn when the correction factor differs from 1 by more than 5 %."""

RADIUS_SPREAD_WARNING = 0.02
"""Fitted arc radii that differ by more than 2 % between views suggest bad arcs."""


@dataclass(frozen=True)
class Circle:
    """A fitted circle in mm with the RMS orthogonal distance of its points."""

    cx: float
    cy: float
    r: float
    rms_mm: float


@dataclass(frozen=True, eq=False)
class AxisCalibration:
    """Turntable axis, scale correction and the per-arc circles they came from."""

    axis_xy_mm: tuple[float, float]
    correction_factor: float
    estimated_diameter_mm: float
    actual_diameter_mm: float
    arc_centres_mm: np.ndarray
    arc_radii_mm: np.ndarray
    warnings: tuple[str, ...]

    def to_dict(self) -> dict[str, Any]:
        """Return a JSON-ready summary."""
        return {
            "axis_xy_mm": list(self.axis_xy_mm),
            "correction_factor": self.correction_factor,
            "estimated_diameter_mm": self.estimated_diameter_mm,
            "actual_diameter_mm": self.actual_diameter_mm,
            "arc_centres_mm": self.arc_centres_mm.tolist(),
            "arc_radii_mm": self.arc_radii_mm.tolist(),
            "warnings": list(self.warnings),
        }


def _taubin(pts: np.ndarray) -> tuple[float, float, float]:
    """Taubin's algebraic circle fit (SVD form); nearly unbiased on short arcs, unlike Kasa.

    Returns:
        (cx, cy, r) in the units of ``pts``.
    """
    mean = pts.mean(axis=0)
    x, y = (pts - mean).T
    z = x * x + y * y
    z_mean = z.mean()
    if z_mean <= 0.0:
        raise CalibrationError("all arc points coincide; no circle can be fitted to this arc")
    z0 = (z - z_mean) / (2.0 * np.sqrt(z_mean))
    _, _, vt = np.linalg.svd(np.stack([z0, x, y], axis=1), full_matrices=False)
    a = vt[2].copy()
    a[0] /= 2.0 * np.sqrt(z_mean)
    a0, a1, a2 = a
    a3 = -z_mean * a0
    if abs(a0) < 1e-12 * max(abs(a1), abs(a2), 1e-300):
        raise CalibrationError(
            "arc points lie on a straight line; no circle can be fitted (check the arc data)"
        )
    cx = -a1 / (2.0 * a0) + mean[0]
    cy = -a2 / (2.0 * a0) + mean[1]
    r = np.sqrt(a1 * a1 + a2 * a2 - 4.0 * a0 * a3) / (2.0 * abs(a0))
    return float(cx), float(cy), float(r)


def fit_circle(points: np.ndarray) -> Circle:
    """Fit a circle by orthogonal distance, started from Taubin's algebraic fit (thesis 6.2.1).

    The thesis refines an initial fit iteratively until the mean squared error stops
    changing; here Levenberg-Marquardt on the orthogonal distances ``|p - c| - r`` runs to
    convergence from the Taubin estimate.

    Args:
        points: (K, 2) points in mm, K >= 3.

    Returns:
        The best-fit Circle.

    Raises:
        CalibrationError: fewer than 3 points, non-finite values, or collinear points.
    """
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) < 3:
        raise CalibrationError(
            f"a circle fit needs at least 3 points in a (K, 2) array, got shape {pts.shape}; "
            "check the arc was extracted"
        )
    if not np.isfinite(pts).all():
        raise CalibrationError("arc points contain NaN or infinity; re-extract the arc")
    cx0, cy0, r0 = _taubin(pts)

    def residuals(p: np.ndarray) -> np.ndarray:
        return np.hypot(pts[:, 0] - p[0], pts[:, 1] - p[1]) - p[2]

    def jacobian(p: np.ndarray) -> np.ndarray:
        dx, dy = pts[:, 0] - p[0], pts[:, 1] - p[1]
        d = np.maximum(np.hypot(dx, dy), 1e-300)
        return np.stack([-dx / d, -dy / d, -np.ones_like(d)], axis=1)

    sol = least_squares(
        residuals,
        np.array([cx0, cy0, r0]),
        jac=jacobian,
        method="lm",
        xtol=1e-15,
        ftol=1e-15,
        gtol=1e-15,
        max_nfev=500,
    )
    cx, cy, r = sol.x
    rms = float(np.sqrt(np.mean(residuals(sol.x) ** 2)))
    return Circle(float(cx), float(cy), float(abs(r)), rms)


def find_axis(arcs: list[np.ndarray], actual_diameter_mm: float) -> AxisCalibration:
    """Locate the turntable axis and the scale correction from calibration-cylinder arcs.

    Thesis 6.2: one circle per arc (6.2.1); axis = mean of the arc centres (6.2.2), which
    is the axis only when the views are spread evenly round the turn (e.g. 8 x 45 deg);
    ``D_e`` = mean fitted diameter and ``C_f = D_a / D_e`` (6.2.4, eq. 6.3).

    Args:
        arcs: world-frame (K, 2) arcs in mm, one per view, already trimmed.
        actual_diameter_mm: the cylinder's true diameter ``D_a``.

    Returns:
        AxisCalibration, with warnings for ``|C_f - 1| > 5 %`` and for inconsistent radii.

    Raises:
        CalibrationError: fewer than 3 arcs, a bad diameter, or an arc that cannot be fitted.
    """
    if not np.isfinite(actual_diameter_mm) or actual_diameter_mm <= 0:
        raise CalibrationError(
            f"calibration cylinder diameter must be a positive number of mm, not "
            f"{actual_diameter_mm}; fix calibration_cylinder.diameter_mm"
        )
    if len(arcs) < 3:
        raise CalibrationError(
            f"finding the turntable axis needs at least 3 cylinder views, got {len(arcs)}; "
            "capture the cylinder at several evenly spaced angles (the thesis uses 8)"
        )
    circles = [fit_circle(arc) for arc in arcs]
    centres = np.array([[c.cx, c.cy] for c in circles])
    radii = np.array([c.r for c in circles])
    axis = centres.mean(axis=0)
    d_est = float(2.0 * radii.mean())
    cf = float(actual_diameter_mm / d_est)
    warnings: list[str] = []
    if abs(cf - 1.0) > CF_WARNING:
        warnings.append(
            f"correction factor {cf:.4f} is more than {CF_WARNING:.0%} from 1 (measured "
            f"diameter {d_est:.3f} mm vs {actual_diameter_mm:.3f} mm); check the grid "
            "calibration and the cylinder diameter"
        )
    spread = float((radii.max() - radii.min()) / radii.mean())
    if spread > RADIUS_SPREAD_WARNING:
        warnings.append(
            f"fitted cylinder radii vary by {spread:.1%} between views; check the cylinder "
            "arcs for outliers or a tilted cylinder"
        )
    return AxisCalibration(
        axis_xy_mm=(float(axis[0]), float(axis[1])),
        correction_factor=cf,
        estimated_diameter_mm=d_est,
        actual_diameter_mm=float(actual_diameter_mm),
        arc_centres_mm=centres,
        arc_radii_mm=radii,
        warnings=tuple(warnings),
    )
