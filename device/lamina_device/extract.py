"""Stripe extraction on the device: difference image, threshold, per-column stripe centre.

The core is the thesis's method (section 5.2): a global Otsu threshold and, per image
column, the intensity-weighted centre of the pixels above it (eq. 5.1, power factor
``p`` = 1). Three things go beyond it: the laser-off frame is subtracted first (the
thesis's own recommendation, 9.2); only one above-threshold run per column is used, so
a stray reflection elsewhere in the column cannot drag the centre away; and points the
noise could have made are dropped (below). By default
that is the run holding the column's peak; ``run_choice="continuity"`` keeps instead
the run that best continues the stripe from the neighbouring columns.

Otsu's criterion is evaluated exactly, over the whole frame, but only at the levels a
stripe may have (from ``min_peak`` up): wherever the thesis's threshold lies there, the
two are the same level. Only when the whole-frame optimum falls into the noise below
``min_peak`` (no stripe in view) does this keep the best level above it, where the
thesis's threshold, clipped to ``min_peak``, would let the noise through.

Trusting a point (issue 10). A weak stripe (grazing views, the top and base of an
object, thin parts, a red laser seen in the luma frame) leaves most columns to the
noise, whose column maxima an Otsu level near the floor lets through. So the noise of
each view is measured (the interquartile range of the signed laser-on minus laser-off
difference on a strided subsample of ~2000 pixels, a few tens of microseconds), stripe
pixels must rise a couple of sigmas above it, and a point is kept only if its peak
clears the multiple of sigma derived for at most ``false_points_per_frame`` noise
points (:func:`gate_sigmas`), the run is no longer than a laser profile can be, and it
belongs to a chain of at least ``min_chain_px`` neighbouring columns whose runs meet
within ``max_row_jump_px`` rows: a stripe is a curve, noise is not. Each point carries
its peak over that noise as a confidence byte for the host. The thesis's method alone
is :meth:`ExtractSettings.thesis`. Optionally the centres are smoothed along each
chain by a local line fit (fewer speckle errors, a small bias on tight curves); the
host fits them along the chains instead, unbiased (``lamina_shared.centreline``).

The centre at the sub-pixel limit (issue 21). By default the centre also weighs 3
pixels beyond either end of the run (``margin_px``: which pixels Otsu's cut keeps
changes with the stripe's sub-pixel phase, a ripple no fit along the stripe removes),
and runs of one column at most 2 rows apart are one run (``bridge_px``: speckle
darkens spots inside a wide stripe), the pixels between weighed in.

Selectable as well: background removal by morphological opening (thesis 5.2.1), a fixed
threshold, weights above the threshold, and the thesis's first method, Otsu
binarisation then line thinning with whole-pixel output (5.2.3, figs. 5.4-5.6), kept so
that its bias can be measured.

Speed: the whole frame is touched three times, by cheap vectorised passes: one
saturating subtraction, one comparison and one test of 8 pixels per machine word (plus
a sum). Otsu's counts, the runs and their sums then come from the few words that hold
a bright pixel, ordered column by column with a single sort, or, in the usual frame
of one run per column, from column sums and one window per column with no ordering;
the noise comes from a subsample and the gate and chains work on the points alone.
On the box these passes run on the extracting thread alone (:func:`run_opencv_inline`).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from functools import cache, cached_property
from statistics import NormalDist
from typing import Any

import cv2
import numpy as np

from lamina_shared.centreline import DEFAULT_ROW_JUMP_PX, chain_starts, one_chain
from lamina_shared.ops import (
    EXTRACT_FULL_SCALE,
    EXTRACT_METHODS,
    EXTRACT_RUN_CHOICES,
    extract_problems,
)
from lamina_shared.protocol import confidence_bytes
from lamina_shared.types import Segment

METHODS = EXTRACT_METHODS
RUN_CHOICES = EXTRACT_RUN_CHOICES

FLAG_SEVERAL_RUNS = 1
"""Point flag: the column held more than one bright run (a reflection, a second surface)."""
FLAG_NOT_PEAK_RUN = 2
"""Point flag: the run kept is not the one holding the column's peak (continuity choice)."""
FLAG_SATURATED = 4
"""Point flag: the run's peak is at full scale, so its centre may be biased."""

_FULL_SCALE = EXTRACT_FULL_SCALE
_NOISE_SAMPLES = 2048  # pixels the noise is estimated from, whatever the frame size
_MIN_NOISE_DN = 0.5  # two 8-bit roundings alone give ~0.4 DN: never trust a quieter estimate
_PIXEL_SIGMAS = 2.0  # stripe pixels lie above this many noise sigmas (keeps the noise out)
# The noise estimate of one frame scatters by ~3 % (a few thousand samples); the gate
# allows for two of those, else an underestimated frame lets several times the rate in.
_NOISE_MARGIN = 1.06
_IQR_SIGMAS = 1.3489795003921634  # 2 Phi^-1(3/4): a Gaussian's interquartile range in sigmas
# Float32 sums of up to this many 8-bit levels times their row offsets stay below 2**24.
_EXACT_SPAN_PX = 256
_SATURATED_FLAGS = np.where(np.arange(256) >= _FULL_SCALE, FLAG_SATURATED, 0).astype(np.uint8)
_SATURATED_FLAGS.flags.writeable = False  # the flags of an 8-bit peak, by level
_ONE_CHAIN = np.zeros(1, np.intp)  # chain_starts of a view whose points form one chain
_ONE_CHAIN.flags.writeable = False


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

    Trusting a point (issue 10): with ``noise_gate`` the frame's noise is estimated and
    a point is strong if its peak clears the multiple of the noise sigma that lets at
    most ``false_points_per_frame`` noise points through (:func:`gate_sigmas`);
    ``min_peak`` stays a floor. A stripe is a curve: points form chains of neighbouring
    columns (one may be skipped) whose runs come within ``max_row_jump_px`` rows of each
    other, and a chain is kept only if ``min_chain_px`` of its points in a row are strong
    (1 keeps isolated columns), its fainter points with it; runs longer than
    ``max_width_px`` rows (or shorter than ``min_width_px``) are no laser profile.
    ``smooth_sigma_px`` > 0 smooths the centres along each chain (a local line fit with
    Gaussian weights of that many columns). ``margin_px`` > 0 weighs that many pixels
    beyond each end of the run into its centre (centre of gravity only; with
    ``subtract_threshold`` they weigh nothing): the centre no longer jumps as the run's
    edge pixels cross the threshold (the sub-pixel bench, issue 21). ``bridge_px`` > 0
    makes runs of one column at most that many rows apart one run, the pixels between
    them weighed in (centre of gravity only): speckle darkens spots inside a wide
    stripe below the threshold, and the brightest piece alone is not its centre.
    :meth:`thesis` turns all of this off.
    """

    threshold: float | None = None
    power: float = 1.0
    min_peak: float = 12.0
    subtract_threshold: bool = False
    method: str = "cog"
    run_choice: str = "peak"
    background_opening_px: int = 0
    noise_gate: bool = True
    false_points_per_frame: float = 1e-4
    min_chain_px: int = 8
    max_row_jump_px: float = DEFAULT_ROW_JUMP_PX
    min_width_px: int = 1
    max_width_px: int = 64
    smooth_sigma_px: float = 0.0
    margin_px: int = 3
    bridge_px: int = 2

    def __post_init__(self) -> None:
        problems = settings_problems(self)
        if problems:
            raise SettingsError(problems)

    @classmethod
    def thesis(cls, **changes: object) -> ExtractSettings:
        """Return the thesis's method alone: no noise gate, no chains, any run width."""
        plain: dict[str, object] = {
            "noise_gate": False, "min_chain_px": 1, "min_width_px": 1, "max_width_px": 255,
            "margin_px": 0, "bridge_px": 0,
        }  # fmt: skip
        return cls(**{**plain, **changes})  # type: ignore[arg-type]


class SettingsError(ValueError):
    """Extraction settings out of range; ``problems`` lists every one."""

    def __init__(self, problems: list[str]) -> None:
        super().__init__("bad extraction settings: " + "; ".join(problems))
        self.problems = problems


def changed_settings(
    base: ExtractSettings, changes: Mapping[str, Any]
) -> tuple[ExtractSettings | None, list[str]]:
    """Return ``base`` with ``changes`` applied, or None and every problem of the result.

    ``changes`` have the kinds of :data:`lamina_shared.ops.EXTRACT_FIELDS` (checked by
    :func:`lamina_shared.ops.check_extract`); whole numbers are accepted as floats.
    """
    values: dict[str, Any] = {
        key: float(value) if _FLOAT_FIELDS.get(key) and type(value) is int else value
        for key, value in changes.items()
    }
    try:
        return dataclasses.replace(base, **values), []
    except SettingsError as exc:
        return None, exc.problems


def settings_problems(settings: ExtractSettings) -> list[str]:
    """Return every problem with ``settings`` (empty when they are usable).

    The ranges are the wire's own (:func:`lamina_shared.ops.extract_problems`), so a host
    checks a scan's changes against them before it asks.
    """
    return extract_problems(dataclasses.asdict(settings))


_DEFAULT = ExtractSettings()
_FLOAT_FIELDS = {
    f.name: f.type in ("float", "float | None") for f in dataclasses.fields(ExtractSettings)
}


def _no_flags() -> np.ndarray:
    return np.zeros(0, np.uint8)


@dataclass(frozen=True)
class StripePoints:
    """Per-column stripe centres of one view, before they are labelled as a segment.

    ``flags`` (uint8 per point, ``FLAG_*`` bits) stays on the device: the wire segment
    carries ``cols``, ``rows``, ``peak``, ``width`` and ``confidence`` (the peak over
    the view's noise sigma, times ``CONFIDENCE_SCALE``, capped at 255; 0 when unknown).
    Left out, flags and confidence are all zeros.
    """

    cols: np.ndarray
    rows: np.ndarray
    peak: np.ndarray
    width: np.ndarray
    flags: np.ndarray = field(default_factory=_no_flags)
    confidence: np.ndarray = field(default_factory=_no_flags)

    def __post_init__(self) -> None:
        for name in ("flags", "confidence"):
            if getattr(self, name).size == 0 and self.cols.size:
                object.__setattr__(self, name, np.zeros(self.cols.size, np.uint8))
        arrays = (self.cols, self.rows, self.peak, self.width, self.flags, self.confidence)
        if len({a.size for a in arrays}) > 1:
            raise ValueError("stripe point arrays differ in length")

    @classmethod
    def of(cls, *arrays: np.ndarray) -> StripePoints:
        """Return the points of arrays known to be alike in length, flags given.

        For the extraction's own results (``cols`` .. ``flags``, optionally
        ``confidence``): the checks of a caller's arrays cost as much again as the
        construction, a few microseconds a view.
        """
        points = object.__new__(cls)
        for name, array in zip(_POINT_FIELDS, arrays, strict=False):
            object.__setattr__(points, name, array)
        if len(arrays) < len(_POINT_FIELDS):
            object.__setattr__(points, "confidence", np.zeros(arrays[0].size, np.uint8))
        return points

    def subset(self, keep: np.ndarray) -> StripePoints:
        """Return the points selected by ``keep`` (a mask or indices)."""
        return StripePoints(
            self.cols[keep], self.rows[keep], self.peak[keep], self.width[keep],
            self.flags[keep], self.confidence[keep],
        )  # fmt: skip


_POINT_FIELDS = ("cols", "rows", "peak", "width", "flags", "confidence")


def _iqr_sigma(counts: np.ndarray) -> float:
    """Return the sigma of Gaussian noise from its values counted by level.

    From the interquartile range, which ignores any offset and which the few percent of
    stripe pixels among the values only widen. Level ``v`` is taken to spread evenly
    over ``[v - 0.5, v + 0.5)``, so the quartiles move smoothly rather than by whole
    steps, as a few DN of noise need.
    """
    cdf = counts.cumsum()
    targets = (0.25 * float(cdf[-1]), 0.75 * float(cdf[-1]))
    quartiles = []
    for target, index in zip(targets, cdf.searchsorted(targets).tolist(), strict=True):
        below = float(cdf[index - 1]) if index else 0.0
        quartiles.append(index - 0.5 + (target - below) / max(float(counts[index]), 1.0))
    return max((quartiles[1] - quartiles[0]) / _IQR_SIGMAS, _MIN_NOISE_DN)


def estimate_noise(on: np.ndarray, off: np.ndarray | None) -> float:
    """Return the noise sigma of laser-on minus laser-off, in 8-bit DN, from a subsample.

    The saturating difference hides half the noise, so the signed difference is taken
    on a strided subsample of a couple of thousand pixels; its interquartile range
    ignores the few percent of stripe pixels and any offset between the frames. Without
    a laser-off frame, neighbouring columns of the laser-on frame are differenced
    instead (the same noise of two pixels). One sigma serves the whole frame: shot noise
    makes bright parts noisier, which the gate's chains and margin absorb.
    """
    height, width = on.shape
    step = max(1, int(math.sqrt(height * width / _NOISE_SAMPLES)))
    rows, cols = slice(step // 2, height, step), slice(step // 2, width - 1, step)
    first = on[rows, cols] if off is None else off[rows, cols]
    second = on[rows, step // 2 + 1 :: step] if off is None else on[rows, cols]
    if on.dtype == np.uint16:
        first, second = first >> 8, second >> 8
    key = np.subtract(second[:, : first.shape[1]], first, dtype=np.int16)
    key += 256
    return _iqr_sigma(np.bincount(key.ravel(), minlength=512))


@cache
def gate_sigmas(
    width_px: int, height_px: int, min_chain_px: int, false_points_per_frame: float
) -> float:
    """Return the noise multiple ``k`` a point's peak must clear for the false-point rate asked.

    In a frame without a stripe each column keeps its noise maximum, which clears
    ``k`` sigmas with probability ``p = 1 - (1 - Q(k))**H`` (``Q`` the Gaussian upper
    tail, ``H`` rows). A false point needs ``L = min_chain_px`` neighbouring columns
    that all do, so the expected false points are at most ``W L p**L`` (``W``
    columns); this returns the ``k`` that makes that ``false_points_per_frame``, never
    below the stripe-pixel level. It takes no credit for the maxima having to line up
    within the row jump (with white noise they seldom do), so it holds for noise that
    is correlated along the columns as well.
    """
    chain = min_chain_px
    per_column = min((false_points_per_frame / (width_px * chain)) ** (1.0 / chain), 0.5)
    per_pixel = -math.expm1(math.log1p(-per_column) / height_px)
    return max(-NormalDist().inv_cdf(per_pixel), _PIXEL_SIGMAS)


def run_opencv_inline() -> None:
    """Make OpenCV run every call on the calling thread, for the whole process.

    The device extracts one frame at a time, in well under a millisecond at the small
    resolutions. Waking OpenCV's worker threads for each of its two whole-frame passes
    (the subtraction and the sum) then costs more than the threads save: at 640x480 on
    a 2-core machine 35 against 11 us per subtraction and 21 against 5 us per sum,
    about a fifth of the extraction, and the workers compete with the camera's own
    threads. The device program calls this for a camera or a replay; the simulator
    keeps OpenCV's threads, which blur its rendered frames (pixel work that does pay).
    """
    cv2.setNumThreads(0)  # 0: every function runs sequentially on its caller's thread


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
    """Return the histogram of a non-negative integer array as counts by level."""
    if image.dtype == np.uint8 and image.size < 1 << 24:
        # cv2 counts 8-bit data several times faster than bincount; its float32 counts
        # are exact below 2**24 pixels.
        return cv2.calcHist([image.ravel()], [0], None, [256], [0, 256]).ravel()
    return np.bincount(image.ravel())


@cache
def _count_and_level(levels: int) -> np.ndarray:
    """Return ``1 + 1j * level`` for levels ``levels - 1`` down to 0 (read-only, shared)."""
    weights = 1 + 1j * np.arange(levels - 1, -1, -1)
    weights.flags.writeable = False
    return weights


def otsu_level(hist: np.ndarray, pixels: int, total: float, floor: int = 0) -> int:
    """Return Otsu's threshold level, searched from ``floor`` up (between-class variance max).

    Pixels strictly above the returned level form the bright class; ties go to the
    lowest level. Only the bins above ``floor`` are read, so ``hist`` may count the
    bright pixels alone, provided ``pixels`` and ``total`` are the whole image's.

    Args:
        hist: pixel counts by level.
        pixels: number of pixels in the whole image.
        total: sum of the whole image's levels.
        floor: lowest level to consider.

    Returns:
        The level, at least ``floor``.
    """
    if floor >= hist.size - 1 or pixels == 0:
        return floor
    # One cumulative sum carries both the count (real) and the sum (imaginary) of the
    # pixels at or above each level, top down: the bright class of the level below.
    bright = (hist[:floor:-1] * _count_and_level(hist.size)[: hist.size - 1 - floor]).cumsum()
    bright = bright[::-1]
    count = bright.real
    excess = count * (total / pixels) - bright.imag  # n1 * mean - s1
    # n0 * n1 * (mean0 - mean1)**2 is pixels**2 * excess**2 / (n0 * n1); 0/0 only where
    # one class is empty, which separates nothing.
    between = excess * excess / np.maximum(count * (pixels - count), 1.0)
    return floor + int(between.argmax())


def otsu_threshold(image: np.ndarray) -> float:
    """Return Otsu's threshold of a non-negative integer image over its whole histogram."""
    return float(otsu_level(_histogram(image), image.size, float(image.sum(dtype=np.float64))))


@dataclass(frozen=True)
class _Bright:
    """The 8-pixel words of an 8-bit image that hold a pixel above some level.

    Found by comparing the frame once and testing 8 pixels per machine word, so the
    full-frame work is two cheap passes; everything after works on these words only.
    ``pixels`` holds the words' 8 pixels each; the image may have been padded on the
    right to a multiple of 8 columns (zeros, never above any level).
    """

    height: int
    width: int
    words: np.ndarray
    pixels: np.ndarray

    @classmethod
    def find(cls, image: np.ndarray, level: int) -> _Bright:
        """Return the words of ``image`` (uint8) holding a pixel strictly above ``level``."""
        if level < 0:
            raise ValueError(f"threshold level {level} is negative")
        height, width = image.shape
        if width % 8 or not image.flags.c_contiguous:
            padded = np.zeros((height, -(-width // 8) * 8), np.uint8)
            padded[:, :width] = image
            image = padded
        all_words = image.reshape(-1).view(np.uint64)
        words = ((image > level).reshape(-1).view(np.uint64) != 0).nonzero()[0]
        return cls(height, image.shape[1], words, all_words[words].view(np.uint8))

    def above(self, level: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Return the pixels above ``level`` in row-major order: column, row and word index."""
        chosen = (self.pixels > math.floor(level)).nonzero()[0]
        word = chosen >> 3
        word_row, word_col = np.divmod(self.words, self.width // 8)
        word_col <<= 3
        col = word_col[word]
        col |= chosen & 7
        return col, word_row[word], chosen

    def column_major(self, level: float) -> tuple[np.ndarray, np.ndarray]:
        """Return the pixels above ``level`` column by column, rows ascending.

        Returns:
            Each pixel's column-major index ``col * height + row`` and its level (int64).
        """
        col, row, chosen = self.above(level)
        # The pixels come row by row, so a stable sort by column alone leaves each
        # column's rows ascending, and 16-bit keys (no frame is wider:
        # DeviceLimits.max_image_side_px) sort by radix, twice as fast as whole indices.
        order = np.argsort(col.astype(np.uint16), kind="stable")
        index = col[order]
        index *= self.height
        index += row[order]
        return index, self.pixels[chosen[order]].astype(np.int64)


@dataclass(frozen=True)
class _Runs:
    """Every above-threshold run of an image, in column-then-row order.

    ``point_index`` is each above-threshold pixel's column-major index ``col * height +
    row``; ``start`` indexes the first pixel of each run. ``moment`` sums weight times
    column-major index, so a run's centre row is ``moment / weight - col * height``.
    """

    height: int
    point_index: np.ndarray
    start: np.ndarray
    col: np.ndarray
    length: np.ndarray
    peak: np.ndarray
    weight: np.ndarray
    moment: np.ndarray

    @property
    def centre(self) -> np.ndarray:
        """Return each run's weighted centre row (eq. 5.1), float64."""
        return self.moment / self.weight - self.col * self.height

    @property
    def several(self) -> bool:
        """Return whether any column holds more than one run."""
        return bool((self.col[1:] == self.col[:-1]).any())

    @cached_property
    def col_start(self) -> np.ndarray:
        """Return the index of the first run of each column holding one."""
        return np.flatnonzero(np.diff(self.col, prepend=-1) != 0)

    @property
    def runs_per_col(self) -> np.ndarray:
        """Return how many runs each column holding one has."""
        return np.diff(np.append(self.col_start, self.col.size))


def _run_bounds(
    index: np.ndarray, height: int, split_columns: bool, bridge_px: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Return each run's first pixel, length, column and first row.

    A gap of more than ``bridge_px`` rows starts a run; a run's length is its span in
    rows, the bridged gaps included.
    """
    starts = np.empty(index.size, bool)
    starts[0] = True
    np.greater(index[1:] - index[:-1], 1 + bridge_px, out=starts[1:])
    if split_columns:  # a run reaching the bottom row must not continue at the next top
        column = index // height
        starts[1:] |= column[1:] != column[:-1]
    start = np.flatnonzero(starts)
    length = np.empty_like(start)
    length[:-1] = index[start[1:] - 1]
    length[-1] = index[-1]
    length -= index[start]
    length += 1
    col, row0 = np.divmod(index[start], height)
    return start, length, col, row0


def _find_runs(
    bright: _Bright,
    threshold: float,
    power: float,
    subtract_threshold: bool,
    bridge: tuple[np.ndarray, int] | None = None,
) -> _Runs | None:
    """Return the above-threshold runs with their eq. 5.1 sums, or None when there are none.

    With ``bridge`` (the 8-bit difference image and a number of rows) runs of one column
    that far apart or nearer are one run, the pixels between them weighed in too.
    """
    index, values = bright.column_major(threshold)
    if index.size == 0:
        return None
    height = bright.height
    bridge_px = 0 if bridge is None else bridge[1]
    start, length, col, row0 = _run_bounds(index, height, False, bridge_px)
    if (row0 + length).max() > height:  # rare: a stripe touching both image edges
        start, length, col, _ = _run_bounds(index, height, True, bridge_px)
    weights = _weights(values, threshold, power, subtract_threshold)
    weight = np.add.reduceat(weights, start)
    moment = np.add.reduceat(weights * index, start)
    if bridge is not None and bridge_px and length.sum() > index.size:
        gaps = _gap_pixels(index, start, bridge_px)
        if gaps[0].size:
            run, gap_index = gaps
            level = _levels_at(bridge[0], gap_index).astype(np.int64)
            gap_weight = np.maximum(_weights(level, threshold, power, subtract_threshold), 0)
            weight = weight + np.bincount(run, gap_weight, start.size).astype(weight.dtype)
            moment = moment + np.bincount(run, gap_weight * gap_index, start.size).astype(
                moment.dtype
            )
    return _Runs(
        height=height,
        point_index=index,
        start=start,
        col=col,
        length=length,
        peak=np.maximum.reduceat(values, start),
        weight=weight,
        moment=moment,
    )


def _levels_at(diff: np.ndarray, index: np.ndarray) -> np.ndarray:
    """Return the levels of ``diff`` at column-major indices ``col * height + row``."""
    height, width = diff.shape
    col, row = np.divmod(index, height)
    row *= width
    row += col
    return diff.reshape(-1)[row]


def _gap_pixels(
    index: np.ndarray, start: np.ndarray, bridge_px: int
) -> tuple[np.ndarray, np.ndarray]:
    """Return the run and the column-major index of every pixel a run bridges."""
    step = index[1:] - index[:-1]
    inside = np.ones(step.size, bool)
    inside[start[1:] - 1] = False  # the step into the next run is no gap of this one
    after = np.flatnonzero(inside & (step > 1))
    runs, pixels = [], []
    for k in range(1, bridge_px + 1):
        chosen = after[step[after] > k]
        runs.append(np.searchsorted(start, chosen, "right") - 1)
        pixels.append(index[chosen] + k)
    return np.concatenate(runs), np.concatenate(pixels)


def _weights(
    values: np.ndarray, threshold: float, power: float, subtract_threshold: bool
) -> np.ndarray:
    """Return the eq. 5.1 weight ``I**p`` (or ``(I - threshold)**p``) of each pixel."""
    if not subtract_threshold and power == 1.0:
        return values  # int64 levels: the sums stay exact
    weights = np.subtract(values, threshold if subtract_threshold else 0.0, dtype=np.float64)
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
    if several.all():
        return peak_choice
    centre = runs.centre
    anchors = runs.col_start[~several]
    expected = np.interp(runs.col, runs.col[anchors], centre[anchors])
    distance = np.abs(centre - expected)
    col_best = np.minimum.reduceat(distance, runs.col_start)
    nearest = _first_per_column(runs, distance == np.repeat(col_best, runs.runs_per_col))
    return np.where(several, nearest, peak_choice)


def _choose_runs(runs: _Runs, run_choice: str) -> tuple[np.ndarray | slice, np.ndarray]:
    """Return per column the run kept (an index, or every run) and its flags."""
    if not runs.several:  # the usual frame: one run per column, nothing to choose
        return slice(None), (runs.peak >= _FULL_SCALE).view(np.uint8) * np.uint8(FLAG_SATURATED)
    chosen = _peak_runs(runs)
    if run_choice == "continuity":
        peak_choice, chosen = chosen, _continuity_runs(runs, chosen)
        flags = np.where(chosen != peak_choice, FLAG_NOT_PEAK_RUN, 0).astype(np.uint8)
    else:
        flags = np.zeros(chosen.size, np.uint8)
    flags[runs.runs_per_col > 1] |= FLAG_SEVERAL_RUNS
    flags[runs.peak[chosen] >= _FULL_SCALE] |= FLAG_SATURATED
    return chosen, flags


def _points(
    runs: _Runs, chosen: np.ndarray | slice, rows: np.ndarray, flags: np.ndarray
) -> StripePoints:
    """Return the stripe points of the chosen runs at the given centre rows."""
    return StripePoints(
        runs.col[chosen].astype(np.uint16),
        rows.astype(np.float32),
        runs.peak[chosen].astype(np.uint8),  # levels are 8-bit already
        np.minimum(runs.length[chosen], _FULL_SCALE).astype(np.uint8),
        flags,
    )


def _centres(
    bright: _Bright,
    threshold: float,
    power: float,
    subtract_threshold: bool,
    run_choice: str,
    diff: np.ndarray | None = None,
    margin_px: int = 0,
    bridge_px: int = 0,
) -> StripePoints:
    """Return the eq. 5.1 centre of the kept run of every column with one.

    With ``diff`` (the 8-bit difference image) runs of one column at most ``bridge_px``
    rows apart are one run (:func:`_find_runs`), and the centre also weighs
    ``margin_px`` pixels beyond each end of the run (:func:`_margin_centres`).
    """
    if diff is not None and power == 1.0 and not subtract_threshold:
        points = _single_run_centres(bright, threshold, diff, margin_px, bridge_px)
        if points is not None:
            return points
    bridge = None if diff is None or bridge_px == 0 else (diff, bridge_px)
    runs = _find_runs(bright, threshold, power, subtract_threshold, bridge)
    if runs is None:
        return _empty_points()
    chosen, flags = _choose_runs(runs, run_choice)
    if diff is None or margin_px == 0:
        return _points(runs, chosen, runs.centre[chosen], flags)
    weighing = (threshold, power, subtract_threshold)
    return _points(runs, chosen, _margin_centres(runs, chosen, diff, margin_px, weighing), flags)


def _single_run_centres(
    bright: _Bright, threshold: float, diff: np.ndarray, margin_px: int, bridge_px: int
) -> StripePoints | None:
    """Return :func:`_centres` (eq. 5.1, ``p`` = 1) when every column holds one run, else None.

    The usual frame's fast path: with one run per column (its gaps no wider than
    ``bridge_px``) nothing needs ordering column by column, so each column's last
    bright row and its count come from unordered reductions, and the run, its bridged
    gaps and ``margin_px`` pixels either side are weighed from one window per column.
    The results equal the general path's (runs, choice, :func:`_margin_centres`).
    """
    col, row = bright.above(threshold)[:2]
    if col.size == 0:
        return _empty_points()
    count = np.bincount(col, minlength=bright.width)
    cols = count.nonzero()[0]
    # A bright row of each column, no ordering: where indices repeat, one assignment
    # wins. Pixels come row by row, so that is the last one in practice (taken in this
    # order it costs half what the first does); if it is not, or the rows are not
    # consecutive, the window below misses bright pixels and the exact bounds are taken.
    bottom = np.empty(bright.width, np.int64)
    bottom[col] = row
    if cols.size < count.size:  # the usual stripe crosses every column: no gathers
        count, bottom = count[cols], bottom[cols]
    length = count
    longest = int(count.max())
    windows = None
    # Rows come in ascending order and every column's run, as its count places it,
    # lies between their ends: the windows then fit.
    start = bottom - count
    start += 1 - margin_px  # each window's first row
    if int(row[0]) >= margin_px and int(row[-1]) + longest + margin_px <= diff.shape[0]:
        windows = _windows(diff, cols, start, longest, length, margin_px)
    if windows is None or not _runs_bright(*windows, margin_px, threshold, col.size):
        top, length = _column_bounds(col, row, cols, bright.width, diff.shape[0])
        if int((length - count).max()) > bridge_px:
            return None  # some column holds two runs: they must be told apart
        longest = int(length.max())
        start = top - margin_px
        windows = _clipped_windows(diff, cols, start, longest, length, margin_px)
    levels, inside = windows
    weight, moment = _window_sums(np.multiply(levels, inside, dtype=np.float32))
    centre = start + moment / weight
    peak = levels.max(axis=0)  # the run's: every other pixel of the window is darker
    flags = _SATURATED_FLAGS[peak]
    if longest > _FULL_SCALE:
        length = np.minimum(length, _FULL_SCALE)
    return StripePoints.of(
        cols.astype(np.uint16), centre.astype(np.float32), peak, length.astype(np.uint8), flags
    )


def _window_sums(weights: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return each window's (column's) sum of weights and of weight times row offset, float32.

    The weights are whole levels, so up to :data:`_EXACT_SPAN_PX` rows the sums are
    exact whatever the order, and one product gives both; longer windows are summed as
    ever, rounding the same way.
    """
    span = weights.shape[0]
    if span <= _EXACT_SPAN_PX:
        return _sum_and_moment(span) @ weights
    return weights.sum(axis=0), np.arange(span, dtype=np.float32) @ weights


@cache
def _sum_and_moment(span: int) -> np.ndarray:
    """Return the (2, span) float32 rows 1 and 0..span-1 (read-only, shared)."""
    rows = np.stack([np.ones(span, np.float32), np.arange(span, dtype=np.float32)])
    rows.flags.writeable = False
    return rows


def _column_bounds(
    col: np.ndarray, row: np.ndarray, cols: np.ndarray, width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Return the first bright row of each of ``cols`` and the rows from there to its last."""
    top = np.full(width, height, np.int64)
    np.minimum.at(top, col, row)
    bottom = np.full(width, -1, np.int64)
    np.maximum.at(bottom, col, row)
    top = top[cols]
    return top, bottom[cols] - top + 1


def _windows(
    diff: np.ndarray,
    cols: np.ndarray,
    start: np.ndarray,
    longest: int,
    length: np.ndarray,
    margin_px: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Return each column's run and margins as (rows, N) levels and where they lie inside.

    The window of a column starts at row ``start``, inside the frame; all are padded to
    the ``longest`` run, the padding marked outside.
    """
    width = diff.shape[1]
    span = longest + 2 * margin_px
    flat = start * width
    flat += cols
    row_offsets, offsets = _window_offsets(span, width)
    flat = flat + row_offsets
    inside = offsets < np.add(length, 2 * margin_px, dtype=np.uint16, casting="unsafe")
    return diff.reshape(-1)[flat], inside


@cache
def _window_offsets(span: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Return a window's (span, 1) offsets in the flat frame and in rows (read-only, shared).

    The rows are 16-bit (no frame is taller: DeviceLimits), which compare several
    times faster.
    """
    flat = np.arange(0, span * width, width)[:, None]
    rows = np.arange(span, dtype=np.uint16)[:, None]
    flat.flags.writeable = False
    rows.flags.writeable = False
    return flat, rows


def _clipped_windows(
    diff: np.ndarray,
    cols: np.ndarray,
    start: np.ndarray,
    longest: int,
    length: np.ndarray,
    margin_px: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Return :func:`_windows` for windows that may cross the frame's edge (outside there)."""
    height, width = diff.shape
    offsets = np.arange(longest + 2 * margin_px)[:, None]
    rows = start + offsets
    inside = (offsets < length + 2 * margin_px) & (rows >= 0) & (rows < height)
    flat = np.clip(rows, 0, height - 1) * width + cols
    return diff.reshape(-1)[flat], inside


def _runs_bright(
    levels: np.ndarray, inside: np.ndarray, margin_px: int, threshold: float, bright: int
) -> bool:
    """Return whether every window's run rows hold all of the ``bright`` pixels found.

    A column's run fills its window less ``margin_px`` rows either side: in the padded
    layout, where the window ``2 margin_px`` rows further down is still inside.
    """
    span = levels.shape[0]
    run = levels[margin_px : span - margin_px] > math.floor(threshold)
    run &= inside[2 * margin_px :]
    return np.count_nonzero(run) == bright


def _margin_centres(
    runs: _Runs,
    chosen: np.ndarray | slice,
    diff: np.ndarray,
    margin_px: int,
    weighing: tuple[float, float, bool],
) -> np.ndarray:
    """Return the chosen runs' centres with ``margin_px`` pixels beyond each end weighed in.

    Otsu's cut keeps only the profile's core, and which pixels it keeps changes with the
    stripe's sub-pixel phase: the centre jumps as an edge pixel crosses the threshold,
    and along a gently sloping stripe these jumps add up to a slow ripple that no fit
    along the stripe removes. The pixels just beyond the run lie below the threshold by
    definition (or belong to a neighbouring run, which is left out), so they weigh
    little and change smoothly. Eq. 5.1 over the widened run, ``weighing`` being its
    threshold, power and threshold subtraction (the margin weighs nothing then).
    """
    threshold, power, subtract_threshold = weighing
    height = runs.height
    col = runs.col[chosen]
    top = runs.point_index[runs.start[chosen]] - col * height  # the run's first row
    # (2 margin, N): the long axis innermost, so every operation runs over the points.
    steps = np.arange(1, margin_px + 1)[:, None]
    rows = np.concatenate([top - steps, (top + runs.length[chosen] - 1) + steps])
    clipped = int(top.min()) < margin_px or int(rows[-1].max()) >= height
    flat = np.clip(rows, 0, height - 1) if clipped else rows.copy()
    flat *= diff.shape[1]
    flat += col
    levels = diff.reshape(-1)[flat]
    if clipped:
        levels[(rows < 0) | (rows >= height)] = 0
    if runs.several:  # a pixel above the threshold out there is another run's
        levels[levels > threshold] = 0
    weights = _weights(levels, threshold, power, subtract_threshold)
    if subtract_threshold:
        weights = np.maximum(weights, 0.0)
    run_weight = runs.weight[chosen]
    weight = run_weight + weights.sum(axis=0, dtype=np.float64)
    moment = runs.centre[chosen] * run_weight + (rows * weights).sum(axis=0, dtype=np.float64)
    return moment / weight


def centre_of_gravity(
    diff: np.ndarray,
    threshold: float,
    power: float = 1.0,
    subtract_threshold: bool = False,
    run_choice: str = "peak",
) -> StripePoints:
    """Return the sub-pixel stripe centre of every column that has one (thesis eq. 5.1).

    Args:
        diff: 8-bit difference image (H, W).
        threshold: pixels strictly above it belong to the stripe (not negative).
        power: the power factor ``p`` applied to intensities.
        subtract_threshold: weight by intensity minus threshold rather than intensity.
        run_choice: ``"peak"`` or ``"continuity"`` when a column holds several runs.

    Returns:
        The columns with a stripe, their centre rows (pixel centres at integers), the
        run's peak intensity and its width in pixels, and the ``FLAG_*`` bits.
    """
    bright = _Bright.find(diff, math.floor(threshold))
    return _centres(bright, threshold, power, subtract_threshold, run_choice)


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
    return _thinning(diff, _Bright.find(diff, math.floor(threshold)), threshold, run_choice)


def _thinning(diff: np.ndarray, bright: _Bright, threshold: float, run_choice: str) -> StripePoints:
    """Return :func:`thinning_centres` from the bright words already found in ``diff``."""
    runs = _find_runs(bright, threshold, 1.0, False)
    if runs is None:
        return _empty_points()
    chosen, flags = _choose_runs(runs, run_choice)
    chosen = np.arange(runs.col.size)[chosen]
    height = diff.shape[0]
    # Thin only the band of rows holding bright pixels, upside down: Guo-Hall's first
    # sub-iteration peels the upper edge, so a run two pixels thick would keep its lower
    # pixel; flipped, it keeps the upper one, as the thesis observed (fig. 5.4).
    point_rows = runs.point_index % height
    top, bottom = int(point_rows.min()), int(point_rows.max()) + 1
    skeleton = thin(diff[top:bottom][::-1] > threshold)[::-1]
    skel_rows, skel_cols = np.nonzero(skeleton.T)[::-1]  # column-major, rows ascending
    point = np.searchsorted(runs.point_index, skel_cols * height + skel_rows + top)
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
        settings: how to find the stripe; :class:`ExtractSettings` defaults when None.

    Returns:
        One point per column where a stripe was found, with its confidence.
    """
    settings = settings or _DEFAULT
    diff = _to_8bit(difference(on, off))
    noise_dn = estimate_noise(on, off)
    if settings.background_opening_px > 0:
        diff = remove_background(diff, settings.background_opening_px)
    floor = math.ceil(settings.min_peak - 1)  # the lowest level a stripe pixel may have
    if settings.noise_gate:  # below a couple of sigmas a pixel is as likely noise as stripe
        floor = max(floor, min(math.floor(_PIXEL_SIGMAS * noise_dn), _FULL_SCALE - 1))
    if settings.threshold is None:
        bright = _Bright.find(diff, floor)
        # Otsu's criterion needs the counts above each candidate level only, which the
        # bright words hold, plus the whole frame's pixel count and sum.
        total = float(cv2.sumElems(diff)[0])
        threshold = float(otsu_level(_histogram(bright.pixels), diff.size, total, floor))
    else:
        threshold = float(max(settings.threshold, floor))
        bright = _Bright.find(diff, math.floor(threshold))
    if settings.method == "thinning":
        points = _thinning(diff, bright, threshold, settings.run_choice)
    else:
        points = _centres(
            bright, threshold, settings.power, settings.subtract_threshold, settings.run_choice,
            diff, settings.margin_px, settings.bridge_px,
        )  # fmt: skip
    return _trust(points, noise_dn, settings, diff.shape)


def _trust(
    points: StripePoints, noise_dn: float, settings: ExtractSettings, shape: tuple[int, ...]
) -> StripePoints:
    """Return the points with their confidence, less those noise, width or chains reject.

    Chains are traced through every point; a chain is kept if ``min_chain_px`` of its
    points in a row clear the noise gate (then none of it is noise but with the rate
    :func:`gate_sigmas` allows), and with it its fainter points, which continue the
    stripe (hysteresis, as Canny's edges): the stripe's fading ends stay.
    """
    if points.cols.size == 0:
        return points
    # One noise for the view: one confidence scale on the wire, a few bytes a segment.
    confidence = confidence_bytes(points.peak, noise_dn)
    index: np.ndarray | slice = slice(None)
    cols, rows, width, peak = points.cols, points.rows, points.width, points.peak
    if _misfits(width, settings):
        # Widths are 1..255, so an unset limit (1 or 255) passes every run.
        fits = (width >= settings.min_width_px) & (width <= settings.max_width_px)
        index = np.flatnonzero(fits)
        cols, rows, width, peak = (a[index] for a in (cols, rows, width, peak))
    strong = None  # every point is strong, as without the gate
    if settings.noise_gate and peak.size:
        k = gate_sigmas(shape[1], shape[0], settings.min_chain_px, settings.false_points_per_frame)
        gate = noise_dn * k * _NOISE_MARGIN
        if int(peak.min()) < gate:  # the usual frame's points all clear it: no mask
            strong = peak >= gate
    chained = settings.min_chain_px > 1 or settings.smooth_sigma_px > 0
    if cols.size and (chained or strong is not None):
        # A view of one run per column is usually one chain, which a cheaper test
        # shows; with several runs (reflections) chain_starts decides alone.
        one_run = not int(np.bitwise_or.reduce(points.flags)) & FLAG_SEVERAL_RUNS
        if one_run and one_chain(cols, rows, width, settings.max_row_jump_px):
            starts = _ONE_CHAIN
        else:
            starts = chain_starts(cols, rows, width, settings.max_row_jump_px)
        kept = _kept_chains(starts, strong, cols.size, settings.min_chain_px)
        if kept is not None:
            index = kept if isinstance(index, slice) else index[kept]
            cols, rows, width = cols[kept], rows[kept], width[kept]
            starts = np.flatnonzero(np.diff(np.searchsorted(starts, kept, "right"), prepend=0))
        if settings.smooth_sigma_px > 0 and cols.size:
            chain = np.zeros(cols.size, np.intp)
            chain[starts[1:]] = 1
            rows = _smoothed(cols, rows, np.cumsum(chain), settings.smooth_sigma_px)
    return StripePoints.of(
        cols, rows, points.peak[index], width, points.flags[index], confidence[index]
    )


def _kept_chains(
    starts: np.ndarray, strong: np.ndarray | None, n: int, min_chain_px: int
) -> np.ndarray | None:
    """Return the indices of the points in kept chains, or None when every point is kept.

    A chain is kept when it holds ``min_chain_px`` consecutive strong points (every
    point is strong without a gate).
    """
    if strong is None or strong.all():
        if min_chain_px <= 1 or (starts.size == 1 and n >= min_chain_px):
            return None  # the usual frame: one chain, strong throughout
        strong = np.ones(n, bool)
    first = np.zeros(n, bool)
    first[starts] = True
    # Stretches: runs of points alike in strength within one chain.
    cut = first.copy()
    cut[1:] |= strong[1:] != strong[:-1]
    stretch = np.flatnonzero(cut)
    length = np.diff(stretch, append=n)
    enough = strong[stretch] & (length >= min_chain_px)
    chain_of = np.cumsum(first)[stretch] - 1
    keep_chain = np.zeros(starts.size, bool)
    keep_chain[chain_of[enough]] = True
    chain_length = np.diff(starts, append=n)
    return np.flatnonzero(np.repeat(keep_chain, chain_length))


def _misfits(width: np.ndarray, settings: ExtractSettings) -> bool:
    """Return whether any run is narrower or wider than a laser profile can be."""
    return (settings.min_width_px > 1 and int(width.min()) < settings.min_width_px) or (
        settings.max_width_px < _FULL_SCALE and int(width.max()) > settings.max_width_px
    )


@cache
def _line_fit_kernels(sigma_px: float) -> np.ndarray:
    """Return the Gaussian weights ``w``, ``w dx`` and ``w dx**2`` of a local line fit (3, K)."""
    radius = math.ceil(3 * sigma_px)
    dx = np.arange(-radius, radius + 1, dtype=np.float64)
    w = np.exp(-0.5 * (dx / sigma_px) ** 2)
    kernels = np.stack([w, w * dx, w * dx * dx])
    kernels.flags.writeable = False
    return kernels


def _smoothed(cols: np.ndarray, rows: np.ndarray, chain: np.ndarray, sigma_px: float) -> np.ndarray:
    """Return each centre replaced by a local line fit along its chain (Gaussian weights).

    Fitting a line rather than averaging keeps a sloping stripe unbiased up to the
    chain's ends; a curving one is biased by about curvature x sigma**2 / 2. Points are
    laid out by column with each chain moved past the reach of the previous one, so
    three correlations over the whole view fit every chain at once and none mixes.
    """
    kernels = _line_fit_kernels(sigma_px)
    radius = kernels.shape[1] // 2
    place = cols.astype(np.intp) + chain * (radius + 1) - int(cols[0])
    lanes = np.zeros((2, int(place[-1]) + 1))
    lanes[0, place] = 1.0
    lanes[1, place] = rows
    # cv2.filter2D correlates: lane[i + dx] * kernel[dx], zero beyond the ends.
    sums = [
        cv2.filter2D(lanes, -1, k[None, :], borderType=cv2.BORDER_CONSTANT)[:, place]
        for k in kernels
    ]
    (s0, t0), (s1, t1), (s2, _) = sums
    det = s0 * s2 - s1 * s1
    usable = det > 1e-6 * s0 * s0  # a single point (or one column) has no slope
    fitted = np.where(usable, (s2 * t0 - s1 * t1) / np.where(usable, det, 1.0), t0 / s0)
    return fitted.astype(np.float32)


def sample_colour(rgb: np.ndarray, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Return the (N, 3) uint8 colour of an (H, W, 3) image at sub-pixel points, bilinearly.

    ``cols``/``rows`` follow the pixel-centre convention of ``lamina_shared.types``; points
    beyond the outer pixel centres take the border pixels' colour.
    """
    height, width = rgb.shape[:2]
    u = np.clip(np.asarray(cols, np.float64), 0.0, width - 1.0)
    v = np.clip(np.asarray(rows, np.float64), 0.0, height - 1.0)
    # The lower corner stays one pixel inside, so the upper one exists (1-px images aside).
    u0 = np.clip(np.floor(u).astype(np.intp), 0, max(width - 2, 0))
    v0 = np.clip(np.floor(v).astype(np.intp), 0, max(height - 2, 0))
    u1, v1 = np.minimum(u0 + 1, width - 1), np.minimum(v0 + 1, height - 1)
    fu, fv = (u - u0)[:, None], (v - v0)[:, None]
    image = np.asarray(rgb, np.float64)
    top = image[v0, u0] * (1.0 - fu) + image[v0, u1] * fu
    bottom = image[v1, u0] * (1.0 - fu) + image[v1, u1] * fu
    mixed = top * (1.0 - fv) + bottom * fv
    return np.clip(np.rint(mixed), 0, 255).astype(np.uint8).reshape(-1, 3)


def to_segment(
    points: StripePoints,
    target: str,
    section: int,
    view: int,
    z_mm: float,
    angle_deg: float,
    rgb_off: np.ndarray | None = None,
    turns: int = 0,
) -> Segment:
    """Label one view's stripe points with where they were taken (flags stay on-device).

    With ``rgb_off`` (the view's laser-off frame in sRGB) each point carries the colour
    there, sampled at its sub-pixel stripe centre. ``turns`` are the step count's whole
    turns at the view (:attr:`Segment.turns`).
    """
    colour = (
        np.zeros((0, 3), np.uint8)
        if rgb_off is None or not len(points.cols)
        else sample_colour(rgb_off, points.cols, points.rows)
    )
    return Segment(
        target, section, view, z_mm, angle_deg, points.cols, points.rows, points.peak,
        points.width, points.confidence, colour, turns,
    )  # fmt: skip
