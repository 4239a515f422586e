"""What a scan leaves behind: PLY files, the raw segments and ``report.json``.

The result of processing is a :class:`ScanReport` (built by :func:`build_report`): the
front ends read its attributes, and ``report.json`` is written from its one
:meth:`ScanReport.to_json`.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np

from lamina_host.reconstruct.axis import AxisCalibration
from lamina_host.reconstruct.calibration import GridCalibration, LiftCalibration
from lamina_host.reconstruct.continuity import SectionJump, outline_jumps
from lamina_host.reconstruct.coverage import Coverage
from lamina_host.reconstruct.efd import EllipticFourier
from lamina_host.reconstruct.expect import Expectation
from lamina_host.reconstruct.measure import (
    RadialErrorTable,
    SphereProbing,
    perimeter,
    polygon_area,
    radial_error_table,
    sphere_probing,
)
from lamina_host.reconstruct.mesh import MeshTopology, contour_normals, obj_bytes, save_ply
from lamina_host.reconstruct.outliers import Rejected
from lamina_host.reconstruct.pipeline import (
    FailedSection,
    ProcessOptions,
    Reconstruction,
    Section,
    coloured_cloud,
    stack,
)
from lamina_host.reconstruct.status import OutlineStatus
from lamina_host.store.files import json_text, replace_file
from lamina_shared.types import Segment

SEGMENT_FIELDS = ("cols", "rows", "peak", "width", "confidence", "colour")
"""Per-point arrays saved; ``confidence`` and ``colour`` may be missing from older files
(then unknown, and no colour)."""


def save_segments(path: Path, segments: list[Segment]) -> None:
    """Write segments losslessly to one ``.npz`` file (kept so a scan can be reprocessed).

    The file is private and replaced whole (see :func:`lamina_host.store.files.replace_file`).
    """
    arrays: dict[str, Any] = {}
    for k, s in enumerate(segments):
        head = np.array([s.section, s.view, s.z_mm, s.angle_deg, s.turns], dtype=np.float64)
        arrays[f"{k:05d}_head"] = head
        arrays[f"{k:05d}_target"] = np.array(s.target)
        for name in SEGMENT_FIELDS:
            arrays[f"{k:05d}_{name}"] = getattr(s, name)

    def write(temporary: Path) -> None:
        with temporary.open("wb") as out:  # a file object: numpy adds no .npz of its own
            np.savez_compressed(out, **arrays)

    replace_file(path, write)


def load_segments(path: Path) -> list[Segment]:
    """Read segments written by :func:`save_segments` (files from before segments carried
    their turns read as turn 0)."""
    with np.load(path) as data:
        keys = sorted({name.split("_", 1)[0] for name in data.files})
        segments = []
        for k in keys:
            section, view, z_mm, angle, *turns = data[f"{k}_head"]
            segment = Segment(
                str(data[f"{k}_target"]),
                int(section),
                int(view),
                float(z_mm),
                float(angle),
                *(data[f"{k}_{n}"] for n in SEGMENT_FIELDS if f"{k}_{n}" in data.files),
            )
            segments.append(replace(segment, turns=int(turns[0])) if turns else segment)
    return segments


@dataclass(frozen=True)
class OutlineEntry:
    """The report's entry of one processed outline (:func:`outline_entry`)."""

    section: int
    part: int
    z_mm: float
    segments: int
    raw_points: int
    outline_points: int
    harmonics: int
    precision_mm: float | None
    """Its section's per-point precision from the views' overlaps, if known."""
    perimeter_mm: float
    area_mm2: float
    efd: EllipticFourier
    status: OutlineStatus
    coverage: Coverage | None
    estimated_outline_points: int
    reason: str = ""
    """Empty: only a failed outline has a reason."""

    def to_json(self) -> dict[str, Any]:
        """Return the entry as ``report.json`` writes it."""
        return {
            "section": self.section,
            "part": self.part,
            "z_mm": self.z_mm,
            "segments": self.segments,
            "raw_points": self.raw_points,
            "outline_points": self.outline_points,
            "harmonics": self.harmonics,
            "precision_mm": self.precision_mm,
            "perimeter_mm": self.perimeter_mm,
            "area_mm2": self.area_mm2,
            "efd": self.efd.to_dict(),
            "status": self.status,
            "coverage": self.coverage.to_dict() if self.coverage is not None else None,
            "estimated_outline_points": self.estimated_outline_points,
        }


@dataclass(frozen=True, eq=False)
class FailedEntry:
    """The report's entry of an outline that could not be processed."""

    outline: FailedSection

    @property
    def section(self) -> int:
        """Return the section's index."""
        return self.outline.index

    @property
    def part(self) -> int:
        """Return the outline's place among its section's outlines."""
        return self.outline.part

    @property
    def z_mm(self) -> float:
        """Return the section's height."""
        return self.outline.z_mm

    @property
    def raw_points(self) -> int:
        """Return the outline's stripe points."""
        return self.outline.points

    @property
    def status(self) -> OutlineStatus:
        """Return :attr:`OutlineStatus.FAILED`."""
        return self.outline.status

    @property
    def reason(self) -> str:
        """Return why the outline could not be processed."""
        return self.outline.reason

    def to_json(self) -> dict[str, Any]:
        """Return the entry as ``report.json`` writes it."""
        return self.outline.to_dict()


@dataclass(frozen=True)
class PointCounts:
    """How many points each stage had, over the whole scan."""

    segments: int
    segment_points: int
    raw_points: int
    outline_points: int
    estimated_outline_points: int

    def to_json(self) -> dict[str, Any]:
        """Return the counts as ``report.json`` writes them."""
        return asdict(self)


@dataclass(frozen=True)
class MeshEntry:
    """The report's mesh: how it was made, what kind of surface, its size and topology."""

    method: str
    topology: MeshTopology | None
    """None when there is no mesh."""
    vertices: int
    faces: int

    @property
    def kind(self) -> str:
        """Return which of :data:`~lamina_host.reconstruct.mesh.MESH_KINDS` the mesh is."""
        return self.topology.kind if self.topology is not None else "none"

    @property
    def boundary_edges(self) -> int:
        """Return the edges on the mesh's boundary (0 without a mesh)."""
        return int(self.topology.boundary_edges) if self.topology is not None else 0

    @property
    def closed(self) -> bool:
        """Return whether the mesh is watertight and two-manifold."""
        return self.topology is not None and self.topology.watertight and self.topology.two_manifold

    @classmethod
    def from_json(cls, entry: Mapping[str, Any]) -> MeshEntry:
        """Return the mesh entry a stored report recorded (what it lacks: none)."""
        return cls(
            str(entry.get("method", "")),
            MeshTopology.from_dict(dict(entry.get("topology") or {})),
            int(entry.get("vertices", 0)),
            int(entry.get("faces", 0)),
        )

    def to_json(self) -> dict[str, Any]:
        """Return the entry as ``report.json`` writes it."""
        return {
            "method": self.method,
            "kind": self.kind,
            "boundary_edges": self.boundary_edges,
            "vertices": self.vertices,
            "faces": self.faces,
            "topology": self.topology.to_dict() if self.topology is not None else {},
        }


@dataclass(frozen=True)
class Accuracy:
    """How far a scan of a known shape is from it: radial errors, and a sphere's probing."""

    expected: str
    """The expected shape as it was given (``--expect``)."""
    table: RadialErrorTable
    sphere: tuple[SphereProbing, SphereProbing] | None = None
    """A sphere's probing errors of the raw points and of the contours."""

    def to_json(self) -> dict[str, Any]:
        """Return the entry as ``report.json`` writes it."""
        entry: dict[str, Any] = {"expected": self.expected, **self.table.to_dict()}
        if self.sphere is not None:
            raw, contours = self.sphere
            entry["sphere"] = {"raw_points": raw.to_dict(), "contours": contours.to_dict()}
        return entry


NO_LIFT_REFERENCE: dict[str, Any] = {
    "calibrated": False,
    "applied": False,
    "scale": 1.0,
    "note": "the device has no lift reference: section heights are the commanded lift heights",
}
"""``report.json``'s ``lift`` for a scan whose lift was trusted, not calibrated."""


@dataclass(frozen=True)
class ScanReport:
    """The result of processing one scan, as ``report.json`` records it (:meth:`to_json`)."""

    device: Mapping[str, Any]
    """The device summary and the scan's identity (``workflow.results.report_device``)."""
    options: ProcessOptions
    calibration: GridCalibration
    axis: AxisCalibration
    sections: tuple[OutlineEntry | FailedEntry, ...]
    """Every outline, processed or failed, by section and part."""
    outliers: Rejected
    point_counts: PointCounts
    mesh: MeshEntry
    timings_s: Mapping[str, float]
    warnings: tuple[str, ...]
    accuracy: Accuracy | None
    """Only for a scan of a known shape (``expect``)."""
    subject_id: str
    volume_mm3: float
    lift: LiftCalibration | None = None
    """The lift's scale from the cylinder's grooves (None: no lift reference)."""

    @property
    def correction_factor(self) -> float:
        """Return the turntable axis's correction factor."""
        return self.axis.correction_factor

    def to_json(self) -> dict[str, Any]:
        """Return the JSON-ready report (``report.json`` and the library's copy)."""
        report: dict[str, Any] = {
            "device": dict(self.device),
            "options": self.options.to_dict(),
            "calibration": self.calibration.to_dict(),
            "axis": self.axis.to_dict(),
            "lift": self.lift.to_dict() if self.lift is not None else dict(NO_LIFT_REFERENCE),
            "correction_factor": self.correction_factor,
            "sections": [entry.to_json() for entry in self.sections],
            "outliers": self.outliers.to_dict(),
            "point_counts": self.point_counts.to_json(),
            "mesh": self.mesh.to_json(),
            "timings_s": dict(self.timings_s),
            "warnings": list(self.warnings),
        }
        if self.accuracy is not None:
            report["accuracy"] = self.accuracy.to_json()
        report["subject_id"] = self.subject_id
        report["volume_mm3"] = self.volume_mm3
        return report


def build_report(
    result: Reconstruction,
    device: Mapping[str, Any],
    segments: list[Segment],
    expect: Expectation | None,
    acquisition_s: Mapping[str, float],
    subject_id: str = "",
    volume_mm3: float = 0.0,
) -> ScanReport:
    """Return the report of one scan.

    Args:
        result: the reconstruction.
        device: the report's device entry.
        segments: the segments reconstructed (the precision comes from their overlaps).
        expect: the shape scanned, when known (the report then gives the accuracy).
        acquisition_s: how long acquiring took, by stage.
        subject_id: the subject's code.
        volume_mm3: the volume between the first and last section.
    """
    outlines: list[OutlineEntry | FailedEntry] = [
        outline_entry(s, s.precision_mm) for s in result.sections
    ]
    outlines += [FailedEntry(f) for f in result.failed]
    outlines.sort(key=lambda entry: (entry.section, entry.part))
    counts = PointCounts(
        segments=len(segments),
        segment_points=int(sum(len(s) for s in segments)),
        raw_points=int(sum(len(s.raw) for s in result.sections)),
        outline_points=int(sum(len(s.contour) for s in result.sections)),
        estimated_outline_points=int(
            sum(len(s.contour) - len(s.measured_contour) for s in result.sections)
        ),
    )
    mesh = MeshEntry(
        result.options.mesh, result.mesh_topology, len(result.vertices), len(result.faces)
    )
    return ScanReport(
        device=device,
        options=result.options,
        calibration=result.grid,
        axis=result.axis,
        sections=tuple(outlines),
        outliers=result.rejected,
        point_counts=counts,
        mesh=mesh,
        timings_s={**acquisition_s, **result.timings_s},
        warnings=(
            *result.warnings,
            *_motion_warnings(result.sections),
            *_jump_warnings(outline_jumps(result.sections)),
        ),
        accuracy=_accuracy(result, expect),
        subject_id=subject_id,
        volume_mm3=volume_mm3,
        lift=result.lift,
    )


def _accuracy(result: Reconstruction, expect: Expectation | None) -> Accuracy | None:
    """Return how far the scan is from the known shape (None when none is known)."""
    if expect is None:
        return None
    # The known shapes have one outline per section: measure each section's largest.
    main = [s for s in result.sections if s.part == 0]
    table = radial_error_table(
        {s.index: s.contour for s in main}, {s.index: s.z_mm for s in main}, expect.radius_mm
    )
    sphere = None
    if expect.kind == "sphere":
        sphere = (
            sphere_probing(_points3d(main, raw=True), 2 * expect.a_mm),
            sphere_probing(_points3d(main, raw=False), 2 * expect.a_mm),
        )
    return Accuracy(expect.spec, table, sphere)


def _outline_name(index: int, part: int) -> str:
    """Return how a warning names an outline: its section, and its part after the first."""
    return f"section {index}" + (f" outline {part}" if part else "")


def _motion_warnings(sections: list[Section]) -> list[str]:
    """Return a warning for each outline whose overlapping views show the subject moving.

    Views also disagree, on a still limb, where the surface is finer than they resolve
    alike (thin parts, deep folds, an open shell: the campaign's still shapes); a
    second scan tells the two apart, so the line says what a repeat would mean.
    """
    return [
        _outline_name(s.index, s.part)
        + f": its overlapping views stand {s.views_apart_mm:.2f} mm apart, beyond their "
        "noise: the subject may have moved during the scan; scan again with the limb "
        "supported and still (if a still limb is warned of again, the surface there is "
        "finer than its views agree on, a thin or deeply folded part: its outline is "
        "less certain than the rest)"
        for s in sorted(sections, key=lambda s: (s.index, s.part))
        if s.views_moved
    ]


def _jump_warnings(jumps: list[SectionJump]) -> list[str]:
    """Return a warning for each outline standing off the line of its neighbours."""
    return [
        _outline_name(j.index, j.part)
        + f": it stands {j.jump_mm:.2f} mm off the line of the sections below and above it "
        + (
            f"(its size {j.size_mm:+.2f} mm in radius"
            if abs(j.size_mm) >= j.centre_mm
            else f"(its centre {j.centre_mm:.2f} mm aside"
        )
        + "), more than a limb's shape changes: the subject may have moved between "
        "sections; scan again with the limb supported and still"
        for j in jumps
        if j.flagged
    ]


def outline_entry(s: Section, precision_mm: float | None = None) -> OutlineEntry:
    """Return the report's entry of one processed outline.

    Args:
        s: the outline.
        precision_mm: its section's per-point precision from the views' overlaps, if known.
    """
    return OutlineEntry(
        section=s.index,
        part=s.part,
        z_mm=s.z_mm,
        segments=s.segments,
        raw_points=len(s.raw),
        outline_points=len(s.contour),
        harmonics=s.harmonics,
        precision_mm=precision_mm,
        perimeter_mm=perimeter(s.contour),
        area_mm2=polygon_area(s.contour),
        efd=s.efd,
        status=s.status,
        coverage=s.coverage,
        estimated_outline_points=int(s.estimated.sum()) if s.estimated is not None else 0,
    )


def _points3d(sections: list[Any], raw: bool) -> np.ndarray:
    """Return the sections' raw points or EFD contours as one (N, 3) array."""
    return stack([s.raw if raw else s.contour for s in sections], [s.z_mm for s in sections])


def measured_cloud(result: Reconstruction) -> tuple[np.ndarray, np.ndarray]:
    """Return the EFD contour samples in seen stretches and their normals, as (N, 3) each.

    Samples in unseen gaps (bridged by EFD or filled from neighbouring sections) are left
    out: points.ply holds measured outline only, while the mesh keeps the estimated parts
    closed (``report.json`` flags them per section).
    """
    points, normals = [], []
    for s in result.sections:
        keep = np.ones(len(s.contour), dtype=bool) if s.estimated is None else ~s.estimated
        flat = np.zeros(int(keep.sum()))
        points.append(np.column_stack([s.contour[keep], flat + s.z_mm]))
        normals.append(np.column_stack([contour_normals(s.contour)[keep], flat]))
    if not points:
        return np.empty((0, 3)), np.empty((0, 3))
    return np.vstack(points), np.vstack(normals)


def write_outputs(out: Path, result: Reconstruction, report: ScanReport) -> dict[str, Path]:
    """Write the point clouds, the mesh and the report into ``out``; return their paths.

    points.ply holds only the measured stretches of the EFD contours (:func:`measured_cloud`).
    A colour scan adds colour_points.ply (the measured points with their overlap-averaged
    colours), colours mesh.ply's vertices and writes mesh.obj with vertex colours.
    Each file is private and replaced whole, never written through a link.
    """
    paths = {
        name: out / name for name in ("raw_points.ply", "points.ply", "mesh.ply", "report.json")
    }
    heights = [s.z_mm for s in result.sections]
    raw = stack([s.raw for s in result.sections], heights)
    replace_file(paths["raw_points.ply"], lambda temporary: save_ply(temporary, raw))
    coloured, colours = coloured_cloud(result.sections)
    if len(coloured):
        paths["colour_points.ply"] = out / "colour_points.ply"
        replace_file(
            paths["colour_points.ply"],
            lambda temporary: save_ply(temporary, coloured, colours=colours),
        )
    points, normals = measured_cloud(result)
    replace_file(
        paths["points.ply"], lambda temporary: save_ply(temporary, points, normals=normals)
    )
    rgb = result.vertex_colours
    if len(result.faces):
        replace_file(
            paths["mesh.ply"],
            lambda temporary: save_ply(temporary, result.vertices, result.faces, colours=rgb),
        )
        if rgb is not None:
            # Vertex colours in the format most viewers take them from (v x y z r g b).
            paths["mesh.obj"] = out / "mesh.obj"
            data = obj_bytes(result.vertices, result.faces, rgb)
            replace_file(paths["mesh.obj"], lambda temporary: temporary.write_bytes(data))
    else:
        del paths["mesh.ply"]
    text = json_text(report.to_json())  # strict JSON: NaN (an unknown spread) is written null
    replace_file(paths["report.json"], lambda temporary: temporary.write_text(text, "utf-8"))
    return paths
