"""Stripe extraction on the device: difference image, threshold, centre of gravity.

The method is the thesis's (section 5.2): a global Otsu threshold and, per image
column, the intensity-weighted centre of the pixels above it (eq. 5.1, power
factor ``p``). Two things go beyond it: the laser-off frame is subtracted first
(the thesis's own recommendation, 9.2), and only the above-threshold run that holds
the column's peak is used, so a stray reflection elsewhere in the column cannot
drag the centre away.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from lamina_shared.types import Segment


@dataclass(frozen=True)
class ExtractSettings:
    """How stripes are found.

    ``threshold`` is ``None`` for Otsu's method or a fixed difference level;
    ``min_peak`` rejects columns whose brightest difference is below it (no stripe).
    ``subtract_threshold`` weights pixels by how far they rise above the threshold
    instead of by their intensity (eq. 5.1): the run's edge pixels then weigh almost
    nothing, so the centre no longer jumps as they enter or leave the run.
    """

    threshold: float | None = None
    power: float = 1.0
    min_peak: float = 12.0
    subtract_threshold: bool = False


@dataclass(frozen=True)
class StripePoints:
    """Per-column stripe centres of one view, before they are labelled as a segment."""

    cols: np.ndarray
    rows: np.ndarray
    peak: np.ndarray
    width: np.ndarray


def difference(on: np.ndarray, off: np.ndarray | None) -> np.ndarray:
    """Return laser-on minus laser-off, clipped at zero, as int32 (laser-on alone if no off)."""
    diff = on.astype(np.int32)
    if off is not None:
        if off.shape != on.shape:
            raise ValueError(f"laser-off frame is {off.shape}, laser-on is {on.shape}")
        diff -= off
        np.maximum(diff, 0, out=diff)
    return diff


def otsu_threshold(image: np.ndarray) -> float:
    """Return Otsu's threshold of a non-negative integer image (between-class variance max)."""
    top = int(image.max())
    if top == 0:
        return 0.0
    hist = np.bincount(image.ravel(), minlength=top + 1).astype(np.float64)
    levels = np.arange(top + 1, dtype=np.float64)
    weight0 = np.cumsum(hist)
    sum0 = np.cumsum(hist * levels)
    total, grand = weight0[-1], sum0[-1]
    weight1 = total - weight0
    with np.errstate(divide="ignore", invalid="ignore"):
        mean0 = sum0 / weight0
        mean1 = (grand - sum0) / weight1
        between = weight0 * weight1 * (mean0 - mean1) ** 2
    between[~np.isfinite(between)] = -1.0
    # Pixels strictly above the returned level form the bright class.
    return float(np.argmax(between))


def centre_of_gravity(
    diff: np.ndarray, threshold: float, power: float = 1.0, subtract_threshold: bool = False
) -> StripePoints:
    """Return the sub-pixel stripe centre of every column that has one (thesis eq. 5.1).

    Args:
        diff: non-negative difference image (H, W).
        threshold: pixels strictly above it belong to the stripe.
        power: the power factor ``p`` applied to intensities.
        subtract_threshold: weight by intensity minus threshold rather than intensity.

    Returns:
        The columns with a stripe, their centre rows (pixel centres at integers),
        the run's peak intensity and its width in pixels.
    """
    height = diff.shape[0]
    peak_row = np.argmax(diff, axis=0)
    cols = np.arange(diff.shape[1])
    peak = diff[peak_row, cols]
    above = diff > threshold
    # Label runs of above-threshold pixels per column; keep the run holding the peak.
    run_id = np.cumsum(~above, axis=0)
    chosen = above & (run_id == run_id[peak_row, cols])
    weights = np.where(chosen, diff - threshold if subtract_threshold else diff, 0)
    weights = weights.astype(np.float64)
    if power != 1.0:
        weights **= power
    total = weights.sum(axis=0)
    keep = (peak > threshold) & (total > 0)
    rows_index = np.arange(height, dtype=np.float64)[:, None]
    centre = (weights[:, keep] * rows_index).sum(axis=0) / total[keep]
    width = chosen[:, keep].sum(axis=0)
    return StripePoints(
        cols[keep].astype(np.uint16),
        centre.astype(np.float32),
        np.minimum(peak[keep], 255).astype(np.uint8),
        np.minimum(width, 255).astype(np.uint8),
    )


def extract(
    on: np.ndarray, off: np.ndarray | None, settings: ExtractSettings | None = None
) -> StripePoints:
    """Return the stripe points of one view from its laser-on and laser-off frames."""
    settings = settings or ExtractSettings()
    diff = difference(on, off)
    if on.dtype == np.uint16:
        # Work in 8-bit units so thresholds and peaks mean the same for any depth.
        diff >>= 8
    threshold = otsu_threshold(diff) if settings.threshold is None else settings.threshold
    threshold = max(threshold, settings.min_peak - 1)
    return centre_of_gravity(diff, threshold, settings.power, settings.subtract_threshold)


def to_segment(
    points: StripePoints, target: str, section: int, view: int, z_mm: float, angle_deg: float
) -> Segment:
    """Label one view's stripe points with where they were taken."""
    return Segment(
        target, section, view, z_mm, angle_deg, points.cols, points.rows, points.peak, points.width
    )
