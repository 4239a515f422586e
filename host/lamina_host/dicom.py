"""A scan's mesh as a DICOM Encapsulated STL object, which PACS archives file and return.

The Encapsulated STL IOD (SOP Class 1.2.840.10008.5.1.4.1.1.104.3, DICOM PS3.3 A.85)
wraps a binary STL file with the patient, study, series, equipment and unit modules an
archive needs. Lamina keeps subjects pseudonymous: Patient ID carries the subject code,
Patient's Name stays empty (never a name), and the institution is what the user configures.

Study, series and frame-of-reference UIDs are derived from the scan (library scan id,
creation time and subject code), so every export of one scan lands in one study and
series; each export gets a fresh SOP Instance UID.
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
from lamina_host.mesh import stl_bytes, stl_triangles
from lamina_host.workflow import InputError

ENCAPSULATED_STL = "1.2.840.10008.5.1.4.1.1.104.3"
"""SOP Class UID of Encapsulated STL Storage."""

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
    """

    subject: str
    scan_id: int
    created: str
    institution: str = ""
    device_serial: str = "unknown"
    device_software: str = ""


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


def encapsulated_stl(vertices: np.ndarray, faces: np.ndarray, context: DicomContext) -> Dataset:
    """Return the Encapsulated STL dataset (with file meta) of a triangle mesh in mm."""
    stl = stl_bytes(vertices, faces, f"Lamina scan {context.scan_id}")
    now = datetime.now(UTC)
    study_date, study_time = _study_datetime(context.created)
    ds = Dataset()
    ds.SpecificCharacterSet = "ISO_IR 100"
    ds.SOPClassUID = ENCAPSULATED_STL
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
    # Encapsulated Document Series.
    ds.Modality = "M3D"
    ds.SeriesInstanceUID = _uid(context, "series")
    ds.SeriesNumber = 1
    ds.SeriesDescription = "Surface mesh (STL)"
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
    # Encapsulated Document.
    ds.InstanceNumber = 1
    ds.ContentDate = now.strftime("%Y%m%d")
    ds.ContentTime = now.strftime("%H%M%S")
    ds.AcquisitionDateTime = study_date + study_time
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
