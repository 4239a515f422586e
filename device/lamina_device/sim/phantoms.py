"""Anatomy-like test objects built by code: hand, foot, bust, bone, ring, stump, arm, face.

Each phantom is a small closed triangle mesh (a few thousand triangles) in the object
frame, sized for the thesis rig (20-30 mm across, sections from z = 0 up to ~20 mm,
inside its 45 mm field) and scaled by ``scale`` for others (``scale=5`` on ``--rig
limb``). What each one makes hard for the scanner:

- ``hand``: a palm and four fingers with rounded tips: four separate outlines per
  section above the palm, narrow gaps that shadow one another;
- ``foot``: an ankle above a foot whose rounded sole (z -2..0.5) overhangs: it faces
  down, so the horizontal sheet lights it and the camera above cannot see it;
- ``bust``: a head with eye sockets, a nose and a mouth: concavities in the outline;
- ``bone``: a shaft flaring into two condyles with a notch between them (a concave
  waist in every section) and rounded ends;
- ``ring``: an upright torus: two outlines per section, each shadowing the other;
- ``stump``: a tapered residual limb with a rounded distal end (the stripe grazes it);
- ``arm``: a tapered, oval forearm with a muscle belly (limb measurements at scale 5);
- ``face``: the front half of the bust's face as a shell of no thickness, open at its
  rims: an open surface, seen from the front and from behind, whose outlines never close.

The limb phantoms (``arm``, ``stump``) take skin relief: ``relief=A`` adds oblique folds
of about A mm (placed mm) at ``wave=`` mm round the outline (default 10 mm) and at two
longer scales, so a section is not an ellipse (``arm:scale=5,relief=0.3,wave=8``).

Parts are built as lofts of closed outlines (rings of vertices joined by strips), and
parts of one phantom touch but do not overlap (the hand's fingers stand on the palm's
top face), so ray casts, sections and the laser-shadow test see one solid. The faces
where parts touch lie inside the solid; the ground truth (``sim.truth``) counts them as
surface, which changes only distances of points inside the hand, near the knuckles.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from lamina_device.sim.objects import AS_BUILT, Placement, TriangleMesh

__all__ = ["OPEN_PHANTOMS", "PHANTOMS", "phantom"]

_N_PHI = 72  # vertices per ring: ~1 mm edges on a 24 mm outline
_RING_STEP_MM = 0.6  # vertical spacing of rings on straight parts (thesis scale)
_DOME_RINGS = 10
# The stump's end is the limb bench's grazing case: with 10 rings its facets meet at 9
# degree creases, and a crease a fraction of the sheet's thickness above a measured
# section lights the two halves of the stripe unequally (Lambert), which biased that
# section's outline outwards by ~0.15 mm. 40 rings (2.25 degrees) is nearer a smooth limb.
_STUMP_DOME_RINGS = 40

RadiusFn = Callable[[np.ndarray, float], np.ndarray]
"""r(phi, z): the outline's radius at polar angles ``phi`` about its centre, at height z."""

RELIEF_PHANTOMS = ("arm", "stump")
"""The limb phantoms that take skin relief (``relief=``, ``wave=``)."""

_RELIEF_WAVES = ((1.0, 1.0, 2.0, 0.0), (0.5, 1.9, 3.1, 1.3), (0.35, 3.3, -4.7, 2.6))
"""Skin relief's components: (weight, wavelength / ``wave``, wavelength along z / that
round the outline, phase): oblique folds at three scales, as skin over tendons and
muscle has, the first ``wave`` long round the outline."""

_RELIEF_SAMPLES_PER_WAVE = 8
"""Mesh edges per shortest relief wavelength, round the outline and along z."""


@dataclass(frozen=True)
class Relief:
    """Skin relief on a limb phantom: folds of ``amplitude_mm`` at ``wavelength_mm`` round
    the outline (and longer ones), in placed mm; ``scale`` is the placement's."""

    amplitude_mm: float
    wavelength_mm: float
    scale: float = 1.0

    def radius_fn(self, radius: RadiusFn, reference_mm: float) -> RadiusFn:
        """Return ``radius`` with the relief added (build units).

        Each component has a whole number of waves round an outline of radius
        ``reference_mm`` (build units), so the relief is continuous round every outline.
        """
        amp = self.amplitude_mm / self.scale / sum(w for w, *_ in _RELIEF_WAVES)
        lam = self.wavelength_mm / self.scale
        parts = []
        for weight, along, up, phase in _RELIEF_WAVES:
            waves = max(1, round(2.0 * math.pi * reference_mm / (lam * along)))
            parts.append((amp * weight, waves, 2.0 * math.pi / (lam * along * up), phase))

        def relieved(phi: np.ndarray, z: float) -> np.ndarray:
            bumps = sum(a * np.cos(n * phi + k * z + ph) for a, n, k, ph in parts)
            return radius(phi, z) + bumps

        return relieved

    def ring_count(self, reference_mm: float) -> int:
        """Return vertices per ring that resolve the shortest wave (at least ``_N_PHI``)."""
        edge = self.wavelength_mm / self.scale / _RELIEF_SAMPLES_PER_WAVE
        return max(_N_PHI, math.ceil(2.0 * math.pi * reference_mm * 1.3 / edge))

    def ring_step(self) -> float:
        """Return the largest vertical ring spacing (build units) that resolves the relief."""
        up = min(abs(along * up) for _, along, up, _ in _RELIEF_WAVES)
        return min(_RING_STEP_MM, self.wavelength_mm * up / self.scale / _RELIEF_SAMPLES_PER_WAVE)


def _levels(z0: float, z1: float, step: float) -> np.ndarray:
    """Return heights from z0 to z1 inclusive at most ``step`` apart."""
    return np.linspace(z0, z1, max(2, math.ceil(abs(z1 - z0) / step) + 1))


def _dome(z_base: float, height: float, rings: int = _DOME_RINGS) -> tuple[np.ndarray, np.ndarray]:
    """Return heights and radius scales of a rounded end (a quarter ellipse) from z_base.

    ``height`` < 0 builds the end downwards. The last level has scale 0 (the apex);
    ``rings`` levels turn the surface by 90 / rings degrees each.
    """
    theta = np.linspace(0.0, 0.5 * math.pi, rings + 1)[1:]
    return z_base + height * np.sin(theta), np.cos(theta)


def _loft(
    z: np.ndarray,
    scale: np.ndarray,
    radius: RadiusFn,
    centre: Callable[[float], tuple[float, float]] = lambda z: (0.0, 0.0),
    n_phi: int = _N_PHI,
) -> np.ndarray:
    """Return the triangles (F, 3, 3) of a closed loft through rings at heights ``z``.

    Ring k is ``centre(z_k) + scale_k * radius(phi, z_k) * (cos phi, sin phi)``; an end
    ring with scale 0 closes as an apex (its degenerate triangles are dropped when the mesh
    welds equal vertices), any other end ring is closed by a flat fan.
    """
    phi = np.linspace(0.0, 2.0 * math.pi, n_phi, endpoint=False)
    unit = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    rings = []
    for zk, sk in zip(z, scale, strict=True):
        cx, cy = centre(float(zk))
        xy = np.array([cx, cy]) + (sk * radius(phi, float(zk)))[:, None] * unit
        rings.append(np.column_stack([xy, np.full(n_phi, zk)]))
    tris = []
    nxt = np.roll(np.arange(n_phi), -1)
    for a, b in itertools.pairwise(rings):
        tris.append(np.stack([a, a[nxt], b[nxt]], axis=1))
        tris.append(np.stack([a, b[nxt], b], axis=1))
    for ring, sk in ((rings[0], scale[0]), (rings[-1], scale[-1])):
        if sk > 0.0:
            hub = np.broadcast_to(ring.mean(axis=0), ring.shape)
            tris.append(np.stack([hub, ring, ring[nxt]], axis=1))
    return np.concatenate(tris)


def _open_loft(z: np.ndarray, radius: RadiusFn, phi0_deg: float, phi1_deg: float) -> np.ndarray:
    """Return the triangles (F, 3, 3) of an open shell: strips through arcs at heights ``z``.

    Arc k runs from ``phi0_deg`` to ``phi1_deg`` (ends included) at ``radius(phi, z_k)``
    about the z axis; nothing joins the arcs' ends or closes the top and bottom, so the
    shell has a rim all round.
    """
    n_phi = max(2, math.ceil(abs(phi1_deg - phi0_deg) / 360.0 * _N_PHI) + 1)
    phi = np.radians(np.linspace(phi0_deg, phi1_deg, n_phi))
    unit = np.stack([np.cos(phi), np.sin(phi)], axis=1)
    arcs = [
        np.column_stack([radius(phi, float(zk))[:, None] * unit, np.full(n_phi, zk)]) for zk in z
    ]
    tris = []
    for a, b in itertools.pairwise(arcs):
        tris.append(np.stack([a[:-1], a[1:], b[1:]], axis=1))
        tris.append(np.stack([a[:-1], b[1:], b[:-1]], axis=1))
    return np.concatenate(tris)


def _profile(*pieces: tuple[np.ndarray, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Join (z, scale) pieces bottom to top, dropping repeated heights at the joins."""
    z = np.concatenate([p[0] for p in pieces])
    s = np.concatenate([p[1] for p in pieces])
    keep = np.concatenate([[True], np.diff(z) > 1e-9])
    return z[keep], s[keep]


def _straight(z0: float, z1: float, step: float = _RING_STEP_MM) -> tuple[np.ndarray, np.ndarray]:
    """Return a (z, scale) piece of constant scale 1, rings at most ``step`` apart."""
    z = _levels(z0, z1, step)
    return z, np.ones_like(z)


def _bump(phi: np.ndarray, phi0_deg: float, width_deg: float) -> np.ndarray:
    """Return a smooth angular bump of height 1 at ``phi0_deg`` (wrapping at 360)."""
    d = (phi - math.radians(phi0_deg) + math.pi) % (2.0 * math.pi) - math.pi
    return np.exp(-0.5 * (d / math.radians(width_deg)) ** 2)


def _round(radius_mm: float) -> RadiusFn:
    """Return the radius function of a circle."""
    return lambda phi, z: np.full_like(phi, radius_mm)


def _fixed_centre(x_mm: float, y_mm: float) -> Callable[[float], tuple[float, float]]:
    """Return a centre function that stays at ``(x_mm, y_mm)`` at every height."""
    return lambda z: (x_mm, y_mm)


def _gauss(z: float, z0: float, width: float) -> float:
    """Return a bump of height 1 at ``z0`` along z."""
    return math.exp(-0.5 * ((z - z0) / width) ** 2)


def _hand() -> np.ndarray:
    """A palm (z -5..7.3) and four fingers on it, rounded tips, 2.2 mm gaps between them."""
    palm_top = 7.3
    palm = _loft(
        *_straight(-5.0, palm_top),
        lambda phi, z: 12.0 * 4.5 / np.hypot(4.5 * np.cos(phi), 12.0 * np.sin(phi)),
    )
    parts = [palm]
    finger_r = 2.1
    for x, length in ((-9.75, 9.0), (-3.25, 12.5), (3.25, 13.5), (9.75, 11.0)):
        top = palm_top + length - finger_r
        z, s = _profile(_straight(palm_top, top), _dome(top, finger_r))
        parts.append(_loft(z, s, _round(finger_r), _fixed_centre(x, 0.0), n_phi=24))
    return np.concatenate(parts)


def _foot() -> np.ndarray:
    """An ankle (z 8..26) over a foot reaching 21 mm forward, its rounded sole overhanging."""

    def half_length(z: float) -> float:
        # Long at the sole, narrowing over the instep into the round ankle.
        return 5.0 + 8.0 / (1.0 + math.exp((z - 3.0) / 1.2))

    def radius(phi: np.ndarray, z: float) -> np.ndarray:
        a, b = 5.5 - 0.8 * (z > 8.0) * min(1.0, (z - 8.0) / 6.0), half_length(z)
        return a * b / np.hypot(b * np.cos(phi), a * np.sin(phi))

    def centre(z: float) -> tuple[float, float]:
        return (0.0, half_length(z) - 5.0)  # the heel stays put, the toes reach +y

    sole = -2.0  # the overhanging edge reaches above z = 0, where scans start
    z, s = _profile(_sole(sole), _straight(sole + 2.5, 26.0))
    return _loft(z, s, radius, centre)


def _sole(z_bottom: float) -> tuple[np.ndarray, np.ndarray]:
    """Return the (z, scale) piece of a rounded sole: 2.5 mm from the flat bottom up."""
    theta = np.linspace(0.15 * math.pi, 0.5 * math.pi, _DOME_RINGS)
    # A quarter ellipse that starts at 0.45 of full size on the floor: the edge overhangs.
    return z_bottom + 2.5 * (1.0 - np.cos(theta)), np.sin(theta)


def _bust() -> np.ndarray:
    """A head 22 x 25 mm facing -y: eye sockets, a nose and a mouth; rounded crown."""

    def radius(phi: np.ndarray, z: float) -> np.ndarray:
        base = 11.0 * 12.5 / np.hypot(12.5 * np.cos(phi), 11.0 * np.sin(phi))
        eyes = -1.8 * _gauss(z, 11.0, 1.3) * (_bump(phi, -62.0, 9.0) + _bump(phi, -118.0, 9.0))
        nose = 2.8 * max(0.0, 1.0 - abs(z - 7.5) / 3.5) * _bump(phi, -90.0, 6.0)
        mouth = -1.6 * _gauss(z, 2.5, 0.7) * _bump(phi, -90.0, 9.0)
        chin = -1.5 * (1.0 - min(1.0, max(0.0, (z + 5.0) / 6.0)))  # a narrower neck below
        return base + eyes + nose + mouth + chin

    top = 16.0
    z, s = _profile(_straight(-5.0, top), _dome(top, 7.0))
    return _loft(z, s, radius, lambda z: (0.0, 0.0))


def _bone() -> np.ndarray:
    """A shaft (r 4) flaring into two condyles with a notch between them; rounded ends."""

    def radius(phi: np.ndarray, z: float) -> np.ndarray:
        flare = 1.0 / (1.0 + math.exp(-(z - 9.0) / 1.5))  # 0 on the shaft, 1 at the condyles
        waist = 0.45 * flare  # above 0.2 the outline's waist turns concave
        return (4.0 + 4.5 * flare) * (1.0 + waist * np.cos(2.0 * phi)) / (1.0 + waist)

    top = 17.0
    bz, bs = _dome(-2.0, -3.0)  # the lower end, built downwards: reverse it
    z, s = _profile((bz[::-1], bs[::-1]), _straight(-2.0, top), _dome(top, 5.0))
    return _loft(z, s, radius)


def _ring() -> np.ndarray:
    """An upright torus (axis along y, z -5..17): two outlines per section for z 1..11."""
    big, small, zc = 8.0, 3.0, 6.0
    u = np.linspace(0.0, 2.0 * math.pi, 96, endpoint=False)
    v = np.linspace(0.0, 2.0 * math.pi, 36, endpoint=False)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    rr = big + small * np.cos(vv)
    pts = np.stack([rr * np.cos(uu), small * np.sin(vv), zc + rr * np.sin(uu)], axis=-1)
    i, j = np.meshgrid(np.arange(len(u)), np.arange(len(v)), indexing="ij")
    i1, j1 = (i + 1) % len(u), (j + 1) % len(v)
    a, b, c, d = pts[i, j], pts[i1, j], pts[i1, j1], pts[i, j1]
    return np.concatenate([np.stack([a, b, c], -2), np.stack([a, c, d], -2)]).reshape(-1, 3, 3)


def _stump(relief: Relief | None = None) -> np.ndarray:
    """A tapered, slightly oval residual limb (24 -> 19 mm) ending in a rounded distal end."""

    def radius(phi: np.ndarray, z: float) -> np.ndarray:
        taper = 12.0 - 2.5 * (z + 5.0) / 17.0
        return taper * (1.0 + 0.06 * np.cos(2.0 * phi) + 0.02 * np.sin(3.0 * phi))

    top = 12.0
    if relief is None:
        z, s = _profile(_straight(-5.0, top), _dome(top, 9.0, _STUMP_DOME_RINGS))
        return _loft(z, s, radius)
    # The relief fades over the dome with its radius (the loft scales it with the ring).
    z, s = _profile(_straight(-5.0, top, relief.ring_step()), _dome(top, 9.0, _STUMP_DOME_RINGS))
    return _loft(z, s, relief.radius_fn(radius, 11.0), n_phi=relief.ring_count(12.0))


def _arm(relief: Relief | None = None) -> np.ndarray:
    """A forearm (wrist 11 -> elbow 17 mm across, z -5..20): tapered, oval, a muscle belly.

    Scaled five times (``arm:scale=5`` on ``--rig limb``) it is an adult forearm: about
    170 mm round at the wrist and 270 mm below the elbow, flatter at the wrist.
    """

    def radius(phi: np.ndarray, z: float) -> np.ndarray:
        u = (z + 5.0) / 25.0
        mean = 5.4 + 2.6 * u + 0.9 * _gauss(z, 14.0, 4.0)
        return mean * (1.0 + (0.14 - 0.08 * u) * np.cos(2.0 * phi) + 0.015 * np.sin(3.0 * phi))

    if relief is None:
        return _loft(*_straight(-5.0, 20.0), radius)
    z, s = _straight(-5.0, 20.0, relief.ring_step())
    return _loft(z, s, relief.radius_fn(radius, 7.0), n_phi=relief.ring_count(9.0))


def _face() -> np.ndarray:
    """The front half (facing -y) of the bust's face, z -5..16, as an open shell (a mask).

    A face is scanned from one side only: there is no back to close its outlines. Each
    section is an arc of 180 degrees with the bust's eye sockets, nose and mouth.
    """

    def radius(phi: np.ndarray, z: float) -> np.ndarray:
        base = 11.0 * 12.5 / np.hypot(12.5 * np.cos(phi), 11.0 * np.sin(phi))
        eyes = -1.8 * _gauss(z, 11.0, 1.3) * (_bump(phi, -62.0, 9.0) + _bump(phi, -118.0, 9.0))
        nose = 2.8 * max(0.0, 1.0 - abs(z - 7.5) / 3.5) * _bump(phi, -90.0, 6.0)
        mouth = -1.6 * _gauss(z, 2.5, 0.7) * _bump(phi, -90.0, 9.0)
        return base + eyes + nose + mouth

    return _open_loft(_levels(-5.0, 16.0, 0.3), radius, -180.0, 0.0)


_BUILDERS: dict[str, Callable[[], np.ndarray]] = {
    "arm": _arm,
    "hand": _hand,
    "foot": _foot,
    "bust": _bust,
    "bone": _bone,
    "ring": _ring,
    "stump": _stump,
    "face": _face,
}
PHANTOMS = ("hand", "foot", "bust", "bone", "ring", "stump", "arm", "face")
"""Names of the built-in phantoms, usable as ``--object NAME[:scale=S,x=,y=,z=,yaw=]``."""

OPEN_PHANTOMS = ("face",)
"""The phantoms that are open surfaces (a rim, no inside), not closed solids."""


def phantom(
    name: str,
    placement: Placement = AS_BUILT,
    relief_mm: float | None = None,
    wave_mm: float | None = None,
) -> TriangleMesh:
    """Return phantom ``name`` placed (scaled about the object origin, yawed, then moved).

    Args:
        name: one of ``PHANTOMS``.
        placement: scale, yaw and shift.
        relief_mm: skin relief's amplitude in placed mm (limb phantoms only, see
            ``RELIEF_PHANTOMS``); None: a smooth surface.
        wave_mm: the relief's shortest wavelength round the outline in placed mm
            (default 10 mm).
    """
    if name not in PHANTOMS:
        raise ValueError(f"unknown phantom {name!r}; use one of {', '.join(PHANTOMS)}")
    if relief_mm is None:
        if wave_mm is not None:
            raise ValueError(f"{name}: wave= needs relief= (the relief's amplitude in mm)")
        return TriangleMesh.from_triangles(placement.apply(_BUILDERS[name]()), name=name)
    if name not in RELIEF_PHANTOMS:
        raise ValueError(
            f"{name}: skin relief is offered on {', '.join(RELIEF_PHANTOMS)}; drop relief="
        )
    relief = Relief(relief_mm, DEFAULT_WAVE_MM if wave_mm is None else wave_mm, placement.scale)
    tris = _RELIEF_BUILDERS[name](relief)
    return TriangleMesh.from_triangles(placement.apply(tris), name=name)


DEFAULT_WAVE_MM = 10.0
"""Skin relief's shortest wavelength when ``wave=`` is not given."""

_RELIEF_BUILDERS: dict[str, Callable[[Relief], np.ndarray]] = {"arm": _arm, "stump": _stump}
