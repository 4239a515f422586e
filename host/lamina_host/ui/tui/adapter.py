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

import re
import sqlite3
from contextlib import suppress
from dataclasses import dataclass, replace
from pathlib import Path

import serial.tools.list_ports

from lamina_host.clinical.measures import COMPARISONS
from lamina_host.clinical.report import MeasureRequest, build_report_data
from lamina_host.clinical.report_page import write_report
from lamina_host.link.errors import DeviceError
from lamina_host.reconstruct.mesh import MESH_METHODS
from lamina_host.reconstruct.pipeline import ProcessOptions
from lamina_host.store.files import disk_full
from lamina_host.store.library import SIDES
from lamina_host.store.subjects import check_subject as check_subject_code
from lamina_host.workflow import check_plan
from lamina_host.workflow.checks import PlanPreset, check_preset_fits
from lamina_host.workflow.exports import export_scan
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
from lamina_shared.device_specs import SIM
from lamina_shared.errors import InputError, LaminaError
from lamina_shared.link import LinkClosed
from lamina_shared.messages import Progress, Welcome
from lamina_shared.presets import RIG_PRESETS
from lamina_shared.types import ScanPlan, Segment

# pymeshlab (the optional extra) must be first imported on the main thread: when its first
# import happens in a worker thread (as meshing here does), the process aborts at exit with
# heap corruption ("malloc_consolidate(): unaligned fastbin chunk detected"), seen with
# pymeshlab 2025.7. Without it only ball pivoting and Poisson are unavailable.
with suppress(ImportError):
    import pymeshlab  # noqa: F401

__all__ = [
    "EXPORT_NAMES",
    "REPORT_NAMES",
    "TRIM_FRACTION",
    "USER_ERRORS",
    "Busy",
    "CompareChoice",
    "DeviceTarget",
    "Progress",
    "Results",
    "ScanData",
    "ScanJob",
    "SectionRow",
    "UserError",
    "check_subject",
    "choose_rig",
    "compare_choices",
    "export_all",
    "is_simulated",
    "parse_plan",
    "process",
    "radius_profile",
    "roundness",
    "scan_object",
    "screen_words",
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


SCREEN_WORDS: tuple[tuple[re.Pattern[str], str], ...] = tuple(
    (re.compile(pattern), words)
    for pattern, words in (
        (r"or use --device sim", "or pick sim in the port list"),
        (r"pass --cylinder-mm", "give its diameter in the device's configuration"),
        (r"the simulator without --noise harsh", "the simulator's thesis camera"),
        (
            r"finish it with lamina scan --resume (\d+)( --device \S+)?",
            r"finish it: connect, open scan \1 in the Library (F7) and press p on the Scan screen",
        ),
        (
            r"process it again with lamina process (\d+) \[options\] "
            r"\(or p on the terminal UI's Library screen\)",
            r"process it again: p on the Library screen (F7)",
        ),
    )
)
"""Advice the workflow words for the command line, and what the screens say instead: a
screen never tells its user to type a command-line option."""


def screen_words(message: str) -> str:
    """Return ``message`` with command-line advice put in the words of the screens."""
    for pattern, words in SCREEN_WORDS:
        message = pattern.sub(words, message)
    return message


def user_message(exc: BaseException) -> str:
    """Return the one line the UI shows for an error a worker caught."""
    return screen_words(_message(exc))


def _message(exc: BaseException) -> str:
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
    n_sections = _whole(sections, "Sections", "e.g. 10")
    try:
        pitch = float(pitch_mm)
    except ValueError:
        raise UserError(_typed("Pitch mm", pitch_mm, "a number of mm, e.g. 2")) from None
    n_views = _whole(views, "Views", "e.g. 8")
    return check_plan(n_sections, pitch, n_views)


def _typed(field: str, text: str, wanted: str) -> str:
    """Return the line refusing what was typed into ``field`` (named as the screen does)."""
    shown = repr(text.strip()) if text.strip() else "empty"
    return f"{field} is {shown}: enter {wanted}"


def _whole(text: str, field: str, example: str) -> int:
    """Return the whole number typed into ``field``, or refuse naming that field alone."""
    try:
        return int(text)
    except ValueError:
        raise UserError(_typed(field, text, f"a whole number, {example}")) from None


def check_subject(subject_id: str) -> str:
    """Return the typed subject code (spaces around it dropped) or raise :class:`UserError`."""
    text = subject_id.strip()
    if not text:
        raise UserError(
            "Subject is empty: enter a subject id before scanning (letters, digits, - and _)"
        )
    return check_subject_code(text)


def scan_object(
    job: ScanJob,
    subject_id: str,
    plan: ScanPlan,
    on_segment: SegmentHandler | None = None,
    on_progress: ProgressHandler | None = None,
    on_notice: NoticeHandler | None = None,
    colour: bool = False,
    side: str = SIDES[0],
    preset: PlanPreset | None = None,
) -> list[Segment]:
    """Start scanning the subject's ``side`` along ``plan`` (with each point's colour if asked).

    The UI calibrates before it scans (the live plot needs the axis); the received views
    stay in the job's acquisition for a resume after an abort or a drop. A ``preset`` is
    refused before anything is recorded when its kind of object is wider than the view.
    """
    request = ScanRequest(check_subject(subject_id), plan, colour=colour, side=side)
    if job.acquisition.axis is None:
        raise UserError("scan the calibration cylinder first (Calibrate screen, F4)")
    if preset is not None:
        check_preset_fits(preset, job.acquisition.field_radius_mm())
    job.device.set_colour(colour)  # before the scan's identity is recorded
    job.acquisition.create(request)
    return job.acquisition.fetch_object(on_segment, on_progress, on_notice)


def is_simulated(job: ScanJob) -> bool:
    """Return True when the job's device is the simulator (its rig is a choice)."""
    return job.device.name == SIM


def choose_rig(job: ScanJob, rig: str) -> Welcome | None:
    """Use the simulated rig ``rig`` from now on; a connected simulator starts again with it.

    The calibration belongs to the rig it was made on, so it is forgotten.

    Returns:
        The restarted simulator's information (None when not connected).

    Raises:
        UserError: not the simulator (a scanner is its own rig), or an unknown rig.
    """
    if rig not in RIG_PRESETS:
        raise UserError(f"Rig {rig!r} is not one of {', '.join(RIG_PRESETS)}")
    if not is_simulated(job):
        raise UserError("Rig: a scanner is its own rig; only the simulator offers a choice")
    job.device.target = replace(job.device.target, rig=rig)
    acquisition = job.acquisition
    acquisition.grid, acquisition.grid_accepted, acquisition.axis = None, False, None
    acquisition.calibrated_by = None
    return job.connect() if job.device.connected else None


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


@dataclass(frozen=True)
class CompareChoice:
    """A scan the open one may be compared with, as the Results screen offers it.

    Attributes:
        scan_id: the library scan compared with.
        kind: ``limbs`` (the other limb: the excess) or ``visits`` (an earlier visit of the
            same side: the change).
        label: the choice in words (side, scan and date).
    """

    scan_id: int
    kind: str
    label: str


def compare_choices(job: ScanJob) -> list[CompareChoice]:
    """Return what the open scan may be compared with: the other limb's latest scan first,
    then the same subject's other visits of its side, newest first (processed scans only).

    None when no scan is open; an unreadable library gives none either (the screen still
    measures the scan itself).
    """
    scan_id = job.scan_id
    if scan_id is None:
        return []
    library = job.store.library()
    record = library.scan(scan_id)
    others = [
        s
        for s in library.scans()
        if s.subject == record.subject and s.id != scan_id and s.has_result
    ]
    choices = []
    opposite = {"left": "right", "right": "left"}.get(record.side)
    limbs = [s for s in others if s.side == opposite]
    if limbs:
        latest = max(limbs, key=lambda s: (s.created, s.id))
        choices.append(
            CompareChoice(
                latest.id,
                COMPARISONS[0],
                f"other limb ({latest.side}): scan {latest.id}, {latest.created[:10]}",
            )
        )
    for visit in sorted(others, key=lambda s: (s.created, s.id), reverse=True):
        if visit.side == record.side:
            choices.append(
                CompareChoice(
                    visit.id, COMPARISONS[1], f"visit: scan {visit.id}, {visit.created[:10]}"
                )
            )
    return choices


REPORT_NAMES = ("report.pdf", "measures.csv", "scan.dcm")
"""What an export from the Results screen adds to :data:`EXPORT_NAMES`: the clinical report,
its table and the DICOM object."""


def export_all(
    job: ScanJob,
    folder: Path,
    request: MeasureRequest | None = None,
    compare_with: CompareChoice | None = None,
) -> list[Path]:
    """Export the open, processed scan into a new (or empty) folder: mesh, JSON report, the
    clinical report (PDF) and its table (CSV) with the comparison chosen, and the DICOM file.

    The measurement is made first, so a comparison that cannot be made is refused before
    anything is written.

    Raises:
        InputError: nothing processed, the folder is not new or empty, or the comparison
            cannot be made (the one line says why).
    """
    scan_id = job.scan_id
    if job.processing.results is None or scan_id is None:
        raise UserError("process the scan first (p on the Results screen)")
    library = job.store.library()
    reference, kind = (None, COMPARISONS[0]) if compare_with is None else (
        compare_with.scan_id, compare_with.kind
    )  # fmt: skip
    data = build_report_data(library, scan_id, request or MeasureRequest(), reference, kind)
    paths = job.processing.export(folder)
    pdf, table, dicom = (folder / name for name in REPORT_NAMES)
    paths += [write_report(pdf, data), write_report(table, data)]
    paths.append(export_scan(library, scan_id, dicom))
    return paths
