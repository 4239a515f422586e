"""The room light under a continuous view's stripe, from the laser-off frames around it.

A continuous view (issue 22) is three frames in a row, laser off, on, off, the table
turning at constant speed from one to the next. The difference image needs the room light
as it was while the laser-on frame was exposed, and neither laser-off frame shows it: the
target stands a few degrees further round in each (on the limb rig at the shipped
continuous speed, 18-60 pixels of skin a frame). Their mean leaves a shadow's edge at
two places, and a crest of skin relief that lay between the two frames' positions shows in
neither: in the difference it is as bright as the stripe itself. On random limb shapes with
relief of a few millimetres' wavelength the scan lost three quarters of its surface so.

So each laser-off frame is first brought to the laser-on frame's instant. The table turns
about a vertical axis and the camera's rows are level, so the target's image moves mostly along
the rows, by an amount that varies smoothly over the target (with each point's distance
from the axis) and is zero on whatever stands still. That motion is found the way a stereo
pair's disparity is: OpenCV's semi-global matcher (``StereoSGBM``) matches the laser-on
frame's rows with each laser-off frame's, and its smoothness terms keep a periodic relief
from being matched a period out. The stripe, a narrow band across the rows, is matched
through by those same terms. Each laser-off frame is then shifted along its rows by its
own motion, and the two are combined as before (:func:`combine_off_frames`): their mean
where they agree, the brighter where they do not (an edge one of them hides).

Only the part of the frame where the two laser-off frames differ is matched, in two
passes (:func:`row_motion_px`). Measured on random limb shapes with fine relief (harsh,
2 sections of 8 views): 0.415 mm at coverage 0.24 with the off frames merely combined,
0.099 mm at 0.93 so (stop-and-go 0.084); on another, 0.416 -> 0.153 mm (stop-and-go
0.091): its skin near the outline's sides also moves up or down the frame (the camera
looks down on the table), which a match along the rows does not follow. A first pass on
frames scaled down by four, not two, measured 0.091 and 0.135 mm on the same shapes but
left 65 DN of false light beside a synthetic stripe on relief of a 9-pixel period (3 mm
on the limb rig's camera), where two leaves 3 DN.
"""

from __future__ import annotations

from concurrent.futures import ThreadPoolExecutor

import cv2
import numpy as np

MOVED_SIGMAS = 3.0
"""How far apart (in the two frames' noise) the off frames must be for a pixel to have moved."""
REACH_FRACTION = 1.0 / 12.0
"""The largest motion matched between two consecutive frames, as a share of the frame's
width (128 pixels at 1536). At the shipped continuous speed the table turns 6 degrees
from one frame to the next that the laser allows (:func:`~lamina_device.timing.frames_apart`);
a point seen at the frame's side, half its width from the axis, moves a twentieth of the
width; the rest is room for a point nearer the camera, whose image moves further. The
random limb shapes' skin moved 18-60 pixels a frame."""
BLOCK_PX = 5
"""The matcher's window (pixels): small, so that a narrow relief crest is matched itself."""
SMOOTH_SMALL, SMOOTH_LARGE = 8, 256
"""The matcher's penalties per window pixel for a one-pixel and a larger change of motion
between neighbours: a rigid turn's motion is smooth, so a large change costs much."""
STILL_QUARTILE = 0.3186
"""The lower quartile of a normal noise's magnitude, in its standard deviations."""
COARSE_SCALE = 2
"""The first matching pass's frames are scaled down by this."""
FINE_REACH_PX = 16
"""The full-size pass looks this far either side of the first pass's motion."""
MOVED_OPENING_PX = 3
"""Single noisy pixels are not motion: the moved pixels are opened by this square."""


def laser_off_reference(before: np.ndarray, lit: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Return the room light of a laser-on frame taken between two laser-off frames.

    Args:
        before: the laser-off frame before the laser-on frame (uint8 or uint16).
        lit: the laser-on frame.
        after: the laser-off frame after it.

    Returns:
        A frame like ``before``: each laser-off frame shifted along its rows to the
        laser-on frame's instant (:func:`row_motion_px`), then combined
        (:func:`combine_off_frames`).
    """
    reach = reach_px(before.shape[1])
    # The matcher finds no motion within a reach of its part's sides: twice the reach.
    box = moving_box(before, after, 2 * reach)
    if box is None:
        return combine_off_frames(before, after)
    rows, cols = box

    def at_lit_instant(frame: np.ndarray) -> np.ndarray:
        at = frame.copy()
        motion = row_motion_px(lit[rows, cols], frame[rows, cols], reach)
        at[rows, cols] = shift_along_rows(frame[rows, cols], motion)
        return at

    # The two matches are independent, and OpenCV lets go of Python's lock while it
    # matches: side by side they take about half the time on two cores (the device runs
    # OpenCV on its calling thread, so without this one core does both, 240 ms a view of
    # a fine-relief limb on a 2-core x86 host against the 125 ms between views).
    with ThreadPoolExecutor(1, thread_name_prefix="room-light") as other:
        after_at = other.submit(at_lit_instant, after)
        before_at = at_lit_instant(before)
        return combine_off_frames(before_at, after_at.result())


def reach_px(width: int) -> int:
    """Return the largest motion matched between consecutive frames of ``width`` pixels."""
    return max(16, round(width * REACH_FRACTION))


def moving_box(before: np.ndarray, after: np.ndarray, margin_px: int) -> tuple[slice, slice] | None:
    """Return the rows and columns where the two laser-off frames differ, widened by
    ``margin_px`` (where a moved pixel came from), or None where nothing moved."""
    moved = _moved(before, after).view(np.uint8)
    kernel = np.ones((MOVED_OPENING_PX, MOVED_OPENING_PX), np.uint8)
    opened = cv2.morphologyEx(moved, cv2.MORPH_OPEN, kernel)
    rows, cols = np.flatnonzero(opened.any(axis=1)), np.flatnonzero(opened.any(axis=0))
    if not len(rows):
        return None
    height, width = before.shape
    return (
        slice(max(0, int(rows[0]) - margin_px), min(height, int(rows[-1]) + margin_px + 1)),
        slice(max(0, int(cols[0]) - margin_px), min(width, int(cols[-1]) + margin_px + 1)),
    )


def row_motion_px(lit: np.ndarray, off: np.ndarray, reach: int) -> np.ndarray:
    """Return how far each pixel's scene moved along its row from ``off`` to ``lit``.

    Matched in two passes, so that the full-size pass searches a few pixels only: the
    frames scaled down by :data:`COARSE_SCALE` over the whole reach, then at full size
    within :data:`FINE_REACH_PX` of that: about half the time of one full-size pass over
    the reach, for the same false light on the limb rig's frames.

    Args:
        lit: the laser-on frame (or a part of it).
        off: a laser-off frame of the same part, a frame or more before or after.
        reach: the largest motion to look for, in pixels, either way.

    Returns:
        A float32 array like ``lit``: the motion ``d`` with ``lit[y, x]`` the scene that
        ``off`` shows at ``[y, x - d]``; 0 where no match was found (and everywhere in a
        part too small to match).
    """
    left, right = _as_8bit(lit, off)
    height, width = left.shape
    small = (width // COARSE_SCALE, height // COARSE_SCALE)
    if min(small) < BLOCK_PX:  # too small to scale down: one full-size pass
        return _matched(left, right, reach)
    coarse = _matched(
        cv2.resize(left, small, interpolation=cv2.INTER_AREA),
        cv2.resize(right, small, interpolation=cv2.INTER_AREA),
        -(-reach // COARSE_SCALE),
    )
    coarse = cv2.resize(coarse * COARSE_SCALE, (width, height), interpolation=cv2.INTER_LINEAR)
    # lit(x) = moved(x - r) = off(x - r - coarse(x - r)): r is small, coarse smooth.
    moved = shift_along_rows(right, coarse)
    return coarse + _matched(left, moved, FINE_REACH_PX)


def _matched(left: np.ndarray, right: np.ndarray, reach: int) -> np.ndarray:
    """Return the disparity ``d`` (pixels) with ``left[y, x]`` matching ``right[y, x - d]``,
    searched within ``reach`` either way (0 where none is found or the frames are too
    small for the matcher's window and reach), median-filtered."""
    half = 16 * -(-reach // 16)  # the matcher counts disparities in sixteens
    height, width = left.shape
    if width <= 2 * half + BLOCK_PX or height < BLOCK_PX:
        return np.zeros(left.shape, np.float32)
    area = BLOCK_PX * BLOCK_PX
    matcher = cv2.StereoSGBM.create(
        minDisparity=-half,
        numDisparities=2 * half,
        blockSize=BLOCK_PX,
        P1=SMOOTH_SMALL * area,
        P2=SMOOTH_LARGE * area,
        disp12MaxDiff=-1,
        uniquenessRatio=0,
        speckleWindowSize=0,
        mode=cv2.STEREO_SGBM_MODE_SGBM_3WAY,
    )
    fixed = matcher.compute(left, right)  # 16ths of a pixel; below the range: no match
    disparity = np.where(fixed < -16 * half, 0, fixed).astype(np.float32) / 16.0
    return cv2.medianBlur(disparity, 5)


def shift_along_rows(frame: np.ndarray, motion: np.ndarray) -> np.ndarray:
    """Return ``frame`` resampled at ``x - motion`` along each row (linear, edges repeated)."""
    height, width = frame.shape
    map_x = np.arange(width, dtype=np.float32)[None, :] - motion
    map_y = np.broadcast_to(np.arange(height, dtype=np.float32)[:, None], frame.shape)
    return cv2.remap(
        frame, map_x, np.ascontiguousarray(map_y), cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_REPLICATE,
    )  # fmt: skip


def combine_off_frames(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Return one room-light frame from two laser-off frames taken around a laser-on frame.

    Where the two agree within their noise, their mean: the room light between them, with
    less noise than either. Where they differ more, something moved across that pixel that
    neither registration nor the mean accounts for (an edge, a silhouette): the brighter of
    the two, which the laser-on frame's own room light, passing from one to the other,
    cannot exceed, so what is left of the motion in the difference is never positive and
    never reads as a stripe.

    Args:
        before: the laser-off frame before the laser-on frame (uint8 or uint16).
        after: the laser-off frame after it.

    Returns:
        A frame like ``before``.
    """
    mean = (before | after) - ((before ^ after) >> 1)  # (b + a + 1) // 2, in their own type
    return np.where(_moved(before, after), np.maximum(before, after), mean)


def _moved(before: np.ndarray, after: np.ndarray) -> np.ndarray:
    """Return where two frames (uint8 or uint16) differ beyond :data:`MOVED_SIGMAS` of
    their noise.

    The noise is read from the smallest quarter of the differences, not their median: a
    target that fills most of the frame moves at most of its pixels.
    """
    difference = cv2.absdiff(before, after)
    sigma = float(np.percentile(difference[::7, ::7], 25)) / STILL_QUARTILE
    return difference > max(MOVED_SIGMAS * sigma, 2.0)


def _as_8bit(lit: np.ndarray, off: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return both frames as uint8 on one scale (the matcher takes 8-bit frames)."""
    if lit.dtype == np.uint8 and off.dtype == np.uint8:
        return np.ascontiguousarray(lit), np.ascontiguousarray(off)
    alpha = 255.0 / max(1.0, float(max(lit.max(), off.max())))
    return cv2.convertScaleAbs(lit, alpha=alpha), cv2.convertScaleAbs(off, alpha=alpha)
