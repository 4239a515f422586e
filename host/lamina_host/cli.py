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
import math
import sqlite3
import sys
import time
from collections.abc import Sequence
from contextlib import suppress
from dataclasses import replace
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import cv2

from lamina_host import __version__
from lamina_host.axis import AXIS_METHODS
from lamina_host.calibration import CALIBRATION_METHODS, CalibrationError
from lamina_host.efd import HARMONIC_RULES
from lamina_host.expect import Expectation, parse_expectation
from lamina_host.files import OutputError, prepare_output_folder, replace_file
from lamina_host.link import DeviceClient, DeviceError, open_device
from lamina_host.mesh import MESH_METHODS
from lamina_host.pipeline import ProcessOptions, Reconstruction, reconstruct
from lamina_host.report import build_report, save_segments, write_outputs
from lamina_host.store import Library, ScanRecord, StoreError, default_library_path
from lamina_host.workflow import (
    SUBJECT_RULE,
    InputError,
    check_count,
    check_plan,
    check_plan_limits,
    check_positive_mm,
    check_subject,
    printable,
)
from lamina_shared.link import LinkClosed
from lamina_shared.presets import NOISE_PRESETS
from lamina_shared.protocol import ProtocolError
from lamina_shared.types import ScanPlan

EXIT_USAGE = 2
RIG_PRESETS = ("thesis", "limb")
"""The simulated rig geometries (lamina_device.sim.RIG_PRESETS; not imported, since the
host must run without the device package)."""


class UsageError(InputError):
    """A mistake in how the command was called."""


SCAN_DEFAULTS: dict[str, Any] = {
    "subject": "anonymous",
    "trim": 0.10,
    "seed": 0,
    "noise": "thesis",
    "rig": "thesis",
}
"""Defaults of scan options a resume must be able to tell from values given (so None)."""


def build_parser() -> argparse.ArgumentParser:
    """Return the command-line parser."""
    parser = argparse.ArgumentParser(prog="lamina", description=__doc__)
    parser.add_argument("--version", action="version", version=f"lamina {__version__}")
    sub = parser.add_subparsers(dest="command", required=True)
    scan = sub.add_parser("scan", help="calibrate, scan and reconstruct one object")
    scan.add_argument(
        "--device", required=True, help="serial port path, 'sim', or 'replay:CAPTURE_DIR'"
    )
    scan.add_argument(
        "-o", "--out", type=Path, help="new output folder (when resuming: the scan's own)"
    )
    scan.add_argument(
        "--subject",
        help=f"pseudonymous subject code (default anonymous): {SUBJECT_RULE}".replace("%", "%%"),
    )
    scan.add_argument("--resume", type=int, metavar="SCAN", help="finish scan SCAN of the library")
    _add_library_option(scan)
    scan.add_argument("--object", help="simulated object (sim only), e.g. cylinder:d=19.05")
    scan.add_argument("--sections", type=int, help="number of sections (default: device's)")
    scan.add_argument("--pitch", type=float, help="section pitch in mm (default 2)")
    scan.add_argument("--views", type=int, help="views per section (default 8)")
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
        help="fraction dropped from each segment end (default 0.10)",
    )
    scan.add_argument("--seed", type=int, help="simulation seed (sim only, default 0)")
    scan.add_argument(
        "--noise",
        choices=NOISE_PRESETS,
        help="simulated noise level: thesis, harsh or none (sim only, default thesis)",
    )
    _add_processing_options(scan)
    scans = sub.add_parser("scans", help="list the scans in the library")
    _add_library_option(scans)
    export = sub.add_parser(
        "export", help="export a scan's mesh (.ply/.obj/.stl) or report (.json)"
    )
    export.add_argument("scan", type=int, help="scan id (see lamina scans)")
    export.add_argument("-o", "--out", required=True, type=Path, help="new file to write")
    _add_library_option(export)
    _add_report_parser(sub)
    tui = sub.add_parser("tui", help="the terminal UI for the whole workflow (works over SSH)")
    tui.add_argument(
        "--device", default="sim", help="serial port path, 'sim' (default) or 'replay:DIR'"
    )
    tui.add_argument("--object", help="simulated object (sim only), e.g. cylinder:d=19.05")
    _add_library_option(tui)
    return parser


def _add_report_parser(sub: Any) -> None:
    """Add ``lamina report``: a processed scan's clinical measurements on one page."""
    from lamina_host.clinical import AXES, COMPARISONS, Thresholds

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
        "--spacing-mm", type=float, default=40.0, help="distance between levels (default 40)"
    )
    report.add_argument(
        "--landmark",
        default="distal",
        help="level 0: distal (default, the narrower end), bottom, top or a height in mm",
    )
    report.add_argument(
        "--limb-axis", choices=AXES, default=AXES[0], help="what distances are measured along"
    )
    for name, default, what in (
        ("difference-ml", limits.limb_difference_ml, "inter-limb volume difference in mL"),
        ("difference-percent", limits.limb_difference_percent, "inter-limb difference in %%"),
        ("circumference-mm", limits.circumference_mm, "circumference difference in mm"),
        ("change-percent", limits.change_percent, "change from baseline in %%"),
    ):
        report.add_argument(
            f"--flag-{name}",
            type=float,
            default=default,
            help=f"flag from this {what} (default {default:g})",
        )
    _add_library_option(report)


def _add_processing_options(parser: argparse.ArgumentParser) -> None:
    """Add the rig choice and the method of each reconstruction stage."""
    parser.add_argument(
        "--rig", choices=RIG_PRESETS, help="simulated rig geometry (sim only, default thesis)"
    )
    parser.add_argument(
        "--pipeline",
        choices=("best", "thesis"),
        default="best",
        help="start from Lamina's best methods or the thesis' (the options below override)",
    )
    parser.add_argument("--calibration", choices=CALIBRATION_METHODS, help="homography estimator")
    parser.add_argument(
        "--distortion", action="store_true", help="estimate radial lens distortion (ml only)"
    )
    parser.add_argument("--axis", choices=AXIS_METHODS, help="turntable axis method")
    parser.add_argument(
        "--angle-correction",
        action=argparse.BooleanOptionalAction,
        help="estimate the turntable's angle scale from the cylinder (default with --axis joint)",
    )
    parser.add_argument("--harmonic-rule", choices=HARMONIC_RULES, help="EFD harmonic rule")
    parser.add_argument("--mesh", choices=MESH_METHODS, help="surface method")
    parser.add_argument(
        "--split-gap",
        type=float,
        help="fit outlines further apart than this many mm separately (0: never split)",
    )


def _process_options(args: argparse.Namespace) -> ProcessOptions:
    """Return the processing options the command line asks for."""
    base = ProcessOptions.thesis() if args.pipeline == "thesis" else ProcessOptions()
    changes: dict[str, Any] = {"trim_fraction": args.trim, "harmonics": args.harmonics}
    for name in ("calibration", "axis", "harmonic_rule", "mesh"):
        if getattr(args, name) is not None:
            changes[name] = getattr(args, name)
    if args.distortion:
        changes["distortion"] = True
    if args.angle_correction is not None:
        changes["angle_correction"] = args.angle_correction
    elif changes.get("axis") == "centroid":
        changes["angle_correction"] = False  # only the joint fit can estimate it
    if args.split_gap is not None:
        if not (math.isfinite(args.split_gap) and args.split_gap >= 0):
            raise UsageError("--split-gap must be 0 (never split) or a positive number of mm")
        changes["split_gap_mm"] = args.split_gap or None
    options = replace(base, **changes)
    if options.distortion and options.calibration != "ml":
        raise UsageError("--distortion needs --calibration ml")
    if options.angle_correction and options.axis != "joint":
        raise UsageError("--angle-correction needs --axis joint")
    return options


def _add_library_option(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--library", type=Path, help="scan library file (default: in the user's data folder)"
    )


RESUMED_OPTIONS = (
    "object", "seed", "noise", "trim", "harmonics", "expect", "cylinder_mm", "rig",
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
    if args.out is None:
        args.out = Path(record.options["out"])


def _finite_or_none(value: object) -> bool:
    return value is None or (isinstance(value, int | float) and math.isfinite(value))


def _apply_defaults(args: argparse.Namespace) -> None:
    """Fill the options left unset (after a resume took its record's)."""
    for name, default in SCAN_DEFAULTS.items():
        if getattr(args, name) is None:
            setattr(args, name, default)


def _plan(args: argparse.Namespace) -> ScanPlan | None:
    """Return the plan the numbers given ask for, or None for the device's default plan."""
    if args.sections is None and args.pitch is None and args.views is None:
        return None
    return check_plan(args.sections, args.pitch, args.views)


def _check_numbers(args: argparse.Namespace) -> None:
    """Refuse any numeric option that is zero where it cannot be, negative or not finite."""
    if not (math.isfinite(args.trim) and 0.0 <= args.trim < 0.5):
        raise UsageError(f"--trim {args.trim} must be at least 0 and below 0.5")
    if args.harmonics is not None:
        check_count("--harmonics", args.harmonics, 1, 100)
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
    _check_numbers(args)
    spawns_device = args.device == "sim" or args.device.startswith("replay:")
    if spawns_device and find_spec("lamina_device") is None:
        raise UsageError(
            f"--device {args.device} runs the device program here, but "
            "lamina-device is not installed: pip install -e device"
        )
    if args.device.startswith("replay:"):
        capture = Path(args.device.removeprefix("replay:"))
        if not (capture / "capture.json").is_file():
            raise UsageError(f"{capture} holds no capture.json: name a capture folder")
    if args.object and args.device != "sim":
        raise UsageError("--object only applies to --device sim")
    if args.rig != "thesis" and args.device != "sim":
        raise UsageError("--rig only applies to --device sim")
    _process_options(args)  # refuse bad method combinations before scanning
    try:
        expect = parse_expectation(args.expect) if args.expect else None
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    plan = _plan(args)
    if record is not None and plan is not None and record.plans.get("object") != plan:
        raise UsageError(
            f"scan {record.id} was planned differently; resume it without "
            "--sections, --pitch and --views"
        )
    return plan, expect


def _progress(event: dict[str, Any]) -> None:
    if event.get("event") != "progress":
        return
    done, total = event.get("done"), event.get("total")
    if sys.stderr.isatty():
        print(
            f"\r  {event.get('target')}: view {done}/{total}", end="", file=sys.stderr, flush=True
        )
    elif done == total:
        print(f"  {event.get('target')}: {total} views", file=sys.stderr)


def _fetch_views(
    client: DeviceClient,
    library: Library,
    scan_id: int,
    target: str,
    identity: dict[str, Any] | None = None,
) -> None:
    """Fetch the views of ``target`` the library lacks; each is committed before its ack."""
    plan = library.scan(scan_id).plans[target]
    held = library.held(scan_id, target)
    if len(held) == len(plan.views):
        return
    if held:
        print(
            f"  {target}: {len(held)} of {len(plan.views)} views already held, "
            f"fetching {len(plan.views) - len(held)}",
            file=sys.stderr,
        )
    client.scan(
        target,
        plan,
        _progress,
        have=held,
        on_segment=lambda seq, segment: library.add_segment(scan_id, seq, segment, identity),
    )


def acquire(
    client: DeviceClient, args: argparse.Namespace, library: Library, scan_id: int, out: Path
) -> tuple[dict[str, Any], dict[str, float]]:
    """Fetch what the library lacks of the scan, then write the received data to ``out``.

    The segments held are written to ``out`` also when acquisition stops early.
    """
    identity = client.identity()
    timings: dict[str, float] = {}
    start = time.perf_counter()
    if library.calibration(scan_id) is None:
        grid, board = client.grab_grid()
        library.save_calibration(scan_id, grid, board, _cylinder_mm(args, client), identity)
    calibration = library.calibration(scan_id)
    assert calibration is not None
    grid_image, board = calibration.grid_image, calibration.board
    diameter = calibration.cylinder_mm
    if diameter is None:
        diameter = _cylinder_mm(args, client)
    if diameter is None:
        raise UsageError("the device does not know its calibration cylinder: pass --cylinder-mm")
    replace_file(out / "calibration-grid.png", lambda path: _write_image(path, grid_image))
    try:
        _fetch_views(client, library, scan_id, "cylinder", identity)
        timings["acquire_calibration"] = time.perf_counter() - start
        start = time.perf_counter()
        _fetch_views(client, library, scan_id, "object", identity)
        timings["acquire_object"] = time.perf_counter() - start
    finally:
        # What arrived is kept in the output folder too, also when the scan stops here.
        cylinder = library.segments(scan_id, "cylinder")
        segments = library.segments(scan_id, "object")
        save_segments(out / "cylinder-segments.npz", cylinder)
        save_segments(out / "segments.npz", segments)
    library.set_status(scan_id, "acquired")
    if sys.stderr.isatty():
        print(file=sys.stderr)
    data = {
        "grid_image": grid_image,
        "board": board,
        "cylinder": cylinder,
        "cylinder_mm": diameter,
        "segments": segments,
    }
    return data, timings


def _cylinder_mm(args: argparse.Namespace, client: DeviceClient) -> float | None:
    """Return the calibration cylinder's diameter: the one given, else the device's."""
    if args.cylinder_mm is not None:
        return float(args.cylinder_mm)
    return client.info.cylinder_diameter_mm if client.info else None


def _write_image(path: Path, image: Any) -> None:
    if not cv2.imwrite(str(path), image):
        raise OutputError(f"the calibration image could not be written to {path}")


def print_summary(report: dict[str, Any], paths: dict[str, Path]) -> None:
    """Print the short human summary of a scan."""
    cal, axis = report["calibration"], report["axis"]
    print(
        f"calibration: {cal['n_corners']} corners, residual RMS {cal['rms_mm']:.4f} mm "
        f"(max {cal['max_mm']:.4f} mm)"
    )
    print(
        f"axis: ({axis['axis_xy_mm'][0]:.3f}, {axis['axis_xy_mm'][1]:.3f}) mm, correction "
        f"factor {report['correction_factor']:.5f}"
    )
    accuracy = {r["section"]: r for r in report.get("accuracy", {}).get("rows", [])}
    header = "section  z_mm  points  harmonics  cover%  status      "
    print(header + ("  rms_own_mm  rms_mean_mm" if accuracy else ""))
    for s in report["sections"]:
        line = f"{s['section']:>7}  {s['z_mm']:4.1f}  {s['raw_points']:>6}  {s['harmonics']:>9}"
        cover = (s.get("coverage") or {}).get("fraction", float("nan"))
        line += f"  {100 * cover:6.1f}  {s.get('status', 'measured'):<12}"
        if s["section"] in accuracy:
            row = accuracy[s["section"]]
            line += f"  {row['rms_own_mm']:10.4f}  {row['rms_mean_mm']:11.4f}"
        print(line)
    if accuracy:
        acc = report["accuracy"]
        print(
            f"   mean RMS radial error: {acc['mean_own_mm']:.4f} mm (own centroid), "
            f"{acc['mean_mean_mm']:.4f} mm (mean centroid); thesis: 0.1069, 0.1354"
        )
    mesh = report["mesh"]
    print(f"mesh: {mesh['faces']} faces, {mesh['vertices']} vertices")
    for warning in report["warnings"]:
        print(f"warning: {warning}")
    for path in paths.values():
        print(f"wrote {path}")


def _open_scan(
    client: DeviceClient, args: argparse.Namespace, library: Library, plan: ScanPlan | None
) -> int:
    """Return the scan to fill: the resumed one, or a new one with the device's plans.

    Raises:
        StoreError: the resumed scan was acquired by another device or setup.
        InputError: a plan beyond the device's limits, or no cylinder diameter known.
    """
    identity = client.identity()
    limits = client.info.limits if client.info else {}
    if args.resume is not None:
        scan_id = int(args.resume)
        library.check_identity(scan_id, identity)
        for target, stored in library.scan(scan_id).plans.items():
            check_plan_limits(target, stored, limits)
        return scan_id
    plans = {
        "cylinder": client.plan_for("cylinder", None),
        "object": client.plan_for("object", plan),
    }
    for target, wanted in plans.items():
        check_plan_limits(target, wanted, limits)
    if _cylinder_mm(args, client) is None:
        raise UsageError("the device does not know its calibration cylinder: pass --cylinder-mm")
    info = client.info
    device = {"software": info.software, "hardware": info.hardware} if info else {}
    return library.create_scan(args.subject, plans, _scan_options(args), device, identity)


def _device_summary(client: DeviceClient) -> dict[str, Any]:
    """Return what the report says about the device that acquired the scan."""
    if client.info is None:
        return {}
    return {
        "software": client.info.software,
        "hardware": client.info.hardware,
        "description": client.info.description,
        "identity": client.identity(),
    }


def _open_library(path: Path | None) -> Library:
    """Open the scan library, saying once on stderr what it had to put right."""
    library = Library(path)
    for notice in library.notices:
        print(f"note: {notice}", file=sys.stderr)
    return library


def _notice(text: str) -> None:
    """Say on stderr what the device is doing (not an error: no ``lamina:`` prefix)."""
    print(f"  {text}", file=sys.stderr)


def scan(args: argparse.Namespace) -> int:
    """Run ``lamina scan``: store into the library, resume what it holds, reconstruct."""
    with _open_library(args.library) as library:
        record = library.scan(args.resume) if args.resume is not None else None
        if record is not None:
            _apply_resume(args, record)
        _apply_defaults(args)
        plan, expect = _check_args(args, record)
        own_out = record is not None and str(args.out.resolve()) == record.options.get("out")
        created = not args.out.exists()
        prepare_output_folder(args.out, allow_files=own_out)
        try:
            scan_id, data, timings, device = _acquire_scan(args, library, plan)
        except BaseException:
            if created:
                with suppress(OSError):
                    args.out.rmdir()  # only while empty: nothing was received into it
            raise
        return _process(args, library, scan_id, data, timings, device, expect)


def _acquire_scan(
    args: argparse.Namespace, library: Library, plan: ScanPlan | None
) -> tuple[int, dict[str, Any], dict[str, float], dict[str, Any]]:
    """Connect, open (or resume) the scan and acquire it; return the scan id and its data."""
    scan_id: int | None = None
    try:
        with open_device(
            args.device, args.object, args.seed, args.noise, rig=args.rig, on_notice=_notice
        ) as client:
            scan_id = _open_scan(client, args, library, plan)
            print(f"scan {scan_id} in library {library.path}", file=sys.stderr)
            data, timings = acquire(client, args, library, scan_id, args.out)
            return scan_id, data, timings, _device_summary(client)
    except (DeviceError, LinkClosed, ProtocolError) as exc:
        if scan_id is None:
            raise
        raise DeviceError(
            f"{exc}; what arrived is kept: finish with lamina scan --resume {scan_id} "
            f"--device {args.device}"
        ) from None


def _process(
    args: argparse.Namespace,
    library: Library,
    scan_id: int,
    data: dict[str, Any],
    timings: dict[str, float],
    device: dict[str, Any],
    expect: Expectation | None,
) -> int:
    """Reconstruct, write the outputs and store them as the scan's result."""
    options = _process_options(args)
    result: Reconstruction = reconstruct(
        data["grid_image"],
        data["board"],
        data["cylinder"],
        data["cylinder_mm"],
        data["segments"],
        options,
    )
    report = build_report(result, device, data["segments"], expect, timings)
    paths = write_outputs(args.out, result, report)
    library.save_result(scan_id, report, paths)
    print_summary(report, paths)
    return 0


def list_scans(args: argparse.Namespace) -> int:
    """Run ``lamina scans``: one line per scan in the library."""
    with _open_library(args.library) as library:
        summaries = library.scans()
        if not summaries:
            print(f"no scans in {library.path}")
            return 0
        print(
            f"{'scan':>5}  {'subject':<12} {'created':<25} {'status':<10} sections  views  result"
        )
        for s in summaries:
            views = f"{s.received}/{s.views}"
            # Codes stored by an older Lamina may hold anything: never print it raw.
            subject, created, status = (printable(t) for t in (s.subject, s.created, s.status))
            print(
                f"{s.id:>5}  {subject:<12} {created:<25} {status:<10} {s.sections:>8}  "
                f"{views:>5}  {'yes' if s.has_result else 'no'}"
            )
    return 0


def export(args: argparse.Namespace) -> int:
    """Run ``lamina export SCAN -o FILE``."""
    with _open_library(args.library) as library:
        path = library.export(args.scan, args.out)
    print(f"wrote {path}")
    return 0


def tui(args: argparse.Namespace) -> int:
    """Run ``lamina tui``: the Textual app on this terminal."""
    if args.object and args.device != "sim":
        raise UsageError("--object only applies to --device sim")
    from lamina_host.tui.app import LaminaApp  # deferred: Textual is only needed here

    LaminaApp(args.device, args.library, args.object).run()
    return 0


def clinical_report(args: argparse.Namespace) -> int:
    """Run ``lamina report SCAN -o FILE``: measure a processed scan and write its report."""
    from lamina_host.clinical import Thresholds, parse_landmark
    from lamina_host.clinical_report import MeasureRequest, build_report_data, write_report

    limits: tuple[float, ...] = (args.flag_difference_ml, args.flag_difference_percent)
    limits += (args.flag_circumference_mm, args.flag_change_percent)
    if not all(math.isfinite(v) and v >= 0 for v in limits):
        raise UsageError("the --flag-... thresholds must be numbers of at least 0")
    if not (math.isfinite(args.spacing_mm) and 1.0 <= args.spacing_mm <= 1000.0):
        raise UsageError(f"--spacing-mm {args.spacing_mm} must be between 1 and 1000 mm")
    outputs = [args.out] + ([args.csv] if args.csv else [])
    for path in outputs:
        if path.suffix.lower() not in (".pdf", ".png", ".csv"):
            raise UsageError(f"cannot write {path.name}: name the file .pdf, .png or .csv")
        if path.exists() or path.is_symlink():
            raise UsageError(f"{path} already exists: choose a new file name")
    request = MeasureRequest(
        args.spacing_mm, parse_landmark(args.landmark), args.limb_axis, Thresholds(*limits)
    )
    with _open_library(args.library) as library:
        data = build_report_data(library, args.scan, request, args.compare, args.compare_as)
    for path in outputs:
        print(f"wrote {write_report(path, data)}")
    for flag in data.comparison.flags if data.comparison else ():
        print(f"flag: {flag}")
    return 0


COMMANDS = {
    "scan": scan,
    "scans": list_scans,
    "export": export,
    "report": clinical_report,
    "tui": tui,
}


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit status."""
    args = build_parser().parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except (
        InputError,
        DeviceError,
        CalibrationError,
        StoreError,
        OutputError,
        ProtocolError,
    ) as exc:
        print(f"lamina: {printable(str(exc))}", file=sys.stderr)
    except LinkClosed as exc:
        print(
            f"lamina: the link to the device broke ({exc}); check the cable and try again",
            file=sys.stderr,
        )
    except sqlite3.Error as exc:
        library = getattr(args, "library", None) or default_library_path()
        print(
            f"lamina: the scan library {library} cannot be used ({exc}): if it is damaged, "
            "restore it from a backup",
            file=sys.stderr,
        )
    except OSError as exc:
        print(f"lamina: {exc.strerror or exc} ({exc.filename or 'no file'})", file=sys.stderr)
    except KeyboardInterrupt:
        print("lamina: interrupted; data received so far is in the output folder", file=sys.stderr)
        return 130
    return EXIT_USAGE
