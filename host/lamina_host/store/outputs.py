"""What a scan leaves behind: PLY files, the raw segments and ``report.json``."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np

from lamina_host.reconstruct.expect import Expectation
from lamina_host.reconstruct.measure import (
    perimeter,
    polygon_area,
    radial_error_table,
    sphere_probing,
)
from lamina_host.reconstruct.mesh import contour_normals, mesh_kind, obj_bytes, save_ply
from lamina_host.reconstruct.pipeline import (
    Reconstruction,
    Section,
    assemble,
    coloured_cloud,
    stack,
)
from lamina_host.reconstruct.precision import section_precision_mm
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
        head = np.array([s.section, s.view, s.z_mm, s.angle_deg], dtype=np.float64)
        arrays[f"{k:05d}_head"] = head
        arrays[f"{k:05d}_target"] = np.array(s.target)
        for name in SEGMENT_FIELDS:
            arrays[f"{k:05d}_{name}"] = getattr(s, name)

    def write(temporary: Path) -> None:
        with temporary.open("wb") as out:  # a file object: numpy adds no .npz of its own
            np.savez_compressed(out, **arrays)

    replace_file(path, write)


def load_segments(path: Path) -> list[Segment]:
    """Read segments written by :func:`save_segments`."""
    with np.load(path) as data:
        keys = sorted({name.split("_", 1)[0] for name in data.files})
        segments = []
        for k in keys:
            section, view, z_mm, angle = data[f"{k}_head"]
            segments.append(
                Segment(
                    str(data[f"{k}_target"]),
                    int(section),
                    int(view),
                    float(z_mm),
                    float(angle),
                    *(data[f"{k}_{n}"] for n in SEGMENT_FIELDS if f"{k}_{n}" in data.files),
                )
            )
    return segments


def build_report(
    result: Reconstruction,
    device: dict[str, Any],
    segments: list[Segment],
    expect: Expectation | None,
    acquisition_s: dict[str, float],
) -> dict[str, Any]:
    """Return the JSON-ready report of one scan."""
    precision = _precision_mm(result, segments)
    outlines = [section_entry(s, precision.get(s.index)) for s in result.sections]
    outlines += [f.to_dict() for f in result.failed]
    outlines.sort(key=lambda entry: (entry["section"], entry["part"]))
    report: dict[str, Any] = {
        "device": device,
        "options": result.options.to_dict(),
        "calibration": result.grid.to_dict(),
        "axis": result.axis.to_dict(),
        "correction_factor": result.axis.correction_factor,
        "sections": outlines,
        "outliers": result.rejected.to_dict(),
        "point_counts": {
            "segments": len(segments),
            "segment_points": int(sum(len(s) for s in segments)),
            "raw_points": int(sum(len(s.raw) for s in result.sections)),
            "outline_points": int(sum(len(s.contour) for s in result.sections)),
            "estimated_outline_points": int(
                sum(len(s.contour) - len(s.measured_contour) for s in result.sections)
            ),
        },
        "mesh": {
            "method": result.options.mesh,
            "kind": mesh_kind(result.mesh_topology),
            "boundary_edges": int(result.mesh_topology.get("boundary_edges", 0)),
            "vertices": len(result.vertices),
            "faces": len(result.faces),
            "topology": result.mesh_topology,
        },
        "timings_s": {**acquisition_s, **result.timings_s},
        "warnings": result.warnings,
    }
    if expect is not None:
        # The known shapes have one outline per section: measure each section's largest.
        main = [s for s in result.sections if s.part == 0]
        table = radial_error_table(
            {s.index: s.contour for s in main}, {s.index: s.z_mm for s in main}, expect.radius_mm
        )
        report["accuracy"] = {"expected": expect.spec, **table.to_dict()}
        if expect.kind == "sphere":
            report["accuracy"]["sphere"] = {
                "raw_points": sphere_probing(_points3d(main, raw=True), 2 * expect.a_mm).to_dict(),
                "contours": sphere_probing(_points3d(main, raw=False), 2 * expect.a_mm).to_dict(),
            }
    return report


def _precision_mm(result: Reconstruction, segments: list[Segment]) -> dict[int, float | None]:
    """Return each section's per-point precision from its views' overlaps (one outline only).

    A section of several outlines (two legs) gets none: its views' polar overlaps about
    one centroid would pair different outlines.
    """
    objects = [s for s in segments if s.target == "object"]
    by_section, _, _ = assemble(objects, result.grid, result.axis, result.options.trim_fraction)
    several = {s.index for s in result.sections if s.part > 0}
    return {k: None if k in several else section_precision_mm(v) for k, v in by_section.items()}


def section_entry(s: Section, precision_mm: float | None = None) -> dict[str, Any]:
    """Return the report's entry of one processed outline.

    Args:
        s: the outline.
        precision_mm: its section's per-point precision from the views' overlaps, if known.
    """
    return {
        "section": s.index,
        "part": s.part,
        "z_mm": s.z_mm,
        "segments": s.segments,
        "raw_points": len(s.raw),
        "outline_points": len(s.contour),
        "harmonics": s.harmonics,
        "precision_mm": precision_mm,
        "perimeter_mm": perimeter(s.contour),
        "area_mm2": polygon_area(s.contour),
        "efd": s.efd.to_dict(),
        "status": s.status,
        "coverage": s.coverage.to_dict() if s.coverage is not None else None,
        "estimated_outline_points": int(s.estimated.sum()) if s.estimated is not None else 0,
    }


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


def write_outputs(out: Path, result: Reconstruction, report: dict[str, Any]) -> dict[str, Path]:
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
    text = json_text(report)  # strict JSON: NaN (an unknown spread) is written null
    replace_file(paths["report.json"], lambda temporary: temporary.write_text(text, "utf-8"))
    return paths
