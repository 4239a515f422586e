"""Elliptic Fourier descriptors for smoothing and closing each section (thesis 6.4).

Coefficients follow Kuhl and Giardina's closed forms (thesis eqs. 6.11-6.14). The number
of harmonics follows one of ``HARMONIC_RULES``:

- ``"residual"`` (default): the fewest harmonics at which the measured points' residual
  reaches their own noise, measured where the views overlap (Kuhl and Giardina's error
  bound of 6.4.6 with epsilon taken from the data); without overlaps, ``"noise"``.
- ``"noise"``: keep every harmonic that stands clearly above the contour's own noise
  floor, measured from the high end of its harmonic spectrum.
- ``"power"``: the fewest harmonics holding ``POWER_FRACTION`` of the cumulative
  harmonic power (the power-spectrum idea of 6.4.6).
- ``"thesis"``: the HN heuristic (6.4.6, eqs. 6.15-6.16) on the 1-degree-binned contour.
- ``"nyquist"``: the Nyquist cap itself, as "many applications" do (6.4.6).

Every rule is capped at the Nyquist limit. ``EfdStack`` aligns each section's start point
and direction and interpolates the coefficients along z (thesis ref. [86], 9.2), so a
contour can be produced at any height and all contours share one parameterisation.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.interpolate import PchipInterpolator, make_smoothing_spline

from lamina_host.reconstruct.calibration import CalibrationError
from lamina_host.reconstruct.measure import (
    centroid,
    perimeter,
    perimeters,
    polygon_area,
    signed_areas,
)
from lamina_host.reconstruct.outline_frame import OutlineFrame, unwrap_angles


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
        if 2 * self.order < n_points:
            # Uniform t makes the series an inverse real FFT: sum_n a_n cos + b_n sin
            # = Re sum_n (a_n - i b_n) e^(2 pi i n k / K), exact below the Nyquist limit.
            a, b, c, d = self.coeffs.T
            spectrum = np.zeros((2, n_points // 2 + 1), dtype=complex)
            spectrum[0, 1 : self.order + 1] = a - 1j * b
            spectrum[1, 1 : self.order + 1] = c - 1j * d
            xy = np.fft.irfft(spectrum * (n_points / 2.0), n_points, axis=1)
            return np.stack([xy[0] + self.a0, xy[1] + self.c0], axis=1)
        t = np.arange(n_points) / n_points
        n = np.arange(1, self.order + 1)[:, None]
        phase = 2.0 * np.pi * n * t[None, :]
        cos, sin = np.cos(phase), np.sin(phase)
        a, b, c, d = self.coeffs.T
        x = self.a0 + a @ cos + b @ sin
        y = self.c0 + c @ cos + d @ sin
        return np.stack([x, y], axis=1)

    def to_dict(self) -> dict[str, Any]:
        """Return the JSON form: DC terms and the (N, 4) coefficient rows."""
        return {"a0": self.a0, "c0": self.c0, "coeffs": self.coeffs.tolist()}

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> EllipticFourier:
        """Rebuild a series from :meth:`to_dict`'s form.

        Raises:
            CalibrationError: the form is not a finite series of at least one harmonic.
        """
        try:
            coeffs = np.asarray(data["coeffs"], dtype=float).reshape(-1, 4)
            a0, c0 = float(data["a0"]), float(data["c0"])
        except (KeyError, TypeError, ValueError):
            raise CalibrationError(
                "a stored EFD section is damaged; process the scan again"
            ) from None
        if len(coeffs) == 0 or not np.isfinite(coeffs).all() or not np.isfinite([a0, c0]).all():
            raise CalibrationError("a stored EFD section is damaged; process the scan again")
        return cls(a0, c0, coeffs)


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


PARAMETERS = ("smoothed", "chord")
"""How the EFD parameter t runs along the points: "chord" is Kuhl-Giardina's (and pyefd's)
polyline arc length; "smoothed" is the arc length of the moving-averaged outline."""


def _steps(pts: np.ndarray, parameter: str) -> np.ndarray:
    """Return the parameter step from each point to the next (closing), all positive.

    Chord lengths of a noisy, dense outline are mostly zig-zag: they lengthen the period
    and make t a random walk, which leaks the fundamental into neighbouring harmonics and
    shrinks it. The arc length of a circular moving average over ``K / 32`` points keeps
    the outline's own progress but not the scatter.
    """
    if parameter == "chord":
        dt = np.linalg.norm(np.roll(pts, -1, axis=0) - pts, axis=1)
    elif parameter == "smoothed":
        half = len(pts) // 64
        if half == 0:
            return _steps(pts, "chord")
        width = 2 * half + 1
        padded = np.concatenate([pts[-half:], pts, pts[:half]])
        # Moving average by running sums: O(K) instead of a K x K/32 convolution.
        csum = np.concatenate([np.zeros((1, 2)), np.cumsum(padded, axis=0)])
        smooth = (csum[width:] - csum[:-width]) / width
        dt = np.linalg.norm(np.roll(smooth, -1, axis=0) - smooth, axis=1)
    else:
        raise ValueError(f"unknown EFD parameter {parameter!r}; use {', '.join(PARAMETERS)}")
    return np.maximum(dt, 1e-9 * max(float(dt.mean()), 1e-300))


def efd_fit(contour: np.ndarray, order: int, parameter: str = "chord") -> EllipticFourier:
    """Fit elliptic Fourier coefficients with DC terms (Kuhl-Giardina, thesis eqs. 6.11-6.14).

    The contour is treated as closed (last point joins the first) and parameterised by t,
    period T. The closed forms hold for any increasing t along the piecewise-linear
    outline; ``parameter`` chooses it (see ``PARAMETERS``; "chord" matches pyefd).

    Args:
        contour: (K, 2) points in mm along a closed outline.
        order: number of harmonics N >= 1.
        parameter: "chord" (Kuhl-Giardina's arc length) or "smoothed".

    Returns:
        EllipticFourier with A0, C0 and (N, 4) coefficients.
    """
    if order < 1:
        raise ValueError(f"EFD order must be at least 1, not {order}")
    pts = _clean_closed(contour)
    dxy = np.roll(pts, -1, axis=0) - pts  # segment p runs from point p to p+1 (closing last)
    dt = _steps(pts, parameter)
    t = np.concatenate([[0.0], np.cumsum(dt)])
    period = t[-1]
    t_prev, t_cur = t[:-1], t[1:]

    n = np.arange(1, order + 1)
    const = period / (2.0 * np.pi**2 * n**2)
    # cos and sin of 2 pi n t / T for every n as powers of one unit phasor: N complex
    # products per point instead of 2N trigonometric calls (hot path for long outlines).
    base = np.exp(2j * np.pi * t / period)
    waves = np.cumprod(np.broadcast_to(base, (order, len(t))), axis=0)
    d_cos = np.diff(waves.real, axis=1)
    d_sin = np.diff(waves.imag, axis=1)
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


def harmonics_binned_thesis(contour: np.ndarray) -> int:
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


HARMONIC_RULES = ("residual", "noise", "power", "thesis", "nyquist")
"""Selectable harmonic-count rules; the first is the default."""

HARMONICS_RANGE = (1, 100)
"""The fixed EFD orders a user may ask for, first to last (None lets the rule choose)."""


def harmonics_problem(harmonics: object, name: str = "harmonics") -> str | None:
    """Return why ``harmonics`` is no fixed order a user may ask for, or None if it is.

    Args:
        harmonics: the order asked for; None (the harmonic rule chooses) is no problem.
        name: how the asking front end names the option (``--harmonics``).
    """
    if harmonics is None:
        return None
    low, high = HARMONICS_RANGE
    if not isinstance(harmonics, int) or isinstance(harmonics, bool):
        return f"{name} {harmonics} must be a whole number between {low} and {high}"
    if not low <= harmonics <= high:
        return f"{name} {harmonics} must be between {low} and {high}"
    return None


POWER_FRACTION = 0.9999
"""The ``"power"`` rule keeps the fewest harmonics holding this share of the power."""

NOISE_POWER_FACTOR = 50.0
"""A harmonic is signal when its power exceeds the noise floor this many times: noise-only
harmonic power is about sigma^2 chi-square(4) (P > 50 sigma^2 ~ 1e-9), but its tail is
heavier in practice, as the 4 coefficients do not get equal shares of the noise."""

MAX_TESTED_HARMONICS = 128
"""The noise rule looks no further: harmonic 128 of a 350 mm limb outline has a 2.7 mm
wavelength, about the section pitch."""

MIN_TESTED_WAVELENGTH_MM = 2.7
"""The residual rule and its relief peaks look as far as this wavelength round a longer
outline (past ``MAX_TESTED_HARMONICS``): skin relief at 4 mm round a 530 mm outline (a
wide random limb shape) lies at harmonic 133, and a rule stopped at 128 kept 66 of its
harmonics and half its coverage (truth: 200 harmonics, 0.225 -> 0.100 mm)."""

_CHI2_4_MEDIAN = 3.3567
"""Median of a chi-square variable with 4 degrees of freedom."""


def _spectrum(pts: np.ndarray, n_max: int, parameter: str) -> np.ndarray:
    """Return harmonic powers a^2+b^2+c^2+d^2 for n = 1..n_max of a closed polyline.

    The polyline is resampled uniformly in the parameter t and transformed by FFT, which
    matches the Kuhl-Giardina coefficients for harmonics well below the resampling rate,
    at O(L log L) instead of O(N K).
    """
    closed = np.vstack([pts, pts[:1]])
    t = np.concatenate([[0.0], np.cumsum(_steps(pts, parameter))])
    length = int(2 ** np.ceil(np.log2(max(8 * n_max, 64))))
    ts = np.arange(length) * (t[-1] / length)
    x = np.interp(ts, t, closed[:, 0])
    y = np.interp(ts, t, closed[:, 1])
    fx = np.fft.rfft(x)[1 : n_max + 1] * (2.0 / length)
    fy = np.fft.rfft(y)[1 : n_max + 1] * (2.0 / length)
    return np.abs(fx) ** 2 + np.abs(fy) ** 2


def harmonics_noise(contour: np.ndarray, parameter: str = "smoothed") -> int:
    """Return the highest harmonic that stands clearly above the noise at its frequency.

    The noise floor at harmonic n is the median power of harmonics n+1 .. 2n+8, scaled to
    sigma^2 by the chi-square(4) median. A local floor, because scanner noise is not
    white: stripe noise is correlated along the stripe and overlap averaging mixes views,
    so mid-frequency harmonics carry more noise than the highest ones. Smooth outlines
    have few, decaying harmonics, so the median over the harmonics above n is noise.
    Harmonics are tested up to 1/16 of the point count (windows stay near 1/8 of it,
    below where the polyline's linear interpolation starts to attenuate noise) and at
    most ``MAX_TESTED_HARMONICS``.

    Returns:
        At least 1, at most the Nyquist cap.
    """
    pts = _clean_closed(contour)
    cap = nyquist_max(len(pts))
    if _spectral_top(len(pts)) < 2:
        return max(1, cap)
    signal = _standing_harmonics(pts, NOISE_POWER_FACTOR, parameter)
    return int(max(1, min(cap, signal[-1] if len(signal) else 1)))


def _spectral_top(n_points: int, most: int = MAX_TESTED_HARMONICS) -> int:
    """Return the highest harmonic the spectral tests look at for this many points."""
    return min(n_points // 16, most)


def highest_tested_order(pts: np.ndarray) -> int:
    """Return the highest order the residual rule tests on a closed polyline: harmonic
    ``MAX_TESTED_HARMONICS``, or on a longer outline that of ``MIN_TESTED_WAVELENGTH_MM``."""
    if len(pts) < 3:  # nothing to fit past harmonic 1 (and no perimeter to take)
        return MAX_TESTED_HARMONICS
    return max(MAX_TESTED_HARMONICS, int(perimeter(pts) / MIN_TESTED_WAVELENGTH_MM))


def _standing_harmonics(
    pts: np.ndarray, factor: float, parameter: str, most: int = MAX_TESTED_HARMONICS
) -> np.ndarray:
    """Return the harmonics whose power exceeds ``factor`` times the local noise floor.

    The floor at harmonic n is the median power of harmonics n+1 .. 2n+8 scaled to sigma^2
    (:func:`harmonics_noise`); harmonics are tested up to 1/16 of the point count and at
    most ``MAX_TESTED_HARMONICS``.

    Args:
        pts: (K, 2) cleaned closed polyline in mm.
        factor: how many times the floor a harmonic's power must exceed.
        parameter: the EFD parameterisation (``PARAMETERS``).

    Returns:
        The harmonic numbers, ascending; empty when fewer than 2 can be tested.
    """
    top = _spectral_top(len(pts), most)
    if top < 2:
        return np.zeros(0, dtype=int)
    power = _spectrum(pts, 2 * top + 8, parameter)
    n = np.arange(1, top + 1)
    # The median of power[k : 2k + 8] for every k at once: rows padded with +inf, which
    # sorts last, so row k's median sits at the middle of its first k + 8 (a sort is
    # several times faster than a NaN-aware median here).
    cols = np.arange(2 * top + 8)
    idx = np.minimum(n[:, None] + cols[None, :], len(power) - 1)
    windows = np.sort(np.where(cols[None, :] < (n + 8)[:, None], power[idx], np.inf), axis=1)
    size = n + 8
    median = 0.5 * (windows[n - 1, (size - 1) // 2] + windows[n - 1, size // 2])
    return n[power[:top] > factor * median / _CHI2_4_MEDIAN]


RESIDUAL_MARGIN = 0.0
"""The ``"residual"`` rule stops when the measured points' RMS residual is at most this
share above their own noise; at 0 the residual must reach the noise itself. The noise
estimate varies by about 5 % between sections, and a wider margin stops short of relief
that each point's noise hides but thousands of points show (half of a 0.16 mm fold at
harmonic 28 of a 220 mm forearm, limb rig, harsh); where the estimate falls below the
plateau the residual settles on, the plateau test (``PLATEAU_MARGIN``) stops the rule."""


@dataclass(frozen=True, eq=False)
class MeasuredPoints:
    """The measured points an outline's order is judged by: their coordinates in the
    outline's ``frame`` (polar about its centre when star-shaped, as the overlap blending
    took them) and their noise from the overlaps."""

    frame: OutlineFrame
    angle_rad: np.ndarray
    radius_mm: np.ndarray
    noise_mm: float


def _truncations(pts: np.ndarray, top: int, parameter: str) -> tuple[np.ndarray, np.ndarray]:
    """Return the polyline's complex FFT coefficients of x and y up to ``top`` and the length.

    The polyline is resampled uniformly in t (as :func:`_spectrum`), so the coefficients
    below the resampling rate are the Kuhl-Giardina ones.
    """
    closed = np.vstack([pts, pts[:1]])
    t = np.concatenate([[0.0], np.cumsum(_steps(pts, parameter))])
    length = int(2 ** np.ceil(np.log2(max(8 * top, 256))))
    ts = np.arange(length) * (t[-1] / length)
    xy = np.stack([np.interp(ts, t, closed[:, 0]), np.interp(ts, t, closed[:, 1])])
    return np.fft.rfft(xy, axis=1), np.array(length)


def _frame_table(frame: OutlineFrame, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return a closed curve's samples as (position, offset) in ``frame``, by position.

    A curve that runs one way round the frame (a star-shaped outline about its centre, or
    one that follows its reference curve) has positions that ascend once reversed if need
    be, with no sort; otherwise the positions in (-pi, pi] are sorted. The positions
    ascend from the first and span less than one turn.
    """
    t, offset = frame.to_local(xy)
    ang = unwrap_angles(t)
    if ang[-1] < ang[0]:
        ang, offset = ang[::-1], offset[::-1]
    if np.all(np.diff(ang) > 0) and ang[-1] - ang[0] < 2.0 * np.pi:
        return ang, offset
    order = np.argsort(t)
    return t[order], frame.to_local(xy)[1][order]


def harmonics_residual(
    contour: np.ndarray,
    measured: MeasuredPoints,
    parameter: str = "smoothed",
    margin: float = RESIDUAL_MARGIN,
) -> int:
    """Return the fewest harmonics at which the measured points' residual reaches their noise.

    Kuhl and Giardina's bound (thesis 6.4.6) asks for an error no larger than a chosen
    epsilon, and the thesis leaves open how to choose it; here it is the points' own
    noise, measured where views overlap (``MeasuredPoints.noise_mm``). The residual of
    order N is the RMS radial distance of the measured points (each view's own points,
    before blending) from the series truncated at N, in the blending's frame; it falls
    as N grows, to the noise once the shape is fitted, and lower only by following noise.
    So the order is the smallest N whose residual is at most ``(1 + margin)`` noise, or
    within ``PLATEAU_MARGIN`` of it and no longer falling (all higher orders together
    remove less than ``PLATEAU_GAIN`` of the noise power beyond what following the noise
    removes, judged by the residual's fall over the upper half of the orders), tested up
    to ``MAX_TESTED_HARMONICS`` and the Nyquist cap: first on a coarse grid of orders,
    then by bisection below the first order that passes. The noise estimate can sit above
    the floor the residual settles on, so the residual can reach it just short of fine
    relief; a harmonic past that order whose power stands ``RELIEF_POWER_FACTOR`` times
    above the blend's local noise floor, and whose removal the measured points confirm
    (they lose more than ``PLATEAU_GAIN`` noise^2 beyond following noise), sets the order
    instead (the highest such).

    Args:
        contour: (K, 2) blended closed contour in mm (what is fitted).
        measured: the measured points and their noise.
        parameter: the EFD parameterisation (``PARAMETERS``).
        margin: share above the noise at which the residual has reached it.

    Returns:
        At least 1, at most the Nyquist cap.
    """
    pts = _clean_closed(contour)
    most = highest_tested_order(pts)
    top = max(1, min(nyquist_max(len(pts)), most))
    spectrum, length = _truncations(pts, top, parameter)
    noise = measured.noise_mm
    cache: dict[int, float] = {}

    def residual(order: int) -> float:
        if order not in cache:
            kept = spectrum.copy()
            kept[:, order + 1 :] = 0.0
            xy = np.fft.irfft(kept, int(length), axis=1).T
            ang, rad = _frame_table(measured.frame, xy)
            # One turn from the first sample, closed: np.interp's period would sort again.
            at = ang[0] + np.mod(measured.angle_rad - ang[0], 2.0 * np.pi)
            fit = np.interp(at, np.append(ang, ang[0] + 2.0 * np.pi), np.append(rad, rad[0]))
            cache[order] = float(np.sqrt(np.mean((measured.radius_mm - fit) ** 2)))
        return cache[order]

    def gain(order: int, beyond: int) -> float:
        # What the orders up to ``beyond`` remove from the residual power, less what
        # following the noise removes (the residual's slope over the upper half of the
        # orders).
        half = max(1, top // 2)
        slope = max(0.0, (residual(half) ** 2 - residual(top) ** 2) / max(1, top - half))
        return residual(order) ** 2 - residual(beyond) ** 2 - slope * (beyond - order)

    def reached(order: int) -> bool:
        r = residual(order)
        if r <= (1.0 + margin) * noise:
            return True
        # Near the noise and no longer falling: the estimate of the noise, not the fit,
        # is what stands between them (it varies by a few % from section to section).
        if r > (1.0 + PLATEAU_MARGIN) * noise:
            return False
        return gain(order, top) <= PLATEAU_GAIN * noise**2

    order = _first_reached(reached, top)
    # Relief smaller than each point's noise hides in the residual but stands out of the
    # blend's spectrum as a narrow peak, since the blend averages the views.
    peaks = _standing_harmonics(pts, RELIEF_POWER_FACTOR, parameter, most)
    for peak in peaks[peaks > order][::-1]:  # within top: the spectral top is the lower
        # The measured points, not only the blend, must lose what the peak adds.
        if gain(order, int(peak)) > PLATEAU_GAIN * noise**2:
            return int(peak)
    return order


def _first_reached(reached: Callable[[int], bool], top: int) -> int:
    """Return the smallest order in 1..top that ``reached`` accepts (``top`` if none).

    ``reached`` is tried on a coarse grid of orders, then by bisection below the first
    grid order it accepts, so it is taken as monotone.
    """
    grid = sorted({n for n in _ORDER_GRID if n < top} | {top})
    previous = 0
    for n in grid:
        if reached(n):
            lo, hi = previous, n  # reached(hi); not reached(lo), or lo = 0
            while hi - lo > 1:
                mid = (lo + hi) // 2
                lo, hi = (lo, mid) if reached(mid) else (mid, hi)
            return max(1, hi)
        previous = n
    return top


PLATEAU_MARGIN = 0.25
"""Within this share above the noise, a residual that the higher orders no longer lower
by ``PLATEAU_GAIN`` noise^2 (beyond following noise) has reached the noise too."""

PLATEAU_GAIN = 0.1
"""Share of the noise power that the higher orders must still remove to be worth it."""

RELIEF_POWER_FACTOR = 2.0 * NOISE_POWER_FACTOR
"""A harmonic past the residual rule's order is kept when its power in the blended outline
exceeds the local noise floor this many times (and the measured points confirm it): twice
the noise rule's factor, above the 20-50 times that noise alone mostly reaches in a limb
outline's spectrum. Skin relief of 0.6-0.8 mm at 4-5 mm round a 270 mm outline stands
100-330 times above it at harmonics 52-55; four times the factor kept only the strongest."""

_ORDER_GRID = (1, 2, 3, 4, 5, 6, 8, 10, 12, 14, 16, 20, 24, 28, 32, 40, 48, 56, 64, 80, 96, 112,
               128, 160, 192, 224, 256, 320, 384)  # fmt: skip
"""Orders tried first, finest where outlines need few; the first reached is refined."""


def harmonics_power(
    contour: np.ndarray, fraction: float = POWER_FRACTION, parameter: str = "smoothed"
) -> int:
    """Return the fewest harmonics whose cumulative power reaches ``fraction`` of the total."""
    pts = _clean_closed(contour)
    cap = max(1, nyquist_max(len(pts)))
    cumulative = np.cumsum(_spectrum(pts, cap, parameter))
    return int(min(cap, np.searchsorted(cumulative, fraction * cumulative[-1]) + 1))


def choose_harmonics(
    contour: np.ndarray,
    rule: str = HARMONIC_RULES[0],
    parameter: str = PARAMETERS[0],
    measured: MeasuredPoints | None = None,
) -> int:
    """Return the EFD order for ``contour`` by one of ``HARMONIC_RULES`` (Nyquist-capped).

    Args:
        contour: (K, 2) closed contour in mm.
        rule: see ``HARMONIC_RULES``.
        parameter: the EFD parameterisation the spectrum rules measure (``PARAMETERS``).
        measured: the measured points and their noise, for the ``"residual"`` rule;
            without them (no two views overlap) it falls back to ``"noise"``.

    Raises:
        ValueError: an unknown rule.
    """
    if rule == "residual" and measured is not None:
        return harmonics_residual(contour, measured, parameter)
    if rule in ("noise", "residual"):
        return harmonics_noise(contour, parameter)
    if rule == "power":
        return harmonics_power(contour, parameter=parameter)
    if rule == "thesis":
        return harmonics_binned_thesis(contour)
    if rule == "nyquist":
        return max(1, nyquist_max(len(_clean_closed(contour))))
    raise ValueError(f"unknown harmonic rule {rule!r}; use one of {', '.join(HARMONIC_RULES)}")


def efd_area(efd: EllipticFourier) -> float:
    """Return the signed area enclosed by the series, positive when counter-clockwise."""
    a, b, c, d = efd.coeffs.T
    n = np.arange(1, efd.order + 1)
    return float(np.pi * np.sum(n * (a * d - b * c)))


def shift_start(efd: EllipticFourier, t0: float) -> EllipticFourier:
    """Return the same curve started at parameter ``t0`` (fraction of the period)."""
    a, b, c, d = efd.coeffs.T
    phi = 2.0 * np.pi * np.arange(1, efd.order + 1) * t0
    cos, sin = np.cos(phi), np.sin(phi)
    coeffs = np.stack([a * cos + b * sin, b * cos - a * sin, c * cos + d * sin, d * cos - c * sin])
    return EllipticFourier(efd.a0, efd.c0, coeffs.T.copy())


def align(efd: EllipticFourier, samples: int = 1024) -> EllipticFourier:
    """Return the curve running counter-clockwise and starting on the +x ray from its centre.

    Reversing is ``t -> -t`` (b and d change sign). The start is where the curve crosses
    the ray from (A0, C0) along +x, found on a dense sampling and refined linearly, so
    contours of neighbouring sections start in the same direction (thesis ref. [86]).
    """
    if efd_area(efd) < 0.0:
        coeffs = efd.coeffs * np.array([1.0, -1.0, 1.0, -1.0])
        efd = EllipticFourier(efd.a0, efd.c0, coeffs)
    pts = efd.evaluate(samples) - np.array([efd.a0, efd.c0])
    y, y_next = pts[:, 1], np.roll(pts[:, 1], -1)
    crossing = np.flatnonzero((y <= 0.0) & (y_next > 0.0) & (pts[:, 0] > 0.0))
    if len(crossing) == 0:
        return efd
    k = int(crossing[np.argmax(pts[crossing, 0])])
    frac = -y[k] / (y_next[k] - y[k])
    return shift_start(efd, (k + frac) / samples)


INTERPOLATIONS = ("linear", "pchip", "smooth")
"""How ``EfdStack`` interpolates coefficients along z; "smooth" is a cubic smoothing spline
whose weight is chosen by generalised cross-validation."""

CLINICAL_INTERPOLATION = "pchip"
"""How measurements interpolate the EFD coefficients between sections: PCHIP is
shape-preserving (no overshoot between sections, so never more girth than the sections
on either side show) and follows a rounded end, where straight lines between sections
cut the dome's corners: on a residual limb at limb scale, 10 mm pitch, the volume error
was -0.55 % with linear coefficients and -0.19 % with PCHIP (tests/benchmarks/bench_limb.py).
It is evaluated only inside the measured range (no extrapolation)."""

SMOOTH_MIN_SECTIONS = 5
"""Cross-validated smoothing needs at least this many sections; fewer are interpolated."""

RING_SAG_MM = 0.01
"""How far, on average round the outline, a contour mesh may fall inside the interpolated
surface between its rings.

A mesh is straight along z between rings, so where the interpolation curves (PCHIP or the
smoothing spline over a rounded end) it cuts inside the curve by the sagitta; the volume
it loses in a slab is about 2/3 of the sagitta times the outline's perimeter and the
slab's height, a share 4 sag / (3 r) of the slab for an outline of radius r: at 0.01 mm,
0.03 % for a 40 mm radius, within the 0.05 % the mesh must agree with the stack
(issue #13). On the simulated stump (``stump:scale=5``, 11 sections at 10 mm) the mesh
holds -0.014 % against the stack with 36 000 faces (0.02 mm: -0.024 %, 27 000 faces;
straight joins: -0.37 %, 11 000 faces)."""

MAX_RINGS_PER_SLAB = 16
"""Cap on the sub-slabs between two sections (a sagitta of 2.5 mm still meets RING_SAG_MM)."""

_SAG_PROBES = np.array([0.25, 0.5, 0.75])
"""Where in a slab the interpolated contour is compared with the straight join: a cubic's
departure from its chord is t (1 - t) (alpha + beta t), largest between the quarter points."""


@dataclass(frozen=True, eq=False)
class EfdStack:
    """Aligned EFD sections of one outline, interpolated along z (thesis ref. [86]).

    ``coeffs`` is (S, N, 4) with every section padded to the largest order; ``dc`` is
    (S, 2); heights ascend.
    """

    z_mm: np.ndarray
    dc: np.ndarray
    coeffs: np.ndarray
    kind: str = "linear"

    @classmethod
    def from_sections(
        cls, z_mm: list[float], efds: list[EllipticFourier], kind: str = "linear"
    ) -> EfdStack:
        """Align every section and stack the coefficients in ascending z."""
        if kind not in INTERPOLATIONS:
            raise ValueError(f"unknown interpolation {kind!r}; use {', '.join(INTERPOLATIONS)}")
        if not efds or len(efds) != len(z_mm):
            raise ValueError("give one height per EFD section, at least one section")
        order = np.argsort(z_mm, kind="stable")
        aligned = [align(efds[k]) for k in order]
        n = max(e.order for e in aligned)
        coeffs = np.zeros((len(aligned), n, 4))
        for s, e in enumerate(aligned):
            coeffs[s, : e.order] = e.coeffs
        dc = np.array([[e.a0, e.c0] for e in aligned])
        return cls(np.asarray(z_mm, dtype=float)[order], dc, coeffs, kind)

    def section(self, z_mm: float) -> EllipticFourier:
        """Return the EFD interpolated at height ``z_mm`` (clamped to the scanned range)."""
        return self.sections(np.array([z_mm]))[0]

    def sections(self, z_mm: np.ndarray) -> list[EllipticFourier]:
        """Return the EFDs interpolated at each of the heights ``z_mm`` (clamped to the
        scanned range), the interpolant built once for all of them."""
        z = np.clip(np.asarray(z_mm, dtype=float).reshape(-1), self.z_mm[0], self.z_mm[-1])
        flat = np.concatenate([self.dc, self.coeffs.reshape(len(self.z_mm), -1)], axis=1)
        smooth = self.kind == "smooth" and len(self.z_mm) >= SMOOTH_MIN_SECTIONS
        if len(self.z_mm) == 1:
            rows = np.repeat(flat[:1], len(z), axis=0)
        elif smooth:
            rows = make_smoothing_spline(self.z_mm, flat, axis=0)(z)
        elif self.kind == "pchip":
            rows = PchipInterpolator(self.z_mm, flat, axis=0)(z)
        else:  # linear, and "smooth" with too few sections to choose a smoothing weight
            k = np.clip(np.searchsorted(self.z_mm, z) - 1, 0, len(self.z_mm) - 2)
            w = ((z - self.z_mm[k]) / (self.z_mm[k + 1] - self.z_mm[k]))[:, None]
            rows = (1.0 - w) * flat[k] + w * flat[k + 1]
        return [
            EllipticFourier(float(row[0]), float(row[1]), row[2:].reshape(-1, 4).copy())
            for row in rows
        ]

    def sample(self, n_points: int, z_mm: np.ndarray | None = None) -> np.ndarray:
        """Return (len(z), n_points, 2) contours at the same parameter values.

        Args:
            n_points: samples per contour, starting on each contour's +x ray.
            z_mm: heights (default: the scanned sections' own heights).
        """
        heights = self.z_mm if z_mm is None else np.asarray(z_mm, dtype=float)
        if len(heights) == 0:
            return np.zeros((0, n_points, 2))
        return np.stack([e.evaluate(n_points) for e in self.sections(heights)])

    def ring_heights(
        self, sag_mm: float = RING_SAG_MM, probe_points: int = 64
    ) -> tuple[np.ndarray, np.ndarray]:
        """Return the heights of a contour mesh's rings that follow this interpolation.

        Each slab between sections gets ``n`` equal sub-slabs, enough that straight joins
        enclose the interpolated volume: the sagitta ``d`` is the interpolated contour's
        area less that of the straight join of the slab's sections, over its perimeter
        (the mean outward departure; probed at the quarter points, largest taken). It
        falls as ``d / n^2`` on ``n`` sub-slabs, so ``n = ceil(sqrt(d / sag_mm))`` (at
        most ``MAX_RINGS_PER_SLAB``). The mean, not the largest point's departure: noise
        in the higher harmonics makes PCHIP wander by a few hundredths of a mm about the
        straight join on a cylinder, which rings would only copy. Linear interpolation,
        and PCHIP where it is straight within ``sag_mm``, add no ring.

        Returns:
            (R,) ascending heights and an (R,) mask, True at the measured sections and
            False at rings the interpolation estimated.
        """
        z = self.z_mm
        if len(z) < 2 or self.kind == "linear":
            return z.copy(), np.ones(len(z), dtype=bool)
        lo, hi = z[:-1], z[1:]
        t = _SAG_PROBES[None, :, None, None]
        probe_z = lo[:, None] + _SAG_PROBES * (hi - lo)[:, None]
        ends = self.sample(probe_points)
        inner = self.sample(probe_points, probe_z.ravel())
        chord = ((1.0 - t) * ends[:-1, None] + t * ends[1:, None]).reshape(inner.shape)
        area_gap = np.abs(np.abs(signed_areas(inner)) - np.abs(signed_areas(chord)))
        sag = (area_gap / np.maximum(perimeters(chord), 1e-12)).reshape(probe_z.shape)
        parts = np.ceil(np.sqrt(sag.max(axis=1) / sag_mm))
        parts = np.clip(parts, 1, MAX_RINGS_PER_SLAB).astype(int)
        heights = np.concatenate(
            [a + (b - a) * np.arange(n) / n for a, b, n in zip(lo, hi, parts, strict=True)]
            + [z[-1:]]
        )
        measured = np.isin(np.arange(len(heights)), np.concatenate([[0], np.cumsum(parts)]))
        return heights, measured
