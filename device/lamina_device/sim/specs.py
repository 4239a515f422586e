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
from lamina_device.sim.random_shapes import parse_random_spec
from lamina_device.sim.texture import patches_cylinder

__all__ = ["MAX_OBJECT_MM", "MIN_SIZE_MM", "SCALE_RANGE", "parse_object"]


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
_PLACEMENT = {"x", "y", "z", "yaw"}
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
        if key in {"x", "y", "z"}
        else (-math.inf, math.inf)
    )
    if not low <= x <= high:
        unit = "" if key == "scale" else " mm"
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
    on the axis, so no placement keys) and ``random`` (``random:seed=17,scale=limb``: the
    seed's random anatomy-like object, :mod:`lamina_device.sim.random_shapes`; it places
    itself, so no placement keys).
    """
    kind, colon, body = spec.strip().partition(":")
    kind = kind.strip().lower()
    if kind not in _FORMS:
        kinds = ", ".join(f[0] for f in _FORMS.values())
        raise ValueError(f"unknown object kind {kind!r} in {spec!r}; accepted forms: {kinds}")
    form = _FORMS[kind][0]
    if kind == "random":
        return parse_random_spec(body if colon else "", form)
    fields = _parse_fields(kind, body if colon else "", form)
    num = {k: _number(kind, k, v, form) for k, v in fields.items() if k != "path"}
    x, y, yaw = num.get("x", 0.0), num.get("y", 0.0), num.get("yaw", 0.0)
    if kind == "cylinder":
        return Cylinder(num["d"], num.get("h", 40.0), x, y, num.get("z", -5.0))
    if kind == "sphere":
        return sphere(num["d"], x, y, num.get("z", 0.0))
    if kind == "ellipsoid":
        return ellipsoid(num["a"], num["b"], num["c"], x, y, num.get("z", 0.0), yaw)
    if kind == "patches":
        return patches_cylinder(num.get("d", 30.0), num.get("h", 40.0))
    placement = Placement(num.get("scale", 1.0), yaw, (x, y, num.get("z", 0.0)))
    if kind in PHANTOMS:
        return _check_extent(kind, phantom(kind, placement, num.get("relief"), num.get("wave")))
    return _check_extent(kind, load_mesh(fields["path"], placement))
