"""The terminal UI's one door to the scan workflow (:mod:`lamina_host.workflow.job`).

The app holds one :class:`~lamina_host.workflow.job.ScanJob`; its steps block (serial
I/O, calibration, meshing), so the UI calls them only from thread workers. What is here
is the UI's own: reading the typed fields into a plan and a subject code, starting a scan
and processing with the UI's checks (:func:`scan_object`, :func:`process`), the list of
serial ports, and the one line shown for an error a worker caught. Every error a user
can act on derives from :class:`LaminaError` (:data:`USER_ERRORS` adds the library's and
the file system's); anything else is a bug and is logged.
"""

from __future__ import annotations

import sqlite3
from contextlib import suppress
from dataclasses import replace

import serial.tools.list_ports

from lamina_host.link.errors import DeviceError
from lamina_host.reconstruct.mesh import MESH_METHODS
from lamina_host.reconstruct.pipeline import ProcessOptions
from lamina_host.store.files import disk_full
from lamina_host.store.subjects import check_subject as check_subject_code
from lamina_host.workflow import check_plan
from lamina_host.workflow.job import (
    EXPORT_NAMES,
    TRIM_FRACTION,
    Busy,
    DeviceTarget,
    NoticeHandler,
    ProgressHandler,
    ScanJob,
    ScanRequest,
    SegmentHandler,
)
from lamina_host.workflow.results import (
    Results,
    ScanData,
    SectionRow,
    radius_profile,
    roundness,
    section_rows,
    volume_mm3,
)
from lamina_shared.errors import InputError, LaminaError
from lamina_shared.link import LinkClosed
from lamina_shared.messages import Progress
from lamina_shared.types import ScanPlan, Segment

# pymeshlab (the optional extra) must be first imported on the main thread: when its first
# import happens in a worker thread (as meshing here does), the process aborts at exit with
# heap corruption ("malloc_consolidate(): unaligned fastbin chunk detected"), seen with
# pymeshlab 2025.7. Without it only ball pivoting and Poisson are unavailable.
with suppress(ImportError):
    import pymeshlab  # noqa: F401

__all__ = [
    "EXPORT_NAMES",
    "TRIM_FRACTION",
    "USER_ERRORS",
    "Busy",
    "DeviceTarget",
    "Progress",
    "Results",
    "ScanData",
    "ScanJob",
    "SectionRow",
    "UserError",
    "check_subject",
    "parse_plan",
    "process",
    "radius_profile",
    "roundness",
    "scan_object",
    "section_rows",
    "serial_ports",
    "user_message",
    "volume_mm3",
]

UserError = InputError
"""Bad input typed into the UI; the text names the field and what to enter (the same
refusals as the command line's, from :mod:`lamina_host.workflow`)."""

FIELD_NAMES = {"mesh": "mesh method"}
"""How the Results screen names a processing option in a refusal (the rules are
``ProcessOptions``'); the others by their own names."""

FIELD_HINTS = {"harmonics": ", or blank for auto"}
"""What a refusal of a typed field adds: how to leave the choice to the pipeline."""

USER_ERRORS: tuple[type[Exception], ...] = (LaminaError, sqlite3.Error, OSError)
"""What a worker reports as a one-line message instead of failing: Lamina's own errors,
and the library's and the file system's (not bugs of Lamina)."""


def user_message(exc: BaseException) -> str:
    """Return the one line the UI shows for an error a worker caught."""
    if isinstance(exc, LinkClosed):
        return f"the link to the device broke ({exc}); check the cable, then reconnect (c)"
    if isinstance(exc, OSError) and not isinstance(exc, DeviceError):
        return f"file error: {exc.strerror or exc} ({exc.filename or 'no file'})"
    if isinstance(exc, sqlite3.Error) and disk_full(exc):
        return (
            f"the disk holding the scan library is full ({exc}): what was stored is kept; "
            "free space on it, then go on (p resumes a scan)"
        )
    if isinstance(exc, sqlite3.Error):
        return f"the scan library cannot be used ({exc}): if it is damaged, restore a backup"
    return str(exc)


def serial_ports() -> list[str]:
    """Return the serial ports this machine has, by path (USB scanners first)."""
    ports = sorted(serial.tools.list_ports.comports(), key=lambda p: (p.vid is None, p.device))
    return [p.device for p in ports]


def parse_plan(sections: str, pitch_mm: str, views: str) -> ScanPlan:
    """Build a regular scan plan from three typed fields.

    Raises:
        UserError: a field is not a number or out of range (the command line's ranges).
    """
    counts = []
    for name, text in (("sections", sections), ("views", views)):
        try:
            counts.append(int(text))
        except ValueError:  # the field that is wrong, alone (issue #24)
            raise UserError(f"{name} {text!r} must be a whole number, e.g. 8") from None
    n_sections, n_views = counts
    try:
        pitch = float(pitch_mm)
    except ValueError:
        raise UserError(f"pitch {pitch_mm!r} must be a number of mm, e.g. 2") from None
    return check_plan(n_sections, pitch, n_views)


def check_subject(subject_id: str) -> str:
    """Return the typed subject code (spaces around it dropped) or raise :class:`UserError`."""
    text = subject_id.strip()
    if not text:
        raise UserError("enter a subject id before scanning (letters, digits, - and _)")
    return check_subject_code(text)


def scan_object(
    job: ScanJob,
    subject_id: str,
    plan: ScanPlan,
    on_segment: SegmentHandler | None = None,
    on_progress: ProgressHandler | None = None,
    on_notice: NoticeHandler | None = None,
    colour: bool = False,
) -> list[Segment]:
    """Start scanning the subject along ``plan`` (with each point's colour if asked).

    The UI calibrates before it scans (the live plot needs the axis); the received views
    stay in the job's acquisition for a resume after an abort or a drop.
    """
    request = ScanRequest(check_subject(subject_id), plan, colour=colour)
    if job.acquisition.axis is None:
        raise UserError("scan the calibration cylinder first (Calibrate screen, F4)")
    job.device.set_colour(colour)  # before the scan's identity is recorded
    job.acquisition.create(request)
    return job.acquisition.fetch_object(on_segment, on_progress, on_notice)


def process(
    job: ScanJob,
    harmonics: int | None = None,
    mesh_method: str = MESH_METHODS[0],
    harmonic_rule: str | None = None,
) -> Results:
    """Reconstruct the job's scan with the chosen harmonics and mesh method; store the result.

    Args:
        job: the UI's scan job.
        harmonics: a fixed EFD order for every section, or None to let the rule choose.
        mesh_method: one of ``MESH_METHODS``.
        harmonic_rule: one of ``HARMONIC_RULES``, or None for the pipeline's default.
    """
    options = ProcessOptions(harmonics=harmonics, mesh=mesh_method)
    if harmonic_rule is not None:
        options = replace(options, harmonic_rule=harmonic_rule)
    if problem := options.problem(FIELD_NAMES, FIELD_HINTS):
        raise UserError(problem)
    return job.processing.process_scan(options)
