"""The stripe's centre line along its chains: where the device's points join up, and a fit.

The device finds each column's centre alone (thesis eq. 5.1); its error is mostly the
speckle's, which changes from column to column while the stripe itself bends slowly.
A local fit along the stripe therefore removes most of it. Both ends use the same
chain rule (:func:`chain_starts`): the device to drop chains too short to be a
stripe, the host to fit each chain on its own, so that a fit never reaches across an
occlusion, a jump to another surface or a gap.

The fit (:func:`refine_rows`) is a local quadratic over a window of neighbouring
points of the chain (Savitzky and Golay's smoother, here with the window cut at the
chain's ends and at left-out points), not a line: a line fit pulls a curved stripe
toward its centre of curvature, a quadratic has no such bias to first order. Every
point weighs the same whatever its brightness, so a brightness step along the stripe
(a crease, a change of colour) does not move the line. Points far off both a wide
first fit and the narrowest one (a speckle dropout, a reflection's run) are left out of
the second fit and replaced by it; a stripe's end that steepens faster than a parabola
follows (a surface turning away to its silhouette) stays near the narrow fit and is
kept. The window adapts: each point takes the widest of :data:`HALF_WIDTHS_PX` whose
parabola would bias a circle of the measured curvature by less than
:data:`MAX_FIT_BIAS_PX` or, on a noisy stripe, by less than half the noise left in that
window's own value (:data:`BIAS_PER_NOISE`: a bias well under the noise a window removes
costs less than the noise a narrower one keeps, so the window weighs the two instead of
holding the bias alone near zero), and whose value stays inside every narrower window's
confidence interval (Katkovnik's intersection of confidence intervals), so relief finer
than a window, a fold of skin, keeps the window that follows it.

One thing no fit along the stripe removes: each column's centre of gravity is itself
pulled toward the centre of curvature where the stripe is both curved and steep (the
column cuts the curved profile obliquely, and its far side reaches further out than
its near side). To second order the pull is ``1.5 y'' v sin^2(theta)`` rows, ``v``
being the variance of the profile the device weighed, across the stripe, and
``theta`` the stripe's slope angle; the fit measures ``y''`` and ``theta``, and the
device's run widths give ``v`` (:data:`PROFILE_VARIANCE_PER_WIDTH2`), so the host takes
the pull off (:func:`curve_pull`).

Speed: every window sum comes from running sums over all the points of every stripe at
once, so the cost per point does not grow with the window, and the host fits a whole
scan's stripes in one pass (:func:`refine_many`). The sums are of whole numbers (rows
in 1/65536 px about each chain's first row, columns about its first column) in 64-bit
integers, whose wrap-around keeps every window's moments exact.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np

from lamina_shared.types import Segment

MAX_COL_GAP = 1
"""A chain may skip this many columns (a speckle dropout) and stay one chain."""

DEFAULT_ROW_JUMP_PX = 4.0
"""The device's default chain rule (``ExtractSettings.max_row_jump_px``)."""

HALF_WIDTHS_PX = (3, 5, 8, 13, 21, 34)
"""The windows the adaptive fit chooses from (points either side), narrowest first."""

MAX_FIT_BIAS_PX = 0.004
"""The largest bias a parabola's fit of a circular stripe may have where it is used, on a
stripe whose centres scatter little (a noise-free render's keep this bound)."""

BIAS_PER_NOISE = 0.5
"""On a noisy stripe, the bias allowed instead, per standard deviation of the window's
fitted value (the stripe's measured scatter, not its floor): measured on the harsh
frames, 0.25-1 all gave 0.68-0.69x the Horus-style RMS against 0.80x with the bias
bound alone; noise-free arcs keep their bias (``bench_subpixel``)."""

PROFILE_VARIANCE_PER_WIDTH2 = 0.17
"""The variance across the stripe of the profile the device's default centre weighs
(its run and 3 pixels beyond either end, ``margin_px``), per square of the run's width
across the stripe: measured on Gaussian profiles of 1.5-8 px, sloped, curved, speckled
and saturated (0.13-0.22; flat tops 0.10-0.15)."""

CURVE_PULL = 1.5
"""The pull of a column's centre of gravity, in ``y'' v sin^2(theta)`` (see the module)."""

_PILOT = 3  # the window (index into HALF_WIDTHS_PX) of the first fit, which finds outliers
_TRUSTED_HALF_WIDTH = 13  # fits this wide and wider measure the stripe's bend reliably
_OUTLIER_SIGMAS = 3.5  # residuals beyond this many sigmas leave the second fit
_MIN_RESIDUAL_PX = 0.15  # never call a point an outlier for less than this
_MEAN_ABS_SIGMAS = math.sqrt(math.pi / 2)  # a Gaussian's sigma over its mean |deviation|
_MEDIAN_ABS_SIGMAS = 1.4826  # a Gaussian's sigma over its median |deviation|
_MIN_ROW_SIGMA_PX = 0.08  # the least row noise assumed: a cleaner stripe (a noise-free
# render) would otherwise keep every few-column wobble of its centre of gravity as relief
_ICI_SIGMAS = 2.5  # the half-width of each fit's confidence interval, in its sigmas
# (a stripe's speckle is correlated along it, so a stricter test of the fits' differences
# stops the window on noise: measured 0.82-0.97x Horus-style instead of 0.70-0.80x with
# the 0.004 px bias bound; with BIAS_PER_NOISE, 2.0 kept more of the relief bench's folds
# but gave 0.72x on the harsh frames, 2.5 gives 0.68x)
_ROW_UNITS = 65536  # rows are summed in these fractions of a pixel
_PILOT_ALONE_POINTS = 4096  # more points than this: the pilot's fit first, alone
_GROUP_POINTS = 32768  # points fitted together: their sums stay in the processor's cache


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


def one_chain(
    cols: np.ndarray, rows: np.ndarray, width: np.ndarray, max_row_jump_px: float
) -> bool:
    """Return True only if :func:`chain_starts` would return ``[0]`` (one chain).

    A cheaper test for the usual view, one stripe through every column: with no column
    skipped, if the largest step between neighbouring centres is within the reach of the
    narrowest run, no pair breaks. It rounds as :func:`chain_starts` does (float32), and
    the reach it tests is the least of the pairs' (rounding keeps the order), so True is
    exact; False says only that :func:`chain_starts` must decide (a gap, or a NaN row).

    Args:
        cols: the points' columns, strictly increasing (at least one point).
        rows: their centre rows.
        width: their run lengths in rows.
        max_row_jump_px: the largest gap between two runs of one chain.
    """
    if int(cols[-1]) - int(cols[0]) != cols.size - 1:
        return False  # a column skipped: the gap rule applies
    if cols.size == 1:
        return True
    step = np.subtract(rows[1:], rows[:-1], dtype=np.float32)
    twice_apart = 2 * max(float(step.max()), -float(step.min()))  # exact: float32 doubled
    least_reach = np.float32(2 * int(width.min())) + np.float32(2 * max_row_jump_px - 2)
    return twice_apart <= float(least_reach)


@cache
def _interior_moments(half_width: int) -> tuple[float, float]:
    """Return ``sum (d/h)**2`` and ``sum (d/h)**4`` over a full window of ``h`` either side."""
    d = np.arange(-half_width, half_width + 1) / half_width
    return float(np.sum(d**2)), float(np.sum(d**4))


@cache
def circle_bias_factor(half_width: int) -> float:
    """Return ``B`` such that the window's parabola misses a circle by ``B |y''|**3``.

    The local quadratic's value is a fixed filter of the rows inside a full window; it
    passes a parabola unchanged, and a circle's next term, ``y'''' x**4 / 24`` with
    ``y'''' = 3 y''**3``, by its fourth moment.
    """
    d = np.arange(-half_width, half_width + 1, dtype=np.float64)
    basis = np.stack([np.ones_like(d), d, d * d], axis=1)
    value_filter = np.linalg.pinv(basis)[0]
    return abs(float(value_filter @ d**4)) * 3.0 / 24.0


@dataclass(frozen=True)
class _Layout:
    """Every stripe's points one after the other, each chain on its own.

    ``x`` is each point's column less its chain's first column; ``first``/``last`` the
    index of its chain's first and last point; ``base_row`` its chain's first row;
    ``step`` is True where a point follows the previous one of its chain in the next
    column; ``before``/``after`` how many points of its chain precede and follow it.
    """

    x: np.ndarray
    first: np.ndarray
    last: np.ndarray
    base_row: np.ndarray
    rows: np.ndarray
    index: np.ndarray
    step: np.ndarray
    before: np.ndarray
    after: np.ndarray

    @classmethod
    def of(cls, cols: np.ndarray, rows: np.ndarray, starts: np.ndarray) -> _Layout:
        """Lay out points (grouped by chain, columns ascending within each) from chain starts."""
        n = cols.size
        length = np.diff(starts, append=n)
        first = np.repeat(starts, length)
        last = np.repeat(starts + length - 1, length)
        x = cols.astype(np.int64) - cols[first].astype(np.int64)
        index = np.arange(n)
        step = np.zeros(n, bool)
        step[1:] = np.diff(x) == 1
        step[starts] = False
        return cls(x, first, last, rows[first], rows, index, step, index - first, last - index)


class _Sums:
    """Running sums of ``used * x**k`` (k = 0..4) and ``used * y * x**k`` (k = 0..2).

    ``reach`` is how many points either side of each point the window may span and
    still be full: every point used, in its chain, in consecutive columns (-1 where
    the point itself is left out).
    """

    def __init__(self, layout: _Layout, used: np.ndarray) -> None:
        x = layout.x
        y = np.rint((layout.rows - layout.base_row) * _ROW_UNITS).astype(np.int64)
        u = used.astype(np.int64)
        powers = [u]
        for _ in range(4):
            powers.append(powers[-1] * x)
        weighted = [powers[k] * y for k in range(3)]
        # Wrap-around in int64 is harmless: window sums are differences, exact mod 2**64.
        self.u = [_running(p, 0) for p in powers]
        # The y sums with their first and last held over the widest reach either side, so
        # every point's full window is one slice less another.
        pad = max(HALF_WIDTHS_PX) + 1
        self.pad = pad
        self.padded_y = [_running(p, pad) for p in weighted]
        self.y = [p[pad : p.size - pad] for p in self.padded_y]
        index = layout.index
        # Runs of consecutive used points: a run starts where a point does not follow on.
        follows = layout.step.copy()
        follows[1:] &= used[1:] & used[:-1]
        begin = np.maximum.accumulate(np.where(follows, 0, index))
        end = np.minimum.accumulate(
            np.where(np.append(follows[1:], False), index.size, index)[::-1]
        )
        self.reach = np.where(used, np.minimum(index - begin, end[::-1] - index), -1)

    @staticmethod
    def window(prefix: list[np.ndarray], lo: np.ndarray, hi: np.ndarray) -> list[np.ndarray]:
        """Return each running sum's total over the points ``lo .. hi - 1``."""
        return [p[hi] - p[lo] for p in prefix]


def _running(values: np.ndarray, pad: int) -> np.ndarray:
    """Return the running sums of ``values`` from 0, the first and last held ``pad`` more places."""
    out = np.empty(values.size + 1 + 2 * pad, values.dtype)
    out[: pad + 1] = 0
    np.cumsum(values, out=out[pad + 1 : out.size - pad])
    out[out.size - pad :] = out[out.size - pad - 1]
    return out


def _central(raw: list[np.ndarray], xi: np.ndarray) -> list[np.ndarray]:
    """Return ``sum w (x - xi)**k`` from ``sum w x**k`` (k = 0..len-1), exactly in integers.

    The binomial expansion in passes of ``m_k += -xi m_(k-1)``, highest k first: pass j
    leaves ``m_k = sum_i C(j, i) (-xi)**i raw_(k-i)`` for every ``k >= j``.
    """
    out = [m.copy() for m in raw]
    step = np.empty_like(xi)
    for j in range(1, len(out)):
        for k in range(len(out) - 1, j - 1, -1):
            np.multiply(xi, out[k - 1], out=step)
            out[k] -= step
    return out


def _solve(s: list[np.ndarray], t: list[np.ndarray]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the coefficients ``a + b x + c x**2`` of the least-squares quadratic.

    ``s[k] = sum (x - xi)**k`` and ``t[k] = sum y (x - xi)**k``, x in units of the
    window's reach; where a window holds too few points for a parabola a line, then a
    mean, is fitted. By cofactors: for a few points, cheaper than a batched solver.
    """
    m00, m01, m02, m12, m22 = s[0], s[1], s[2], s[3], s[4]
    m11 = m02
    c00 = m11 * m22 - m12 * m12
    c01 = m02 * m12 - m01 * m22
    c02 = m01 * m12 - m02 * m11
    c11 = m00 * m22 - m02 * m02
    c12 = m01 * m02 - m00 * m12
    c22 = m00 * m11 - m01 * m01
    det = m00 * c00 + m01 * c01 + m02 * c02
    # Degenerate windows (one or two columns) by the moments' own scale.
    good = det > 1e-6 * m00 * m11 * m22
    safe = np.where(good, det, 1.0)
    a = (c00 * t[0] + c01 * t[1] + c02 * t[2]) / safe
    b = (c01 * t[0] + c11 * t[1] + c12 * t[2]) / safe
    c = (c02 * t[0] + c12 * t[1] + c22 * t[2]) / safe
    if not good.all():  # chain ends too short for a parabola: a line, or the mean
        line = c22 > 1e-6 * m00 * m11
        safe_line = np.where(line, c22, 1.0)
        line_a = (m11 * t[0] - m01 * t[1]) / safe_line
        line_b = (m00 * t[1] - m01 * t[0]) / safe_line
        mean = t[0] / np.maximum(m00, 1e-12)
        a = np.where(good, a, np.where(line, line_a, mean))
        b = np.where(good, b, np.where(line, line_b, 0.0))
        c = np.where(good, c, 0.0)
    return a, b, c


def _window_fits(
    layout: _Layout, sums: _Sums, half_widths: Sequence[int]
) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """Return, per half-width, the local quadratic's value (rows), slope and bend.

    Windows reach ``h`` points either side within the chain. Where a window is full
    (:attr:`_Sums.reach`) the fit is a fixed filter of three window sums, so every point
    is first fitted so; the others, near chain ends, skipped columns and left-out
    points, are then solved in full, every width's together.
    """
    if not half_widths:
        return []
    fits = []
    edges, reaches = [], []
    for width in half_widths:
        fits.append(_full_window_fit(layout, sums, width))
        edge = np.flatnonzero(sums.reach < width)
        edges.append(edge)
        reaches.append(np.full(edge.size, width))
    edge = np.concatenate(edges)
    if edge.size:
        solved = _solve_windows(layout, sums, edge, np.concatenate(reaches))
        at = np.cumsum([0, *(e.size for e in edges)])
        for k, (value, slope, bend) in enumerate(fits):
            part = slice(at[k], at[k + 1])
            value[edges[k]], slope[edges[k]], bend[edges[k]] = (a[part] for a in solved)
    return fits


def _full_window_fit(
    layout: _Layout, sums: _Sums, h: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return every point's fit as if its window of ``h`` either side were full."""
    n = layout.x.size
    if h < sums.pad:  # every window unclipped: slices of the held running sums
        low, high = sums.pad - h, sums.pad + h + 1
        t0, t1, t2 = (p[high : high + n] - p[low : low + n] for p in sums.padded_y)
    else:
        index = layout.index
        t0, t1, t2 = _Sums.window(sums.y, np.maximum(index - h, 0), np.minimum(index + h + 1, n))
    xi = layout.x
    t1 -= xi * t0  # about each point: sum y (x - xi), then sum y (x - xi)**2
    t2 -= xi * (t1 + (t1 + xi * t0))
    s2, s4 = _interior_moments(h)
    s0 = 2 * h + 1
    det = (s0 * s4 - s2 * s2) * _ROW_UNITS
    value = t0 * (s4 / det)
    value -= t2 * (s2 / (det * h * h))
    value += layout.base_row
    slope = t1 * (1.0 / (s2 * _ROW_UNITS * h * h))
    bend = t2 * (2.0 * s0 / (det * h**4))
    bend -= t0 * (2.0 * s2 / (det * h * h))
    return value, slope, bend


def _solve_windows(
    layout: _Layout, sums: _Sums, edge: np.ndarray, h: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the fit (value, slope, bend) of points ``edge``, each with its own reach ``h``."""
    lo = np.maximum(edge - h, layout.first[edge])
    hi = np.minimum(edge + h, layout.last[edge]) + 1
    xi = layout.x[edge]
    s = _central(_Sums.window(sums.u, lo, hi), xi)
    t = [m / _ROW_UNITS for m in _central(_Sums.window(sums.y, lo, hi), xi)]
    scale = h.astype(np.float64)
    power = [np.ones_like(scale), scale, scale * scale]
    power += [power[2] * scale, power[2] * power[2]]
    a, b, c = _solve([s[k] / power[k] for k in range(5)], [t[k] / power[k] for k in range(3)])
    return a + layout.base_row[edge], b / scale, 2.0 * c / power[2]


def _outliers_left_out(
    layout: _Layout, stripe: np.ndarray, stripes: int, fits: Sequence[np.ndarray]
) -> np.ndarray:
    """Return which points a second fit uses: all but those off every first fit.

    A point is off a fit when its residual exceeds :data:`_OUTLIER_SIGMAS` of that fit's
    scatter along its stripe. The pilot's wide window alone would also call off the
    genuine points where the stripe bends faster than a parabola follows (its steep
    ends at a grazing surface), and the second fit would then extrapolate across them;
    the narrowest window follows such a bend, while a lone point far off stays off it.
    """
    off = np.ones(layout.rows.size, bool)
    count = np.maximum(np.bincount(stripe, minlength=stripes), 1)
    for fitted in fits:
        residual = np.abs(layout.rows - fitted)
        mean = np.bincount(stripe, residual, stripes) / count
        limit = np.maximum(_OUTLIER_SIGMAS * _MEAN_ABS_SIGMAS * mean, _MIN_RESIDUAL_PX)
        off &= residual > limit[stripe]
    return ~off


def curve_pull(bend: np.ndarray, slope: np.ndarray, width: np.ndarray) -> np.ndarray:
    """Return how far each column's centre of gravity lies toward the centre of curvature.

    Args:
        bend: the stripe's second derivative ``y''`` (rows per column squared).
        slope: its slope ``dy/dx``.
        width: the run widths the device saw, in rows (along the column).

    Returns:
        The pull in rows, with the sign of ``bend`` (subtract it from the centre).
    """
    sin2 = slope * slope / (1.0 + slope * slope)
    across = np.asarray(width, np.float64) ** 2 * (1.0 - sin2)  # the width across, squared
    return CURVE_PULL * PROFILE_VARIANCE_PER_WIDTH2 * bend * across * sin2


def refine_many(
    stripes: Sequence[tuple[np.ndarray, np.ndarray, np.ndarray]],
    max_row_jump_px: float = DEFAULT_ROW_JUMP_PX,
    half_width_px: int | None = None,
    correct_pull: bool = True,
) -> list[np.ndarray]:
    """Return every stripe's centre rows fitted along its chains, many stripes at once.

    Without ``half_width_px`` each point's window adapts to the stripe: the widest of
    :data:`HALF_WIDTHS_PX` whose fit (and every narrower one's from the trusted width
    on) bends the stripe so little that a parabola's bias on a circle,
    ``circle_bias_factor(h) |y''|**3``, stays below :data:`MAX_FIT_BIAS_PX`: wide along
    straight stretches, where it removes most of the speckle, narrow on tight curves.

    Args:
        stripes: per stripe (one segment), its columns (strictly increasing), the
            device's centre rows and run widths (for the chain rule and the pull).
        max_row_jump_px: the device's chain rule (``ExtractSettings.max_row_jump_px``).
        half_width_px: a fixed window of that many points either side (0 returns the
            rows), or None to adapt it.
        correct_pull: take off the centre of gravity's pull on curves (:func:`curve_pull`).

    Returns:
        Per stripe, the fitted rows (float64), one per point; chains of one or two points
        keep their own mean or line.
    """
    stripes = list(stripes)
    if half_width_px == 0:
        return [np.asarray(rows, np.float64).copy() for _, rows, _ in stripes]
    levels = HALF_WIDTHS_PX if half_width_px is None else (int(half_width_px),)
    out: list[np.ndarray] = []
    group: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    points = 0
    # Groups of stripes small enough for the processor's cache, whole stripes each.
    for k, stripe in enumerate(stripes):
        group.append(stripe)
        points += len(stripe[0])
        if points >= _GROUP_POINTS or k == len(stripes) - 1:
            out += _refine_group(group, max_row_jump_px, levels, correct_pull)
            group, points = [], 0
    return out


def _refine_group(
    stripes: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    max_row_jump_px: float,
    levels: tuple[int, ...],
    correct_pull: bool,
) -> list[np.ndarray]:
    """Return :func:`refine_many` of a few stripes, laid out one after the other."""
    sizes = [len(cols) for cols, _, _ in stripes]
    if sum(sizes) == 0:
        return [np.zeros(0) for _ in stripes]
    cols = np.concatenate([np.asarray(c) for c, _, _ in stripes]).astype(np.int64)
    rows = np.concatenate([np.asarray(r, np.float64) for _, r, _ in stripes])
    width = np.concatenate([np.asarray(w) for _, _, w in stripes])
    offsets = np.cumsum([0, *sizes])
    # Chains of every stripe, and a break wherever a new stripe begins.
    starts = np.union1d(chain_starts(cols, rows, width, max_row_jump_px), offsets[:-1])
    layout = _Layout.of(cols, rows, starts)
    stripe = np.repeat(np.arange(len(stripes)), sizes)
    # The pilot's fit finds the points far off; every width is then fitted without
    # them. A few stripes seldom hold one: every width is fitted with the pilot at once,
    # and again only if one turns up. Many stripes nearly always hold a few.
    pilot = levels[min(_PILOT, len(levels) - 1)]
    every = _Sums(layout, np.ones(cols.size, bool))
    first = levels if cols.size <= _PILOT_ALONE_POINTS else tuple({levels[0], pilot})
    by_width = dict(zip(first, _window_fits(layout, every, first), strict=True))
    used = _outliers_left_out(
        layout, stripe, len(stripes), [by_width[pilot][0], by_width[levels[0]][0]]
    )
    if not used.all() or len(first) < len(levels):
        sums = every if used.all() else _Sums(layout, used)
        again = [h for h in levels if h not in by_width or sums is not every]
        by_width.update(zip(again, _window_fits(layout, sums, again), strict=True))
    best = np.zeros(0)
    slope = bend = None
    noise = _stripe_sigma(layout, stripe, len(stripes), by_width[levels[0]][0], levels[0])
    sigma = np.maximum(noise, _MIN_ROW_SIGMA_PX)
    # Narrowest first: a wider fit replaces a narrower one where it and every wider fit
    # before it bend little, and where it still agrees with every narrower one within
    # their noise (detail finer than the window, a skin fold, is not a circle's bend).
    # The narrowest fits' curvature is too noisy to veto; the pull is measured by the
    # trusted width's fit (straighter stripes hardly pull).
    fits = np.ones(cols.size, bool)
    agree = np.ones(cols.size, bool)
    lower, upper = np.full(cols.size, -np.inf), np.full(cols.size, np.inf)
    interval, bias_noise = _ICI_SIGMAS * sigma, BIAS_PER_NOISE * noise
    for level in levels:
        value, level_slope, level_bend = by_width[level]
        # Intersection of confidence intervals (Katkovnik's rule): a wider fit is taken
        # only while every narrower one's interval still meets its own.
        spread = np.sqrt(_value_variance(layout, level))
        reach = interval * spread
        np.maximum(lower, value - reach, out=lower)
        np.minimum(upper, value + reach, out=upper)
        agree &= lower <= upper
        # A bias under half the value's own noise costs less than the noise it removes.
        allowed = np.maximum(MAX_FIT_BIAS_PX, bias_noise * spread)
        passes = circle_bias_factor(level) * np.abs(level_bend) ** 3 <= allowed
        fits = (passes if level < _TRUSTED_HALF_WIDTH else fits & passes) & agree
        best = value if level == levels[0] else np.where(fits, value, best)
        if level == _TRUSTED_HALF_WIDTH or (slope is None and level == levels[-1]):
            slope, bend = level_slope, level_bend
    if correct_pull and slope is not None and bend is not None:
        best -= curve_pull(bend, slope, _local_mean(layout, width.astype(np.float64)))
    return np.split(best, offsets[1:-1])


def _value_variance(layout: _Layout, h: int) -> np.ndarray:
    """Return each point's fitted value's variance, in units of one row's, for reach ``h``.

    A full window's quadratic weighs its centre by ``s4 / (s0 s4 - s2**2)``, about
    ``2.25 / n`` for ``n`` points; a window cut at a chain end is given the same per
    point (it is somewhat noisier, so its interval is narrower than it should be: it
    widens the window less readily, never more).
    """
    s2, s4 = _interior_moments(h)
    full = 2 * h + 1
    centre = s4 / (full * s4 - s2 * s2)
    count = np.minimum(layout.before, h) + np.minimum(layout.after, h) + 1
    return (centre * full) / count


def _stripe_sigma(
    layout: _Layout, stripe: np.ndarray, stripes: int, fitted: np.ndarray, h: int
) -> np.ndarray:
    """Return each point's stripe's row noise (one point's sigma) from a narrow fit's residuals."""
    residual = np.abs(layout.rows - fitted)
    count = np.bincount(stripe, minlength=stripes)
    start = np.concatenate(([0], np.cumsum(count)[:-1]))
    # By stripe, each stripe's residuals ascending: one sort of the residuals lifted by
    # their stripe (each stripe's band above the one below) is several times faster than
    # a lexsort, and one call, which a loop of selections per stripe was not (it kept the
    # terminal UI's thread waiting 35-40 ms at a time). The medians are picked from the
    # residuals themselves.
    band = float(residual.max()) + 1.0 if residual.size else 1.0
    order = np.argsort(residual + stripe * band)
    middle = residual[order][np.minimum(start + count // 2, max(residual.size - 1, 0))]
    median = np.where(count > 0, middle, 0.0)
    # A residual keeps 1 - (the centre's weight) of the point's variance.
    s2, s4 = _interior_moments(h)
    keep = 1.0 - s4 / ((2 * h + 1) * s4 - s2 * s2)
    sigma = median * _MEDIAN_ABS_SIGMAS / math.sqrt(keep)
    return sigma[stripe]


def _local_mean(layout: _Layout, values: np.ndarray) -> np.ndarray:
    """Return each point's mean of ``values`` over its chain within the pilot's window."""
    h = HALF_WIDTHS_PX[_PILOT]
    lo = layout.index - np.minimum(layout.before, h)
    hi = layout.index + np.minimum(layout.after, h) + 1
    running = np.concatenate(([0.0], np.cumsum(values)))
    return (running[hi] - running[lo]) / (hi - lo)


def refine_rows(
    cols: np.ndarray,
    rows: np.ndarray,
    width: np.ndarray,
    max_row_jump_px: float = DEFAULT_ROW_JUMP_PX,
    half_width_px: int | None = None,
    correct_pull: bool = True,
) -> np.ndarray:
    """Return one stripe's centre rows fitted along its chains (:func:`refine_many`).

    Args:
        cols: the points' columns, strictly increasing (one segment).
        rows: the device's centre rows.
        width: the run lengths the device saw.
        max_row_jump_px: the device's chain rule.
        half_width_px: a fixed window (0 returns ``rows``), or None to adapt it.
        correct_pull: take off the centre of gravity's pull on curves.

    Returns:
        The fitted rows (float64), one per point.
    """
    return refine_many([(cols, rows, width)], max_row_jump_px, half_width_px, correct_pull)[0]


def refined_rows(segments: Sequence[Segment]) -> list[np.ndarray]:
    """Return every segment's rows fitted along its chains, in the segment's own order.

    The host's half of the stripe extraction: the device sends each column's centre,
    this fits them along the stripe (:func:`refine_many`, adaptive window) with the
    device's default chain rule, all segments at once. A segment without one point
    per column keeps its rows.
    """
    out = [np.asarray(segment.rows, np.float64).copy() for segment in segments]
    stripes, fitted_to = [], []
    for k, segment in enumerate(segments):
        if len(segment) < 2:
            continue
        order: np.ndarray | slice = slice(None)  # the device lists points by column
        if np.any(np.diff(segment.cols.astype(np.int64)) <= 0):
            order = np.argsort(segment.cols, kind="stable")
            if np.any(np.diff(segment.cols[order].astype(np.int64)) <= 0):
                continue  # not one point per column: left as it is
        stripes.append((segment.cols[order], segment.rows[order], segment.width[order]))
        fitted_to.append((k, order))
    for (k, order), rows in zip(fitted_to, refine_many(stripes), strict=True):
        out[k][order] = rows
    return out


def refined_segments(segments: Sequence[Segment]) -> list[Segment]:
    """Return the segments with their rows fitted along their chains (:func:`refined_rows`)."""
    return [
        dataclasses.replace(segment, rows=rows.astype(np.float32))
        for segment, rows in zip(segments, refined_rows(segments), strict=True)
    ]


def refined_uv(segment: Segment) -> np.ndarray:
    """Return one segment's (N, 2) image points with the rows fitted (:func:`refined_rows`)."""
    uv = segment.uv
    uv[:, 1] = refined_rows([segment])[0]
    return uv
