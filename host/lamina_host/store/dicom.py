"""A scan's mesh as a DICOM Encapsulated STL object, which PACS archives file and return.

The Encapsulated STL IOD (SOP Class 1.2.840.10008.5.1.4.1.1.104.3, DICOM PS3.3 A.85)
wraps a binary STL file with the patient, study, series, equipment and unit modules an
archive needs. Lamina keeps subjects pseudonymous: Patient ID carries the subject code,
Patient's Name stays empty (never a name), and the institution is what the user configures.

The limb side a scan records is written as the object's laterality (R or L) and in the
series description: Image Laterality (0020,0062) of the Encapsulated Document module for
Encapsulated STL (that IOD's series module has no Laterality), Laterality (0020,0060) of
the series for the Surface Scan Mesh. A scan of side ``none`` has neither.

Study, series and frame-of-reference UIDs are derived from the scan (library scan id,
creation time and subject code), so every export of one scan lands in one study and
series; each export gets a fresh SOP Instance UID.

Experimental: the mesh as a Surface Scan Mesh object (SOP Class
1.2.840.10008.5.1.4.1.1.68.1, PS3.3 A.68: the Optical Surface Scanner series, the Surface
Mesh module holding the vertices and triangles themselves, and the Scan Procedure).
Few viewers read it yet, and dicom3tools' dciodvfy (2022) has no definition of this IOD
("Information Object Not found"), so only its encoding is checked here (pydicom reads it
back and the mesh is compared). The scan procedure is described with codes of Lamina's
own coding scheme (``99LAMINA``), not with codes from DICOM's context groups.
"""

from __future__ import annotations

import io
from dataclasses import dataclass
from datetime import UTC, datetime

import numpy as np
import pydicom
from pydicom.dataset import Dataset, FileMetaDataset
from pydicom.uid import ExplicitVRLittleEndian, generate_uid

from lamina_host import __version__
from lamina_host.reconstruct.mesh import stl_bytes, stl_triangles
from lamina_shared.errors import InputError

ENCAPSULATED_STL = "1.2.840.10008.5.1.4.1.1.104.3"
"""SOP Class UID of Encapsulated STL Storage."""
SURFACE_SCAN_MESH = "1.2.840.10008.5.1.4.1.1.68.1"
"""SOP Class UID of Surface Scan Mesh Storage (experimental here)."""
DICOM_SOPS = {"encapsulated-stl": ENCAPSULATED_STL, "surface-scan": SURFACE_SCAN_MESH}
"""What ``lamina export --dicom-sop`` chooses from; the first is the default."""

MANUFACTURER = "Lamina project"
MODEL_NAME = "Lamina light-sectioning scanner"
INSTITUTION_MAX_CHARS = 64
"""Institution Name is a DICOM LO value: at most 64 characters."""


@dataclass(frozen=True)
class DicomContext:
    """What a DICOM file says about the scan besides its mesh.

    Attributes:
        subject: the pseudonymous subject code (Patient ID and Patient's Name).
        scan_id: the scan's id in its library (Study ID, and part of the UIDs' seed).
        created: the scan's ISO 8601 creation time (study date and time).
        institution: Institution Name, or "" to leave it out.
        device_serial: the scanner's serial (Device Serial Number), "unknown" if not known.
        device_software: the scanner's software version, if known.
        side: the limb scanned, ``left``, ``right`` or ``none`` (Laterality L, R or absent).
    """

    subject: str
    scan_id: int
    created: str
    institution: str = ""
    device_serial: str = "unknown"
    device_software: str = ""
    side: str = "none"


LATERALITY = {"left": "L", "right": "R"}
"""DICOM (Image) Laterality of each limb side; a scan of side ``none`` has none."""


def check_institution(name: str) -> str:
    """Return ``name`` if it is a valid Institution Name, else raise InputError (one line)."""
    if len(name) > INSTITUTION_MAX_CHARS or not all(" " <= ch <= "~" for ch in name):
        raise InputError(
            f"--institution must be at most {INSTITUTION_MAX_CHARS} printable ASCII "
            "characters (letters, digits, spaces, punctuation)"
        )
    if "\\" in name:
        raise InputError("--institution cannot contain a backslash (DICOM separates values by it)")
    return name.strip()


def _uid(context: DicomContext, role: str) -> str:
    """Return a UID fixed by the scan and ``role``, so repeated exports share study and series."""
    return generate_uid(entropy_srcs=[context.subject, str(context.scan_id), context.created, role])


def _code(value: str, scheme: str, meaning: str) -> Dataset:
    item = Dataset()
    item.CodeValue = value
    item.CodingSchemeDesignator = scheme
    item.CodeMeaning = meaning
    return item


def _study_datetime(created: str) -> tuple[str, str]:
    """Return DICOM DA and TM strings of an ISO 8601 time (UTC), or now if unreadable."""
    try:
        moment = datetime.fromisoformat(created).astimezone(UTC)
    except ValueError:
        moment = datetime.now(UTC)
    return moment.strftime("%Y%m%d"), moment.strftime("%H%M%S")


def _new_dataset(sop: str, context: DicomContext, series: tuple[str, int, str]) -> Dataset:
    """Return a dataset of SOP class ``sop`` with the modules both IODs share filled.

    ``series``: the series' modality, number and description (its UID follows from them).
    """
    modality, number, description = series
    now = datetime.now(UTC)
    study_date, study_time = _study_datetime(context.created)
    ds = Dataset()
    ds.SOPClassUID = sop
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.SOPInstanceUID = generate_uid()
    ds.InstanceCreationDate = now.strftime("%Y%m%d")
    ds.InstanceCreationTime = now.strftime("%H%M%S")
    # Patient: the pseudonymous code only. The name stays empty (type 2): a bare code in a
    # Person Name is the retired name form validators warn about.
    ds.PatientName = ""
    ds.PatientID = context.subject
    ds.PatientBirthDate = ""
    ds.PatientSex = ""
    # General Study.
    ds.StudyInstanceUID = _uid(context, "study")
    ds.StudyDate = study_date
    ds.StudyTime = study_time
    ds.ReferringPhysicianName = ""
    ds.StudyID = str(context.scan_id)[:16]
    ds.AccessionNumber = ""
    ds.StudyDescription = "Lamina 3D surface scan"
    # Frame of Reference: the scan's object frame (turntable axis, first section at z 0).
    ds.FrameOfReferenceUID = _uid(context, "frame")
    ds.PositionReferenceIndicator = ""
    # General and Enhanced General Equipment.
    ds.Manufacturer = MANUFACTURER
    if context.institution:
        ds.InstitutionName = context.institution
    ds.ManufacturerModelName = MODEL_NAME
    ds.DeviceSerialNumber = (context.device_serial or "unknown")[:64]
    ds.SoftwareVersions = [f"lamina-host {__version__}"] + (
        [f"lamina-device {context.device_software}"[:64]] if context.device_software else []
    )
    ds.InstanceNumber = 1
    ds.ContentDate = now.strftime("%Y%m%d")
    ds.ContentTime = now.strftime("%H%M%S")
    # General Series (the Encapsulated Document or Optical Surface Scanner series).
    ds.Modality = modality
    ds.SeriesInstanceUID = _uid(context, "series" if number == 1 else f"series-{modality}")
    ds.SeriesNumber = number
    ds.SeriesDescription = description
    if context.side in LATERALITY:
        ds.SeriesDescription = f"{description}, {context.side} limb"[:64]
    return ds


def encapsulated_stl(vertices: np.ndarray, faces: np.ndarray, context: DicomContext) -> Dataset:
    """Return the Encapsulated STL dataset (with file meta) of a triangle mesh in mm."""
    stl = stl_bytes(vertices, faces, f"Lamina scan {context.scan_id}")
    ds = _new_dataset(ENCAPSULATED_STL, context, ("M3D", 1, "Surface mesh (STL)"))
    # Encapsulated Document.
    ds.AcquisitionDateTime = ds.StudyDate + ds.StudyTime
    if context.side in LATERALITY:
        ds.ImageLaterality = LATERALITY[context.side]
    ds.BurnedInAnnotation = "NO"
    # A surface scan of a face can identify its subject: flag it, archives then treat it so.
    ds.RecognizableVisualFeatures = "YES"
    ds.DocumentTitle = f"Lamina scan {context.scan_id} surface mesh"[:64]
    ds.ConceptNameCodeSequence = []
    ds.MIMETypeOfEncapsulatedDocument = "model/stl"
    ds.EncapsulatedDocument = stl + (b"\0" if len(stl) % 2 else b"")
    ds.EncapsulatedDocumentLength = len(stl)
    # Manufacturing 3D Model: coordinates are millimetres.
    ds.MeasurementUnitsCodeSequence = [_code("mm", "UCUM", "millimeter")]
    ds.file_meta = _file_meta(ds)
    return ds


def surface_scan_mesh(
    vertices: np.ndarray, faces: np.ndarray, context: DicomContext, closed: bool = True
) -> Dataset:
    """Return the (experimental) Surface Scan Mesh dataset of a triangle mesh in mm.

    ``closed``: the mesh is watertight (the Surface Mesh module's Finite Volume and
    Manifold say YES, else UNKNOWN).
    """
    ds = _new_dataset(
        SURFACE_SCAN_MESH, context, ("OSS", 2, "Surface mesh (Surface Scan Mesh, experimental)")
    )
    # Scan Procedure: a laser line on a turntable (Lamina's own codes, see the module text).
    ds.SurfaceScanAcquisitionTypeCodeSequence = [
        _code("LIGHT-SECTION", "99LAMINA", "Laser light sectioning")
    ]
    if context.side in LATERALITY:
        ds.Laterality = LATERALITY[context.side]
    ds.SurfaceScanModeCodeSequence = [_code("TURNTABLE", "99LAMINA", "Turntable views")]
    ds.RegistrationMethodCodeSequence = [_code("AXIS-CAL", "99LAMINA", "Calibrated turntable axis")]
    # Surface Mesh: one surface, its points and triangles. DICOM numbers the points from 1
    # (PS3.3 C.27.4.1; the tetrahedron of PS3.17 JJ.2), Lamina's meshes from 0.
    coords = np.ascontiguousarray(vertices, "<f4")
    points = Dataset()
    points.NumberOfSurfacePoints = len(coords)
    points.PointCoordinatesData = coords.tobytes()
    points.PointsBoundingBoxCoordinates = [*map(float, coords.min(0)), *map(float, coords.max(0))]
    primitives = Dataset()
    primitives.LongVertexPointIndexList = b""
    primitives.LongEdgePointIndexList = b""
    primitives.LongTrianglePointIndexList = np.ascontiguousarray(faces + 1, "<u4").tobytes()
    for empty in ("TriangleStripSequence", "TriangleFanSequence", "LineSequence", "FacetSequence"):
        setattr(primitives, empty, [])
    surface = Dataset()
    surface.SurfaceNumber = 1
    surface.SurfaceComments = f"Lamina scan {context.scan_id}"
    surface.SurfaceProcessing = "NO"
    surface.RecommendedDisplayGrayscaleValue = 0xFFFF
    surface.RecommendedDisplayCIELabValue = [0xFFFF, 0x8080, 0x8080]
    surface.RecommendedPresentationOpacity = 1.0
    surface.RecommendedPresentationType = "SURFACE"
    surface.FiniteVolume = "YES" if closed else "UNKNOWN"
    surface.Manifold = "YES" if closed else "UNKNOWN"
    surface.SurfacePointsSequence = [points]
    surface.SurfacePointsNormalsSequence = []
    surface.SurfaceMeshPrimitivesSequence = [primitives]
    ds.NumberOfSurfaces = 1
    ds.SurfaceSequence = [surface]
    ds.file_meta = _file_meta(ds)
    return ds


def read_surface_mesh(path_or_bytes: str | bytes | io.BytesIO) -> tuple[np.ndarray, np.ndarray]:
    """Return the float32 vertices and triangles of a Surface Scan Mesh file (path or bytes)."""
    source = io.BytesIO(path_or_bytes) if isinstance(path_or_bytes, bytes) else path_or_bytes
    ds = pydicom.dcmread(source)
    if ds.SOPClassUID != SURFACE_SCAN_MESH:
        raise ValueError(f"not a Surface Scan Mesh object (SOP Class {ds.SOPClassUID})")
    surface = ds.SurfaceSequence[0]
    points = surface.SurfacePointsSequence[0]
    vertices = np.frombuffer(points.PointCoordinatesData, "<f4").reshape(-1, 3)
    if len(vertices) != int(points.NumberOfSurfacePoints):
        raise ValueError("the surface's point count does not match its coordinates")
    index = surface.SurfaceMeshPrimitivesSequence[0].LongTrianglePointIndexList
    return vertices, np.frombuffer(index, "<u4").reshape(-1, 3).astype(np.int64) - 1


def _file_meta(ds: Dataset) -> FileMetaDataset:
    meta = FileMetaDataset()
    meta.MediaStorageSOPClassUID = ds.SOPClassUID
    meta.MediaStorageSOPInstanceUID = ds.SOPInstanceUID
    meta.TransferSyntaxUID = ExplicitVRLittleEndian
    meta.ImplementationVersionName = f"LAMINA_{__version__}"[:16]
    return meta


def dicom_bytes(ds: Dataset) -> bytes:
    """Return a dataset as a DICOM Part 10 file (preamble, file meta, explicit VR LE)."""
    buffer = io.BytesIO()
    ds.save_as(buffer, enforce_file_format=True)
    return buffer.getvalue()


def read_stl_triangles(path_or_bytes: str | bytes | io.BytesIO) -> np.ndarray:
    """Return the (F, 3, 3) float32 triangles of an Encapsulated STL file (path or bytes)."""
    source = io.BytesIO(path_or_bytes) if isinstance(path_or_bytes, bytes) else path_or_bytes
    ds = pydicom.dcmread(source)
    if ds.SOPClassUID != ENCAPSULATED_STL:
        raise ValueError(f"not an Encapsulated STL object (SOP Class {ds.SOPClassUID})")
    data = bytes(ds.EncapsulatedDocument)[: int(ds.EncapsulatedDocumentLength)]
    return stl_triangles(data)
