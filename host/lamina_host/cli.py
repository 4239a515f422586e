"""``lamina``: scan with a Lamina device and turn the stripes into contours and a mesh.

Every user mistake ends in one line on stderr naming the problem and what to do,
with a non-zero exit status; data already received is written before processing.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
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
from lamina_host.link import DeviceClient, DeviceError, open_device
from lamina_host.mesh import MESH_METHODS
from lamina_host.pipeline import ProcessOptions, Reconstruction, reconstruct
from lamina_host.report import build_report, save_segments, write_outputs
from lamina_host.store import Library, StoreError
from lamina_shared.link import LinkClosed
from lamina_shared.types import ScanPlan

EXIT_USAGE = 2
RIG_PRESETS = ("thesis", "limb")
"""The simulated rig geometries (lamina_device.sim.RIG_PRESETS; not imported, since the
host must run without the device package)."""


class UsageError(ValueError):
    """A mistake in how the command was called."""


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
    scan.add_argument("--subject", default="anonymous", help="pseudonymous subject code")
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
        default=0.10,
        help="fraction dropped from each segment end (default 0.10)",
    )
    scan.add_argument("--seed", type=int, default=0, help="simulation seed (sim only)")
    scan.add_argument(
        "--noise",
        choices=("thesis", "none"),
        default="thesis",
        help="simulated noise level (sim only)",
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
    tui = sub.add_parser("tui", help="the terminal UI for the whole workflow (works over SSH)")
    tui.add_argument(
        "--device", default="sim", help="serial port path, 'sim' (default) or 'replay:DIR'"
    )
    tui.add_argument("--object", help="simulated object (sim only), e.g. cylinder:d=19.05")
    _add_library_option(tui)
    return parser


def _add_processing_options(parser: argparse.ArgumentParser) -> None:
    """Add the rig choice and the method of each reconstruction stage."""
    parser.add_argument(
        "--rig", choices=RIG_PRESETS, default="thesis", help="simulated rig geometry (sim only)"
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
        if args.split_gap < 0:
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


def _apply_resume(args: argparse.Namespace, library: Library) -> None:
    """Take a resumed scan's options (and output folder, unless given) from the library."""
    record = library.scan(args.resume)
    for name in RESUMED_OPTIONS:
        setattr(args, name, record.options.get(name, getattr(args, name)))
    args.subject = record.subject
    if args.out is None:
        args.out = Path(record.options["out"])


def _plan(args: argparse.Namespace) -> ScanPlan | None:
    if args.sections is None and args.pitch is None and args.views is None:
        return None
    try:
        return ScanPlan.regular(args.sections or 4, args.pitch or 2.0, args.views or 8)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _check_args(
    args: argparse.Namespace, own_out: str | None = None
) -> tuple[ScanPlan | None, Expectation | None]:
    if args.out is None:
        raise UsageError("name an output folder with -o OUT")
    resuming_into_own = own_out is not None and str(args.out.resolve()) == own_out
    if args.out.exists() and any(args.out.iterdir()) and not resuming_into_own:
        raise UsageError(
            f"output folder {args.out} is not empty; choose a new folder so "
            "no earlier scan is overwritten"
        )
    if not 0.0 <= args.trim < 0.5:
        raise UsageError(f"--trim {args.trim} must be at least 0 and below 0.5")
    if args.harmonics is not None and args.harmonics < 1:
        raise UsageError("--harmonics must be 1 or more")
    spawns_device = args.device == "sim" or args.device.startswith("replay:")
    if spawns_device and find_spec("lamina_device") is None:
        raise UsageError(
            f"--device {args.device} runs the device program here, but "
            "lamina-device is not installed: pip install -e device"
        )
    if args.object and args.device != "sim":
        raise UsageError("--object only applies to --device sim")
    if args.rig != "thesis" and args.device != "sim":
        raise UsageError("--rig only applies to --device sim")
    _process_options(args)  # refuse bad method combinations before scanning
    try:
        expect = parse_expectation(args.expect) if args.expect else None
    except ValueError as exc:
        raise UsageError(str(exc)) from None
    return _plan(args), expect


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


def _fetch_views(client: DeviceClient, library: Library, scan_id: int, target: str) -> None:
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
        on_segment=lambda seq, segment: library.add_segment(scan_id, seq, segment),
    )


def acquire(
    client: DeviceClient, args: argparse.Namespace, library: Library, scan_id: int, out: Path
) -> tuple[dict[str, Any], dict[str, float]]:
    """Fetch what the library lacks of the scan, then write the received data to ``out``."""
    timings: dict[str, float] = {}
    start = time.perf_counter()
    if library.calibration(scan_id) is None:
        grid, board = client.grab_grid()
        assert client.info is not None
        library.save_calibration(
            scan_id, grid, board, args.cylinder_mm or client.info.cylinder_diameter_mm
        )
    calibration = library.calibration(scan_id)
    assert calibration is not None
    grid_image, board = calibration.grid_image, calibration.board
    cv2.imwrite(str(out / "calibration-grid.png"), grid_image)
    _fetch_views(client, library, scan_id, "cylinder")
    cylinder = library.segments(scan_id, "cylinder")
    save_segments(out / "cylinder-segments.npz", cylinder)
    timings["acquire_calibration"] = time.perf_counter() - start
    start = time.perf_counter()
    _fetch_views(client, library, scan_id, "object")
    segments = library.segments(scan_id, "object")
    save_segments(out / "segments.npz", segments)
    library.set_status(scan_id, "acquired")
    timings["acquire_object"] = time.perf_counter() - start
    if sys.stderr.isatty():
        print(file=sys.stderr)
    diameter = calibration.cylinder_mm
    if diameter is None:
        raise UsageError("the device does not know its calibration cylinder: pass --cylinder-mm")
    data = {
        "grid_image": grid_image,
        "board": board,
        "cylinder": cylinder,
        "cylinder_mm": diameter,
        "segments": segments,
    }
    return data, timings


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
    """Return the scan to fill: the resumed one, or a new one with the device's plans."""
    if args.resume is not None:
        return int(args.resume)
    plans = {
        "cylinder": client.plan_for("cylinder", None),
        "object": client.plan_for("object", plan),
    }
    info = client.info
    device = {"software": info.software, "hardware": info.hardware} if info else {}
    return library.create_scan(args.subject, plans, _scan_options(args), device)


def scan(args: argparse.Namespace) -> int:
    """Run ``lamina scan``: store into the library, resume what it holds, reconstruct."""
    with Library(args.library) as library:
        own_out = None
        if args.resume is not None:
            _apply_resume(args, library)
            own_out = library.scan(args.resume).options.get("out")
        plan, expect = _check_args(args, own_out)
        args.out.mkdir(parents=True, exist_ok=True)
        scan_id: int | None = None
        try:
            with open_device(
                args.device, args.object, args.seed, args.noise, rig=args.rig
            ) as client:
                scan_id = _open_scan(client, args, library, plan)
                print(f"scan {scan_id} in library {library.path}", file=sys.stderr)
                data, timings = acquire(client, args, library, scan_id, args.out)
                device = (
                    {
                        "software": client.info.software,
                        "hardware": client.info.hardware,
                        "description": client.info.description,
                    }
                    if client.info
                    else {}
                )
        except (DeviceError, LinkClosed) as exc:
            if scan_id is None:
                raise
            raise DeviceError(
                f"{exc}; what arrived is kept: finish with lamina scan --resume {scan_id} "
                f"--device {args.device}"
            ) from None
        return _process(args, library, scan_id, data, timings, device, expect)


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
    with Library(args.library) as library:
        summaries = library.scans()
        if not summaries:
            print(f"no scans in {library.path}")
            return 0
        print(
            f"{'scan':>5}  {'subject':<12} {'created':<25} {'status':<10} sections  views  result"
        )
        for s in summaries:
            views = f"{s.received}/{s.views}"
            print(
                f"{s.id:>5}  {s.subject:<12} {s.created:<25} {s.status:<10} {s.sections:>8}  "
                f"{views:>5}  {'yes' if s.has_result else 'no'}"
            )
    return 0


def export(args: argparse.Namespace) -> int:
    """Run ``lamina export SCAN -o FILE``."""
    with Library(args.library) as library:
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


COMMANDS = {"scan": scan, "scans": list_scans, "export": export, "tui": tui}


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit status."""
    args = build_parser().parse_args(argv)
    try:
        return COMMANDS[args.command](args)
    except (UsageError, DeviceError, CalibrationError, StoreError) as exc:
        print(f"lamina: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except LinkClosed as exc:
        print(
            f"lamina: the link to the device broke ({exc}); check the cable and try again",
            file=sys.stderr,
        )
        return EXIT_USAGE
    except KeyboardInterrupt:
        print("lamina: interrupted; data received so far is in the output folder", file=sys.stderr)
        return 130
