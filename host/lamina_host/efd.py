"""Elliptic Fourier descriptors for smoothing and closing each section (thesis 6.4).

Coefficients follow Kuhl and Giardina's closed forms (thesis eqs. 6.11-6.14), the
harmonic count follows the thesis' HN heuristic (6.4.6, eqs. 6.15-6.16) capped at the
Nyquist limit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lamina_host.calibration import CalibrationError
from lamina_host.measure import centroid, perimeter, polygon_area


@dataclass(frozen=True, eq=False)
class EllipticFourier:
    """A truncated elliptic Fourier series: DC terms and (N, 4) rows (a_n, b_n, c_n, d_n)."""

    a0: float
    c0: float
    coeffs: np.ndarray

    @property
    def order(self) -> int:
        """Return the number of harmonics N."""
        return int(self.coeffs.shape[0])

    def evaluate(self, n_points: int) -> np.ndarray:
        """Sample the series (thesis eqs. 6.9-6.10) at ``n_points`` uniform steps of t.

        Args:
            n_points: number of samples over one period; t = k / n_points, k = 0..n-1.

        Returns:
            (n_points, 2) points in mm, starting at the input's first point and running the
            same way round as the input.
        """
        if n_points < 1:
            raise ValueError(f"n_points must be at least 1, not {n_points}")
        t = np.arange(n_points) / n_points
        n = np.arange(1, self.order + 1)[:, None]
        phase = 2.0 * np.pi * n * t[None, :]
        cos, sin = np.cos(phase), np.sin(phase)
        a, b, c, d = self.coeffs.T
        x = self.a0 + a @ cos + b @ sin
        y = self.c0 + c @ cos + d @ sin
        return np.stack([x, y], axis=1)


def _clean_closed(contour: np.ndarray) -> np.ndarray:
    """Drop consecutive duplicate points and an explicit closing point (they give dt = 0)."""
    pts = np.asarray(contour, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2:
        raise CalibrationError(f"a contour must be an (N, 2) array, got shape {pts.shape}")
    if not np.isfinite(pts).all():
        raise CalibrationError("the contour contains NaN or infinity; check the section data")
    if len(pts) > 1:
        step = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        pts = pts[np.concatenate([[True], step > 0.0])]
    while len(pts) > 1 and np.array_equal(pts[0], pts[-1]):
        pts = pts[:-1]
    if len(pts) < 3:
        raise CalibrationError(
            f"a closed contour needs at least 3 distinct points, got {len(pts)}; "
            "check the section produced data"
        )
    return pts


def efd_fit(contour: np.ndarray, order: int) -> EllipticFourier:
    """Fit elliptic Fourier coefficients with DC terms (Kuhl-Giardina, thesis eqs. 6.11-6.14).

    The contour is treated as closed (last point joins the first) and parameterised by arc
    length t, period T = perimeter.

    Args:
        contour: (K, 2) points in mm along a closed outline.
        order: number of harmonics N >= 1.

    Returns:
        EllipticFourier with A0, C0 and (N, 4) coefficients.
    """
    if order < 1:
        raise ValueError(f"EFD order must be at least 1, not {order}")
    pts = _clean_closed(contour)
    dxy = np.roll(pts, -1, axis=0) - pts  # segment p runs from point p to p+1 (closing last)
    dt = np.linalg.norm(dxy, axis=1)
    t = np.concatenate([[0.0], np.cumsum(dt)])
    period = t[-1]
    t_prev, t_cur = t[:-1], t[1:]

    n = np.arange(1, order + 1)[:, None]
    const = period / (2.0 * np.pi**2 * n[:, 0] ** 2)
    phi = 2.0 * np.pi * n * t[None, :] / period
    d_cos = np.cos(phi[:, 1:]) - np.cos(phi[:, :-1])
    d_sin = np.sin(phi[:, 1:]) - np.sin(phi[:, :-1])
    slope = dxy / dt[:, None]  # (dx_p/dt_p, dy_p/dt_p)
    a = const * (d_cos @ slope[:, 0])  # eq. 6.12
    b = const * (d_sin @ slope[:, 0])  # eq. 6.13
    c = const * (d_cos @ slope[:, 1])
    d = const * (d_sin @ slope[:, 1])

    # Eq. 6.14: xi_p = sum_{j<p} dx_j - (dx_p/dt_p) sum_{j<p} dt_j (and delta_p for y).
    cum_prev = np.concatenate([[[0.0, 0.0]], np.cumsum(dxy, axis=0)[:-1]])
    xi = cum_prev - slope * t_prev[:, None]
    dt2 = (t_cur**2 - t_prev**2)[:, None]
    # Eq. 6.11, relative to the first point, so add it back for absolute DC terms.
    dc = (np.sum(slope / 2.0 * dt2 + xi * dt[:, None], axis=0) / period) + pts[0]
    return EllipticFourier(float(dc[0]), float(dc[1]), np.stack([a, b, c, d], axis=1))


def harmonics_thesis(contour: np.ndarray) -> int:
    """Return the thesis' harmonic number HN = 1 / (PA * RF), rounded (6.4.6, eqs. 6.15-6.16).

    PA = perimeter / area and RF = 4 pi area / perimeter^2, both from the closed polyline
    in mm. Note the product simplifies to HN = perimeter / (4 pi): it depends on the
    contour's length in mm, not on its shape.

    Returns:
        HN rounded half up, at least 1.
    """
    pts = _clean_closed(contour)
    pm = perimeter(pts)
    area = polygon_area(pts)
    if area <= 0.0:
        raise CalibrationError("the contour encloses no area; cannot choose EFD harmonics")
    pa = pm / area
    rf = 4.0 * np.pi * area / pm**2
    return max(1, int(np.floor(1.0 / (pa * rf) + 0.5)))


def nyquist_max(n_points: int) -> int:
    """Return the Nyquist cap on harmonics for F_s = n_points (thesis 6.4.6).

    F_s / 2 for even F_s, (F_s - 1) / 2 for odd F_s, i.e. ``n_points // 2``.
    """
    if n_points < 0:
        raise ValueError(f"n_points must be non-negative, not {n_points}")
    return n_points // 2


def _bin_by_angle(pts: np.ndarray, bin_deg: float = 1.0) -> np.ndarray:
    """Return the mean-radius point of each non-empty polar-angle bin about the centroid."""
    centre = centroid(pts)
    d = pts - centre
    ang = np.arctan2(d[:, 1], d[:, 0])
    rad = np.hypot(d[:, 0], d[:, 1])
    n_bins = round(360.0 / bin_deg)
    idx = np.minimum(((ang + np.pi) / (2.0 * np.pi) * n_bins).astype(int), n_bins - 1)
    counts = np.bincount(idx, minlength=n_bins)
    sums = np.bincount(idx, weights=rad, minlength=n_bins)
    full = counts > 0
    mean_r = sums[full] / counts[full]
    centres = -np.pi + (np.flatnonzero(full) + 0.5) * (2.0 * np.pi / n_bins)
    return centre + np.stack([mean_r * np.cos(centres), mean_r * np.sin(centres)], axis=1)


def choose_harmonics(contour: np.ndarray) -> int:
    """Choose the EFD order: min(HN of the 1-degree-binned contour, Nyquist cap).

    Point noise makes a polyline zig-zag, inflating its perimeter and hence HN (which is
    perimeter / 4 pi). So HN (thesis 6.4.6) is evaluated on the contour binned to 1 degree
    of polar angle about its area centroid (mean radius per bin), which keeps the outline
    but averages out the zig-zag. The Nyquist cap uses the original point count. This
    binning is Lamina's choice, not the thesis'; it assumes a star-shaped section.

    Args:
        contour: (K, 2) closed contour in mm.

    Returns:
        Number of harmonics, at least 1.
    """
    pts = _clean_closed(contour)
    binned = _bin_by_angle(pts)
    hn = harmonics_thesis(binned) if len(binned) >= 3 else 1
    return max(1, min(hn, nyquist_max(len(pts))))
