"""Random, smooth, anatomy-like objects from a seed, for a campaign over unseen shapes.

The phantoms of :mod:`lamina_device.sim.phantoms` each carry one difficulty; the world
mixes them. :func:`random_shape` draws an object from a seed at the thesis scale (a body
10-30 mm across) or the limb scale (five times larger), so any result can be replayed with
``--object random:seed=17,scale=limb``. Each object mixes, with seed-drawn odds:

- a main body whose sections are star-shaped (an oval with low harmonics and dents:
  concavities) or not star-shaped (the same outline bent into a kidney or a C);
- skin relief of 0.1-1 mm at 3-30 mm wavelength, tapers and waists along the height;
- one to four separate parts beside the body (fingers, flaps 2-6 mm thick, stalks) or
  a row of two to five digits with no body: two to five outlines per section;
- rounded ends (domes), tips (ogives) and flat caps, or no end at all: the surface
  ends in a rim (the proximal cut of every limb scan) or runs on beyond the lift's
  range and the scanned band;
- a shell seen from one side, as a face is: an open surface whose sections are open
  arcs (:class:`~lamina_device.sim.objects.SectionCurve` ``closed=False``);
- placed off the axis, tilted by up to 20 degrees, or wider than the camera's view.

Every object is a :class:`~lamina_device.sim.objects.TriangleMesh` (so ray casts, true
sections and the true surface of :mod:`lamina_device.sim.truth` are exact for it), built
as lofts of rings like the phantoms; parts never overlap. The scanned band (heights
-3 to 11 mm at the thesis scale, -15 to 55 mm at the limb scale, where small test scans lie) is
meshed finely enough for the relief; above and below it the rings are coarser.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field, replace

import numpy as np

from lamina_device.sim.axes import SIM_LIFT_TRAVEL_MM
from lamina_device.sim.objects import TriangleMesh, tilt_matrix

__all__ = ["SCALES", "RandomShape", "ShapeFeatures", "parse_random_spec", "random_shape"]

SCALES = {"thesis": 1.0, "limb": 5.0}
"""Size unit of each scale: a thesis-rig object is ~20 mm across, a limb ~100 mm."""

_BAND_MM = (-3.0, 11.0)  # heights (thesis units) meshed finely: where scans begin
_BAND_STEP = {"thesis": 0.5, "limb": 1.5}  # ring spacing there, mm
_COARSE_STEP = {"thesis": 2.5, "limb": 8.0}  # ring spacing elsewhere, mm
_EDGE_MM = {"thesis": 0.5, "limb": 1.5}  # longest ring edge, mm
_MAX_RING_VERTICES = 480
_END_RINGS = 10
_RELIEF_SCALE_CAP = {"thesis": 0.5, "limb": 1.0}  # deepest relief, mm (thesis bodies are small)
_FIELD_HALF_MM = 22.0  # half the thesis camera's field at the axis, thesis units


@dataclass(frozen=True)
class ShapeFeatures:
    """What a random shape holds: for reports, for choosing seeds and for tests."""

    seed: int
    scale: str
    body: str  # "star", "bent" (non-star-shaped), "shell" (open, one side) or "none"
    parts: int  # separate parts beside the body (fingers, flaps, stalks)
    thin_parts: int  # parts 2-6 mm thick
    bottom: str  # end of the body: "dome", "tip", "flat", "rim" or "beyond"
    top: str
    relief_mm: float  # relief amplitude (0: smooth)
    relief_wavelength_mm: float
    tilt_deg: float
    offset_mm: float  # the body's distance from the turntable axis
    wide: bool  # wider than the camera's view
    tall: bool  # runs on past the lift's range
    closed: bool  # every part is a closed solid (volume is defined)

    def summary(self) -> str:
        """Return one line naming the features, for tables and failure lists."""
        flags = [
            self.body,
            f"{self.parts} part(s)" + (f" ({self.thin_parts} thin)" if self.thin_parts else ""),
            f"ends {self.bottom}/{self.top}",
        ]
        if self.relief_mm:
            flags.append(f"relief {self.relief_mm:.2f} mm @ {self.relief_wavelength_mm:.0f} mm")
        if self.tilt_deg:
            flags.append(f"tilt {self.tilt_deg:.0f} deg")
        flags += ["wide"] * self.wide + ["tall"] * self.tall
        return ", ".join(flags)


@dataclass(frozen=True, eq=False)
class RandomShape(TriangleMesh):
    """A seed-drawn triangle mesh and the features it was drawn with."""

    features: ShapeFeatures | None = field(default=None, repr=False)


@dataclass(frozen=True)
class _Relief:
    """Skin relief: a sum of plane waves over (arc length, height), mm."""

    amplitude_mm: np.ndarray
    wavelength_mm: np.ndarray
    direction_rad: np.ndarray
    phase_rad: np.ndarray

    def at(self, arc_mm: np.ndarray, z_mm: float) -> np.ndarray:
        """Return the outward displacement (mm) at arc lengths along a ring at height z."""
        out = np.zeros_like(arc_mm)
        for a, lam, d, p in zip(
            self.amplitude_mm, self.wavelength_mm, self.direction_rad, self.phase_rad, strict=True
        ):
            k = 2.0 * math.pi / lam
            out += a * np.cos(k * (math.cos(d) * arc_mm + math.sin(d) * z_mm) + p)
        return out


_NO_RELIEF = _Relief(np.zeros(0), np.ones(0), np.zeros(0), np.zeros(0))


@dataclass(frozen=True)
class _Part:
    """One loft: outline shape, centre, height range and how each end is finished."""

    centre: tuple[float, float]
    half_axes: tuple[float, float]  # of the base oval, mm
    angle_rad: float  # orientation of the oval
    harmonics: tuple[tuple[int, float, float], ...] = ()  # (k, relative amplitude, phase)
    dents: tuple[tuple[float, float, float], ...] = ()  # (angle, relative depth, width rad)
    bend_rad: float = 0.0  # total bend of the oval's long axis (0: star-shaped)
    z_range: tuple[float, float] = (-5.0, 20.0)
    ends: tuple[str, str] = ("dome", "dome")  # bottom, top: dome, tip, flat, rim, beyond
    end_height_mm: tuple[float, float] = (3.0, 3.0)
    taper: float = 0.0  # relative change of size from bottom to top
    waist: tuple[float, float, float] = (0.0, 0.0, 1.0)  # relative depth, height, width
    arc_deg: float = 360.0  # < 360: an open shell over this much of the outline
    relief: _Relief = _NO_RELIEF


def _profile_scale(part: _Part, z: float) -> float:
    """Return the outline's size factor at height z from taper and waist."""
    z0, z1 = part.z_range
    u = (z - z0) / max(z1 - z0, 1e-9)
    depth, zc, width = part.waist
    return (1.0 + part.taper * (u - 0.5)) * (1.0 - depth * math.exp(-0.5 * ((z - zc) / width) ** 2))


def _ring(part: _Part, phi: np.ndarray, z: float, scale: float) -> np.ndarray:
    """Return one ring (N, 3) of a part at height z, its outline shrunk by ``scale``."""
    a, b = part.half_axes
    size = _profile_scale(part, z) * scale
    r = a * b / np.hypot(b * np.cos(phi), a * np.sin(phi))
    shape = np.ones_like(phi)
    for k, amp, ph in part.harmonics:
        shape += amp * np.cos(k * phi + ph)
    for ang, depth, width in part.dents:
        d = (phi - ang + math.pi) % (2.0 * math.pi) - math.pi
        shape -= depth * np.exp(-0.5 * (d / width) ** 2)
    r = r * shape * size
    # Relief is skin deep: it does not shrink with the ends, only fades out at an apex.
    arc = phi * 0.5 * (a + b)
    r = r + part.relief.at(arc, z) * min(1.0, scale * 4.0)
    x, y = r * np.cos(phi), r * np.sin(phi)
    if part.bend_rad:
        # Bend the oval's long (x) axis round a circle: a kidney or a C, not star-shaped.
        radius = 2.0 * a / part.bend_rad
        theta = x / radius
        x, y = (radius - y) * np.sin(theta), radius - (radius - y) * np.cos(theta)
        y = y - radius * (1.0 - math.sin(part.bend_rad / 2.0) / (part.bend_rad / 2.0))
    c, s = math.cos(part.angle_rad), math.sin(part.angle_rad)
    xy = np.column_stack([c * x - s * y, s * x + c * y]) + np.asarray(part.centre)
    return np.column_stack([xy, np.full(len(phi), z)])


def _levels(z0: float, z1: float, unit: float, scale: str) -> np.ndarray:
    """Return ring heights from z0 to z1: fine inside the scanned band, coarse outside."""
    lo, hi = (v * unit for v in _BAND_MM)
    fine, coarse = _BAND_STEP[scale], _COARSE_STEP[scale]
    marks = sorted({z0, z1, *(v for v in (lo, hi) if z0 < v < z1)})
    out = []
    for p, q in itertools.pairwise(marks):
        step = fine if lo <= 0.5 * (p + q) <= hi else coarse
        out.append(np.linspace(p, q, max(2, math.ceil((q - p) / step) + 1)))
    z = np.concatenate(out)
    return z[np.concatenate([[True], np.diff(z) > 1e-9])]


def _end(kind: str, z_edge: float, height: float) -> tuple[np.ndarray, np.ndarray]:
    """Return (heights, scales) of an end beyond ``z_edge`` (height < 0: downwards).

    A dome is a quarter ellipse; a tip an ogive (the scale falls as cos^2.5), narrow at
    its apex. Either ends in scale 0, an apex that closes the loft.
    """
    theta = np.linspace(0.0, 0.5 * math.pi, _END_RINGS + 1)[1:]
    power = 2.5 if kind == "tip" else 1.0
    scale = np.cos(theta) ** power
    scale[-1] = 0.0
    return z_edge + height * np.sin(theta), scale


def _part_triangles(part: _Part, unit: float, scale: str) -> np.ndarray:
    """Return the triangles (F, 3, 3) of one part: the loft, its ends and caps."""
    z0, z1 = part.z_range
    body = _levels(z0, z1, unit, scale)
    zs, ss = [body], [np.ones_like(body)]
    bottom, top = part.ends
    if bottom in ("dome", "tip"):
        z, s = _end(bottom, z0, -part.end_height_mm[0])
        zs.insert(0, z[::-1])
        ss.insert(0, s[::-1])
    if top in ("dome", "tip"):
        z, s = _end(top, z1, part.end_height_mm[1])
        zs.append(z)
        ss.append(s)
    z_all, s_all = np.concatenate(zs), np.concatenate(ss)
    a, b = part.half_axes
    perimeter = math.pi * (a + b) * (1.0 + abs(part.bend_rad) / 4.0) * (1.0 + _max_shape(part))
    n = int(np.clip(math.ceil(perimeter * part.arc_deg / 360.0 / _EDGE_MM[scale]), 24, 960))
    n = min(n, _MAX_RING_VERTICES) if part.arc_deg >= 360.0 else n
    closed = part.arc_deg >= 360.0
    if closed:
        phi = np.linspace(0.0, 2.0 * math.pi, n, endpoint=False)
    else:
        half = math.radians(part.arc_deg) / 2.0
        phi = np.linspace(-half, half, n)
    rings = [_ring(part, phi, float(z), float(s)) for z, s in zip(z_all, s_all, strict=True)]
    idx = np.arange(n)
    nxt = np.roll(idx, -1) if closed else idx[1:]
    cur = idx if closed else idx[:-1]
    tris = []
    for r0, r1 in itertools.pairwise(rings):
        tris.append(np.stack([r0[cur], r0[nxt], r1[nxt]], axis=1))
        tris.append(np.stack([r0[cur], r1[nxt], r1[cur]], axis=1))
    if closed:
        for ring, s, kind in ((rings[0], s_all[0], bottom), (rings[-1], s_all[-1], top)):
            if s > 0.0 and kind == "flat":
                hub = np.broadcast_to(ring.mean(axis=0), ring.shape)
                tris.append(np.stack([hub, ring[cur], ring[nxt]], axis=1))
    return np.concatenate(tris)


def _max_shape(part: _Part) -> float:
    """Return the largest relative bulge of the harmonics (for sizes and spacing)."""
    return float(sum(abs(amp) for _, amp, _ in part.harmonics))


def _reach_mm(part: _Part) -> float:
    """Return a bound on how far the part reaches from its centre in any section."""
    a, b = part.half_axes
    relief = float(np.sum(part.relief.amplitude_mm))
    size = (1.0 + abs(part.taper) / 2.0) * (1.0 + _max_shape(part))
    return max(a, b) * size + relief


def _rotation(tilt_deg: float, tilt_dir_rad: float, yaw_rad: float) -> np.ndarray:
    """Return the 3x3 rotation: tilt about the horizontal axis at ``tilt_dir_rad``, then yaw."""
    # Turning about the axis at azimuth d leans +z towards d - 90 degrees.
    tilt = tilt_matrix(tilt_deg, math.degrees(tilt_dir_rad) - 90.0)
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    yaw = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return yaw @ tilt


def _relief(rng: np.random.Generator, scale: str) -> _Relief:
    """Draw skin relief (or none): 0.1-1 mm in all, wavelengths 3-30 mm."""
    if rng.random() < 0.25:
        return _NO_RELIEF
    count = int(rng.integers(1, 4))
    total = float(rng.uniform(0.1, _RELIEF_SCALE_CAP[scale]))
    weights = rng.dirichlet(np.ones(count))
    return _Relief(
        total * weights,
        np.exp(rng.uniform(math.log(3.0), math.log(30.0), count)),
        rng.uniform(0.0, math.pi, count),
        rng.uniform(0.0, 2.0 * math.pi, count),
    )


def _end_kind(rng: np.random.Generator, kinds: tuple[str, ...], p: tuple[float, ...]) -> str:
    """Draw one end finish."""
    return str(rng.choice(kinds, p=np.asarray(p) / sum(p)))


def _body(rng: np.random.Generator, unit: float, scale: str) -> tuple[_Part | None, str, bool]:
    """Draw the main body (or none): its part, its kind and whether it is wide."""
    kind = str(rng.choice(["star", "bent", "shell", "none"], p=[0.5, 0.2, 0.15, 0.15]))
    if kind == "none":
        return None, kind, False
    wide = bool(rng.random() < 0.1)
    mean_r = unit * (rng.uniform(24.0, 30.0) if wide else rng.uniform(5.0, 12.0))
    aspect = rng.uniform(1.0, 1.8)
    if kind == "bent":
        aspect = rng.uniform(2.2, 3.2)
    a = mean_r * math.sqrt(aspect)
    b = mean_r / math.sqrt(aspect)
    harmonics = tuple(
        (int(k), float(rng.uniform(0.0, 0.06)), float(rng.uniform(0.0, 2.0 * math.pi)))
        for k in rng.choice([2, 3, 4, 5], size=int(rng.integers(0, 3)), replace=False)
    )
    dents = tuple(
        (
            float(rng.uniform(0, 2 * math.pi)),
            float(rng.uniform(0.05, 0.2)),
            float(rng.uniform(0.2, 0.5)),
        )
        for _ in range(int(rng.integers(0, 3)))
    )
    bottom = _end_kind(rng, ("dome", "tip", "flat", "rim", "beyond"), (3, 1, 1, 1, 2))
    top = _end_kind(rng, ("dome", "flat", "rim", "beyond"), (1, 1, 3, 2))
    arc = 360.0
    if kind == "shell":
        # A face: a nose (a negative dent) between two eye sockets, over an open arc.
        arc = float(rng.uniform(100.0, 220.0))
        dents += ((0.0, -0.15, 0.12), (0.45, 0.08, 0.15), (-0.45, 0.08, 0.15))
        bottom = "rim" if bottom in ("dome", "tip", "flat") else bottom
        top = "rim" if top in ("dome", "flat") else top
    z0 = unit * float(rng.uniform(-6.0, 1.0)) if bottom != "beyond" else -unit * 30.0
    z1 = unit * float(rng.uniform(14.0, 30.0))
    if top == "beyond":
        z1 = SIM_LIFT_TRAVEL_MM + unit * 20.0
    part = _Part(
        centre=(0.0, 0.0),
        half_axes=(a, b),
        angle_rad=float(rng.uniform(0.0, 2.0 * math.pi)),
        harmonics=harmonics,
        dents=dents,
        bend_rad=float(rng.uniform(2.6, 4.0)) if kind == "bent" else 0.0,
        z_range=(z0, z1),
        ends=(bottom, top),
        end_height_mm=(b * float(rng.uniform(0.5, 1.5)), b * float(rng.uniform(0.5, 1.2))),
        taper=float(rng.uniform(-0.3, 0.3)),
        waist=(float(rng.uniform(0.0, 0.12)), float(rng.uniform(0.0, 12.0)) * unit, 3.0 * unit),
        arc_deg=arc,
        relief=_relief(rng, scale),
    )
    return part, kind, wide


def _small_part(
    rng: np.random.Generator, unit: float, scale: str, centre: tuple[float, float], thin: bool
) -> _Part:
    """Draw a finger, a flap (2-6 mm thick) or a stalk standing at ``centre``."""
    if thin:
        half_thick = float(rng.uniform(1.0, 3.0))  # 2-6 mm thick at either scale
        half_wide = half_thick * float(rng.uniform(1.0, 2.5 if scale == "thesis" else 4.0))
    else:
        half_thick = unit * float(rng.uniform(1.5, 3.5))
        half_wide = half_thick * float(rng.uniform(1.0, 1.6))
    z0 = unit * float(rng.uniform(-8.0, -1.0))
    z1 = unit * float(rng.uniform(1.0, 14.0))
    top = _end_kind(rng, ("dome", "tip", "flat"), (3, 2, 1))
    return _Part(
        centre=centre,
        half_axes=(half_wide, half_thick),
        angle_rad=float(rng.uniform(0.0, 2.0 * math.pi)),
        z_range=(z0, z1),
        ends=("dome", top),
        end_height_mm=(half_thick, half_thick * float(rng.uniform(1.0, 3.0))),
        taper=float(rng.uniform(-0.3, 0.2)),
        relief=_relief(rng, scale) if not thin and rng.random() < 0.3 else _NO_RELIEF,
    )


def _place_parts(
    rng: np.random.Generator, unit: float, scale: str, body: _Part | None, count: int
) -> list[_Part]:
    """Draw ``count`` parts around the body (or in a row), none touching another."""
    gap = unit * float(rng.uniform(1.2, 3.0))
    if body is None:
        return _row(rng, unit, scale, count, gap)
    parts: list[_Part] = []
    body_reach = _reach_mm(body)
    for _ in range(count):
        thin = bool(rng.random() < 0.5)
        for _attempt in range(40):
            ang = float(rng.uniform(0.0, 2.0 * math.pi))
            rho = body_reach + gap + unit * float(rng.uniform(2.0, 6.0))
            centre = (rho * math.cos(ang), rho * math.sin(ang))
            part = _small_part(rng, unit, scale, centre, thin)
            if all(
                math.dist(centre, o.centre) > _reach_mm(part) + _reach_mm(o) + gap
                for o in [*parts, body]
            ):
                parts.append(part)
                break
    return parts


def _row(rng: np.random.Generator, unit: float, scale: str, count: int, gap: float) -> list[_Part]:
    """Draw ``count`` digits side by side across the axis, ``gap`` apart at their widest."""
    parts: list[_Part] = []
    x = 0.0
    for k in range(count):
        part = _small_part(rng, unit, scale, (0.0, 0.0), bool(rng.random() < 0.5))
        reach = _reach_mm(part)
        x += reach if k else 0.0
        parts.append(replace(part, centre=(x, unit * float(rng.uniform(-2.0, 2.0)))))
        x += reach + gap
    middle = 0.5 * (parts[0].centre[0] + parts[-1].centre[0]) if parts else 0.0
    return [replace(p, centre=(p.centre[0] - middle, p.centre[1])) for p in parts]


def random_shape(seed: int, scale: str = "thesis") -> RandomShape:
    """Return the random anatomy-like object of ``seed`` at ``scale`` (thesis or limb).

    Args:
        seed: any non-negative integer; the same seed and scale give the same object.
        scale: ``thesis`` (bodies 10-30 mm across, some wider than the 45 mm view) or
            ``limb`` (five times larger, for ``--rig limb``).

    Returns:
        The placed mesh (object frame: turntable axis, first section at z = 0) with the
        features it was drawn with.

    Raises:
        ValueError: an unknown scale or a negative seed.
    """
    if scale not in SCALES:
        raise ValueError(f"random: scale={scale!r} is not one of {', '.join(SCALES)}")
    if seed < 0:
        raise ValueError(f"random: seed={seed} must be a non-negative integer")
    unit = SCALES[scale]
    rng = np.random.default_rng([seed, list(SCALES).index(scale)])
    body, kind, wide = _body(rng, unit, scale)
    count = int(rng.integers(2, 6)) if body is None else int(rng.choice([0, 0, 1, 2, 3, 4]))
    parts = _place_parts(rng, unit, scale, body, count)
    solids = ([body] if body is not None else []) + parts
    tris = np.concatenate([_part_triangles(p, unit, scale) for p in solids])
    tilt = float(rng.uniform(5.0, 20.0)) if rng.random() < 0.35 else 0.0
    rot = _rotation(tilt, float(rng.uniform(0, 2 * math.pi)), float(rng.uniform(0, 2 * math.pi)))
    offset = unit * float(rng.uniform(0.0, 6.0)) if rng.random() < 0.5 else 0.0
    shift_dir = float(rng.uniform(0.0, 2.0 * math.pi))
    shift = np.array([offset * math.cos(shift_dir), offset * math.sin(shift_dir), 0.0])
    placed = tris @ rot.T + shift
    ends = body.ends if body is not None else ("none", "none")
    thin = sum(1 for p in parts if 2.0 * min(p.half_axes) <= 6.0)
    features = ShapeFeatures(
        seed=seed,
        scale=scale,
        body=kind,
        parts=len(parts),
        thin_parts=thin,
        bottom=ends[0],
        top=ends[1],
        relief_mm=float(np.sum(body.relief.amplitude_mm)) if body is not None else 0.0,
        relief_wavelength_mm=float(np.min(body.relief.wavelength_mm))
        if body is not None and len(body.relief.wavelength_mm)
        else 0.0,
        tilt_deg=tilt,
        offset_mm=offset,
        wide=wide or (body is not None and _reach_mm(body) > _FIELD_HALF_MM * unit),
        tall=ends[1] == "beyond",
        closed=body is None or (kind != "shell" and "rim" not in ends and "beyond" not in ends),
    )
    mesh = TriangleMesh.from_triangles(placed)
    name = f"random:seed={seed},scale={scale}"
    return RandomShape(mesh.vertices, mesh.faces, name, features)


def parse_random_spec(body: str, form: str) -> RandomShape:
    """Build the object of ``random:seed=N[,scale=thesis|limb]`` (the part after the colon).

    Args:
        body: ``seed=17,scale=limb``.
        form: the example form to quote in error messages.

    Returns:
        The object :func:`random_shape` draws.

    Raises:
        ValueError: a missing, repeated or unknown key or a bad value (one line).
    """
    fields: dict[str, str] = {}
    for part in filter(None, (p.strip() for p in body.split(","))):
        key, eq, value = (s.strip() for s in part.partition("="))
        if not eq or not value:
            raise ValueError(f"random: {part!r} is not key=value; expected e.g. {form}")
        if key not in ("seed", "scale"):
            raise ValueError(
                f"random: unknown key {key!r}; accepted: scale, seed and the placement keys "
                f"x, y, z, yaw, tilt, tilt_dir (e.g. {form})"
            )
        if key in fields:
            raise ValueError(f"random: key {key!r} given twice; expected e.g. {form}")
        fields[key] = value
    if "seed" not in fields:
        raise ValueError(f"random: missing seed=; expected e.g. {form}")
    seed = fields["seed"]
    if not seed.isdigit():
        raise ValueError(f"random: seed={seed!r} must be a non-negative integer; e.g. {form}")
    return random_shape(int(seed), fields.get("scale", "thesis").lower())
