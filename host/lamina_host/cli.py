"""``lamina``: scan with a Lamina device and turn the stripes into contours and a mesh.

Every user mistake ends in one line on stderr naming the problem and what to do,
with a non-zero exit status; data already received is written before processing.
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Sequence
from importlib.util import find_spec
from pathlib import Path
from typing import Any

import cv2

from lamina_host import __version__
from lamina_host.calibration import CalibrationError
from lamina_host.expect import Expectation, parse_expectation
from lamina_host.link import DeviceClient, DeviceError, open_device
from lamina_host.pipeline import ProcessOptions, Reconstruction, reconstruct
from lamina_host.report import build_report, save_segments, write_outputs
from lamina_shared.link import LinkClosed
from lamina_shared.types import ScanPlan

EXIT_USAGE = 2


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
    scan.add_argument("-o", "--out", required=True, type=Path, help="new output folder")
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
    scan.add_argument("--harmonics", type=int, help="EFD harmonics (default: thesis HN rule)")
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
    return parser


def _plan(args: argparse.Namespace) -> ScanPlan | None:
    if args.sections is None and args.pitch is None and args.views is None:
        return None
    try:
        return ScanPlan.regular(args.sections or 4, args.pitch or 2.0, args.views or 8)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _check_args(args: argparse.Namespace) -> tuple[ScanPlan | None, Expectation | None]:
    if args.out.exists() and any(args.out.iterdir()):
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


def acquire(
    client: DeviceClient, args: argparse.Namespace, plan: ScanPlan | None, out: Path
) -> tuple[dict[str, Any], dict[str, float]]:
    """Fetch calibration data and segments from the device, saving each as it arrives."""
    timings: dict[str, float] = {}
    start = time.perf_counter()
    grid_image, board = client.grab_grid()
    cv2.imwrite(str(out / "calibration-grid.png"), grid_image)
    cylinder = client.scan("cylinder", None, _progress)
    save_segments(out / "cylinder-segments.npz", cylinder)
    timings["acquire_calibration"] = time.perf_counter() - start
    start = time.perf_counter()
    segments = client.scan("object", plan, _progress)
    save_segments(out / "segments.npz", segments)
    timings["acquire_object"] = time.perf_counter() - start
    if sys.stderr.isatty():
        print(file=sys.stderr)
    info = client.info
    assert info is not None
    diameter = args.cylinder_mm or info.cylinder_diameter_mm
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
    header = "section  z_mm  points  harmonics"
    print(header + ("  rms_own_mm  rms_mean_mm" if accuracy else ""))
    for s in report["sections"]:
        line = f"{s['section']:>7}  {s['z_mm']:4.1f}  {s['raw_points']:>6}  {s['harmonics']:>9}"
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


def scan(args: argparse.Namespace) -> int:
    """Run ``lamina scan``."""
    plan, expect = _check_args(args)
    args.out.mkdir(parents=True, exist_ok=True)
    with open_device(args.device, args.object, args.seed, args.noise) as client:
        data, timings = acquire(client, args, plan, args.out)
        device = (
            {
                "software": client.info.software,
                "hardware": client.info.hardware,
                "description": client.info.description,
            }
            if client.info
            else {}
        )
    options = ProcessOptions(trim_fraction=args.trim, harmonics=args.harmonics)
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
    print_summary(report, paths)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit status."""
    args = build_parser().parse_args(argv)
    try:
        return scan(args)
    except (UsageError, DeviceError, CalibrationError) as exc:
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
