"""A limb's mesh in the frame prosthetic and orthotic CAD works in (``.limb.stl`` exports).

The limb frame, in mm:

- **z** runs along the limb's axis from its distal end towards the proximal end: the straight
  centre line fitted through the section centroids (:func:`~lamina_host.clinical.measures.fit_axis`,
  ``centreline``), the axis ``lamina report --limb-axis centreline`` measures along. With fewer
  than two closed sections there is no centre line and the turntable axis is used.
- **origin**: the point of that axis level with the distal extremity of the mesh, so the
  mesh's lowest point has z = 0. The distal end is the narrower end, as the clinical
  measurements take it (:func:`~lamina_host.clinical.measures.measure_limb`).
- **x, y**: the scanner's turntable x and y turned by the smallest rotation that brings the
  axis onto z (a half turn about x when the distal end was at the top).

The transform is a rotation and a translation, so lengths, girths and the volume stay as they
were. The frame is written into the STL header (80 characters) and, in full, into a JSON
sidecar: the axis (scanner frame), the landmark, which end was distal, and the 4x4 matrix
from scanner to limb coordinates.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from lamina_host.clinical.measures import (
    AXES,
    ClinicalError,
    LimbAxis,
    measure_limb,
    sections_from_report,
)
from lamina_host.reconstruct.mesh import load_ply, signed_volume, stl_bytes
from lamina_host.store.library import Library

FRAME_AXIS = "centreline"
"""The axis the limb frame's z follows (falls back to the turntable's, see the module text)."""


@dataclass(frozen=True)
class LimbFrame:
    """Where the limb frame lies in the scanner's: the axis, the distal end and the transform.

    Attributes:
        axis: the limb axis in scanner coordinates (z component > 0).
        distal_top: the distal end was at the top of the scan (the axis is reversed).
        rotation: the 3x3 rotation taking scanner directions to limb-frame ones.
        origin_mm: the limb frame's origin in scanner coordinates (on the axis).
    """

    axis: LimbAxis
    distal_top: bool
    rotation: tuple[tuple[float, ...], ...]
    origin_mm: tuple[float, float, float]

    def matrix(self) -> np.ndarray:
        """Return the 4x4 homogeneous transform from scanner to limb-frame coordinates."""
        r = np.array(self.rotation)
        m = np.eye(4)
        m[:3, :3] = r
        m[:3, 3] = -r @ np.array(self.origin_mm)
        return m

    def apply(self, points_mm: np.ndarray) -> np.ndarray:
        """Return scanner-frame points (N, 3) in limb-frame coordinates."""
        return (np.asarray(points_mm, float) - np.array(self.origin_mm)) @ np.array(self.rotation).T

    def header(self) -> str:
        """Return the STL header text (at most 80 ASCII characters) naming the frame."""
        end = "top" if self.distal_top else "bottom"
        text = (
            f"Lamina limb frame: +z limb axis ({self.axis.method}, tilt "
            f"{self.axis.tilt_deg:.1f} deg), distal end ({end}) at z=0"
        )
        return text[:80]


def rotation_onto_z(direction: np.ndarray) -> np.ndarray:
    """Return the smallest rotation taking the unit vector ``direction`` onto +z.

    Rodrigues' formula about ``direction x z``; the opposite vector, -z, takes a half
    turn about x (any axis normal to z would do; x keeps y's sign convention readable).
    """
    d = np.asarray(direction, float) / np.linalg.norm(direction)
    z = np.array([0.0, 0.0, 1.0])
    c = float(d @ z)
    if c < -1.0 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(d, z)
    k = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + k + k @ k / (1.0 + c)


def _axis_point(axis: LimbAxis, z_mm: float) -> np.ndarray:
    """Return the point of the axis at height ``z_mm`` (scanner frame)."""
    position = float(axis.position_mm(z_mm))
    return np.array(axis.origin_mm) + position * np.array(axis.direction)


def limb_frame(report: dict[str, Any], vertices_mm: np.ndarray, scan_id: int) -> LimbFrame:
    """Return the limb frame of a processed scan: from its report's outlines and its mesh.

    Raises:
        ClinicalError: the report holds no outlines the clinical measurements can use.
    """
    sections = sections_from_report(report, scan_id)
    try:
        measured = measure_limb(sections, axis=FRAME_AXIS)
    except ClinicalError:
        measured = measure_limb(sections, axis=AXES[0])  # a single closed section
    lo, hi = measured.coverage_mm
    distal_top = hi > lo and math.isclose(measured.landmark_z_mm, hi, abs_tol=1e-6)
    axis = measured.axis
    up = -np.array(axis.direction) if distal_top else np.array(axis.direction)
    rotation = rotation_onto_z(up)
    # The origin: the axis point level with the distal section, then moved along the axis
    # to the mesh's own distal extremity (its caps may reach past that section).
    anchor = _axis_point(axis, measured.landmark_z_mm)
    lowest = float(((np.asarray(vertices_mm, float) - anchor) @ rotation.T)[:, 2].min())
    origin = anchor + lowest * up
    return LimbFrame(
        axis,
        distal_top,
        tuple(tuple(float(x) for x in row) for row in rotation),
        (float(origin[0]), float(origin[1]), float(origin[2])),
    )


def limb_stl_files(library: Library, scan_id: int) -> tuple[bytes, bytes]:
    """Return the scan's mesh in the limb frame as binary STL, and its JSON sidecar.

    Raises:
        StoreError: the scan has no result or no mesh.
        ClinicalError: its report holds no outlines to find the limb axis from.
    """
    vertices, faces = load_ply(library.result_mesh(scan_id))
    record = library.scan(scan_id)
    frame = limb_frame(library.result(scan_id) or {}, vertices, scan_id)
    moved = frame.apply(vertices)
    stl = stl_bytes(moved, faces, frame.header())
    sidecar = {
        "format": "Lamina limb-frame STL",
        "scan_id": scan_id,
        "subject": record.subject,
        "side": record.side,
        "units": "mm",
        "frame": {
            "z": "the limb axis, from the distal end towards the proximal end",
            "origin": "the point of the limb axis level with the mesh's distal extremity",
            "x_y": "the scanner's x and y, turned by the smallest rotation taking the axis to z",
        },
        "landmark": "distal end",
        "distal_end": "top" if frame.distal_top else "bottom",
        "axis_scanner": frame.axis.to_dict(),
        "origin_scanner_mm": list(frame.origin_mm),
        "scanner_to_limb": frame.matrix().tolist(),
        "length_mm": float(moved[:, 2].max()) if len(moved) else 0.0,
        "volume_mm3": signed_volume(moved, faces),
    }
    return stl, (json.dumps(sidecar, indent=2) + "\n").encode()
