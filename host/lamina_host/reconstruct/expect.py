"""Known shapes to check a scan against: ``--expect cylinder:d=19.05`` and friends.

An expectation gives the true outline radius of each section as a function of the
polar angle about the section's centre, so the thesis's accuracy figure (Table 8.3,
RMS radial error about each section's own centroid and about the mean centroid)
can be computed for round and for oval objects alike.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

_KEYS = {
    "cylinder": ({"d"}, {"h", "x", "y", "z"}),
    "sphere": ({"d"}, {"x", "y", "z"}),
    "ellipsoid": ({"a", "b", "c"}, {"x", "y", "z"}),
}


@dataclass(frozen=True)
class Expectation:
    """A known object: ``kind`` with semi-axes ``a``/``b`` in the plane, ``c`` vertically."""

    kind: str
    a_mm: float
    b_mm: float
    c_mm: float
    centre_z_mm: float
    spec: str

    def radius_mm(self, phi: np.ndarray, z_mm: float) -> np.ndarray:
        """Return the true outline radius at polar angles ``phi`` of the section at ``z_mm``."""
        scale = 1.0
        if self.kind in ("sphere", "ellipsoid"):
            u = (z_mm - self.centre_z_mm) / self.c_mm
            scale = math.sqrt(max(0.0, 1.0 - u * u))
        a, b = self.a_mm * scale, self.b_mm * scale
        return a * b / np.sqrt((b * np.cos(phi)) ** 2 + (a * np.sin(phi)) ** 2)


def parse_expectation(spec: str) -> Expectation:
    """Parse ``cylinder:d=19.05``, ``sphere:d=25[,z=0]`` or ``ellipsoid:a=,b=,c=[,z=]``."""
    kind, _, rest = spec.partition(":")
    if kind not in _KEYS:
        raise ValueError(
            f"--expect {spec!r}: unknown shape {kind!r}; use cylinder:d=MM, sphere:d=MM "
            "or ellipsoid:a=MM,b=MM,c=MM"
        )
    values: dict[str, float] = {}
    for item in filter(None, rest.split(",")):
        key, eq, text = item.partition("=")
        try:
            values[key.strip()] = float(text) if eq else math.nan
        except ValueError:
            raise ValueError(f"--expect {spec!r}: {key}={text!r} is not a number") from None
    required, optional = _KEYS[kind]
    problems = [f"{k} is missing" for k in sorted(required - values.keys())]
    problems += [f"{k} is not a known key" for k in sorted(values.keys() - required - optional)]
    problems += [
        f"{k} must be a positive number"
        for k in sorted(required & values.keys())
        if not (values[k] > 0 and math.isfinite(values[k]))
    ]
    if problems:
        raise ValueError(f"--expect {spec!r}: " + "; ".join(problems))
    if kind == "ellipsoid":
        a, b, c = values["a"], values["b"], values["c"]
    else:
        a = b = c = values["d"] / 2.0
    return Expectation(kind, a, b, c, values.get("z", 0.0), spec)
