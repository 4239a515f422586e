"""Stripe extraction on the device: difference image, threshold, per-column stripe centre.

The default is the thesis's method (section 5.2): a global Otsu threshold and, per image
column, the intensity-weighted centre of the pixels above it (eq. 5.1, power factor
``p`` = 1). Two things go beyond it: the laser-off frame is subtracted first (the
thesis's own recommendation, 9.2), and only one above-threshold run per column is used,
so a stray reflection elsewhere in the column cannot drag the centre away. By default
that is the run holding the column's peak; ``run_choice="continuity"`` keeps instead
the run that best continues the stripe from the neighbouring columns.

Selectable as well: background removal by morphological opening (thesis 5.2.1), a fixed
threshold, weights above the threshold, and the thesis's first method, Otsu
binarisation then line thinning with whole-pixel output (5.2.3, figs. 5.4-5.6), kept so
that its bias can be measured.

Speed: the work is one saturating subtraction, one histogram (Otsu), one comparison and
then arithmetic on the few above-threshold pixels only (a few per column), never on
full-frame int32 or float temporaries.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cache

import cv2
import numpy as np

from lamina_shared.types import Segment

METHODS = ("cog", "thinning")
RUN_CHOICES = ("peak", "continuity")

FLAG_SEVERAL_RUNS = 1
"""Point flag: the column held more than one bright run (a reflection, a second surface)."""
FLAG_NOT_PEAK_RUN = 2
"""Point flag: the run kept is not the one holding the column's peak (continuity choice)."""
FLAG_SATURATED = 4
"""Point flag: the run's peak is at full scale, so its centre may be biased."""

_FULL_SCALE = 255


@dataclass(frozen=True)
class ExtractSettings:
    """How stripes are found.

    ``threshold`` is ``None`` for Otsu's method or a fixed difference level (8-bit
    units); ``min_peak`` rejects columns whose brightest difference is below it (no
    stripe). ``subtract_threshold`` weights pixels by how far they rise above the
    threshold instead of by their intensity (eq. 5.1): the run's edge pixels then weigh
    almost nothing, so the centre no longer jumps as they enter or leave the run.
    ``method`` is ``"cog"`` (centre of gravity, eq. 5.1) or ``"thinning"`` (Otsu
    binarisation and line thinning, whole pixels). ``run_choice`` picks the run kept in
    a column holding several: ``"peak"`` (the brightest) or ``"continuity"`` (the one
    nearest the stripe through the neighbouring columns). ``background_opening_px`` > 0
    removes what survives a vertical opening of that many rows (thesis 5.2.1; the
    stripe, thinner than the element, is kept, broad background is removed).
    ``otsu_row_step`` > 1 computes Otsu's histogram from every n-th row only: faster, but
    the threshold is then an estimate of the thesis's whole-frame one.
    """

    threshold: float | None = None
    power: float = 1.0
    min_peak: float = 12.0
    subtract_threshold: bool = False
    method: str = "cog"
    run_choice: str = "peak"
    background_opening_px: int = 0
    otsu_row_step: int = 1

    def __post_init__(self) -> None:
        problems = settings_problems(self)
        if problems:
            raise ValueError("bad extraction settings: " + "; ".join(problems))


def settings_problems(settings: ExtractSettings) -> list[str]:
    """Return every problem with ``settings`` (empty when they are usable)."""
    problems = []
    if settings.threshold is not None and not 0 <= settings.threshold < _FULL_SCALE:
        problems.append(f"threshold {settings.threshold} is not in 0..254 (or None for Otsu)")
    if not 0 < settings.power <= 8:
        problems.append(f"power {settings.power} is not in (0, 8]")
    if not 1 <= settings.min_peak <= _FULL_SCALE:
        problems.append(f"min_peak {settings.min_peak} is not in 1..255")
    if settings.method not in METHODS:
        problems.append(f"method {settings.method!r} is not one of {', '.join(METHODS)}")
    if settings.run_choice not in RUN_CHOICES:
        problems.append(
            f"run_choice {settings.run_choice!r} is not one of {', '.join(RUN_CHOICES)}"
        )
    if settings.otsu_row_step < 1:
        problems.append(f"otsu_row_step {settings.otsu_row_step} is below 1")
    if settings.background_opening_px < 0:
        problems.append(f"background_opening_px {settings.background_opening_px} is negative")
    return problems


def _no_flags() -> np.ndarray:
    return np.zeros(0, np.uint8)


@dataclass(frozen=True)
class StripePoints:
    """Per-column stripe centres of one view, before they are labelled as a segment.

    ``flags`` (uint8 per point, ``FLAG_*`` bits) stays on the device: the wire segment
    carries only ``cols``, ``rows``, ``peak`` and ``width``. Left out, it is all zeros.
    """

    cols: np.ndarray
    rows: np.ndarray
    peak: np.ndarray
    width: np.ndarray
    flags: np.ndarray = field(default_factory=_no_flags)

    def __post_init__(self) -> None:
        if self.flags.size == 0 and self.cols.size:
            object.__setattr__(self, "flags", np.zeros(self.cols.size, np.uint8))
        sizes = {a.size for a in (self.cols, self.rows, self.peak, self.width, self.flags)}
        if len(sizes) > 1:
            raise ValueError("stripe point arrays differ in length")


def difference(on: np.ndarray, off: np.ndarray | None) -> np.ndarray:
    """Return laser-on minus laser-off, clipped at zero, in the frames' own dtype.

    Args:
        on: the laser-on frame (H, W), uint8 or uint16.
        off: the laser-off frame of the same shape and dtype, or None (laser-on alone).

    Returns:
        A new (H, W) array; the saturating subtraction never wraps around.
    """
    if on.ndim != 2 or on.dtype not in (np.uint8, np.uint16):
        raise ValueError(f"frames must be 2-D uint8 or uint16, got {on.ndim}-D {on.dtype}")
    if off is None:
        return on.copy()
    if off.shape != on.shape or off.dtype != on.dtype:
        raise ValueError(
            f"laser-off frame is {off.shape} {off.dtype}, laser-on is {on.shape} {on.dtype}"
        )
    return cv2.subtract(on, off)


def _to_8bit(diff: np.ndarray) -> np.ndarray:
    """Return ``diff`` in 8-bit units, so thresholds and peaks mean the same for any depth."""
    if diff.dtype == np.uint8:
        return diff
    return (diff >> 8).astype(np.uint8)


def remove_background(diff8: np.ndarray, opening_px: int) -> np.ndarray:
    """Return ``diff8`` minus its morphological opening by a vertical line (thesis 5.2.1).

    The thesis used a rectangular structuring element; a column of ``opening_px`` rows is
    the narrowest rectangle that removes a horizontal stripe thinner than it, while
    anything broader (uneven ambient light, glare) survives the opening and is removed.
    """
    kernel = cv2.getStructuringElement(cv2.MORPH_RECT, (1, opening_px))
    return cv2.morphologyEx(diff8, cv2.MORPH_TOPHAT, kernel)


def _histogram(image: np.ndarray) -> np.ndarray:
    """Return the histogram of a non-negative integer image as float64 counts."""
    if image.dtype == np.uint8 and image.size < 1 << 24:
        # cv2 counts 8-bit images several times faster than bincount; its float32 counts
        # are exact below 2**24 pixels.
        return cv2.calcHist([image], [0], None, [256], [0, 256]).ravel().astype(np.float64)
    return np.bincount(image.ravel()).astype(np.float64)


def otsu_threshold(image: np.ndarray) -> float:
    """Return Otsu's threshold of a non-negative integer image (between-class variance max).

    Pixels strictly above the returned level form the bright class; ties go to the
    lowest level.
    """
    hist = _histogram(image)
    levels = np.arange(hist.size, dtype=np.float64)
    weight0 = np.cumsum(hist)
    sum0 = np.cumsum(hist * levels)
    total, grand = weight0[-1], sum0[-1]
    weight1 = total - weight0
    with np.errstate(divide="ignore", invalid="ignore"):
        mean0 = sum0 / weight0
        mean1 = (grand - sum0) / weight1
        between = weight0 * weight1 * (mean0 - mean1) ** 2
    between[~np.isfinite(between)] = -1.0
    return float(np.argmax(between))


@dataclass(frozen=True)
class _Runs:
    """Every above-threshold run of an image, in column-then-row order.

    ``point_*`` describe the above-threshold pixels; ``start`` indexes the first pixel of
    each run and ``col_start`` the first run of each column.
    """

    point_rows: np.ndarray
    point_keys: np.ndarray
    start: np.ndarray
    col: np.ndarray
    row0: np.ndarray
    length: np.ndarray
    peak: np.ndarray
    weight: np.ndarray
    moment: np.ndarray
    col_start: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        """Return each run's weighted centre row (eq. 5.1), float64."""
        with np.errstate(divide="ignore", invalid="ignore"):
            return self.moment / self.weight

    @property
    def runs_per_col(self) -> np.ndarray:
        """Return how many runs each column holding one has."""
        return np.diff(np.append(self.col_start, self.col.size))


def _find_runs(
    image: np.ndarray, threshold: float, power: float, subtract_threshold: bool
) -> _Runs:
    """Return the above-threshold runs of ``image`` with their eq. 5.1 sums."""
    height, width = image.shape
    flat = _above(image, threshold)
    values = image.ravel()[flat]
    rows, cols = np.divmod(flat, width)
    # Column-major order: a stable sort on columns keeps each column's rows ascending.
    order = np.argsort(cols.astype(np.uint16 if width <= 65535 else np.int64), kind="stable")
    rows, cols, values = rows[order], cols[order], values[order]
    # Keys jump by 2 between columns, so a run never continues into the next column.
    keys = cols * (height + 1) + rows
    start = np.flatnonzero(np.diff(keys, prepend=-2) != 1)
    weights = _weights(values, threshold, power, subtract_threshold)
    run_col = cols[start]
    return _Runs(
        point_rows=rows,
        point_keys=keys,
        start=start,
        col=run_col,
        row0=rows[start],
        length=np.diff(np.append(start, keys.size)),
        peak=np.maximum.reduceat(values, start) if start.size else values[:0],
        weight=np.add.reduceat(weights, start) if start.size else weights[:0],
        moment=np.add.reduceat(weights * rows, start) if start.size else weights[:0],
        col_start=np.flatnonzero(np.diff(run_col, prepend=-1) != 0),
    )


def _above(image: np.ndarray, threshold: float) -> np.ndarray:
    """Return the flat indices (row-major) of the pixels strictly above ``threshold``."""
    # For integers "> t" is "> floor(t)"; an integer level also keeps the comparison in
    # the image's own dtype instead of a float64 copy of the frame.
    level = math.floor(threshold)
    rows_hit = np.flatnonzero(image.max(axis=1) > level)
    if rows_hit.size == 0:
        return np.zeros(0, np.intp)
    # Only the band of rows the stripe crosses is scanned pixel by pixel.
    top, bottom = int(rows_hit[0]), int(rows_hit[-1]) + 1
    return np.flatnonzero(image[top:bottom] > level) + top * image.shape[1]


def _weights(
    values: np.ndarray, threshold: float, power: float, subtract_threshold: bool
) -> np.ndarray:
    """Return the eq. 5.1 weight ``I**p`` (or ``(I - threshold)**p``) of each pixel."""
    if subtract_threshold:
        weights = values - threshold
    elif power == 1.0:
        return values.astype(np.int64)  # exact integer sums
    else:
        weights = values
    weights = weights.astype(np.float64)
    if power != 1.0:
        weights **= power
    return weights


def _first_per_column(runs: _Runs, candidate: np.ndarray) -> np.ndarray:
    """Return, per column, the index of its first run where ``candidate`` holds."""
    index = np.where(candidate, np.arange(candidate.size), candidate.size)
    return np.minimum.reduceat(index, runs.col_start)


def _peak_runs(runs: _Runs) -> np.ndarray:
    """Return per column the run holding the column's peak (the topmost on a tie)."""
    col_peak = np.maximum.reduceat(runs.peak, runs.col_start)
    return _first_per_column(runs, runs.peak == np.repeat(col_peak, runs.runs_per_col))


def _continuity_runs(runs: _Runs, peak_choice: np.ndarray) -> np.ndarray:
    """Return per column the run nearest the stripe as its single-run neighbours trace it.

    Columns with one run are the anchors; in a column with several, the expected row is
    interpolated between the nearest anchors either side and the nearest run is kept.
    """
    several = runs.runs_per_col > 1
    if not several.any() or several.all():
        return peak_choice
    centre = runs.centre
    anchors = runs.col_start[~several]
    expected = np.interp(runs.col, runs.col[anchors], centre[anchors])
    distance = np.abs(centre - expected)
    col_best = np.minimum.reduceat(distance, runs.col_start)
    nearest = _first_per_column(runs, distance == np.repeat(col_best, runs.runs_per_col))
    return np.where(several, nearest, peak_choice)


def _choose_runs(runs: _Runs, run_choice: str) -> tuple[np.ndarray, np.ndarray]:
    """Return per column the run kept and its flags."""
    chosen = _peak_runs(runs)
    if run_choice == "continuity":
        peak_choice, chosen = chosen, _continuity_runs(runs, chosen)
        flags = np.where(chosen != peak_choice, FLAG_NOT_PEAK_RUN, 0).astype(np.uint8)
    else:
        flags = np.zeros(chosen.size, np.uint8)
    flags[runs.runs_per_col > 1] |= FLAG_SEVERAL_RUNS
    flags[runs.peak[chosen] >= _FULL_SCALE] |= FLAG_SATURATED
    return chosen, flags


def _points(runs: _Runs, chosen: np.ndarray, rows: np.ndarray, flags: np.ndarray) -> StripePoints:
    """Return the stripe points of the chosen runs at the given centre rows."""
    return StripePoints(
        runs.col[chosen].astype(np.uint16),
        rows.astype(np.float32),
        np.minimum(runs.peak[chosen], _FULL_SCALE).astype(np.uint8),
        np.minimum(runs.length[chosen], _FULL_SCALE).astype(np.uint8),
        flags,
    )


def centre_of_gravity(
    diff: np.ndarray,
    threshold: float,
    power: float = 1.0,
    subtract_threshold: bool = False,
    run_choice: str = "peak",
) -> StripePoints:
    """Return the sub-pixel stripe centre of every column that has one (thesis eq. 5.1).

    Args:
        diff: non-negative integer difference image (H, W).
        threshold: pixels strictly above it belong to the stripe.
        power: the power factor ``p`` applied to intensities.
        subtract_threshold: weight by intensity minus threshold rather than intensity.
        run_choice: ``"peak"`` or ``"continuity"`` when a column holds several runs.

    Returns:
        The columns with a stripe, their centre rows (pixel centres at integers), the
        run's peak intensity and its width in pixels, and the ``FLAG_*`` bits.
    """
    runs = _find_runs(diff, threshold, power, subtract_threshold)
    if runs.start.size == 0:
        return _empty_points()
    chosen, flags = _choose_runs(runs, run_choice)
    keep = runs.weight[chosen] > 0
    chosen, flags = chosen[keep], flags[keep]
    return _points(runs, chosen, runs.centre[chosen], flags)


def _empty_points() -> StripePoints:
    """Return a view without stripe points."""
    return StripePoints(
        np.zeros(0, np.uint16), np.zeros(0, np.float32), np.zeros(0, np.uint8),
        np.zeros(0, np.uint8), np.zeros(0, np.uint8),
    )  # fmt: skip


@cache
def _thinning_luts() -> tuple[np.ndarray, np.ndarray]:
    """Return the deletion tables of the two sub-iterations of Guo and Hall's thinning.

    Guo and Hall's parallel thinning as given in Lam, Lee and Suen's survey (1992,
    p. 879), the one Matlab's iterative thinning implements (the thesis's [50], [51]).
    The neighbour code has bit k set when neighbour x(k+1) is set, x1 = east, then
    counter-clockwise.
    """
    code = np.arange(256)

    def x(i: int) -> np.ndarray:
        """Return neighbour x_i (1-based, x9 = x1) for every code."""
        return (code >> ((i - 1) % 8)) & 1

    crossings = sum((1 - x(2 * i - 1)) & (x(2 * i) | x(2 * i + 1)) for i in range(1, 5))
    n1 = sum(x(2 * k - 1) | x(2 * k) for k in range(1, 5))
    n2 = sum(x(2 * k) | x(2 * k + 1) for k in range(1, 5))
    fewest = np.minimum(n1, n2)
    base = (crossings == 1) & (fewest >= 2) & (fewest <= 3)
    first = base & (((x(2) | x(3) | (1 - x(8))) & x(1)) == 0)
    second = base & (((x(6) | x(7) | (1 - x(4))) & x(5)) == 0)
    return first, second


def thin(mask: np.ndarray) -> np.ndarray:
    """Return the 8-connected skeleton of a binary image (Guo-Hall thinning, to stability).

    Args:
        mask: (H, W) boolean image.

    Returns:
        A boolean image of the same shape holding the skeleton, one pixel thick.
    """
    padded = np.zeros((mask.shape[0] + 2, mask.shape[1] + 2), np.uint8)
    padded[1:-1, 1:-1] = mask
    inner = padded[1:-1, 1:-1]
    # Neighbour x(k+1) seen from the centre; x1 = east, counter-clockwise (rows grow down).
    offsets = ((0, 1), (-1, 1), (-1, 0), (-1, -1), (0, -1), (1, -1), (1, 0), (1, 1))
    shape = inner.shape
    views = [padded[1 + dr : 1 + dr + shape[0], 1 + dc : 1 + dc + shape[1]] for dr, dc in offsets]
    changed = True
    while changed:
        changed = False
        for lut in _thinning_luts():
            code = np.zeros(shape, np.uint8)
            for bit, view in enumerate(views):
                code |= view << bit
            delete = lut[code] & (inner == 1)
            if delete.any():
                inner[delete] = 0
                changed = True
    return inner.astype(bool)


def thinning_centres(diff: np.ndarray, threshold: float, run_choice: str = "peak") -> StripePoints:
    """Return the stripe's skeleton pixel in every column that has one (thesis 5.2.3).

    The image is binarised at ``threshold`` and thinned; in each column the skeleton
    pixel inside the chosen run is the stripe point, the upper one when there are two,
    as the thesis observed (fig. 5.4). Rows are whole pixels.
    """
    runs = _find_runs(diff, threshold, 1.0, False)
    if runs.start.size == 0:
        return _empty_points()
    chosen, flags = _choose_runs(runs, run_choice)
    # Thin only the band of rows holding bright pixels, upside down: Guo-Hall's first
    # sub-iteration peels the upper edge, so a run two pixels thick would keep its lower
    # pixel; flipped, it keeps the upper one, as the thesis observed (fig. 5.4).
    top, bottom = int(runs.point_rows.min()), int(runs.point_rows.max()) + 1
    skeleton = thin(diff[top:bottom][::-1] > threshold)[::-1]
    skel_rows, skel_cols = np.nonzero(skeleton.T)[::-1]  # column-major, rows ascending
    skel_keys = skel_cols * (diff.shape[0] + 1) + skel_rows + top
    point = np.searchsorted(runs.point_keys, skel_keys)
    skel_run = np.searchsorted(runs.start, point, side="right") - 1
    # The first skeleton pixel of a run is its uppermost.
    run_with_skeleton, first = np.unique(skel_run, return_index=True)
    has = np.isin(chosen, run_with_skeleton)
    chosen, flags = chosen[has], flags[has]
    rows = skel_rows[first[np.searchsorted(run_with_skeleton, chosen)]] + top
    return _points(runs, chosen, rows, flags)


def extract(
    on: np.ndarray, off: np.ndarray | None, settings: ExtractSettings | None = None
) -> StripePoints:
    """Return the stripe points of one view from its laser-on and laser-off frames.

    Args:
        on: laser-on frame (H, W), uint8 or uint16 (16-bit is worked in 8-bit units).
        off: laser-off frame like ``on``, or None to use the laser-on frame alone.
        settings: how to find the stripe; the thesis's method when None.

    Returns:
        One point per column where a stripe was found.
    """
    settings = settings or ExtractSettings()
    diff = _to_8bit(difference(on, off))
    if settings.background_opening_px > 0:
        diff = remove_background(diff, settings.background_opening_px)
    if settings.threshold is None:
        threshold = otsu_threshold(diff[:: settings.otsu_row_step])
    else:
        threshold = settings.threshold
    threshold = max(threshold, settings.min_peak - 1)
    if settings.method == "thinning":
        return thinning_centres(diff, threshold, settings.run_choice)
    return centre_of_gravity(
        diff, threshold, settings.power, settings.subtract_threshold, settings.run_choice
    )


def to_segment(
    points: StripePoints, target: str, section: int, view: int, z_mm: float, angle_deg: float
) -> Segment:
    """Label one view's stripe points with where they were taken (flags stay on-device)."""
    return Segment(
        target, section, view, z_mm, angle_deg, points.cols, points.rows, points.peak, points.width
    )
