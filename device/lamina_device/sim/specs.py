"""What ``--object`` names: a solid, a mesh file, a phantom or a random shape, parsed.

A spec is ``kind:key=value,...``. Every number is checked (finite, positive where it is
a size, within what a simulated rig can hold) and every refusal names the key and shows
the accepted form, so a typo gives one line rather than a renderer working on nonsense.
"""

from __future__ import annotations

import math

import numpy as np

from lamina_device.sim.objects import (
    Cylinder,
    Placement,
    SceneObject,
    TriangleMesh,
    ellipsoid,
    load_mesh,
    sphere,
)
from lamina_device.sim.phantoms import PHANTOMS, RELIEF_PHANTOMS, phantom
from lamina_device.sim.random_shapes import RandomShape, parse_random_spec
from lamina_device.sim.texture import patches_cylinder

__all__ = ["MAX_OBJECT_MM", "MAX_TILT_DEG", "MIN_SIZE_MM", "SCALE_RANGE", "parse_object"]


_FORMS = {
    "cylinder": ("cylinder:d=19.05,h=40", {"d"}, {"h"}),
    "sphere": ("sphere:d=25", {"d"}, set()),
    "ellipsoid": ("ellipsoid:a=10,b=6.5,c=20", {"a", "b", "c"}, set()),
    "mesh": ("mesh:path=/some/file.stl,scale=1", {"path"}, {"scale"}),
    "patches": ("patches:d=30,h=40", set(), {"d", "h"}),
    "random": ("random:seed=17,scale=thesis", {"seed"}, {"scale"}),
    **{name: (f"{name}:scale=1", set(), {"scale"}) for name in PHANTOMS},
    **{
        name: (f"{name}:scale=1,relief=0.3,wave=10", set(), {"scale", "relief", "wave"})
        for name in RELIEF_PHANTOMS
    },
}
_PLACEMENT = {"x", "y", "z", "yaw", "tilt", "tilt_dir", "pivot"}
_TILTED = ("mesh", "random", *PHANTOMS)
"""The kinds that take ``tilt=`` (the solids and the patches cylinder stand upright)."""
MAX_TILT_DEG = 60.0
"""Steepest tilt a placed object may have: beyond it no horizontal section is a limb's."""
_POSITIVE = {"d", "h", "a", "b", "c", "scale", "relief", "wave"}
MAX_OBJECT_MM = 1000.0
"""Largest size, distance from the axis or extent a simulated object may have: a metre,
far beyond any turntable (the limb rig's field is a few hundred mm)."""
MIN_SIZE_MM = 0.01
"""Smallest size of a simulated solid: below a pixel of any rig."""
SCALE_RANGE = (1e-3, 1e3)
"""Scales a phantom or mesh may take (a mesh in metres needs 1000)."""
_LENGTHS = {"d", "h", "a", "b", "c"}


def _parse_fields(kind: str, body: str, form: str) -> dict[str, str]:
    """Split ``k=v,k=v`` into a dict, rejecting malformed, empty, repeated or unknown keys."""
    _, required, optional = _FORMS[kind]
    allowed = required | optional | _PLACEMENT
    fields: dict[str, str] = {}
    for part in filter(None, (p.strip() for p in body.split(","))):
        key, eq, value = (s.strip() for s in part.partition("="))
        if not eq:
            raise ValueError(f"{kind}: {part!r} is not key=value; expected e.g. {form}")
        if key not in allowed:
            raise ValueError(
                f"{kind}: unknown key {key!r}; accepted: {', '.join(sorted(allowed))} (e.g. {form})"
            )
        if key in fields:
            raise ValueError(f"{kind}: key {key!r} given twice; expected e.g. {form}")
        if not value:
            raise ValueError(f"{kind}: key {key!r} has no value; expected e.g. {form}")
        fields[key] = value
    missing = sorted(required - fields.keys())
    if missing:
        raise ValueError(
            f"{kind}: missing {', '.join(k + '=' for k in missing)}; expected e.g. {form}"
        )
    return fields


def _number(kind: str, key: str, value: str, form: str) -> float:
    """Parse one finite number (positive for sizes), naming the key when it is bad."""
    try:
        x = float(value)
    except ValueError:
        raise ValueError(f"{kind}: {key}={value!r} is not a number; expected e.g. {form}") from None
    if not math.isfinite(x) or (key in _POSITIVE and x <= 0):
        kind_of = "a positive number" if key in _POSITIVE else "a finite number"
        raise ValueError(f"{kind}: {key}={value!r} must be {kind_of}; expected e.g. {form}")
    # Bounded, so a typo cannot make the renderer work on a kilometre-wide object.
    low, high = (
        SCALE_RANGE
        if key == "scale"
        else (MIN_SIZE_MM, MAX_OBJECT_MM)
        if key in _LENGTHS
        else (-MAX_OBJECT_MM, MAX_OBJECT_MM)
        if key in {"x", "y", "z", "pivot"}
        else (0.0, MAX_TILT_DEG)
        if key == "tilt"
        else (-math.inf, math.inf)
    )
    if not low <= x <= high:
        unit = "" if key == "scale" else " deg" if key == "tilt" else " mm"
        raise ValueError(
            f"{kind}: {key}={value} is outside {low:g}..{high:g}{unit}, beyond what the "
            f"simulated rig can hold; expected e.g. {form}"
        )
    return x


def _check_extent(kind: str, mesh: TriangleMesh) -> TriangleMesh:
    """Return ``mesh`` unless it is larger than :data:`MAX_OBJECT_MM` across."""
    if len(mesh.vertices):
        extent = float(np.max(np.ptp(mesh.vertices, axis=0)))
        reach = float(np.max(np.abs(mesh.vertices)))
        if not (math.isfinite(extent) and extent <= MAX_OBJECT_MM and reach <= 2 * MAX_OBJECT_MM):
            raise ValueError(
                f"{kind}: the placed object is {extent:.4g} mm across, beyond the "
                f"{MAX_OBJECT_MM:g} mm a simulated rig can hold; use a smaller scale"
            )
    return mesh


def parse_object(spec: str) -> SceneObject:
    """Build a scene object from ``kind:key=value,...``: a solid, a mesh file or a phantom.

    Kinds: cylinder, sphere, ellipsoid, mesh, the phantoms of
    :mod:`lamina_device.sim.phantoms` (hand, foot, bust, bone, ring, stump, arm, face;
    ``scale=``; the limbs arm and stump also ``relief=`` and ``wave=``, skin relief),
    ``patches`` (a skin-tone cylinder with colour patches, :mod:`lamina_device.sim.texture`;
    on the axis) and ``random`` (``random:seed=17,scale=limb``: the seed's random
    anatomy-like object, :mod:`lamina_device.sim.random_shapes`, which places itself
    before any placement keys move it).

    Placement keys: ``x=``, ``y=``, ``z=`` (mm) and ``yaw=`` (deg) for every kind but
    ``patches``; ``tilt=`` (deg, 0 to :data:`MAX_TILT_DEG`), ``tilt_dir=`` (the azimuth
    the top leans towards, deg, default 0: +x) and ``pivot=`` (the height on the object's
    own axis it leans about, scaled mm, default 0) for phantoms, meshes and random shapes:
    yaw about the object's own axis, then the tilt about the pivot, then the shift.
    """
    kind, colon, body = spec.strip().partition(":")
    kind = kind.strip().lower()
    if kind not in _FORMS:
        kinds = ", ".join(f[0] for f in _FORMS.values())
        raise ValueError(f"unknown object kind {kind!r} in {spec!r}; accepted forms: {kinds}")
    form = _FORMS[kind][0]
    if kind == "random":
        return _placed_random(body if colon else "", form)
    fields = _parse_fields(kind, body if colon else "", form)
    num = {k: _number(kind, k, v, form) for k, v in fields.items() if k != "path"}
    _check_tilt(kind, num, form)
    x, y, yaw = num.get("x", 0.0), num.get("y", 0.0), num.get("yaw", 0.0)
    if kind == "cylinder":
        return Cylinder(num["d"], num.get("h", 40.0), x, y, num.get("z", -5.0))
    if kind == "sphere":
        return sphere(num["d"], x, y, num.get("z", 0.0))
    if kind == "ellipsoid":
        return ellipsoid(num["a"], num["b"], num["c"], x, y, num.get("z", 0.0), yaw)
    if kind == "patches":
        return patches_cylinder(num.get("d", 30.0), num.get("h", 40.0))
    placement = _placement(num, num.get("scale", 1.0))
    if kind in PHANTOMS:
        return _check_extent(kind, phantom(kind, placement, num.get("relief"), num.get("wave")))
    return _check_extent(kind, load_mesh(fields["path"], placement))


def _placement(num: dict[str, float], scale: float = 1.0) -> Placement:
    """Return the placement the keys ask for: scale, yaw, tilt (and its direction), shift."""
    shift = (num.get("x", 0.0), num.get("y", 0.0), num.get("z", 0.0))
    return Placement(scale, num.get("yaw", 0.0), shift, num.get("tilt", 0.0),
                     num.get("tilt_dir", 0.0), num.get("pivot", 0.0))  # fmt: skip


def _check_tilt(kind: str, num: dict[str, float], form: str) -> None:
    """Refuse ``tilt=``, ``tilt_dir=``, ``pivot=`` on a kind that stands upright, and the
    last two without a tilt (one line)."""
    if ("tilt" in num or "tilt_dir" in num or "pivot" in num) and kind not in _TILTED:
        raise ValueError(
            f"{kind}: tilt= is offered on the phantoms, mesh files and random shapes; a "
            f"{kind} stands upright (e.g. {form})"
        )
    for key in ("tilt_dir", "pivot"):
        if key in num and "tilt" not in num:
            raise ValueError(f"{kind}: {key}= needs tilt= (the tilt in degrees); e.g. tilt=3")


def _placed_random(body: str, form: str) -> SceneObject:
    """Build ``random:seed=N[,scale=...]`` and move it by any placement keys given.

    The shape places itself first (its own offset and tilt); ``x=``, ``y=``, ``z=``,
    ``yaw=``, ``tilt=``, ``tilt_dir=`` and ``pivot=`` then move it as they move a phantom.
    """
    own: list[str] = []
    moves: list[str] = []
    for part in filter(None, (p.strip() for p in body.split(","))):
        key = part.partition("=")[0].strip()
        (moves if key in _PLACEMENT else own).append(part)
    shape = parse_random_spec(",".join(own), form)
    if not moves:
        return shape
    fields: dict[str, str] = {}
    for part in moves:
        key, _, value = (s.strip() for s in part.partition("="))
        if key in fields:
            raise ValueError(f"random: key {key!r} given twice; expected e.g. {form}")
        if not value:
            raise ValueError(f"random: key {key!r} has no value; expected e.g. {form}")
        fields[key] = value
    num = {k: _number("random", k, v, form) for k, v in fields.items()}
    _check_tilt("random", num, form)
    placed = _placement(num).apply(shape.vertices)
    moved = RandomShape(placed, shape.faces, shape.name, shape.features)
    return _check_extent("random", moved)
