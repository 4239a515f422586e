"""The simulator's renderer: physically honest camera frames of the light-sectioning rig.

Every pixel casts one ray from the pinhole to the nearest surface. A lit pixel gets the
ambient term (albedo x a smooth, non-uniform ambient field x simple shading) and, in the
laser-on frame, a laser term: peak x Gaussian sheet profile in world z x Lambert cosine
toward the laser source x "can the laser reach this point" x multiplicative speckle.
The sensor then adds shot and read noise and quantises to 8 bits. The non-uniform ambient
(gradient, vignette, a soft shadow) is there because the thesis removes exactly that kind
of background before finding the stripe (section 5.2.1); the stripe centre is what a
centre-of-gravity extractor (section 5.2.3) must find.

Colour presets (``NoiseModel.harsh``) render the red, green and blue channels with their
own noise, the laser almost only in red, and hand extraction the frame the Pi camera
backend reads: the Y plane of YUV420, BT.601 luma of the RGB the ISP formed. The stripe
is then about a third as bright in Y as in R, while the room light is not dimmed at all.
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace

import cv2
import numpy as np

from lamina_device.sim.objects import SceneObject, cylinder, grooved_cylinder, section_edges
from lamina_device.sim.rig import Rig
from lamina_device.sim.texture import Textured
from lamina_shared.presets import NOISE_PRESETS, make_preset

__all__ = [
    "BLUR_SAMPLES",
    "BT601_LUMA",
    "NOISE_PRESETS",
    "ROLLING_BANDS",
    "Exposure",
    "NoiseModel",
    "SimScene",
    "ambient_field",
    "laser_reaches",
    "laser_reaches_edges",
    "luma",
    "speckle_field",
]

BT601_LUMA = np.array([0.299, 0.587, 0.114])
"""Weights of R, G, B in the Y plane the Pi camera's YUV420 stream carries (BT.601)."""

ROLLING_BANDS = 16
"""Row bands of a moving frame, each exposed at its own time (the rolling shutter): 54 rows
of the limb camera, 0.5 ms of its 8 ms read-out."""
BLUR_SAMPLES = 4
"""Poses averaged across each band's exposure for the stripe's motion blur."""
_BLUR_REACH_MM = 3.0  # the sheet's reach plus how far a hit may move in z within a blur
_BLUR_REACH_PX = 6  # columns a hit near the sheet may move sideways within a blur
_VIEW_CACHE_SIZE = 4
_SHEET_REACH_SIGMAS = 5.0  # beyond 5 sigma the sheet adds < 1e-5 of its peak
_SLAB_SIGMAS = 0.5  # lit-test outlines are sliced every half sigma of sheet height
_MIN_FACING = 0.05  # the lit test's forgiveness stops growing toward grazing incidence here
_GRID_SAMPLES = 64  # samples per pixel on the board: edges land to ~1/64 px
_GRID_LATTICE_STEP = 39  # coprime to 64 and near 64 / golden ratio: well-spread samples


@dataclass(frozen=True)
class NoiseModel:
    """Light levels and noise of the simulated camera; defaults are the thesis-like model."""

    read_noise_dn: float = 1.5
    shot_gain_dn: float = 0.15  # DN per photo-electron: shot variance = gain x signal (DN^2)
    speckle_contrast: float = 0.5  # std / mean of the multiplicative speckle
    speckle_grain_px: float = 1.0  # Gaussian sigma of the speckle correlation, px
    laser_peak_dn: float = 170.0  # stripe peak on a surface facing the laser squarely
    albedo: float = 0.8
    ambient_dn: float = 70.0  # a white (albedo 1) surface facing the lamp, mid-image
    background_dn: float = 22.0  # the box interior beyond the object (no laser there)
    ambient_gradient: tuple[float, float] = (0.25, -0.15)  # fractional change across u, v
    vignette: float = 0.2  # fractional fall-off at the image corners
    shadow_depth: float = 0.35  # soft shadow, like the one the thesis shows (figure 5.3)
    shadow_centre_frac: tuple[float, float] = (0.15, 0.85)  # (u, v) as fractions of the size
    shadow_radius_frac: float = 0.2
    grid_white_dn: float = 190.0  # the board is photographed with its own exposure
    grid_black_dn: float = 25.0
    grid_paper_margin_mm: float = 3.0  # white paper beyond the outer squares
    speckle_lognormal: bool = False  # log-normal speckle instead of the exponential mixture
    halo_fraction: float = 0.0  # share of the stripe's light scattered into a broad halo
    halo_sigma_px: float = 12.0  # Gaussian sigma of that halo
    lens_division_k: float = 0.0  # the lens's radial distortion; SimScene gives it to its rig
    # None renders one grey channel (thesis); otherwise R, G, B responses to the laser,
    # and the frame is the BT.601 luma of separately exposed R, G and B channels.
    laser_rgb: tuple[float, float, float] | None = None
    ambient_rgb: tuple[float, float, float] = (1.0, 1.0, 1.0)  # room light, R, G, B

    @classmethod
    def thesis(cls) -> NoiseModel:
        """Return the default model: ~0.05 mm RMS per-point scatter in the laser plane."""
        return cls()

    @classmethod
    def harsh(cls) -> NoiseModel:
        """Return a Pi camera at analog gain ~6 in a lit room, seen through a real lens.

        The values sit inside the ranges issue #10 gives for such a camera. Within them
        the extraction's noise share falls off a cliff (Otsu's level leaves the noise), so
        they were set where Lamina's extraction at the time of the issue finds 25-50 % of
        its points in the noise on these phantoms and the cylinder, as the issue saw on
        objects rendered by an independent simulator (23-65 %), rather than past the cliff
        on either side:

        - read noise 2.5 DN (range 1.5-3) and shot variance 0.40 x signal (0.3-0.6): the
          per-channel noise of analog gain ~6;
        - ambient: a white surface facing the lamp reads 110 DN, the box beyond 70 DN: the
          laser-off luma averages ~52 DN (range 45-90), and gradient, vignette and a soft
          shadow make it ~60 % non-uniform (range 30-70 %);
        - log-normal speckle of contrast 0.45 (0.3-0.6), grains of 1.2 px: partially
          developed speckle seen through a lens that averages a few grains per pixel;
        - 40 % of the stripe's light scattered into a halo of 20 px sigma: ~4 % of the
          stripe's peak at its centre, ~2 % at 15-40 px (sub-surface and lens scatter);
        - barrel distortion k = -0.02 of the division model at the half diagonal (~4 px
          at the image corners), which ``lamina scan --distortion`` can estimate;
        - the red laser reaches green and blue pixels at 10 % and 3 % (Bayer filter
          cross-talk at 650 nm); the room light is warm (1, 0.95, 0.8). In the luma the
          stripe keeps ~36 % of its red peak of 150 DN, the ambient ~93 % of its level.
        """
        return cls(
            read_noise_dn=2.5,
            shot_gain_dn=0.40,
            speckle_contrast=0.45,
            speckle_grain_px=1.2,
            speckle_lognormal=True,
            laser_peak_dn=150.0,
            ambient_dn=110.0,
            background_dn=70.0,
            ambient_gradient=(0.35, -0.25),
            vignette=0.3,
            shadow_depth=0.3,
            halo_fraction=0.4,
            halo_sigma_px=20.0,
            lens_division_k=-0.02,
            laser_rgb=(1.0, 0.1, 0.03),
            ambient_rgb=(1.0, 0.95, 0.8),
        )

    @classmethod
    def wide(cls) -> NoiseModel:
        """Return the harsh camera behind a wide-angle lens: barrel distortion k = -0.1 of the
        division model at the half diagonal, five times the harsh preset's (an image corner
        sees what a pinhole would image 11 % further out: ~100 px on the limb camera)."""
        return replace(cls.harsh(), lens_division_k=-0.1)

    @classmethod
    def none(cls) -> NoiseModel:
        """Return a noise-free model (no speckle, shot or read noise); ambient stays."""
        return cls(read_noise_dn=0.0, shot_gain_dn=0.0, speckle_contrast=0.0)

    @classmethod
    def preset(cls, name: str) -> NoiseModel:
        """Return the model named ``name`` (one of ``NOISE_PRESETS``)."""
        makers: dict[str, Callable[[], NoiseModel]] = {n: getattr(cls, n) for n in NOISE_PRESETS}
        return make_preset("noise", name, makers)


def _stable_seed(*parts: object) -> int:
    """Return a 64-bit seed from the repr of ``parts`` (stable across runs, unlike hash())."""
    return int.from_bytes(hashlib.sha256(repr(parts).encode()).digest()[:8], "little")


def ambient_field(image_size: tuple[int, int], noise: NoiseModel) -> np.ndarray:
    """Return the (H, W) smooth ambient multiplier: gradient x vignette x soft shadow."""
    w, h = image_size
    y, x = np.mgrid[0:h, 0:w].astype(float)
    x, y = x / (w - 1) - 0.5, y / (h - 1) - 0.5
    gradient = 1.0 + noise.ambient_gradient[0] * x + noise.ambient_gradient[1] * y
    vignette = 1.0 - noise.vignette * (x * x + y * y) / 0.5
    sx, sy = (c - 0.5 for c in noise.shadow_centre_frac)
    blob = np.exp(-((x - sx) ** 2 + (y - sy) ** 2) / (2.0 * noise.shadow_radius_frac**2))
    return gradient * vignette * (1.0 - noise.shadow_depth * blob)


def speckle_field(
    rng: np.random.Generator,
    shape: tuple[int, int],
    contrast: float,
    grain_px: float,
    lognormal: bool = False,
) -> np.ndarray:
    """Return unit-mean multiplicative speckle with the given contrast and grain size.

    ``lognormal`` gives exp(s g - s^2 / 2) of a smooth unit Gaussian field g, with
    s^2 = ln(1 + contrast^2): partially developed speckle, heavier-tailed than the mixture.
    """
    if contrast <= 0.0:
        return np.ones(shape)
    if lognormal:
        return _lognormal_speckle(rng, shape, contrast, grain_px)
    # Fully developed speckle is |low-passed complex Gaussian field|^2 (exponential, contrast
    # 1); mixing it with a constant keeps the mean at 1 and sets the contrast.
    ksize = 2 * math.ceil(3.0 * grain_px) + 1
    field = rng.standard_normal((2, *shape))
    re = cv2.GaussianBlur(field[0], (ksize, ksize), grain_px)
    im = cv2.GaussianBlur(field[1], (ksize, ksize), grain_px)
    k1 = cv2.getGaussianKernel(ksize, grain_px)
    expected = 2.0 * float(np.sum(k1**2)) ** 2  # E|k * n|^2 for unit real and imaginary parts
    return (1.0 - contrast) + contrast * (re * re + im * im) / expected


def _lognormal_speckle(
    rng: np.random.Generator, shape: tuple[int, int], contrast: float, grain_px: float
) -> np.ndarray:
    """Return unit-mean log-normal speckle of the given contrast and grain size."""
    ksize = 2 * math.ceil(3.0 * grain_px) + 1
    k1 = cv2.getGaussianKernel(ksize, grain_px)
    blurred = cv2.GaussianBlur(rng.standard_normal(shape), (ksize, ksize), grain_px)
    g = np.asarray(blurred) / float(np.sum(k1**2))  # blurred unit noise: variance (sum k1^2)^2
    s2 = math.log1p(contrast * contrast)
    return np.asarray(np.exp(math.sqrt(s2) * g - 0.5 * s2))


def _noisy(rng: np.random.Generator, expected_dn: np.ndarray, noise: NoiseModel) -> np.ndarray:
    """Return an expected image with shot and read noise added, unquantised."""
    signal = expected_dn
    if noise.shot_gain_dn > 0.0:
        sd = np.sqrt(noise.shot_gain_dn * np.maximum(signal, 0.0))
        signal = signal + sd * rng.standard_normal(signal.shape)
    if noise.read_noise_dn > 0.0:
        signal = signal + noise.read_noise_dn * rng.standard_normal(signal.shape)
    return signal


def _expose(rng: np.random.Generator, expected_dn: np.ndarray, noise: NoiseModel) -> np.ndarray:
    """Add shot and read noise to an expected image, round and clip to uint8."""
    return np.clip(np.rint(_noisy(rng, expected_dn, noise)), 0, 255).astype(np.uint8)


def luma(rgb: np.ndarray) -> np.ndarray:
    """Return the uint8 Y plane (BT.601, full range) of an (H, W, 3) RGB image in DN."""
    return np.clip(np.rint(np.asarray(rgb, dtype=float) @ BT601_LUMA), 0, 255).astype(np.uint8)


def _expand_ranges(starts: np.ndarray, counts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Return (owner, index) pairs enumerating ``starts[k] + 0..counts[k]-1`` for every k."""
    owner = np.repeat(np.arange(len(counts)), counts)
    first = np.cumsum(counts) - counts
    return owner, np.repeat(starts, counts) + np.arange(owner.size) - np.repeat(first, counts)


def _cross2(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Return the z component of the cross product of (N, 2) vectors."""
    return a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]


def laser_reaches(
    source_xy: np.ndarray,
    points_xy: np.ndarray,
    polygons: list[np.ndarray],
    tol_mm: np.ndarray,
    closed: Sequence[bool] | None = None,
) -> np.ndarray:
    """Return (N,) True where the segment source->point crosses no polygon edge.

    The last ``tol_mm`` (scalar or (N,)) of each segment is ignored, so a point on the
    outline does not shadow itself. ``closed`` flags each polygon closed (the default)
    or an open chain (an open mesh's section), which has no edge from its last point
    back to its first.
    """
    if not polygons:
        return np.ones(len(np.asarray(points_xy).reshape(-1, 2)), dtype=bool)
    if closed is None or all(closed):
        a = np.concatenate(polygons)
        b = np.concatenate([np.roll(p, -1, axis=0) for p in polygons])
    else:
        a = np.concatenate([p if c else p[:-1] for p, c in zip(polygons, closed, strict=True)])
        b = np.concatenate(
            [np.roll(p, -1, axis=0) if c else p[1:] for p, c in zip(polygons, closed, strict=True)]
        )
    return laser_reaches_edges(source_xy, points_xy, a, b, tol_mm)


def laser_reaches_edges(
    source_xy: np.ndarray, points_xy: np.ndarray, a: np.ndarray, b: np.ndarray, tol_mm: np.ndarray
) -> np.ndarray:
    """Return (N,) True where the segment source->point crosses no edge ``a[k]``-``b[k]``.

    As :func:`laser_reaches`, with the section given as its edges' end points (S, 2).
    """
    pts = np.asarray(points_xy, dtype=float).reshape(-1, 2)
    if len(a) == 0 or len(pts) == 0:
        return np.ones(len(pts), dtype=bool)
    src = np.asarray(source_xy, dtype=float)
    ref = np.arctan2(*(a.mean(axis=0) - src)[::-1])

    def bearing(p: np.ndarray) -> np.ndarray:
        """Return the direction of points seen from the source, relative to the outline."""
        # Angles about the source measured from the polygon's direction never wrap unless
        # the outline surrounds the source, which the rig never does.
        ang = np.arctan2(p[:, 1] - src[1], p[:, 0] - src[0]) - ref
        return (ang + np.pi) % (2.0 * np.pi) - np.pi

    ba, bb = bearing(a), bearing(b)
    lo, hi = np.minimum(ba, bb), np.maximum(ba, bb)
    order = np.argsort(lo)
    lo, hi, a, b = lo[order], hi[order], a[order], b[order]
    phi = bearing(pts)
    # Only edges whose bearing interval can contain the point's bearing are candidates.
    start = np.searchsorted(lo, phi - (hi - lo).max(), side="left")
    stop = np.searchsorted(lo, phi, side="right")
    owner, edge = _expand_ranges(start, stop - start)
    keep = hi[edge] >= phi[owner]
    owner, edge = owner[keep], edge[keep]
    ray = pts - src
    length = np.linalg.norm(ray, axis=1)
    ray *= (np.maximum(length - tol_mm, 0.0) / np.maximum(length, 1e-300))[:, None]
    d, e, w = ray[owner], b[edge] - a[edge], a[edge] - src
    den = _cross2(d, e)
    ok = np.abs(den) > 1e-300
    den = np.where(ok, den, 1.0)
    s, u = _cross2(w, e) / den, _cross2(w, d) / den
    blocked = ok & (s >= 0.0) & (s <= 1.0) & (u >= 0.0) & (u <= 1.0)
    reaches = np.ones(len(pts), dtype=bool)
    reaches[owner[blocked]] = False
    return reaches


def _rz(angle_deg: float) -> np.ndarray:
    """Return the 3x3 rotation about +z."""
    c, s = math.cos(math.radians(angle_deg)), math.sin(math.radians(angle_deg))
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, eq=False)
class _Surface:
    """What some pixels' rays hit with the target at one pose, and the room light there."""

    hit: np.ndarray
    """(N,) True where the ray hits the target."""
    p: np.ndarray
    """(H, 3) world points of the hits."""
    normal: np.ndarray
    """(H, 3) world unit normals of the hits."""
    ambient: np.ndarray
    """(N,) the room light each pixel receives, DN."""
    tint: np.ndarray | None
    """(N, 3) reflectance over the plain albedo (textured targets), else None."""
    axis: np.ndarray
    """The turntable axis as the target sees it (shifted by a sway), world mm."""


@dataclass(frozen=True)
class Exposure:
    """When a rolling-shutter frame's rows are exposed, and where the target is meanwhile.

    Row ``r`` is exposed from ``start_s + r * row_s`` for ``exposure_s`` (seconds on the
    simulator's clock); ``pose(t, around)`` is the target's true turntable angle (degrees)
    and sway shift (x, y mm) at time ``t``, for a band of rows exposed around ``around``
    (a mechanical error model may depend on where in its turn the table is then).
    """

    start_s: float
    exposure_s: float
    row_s: float
    pose: Callable[[float, float], tuple[float, tuple[float, float]]]

    def row_start_s(self, row: float) -> float:
        """Return when ``row`` starts its exposure."""
        return self.start_s + row * self.row_s

    def row_middle_s(self, row: float) -> float:
        """Return the middle of ``row``'s exposure."""
        return self.row_start_s(row) + 0.5 * self.exposure_s

    def middle_s(self, rows: int) -> float:
        """Return the middle of the frame's exposure, a frame of ``rows`` rows."""
        return self.row_middle_s(0.5 * (rows - 1))


@dataclass(frozen=True, eq=False)
class _View:
    """Noise-free expected images of one (target, angle, z) geometry."""

    ambient_dn: np.ndarray
    laser_dn: np.ndarray
    halo_dn: np.ndarray | None = None
    tint: np.ndarray | None = None
    """(H, W, 3) surface reflectance over the plain albedo (a textured object), else None."""


class SimScene:
    """The rig with a board, the calibration cylinder and optionally an object to scan."""

    def __init__(
        self,
        rig: Rig,
        obj: SceneObject | None = None,
        noise: NoiseModel | None = None,
        seed: int = 0,
    ) -> None:
        """Set up the scene; nothing is rendered until asked."""
        self.noise = noise if noise is not None else NoiseModel.thesis()
        if self.noise.lens_division_k != 0.0:
            rig = replace(rig, division_k=self.noise.lens_division_k)
        self.rig = rig
        self.obj = obj
        self.seed = seed
        ox, oy = rig.cylinder_offset_mm
        d, h = rig.cylinder_diameter_mm, rig.cylinder_height_mm
        self.cylinder: SceneObject = (
            grooved_cylinder(d, h, ox, oy, -5.0, rig.cylinder_grooves_mm, rig.groove_depth_mm)
            if rig.cylinder_grooves_mm
            else cylinder(d, h, ox, oy, -5.0)
        )
        w, h = rig.image_size
        self._shape = (h, w)
        self._centre, dirs = rig.pixel_rays()
        self._dirs = dirs.reshape(-1, 3)
        self._field = ambient_field(rig.image_size, self.noise)
        self._views: OrderedDict[tuple[str, float, float, float, float], _View] = OrderedDict()
        self._grid: np.ndarray | None = None

    def _target(self, target: str) -> SceneObject:
        """Return the solid for ``target``, refusing unknown targets and a missing object."""
        if target == "cylinder":
            return self.cylinder
        if target == "object":
            if self.obj is None:
                raise ValueError("this scene has no object: pass obj= to SimScene")
            return self.obj
        raise ValueError(f"unknown target {target!r}; expected 'grid', 'cylinder' or 'object'")

    def truth_outline(self, target: str, z_mm: float) -> list[np.ndarray]:
        """Return the object-frame section polygons of ``target`` at section height ``z_mm``."""
        return self._target(target).section_outline(z_mm)

    def render(
        self,
        target: str,
        angle_deg: float,
        z_mm: float,
        laser_on: bool,
        noise_key: tuple[object, ...] = (),
        exposure_scale: float = 1.0,
        shift_mm: tuple[float, float] = (0.0, 0.0),
    ) -> np.ndarray:
        """Return one uint8 (H, W) frame of ``target`` at the true angle and section height.

        ``shift_mm`` moves the target off its place on the turntable (world x, y): a
        patient's sway at the moment of the frame.

        ``exposure_scale`` (exposure time over the nominal one) multiplies the light that
        reaches the sensor, ambient and laser alike, before noise and 8-bit clipping, so a
        long exposure saturates the stripe as a real sensor does. At 1.0 the frame is
        bit-identical to one rendered without it.
        """
        if self.noise.laser_rgb is not None:
            rgb = self._channels(
                target, angle_deg, z_mm, laser_on, noise_key, exposure_scale, shift_mm
            )
            return luma(rgb)
        rng = self._rng(target, angle_deg, z_mm, laser_on, noise_key)
        if target == "grid":
            return _expose(rng, self._grid_expected(), self.noise)
        view = self._view(target, float(angle_deg), float(z_mm), shift_mm)
        return self._grey(view, rng, laser_on, exposure_scale)

    def _grey(
        self, view: _View, rng: np.random.Generator, laser_on: bool, exposure_scale: float
    ) -> np.ndarray:
        """Return the uint8 frame of a grey (thesis-like) model from a view's expected light."""
        expected = (
            view.ambient_dn if view.tint is None else view.ambient_dn * (view.tint @ BT601_LUMA)
        )
        if laser_on:
            n = self.noise
            speckle = speckle_field(rng, self._shape, n.speckle_contrast, n.speckle_grain_px)
            expected = expected + view.laser_dn * speckle
        if exposure_scale != 1.0:
            expected = expected * exposure_scale
        return _expose(rng, expected, self.noise)

    def render_exposure(
        self,
        target: str,
        z_mm: float,
        laser_on: bool,
        exposure: Exposure,
        noise_key: tuple[object, ...] = (),
        exposure_scale: float = 1.0,
    ) -> tuple[np.ndarray, np.ndarray | None]:
        """Return a frame of ``target`` moving during its rolling-shutter ``exposure``.

        The continuous scan's frames: each band of :data:`ROLLING_BANDS` rows sees the
        target where it is at that band's own exposure (the rolling shutter), and the laser
        light is the mean of :data:`BLUR_SAMPLES` poses across each band's exposure (the
        stripe's motion blur). The room light is taken at the middle of each band's
        exposure without blur: a moving edge then stays sharp, which the laser-off frames
        must cancel as they would a blurred one (a harsher test, not a kinder one). The
        speckle keeps its full contrast, though a moving surface would average some of it.

        Args:
            target: ``cylinder`` or ``object``.
            z_mm: the true section height (the lift stands still during a view).
            laser_on: whether the laser is on for the whole exposure.
            exposure: the frame's row timing and the target's pose over time.
            noise_key: what makes this frame's noise its own.
            exposure_scale: as in :meth:`render`.

        Returns:
            The uint8 (H, W) frame and, for colour models, its (H, W, 3) uint8 RGB.
        """
        view = self._moving_view(target, float(z_mm), exposure, laser_on)
        middle = exposure.middle_s(self._shape[0])
        angle, _ = exposure.pose(middle, middle)
        rng = self._rng(target, angle, z_mm, laser_on, ("moving", *noise_key))
        if self.noise.laser_rgb is None:
            return self._grey(view, rng, laser_on, exposure_scale), None
        rgb = self._colour(view, rng, laser_on, exposure_scale)
        return luma(rgb), np.rint(rgb).astype(np.uint8)

    def render_rgb(
        self,
        target: str,
        angle_deg: float,
        z_mm: float,
        laser_on: bool,
        noise_key: tuple[object, ...] = (),
        exposure_scale: float = 1.0,
        shift_mm: tuple[float, float] = (0.0, 0.0),
    ) -> np.ndarray:
        """Return the (H, W, 3) uint8 RGB frame whose luma :meth:`render` returns.

        Only for colour models (``noise.laser_rgb`` set); the channels carry the same
        noise as the frame :meth:`render` gives for the same arguments.
        """
        rgb = self._channels(target, angle_deg, z_mm, laser_on, noise_key, exposure_scale, shift_mm)
        return np.rint(rgb).astype(np.uint8)

    def _rng(
        self,
        target: str,
        angle_deg: float,
        z_mm: float,
        laser_on: bool,
        noise_key: tuple[object, ...],
    ) -> np.random.Generator:
        """Return the generator of one frame's noise: repeatable per frame, not per call order."""
        key = (self.seed, target, float(angle_deg), float(z_mm), bool(laser_on), tuple(noise_key))
        return np.random.default_rng(_stable_seed(*key))

    def _channels(
        self,
        target: str,
        angle_deg: float,
        z_mm: float,
        laser_on: bool,
        noise_key: tuple[object, ...],
        exposure_scale: float,
        shift_mm: tuple[float, float] = (0.0, 0.0),
    ) -> np.ndarray:
        """Return the noisy (H, W, 3) float R, G, B of a colour model, clipped to 0..255."""
        if self.noise.laser_rgb is None:
            raise ValueError("this noise model renders one grey channel; use render()")
        rng = self._rng(target, angle_deg, z_mm, laser_on, noise_key)
        if target == "grid":
            grid = _View(self._grid_expected(), np.zeros(0))
            return self._colour(grid, rng, False, exposure_scale)
        view = self._view(target, float(angle_deg), float(z_mm), shift_mm)
        return self._colour(view, rng, laser_on, exposure_scale)

    def _colour(
        self, view: _View, rng: np.random.Generator, laser_on: bool, exposure_scale: float
    ) -> np.ndarray:
        """Return the noisy (H, W, 3) float R, G, B of a view's expected light, 0..255."""
        n = self.noise
        assert n.laser_rgb is not None
        ambient, tint = view.ambient_dn, view.tint
        laser: np.ndarray | None = None
        if laser_on:
            grain = n.speckle_grain_px
            speckle = speckle_field(
                rng, self._shape, n.speckle_contrast, grain, n.speckle_lognormal
            )
            laser = view.laser_dn * speckle
            if view.halo_dn is not None:
                laser = laser + view.halo_dn
        out = np.empty((*self._shape, 3))
        for c in range(3):
            expected = ambient * n.ambient_rgb[c]
            if tint is not None:
                expected = expected * tint[..., c]
            if laser is not None:
                expected = expected + laser * n.laser_rgb[c]
            out[..., c] = _noisy(rng, expected * exposure_scale, n)
        return np.clip(out, 0.0, 255.0)

    def _view(
        self, target: str, angle_deg: float, z_mm: float, shift_mm: tuple[float, float]
    ) -> _View:
        """Return the cached noise-free images of a geometry, computing them on a miss."""
        key = (target, angle_deg, z_mm, float(shift_mm[0]), float(shift_mm[1]))
        if key in self._views:
            self._views.move_to_end(key)
            return self._views[key]
        view = self._compute_view(self._target(target), angle_deg, z_mm, shift_mm)
        self._views[key] = view
        if len(self._views) > _VIEW_CACHE_SIZE:
            self._views.popitem(last=False)
        return view

    def _compute_view(
        self, obj: SceneObject, angle_deg: float, z_mm: float, shift_mm: tuple[float, float]
    ) -> _View:
        """Ray cast every pixel and evaluate ambient and laser light, noise-free."""
        seen = self._surface(obj, slice(None), angle_deg, z_mm, shift_mm)
        laser = np.zeros_like(seen.ambient)
        laser[np.flatnonzero(seen.hit)] = self._laser_term(
            obj, seen.p, seen.normal, angle_deg, z_mm, seen.axis[:2]
        )
        laser_img = laser.reshape(self._shape)
        tint = None if seen.tint is None else seen.tint.reshape(*self._shape, 3)
        return _View(seen.ambient.reshape(self._shape), laser_img, self._halo(laser_img), tint)

    def _halo(self, laser_img: np.ndarray) -> np.ndarray | None:
        """Return the stripe's light scattered in the surface and the lens (None without)."""
        n = self.noise
        if n.halo_fraction <= 0.0:
            return None
        # A sum-normalised blur keeps its energy at halo_fraction of the stripe's, so its
        # peak is a few % of the stripe's.
        s = n.halo_sigma_px
        k = 2 * math.ceil(3.0 * s) + 1
        return n.halo_fraction * cv2.GaussianBlur(laser_img, (k, k), s)

    def _surface(
        self,
        obj: SceneObject,
        pixels: slice | np.ndarray,
        angle_deg: float,
        z_mm: float,
        shift_mm: tuple[float, float],
    ) -> _Surface:
        """Ray cast ``pixels`` (flat indices) with the target at one pose; shade the room light."""
        rig, n = self.rig, self.noise
        # A target shifted off its place is the turntable's axis shifted, as it sees it.
        axis = np.array([rig.axis_xy_mm[0] + shift_mm[0], rig.axis_xy_mm[1] + shift_mm[1], 0.0])
        to_obj = _rz(-angle_deg)
        lift = np.array([0.0, 0.0, z_mm])  # world z = object z - z_mm
        dirs = self._dirs[pixels]
        t, normal_obj = obj.raycast(to_obj @ (self._centre - axis) + lift, dirs @ to_obj.T)
        hit = np.isfinite(t)
        p = self._centre + t[hit, None] * dirs[hit]
        normal = normal_obj[hit] @ _rz(angle_deg).T
        field = self._field.ravel()[pixels]
        ambient = n.background_dn * field
        # Soft lamp from above-front-left plus fill light: enough shading to look like a solid.
        lamp = np.array([-0.4, -0.6, 0.7]) / np.linalg.norm([-0.4, -0.6, 0.7])
        shade = 0.35 + 0.65 * np.maximum(normal @ lamp, 0.0)
        ambient[hit] = n.albedo * n.ambient_dn * field[hit] * shade
        tint: np.ndarray | None = None
        if isinstance(obj, Textured):
            surface = to_obj @ (self._centre - axis) + lift + t[hit, None] * (dirs[hit] @ to_obj.T)
            tint = np.ones((len(field), 3))
            tint[hit] = obj.texture.reflectance(surface) / n.albedo
        return _Surface(hit, p, normal, ambient, tint, axis)

    def _moving_view(self, target: str, z_mm: float, exposure: Exposure, laser_on: bool) -> _View:
        """Return the expected light of a frame whose target moves during its exposure."""
        obj = self._target(target)
        height, width = self._shape
        ambient = np.empty(height * width)
        tint = np.ones((height * width, 3)) if isinstance(obj, Textured) else None
        laser = np.zeros(height * width)
        reach_mm = _SHEET_REACH_SIGMAS * self.rig.laser_sigma_mm + _BLUR_REACH_MM
        for rows in np.array_split(np.arange(height), min(ROLLING_BANDS, height)):
            band = slice(int(rows[0]) * width, (int(rows[-1]) + 1) * width)
            mid_row = 0.5 * float(rows[0] + rows[-1])
            around = exposure.row_middle_s(mid_row)
            angle, shift = exposure.pose(around, around)
            seen = self._surface(obj, band, angle, z_mm, shift)
            ambient[band] = seen.ambient
            if tint is not None and seen.tint is not None:
                tint[band] = seen.tint
            if not laser_on:
                continue
            # Only pixels near the sheet can be lit as the target turns a little more.
            near = np.zeros(len(seen.hit), np.uint8)
            near[np.flatnonzero(seen.hit)[np.abs(seen.p[:, 2]) < reach_mm]] = 1
            if not near.any():
                continue
            kernel = np.ones((3, 2 * _BLUR_REACH_PX + 1), np.uint8)
            grown = cv2.dilate(near.reshape(len(rows), width), kernel).ravel()
            pixels = band.start + np.flatnonzero(grown)
            total = np.zeros(len(pixels))
            for k in range(BLUR_SAMPLES):
                share = (k + 0.5) / BLUR_SAMPLES
                when = exposure.row_start_s(mid_row) + share * exposure.exposure_s
                angle_k, shift_k = exposure.pose(when, around)
                lit = self._surface(obj, pixels, angle_k, z_mm, shift_k)
                total[np.flatnonzero(lit.hit)] += self._laser_term(
                    obj, lit.p, lit.normal, angle_k, z_mm, lit.axis[:2]
                )
            laser[pixels] = total / BLUR_SAMPLES
        laser_img = laser.reshape(self._shape)
        tint_img = None if tint is None else tint.reshape(height, width, 3)
        return _View(ambient.reshape(self._shape), laser_img, self._halo(laser_img), tint_img)

    def _laser_term(
        self,
        obj: SceneObject,
        p: np.ndarray,
        normal: np.ndarray,
        angle_deg: float,
        z_mm: float,
        axis_xy_mm: np.ndarray,
    ) -> np.ndarray:
        """Return the noise-free laser DN at world surface points ``p`` with world normals."""
        rig = self.rig
        sigma = rig.laser_sigma_mm
        out = np.zeros(len(p))
        near = np.flatnonzero(np.abs(p[:, 2]) < _SHEET_REACH_SIGMAS * sigma)
        if near.size == 0:
            return out
        q, nrm = p[near], normal[near]
        to_src = rig.laser_source_mm - q
        to_src /= np.linalg.norm(to_src, axis=1, keepdims=True)
        cosine = np.maximum(np.einsum("ij,ij->i", nrm, to_src), 0.0)
        sheet = np.exp(-(q[:, 2] ** 2) / (2.0 * sigma**2))
        lit = self._lit(obj, q, nrm, angle_deg, z_mm, axis_xy_mm)
        out[near] = self.noise.laser_peak_dn * sheet * cosine * lit
        return out

    def _lit(
        self,
        obj: SceneObject,
        q: np.ndarray,
        nrm: np.ndarray,
        angle_deg: float,
        z_mm: float,
        axis_xy_mm: np.ndarray,
    ) -> np.ndarray:
        """Return True where the laser, travelling in the sheet, reaches world points ``q``."""
        rig = self.rig
        to_obj = _rz(-angle_deg)[:2, :2]
        axis = np.asarray(axis_xy_mm, dtype=float)
        src = to_obj @ (np.asarray(rig.laser_source_xy_mm) - axis)
        q_obj = (q[:, :2] - axis) @ to_obj.T
        # Test each point against the section at (nearly) its own height: slabs every half
        # sigma. A point may then sit off its slab's outline by up to half a slab times the
        # surface's horizontal slope, across the surface; along the ray that is that much
        # over the cosine of the incidence in the plane, so that much of the segment's end
        # is forgiven (forgiving only the offset across left oblique, sloping surfaces
        # banded: every other slab's points fell short of their outline and went dark).
        slab_mm = _SLAB_SIGMAS * rig.laser_sigma_mm
        slab = np.rint(q[:, 2] / slab_mm).astype(int)
        n_xy = np.hypot(nrm[:, 0], nrm[:, 1])
        ray = q[:, :2] - np.asarray(rig.laser_source_xy_mm)
        facing = np.abs(np.einsum("ij,ij->i", ray, nrm[:, :2]))
        facing /= np.maximum(np.hypot(ray[:, 0], ray[:, 1]) * n_xy, 1e-9)
        across = 0.5 * slab_mm * np.abs(nrm[:, 2]) / np.maximum(n_xy, 1e-3)
        tol = 1e-3 + np.minimum(across / np.maximum(facing, _MIN_FACING), 1.0)
        lit = np.ones(len(q), dtype=bool)
        for k in np.unique(slab):
            sel = slab == k
            a, b = section_edges(obj, z_mm + k * slab_mm)
            lit[sel] = laser_reaches_edges(src, q_obj[sel], a, b, tol[sel])
        return lit

    def _grid_expected(self) -> np.ndarray:
        """Return the noise-free board image, supersampled so corners land exactly."""
        if self._grid is not None:
            return self._grid
        w, h = self.rig.image_size
        inv = np.linalg.inv(self.rig.plane_homography())
        v, u = np.mgrid[0:h, 0:w].astype(float)
        lens = self.rig.division_k != 0.0
        total = np.zeros((h, w))
        # A rank-1 lattice: every sample has its own row and column offset, so even edges
        # parallel to the pixel grid are resolved to 1/N px (a square s x s grid gives 1/s).
        n = _GRID_SAMPLES
        for k in range(n):
            du, dv = (k + 0.5) / n - 0.5, ((k * _GRID_LATTICE_STEP) % n + 0.5) / n - 0.5
            us, vs = u + du, v + dv
            if lens:
                ideal = self.rig.undistort_px(np.stack([us, vs], axis=-1))
                us, vs = ideal[..., 0], ideal[..., 1]
            x, y, s = (inv[r, 0] * us + inv[r, 1] * vs + inv[r, 2] for r in range(3))
            total += self._board_value(x / s, y / s)
        self._grid = total / n * self._field
        return self._grid

    def _board_value(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Return the DN (before the ambient field) at world plane points: squares, paper, box."""
        n, board = self.noise, self.rig.board
        sq = board.square_mm
        i = np.floor((x - board.origin_mm[0]) / sq)
        j = np.floor((y - board.origin_mm[1]) / sq)
        nx, ny = board.inner_corners
        on_board = (i >= -1) & (i <= nx - 1) & (j >= -1) & (j <= ny - 1)
        margin = n.grid_paper_margin_mm + sq
        ox, oy = board.origin_mm
        on_paper = (
            (x >= ox - margin)
            & (x <= ox + (nx - 1) * sq + margin)
            & (y >= oy - margin)
            & (y <= oy + (ny - 1) * sq + margin)
        )
        black = on_board & ((i + j) % 2 == 0)
        value = np.where(on_paper, n.grid_white_dn, n.background_dn)
        return np.where(black, n.grid_black_dn, value)
