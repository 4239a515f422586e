"""``lamina export`` to DICOM Encapsulated STL and to the compact record, on a real scan.

The DICOM file is checked by ``dciodvfy`` (dicom3tools, the reference IOD checker) and
read back with pydicom; the record is rebuilt and compared with the scan's own report.
"""

from __future__ import annotations

import json
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import numpy as np
import pydicom
import pytest

from lamina_host.reconstruct.measure import perimeter, polygon_area
from lamina_host.reconstruct.mesh import load_ply, tube_mesh
from lamina_host.store.dicom import (
    ENCAPSULATED_STL,
    SURFACE_SCAN_MESH,
    DicomContext,
    dicom_bytes,
    encapsulated_stl,
    read_stl_triangles,
    read_surface_mesh,
)
from lamina_host.store.library import Library
from lamina_host.store.record import load_record

from .conftest import SUBJECT

DCIODVFY = shutil.which("dciodvfy")
needs_dciodvfy = pytest.mark.skipif(
    DCIODVFY is None,
    reason="dciodvfy is not installed: apt-get install -y dicom3tools (the DICOM IOD checker)",
)


def lamina(*args: str) -> subprocess.CompletedProcess[str]:
    """Run ``lamina`` in a fresh process."""
    return subprocess.run(
        [sys.executable, "-m", "lamina_host", *args], capture_output=True, text=True, timeout=300
    )


def export_scan_1(library: Path, out: Path, *options: str) -> None:
    """Export scan 1 of ``library`` to ``out`` with ``lamina export``; it must succeed."""
    done = lamina("export", "1", "-o", str(out), "--library", str(library), *options)
    assert done.returncode == 0, done.stderr


def dciodvfy(path: Path) -> tuple[list[str], list[str]]:
    """Return the errors and warnings ``dciodvfy`` reports for a file."""
    assert DCIODVFY is not None
    done = subprocess.run([DCIODVFY, str(path)], capture_output=True, text=True, timeout=60)
    lines = (done.stdout + done.stderr).splitlines()
    errors = [line for line in lines if line.startswith("Error")]
    warnings = [line for line in lines if line.startswith("Warning")]
    return errors, warnings


def ring_mesh() -> tuple[np.ndarray, np.ndarray]:
    """A closed 10 mm radius tube, 4 mm tall."""
    t = np.linspace(0.0, 2.0 * np.pi, 32, endpoint=False)
    ring = np.column_stack([10.0 * np.cos(t), 10.0 * np.sin(t)])
    return tube_mesh(np.stack([ring] * 3), np.array([0.0, 2.0, 4.0]))


@needs_dciodvfy
def test_encapsulated_stl_passes_dciodvfy_and_keeps_the_mesh_exactly(tmp_path: Path) -> None:
    vertices, faces = ring_mesh()
    context = DicomContext(SUBJECT, 3, "2026-11-29T13:00:00+00:00", "Lamina Test Clinic")
    path = tmp_path / "mesh.dcm"
    path.write_bytes(dicom_bytes(encapsulated_stl(vertices, faces, context)))
    errors, warnings = dciodvfy(path)
    print("dciodvfy warnings:", warnings)
    assert errors == []
    assert np.array_equal(read_stl_triangles(str(path)), vertices.astype(np.float32)[faces])


def test_every_export_of_a_scan_shares_its_study_and_series() -> None:
    vertices, faces = ring_mesh()
    context = DicomContext(SUBJECT, 3, "2026-11-29T13:00:00+00:00")
    one, two = (encapsulated_stl(vertices, faces, context) for _ in range(2))
    assert one.StudyInstanceUID == two.StudyInstanceUID
    assert one.SeriesInstanceUID == two.SeriesInstanceUID
    assert one.SOPInstanceUID != two.SOPInstanceUID
    other = encapsulated_stl(vertices, faces, DicomContext(SUBJECT, 4, context.created))
    assert other.StudyInstanceUID != one.StudyInstanceUID
    assert "InstitutionName" not in one
    assert "ImageLaterality" not in one and "Laterality" not in one  # side none: no laterality
    right = encapsulated_stl(
        vertices, faces, DicomContext(SUBJECT, 3, context.created, side="right")
    )
    assert right.ImageLaterality == "R" and right.SeriesInstanceUID == one.SeriesInstanceUID


@needs_dciodvfy
def test_cli_exports_a_scan_as_dicom(scanned_library: Path, tmp_path: Path) -> None:
    out = tmp_path / "scan1.dcm"
    export_scan_1(scanned_library, out, "--institution", "Lamina Test Clinic")
    assert stat.S_IMODE(out.stat().st_mode) == 0o600
    errors, warnings = dciodvfy(out)
    print("dciodvfy warnings:", warnings)
    assert errors == []
    ds = pydicom.dcmread(out)
    assert ds.SOPClassUID == ENCAPSULATED_STL and ds.MIMETypeOfEncapsulatedDocument == "model/stl"
    assert ds.PatientID == SUBJECT and str(ds.PatientName) == ""
    assert ds.InstitutionName == "Lamina Test Clinic" and ds.Modality == "M3D"
    assert ds.MeasurementUnitsCodeSequence[0].CodeValue == "mm"
    # Issue #24: no limb side in the DICOM file. The scan is a left limb: Image Laterality
    # (the Encapsulated Document module's; this IOD's series has no Laterality), no warning.
    assert ds.ImageLaterality == "L" and ds.SeriesDescription.endswith("left limb")
    assert "Laterality" not in ds and warnings == []
    with Library(scanned_library) as library:
        vertices, faces = load_ply(library.result_mesh(1))
    triangles = read_stl_triangles(str(out))
    assert len(faces) > 100 and np.array_equal(triangles, vertices[faces])


def test_cli_exports_a_surface_scan_mesh_that_reads_back_exactly(
    scanned_library: Path, tmp_path: Path
) -> None:
    """``--dicom-sop surface-scan``: the experimental Surface Scan Mesh, the mesh kept exactly.

    dciodvfy (dicom3tools 2022) has no definition of this IOD, so it can only say so; if
    a later one knows it, it must find no error.
    """
    out = tmp_path / "scan1-oss.dcm"
    export_scan_1(scanned_library, out, "--dicom-sop", "surface-scan")
    ds = pydicom.dcmread(out)
    assert ds.SOPClassUID == SURFACE_SCAN_MESH and ds.Modality == "OSS"
    assert ds.Laterality == "L"  # the series' laterality: the scan is a left limb
    assert ds.PatientID == SUBJECT and str(ds.PatientName) == ""
    surface = ds.SurfaceSequence[0]
    assert ds.NumberOfSurfaces == 1 and surface.SurfaceNumber == 1
    with Library(scanned_library) as library:
        vertices, faces = load_ply(library.result_mesh(1))
        topology = (library.result(1) or {})["mesh"]["topology"]
    watertight = topology["watertight"] and topology["two_manifold"]
    assert surface.FiniteVolume == ("YES" if watertight else "UNKNOWN")
    got_vertices, got_faces = read_surface_mesh(str(out))
    assert np.array_equal(got_vertices, vertices.astype(np.float32))
    assert np.array_equal(got_faces, faces) and len(faces) > 100
    # DICOM numbers surface points from 1.
    index = np.frombuffer(
        surface.SurfaceMeshPrimitivesSequence[0].LongTrianglePointIndexList, "<u4"
    )
    assert index.min() == 1 and index.max() == len(vertices)
    if DCIODVFY is not None:
        errors, _ = dciodvfy(out)
        assert errors in ([], ["Error - Information Object Not found"]), errors


def test_cli_refuses_bad_export_requests_in_one_line(scanned_library: Path, tmp_path: Path) -> None:
    library = ("--library", str(scanned_library))
    existing = tmp_path / "old.dcm"
    existing.write_bytes(b"earlier")
    cases = [
        (("export", "1", "-o", str(tmp_path / "x.dcm"), "--institution", "a\tb"), "institution"),
        (("export", "1", "-o", str(tmp_path / "x.dcm"), "--institution", "a" * 65), "institution"),
        (("export", "1", "-o", str(existing)), "already exists"),
        (("export", "1", "-o", str(tmp_path / "x.dicom")), ".dcm"),
        (("export", "1", "-o", str(tmp_path / "none" / "x.lrec")), "does not exist"),
        (("export", "9", "-o", str(tmp_path / "x.lrec")), "no scan 9"),
    ]
    for args, needle in cases:
        done = lamina(*args, *library)
        assert done.returncode != 0 and done.stdout == ""
        assert done.stderr.count("\n") == 1 and needle in done.stderr, done.stderr
    assert existing.read_bytes() == b"earlier"
    assert not (tmp_path / "x.dcm").exists() and not (tmp_path / "x.lrec").exists()


def test_cli_record_rebuilds_the_scan_measurements(scanned_library: Path, tmp_path: Path) -> None:
    """The record's contours measure as the scan's report did (0.1 %), and so does its mesh."""
    out = tmp_path / "scan1.lrec"
    done = lamina("export", "1", "-o", str(out), "--library", str(scanned_library))
    assert done.returncode == 0, done.stderr
    assert stat.S_IMODE(out.stat().st_mode) == 0o600
    record = load_record(out.read_bytes())
    with Library(scanned_library) as library:
        report = library.result(1)
    assert report is not None and record.subject == SUBJECT and record.scan_id == 1
    assert record.side == "left"  # issue #24: the side in the .lrec record
    print(f"record {out.stat().st_size} bytes for {len(record.outlines)} outlines")
    assert record.axis["axis_xy_mm"] == report["axis"]["axis_xy_mm"]
    assert record.calibration["matrix"] == report["calibration"]["matrix"]
    rebuilt = record.sections()
    assert len(rebuilt) == len(report["sections"])
    for row, section in zip(report["sections"], rebuilt, strict=True):
        assert (section.index, section.z_mm) == (row["section"], row["z_mm"])
        assert perimeter(section.contour) == pytest.approx(row["perimeter_mm"], rel=1e-3)
        assert polygon_area(section.contour) == pytest.approx(row["area_mm2"], rel=1e-3)
    volume = report["mesh"]["topology"]["volume_mm3"]
    assert record.mesh_volume_mm3() == pytest.approx(volume, rel=1e-3)
    assert json.loads(json.dumps(record.options))["mesh"] == report["options"]["mesh"]
