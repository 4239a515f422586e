"""``lamina``: scan with a Lamina device and turn the stripes into contours and a mesh.

Every user mistake ends in one line on stderr naming the problem and what to do,
with a non-zero exit status; data already received is written before processing.
Everything that can be checked (options, plan, subject code, output folder, library,
the device's limits) is checked before a scan is created or acquisition starts, and a
resume is refused unless the device, its setup and the options are those the scan
began with.
"""

from __future__ import annotations

import argparse
import difflib
import math
import os
import re
import signal
import sqlite3
import sys
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager, suppress
from dataclasses import replace
from importlib.util import find_spec
from pathlib import Path
from typing import Any, NoReturn

from lamina_host import __version__
from lamina_host.clinical.measures import AXES, COMPARISONS, Thresholds, parse_landmark
from lamina_host.clinical.report import (
    LENGTH_UNITS,
    MeasureRequest,
    build_report_data,
    headline_flags,
)
from lamina_host.clinical.report_page import write_report
from lamina_host.link.errors import DeviceError, RequestRefused
from lamina_host.link.local_box import is_endpoint
from lamina_host.reconstruct.assembly import DEFAULT_TRIM_FRACTION, THESIS_TRIM_FRACTION
from lamina_host.reconstruct.axis import gear_advice
from lamina_host.reconstruct.expect import Expectation, parse_expectation
from lamina_host.reconstruct.mesh import meshlab
from lamina_host.reconstruct.pipeline import ANGLE_CORRECTION_AXIS, OPTION_CHOICES, ProcessOptions
from lamina_host.reconstruct.status import OutlineStatus
from lamina_host.store.dicom import DICOM_SOPS, check_institution
from lamina_host.store.files import (
    OutputError,
    disk_full,
    new_file_problem,
    prepare_output_folder,
)
from lamina_host.store.library import (
    SIDES,
    Library,
    ScanRecord,
    default_library_path,
    formats_text,
)
from lamina_host.store.outputs import FailedEntry, ScanReport
from lamina_host.store.pacs import (
    DEFAULT_CALLING_AE,
    DEFAULT_TIMEOUT_S,
    check_ae_title,
    check_timeout,
    parse_target,
    send_dicom,
)
from lamina_host.store.subjects import SUBJECT_RULE, check_subject
from lamina_host.workflow import (
    DEFAULT_PITCH_MM,
    DEFAULT_SECTIONS,
    DEFAULT_VIEWS,
    check_count,
    check_plan,
    check_positive_mm,
)
from lamina_host.workflow.batch import (
    ClinicalMeasure,
    check_output,
    check_pattern,
    run_batch,
    select_scans,
    write_table,
)
from lamina_host.workflow.exports import ALL_FORMATS, dicom_export, export_scan
from lamina_host.workflow.job import Acquired, DeviceTarget, ScanJob, ScanRequest, acquire
from lamina_host.workflow.results import distortion_summary, lift_summary, mesh_summary
from lamina_shared.device_specs import SIM, replay_folder, spawns_device
from lamina_shared.durations import duration_text
from lamina_shared.errors import InputError, LaminaError, printable
from lamina_shared.link import LinkClosed
from lamina_shared.messages import Progress
from lamina_shared.ops import ArgsError, ExtractChanges, parse_extract_text
from lamina_shared.presets import NOISE_PRESETS, RIG_PRESETS
from lamina_shared.protocol import ProtocolError
from lamina_shared.types import SCAN_MODES, ScanPlan

EXIT_USAGE = 2
PLAN_REFUSALS = frozenset({"limit", "bad-args", "unsupported"})
"""Refusal codes of a device that will refuse the same plan again (no resume can help)."""


class UsageError(InputError):
    """A mistake in how the command was called."""


class Interrupted(KeyboardInterrupt):
    """Ctrl+C, SIGTERM or SIGHUP stopped a command; ``hint`` says how to go on (or "")."""

    def __init__(self, hint: str = "") -> None:
        super().__init__(hint)
        self.hint = hint


STOP_SIGNALS = (signal.SIGTERM, signal.SIGHUP)
"""Signals that end ``lamina scan`` as Ctrl+C does (an SSH session dropping, a terminal
closed, a service manager stopping it): what arrived is written, and the resume named."""


def _interrupt(signum: int, frame: Any) -> None:
    """Turn a stop signal into the interrupt Ctrl+C gives (on the main thread)."""
    raise Interrupted()


@contextmanager
def _stop_signals_interrupt() -> Iterator[None]:
    """While inside, SIGTERM and SIGHUP interrupt like SIGINT; the old handlers come back."""
    previous = {number: signal.signal(number, _interrupt) for number in STOP_SIGNALS}
    try:
        yield
    finally:
        for number, handler in previous.items():
            signal.signal(number, handler)


SCAN_DEFAULTS: dict[str, Any] = {
    "subject": "anonymous",
    "trim": None,  # the pipeline's own (_pipeline_trim)
    "seed": 0,
    "noise": "thesis",
    "rig": "thesis",
    "colour": False,
    "sway": "none",
}
"""Defaults of scan options a resume must be able to tell from values given (so None)."""


def did_you_mean(word: str, choices: Sequence[str]) -> str:
    """Return "; did you mean X?" for the choice nearest ``word`` (or "" if none is near)."""
    near = difflib.get_close_matches(word, list(choices), n=1, cutoff=0.6)
    return f"; did you mean {near[0]}?" if near else ""


_INVALID_CHOICE = re.compile(r"argument (\S+): invalid choice: '(.*)' \(choose from (.*)\)$")


class LaminaParser(argparse.ArgumentParser):
    """argparse's parser, refusing a mistake in one line (not the whole usage) with a hint.

    A word that is not one of an option's choices is answered with the nearest choice.
    """

    def error(self, message: str) -> NoReturn:
        """Print one line naming the mistake and the nearest right word, then exit 2."""
        found = _INVALID_CHOICE.search(message)
        if found is not None:
            option, value, listed = found.groups()
            choices = re.findall(r"'([^']*)'", listed)
            what = "no command" if option == "command" else f"not a choice of {option}"
            message = f"{value!r} is {what} (choose from {', '.join(choices)})" + did_you_mean(
                value, choices
            )
        self.exit(EXIT_USAGE, f"{self.prog}: {message} (see {self.prog} --help)\n")


def check_option_names(parser: argparse.ArgumentParser, argv: Sequence[str]) -> None:
    """Refuse an option the command does not have, in one line with the nearest one.

    Checked before parsing, so that a misspelt required option (``--devce``) is named as
    the mistake, not reported as the required one missing. Abbreviations argparse accepts
    (a unique start of an option) pass.
    """
    commands = next(
        (a.choices for a in parser._actions if isinstance(a, argparse._SubParsersAction)), {}
    )
    if not argv or argv[0] not in commands:
        return  # no command yet, or an unknown one: argparse says so
    command = commands[argv[0]]
    known = [o for o in command._option_string_actions if o.startswith("--")]
    for word in argv[1:]:
        if word == "--":
            return
        name = word.split("=", 1)[0]
        if word.startswith("--") and not any(o.startswith(name) for o in known):
            command.error(f"there is no option {name}{did_you_mean(name, known)}")


DEVICE_WORDS = (SIM, "local")
"""The device names that are words rather than ports or URLs (``replay:DIR`` has a folder)."""


def check_device_name(device: str) -> None:
    """Refuse a DEVICE that is a near miss of ``sim`` or ``local``, in one line.

    A port that does not exist is otherwise named by the link when it opens it; a typo
    of a word Lamina knows is named here, before anything starts.
    """
    if spawns_device(device) or is_endpoint(device) or "://" in device:
        return
    near = difflib.get_close_matches(device, DEVICE_WORDS, n=1, cutoff=0.6)
    if near and not os.path.exists(device):
        raise UsageError(
            f"--device {device} is neither a serial port here nor a device Lamina knows; "
            f"did you mean --device {near[0]}?"
        )


def build_parser() -> argparse.ArgumentParser:
    """Return the command-line parser."""
    parser = LaminaParser(prog="lamina", description=__doc__)
    parser.add_argument("--version", action="version", version=f"lamina {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    scan = sub.add_parser("scan", help="calibrate, scan and reconstruct one object")
    scan.add_argument(
        "--device",
        required=True,
        help="serial port path, 'local' (the device service on this machine, or "
        "socket://HOST:PORT), another pyserial URL (spy://PORT?file=LOG logs the wire), "
        "'sim', or 'replay:CAPTURE_DIR'",
    )
    scan.add_argument(
        "-o", "--out", type=Path, help="new output folder (when resuming: the scan's own)"
    )
    scan.add_argument(
        "--subject",
        help=f"pseudonymous subject code (default anonymous): {SUBJECT_RULE}".replace("%", "%%"),
    )
    scan.add_argument(
        "--side", choices=SIDES, help="the limb scanned: left, right or none (default none)"
    )
    scan.add_argument("--resume", type=int, metavar="SCAN", help="finish scan SCAN of the library")
    scan.add_argument(
        "--reprocess",
        action="store_true",
        help="with --resume of a complete scan: process it again (its outputs are replaced)",
    )
    _add_library_option(scan)
    scan.add_argument("--object", help="simulated object (sim only), e.g. cylinder:d=19.05")
    scan.add_argument(
        "--sections",
        type=int,
        help=f"number of sections (default {DEFAULT_SECTIONS}; with none of --sections, --pitch "
        "and --views the device's own plan)",
    )
    scan.add_argument(
        "--pitch", type=float, help=f"section pitch in mm (default {DEFAULT_PITCH_MM:g})"
    )
    scan.add_argument("--views", type=int, help=f"views per section (default {DEFAULT_VIEWS})")
    scan.add_argument(
        "--extract",
        type=_extract_option,
        metavar="KEY=VALUE[,KEY=VALUE]",
        help="change the device's stripe extraction for this scan, e.g. method=thinning,power=2",
    )
    scan.add_argument(
        "--mode",
        choices=SCAN_MODES,
        help="how the object's views are taken: stop-and-go (default, the table stops at "
        "each) or continuous (it turns through each section while the camera streams: a "
        "leg in under two minutes, on a device that offers it)",
    )
    scan.add_argument(
        "--sway",
        help="move the simulated object as a patient would (sim only): none, patient, or "
        "drift=MM_PER_MIN,breath=MM,hz=HZ",
    )
    scan.add_argument(
        "--colour",
        action="store_const",
        const=True,
        help="sample each point's colour from the laser-off frames: coloured mesh.ply, "
        "mesh.obj and raw_points.ply (a colour camera; the simulator with --noise harsh)",
    )
    scan.add_argument(
        "--expect", help="known shape to measure accuracy against, e.g. cylinder:d=19.05"
    )
    scan.add_argument(
        "--cylinder-mm",
        type=float,
        help="calibration cylinder diameter (default: what the device reports)",
    )
    scan.add_argument("--harmonics", type=int, help="fixed EFD harmonics (default: by rule)")
    scan.add_argument(
        "--trim",
        type=float,
        help=f"fraction dropped from each segment end (default {DEFAULT_TRIM_FRACTION:g}; "
        f"{THESIS_TRIM_FRACTION:g} with --pipeline thesis)",
    )
    scan.add_argument("--seed", type=int, help="simulation seed (sim only, default 0)")
    scan.add_argument(
        "--noise",
        choices=NOISE_PRESETS,
        help="simulated noise level: thesis, harsh or none (sim only, default thesis)",
    )
    _add_processing_options(scan)
    _add_process_parser(sub)
    scans = sub.add_parser("scans", help="list the scans in the library")
    scans.add_argument(
        "--set-side",
        nargs=2,
        metavar=("SCAN", "SIDE"),
        help="record which limb scan SCAN is (left, right or none), then list",
    )
    scans.add_argument(
        "--set-test",
        type=int,
        metavar="SCAN",
        help="mark scan SCAN as a test (kept, but out of trends and comparisons), then list",
    )
    scans.add_argument(
        "--unset-test", type=int, metavar="SCAN", help="count scan SCAN as a visit again, then list"
    )
    scans.add_argument("--subject", help="list only the scans of this subject code")
    _add_library_option(scans)
    export = sub.add_parser(
        "export",
        help=f"export a scan as {formats_text(ALL_FORMATS)}",
    )
    export.add_argument("scan", type=int, help="scan id (see lamina scans)")
    export.add_argument("-o", "--out", required=True, type=Path, help="new file to write")
    export.add_argument(
        "--institution",
        default="",
        help="Institution Name written into a .dcm export (default: none)",
    )
    export.add_argument(
        "--dicom-sop",
        choices=DICOM_SOPS,
        default=next(iter(DICOM_SOPS)),
        help="the DICOM object of a .dcm: encapsulated-stl (default) or surface-scan "
        "(Surface Scan Mesh, experimental: few viewers read it)",
    )
    _add_library_option(export)
    batch = sub.add_parser(
        "batch", help="reprocess and measure many scans in parallel (Dask) into a CSV table"
    )
    _add_library_option(batch)
    batch.add_argument(
        "--subjects",
        required=True,
        metavar="PATTERN",
        help="subject codes to include, with wildcards * ? [...] (quote it), e.g. 'P0*'",
    )
    batch.add_argument(
        "--measure",
        action="store_true",
        help="measure each scan as lamina report does: circumferences at levels from the "
        "landmark, segment, stack, frustum and mesh volumes (one row per level)",
    )
    _add_measure_options(batch)
    batch.add_argument("-o", "--out", required=True, type=Path, help="new CSV file to write")
    batch.add_argument(
        "--workers", type=int, help="local worker processes (default: all cores; 1: serial)"
    )
    batch.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="run on a dask.distributed scheduler, e.g. tcp://host:8786 (default: local)",
    )
    _add_report_parser(sub)
    _add_send_parser(sub)
    tui = sub.add_parser("tui", help="the terminal UI for the whole workflow (works over SSH)")
    _add_ui_options(tui)
    ui = sub.add_parser("serve-ui", help="serve the terminal UI to a web browser (textual-serve)")
    ui.add_argument(
        "--host", default="127.0.0.1", help="address to listen on (default: this machine only)"
    )
    ui.add_argument("--port", type=int, default=8000, help="TCP port (default 8000)")
    ui.add_argument(
        "--allow-remote",
        action="store_true",
        help="allow a --host other machines can reach (the UI has no login)",
    )
    _add_ui_options(ui)
    return parser


def _add_ui_options(parser: argparse.ArgumentParser) -> None:
    """Add what the terminal UI connects to: ``tui`` and ``serve-ui`` (each browser's tui)."""
    parser.add_argument(
        "--device",
        default="sim",
        help="serial port path, 'local' (the device service on this machine, or "
        "socket://HOST:PORT), 'sim' (default) or 'replay:DIR'",
    )
    parser.add_argument("--object", help="simulated object (sim only), e.g. cylinder:d=19.05")
    parser.add_argument(
        "--noise",
        choices=NOISE_PRESETS,
        help="simulated camera (sim only); 'harsh' is a colour camera, for colour scans",
    )
    parser.add_argument(
        "--rig", choices=RIG_PRESETS, help="simulated rig at start (sim only; the Scan screen "
        "changes it)",
    )  # fmt: skip
    _add_library_option(parser)


def _check_ui_options(args: argparse.Namespace) -> list[str]:
    """Refuse sim-only options for another device; return them as ``lamina tui`` options."""
    check_device_name(args.device)
    if (args.object or args.noise or args.rig) and args.device != SIM:
        raise UsageError("--object, --noise and --rig only apply to --device sim")
    options = ["--device", args.device]
    for flag, value in (("--object", args.object), ("--noise", args.noise), ("--rig", args.rig)):
        options += [flag, value] if value else []
    return options + (["--library", str(args.library.resolve())] if args.library else [])


def _add_measure_options(parser: argparse.ArgumentParser) -> None:
    """Add how a limb is measured: level spacing, landmark and axis (report and batch)."""
    parser.add_argument(
        "--spacing-mm", type=float, default=40.0, help="distance between levels (default 40)"
    )
    parser.add_argument(
        "--landmark",
        default="distal",
        help="level 0: distal (default, the narrower end), bottom, top or a height in mm",
    )
    parser.add_argument(
        "--limb-axis", choices=AXES, default=AXES[0], help="what distances are measured along"
    )


def _check_spacing(spacing_mm: float) -> float:
    """Return a usable level spacing, else raise UsageError (one line)."""
    if not (math.isfinite(spacing_mm) and 1.0 <= spacing_mm <= 1000.0):
        raise UsageError(f"--spacing-mm {spacing_mm} must be between 1 and 1000 mm")
    return spacing_mm


def _add_report_parser(sub: Any) -> None:
    """Add ``lamina report``: a processed scan's clinical measurements on one page."""
    limits = Thresholds()
    report = sub.add_parser(
        "report", help="write a scan's clinical report (.pdf/.png) or its measurement table (.csv)"
    )
    report.add_argument("scan", type=int, help="scan id (see lamina scans)")
    report.add_argument("-o", "--out", required=True, type=Path, help="new .pdf, .png or .csv")
    report.add_argument("--csv", type=Path, help="also write the measurement table to this CSV")
    report.add_argument("--compare", type=int, metavar="SCAN", help="the scan to compare with")
    report.add_argument(
        "--compare-as",
        choices=COMPARISONS,
        default=COMPARISONS[0],
        help="limbs: excess over the other limb (default); visits: change from a baseline",
    )
    report.add_argument(
        "--compare-other-subject",
        action="store_true",
        help="allow --compare with a scan of another subject code (both codes are printed)",
    )
    report.add_argument(
        "--length-unit",
        choices=LENGTH_UNITS,
        default=next(iter(LENGTH_UNITS)),
        help="unit of the table's distances and girths: cm (default) or mm",
    )
    _add_measure_options(report)
    for name, default, what in (
        ("difference-ml", limits.limb_difference_ml, "inter-limb volume difference in mL"),
        ("difference-percent", limits.limb_difference_percent, "inter-limb difference in %%"),
        ("circumference-mm", limits.circumference_mm, "circumference difference in mm"),
        ("change-percent", limits.change_percent, "change from baseline in %%"),
        ("rvc-percent", limits.rvc_percent, "relative volume change in %% (lymphoedema)"),
        ("subclinical-percent", limits.subclinical_percent, "relative volume change in %% "
         "(subclinical)"),
    ):  # fmt: skip
        report.add_argument(
            f"--flag-{name}",
            type=float,
            default=default,
            help=f"flag from this {what} (default {default:g})",
        )
    _add_library_option(report)


def _add_process_parser(sub: Any) -> None:
    """Add ``lamina process``: a stored scan processed again with this version's pipeline."""
    process = sub.add_parser(
        "process",
        help="process a stored scan again (acquired, or processed before) with this version "
        "of Lamina and the options given; the result replaces the stored one",
    )
    process.add_argument("scan", type=int, help="scan id (see lamina scans)")
    process.add_argument(
        "-o", "--out", type=Path, help="new folder for the outputs (default: the library only)"
    )
    process.add_argument(
        "--expect", help="known shape to measure accuracy against (default: the scan's own)"
    )
    process.add_argument(
        "--harmonics", type=int, help="fixed EFD harmonics (default: the scan's own, else by rule)"
    )
    process.add_argument(
        "--trim", type=float, help="fraction dropped from each segment end (default: the scan's)"
    )
    _add_method_options(process)
    _add_library_option(process)


def _add_processing_options(parser: argparse.ArgumentParser) -> None:
    """Add the rig choice and the method of each reconstruction stage."""
    parser.add_argument(
        "--rig", choices=RIG_PRESETS, help="simulated rig geometry (sim only, default thesis)"
    )
    _add_method_options(parser)


def _add_method_options(parser: argparse.ArgumentParser) -> None:
    """Add the method of each reconstruction stage (scan and process)."""
    parser.add_argument(
        "--pipeline",
        choices=("best", "thesis"),
        default="best",
        help="start from Lamina's best methods or the thesis' (the options below override)",
    )
    parser.add_argument(
        "--calibration", choices=OPTION_CHOICES["calibration"], help="homography estimator"
    )
    parser.add_argument(
        "--distortion",
        nargs="?",
        const="on",
        choices=OPTION_CHOICES["distortion"],
        help="radial lens distortion (ml only): auto estimates it from the board and keeps it "
        "where the board's rows show it (default), on always, off never; --distortion alone: on",
    )
    parser.add_argument("--axis", choices=OPTION_CHOICES["axis"], help="turntable axis method")
    parser.add_argument(
        "--angle-correction",
        action=argparse.BooleanOptionalAction,
        help="estimate the turntable's angle scale from the cylinder (default with --axis "
        f"{ANGLE_CORRECTION_AXIS})",
    )
    parser.add_argument(
        "--harmonic-rule", choices=OPTION_CHOICES["harmonic_rule"], help="EFD harmonic rule"
    )
    parser.add_argument("--mesh", choices=OPTION_CHOICES["mesh"], help="surface method")
    parser.add_argument(
        "--split-gap",
        type=float,
        help="fit outlines further apart than this many mm separately (0: never split)",
    )


OPTION_FLAGS = {
    "trim_fraction": "--trim",
    "harmonics": "--harmonics",
    "calibration": "--calibration",
    "distortion": "--distortion",
    "axis": "--axis",
    "angle_correction": "--angle-correction",
    "harmonic_rule": "--harmonic-rule",
    "mesh": "--mesh",
}
"""The flag naming each processing option in a refusal (the rules are ``ProcessOptions``')."""


def _process_options(args: argparse.Namespace) -> ProcessOptions:
    """Return the processing options the command line asks for."""
    base = ProcessOptions.thesis() if args.pipeline == "thesis" else ProcessOptions()
    changes: dict[str, Any] = {"trim_fraction": args.trim, "harmonics": args.harmonics}
    for name in ("calibration", "axis", "harmonic_rule", "mesh"):
        if getattr(args, name) is not None:
            changes[name] = getattr(args, name)
    if args.distortion is not None:
        changes["distortion"] = args.distortion
    if args.angle_correction is not None:
        changes["angle_correction"] = args.angle_correction
    elif changes.get("axis", ANGLE_CORRECTION_AXIS) != ANGLE_CORRECTION_AXIS:
        changes["angle_correction"] = False  # only that axis fit can estimate it
    if args.split_gap is not None:
        if not (math.isfinite(args.split_gap) and args.split_gap >= 0):
            raise UsageError("--split-gap must be 0 (never split) or a positive number of mm")
        changes["split_gap_mm"] = args.split_gap or None
    options = replace(base, **changes)
    if problem := options.problem(OPTION_FLAGS):
        raise UsageError(problem)
    if options.mesh != "contours":
        meshlab(options.mesh)  # refuse now, one line, rather than after the scan
    return options


def _add_library_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--library", type=Path, help="scan library file (default: in the user's data folder)"
    )


RESUMED_OPTIONS = (
    "object", "seed", "noise", "trim", "harmonics", "expect", "cylinder_mm", "rig", "colour",
    "sway",
)  # fmt: skip
"""What a resumed scan takes from its library record rather than the command line."""


def _scan_options(args: argparse.Namespace) -> dict[str, Any]:
    options = {name: getattr(args, name) for name in RESUMED_OPTIONS}
    return {**options, "device": args.device, "out": str(args.out.resolve())}


def _apply_resume(args: argparse.Namespace, record: ScanRecord) -> None:
    """Take a resumed scan's options (and output folder, unless given) from its record.

    An option given on the command line that differs from the record is refused, never
    silently replaced: the scan goes on exactly as it began.
    """
    recorded = dict(record.options)
    if not _finite_or_none(recorded.get("cylinder_mm")):
        recorded.pop("cylinder_mm")  # an older Lamina stored NaN: take what is given now
    for name in RESUMED_OPTIONS:
        if name not in recorded:
            continue  # recorded by an older Lamina or the terminal UI: keep what is given
        given, stored = getattr(args, name), recorded[name]
        if given is not None and given != stored:
            flag = "--" + name.replace("_", "-")
            raise UsageError(
                f"scan {record.id} was started with {flag} {stored}; resume it without {flag} "
                "or with the same value"
            )
        setattr(args, name, stored)
    if args.subject is not None and args.subject != record.subject:
        raise UsageError(
            f"scan {record.id} belongs to another subject code; resume it without --subject"
        )
    args.subject = record.subject
    if args.side is not None and args.side != record.side:
        raise UsageError(f"scan {record.id} records side {record.side}; resume it without --side")
    args.side = record.side
    if args.out is None:
        folder = record.options.get("out")
        if not isinstance(folder, str) or not folder:
            # Begun in the terminal UI or the browser, which keep no output folder.
            raise UsageError(
                f"scan {record.id} has no output folder of its own (begun in the terminal UI "
                f"or a browser): resume it with -o NEW_FOLDER, or finish it in the UI"
            )
        args.out = Path(folder)


def _finite_or_none(value: object) -> bool:
    return value is None or (isinstance(value, int | float) and math.isfinite(value))


def _apply_defaults(args: argparse.Namespace) -> None:
    """Fill the options left unset (after a resume took its record's)."""
    for name, default in SCAN_DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, default)
    if args.trim is None:
        args.trim = _pipeline_trim(args)


def _pipeline_trim(args: argparse.Namespace) -> float:
    """Return the trim fraction of the pipeline asked for (the thesis' or Lamina's)."""
    return THESIS_TRIM_FRACTION if args.pipeline == "thesis" else DEFAULT_TRIM_FRACTION


def _plan(args: argparse.Namespace) -> ScanPlan | None:
    """Return the plan the numbers given ask for, or None for the device's default plan."""
    if args.sections is None and args.pitch is None and args.views is None:
        return None
    return check_plan(args.sections, args.pitch, args.views)


def _check_numbers(args: argparse.Namespace) -> None:
    """Refuse any numeric option that is zero where it cannot be, negative or not finite."""
    if args.cylinder_mm is not None:
        check_positive_mm("--cylinder-mm", args.cylinder_mm, 1000.0)
    check_count("--seed", args.seed, 0, 2**32 - 1)


def _check_args(
    args: argparse.Namespace, record: ScanRecord | None = None
) -> tuple[ScanPlan | None, Expectation | None]:
    """Check every option before anything is created; return the plan and expectation."""
    if args.out is None:
        raise UsageError("name an output folder with -o OUT")
    check_subject(args.subject)
    check_device_name(args.device)
    _check_numbers(args)
    if spawns_device(args.device) and find_spec("lamina_device") is None:
        raise UsageError(
            f"--device {args.device} runs the device program here, but "
            "lamina-device is not installed: pip install -e device"
        )
    if (folder := replay_folder(args.device)) is not None:
        capture = Path(folder)
        if not (capture / "capture.json").is_file():
            raise UsageError(f"{capture} holds no capture.json: name a capture folder")
    if args.object and args.device != SIM:
        raise UsageError("--object only applies to --device sim")
    if args.rig != "thesis" and args.device != SIM:
        raise UsageError("--rig only applies to --device sim")
    if args.sway != "none" and args.device != SIM:
        raise UsageError(
            "--sway only applies to --device sim: a real subject's sway is the subject's own"
        )
    _process_options(args)  # refuse bad method combinations before scanning
    try:
        expect = parse_expectation(args.expect) if args.expect else None
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    plan = _plan(args)
    stored = record.plans.get("object") if record is not None else None
    if stored is not None and plan is not None and stored.views != plan.views:
        raise UsageError(
            f"scan {record.id if record else '?'} was planned differently; resume it without "
            "--sections, --pitch and --views"
        )
    if stored is not None and args.mode is not None and stored.mode != args.mode:
        raise UsageError(
            f"scan {record.id if record else '?'} is a {stored.mode} scan; resume it without "
            "--mode or with the same mode"
        )
    return plan, expect


def _progress(p: Progress) -> None:
    """Show a scan's progress on stderr: a running count on a terminal, else one line."""
    if p.starting:
        print(
            f"  {p.target}: {p.done} of {p.total} views already held, fetching {p.total - p.done}",
            file=sys.stderr,
        )
        return
    if sys.stderr.isatty():
        print(f"\r  {p.target}: view {p.done}/{p.total}", end="", file=sys.stderr, flush=True)
        if p.done == p.total:
            print(file=sys.stderr)
    elif p.done == p.total:
        print(f"  {p.target}: {p.total} views", file=sys.stderr)


def print_summary(report: ScanReport, paths: Mapping[str, Path]) -> None:
    """Print the short human summary of a scan."""
    cal, axis = report.calibration, report.axis
    print(
        f"calibration: {cal.n_corners} corners, residual RMS {cal.rms_mm:.4f} mm "
        f"(max {cal.max_mm:.4f} mm)"
    )
    if line := distortion_summary(cal.distortion):
        print(f"lens: {line}")
    print(
        f"axis: ({axis.axis_xy_mm[0]:.3f}, {axis.axis_xy_mm[1]:.3f}) mm, correction "
        f"factor {report.correction_factor:.5f}"
    )
    if advice := gear_advice(axis):
        print(f"turntable: {advice}")
    print(f"lift: {lift_summary(report.lift)}")
    table = report.accuracy.table if report.accuracy is not None else None
    accuracy = {r.section: r for r in table.rows} if table is not None else {}
    header = "section  z_mm  points  harmonics  cover%  status      "
    print(header + ("  rms_own_mm  rms_mean_mm" if accuracy else ""))
    for s in report.sections:
        line = f"{s.section:>7}  {s.z_mm:4.1f}  {s.raw_points:>6}"
        if isinstance(s, FailedEntry):
            print(f"{line}  {'-':>9}  {'-':>6}  {OutlineStatus.FAILED:<12}  {s.reason}")
            continue
        line += f"  {s.harmonics:>9}"
        cover = s.coverage.fraction if s.coverage is not None else float("nan")
        line += f"  {100 * cover:6.1f}  {s.status:<12}"
        if s.section in accuracy:
            row = accuracy[s.section]
            line += f"  {row.rms_own_mm:10.4f}  {row.rms_mean_mm:11.4f}"
        print(line)
    if table is not None and accuracy:
        print(
            f"   mean RMS radial error: {table.mean_own_mm:.4f} mm (own centroid), "
            f"{table.mean_mean_mm:.4f} mm (mean centroid) from the shape given by --expect"
        )
    print(f"mesh: {mesh_summary(report.mesh)}")
    for warning in report.warnings:
        print(f"warning: {warning}")
    for path in paths.values():
        print(f"wrote {path}")


def _open_library(path: Path | None, create: bool = False) -> Library:
    """Open the scan library, saying once on stderr what it had to put right.

    Only ``lamina scan`` (``create``) makes a library where there is none. The commands
    that read one refuse a file that is not there rather than make an empty one: a
    mistyped ``--library`` would otherwise list "no scans", as if the scans were lost,
    and leave an empty library (and its folders) behind.

    Raises:
        InputError: ``create`` is False and there is no library file at the path.
    """
    where = path if path is not None else default_library_path()
    if not create and not os.path.lexists(where):
        if path is None:
            raise InputError(
                f"there is no scan library at {where} yet: nothing has been scanned here "
                "(lamina scan makes it; --library names a library elsewhere)"
            )
        raise InputError(
            f"there is no scan library at {where}: check the --library path "
            "(lamina scan makes the library the first time it records into it)"
        )
    library = Library(path)
    for notice in library.notices:
        print(f"note: {notice}", file=sys.stderr)
    return library


def _extract_option(text: str) -> ExtractChanges:
    """Return ``--extract``'s changes; argparse reports a bad one in one line."""
    try:
        return parse_extract_text(text)
    except ArgsError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _notice(text: str) -> None:
    """Say on stderr what the device is doing (not an error: no ``lamina:`` prefix)."""
    print(f"  {text}", file=sys.stderr)


def _request(args: argparse.Namespace, plan: ScanPlan | None) -> ScanRequest:
    """Return the typed scan request the checked arguments ask for."""
    return ScanRequest(
        args.subject,
        plan,
        None if args.cylinder_mm is None else float(args.cylinder_mm),
        _scan_options(args),
        getattr(args, "extract", None),
        bool(getattr(args, "colour", False)),
        args.side or SIDES[0],
        getattr(args, "mode", None),
    )


def scan(args: argparse.Namespace) -> int:
    """Run ``lamina scan``: store into the library, resume what it holds, reconstruct."""
    with _stop_signals_interrupt():
        return _scan(args)


def _scan(args: argparse.Namespace) -> int:
    with _open_library(args.library, create=True) as library:
        record = library.scan(args.resume) if args.resume is not None else None
        if args.reprocess and record is None:
            raise UsageError("--reprocess applies to a scan resumed with --resume SCAN")
        if record is not None and record.status == "processed" and not args.reprocess:
            print(
                f"scan {record.id} is complete (every view held, processed); nothing was "
                f"written: see it with lamina report {record.id} -o FILE.pdf, or process it "
                f"again with --reprocess"
            )
            return 0
        if record is not None:
            _apply_resume(args, record)
        _apply_defaults(args)
        plan, expect = _check_args(args, record)
        request = _request(args, plan)
        own_out = record is not None and str(args.out.resolve()) == record.options.get("out")
        created = not args.out.exists()
        prepare_output_folder(args.out, allow_files=own_out)
        target = DeviceTarget(args.device, args.object, args.seed, args.noise, args.rig, args.sway)
        job = ScanJob(target, library=library)  # one connection for the whole scan
        try:
            acquired = _acquire_scan(job, args, request)
        except BaseException:
            if created:
                with suppress(OSError):
                    args.out.rmdir()  # only while empty: nothing was received into it
            raise
        finally:
            job.close()
        try:
            results = job.processing.process_scan(
                _process_options(args), expect, acquired.timings_s, args.out
            )
        except (sqlite3.Error, OutputError) as exc:
            if not disk_full(exc):
                raise
            raise DiskFull(
                f"{_filled(exc, job)}: the disk is full; the scan is acquired and kept: free space "
                f"on it, then process it with lamina scan --resume {acquired.scan_id} "
                f"--device {args.device}"
            ) from None
    print_summary(results.report, results.paths)
    return 0


def _acquire_scan(job: ScanJob, args: argparse.Namespace, request: ScanRequest) -> Acquired:
    """Connect and acquire; a stop after the scan exists says how to finish it."""
    job.connect(on_notice=_notice)
    # Before calibrating: the extraction settings are part of what the scan records.
    job.device.set_extract(request.extract)
    job.device.set_colour(request.colour)

    def opened(scan_id: int) -> None:
        # The scan exists: its plan passed every check, so the estimate is of what will run.
        print(f"scan {scan_id} in library {job.library_path}", file=sys.stderr)
        _say_estimate(job)

    try:
        return acquire(job, request, args.resume, args.out, _progress, on_opened=opened)
    except KeyboardInterrupt:
        if job.scan_id is None:
            raise
        raise Interrupted(
            f"finish with lamina scan --resume {job.scan_id} --device {args.device}"
        ) from None
    except (sqlite3.Error, OutputError) as exc:
        if job.scan_id is None or not disk_full(exc):
            raise
        raise DiskFull(
            f"{_filled(exc, job)}: the disk is full; what was stored is kept: free space on "
            f"it, then finish with lamina scan --resume {job.scan_id} --device {args.device}"
        ) from None
    except (DeviceError, LinkClosed, ProtocolError) as exc:
        if job.scan_id is None:
            raise
        if isinstance(exc, RequestRefused) and exc.code in PLAN_REFUSALS:
            # The device refuses the scan's plan itself: a resume would meet the same refusal.
            raise DeviceError(
                f"{exc}; what arrived is kept in scan {job.scan_id}, but this device cannot "
                "finish its plan: scan again with a plan within the device's limits"
            ) from None
        raise DeviceError(
            f"{exc}; what arrived is kept: finish with lamina scan --resume {job.scan_id} "
            f"--device {args.device}"
        ) from None


def _say_estimate(job: ScanJob) -> None:
    """Say, before the object scan, how long the subject must hold still for it.

    The views still to take (a resumed scan has some already). Only a word of advice: a
    device that cannot say, or a refusal (the scan then meets it and says so), leaves it out.
    """
    plan, held = job.acquisition.plan, job.acquisition.held
    if plan is None:
        return
    left = plan.with_views(tuple(v for k, v in enumerate(plan.views) if k not in held))
    if not left.views:
        return
    try:
        estimate = job.device.estimate("object", left)
    except (DeviceError, LinkClosed, ProtocolError):
        return
    if estimate is not None and estimate.views:
        print(
            f"the object scan takes about {duration_text(estimate.modelled_s)} "
            f"({estimate.views} views): ask the subject to hold still for that long",
            file=sys.stderr,
        )


class DiskFull(LaminaError):
    """A disk filled during a scan; the text names the file and how to finish the scan."""


def _filled(exc: sqlite3.Error | OutputError, job: ScanJob) -> str:
    """Return what could not be written: the output file the error names, or the library."""
    if isinstance(exc, OutputError):
        return str(exc)
    return f"the scan library {job.library_path or default_library_path()} cannot grow ({exc})"


def process(args: argparse.Namespace) -> int:
    """Run ``lamina process SCAN``: reconstruct a stored scan again and store the result.

    Trim, harmonics and the expected shape default to what the scan was started with;
    the methods to the command line's (Lamina's best unless given).
    """
    with _open_library(args.library) as library:
        record = library.scan(args.scan)
        path = library.path
    for name in ("trim", "harmonics", "expect"):
        if getattr(args, name) is None:
            setattr(args, name, record.options.get(name))
    if args.trim is None:
        args.trim = _pipeline_trim(args)
    options = _process_options(args)  # the trim and harmonics recorded are checked too
    try:
        expect = parse_expectation(args.expect) if args.expect else None
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    if args.out is not None:
        prepare_output_folder(args.out)
    job = ScanJob(DeviceTarget(), path)
    results = job.processing.process_stored(args.scan, options, expect, args.out)
    print_summary(results.report, results.paths)
    print(f"scan {args.scan} processed; the result is stored in library {path}")
    return 0


def list_scans(args: argparse.Namespace) -> int:
    """Run ``lamina scans``: one line per scan in the library."""
    if args.set_test is not None and args.set_test == args.unset_test:
        raise UsageError("give a scan to --set-test or to --unset-test, not to both")
    asked = (args.set_side, args.set_test, args.unset_test) != (None, None, None)
    default = default_library_path()
    if args.library is None and not os.path.lexists(default) and not asked:
        # A new box, where nothing has been scanned yet: no mistake to refuse.
        print(f"no scans yet: the scan library {default} is made by lamina scan")
        return 0
    with _open_library(args.library) as library:
        if args.set_side:
            scan_id, side = args.set_side
            if not scan_id.isdigit():
                raise UsageError(f"--set-side {scan_id[:20]!r}: give a scan id, e.g. 3 left")
            library.set_side(int(scan_id), side)
        for scan_id, test in ((args.set_test, True), (args.unset_test, False)):
            if scan_id is not None:
                library.set_test(scan_id, test)
        summaries = library.scans(subject=args.subject)
        if not summaries:
            whose = f" of subject {printable(args.subject)}" if args.subject else ""
            print(f"no scans{whose} in {library.path}")
            return 0
        print(
            f"{'scan':>5}  {'subject':<12} {'side':<5}  {'created':<25} {'status':<10} "
            "sections  views  result  test"
        )
        for s in summaries:
            views = f"{s.received}/{s.views}"
            # Codes stored by an older Lamina may hold anything: never print it raw.
            subject, created, status = (printable(t) for t in (s.subject, s.created, s.status))
            print(
                f"{s.id:>5}  {subject:<12} {s.side:<5}  {created:<25} {status:<10} "
                f"{s.sections:>8}  {views:>5}  {'yes' if s.has_result else 'no':<6}  "
                f"{'test' if s.test else ''}".rstrip()
            )
    return 0


def export(args: argparse.Namespace) -> int:
    """Run ``lamina export SCAN -o FILE``: the format follows the file's extension."""
    institution = check_institution(args.institution)
    with _open_library(args.library) as library:
        path = export_scan(library, args.scan, args.out, institution, args.dicom_sop)
    print(f"wrote {path}")
    return 0


def batch(args: argparse.Namespace) -> int:
    """Run ``lamina batch``: reprocess matching scans in parallel, write the table as CSV.

    Returns 1 (after writing the table of the others) when some scans could not be measured.
    """
    if not args.measure:
        raise UsageError("lamina batch needs --measure (the only batch job so far)")
    if args.workers is not None:
        check_count("--workers", args.workers, 1, 256)
    check_pattern(args.subjects)
    check_output(args.out)
    measure = ClinicalMeasure(
        _check_spacing(args.spacing_mm), parse_landmark(args.landmark), args.limb_axis
    )
    with _open_library(args.library) as library:
        scan_ids = select_scans(library, args.subjects)
        outcomes = run_batch(
            library, scan_ids, measure, workers=args.workers, address=args.scheduler
        )
    failed = [o for o in outcomes if o.error is not None]
    for outcome in failed:
        print(f"lamina: scan {outcome.scan_id} not measured: {printable(outcome.error or '')}",
              file=sys.stderr)  # fmt: skip
    write_table(args.out, outcomes)
    print(f"wrote {args.out} ({len(outcomes) - len(failed)} of {len(outcomes)} scans)")
    return 1 if failed else 0


def tui(args: argparse.Namespace) -> int:
    """Run ``lamina tui``: the Textual app on this terminal."""
    _check_ui_options(args)
    from lamina_host.ui.tui.app import LaminaApp  # deferred: Textual is only needed here

    noise, rig = args.noise or "thesis", args.rig or "thesis"
    LaminaApp(args.device, args.library, args.object, noise=noise, rig=rig).run()
    return 0


def serve_ui(args: argparse.Namespace) -> int:
    """Run ``lamina serve-ui``: the terminal UI in a browser, until interrupted."""
    tui_options = _check_ui_options(args)
    if not 0 < args.port < 65536:
        raise UsageError(f"--port {args.port} must be from 1 to 65535")
    from lamina_host.ui.browser import serve_ui as run_server  # deferred: aiohttp is heavy

    try:
        run_server(args.host, args.port, tui_options, args.allow_remote)
    except OSError as exc:
        raise UsageError(
            f"cannot serve the UI on {args.host}:{args.port} ({exc.strerror or exc}): "
            "choose another --port, or stop what uses it"
        ) from None
    return 0


def clinical_report(args: argparse.Namespace) -> int:
    """Run ``lamina report SCAN -o FILE``: measure a processed scan and write its report."""
    limits: tuple[float, ...] = (args.flag_difference_ml, args.flag_difference_percent)
    limits += (args.flag_circumference_mm, args.flag_change_percent)
    limits += (args.flag_rvc_percent, args.flag_subclinical_percent)
    if not all(math.isfinite(v) and v >= 0 for v in limits):
        raise UsageError("the --flag-... thresholds must be numbers of at least 0")
    _check_spacing(args.spacing_mm)
    outputs = [args.out] + ([args.csv] if args.csv else [])
    for path in outputs:
        if path.suffix.lower() not in (".pdf", ".png", ".csv"):
            raise UsageError(f"cannot write {path.name}: name the file .pdf, .png or .csv")
        if problem := new_file_problem(path):
            raise UsageError(problem)  # before the measuring, not after it
    request = MeasureRequest(
        args.spacing_mm,
        parse_landmark(args.landmark),
        args.limb_axis,
        Thresholds(*limits),
        args.length_unit,
    )
    with _open_library(args.library) as library:
        data = build_report_data(
            library, args.scan, request, args.compare, args.compare_as, args.compare_other_subject
        )
    for path in outputs:
        print(f"wrote {write_report(path, data)}")
    for flag in headline_flags(data):
        print(f"flag: {flag}")
    return 0


# ``lamina send``: the scan's DICOM object to a PACS (C-STORE). Self-contained block.
def _add_send_parser(sub: Any) -> None:
    """Add ``lamina send SCAN --to AE_TITLE@HOST:PORT``."""
    send = sub.add_parser(
        "send",
        help="store a scan's DICOM object (as lamina export writes it) in a PACS (C-STORE)",
    )
    send.add_argument("scan", type=int, help="scan id (see lamina scans)")
    send.add_argument(
        "--to",
        required=True,
        metavar="AE_TITLE@HOST:PORT",
        help="the PACS: its AE title, host and DICOM port, e.g. ORTHANC@pacs.local:4242",
    )
    send.add_argument(
        "--calling-ae",
        default=DEFAULT_CALLING_AE,
        help=f"the AE title Lamina calls from (default: {DEFAULT_CALLING_AE})",
    )
    send.add_argument(
        "--timeout-s",
        type=float,
        default=DEFAULT_TIMEOUT_S,
        help=f"longest wait for the connection and each answer (default: {DEFAULT_TIMEOUT_S:g})",
    )
    send.add_argument("--institution", default="", help="Institution Name written into the object")
    send.add_argument(
        "--dicom-sop",
        choices=DICOM_SOPS,
        default=next(iter(DICOM_SOPS)),
        help="the DICOM object: encapsulated-stl (default) or surface-scan (experimental)",
    )
    _add_library_option(send)


def send_scan(args: argparse.Namespace) -> int:
    """Run ``lamina send SCAN --to ...``: C-STORE the scan's DICOM object; the library unchanged."""
    target = parse_target(args.to)
    calling_ae = check_ae_title(args.calling_ae, "--calling-ae")
    timeout_s = check_timeout(args.timeout_s)
    institution = check_institution(args.institution)
    with _open_library(args.library) as library:
        data = dicom_export(library, args.scan, institution, args.dicom_sop)
    receipt = send_dicom(data, target, calling_ae, timeout_s)
    warning = f" (warning 0x{receipt.status:04X}: {receipt.meaning})" if receipt.status else ""
    print(f"stored scan {args.scan} in {target.describe()}: instance {receipt.sop_instance_uid}"
          f"{warning}")  # fmt: skip
    return 0


COMMANDS = {
    "scan": scan,
    "process": process,
    "scans": list_scans,
    "export": export,
    "report": clinical_report,
    "batch": batch,
    "tui": tui,
    "serve-ui": serve_ui,
    "send": send_scan,
}


PATH_OPTIONS = {"out": "-o", "csv": "--csv", "library": "--library"}
"""Options naming a file or folder, by their argparse name."""


def _check_path_names(args: argparse.Namespace) -> None:
    """Refuse a path whose name is not UTF-8 text (bytes the shell passed through).

    Such a name can be neither shown nor recorded faithfully (and OpenCV crashed on
    one): it is refused before anything is created.
    """
    for name, flag in PATH_OPTIONS.items():
        path = getattr(args, name, None)
        if path is None:
            continue
        try:
            str(path).encode("utf-8")
        except UnicodeEncodeError:
            shown = str(path).encode("utf-8", "backslashreplace").decode("ascii", "replace")
            raise UsageError(
                f"{flag} {printable(shown)} is not UTF-8 text: name it in UTF-8 (letters, "
                "digits, '-' and '_' are safe)"
            ) from None


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit status."""
    parser = build_parser()
    check_option_names(parser, list(sys.argv[1:] if argv is None else argv))
    args = parser.parse_args(argv)
    try:
        _check_path_names(args)
        return COMMANDS[args.command](args)
    except LinkClosed as exc:
        print(
            f"lamina: the link to the device broke ({exc}); check the cable and try again",
            file=sys.stderr,
        )
    except LaminaError as exc:
        print(f"lamina: {printable(str(exc))}", file=sys.stderr)
    except sqlite3.Error as exc:
        library = getattr(args, "library", None) or default_library_path()
        if disk_full(exc):
            print(
                f"lamina: the disk holding the scan library {library} is full ({exc}): "
                "free space on it, then run the command again",
                file=sys.stderr,
            )
            return EXIT_USAGE
        print(
            f"lamina: the scan library {library} cannot be used ({exc}): if it is damaged, "
            "restore it from a backup",
            file=sys.stderr,
        )
    except OSError as exc:
        print(f"lamina: {exc.strerror or exc} ({exc.filename or 'no file'})", file=sys.stderr)
    except KeyboardInterrupt as exc:
        hint = exc.hint if isinstance(exc, Interrupted) else ""
        with suppress(OSError):  # a closed terminal (SIGHUP) may take stderr with it
            print(
                "lamina: interrupted; data received so far is in the output folder"
                + (f" and the library: {hint}" if hint else ""),
                file=sys.stderr,
            )
        return 130
    return EXIT_USAGE
