"""The stripe's centre line along its chains: where the device's points join up, and a fit.

The device finds each column's centre alone (thesis eq. 5.1); its error is mostly the
speckle's, which changes from column to column while the stripe itself bends slowly.
A local fit along the stripe therefore removes most of it. Both ends use the same
chain rule (:func:`chain_starts`): the device to drop chains too short to be a
stripe, the host to fit each chain on its own, so that a fit never reaches across an
occlusion, a jump to another surface or a gap.

The fit (:func:`refine_rows`) is a local quadratic with Gaussian weights, not a line:
a line fit pulls a curved stripe toward its centre of curvature by about
``curvature x sigma**2 / 2`` (0.1 px on an arc of 20 px with sigma 2), a quadratic has
no such bias. Every point weighs the same whatever its brightness, so a brightness
step along the stripe (a crease, a change of colour) does not move the line. Points
far off the first fit (a speckle dropout, a reflection's run) are left out of a
second one and replaced by it.
"""

from __future__ import annotations

import math
from functools import cache

import numpy as np

from lamina_shared.types import Segment

MAX_COL_GAP = 1
"""A chain may skip this many columns (a speckle dropout) and stay one chain."""

SIGMA_LEVELS_PX = (2.5, 3.5, 5.0, 7.0, 10.0, 14.0)
"""The reaches the adaptive fit chooses from (Gaussian sigma, columns), narrowest first."""

MAX_FIT_BIAS_PX = 0.004
"""The largest bias a parabola's fit of a circular stripe may have where it is used."""

_TRUSTED_CURVATURE_PX = 5.0  # fits this wide and wider measure the stripe's bend reliably
_OUTLIER_SIGMAS = 3.5  # residuals beyond this many robust sigmas leave the second fit
_MIN_RESIDUAL_PX = 0.15  # never call a point an outlier for less than this
_MAD_SIGMAS = 1.4826  # a Gaussian's sigma over its median absolute deviation


def chain_starts(
    cols: np.ndarray, rows: np.ndarray, width: np.ndarray, max_row_jump_px: float
) -> np.ndarray:
    """Return the index of each chain's first point (0 first).

    Neighbouring points (``MAX_COL_GAP`` columns may be skipped) whose runs come within
    ``max_row_jump_px`` rows of each other share a chain; a run of ``w`` rows spans its
    centre +- (w - 1) / 2, so a steep stripe, whose runs are long, stays one chain.

    Args:
        cols: the points' columns, strictly increasing (at least one point).
        rows: their centre rows.
        width: their run lengths in rows.
        max_row_jump_px: the largest gap between two runs of one chain.

    Returns:
        The chain starts, ascending, beginning with 0.
    """
    twice_apart = np.subtract(rows[1:], rows[:-1], dtype=np.float32)
    np.abs(twice_apart, out=twice_apart)
    twice_apart += twice_apart
    twice_reach = np.add(width[1:], width[:-1], dtype=np.float32)
    twice_reach += 2 * max_row_jump_px - 2
    broken = twice_apart > twice_reach
    if int(cols[-1]) - int(cols[0]) != cols.size - 1:  # not every column: look for gaps
        broken |= (cols[1:] - cols[:-1]) > 1 + MAX_COL_GAP
    starts = np.flatnonzero(broken)
    starts += 1
    return np.concatenate(([0], starts))


@cache
def _kernels(sigma_px: float) -> np.ndarray:
    """Return the Gaussian weights times ``(dx / sigma)**k``, k = 0..4, reversed (5, K)."""
    radius = math.ceil(3 * sigma_px)
    dx = np.arange(-radius, radius + 1, dtype=np.float64) / sigma_px
    w = np.exp(-0.5 * dx * dx)
    # np.convolve flips its kernel: reversing makes it a correlation, sum_d lane[i + d] k[d].
    kernels = np.stack([w * dx**k for k in range(5)])[:, ::-1].copy()
    kernels.flags.writeable = False
    return kernels


def _lanes(cols: np.ndarray, starts: np.ndarray, radius: int) -> np.ndarray:
    """Return each point's place on one line where chains sit beyond each other's reach."""
    chain = np.zeros(cols.size, np.intp)
    chain[starts[1:]] = 1
    return cols.astype(np.intp) - int(cols[0]) + np.cumsum(chain) * (radius + 1) + radius


def _quadratic_fit(
    place: np.ndarray, rows: np.ndarray, used: np.ndarray, sigma_px: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the local quadratic fit's value, slope and second derivative at each point.

    Weighted least squares over the used points within 3 sigma on the same chain;
    where a chain has too few points for a parabola a line, then a mean, is fitted.
    """
    kernels = _kernels(sigma_px)
    radius = kernels.shape[1] // 2
    size = int(place[-1]) + radius + 1
    weight, value = np.zeros(size), np.zeros(size)
    weight[place] = used
    value[place] = np.where(used, rows, 0.0)
    s = [np.convolve(weight, k, "same")[place] for k in kernels]
    t = [np.convolve(value, k, "same")[place] for k in kernels[:3]]
    # Normal equations of y = a + b x + c x^2 (x in sigmas): M [a b c] = t.
    m00, m01, m02, m11, m12, m22 = s[0], s[1], s[2], s[2], s[3], s[4]
    c00 = m11 * m22 - m12 * m12
    c01 = m02 * m12 - m01 * m22
    c02 = m01 * m12 - m02 * m11
    c11 = m00 * m22 - m02 * m02
    c12 = m01 * m02 - m00 * m12
    c22 = m00 * m11 - m01 * m01
    det = m00 * c00 + m01 * c01 + m02 * c02
    good = det > 1e-3 * np.maximum(s[0], 1e-12) ** 3
    safe = np.where(good, det, 1.0)
    a = (c00 * t[0] + c01 * t[1] + c02 * t[2]) / safe
    b = (c01 * t[0] + c11 * t[1] + c12 * t[2]) / safe
    c = (c02 * t[0] + c12 * t[1] + c22 * t[2]) / safe
    if not good.all():  # chain ends too short for a parabola: a line, or the mean
        line_det = m00 * m11 - m01 * m01
        line = line_det > 1e-3 * np.maximum(s[0], 1e-12) ** 2
        safe_line = np.where(line, line_det, 1.0)
        line_a = (m11 * t[0] - m01 * t[1]) / safe_line
        line_b = (m00 * t[1] - m01 * t[0]) / safe_line
        mean = t[0] / np.maximum(s[0], 1e-12)
        a = np.where(good, a, np.where(line, line_a, mean))
        b = np.where(good, b, np.where(line, line_b, 0.0))
        c = np.where(good, c, 0.0)
    return a, b / sigma_px, 2.0 * c / (sigma_px * sigma_px)


def refine_rows(
    cols: np.ndarray,
    rows: np.ndarray,
    width: np.ndarray,
    max_row_jump_px: float = 4.0,
    sigma_px: float | None = None,
) -> np.ndarray:
    """Return the centre rows replaced by a local quadratic fit along each chain.

    Without ``sigma_px`` the fit's reach adapts to the stripe: each point takes the
    widest of :data:`SIGMA_LEVELS_PX` whose fit (and every narrower one) bends the
    stripe so little that a parabola's residual bias, ``3 sigma**4 |y''|**3 / 8`` on a
    circle, stays below :data:`MAX_FIT_BIAS_PX`: wide along straight stretches, where
    it removes most of the speckle, narrow on tight curves.

    Args:
        cols: the points' columns, strictly increasing (one segment).
        rows: the device's centre rows.
        width: the run lengths the device saw (for the chain rule).
        max_row_jump_px: the device's chain rule (``ExtractSettings.max_row_jump_px``).
        sigma_px: a fixed Gaussian sigma of the fit in columns (0 returns ``rows``),
            or None to adapt it.

    Returns:
        The fitted rows (float64), one per point; chains of one or two points keep a
        line's or their own mean.
    """
    rows = np.asarray(rows, np.float64)
    if cols.size < 2 or (sigma_px is not None and sigma_px <= 0):
        return rows.copy()
    starts = chain_starts(cols, rows, width, max_row_jump_px)
    levels = SIGMA_LEVELS_PX if sigma_px is None else (float(sigma_px),)
    reach = _kernels(max(levels)).shape[1] // 2
    place = _lanes(cols, starts, reach)
    pilot = levels[len(levels) // 2]
    fitted, _, _ = _quadratic_fit(place, rows, np.ones(cols.size, bool), pilot)
    residual = np.abs(rows - fitted)
    limit = max(_OUTLIER_SIGMAS * _MAD_SIGMAS * float(np.median(residual)), _MIN_RESIDUAL_PX)
    used = residual <= limit
    best = rows
    # Narrowest first: a wider fit replaces a narrower one where it and every wider fit
    # before it bend little. The narrowest fits' curvature is too noisy to veto.
    fits = np.ones(cols.size, bool)
    for level in levels:
        value, _, bend = _quadratic_fit(place, rows, used, level)
        passes = 3.0 * level**4 * np.abs(bend) ** 3 / 8.0 <= MAX_FIT_BIAS_PX
        fits = passes if level <= _TRUSTED_CURVATURE_PX else fits & passes
        best = value if level == levels[0] else np.where(fits, value, best)
    return best


def refined_uv(segment: Segment) -> np.ndarray:
    """Return a segment's (N, 2) image points with the rows fitted along its chains.

    The host's half of the stripe extraction: the device sends each column's centre,
    this fits them along the stripe (:func:`refine_rows`, adaptive reach) with the
    device's default chain rule. Points come back in the segment's own order.
    """
    uv = segment.uv
    if len(segment) < 2:
        return uv
    order = np.argsort(segment.cols, kind="stable")
    cols = segment.cols[order]
    if np.any(np.diff(cols.astype(np.int64)) <= 0):  # not one point per column: leave it
        return uv
    uv[order, 1] = refine_rows(cols, segment.rows[order], segment.width[order])
    return uv
