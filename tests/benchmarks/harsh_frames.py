"""Harsh simulated views with known stripe rows: the one place tests and benchmarks get them.

Issue 10's camera: a Pi sensor at raised gain (read noise ~2.5 DN, shot variance ~0.5 x
signal), bright uneven ambient light, strong speckle, and a red laser that shows only
weakly in the luma frame (peak ~55 DN). The views are the ones where a weak or short
stripe lets noise through: a sphere seen near its top and bottom, a thin cylinder, a
flat ellipsoid at grazing angles, and stripe-free views (the sheet passes above the
object) for the false-point rate. The anatomical views (issue 21) are the per-point
accuracy's test: the code-built phantoms (a face, a hand, a foot, a forearm, a stump's
rounded end, a bone, a torus), whose stripes bend, break at occlusions and cross
creases of shading.

``noise_model(preset)`` names the light and noise model. The default is the
simulator's own ``NoiseModel.harsh()`` (RGB sensor read as luma, halo, lens); the
``issue10`` model is the grey-level approximation the extraction was first tuned on,
kept so both can be compared.

Truth comes from the renderer itself: the same view rendered without noise, speckle or
ambient light, with the laser at 250 DN; its intensity-weighted centre in each column
(per run, where a column holds several) is the true stripe row.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from functools import cache

import numpy as np

from lamina_device.sim import NoiseModel, Rig, SimScene, parse_object

PRESETS = {
    # Issue 10's figures: read noise 1.5-3 DN, shot variance 0.3-0.6 x signal, ambient
    # 45-90 DN with 30-70 % non-uniformity, speckle contrast 0.3-0.6, weak red laser in luma.
    "issue10": NoiseModel(
        read_noise_dn=2.5,
        shot_gain_dn=0.5,
        ambient_dn=85.0,
        laser_peak_dn=55.0,
        speckle_contrast=0.5,
        ambient_gradient=(0.5, -0.3),
    ),
    "harsh": NoiseModel.harsh(),
    "thesis": NoiseModel.thesis(),
}
DEFAULT_PRESET = "harsh"

_TRUTH_LASER_DN = 250.0  # noise-free truth render: as bright as 8 bits allow, for precision
TRUTH_MIN_DN = 4.0
"""A column has a true stripe where the noise-free laser peak reaches this (frame DN)."""

WEAK_VIEWS = (
    # (name, object spec, angle_deg, z_mm): weak, short or partial stripes
    ("sphere near top", "sphere:d=20", 0.0, 8.5),
    ("sphere near top", "sphere:d=20", 90.0, 9.0),
    ("sphere near bottom", "sphere:d=20", 45.0, -8.5),
    ("sphere near bottom", "sphere:d=20", 200.0, -9.0),
    ("thin cylinder", "cylinder:d=3", 0.0, 5.0),
    ("thin cylinder", "cylinder:d=2,x=6,y=3", 30.0, 10.0),
    ("grazing ellipsoid", "ellipsoid:a=18,b=4,c=30", 80.0, 0.0),
    ("grazing ellipsoid", "ellipsoid:a=18,b=4,c=30", 265.0, 6.0),
)
GOOD_VIEWS = (
    ("cylinder wall", "cylinder:d=19.05", 0.0, 10.0),
    ("ellipsoid equator", "ellipsoid:a=12,b=9,c=20", 30.0, 0.0),
    ("ellipsoid equator", "ellipsoid:a=12,b=9,c=20", 150.0, 2.0),
)
ANATOMICAL_VIEWS = (
    ("face, nose on", "bust", 0.0, 8.0),
    ("face, cheek", "bust", 60.0, 12.0),
    ("hand, fingers", "hand", 20.0, 10.0),
    ("foot, ankle", "foot", 120.0, 4.0),
    ("forearm, belly", "arm", 200.0, 7.0),
    ("stump, rounded end", "stump", 300.0, 14.0),
    ("bone, waist", "bone", 45.0, 8.0),
    ("torus", "ring", 90.0, 6.0),
)
STRIPE_FREE_OBJECT = ("sphere above the sheet", "sphere:d=20", 0.0, 14.0)
"""The sheet passes 4 mm above the top of the sphere: the laser lights nothing in view."""


@dataclass(frozen=True)
class View:
    """One rendered view: its frames, the true stripe rows and the rig that made them.

    ``truth_rows`` is (K, W): up to K true stripe rows per column (NaN where fewer);
    ``truth_top`` and ``truth_bottom`` bound each true stripe's band (the rows where
    it exceeds 10 % of its column's peak); ``truth_peak_dn`` is each column's
    noise-free laser peak in the frame's DN.
    """

    name: str
    on: np.ndarray
    off: np.ndarray
    truth_rows: np.ndarray
    truth_top: np.ndarray
    truth_bottom: np.ndarray
    truth_peak_dn: np.ndarray
    rig: Rig


def noise_model(preset: str = DEFAULT_PRESET) -> NoiseModel:
    """Return the named light and noise model (see :data:`PRESETS`)."""
    return PRESETS[preset]


@cache
def _scene(spec: str, preset: str, rig: Rig, seed: int, truth: bool) -> SimScene:
    """Return the (cached) scene; ``truth`` renders the laser alone, noise-free."""
    noise = noise_model(preset)
    if truth:
        noise = replace(
            noise, read_noise_dn=0.0, shot_gain_dn=0.0, speckle_contrast=0.0, ambient_dn=0.0,
            background_dn=0.0, laser_peak_dn=_TRUTH_LASER_DN, halo_fraction=0.0,
        )  # fmt: skip
    return SimScene(rig, parse_object(spec), noise, seed)


def _column_truth(laser: np.ndarray, min_dn: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (3, K, W) centre, top and bottom rows of every true stripe run, and the peaks.

    A run is where the noise-free laser exceeds 10 % of its column's peak: the band a
    point on the stripe may fall in, however speckle scatters it; its centre is the
    intensity-weighted one.
    """
    height, width = laser.shape
    peak = laser.max(axis=0)
    found: list[list[tuple[float, float, float]]] = [[] for _ in range(width)]
    rows = np.arange(height, dtype=np.float64)
    for col in np.flatnonzero(peak >= min_dn):
        column = laser[:, col]
        above = column >= max(0.1 * peak[col], min_dn)
        edges = np.flatnonzero(np.diff(np.concatenate([[0], above.view(np.int8), [0]])))
        for start, stop in zip(edges[0::2], edges[1::2], strict=True):
            w = column[start:stop]
            centre = float((rows[start:stop] * w).sum() / w.sum())
            found[col].append((centre, float(start), float(stop - 1)))
    depth = max(1, max(len(c) for c in found))
    truth = np.full((3, depth, width), np.nan)
    for col, runs in enumerate(found):
        if runs:
            truth[:, : len(runs), col] = np.array(runs).T
    return truth, peak


def render_view(
    name: str,
    spec: str,
    angle_deg: float,
    z_mm: float,
    preset: str = DEFAULT_PRESET,
    rig: Rig | None = None,
    seed: int = 0,
    key: tuple[object, ...] = (),
) -> View:
    """Return the laser-on and laser-off frames of one view with its true stripe rows."""
    rig = rig or Rig()
    scene = _scene(spec, preset, rig, seed, False)
    on = scene.render("object", angle_deg, z_mm, True, key)
    off = scene.render("object", angle_deg, z_mm, False, key)
    laser = _scene(spec, preset, rig, seed, True).render("object", angle_deg, z_mm, True)
    scale = noise_model(preset).laser_peak_dn / _TRUTH_LASER_DN
    laser_dn = laser.astype(np.float64) * scale
    (centre, top, bottom), peak = _column_truth(laser_dn, TRUTH_MIN_DN)
    return View(name, on, off, centre, top, bottom, peak, rig)


def weak_views(preset: str = DEFAULT_PRESET, rig: Rig | None = None) -> list[View]:
    """Return the weak, short and grazing stripe views."""
    return [render_view(*v, preset=preset, rig=rig) for v in WEAK_VIEWS]


def good_views(preset: str = DEFAULT_PRESET, rig: Rig | None = None) -> list[View]:
    """Return views with a long, well-lit stripe."""
    return [render_view(*v, preset=preset, rig=rig) for v in GOOD_VIEWS]


def anatomical_views(preset: str = DEFAULT_PRESET, rig: Rig | None = None) -> list[View]:
    """Return views of the anatomy-like phantoms (``sim.phantoms``)."""
    return [render_view(*v, preset=preset, rig=rig) for v in ANATOMICAL_VIEWS]


def stripe_free_views(
    count: int, preset: str = DEFAULT_PRESET, rig: Rig | None = None
) -> list[View]:
    """Return ``count`` stripe-free views, each with its own noise."""
    name, spec, angle_deg, z_mm = STRIPE_FREE_OBJECT
    return [
        render_view(name, spec, angle_deg, z_mm, preset=preset, rig=rig, key=(k,))
        for k in range(count)
    ]


@dataclass(frozen=True)
class Score:
    """How a set of extracted points compares with the truth."""

    points: int
    outliers: int
    """Points more than ``tolerance_px`` from every true stripe row of their column."""
    off_stripe: int
    """Points more than ``tolerance_px`` outside every true stripe's band: noise points,
    not the scatter speckle gives points on the stripe."""
    truth_columns: int
    rms_px: float
    """RMS error of the points that are not outliers, px."""
    rms_mm: float
    """The same in the laser plane, mm."""
    beyond_1mm: int = 0
    """Points more than 1 mm from the true stripe point of their column in the laser plane
    (points without a true stripe in their column among them)."""
    good_mm: int = 0
    """Points within :data:`GOOD_MM` of the true stripe point in the laser plane."""
    rms_good_mm: float = float("nan")
    """RMS error of those points, mm."""

    @property
    def outlier_fraction(self) -> float:
        """Return outliers over points (0 without points)."""
        return self.outliers / self.points if self.points else 0.0

    @property
    def off_stripe_fraction(self) -> float:
        """Return points off every true stripe band over points (0 without points)."""
        return self.off_stripe / self.points if self.points else 0.0

    @property
    def found_fraction(self) -> float:
        """Return good points over the columns with a true stripe."""
        return (self.points - self.outliers) / self.truth_columns if self.truth_columns else 0.0


GOOD_MM = 0.25
"""A point this close to the truth in the laser plane counts as good (issue 21's measure)."""


def errors_px(view: View, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Return each point's distance to the nearest true stripe row of its column (inf if none)."""
    truth = view.truth_rows[:, cols.astype(np.intp)]
    error = np.abs(truth - rows.astype(np.float64)[None, :])
    return np.min(np.where(np.isnan(error), np.inf, error), axis=0)


def off_stripe_px(view: View, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Return each point's distance outside the nearest true stripe band (0 inside, inf if none)."""
    index = cols.astype(np.intp)
    r = rows.astype(np.float64)[None, :]
    outside = np.maximum(view.truth_top[:, index] - r, r - view.truth_bottom[:, index])
    return np.min(np.where(np.isnan(outside), np.inf, np.maximum(outside, 0.0)), axis=0)


def _plane_mm(rig: Rig, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Return image points mapped into the laser plane (mm)."""
    return rig.backproject_to_plane(np.stack([cols, rows], axis=1).astype(np.float64))


def score(
    views: list[View], found: list[tuple[np.ndarray, np.ndarray]], tolerance_px: float = 1.0
) -> Score:
    """Score the (cols, rows) found in each view against its truth."""
    points = outliers = off_stripe = columns = beyond_1mm = 0
    squares_px: list[np.ndarray] = []
    squares_mm: list[np.ndarray] = []
    good_squares_mm: list[np.ndarray] = []
    for view, (cols, rows) in zip(views, found, strict=True):
        error = errors_px(view, cols, rows)
        good = error <= tolerance_px
        points += cols.size
        outliers += int((~good).sum())
        off_stripe += int((off_stripe_px(view, cols, rows) > tolerance_px).sum())
        columns += int((view.truth_peak_dn >= TRUTH_MIN_DN).sum())
        squares_px.append(error[good] ** 2)
        nearest = view.truth_rows[:, cols[good].astype(np.intp)]
        index = np.nanargmin(np.abs(nearest - rows[good][None, :]), axis=0) if good.any() else []
        true_rows = nearest[index, np.arange(int(good.sum()))]
        found_mm = _plane_mm(view.rig, cols[good], rows[good])
        true_mm = _plane_mm(view.rig, cols[good], true_rows)
        squares_mm.append(np.sum((found_mm - true_mm) ** 2, axis=1))
        # Every point against its nearest true row, in mm; no true row: beyond 1 mm.
        has_truth = np.isfinite(error)
        beyond_1mm += int((~has_truth).sum())
        distance_mm = distances_mm(view, cols[has_truth], rows[has_truth])
        beyond_1mm += int((distance_mm > 1.0).sum())
        good_squares_mm.append(distance_mm[distance_mm <= GOOD_MM] ** 2)
    all_px, all_mm = np.concatenate(squares_px), np.concatenate(squares_mm)
    good_mm = np.concatenate(good_squares_mm)
    rms_px = float(np.sqrt(all_px.mean())) if all_px.size else float("nan")
    rms_mm = float(np.sqrt(all_mm.mean())) if all_mm.size else float("nan")
    rms_good = float(np.sqrt(good_mm.mean())) if good_mm.size else float("nan")
    return Score(
        points, outliers, off_stripe, columns, rms_px, rms_mm, beyond_1mm, good_mm.size, rms_good
    )


def distances_mm(view: View, cols: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Return each point's distance (mm, laser plane) to the nearest true point of its column."""
    if cols.size == 0:
        return np.zeros(0)
    found_mm = _plane_mm(view.rig, cols, rows)
    best = np.full(cols.size, np.inf)
    for truth_rows in view.truth_rows:
        true_rows = truth_rows[cols.astype(np.intp)]
        known = np.isfinite(true_rows)
        if known.any():
            true_mm = _plane_mm(view.rig, cols[known], true_rows[known])
            best[known] = np.minimum(best[known], np.linalg.norm(found_mm[known] - true_mm, axis=1))
    return best
