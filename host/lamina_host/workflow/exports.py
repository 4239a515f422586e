"""``lamina export`` beyond the stored files: DICOM Encapsulated STL and the compact record.

The library writes the mesh formats and the report itself (:meth:`Library.export`);
these two need more than a stored file: the DICOM object wraps the mesh with the
scan's study data, and the compact record is rebuilt from the scan's segments and
calibration by the current pipeline with the options its result recorded.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from types import MappingProxyType
from typing import Any

from lamina_host.clinical.limb_frame import limb_stl_files
from lamina_host.reconstruct.mesh import load_ply
from lamina_host.store.dicom import (
    DICOM_SOPS,
    SURFACE_SCAN_MESH,
    DicomContext,
    dicom_bytes,
    encapsulated_stl,
    surface_scan_mesh,
)
from lamina_host.store.library import (
    EXPORT_FORMATS,
    Library,
    StoreError,
    check_new_file,
    no_result_line,
    unknown_format,
)
from lamina_host.store.outputs import MeshEntry
from lamina_host.store.record import record_bytes
from lamina_host.workflow.batch import reprocess

LIMB_STL = ".limb.stl"
"""The mesh in the limb frame for prosthetic CAD (:mod:`lamina_host.clinical.limb_frame`),
with a JSON sidecar of the same stem (``leg.limb.stl``, ``leg.limb.json``)."""
EXPORTERS: Mapping[str, str] = MappingProxyType(
    {
        ".dcm": "DICOM Encapsulated STL",
        ".lrec": "compact follow-up record",
        LIMB_STL: "mesh in the limb frame, for prosthetic CAD",
    }
)
"""Formats :func:`export_scan` adds to the library's own (:data:`EXPORT_FORMATS`)."""

ALL_FORMATS: Mapping[str, str] = MappingProxyType({**EXPORT_FORMATS, **EXPORTERS})
"""Every format ``lamina export`` writes, by extension, with what each holds."""


def export_format(path: Path) -> str:
    """Return the format a file name asks for: its extension, or ``.limb.stl`` (two of them)."""
    return LIMB_STL if path.name.lower().endswith(LIMB_STL) else path.suffix.lower()


def export_scan(
    library: Library,
    scan_id: int,
    path: Path,
    institution: str = "",
    dicom_sop: str = next(iter(DICOM_SOPS)),
) -> Path:
    """Write scan ``scan_id`` to the new file ``path`` in the format its extension names.

    ``dicom_sop`` chooses the DICOM object of a ``.dcm`` (:data:`DICOM_SOPS`).

    Raises:
        StoreError: unknown extension, an existing file, or a scan without a result.
    """
    suffix = export_format(path)
    if suffix == LIMB_STL:
        return _limb_export(library, scan_id, path)
    if suffix in EXPORT_FORMATS:
        return library.export(scan_id, path)
    if suffix not in EXPORTERS:
        raise unknown_format(path, ALL_FORMATS)
    check_new_file(path)
    if suffix == ".dcm":
        data = dicom_export(library, scan_id, institution, dicom_sop)
    else:
        data = record_export(library, scan_id)
    return library.write_export(scan_id, path, data)


def _limb_export(library: Library, scan_id: int, path: Path) -> Path:
    """Write the limb-frame STL to ``path`` and its JSON sidecar beside it (both new files)."""
    sidecar = path.with_name(path.name[: -len(".stl")] + ".json")
    check_new_file(path)
    check_new_file(sidecar)
    stl, frame = limb_stl_files(library, scan_id)
    library.write_export(scan_id, sidecar, frame)
    return library.write_export(scan_id, path, stl)


def _serial(identity: dict[str, Any]) -> str:
    return str(identity.get("serial") or identity.get("source") or "unknown")


def dicom_export(
    library: Library, scan_id: int, institution: str = "", sop: str = next(iter(DICOM_SOPS))
) -> bytes:
    """Return the scan's stored mesh as a DICOM file: Encapsulated STL or Surface Scan Mesh."""
    vertices, faces = load_ply(library.result_mesh(scan_id))
    record = library.scan(scan_id)
    context = DicomContext(
        record.subject,
        scan_id,
        record.created,
        institution,
        _serial(record.identity),
        str(record.device.get("software", "")),
        record.side,
    )
    if DICOM_SOPS[sop] == SURFACE_SCAN_MESH:
        report = library.result(scan_id) or {}
        closed = MeshEntry.from_json(report.get("mesh", {})).closed
        return dicom_bytes(surface_scan_mesh(vertices, faces, context, closed))
    return dicom_bytes(encapsulated_stl(vertices, faces, context))


def record_export(library: Library, scan_id: int) -> bytes:
    """Return the scan's compact record, reprocessed from its segments and calibration."""
    scan = library.scan(scan_id)
    if library.result(scan_id) is None:
        raise StoreError(no_result_line(scan))
    inputs = library.inputs(scan_id)
    result = reprocess(inputs)
    return record_bytes(result, scan_id, inputs.subject, inputs.created, scan.side)
