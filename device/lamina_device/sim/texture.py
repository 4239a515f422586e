"""Coloured test objects: a solid painted skin-tone with patches of known colour.

Colour scans (issue 14) need a ground truth: :class:`Textured` wraps any scene object
with a :class:`Texture`, a base reflectance (skin) and vertical bands of other
reflectances (a bruise, a wound, two marker colours) at known object-frame azimuths.
The renderer multiplies the room light by the reflectance in each of R, G and B; the
laser's reflection is left as the solid's own (the pigments modulate the room light
only, so colour does not move the stripe). ``patches:d=30`` is such a cylinder.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from lamina_device.sim.objects import Cylinder, SceneObject

__all__ = [
    "PATCHES",
    "SKIN",
    "Patch",
    "PatchError",
    "Texture",
    "Textured",
    "colour_errors",
    "patches_cylinder",
]

SKIN = (0.80, 0.58, 0.46)
"""Reflectance (R, G, B) of the base: a light skin tone."""


@dataclass(frozen=True)
class Patch:
    """A vertical band of one reflectance: ``width_deg`` wide about azimuth ``centre_deg``."""

    name: str
    reflectance: tuple[float, float, float]
    centre_deg: float
    width_deg: float

    def covers(self, azimuth_deg: np.ndarray, margin_deg: float = 0.0) -> np.ndarray:
        """Return True where an azimuth lies in the band, ``margin_deg`` inside its edges."""
        offset = (np.asarray(azimuth_deg) - self.centre_deg + 180.0) % 360.0 - 180.0
        return np.abs(offset) <= self.width_deg / 2.0 - margin_deg


PATCHES = (
    Patch("bruise", (0.38, 0.22, 0.40), 0.0, 50.0),
    Patch("blue marker", (0.12, 0.25, 0.75), 90.0, 50.0),
    Patch("green marker", (0.15, 0.60, 0.22), 180.0, 50.0),
    Patch("wound", (0.72, 0.10, 0.10), 270.0, 50.0),
)
"""The default patches: four 50 deg bands, 40 deg of skin between neighbours."""


@dataclass(frozen=True)
class Texture:
    """Reflectance over an object's surface: ``base`` except in the ``patches`` bands.

    Azimuths are taken about ``centre_xy_mm`` in the object frame, counter-clockwise
    from +x, as the turntable's angles are.
    """

    base: tuple[float, float, float] = SKIN
    patches: tuple[Patch, ...] = PATCHES
    centre_xy_mm: tuple[float, float] = (0.0, 0.0)

    def azimuth_deg(self, points_mm: np.ndarray) -> np.ndarray:
        """Return the azimuth in degrees [0, 360) of object-frame points (N, 2+)."""
        p = np.asarray(points_mm, float)
        dx, dy = p[:, 0] - self.centre_xy_mm[0], p[:, 1] - self.centre_xy_mm[1]
        return np.degrees(np.arctan2(dy, dx)) % 360.0

    def patch_index(self, points_mm: np.ndarray, margin_deg: float = 0.0) -> np.ndarray:
        """Return each point's patch index, -1 on the base (and within ``margin_deg`` of an edge).

        With a margin, points within it of a band edge get -2: neither patch nor clean base.
        """
        azimuth = self.azimuth_deg(points_mm)
        index = np.full(len(azimuth), -1)
        for k, patch in enumerate(self.patches):
            index[patch.covers(azimuth)] = k
            if margin_deg > 0:
                edge = patch.covers(azimuth, -margin_deg) & ~patch.covers(azimuth, margin_deg)
                index[edge] = -2
        return index

    def reflectance(self, points_mm: np.ndarray) -> np.ndarray:
        """Return the (N, 3) R, G, B reflectance at object-frame surface points."""
        index = self.patch_index(points_mm)
        table = np.array([*(p.reflectance for p in self.patches), self.base], float)
        return table[index]  # -1 picks the base, the table's last row


@dataclass(frozen=True)
class Textured:
    """A scene object with a coloured surface (answers :class:`SceneObject`)."""

    solid: SceneObject
    texture: Texture = field(default_factory=Texture)

    @property
    def name(self) -> str:
        """Return the solid's name with ``+patches``."""
        return f"{self.solid.name}+patches"

    def raycast(self, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Return the solid's first hit distances and normals."""
        return self.solid.raycast(origins, dirs)

    def section_outline(self, z_mm: float) -> list[np.ndarray]:
        """Return the solid's cross-section at ``z_mm``."""
        return self.solid.section_outline(z_mm)


def patches_cylinder(diameter_mm: float = 30.0, height_mm: float = 40.0) -> Textured:
    """Return an upright skin-tone cylinder on the axis with the four :data:`PATCHES`."""
    if not (math.isfinite(diameter_mm) and diameter_mm > 0):
        raise ValueError(f"patches: d={diameter_mm} must be a positive number")
    return Textured(Cylinder(diameter_mm, height_mm, 0.0, 0.0, -5.0, name="patches"))


@dataclass(frozen=True)
class PatchError:
    """How far one patch's measured colours lie from its truth, in 8-bit DN and CIE76 dE."""

    name: str
    points: int
    truth: tuple[float, float, float]
    bias: tuple[float, float, float]
    rms: tuple[float, float, float]
    mean_delta_e: float


def _triple(values: np.ndarray) -> tuple[float, float, float]:
    """Return three values as plain floats rounded to 0.01."""
    r, g, b = (round(float(v), 2) for v in values)
    return r, g, b


def _lab(rgb: np.ndarray) -> np.ndarray:
    """Return CIE L*a*b* of (N, 3) 8-bit sRGB values (OpenCV, D65)."""
    import cv2  # the device installs opencv

    scaled = np.clip(np.asarray(rgb, np.float32) / 255.0, 0.0, 1.0).reshape(-1, 1, 3)
    return np.asarray(cv2.cvtColor(scaled, cv2.COLOR_RGB2Lab), float).reshape(-1, 3)


def colour_errors(
    points_mm: np.ndarray,
    colours: np.ndarray,
    texture: Texture | None = None,
    margin_deg: float = 5.0,
) -> tuple[np.ndarray, list[PatchError]]:
    """Compare measured colours at object-frame points with the texture's patches.

    A camera's gain per channel (room light, exposure, white balance) is unknown, so one
    gain per channel is taken from the skin (the median over base points) and each
    patch's truth is its reflectance times that gain. Points within ``margin_deg`` of a
    band edge are left out (the edge itself is a mix). Returns the gains and one
    :class:`PatchError` per patch.
    """
    texture = texture or Texture()
    index = texture.patch_index(points_mm, margin_deg)
    rgb = np.asarray(colours, float)
    gain = np.median(rgb[index == -1], axis=0) / np.asarray(texture.base)
    errors = []
    for k, patch in enumerate(texture.patches):
        mine = rgb[index == k]
        truth = gain * np.asarray(patch.reflectance)
        diff = mine - truth if len(mine) else np.full((1, 3), np.nan)
        delta_e = np.linalg.norm(_lab(mine) - _lab(truth[None]), axis=1) if len(mine) else [np.nan]
        errors.append(
            PatchError(
                patch.name,
                len(mine),
                _triple(truth),
                _triple(diff.mean(axis=0)),
                _triple(np.sqrt((diff**2).mean(axis=0))),
                float(np.mean(delta_e)),
            )
        )
    return gain, errors
