"""The compact follow-up record of a scan (``.lrec``): EFD coefficients, calibration, axis.

A clinic keeps years of follow-up visits; the record keeps what is needed to redraw a
scan's contours, re-measure it and rebuild its mesh in a few kilobytes (a 40-section limb
scan fits in well under 10 KB), where the raw segments take megabytes.

Layout: ``b"LREC"``, one version byte, then a zlib stream holding a little-endian u32
length, that many bytes of JSON (scan, subject code, limb side, calibration and axis
summaries, processing options, one row per outline: section, part, height, harmonics,
segments)
and the coefficients. Each outline's EFD is first aligned (counter-clockwise, starting
on the +x ray, :func:`lamina_host.reconstruct.efd.align`: the same curve, so the same measurements),
padded to the record's largest order, quantised to :data:`QUANTUM_MM` and differenced
from the outline before it; neighbouring sections of a limb differ little, so these
differences are small integers, zig-zag coded and split into byte planes before zlib.
The quantisation moves a contour point by about 10 um at most (with 100 harmonics).
A record written before the side was kept reads as side ``none``.
"""

from __future__ import annotations

import json
import struct
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from lamina_host.reconstruct.efd import EllipticFourier, align
from lamina_host.reconstruct.mesh import signed_volume
from lamina_host.reconstruct.pipeline import ProcessOptions, Reconstruction, Section, build_mesh
from lamina_shared.errors import LaminaError

MAGIC = b"LREC"
VERSION = 1
QUANTUM_MM = 1e-3
"""Coefficient step: 1 um, a tenth of the best scan's point noise."""

CALIBRATION_KEYS = ("method", "matrix", "division_k", "distortion_centre_px",
                    "distortion_radius_px", "n_corners", "rms_mm", "max_mm")  # fmt: skip
AXIS_KEYS = ("method", "axis_xy_mm", "correction_factor", "angle_scale", "angle_scale_sd",
             "angle_wave_deg", "estimated_diameter_mm", "actual_diameter_mm",
             "cylinder_offset_mm", "rms_mm")  # fmt: skip
"""The axis calibration a record keeps for provenance (the gear's whole fit among it)."""
OPTION_KEYS = ("outline_points", "mesh", "interpolation", "ball_radius_mm")
"""What of the processing options the rebuild needs (the rest is kept for provenance)."""


class RecordError(LaminaError, ValueError):
    """The bytes are not a Lamina compact record this version reads."""


@dataclass(frozen=True)
class RecordOutline:
    """One outline of the record: where it lies and its (aligned) EFD."""

    section: int
    part: int
    z_mm: float
    segments: int
    efd: EllipticFourier


@dataclass(frozen=True)
class CompactRecord:
    """A scan as its compact record holds it; rebuilds contours, measurements and mesh."""

    scan_id: int
    subject: str
    created: str
    calibration: dict[str, Any]
    axis: dict[str, Any]
    options: dict[str, Any]
    outlines: tuple[RecordOutline, ...]
    side: str = "none"
    """The limb scanned: left, right or none (as the library records it)."""

    def process_options(self) -> ProcessOptions:
        """Return the processing options the scan used (those the record keeps)."""
        return ProcessOptions.from_dict(self.options)

    def sections(self) -> list[Section]:
        """Return the outlines as pipeline sections (no raw points), contours re-sampled."""
        points = int(self.options.get("outline_points", ProcessOptions.outline_points))
        empty = np.empty((0, 2))
        return [
            Section(o.section, o.z_mm, o.segments, empty, o.efd, o.efd.evaluate(points), o.part)
            for o in self.outlines
        ]

    def mesh(self) -> tuple[np.ndarray, np.ndarray]:
        """Rebuild the mesh by the scan's own surface method; return vertices and faces."""
        vertices, faces, _ = build_mesh(self.sections(), self.process_options())
        return vertices, faces

    def mesh_volume_mm3(self) -> float:
        """Return the rebuilt mesh's enclosed volume in mm^3."""
        vertices, faces = self.mesh()
        return signed_volume(vertices, faces) if len(faces) else 0.0


def _subset(summary: dict[str, Any], keys: tuple[str, ...]) -> dict[str, Any]:
    return {k: summary[k] for k in keys if k in summary}


def _zigzag(values: np.ndarray) -> np.ndarray:
    return ((values << 1) ^ (values >> 63)).astype(np.uint64)


def _unzigzag(values: np.ndarray) -> np.ndarray:
    return (values >> np.uint64(1)).astype(np.int64) ^ -(values & np.uint64(1)).astype(np.int64)


def _pack(efds: list[EllipticFourier], order: int) -> bytes:
    """Return the outlines' coefficients quantised, differenced, zig-zagged, in byte planes."""
    rows = np.zeros((len(efds), 2 + 4 * order))
    for k, e in enumerate(efds):
        rows[k, :2] = e.a0, e.c0
        rows[k, 2 : 2 + 4 * e.order] = e.coeffs.ravel()
    if not np.isfinite(rows).all() or np.abs(rows).max(initial=0.0) > 1e6:
        raise RecordError("an outline's EFD is not finite or beyond 1 km: nothing to record")
    steps = np.rint(rows / QUANTUM_MM).astype(np.int64)
    deltas = np.diff(steps, axis=0, prepend=np.zeros((1, steps.shape[1]), np.int64))
    coded = _zigzag(deltas.ravel()).astype("<u4")
    return coded.view(np.uint8).reshape(-1, 4).T.tobytes()


def _unpack(data: bytes, orders: list[int]) -> list[np.ndarray]:
    width = 2 + 4 * max(orders, default=0)
    count = len(orders) * width
    if len(data) != 4 * count:
        raise RecordError("the record's coefficients are incomplete: the file is damaged")
    planes = np.frombuffer(data, np.uint8).reshape(4, count).T.copy()
    coded = planes.view("<u4").ravel().astype(np.uint64)
    steps = np.cumsum(_unzigzag(coded).reshape(len(orders), width), axis=0)
    return [row * QUANTUM_MM for row in steps]


def record_bytes(
    result: Reconstruction, scan_id: int, subject: str, created: str, side: str = "none"
) -> bytes:
    """Return the compact record of a reconstruction (see the module docstring).

    ``side`` is the limb scanned (left, right or none).
    """
    efds = [align(s.efd) for s in result.sections]
    order = max((e.order for e in efds), default=0)
    header = {
        "scan": scan_id,
        "subject": subject,
        "created": created,
        "side": side,
        "quantum_mm": QUANTUM_MM,
        "calibration": _subset(result.grid.to_dict(), CALIBRATION_KEYS),
        "axis": _subset(result.axis.to_dict(), AXIS_KEYS),
        "options": _subset(result.options.to_dict(), OPTION_KEYS),
        "outlines": [
            [s.index, s.part, s.z_mm, e.order, s.segments]
            for s, e in zip(result.sections, efds, strict=True)
        ],
    }
    text = json.dumps(header, separators=(",", ":")).encode()
    payload = struct.pack("<I", len(text)) + text + _pack(efds, order)
    return MAGIC + bytes([VERSION]) + zlib.compress(payload, 9)


def load_record(data: bytes) -> CompactRecord:
    """Read a compact record.

    Raises:
        RecordError: not a record, a newer version, or damaged.
    """
    if not data.startswith(MAGIC) or len(data) < len(MAGIC) + 1:
        raise RecordError("not a Lamina compact record (.lrec)")
    if data[len(MAGIC)] != VERSION:
        raise RecordError(f"compact record version {data[len(MAGIC)]} needs a newer Lamina")
    try:
        payload = zlib.decompress(data[len(MAGIC) + 1 :])
        (size,) = struct.unpack_from("<I", payload)
        header = json.loads(payload[4 : 4 + size])
        rows = header["outlines"]
        orders = [int(row[3]) for row in rows]
        coefficients = _unpack(payload[4 + size :], orders)
    except (zlib.error, struct.error, ValueError, KeyError, TypeError, IndexError) as exc:
        raise RecordError(f"the compact record is damaged ({exc})") from None
    outlines = tuple(
        RecordOutline(
            int(row[0]),
            int(row[1]),
            float(row[2]),
            int(row[4]),
            EllipticFourier(float(c[0]), float(c[1]), c[2 : 2 + 4 * n].reshape(n, 4).copy()),
        )
        for row, n, c in zip(rows, orders, coefficients, strict=True)
    )
    return CompactRecord(
        int(header["scan"]),
        str(header["subject"]),
        str(header["created"]),
        header["calibration"],
        header["axis"],
        header["options"],
        outlines,
        str(header.get("side", "none")),
    )
