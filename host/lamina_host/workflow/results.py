"""Typed results of the scan workflow: the raw scan, section rows, a processed scan.

Both front ends show these; neither builds its own. :func:`device_summary` is the one
place the device information recorded with a scan (and in its report) is built.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lamina_host.reconstruct.calibration import DistortionTest, LiftCalibration
from lamina_host.reconstruct.measure import perimeter, polygon_area
from lamina_host.reconstruct.pipeline import Reconstruction, Section
from lamina_host.reconstruct.status import OutlineStatus
from lamina_host.store.outputs import MeshEntry, ScanReport
from lamina_shared.messages import Welcome
from lamina_shared.types import BoardSpec, LiftReference, Segment


def device_summary(info: Welcome | None) -> dict[str, str]:
    """Return what a scan records about the device that acquires it (empty when unknown)."""
    if info is None:
        return {}
    return {"software": info.software, "hardware": info.hardware, "description": info.description}


def report_device(device: Mapping[str, Any], identity: Mapping[str, Any] | None) -> dict[str, Any]:
    """Return the report's ``device`` entry: the recorded summary and the scan's identity."""
    report = dict(device)
    if identity:
        report["identity"] = dict(identity)
    return report


def mesh_summary(mesh: MeshEntry) -> str:
    """Return one line on a report's mesh: what kind of surface, faces, vertices.

    A closed mesh is watertight and two-manifold; an open surface has a boundary where
    nothing was seen (its edge count is given).
    """
    size = f"{mesh.faces} faces, {mesh.vertices} vertices"
    if mesh.kind == "closed":
        return f"closed (watertight), {size}"
    if mesh.kind == "open surface":
        return f"open surface ({mesh.boundary_edges} boundary edges), {size}"
    return f"{mesh.kind}, {size}"


def lift_summary(lift: LiftCalibration | None) -> str:
    """Return one line on how the section heights were found: the lift calibrated or trusted."""
    if lift is None:
        return "trusted (the device has no lift reference): heights as commanded"
    if not lift.applied:
        return "trusted: its calibration failed (see the warnings)"
    low, high = lift.reference.marks_mm
    return (
        f"scale {lift.scale:.5f} ({lift.error_percent:+.3f} %) from the cylinder's grooves at "
        f"{low:g} and {high:g} mm, applied to every section height"
    )


def distortion_summary(test: DistortionTest | None) -> str | None:
    """Return one line on a calibration's lens distortion test (None without one)."""
    if test is None:
        return None
    change = (
        f"corner residual {test.rms_px_without:.3f} px without, {test.rms_px_with:.3f} px with it"
    )
    if test.applied:
        return f"radial distortion k = {test.division_k:.5f} removed ({change})"
    if test.significant:
        return f"radial distortion shown by the board but kept (--distortion off; {change})"
    return f"no measurable distortion (F {test.f_statistic:.1f} < {test.f_critical:.1f})"


@dataclass
class ScanData:
    """The raw data of one scan: what processing needs and what the library keeps."""

    grid_image: np.ndarray | None = None
    board: BoardSpec | None = None
    cylinder: list[Segment] = field(default_factory=list)
    cylinder_mm: float | None = None
    segments: list[Segment] = field(default_factory=list)
    subject_id: str = ""
    device: dict[str, str] = field(default_factory=dict)
    complete: bool = False
    lift_reference: LiftReference | None = None
    """The calibration cylinder's marks that calibrate the lift (None: trusted)."""
    row_turn_deg: float = 0.0
    """The table's turn per image row in the object's views (a continuous scan's rolling
    shutter, :func:`lamina_host.link.identity.row_turn_deg`; 0.0: stop-and-go)."""
    laser_off_turn_later: bool = False
    """The object's continuous views took their laser-off frames a turn of the count later
    (:func:`lamina_host.link.identity.laser_off_turn_later`)."""


@dataclass(frozen=True)
class SectionRow:
    """One section's measurements, as the Results table and the report give them."""

    index: int
    z_mm: float
    points: int
    perimeter_mm: float
    area_mm2: float
    roundness: float
    harmonics: int
    coverage_percent: float = 100.0
    """Share of the circumference the views saw (``lamina_host.reconstruct.coverage``)."""
    status: OutlineStatus = OutlineStatus.MEASURED
    """How the outline was closed (:class:`OutlineStatus`): measured,
    bridged, interpolated, open, or failed (then the measurements are NaN)."""
    reason: str = ""
    """Why a failed outline could not be processed (empty otherwise)."""

    @property
    def failed(self) -> bool:
        """Return whether the outline could not be processed (it has no measurements)."""
        return self.status == OutlineStatus.FAILED


@dataclass(frozen=True)
class Results:
    """A processed scan: the reconstruction, its section rows and its report."""

    reconstruction: Reconstruction
    rows: list[SectionRow]
    report: ScanReport
    paths: dict[str, Path] = field(default_factory=dict)
    """The files written for the scan (empty when they went only into the library)."""

    @property
    def volume_mm3(self) -> float:
        """Return the volume between the first and last section."""
        return self.report.volume_mm3

    @property
    def mesh_method(self) -> str:
        """Return how the mesh was made."""
        return self.report.mesh.method


def colour_bins(section: Section, bins: int = 32) -> np.ndarray | None:
    """Return the section's mean colour in ``bins`` equal angular sectors, or None uncoloured.

    Angles are taken about the centroid of the coloured points, from +x counter-clockwise;
    a sector no coloured point falls in is -1 in every channel.
    """
    points, colours = section.colour_points, section.colours
    if points is None or colours is None or not len(points):
        return None
    d = points - points.mean(axis=0)
    sector = np.floor((np.arctan2(d[:, 1], d[:, 0]) % (2 * math.pi)) / (2 * math.pi) * bins)
    sector = np.minimum(sector.astype(int), bins - 1)
    counts = np.bincount(sector, minlength=bins)
    sums = np.stack([np.bincount(sector, colours[:, c].astype(float), bins) for c in range(3)], 1)
    return np.where(counts[:, None] > 0, sums / np.maximum(counts, 1)[:, None], -1.0)


def roundness(contour: np.ndarray) -> float:
    """Return the isoperimetric quotient 4*pi*A/P^2: 1 for a circle, less for any other shape."""
    p = perimeter(contour)
    return 4.0 * math.pi * polygon_area(contour) / (p * p) if p > 0 else 0.0


def section_rows(result: Reconstruction) -> list[SectionRow]:
    """Measure every section's EFD contour; a failed outline's row has NaN measurements."""
    rows = [
        SectionRow(
            s.index,
            s.z_mm,
            len(s.raw),
            perimeter(s.contour),
            polygon_area(s.contour),
            roundness(s.contour),
            s.harmonics,
            100.0 * (s.coverage.fraction if s.coverage is not None else 1.0),
            s.status,
        )
        for s in result.sections
    ]
    nan = float("nan")
    rows += [
        SectionRow(f.index, f.z_mm, f.points, nan, nan, nan, 0, 0.0, f.status, f.reason)
        for f in result.failed
    ]
    return sorted(rows, key=lambda r: r.z_mm)


def volume_mm3(rows: list[SectionRow]) -> float:
    """Return the volume between the first and last section (trapezoid rule over areas)."""
    rows = [r for r in rows if not r.failed]
    if len(rows) < 2:
        return 0.0
    z = np.array([r.z_mm for r in rows])
    area = np.array([r.area_mm2 for r in rows])
    order = np.argsort(z)
    return float(np.trapezoid(area[order], z[order]))


def radius_profile(rows: list[SectionRow]) -> tuple[list[float], list[float]]:
    """Return (z_mm, equivalent radius sqrt(A/pi) in mm) per section, for the profile plot."""
    rows = [r for r in rows if not r.failed]
    return [r.z_mm for r in rows], [math.sqrt(r.area_mm2 / math.pi) for r in rows]
