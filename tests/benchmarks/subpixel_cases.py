"""Synthetic stripes with an exact centre line, and the centre finders compared on them.

Each case is one 640-column frame pair whose stripe intensity is a known profile of the
normal distance to a known centre curve (straight and sloped lines, circular arcs),
integrated over each pixel (4 x 4 samples), times a reflectance (a brightness step
whose edge crosses the stripe), times the laser's speckle, over ambient light, with the
shot and read noise of a simulator preset (``thesis`` or ``harsh``; the harsh preset's
red laser is seen through the luma weights). The truth in every column is the row
where the centre curve crosses the pixel-centre column: not an intensity-weighted
centre, so a method's own bias on curves, steps or saturation shows.

Methods: the centre of gravity over the Otsu run alone (eq. 5.1, p = 1 and 2: the
device's default before issue 21); Gaussian and parabolic three-point peak fits and a
Hessian normal-direction centre (Steger-like), each started from the device's points;
the device's line fit along chains (an option); the device's default (eq. 5.1 with 3
pixels beyond each end of the run weighed in, ``margin_px``, and speckle gaps bridged,
``bridge_px``), alone and with the host's fit along chains (``lamina_shared.centreline``,
what the reconstruction uses), the latter also without its correction of the curve's
pull; and the Horus-style baseline.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import cv2
import numpy as np
from bench_extraction import horus_extract

from lamina_device.extract import ExtractSettings, extract
from lamina_device.sim import NoiseModel
from lamina_device.sim.render import BT601_LUMA, speckle_field
from lamina_shared.centreline import refine_rows

WIDTH, HEIGHT = 640, 160
_SUPER = 4  # samples per pixel side
_STEP_PERIOD_PX = 80.0  # columns between two brightness steps
_EDGE_PX = 3  # columns next to a stripe end or gap are not scored (no centre line there)


@dataclass(frozen=True)
class Case:
    """One synthetic stripe: its shape, profile and light."""

    name: str
    shape: str = "line"  # "line" (slope, ripple) or "arcs" (radius_px)
    fwhm_px: float = 3.0
    profile: str = "gaussian"  # or "flat" (a flat top of fwhm_px, soft 0.5 px edges)
    slope: float = 0.08
    radius_px: float = 0.0
    speckle_contrast: float | None = None  # None: the preset's
    peak_scale: float = 1.0  # > 1 saturates
    step_ratio: float = 1.0  # reflectance of the dim side of the steps (1: no steps)
    gaps: bool = False  # occluded stretches of columns


CASES = (
    Case("gaussian 1.5 px", fwhm_px=1.5),
    Case("gaussian 3 px", fwhm_px=3.0),
    Case("gaussian 5 px", fwhm_px=5.0),
    Case("gaussian 8 px", fwhm_px=8.0),
    Case("flat-top 3 px", fwhm_px=3.0, profile="flat"),
    Case("flat-top 6 px", fwhm_px=6.0, profile="flat"),
    Case("sloped 0.6", slope=0.6),
    Case("sloped 1.2", slope=1.2),
    Case("arcs r=10", shape="arcs", radius_px=10.0),
    Case("arcs r=20", shape="arcs", radius_px=20.0),
    Case("arcs r=20, 6 px", shape="arcs", radius_px=20.0, fwhm_px=6.0),
    Case("arcs r=50", shape="arcs", radius_px=50.0),
    Case("arcs r=100", shape="arcs", radius_px=100.0),
    Case("arcs r=500", shape="arcs", radius_px=500.0),
    Case("speckle 0.3", speckle_contrast=0.3),
    Case("speckle 0.6", speckle_contrast=0.6),
    Case("saturated x2.5", peak_scale=2.5),
    Case("brightness steps 0.4", step_ratio=0.4),
    Case("occlusion gaps", gaps=True),
)
PRESETS = {"thesis": NoiseModel.thesis(), "harsh": NoiseModel.harsh()}


@dataclass(frozen=True)
class Frames:
    """One case's frames and truth: ``truth`` per column (NaN: no scored stripe)."""

    on: np.ndarray
    off: np.ndarray
    truth: np.ndarray
    step_side: np.ndarray
    """Per column: 1 where a brightness step lies inside the profile (bright side
    above), 0 elsewhere."""
    bend: np.ndarray
    """Per column: +1 on a hill (centre of curvature below), -1 in a valley, 0 straight."""


def _profile(case: Case, distance: np.ndarray) -> np.ndarray:
    """Return the stripe's relative intensity at each normal distance (px)."""
    if case.profile == "flat":
        half, soft = case.fwhm_px / 2, 0.5 * math.sqrt(2.0)
        erf = np.vectorize(math.erf, otypes=[float])
        return 0.5 * (erf((distance + half) / soft) - erf((distance - half) / soft))
    sigma = case.fwhm_px / (2 * math.sqrt(2 * math.log(2)))
    return np.exp(-0.5 * (distance / sigma) ** 2)


def _arcs(radius_px: float) -> list[tuple[float, float, float]]:
    """Return (centre column, centre row, +1 hill / -1 valley) of arcs tiling the frame."""
    half_span = radius_px * math.sin(math.radians(55.0))
    half_span = min(half_span, 280.0)
    pitch = 2 * half_span + 12
    arcs = []
    x, sign = half_span + 8, 1.0
    while x + half_span < WIDTH - 4:
        sag = radius_px - math.sqrt(radius_px**2 - half_span**2)
        centre_row = HEIGHT / 2 + sign * (radius_px - sag / 2)
        arcs.append((x, centre_row, sign))
        x, sign = x + pitch, -sign
    return arcs


def _geometry(
    case: Case, x: np.ndarray, y: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return the normal distance at the samples, the true row per column (NaN: none)
    and the side the centre curve bends to (:attr:`Frames.bend`)."""
    cols = np.arange(WIDTH, dtype=np.float64)
    if case.shape == "arcs":
        r = case.radius_px
        distance = np.full(x.shape, np.inf)
        truth, bend = np.full(WIDTH, np.nan), np.zeros(WIDTH)
        for cx, cy, sign in _arcs(r):
            half_span = min(r * math.sin(math.radians(55.0)), 280.0)
            inside = np.abs(x - cx) <= half_span
            d = np.abs(np.hypot(x - cx, y - cy) - r)
            # only the half of the circle the arc is on
            d = np.where(inside & (sign * (cy - y) > 0), d, np.inf)
            distance = np.minimum(distance, d)
            on_arc = np.abs(cols - cx) <= half_span - _EDGE_PX
            truth[on_arc] = cy - sign * np.sqrt(r * r - (cols[on_arc] - cx) ** 2)
            bend[on_arc] = sign
        return distance, truth, bend
    ripple = 2.0 * np.sin(cols / 29.0) if case.slope < 0.3 else 0.0 * cols
    start = HEIGHT / 2 - case.slope * WIDTH / 2
    if case.slope * WIDTH > HEIGHT - 20:  # steep: a zigzag that stays in the frame
        period = (HEIGHT - 30) / case.slope
        phase = np.mod(cols, 2 * period)
        line = 15 + case.slope * np.where(phase < period, phase, 2 * period - phase)
        corner = np.minimum(np.mod(cols, period), period - np.mod(cols, period)) > 8
    else:
        line = start + case.slope * cols + ripple
        corner = np.ones(WIDTH, bool)
    # Normal distance of a sample to the (locally straight) line through its column.
    index = np.clip(np.rint(x).astype(np.intp), 0, WIDTH - 1)
    slope_local = np.gradient(line)[index]
    distance = (y - line[index] - slope_local * (x - index)) / np.sqrt(1 + slope_local**2)
    truth = np.where(corner, line, np.nan)
    truth[:_EDGE_PX] = truth[-_EDGE_PX:] = np.nan
    return distance, truth, np.zeros(WIDTH)


def render(case: Case, preset: str, seed: int = 0, model: NoiseModel | None = None) -> Frames:
    """Return the frames and truth of ``case`` under the named noise preset (or ``model``)."""
    noise = model or PRESETS[preset]
    rng = np.random.default_rng(seed)
    offsets = (np.arange(_SUPER) + 0.5) / _SUPER - 0.5
    ys = (np.arange(HEIGHT)[:, None] + offsets[None, :]).ravel()
    xs = (np.arange(WIDTH)[:, None] + offsets[None, :]).ravel()
    y, x = np.meshgrid(ys, xs, indexing="ij")
    distance, truth, bend = _geometry(case, x, y)
    light = _profile(case, distance)
    step_side = np.zeros(WIDTH)
    if case.step_ratio != 1.0:
        # A sawtooth of reflectance: it climbs slowly from the dim level back to 1 over
        # 80 columns, then drops along a steep edge (2 rows per column). Every edge has
        # its bright side above where it crosses the stripe, so a fit along the stripe
        # cannot average one step's pull against the next one's.
        phase = np.mod(x + 0.5 * (y - HEIGHT / 2), _STEP_PERIOD_PX) / _STEP_PERIOD_PX
        light = light * (case.step_ratio + (1.0 - case.step_ratio) * phase)
        q = np.mod(np.arange(WIDTH) + 0.5 * (np.nan_to_num(truth) - HEIGHT / 2), _STEP_PERIOD_PX)
        near = np.minimum(q, _STEP_PERIOD_PX - q)
        step_side = np.where(near <= case.fwhm_px / 2, 1.0, 0.0)
    laser = light.reshape(HEIGHT, _SUPER, WIDTH, _SUPER).mean(axis=(1, 3))
    if case.gaps:
        gaps = np.zeros(WIDTH, bool)
        for start in rng.integers(20, WIDTH - 40, 12):
            gaps[start : start + rng.integers(3, 20)] = True
        laser[:, gaps] = 0.0
        hidden = np.convolve(gaps, np.ones(2 * _EDGE_PX + 1), "same") > 0
        truth = np.where(hidden, np.nan, truth)
    contrast = noise.speckle_contrast
    if case.speckle_contrast is not None and contrast > 0:  # a noise-free model keeps none
        contrast = case.speckle_contrast
    speckle = speckle_field(
        rng, laser.shape, contrast, noise.speckle_grain_px, noise.speckle_lognormal
    )
    through_luma = 1.0 if noise.laser_rgb is None else float(np.dot(noise.laser_rgb, BT601_LUMA))
    peak_dn = noise.laser_peak_dn * noise.albedo * through_luma * case.peak_scale
    ambient = noise.ambient_dn * noise.albedo * (1.0 + 0.3 * np.linspace(-1, 1, WIDTH))[None, :]
    frames = []
    for expected in (ambient + peak_dn * laser * speckle, ambient + 0.0 * laser):
        sd = np.sqrt(noise.read_noise_dn**2 + noise.shot_gain_dn * expected)
        noisy = expected + sd * rng.standard_normal(expected.shape)
        frames.append(np.clip(np.rint(noisy), 0, 255).astype(np.uint8))
    return Frames(frames[0], frames[1], truth, step_side, bend)


# --- the centre finders ------------------------------------------------------------------

Found = tuple[np.ndarray, np.ndarray]
Method = Callable[[np.ndarray, np.ndarray], Found]


def _device(settings: ExtractSettings) -> Method:
    """Return the device's extraction with ``settings`` as a method."""

    def run(on: np.ndarray, off: np.ndarray) -> Found:
        points = extract(on, off, settings)
        return points.cols, points.rows.astype(np.float64)

    return run


def _host_refined(settings: ExtractSettings, correct_pull: bool = True) -> Method:
    """Return the device's points (with ``settings``) refined on the host along their chains."""

    def run(on: np.ndarray, off: np.ndarray) -> Found:
        points = extract(on, off, settings)
        fitted = refine_rows(points.cols, points.rows, points.width, correct_pull=correct_pull)
        return points.cols, fitted

    return run


def _peak_fit(kind: str) -> Method:
    """Return a three-point peak fit (``gaussian`` or ``parabolic``) about the device's points."""

    def run(on: np.ndarray, off: np.ndarray) -> Found:
        points = extract(on, off)
        diff = cv2.subtract(on, off).astype(np.float64)
        cols = points.cols.astype(np.intp)
        height = diff.shape[0]
        near = np.clip(np.rint(points.rows).astype(np.intp), 2, height - 3)
        window = near[:, None] + np.arange(-2, 3)[None, :]
        peak = window[np.arange(cols.size), np.argmax(diff[window, cols[:, None]], axis=1)]
        peak = np.clip(peak, 1, height - 2)
        a, b, c = (diff[peak + k, cols] for k in (-1, 0, 1))
        if kind == "gaussian":
            a, b, c = (np.log(np.maximum(v, 1.0)) for v in (a, b, c))
        denominator = a - 2 * b + c
        curved = denominator < 0  # a maximum: the parabola opens downward
        shift = np.where(curved, 0.5 * (a - c) / np.where(curved, denominator, -1.0), 0.0)
        return points.cols, peak + np.clip(shift, -1.0, 1.0)

    return run


def steger(on: np.ndarray, off: np.ndarray) -> Found:
    """Return a Hessian normal-direction centre (Steger-like) started from the device's points.

    The difference image is smoothed with a Gaussian matched to the stripe (sigma = the
    median run width over 2 sqrt 3); at each point's pixel the Hessian's most negative
    eigenvector is the stripe normal, the second-order Taylor expansion along it gives
    the sub-pixel ridge point, and the ridge's tangent carries it to the point's column.
    """
    points = extract(on, off)
    if points.cols.size == 0:
        return points.cols, points.rows.astype(np.float64)
    sigma = max(1.0, float(np.median(points.width)) / (2 * math.sqrt(3)))
    image = cv2.GaussianBlur(cv2.subtract(on, off).astype(np.float32), (0, 0), sigma)
    g = image.astype(np.float64)
    height, width = g.shape
    x = np.clip(points.cols.astype(np.intp), 1, width - 2)
    y = np.clip(np.rint(points.rows).astype(np.intp), 1, height - 2)
    for _ in range(2):  # a second step from the pixel nearest the first estimate
        rx = 0.5 * (g[y, x + 1] - g[y, x - 1])
        ry = 0.5 * (g[y + 1, x] - g[y - 1, x])
        rxx = g[y, x + 1] - 2 * g[y, x] + g[y, x - 1]
        ryy = g[y + 1, x] - 2 * g[y, x] + g[y - 1, x]
        rxy = 0.25 * (g[y + 1, x + 1] - g[y + 1, x - 1] - g[y - 1, x + 1] + g[y - 1, x - 1])
        mean, spread = 0.5 * (rxx + ryy), np.hypot(0.5 * (rxx - ryy), rxy)
        lam = mean - spread
        nx, ny = lam - ryy, rxy
        flat = np.hypot(nx, ny) < 1e-9
        nx, ny = np.where(flat, 0.0, nx), np.where(flat, 1.0, ny)
        norm = np.hypot(nx, ny)
        nx, ny = nx / norm, ny / norm
        t = np.where(lam < 0, -(rx * nx + ry * ny) / np.where(lam < 0, lam, -1.0), 0.0)
        ny_safe = np.where(np.abs(ny) < 0.2, np.copysign(0.2, ny), ny)
        row = y + np.clip(t / ny_safe, -2.0, 2.0)
        y = np.clip(np.rint(row).astype(np.intp), 1, height - 2)
    return points.cols, row


RUN_ALONE = ExtractSettings(margin_px=0, bridge_px=0)
DEFAULT_AND_FIT = "default + fit"
"""The product's default: the device's default centre, fitted along chains by the host."""
METHODS: dict[str, Method] = {
    "COG p=1, run": _device(RUN_ALONE),
    "COG p=2, run": _device(ExtractSettings(power=2.0, margin_px=0, bridge_px=0)),
    "Gauss 3-pt": _peak_fit("gaussian"),
    "parabola 3-pt": _peak_fit("parabolic"),
    "Hessian (Steger)": steger,
    "line fit s2 (dev.)": _device(ExtractSettings(smooth_sigma_px=2.0, margin_px=0, bridge_px=0)),
    "device default": _device(ExtractSettings()),
    DEFAULT_AND_FIT: _host_refined(ExtractSettings()),
    "fit, no pull": _host_refined(ExtractSettings(), correct_pull=False),
    "Horus-style": lambda on, off: horus_extract(on, off),
}


@dataclass(frozen=True)
class Scored:
    """A method's errors on one case (px; + is downward)."""

    bias_px: float
    rms_px: float
    beyond_1px: float
    found: float


def score(frames: Frames, found: Found) -> Scored:
    """Return the bias and RMS of the points within 1 px, the share beyond, and coverage.

    On brightness steps the bias is the mean error over the columns where the step lies
    inside the profile; on arcs the mean error toward the centre of curvature; elsewhere
    the mean error over every scored column.
    """
    cols, rows = found
    truth = frames.truth[cols.astype(np.intp)]
    scored = np.isfinite(truth)
    error = rows[scored] - truth[scored]
    good = np.abs(error) <= 1.0
    columns = int(np.isfinite(frames.truth).sum())
    if not good.any():
        return Scored(math.nan, math.nan, 1.0, 0.0)
    side = frames.step_side[cols.astype(np.intp)][scored]
    if np.any(side != 0):
        at_step = good & (side != 0)
        bias = abs(float(np.mean(error[at_step]))) if at_step.any() else math.nan
    elif np.any(frames.bend != 0):  # signed toward the centre of curvature
        bend = frames.bend[cols.astype(np.intp)][scored]
        bias = abs(float(np.mean((error * bend)[good])))
    else:
        bias = abs(float(np.mean(error[good])))
    return Scored(
        bias, float(np.sqrt(np.mean(error[good] ** 2))), 1.0 - float(good.mean()),
        float(good.sum()) / max(columns, 1),
    )  # fmt: skip
