"""``lamina-device``: serve a host over a serial port, record a raw capture, check a config.

Every user mistake ends in one line on stderr naming the problem and a non-zero
exit status, never a traceback. ``serve`` outlives its hosts: it ends with status 0
only when a host asks it to shut down, and with status 1 when its serial port stays
unusable (the systemd unit restarts it either way).
"""

from __future__ import annotations

import argparse
import contextlib
import logging
import signal
import sys
from collections.abc import Callable, Sequence
from pathlib import Path
from types import FrameType

import serial

from lamina_device import __version__
from lamina_device.acquisition import acquire, grab_grid
from lamina_device.backends import open_hardware
from lamina_device.config import check_config
from lamina_device.extract import run_opencv_inline
from lamina_device.hardware import Hardware
from lamina_device.listen import ListeningPort, open_listener
from lamina_device.safety import LaserShutdown
from lamina_device.server import DeviceServer, PortLost
from lamina_shared.capture import CaptureError, CaptureWriter
from lamina_shared.device_specs import SIM
from lamina_shared.errors import LaminaError
from lamina_shared.limits import DeviceLimits
from lamina_shared.link import Channel
from lamina_shared.local import EndpointError, local_url
from lamina_shared.messages import Progress
from lamina_shared.ops import ArgsError, Problems, check_plan
from lamina_shared.presets import NOISE_PRESETS, RIG_PRESETS
from lamina_shared.spawned import watch_parent
from lamina_shared.types import ScanPlan

EXIT_USAGE = 2
EXIT_PORT_LOST = 1
LISTED_PROBLEMS = 10
"""Problems of a refused capture listed one per line (all are counted in the summary)."""


def _terminate(signum: int, frame: FrameType | None) -> None:
    # gpiozero installs no SIGTERM handler and systemd's stop skips atexit, so turn the
    # signal into SystemExit: the finally blocks then switch the laser off.
    raise SystemExit(128 + signum)


def _add_hardware_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--hardware", required=True, help="sim, replay:CAPTURE_DIR or pi (the scanner box)"
    )
    parser.add_argument(
        "--config",
        type=Path,
        help="TOML configuration (default: packaged); the simulator takes its speeds, frame "
        "timing and continuous settings from it",
    )
    parser.add_argument("--object", help="simulated object, e.g. cylinder:d=19.05 (sim only)")
    parser.add_argument("--seed", type=int, default=0, help="simulation noise seed")
    parser.add_argument(
        "--noise",
        choices=NOISE_PRESETS,
        default="thesis",
        help="simulated noise and mechanical error: thesis-like (default), harsh (Pi camera "
        "at high gain in a lit room, real lens, eccentric gear) or none",
    )
    parser.add_argument(
        "--rig",
        choices=RIG_PRESETS,
        default="thesis",
        help="simulated rig geometry: thesis scale (640x480) or limb scale (1536x864)",
    )
    parser.add_argument(
        "--sway",
        default="none",
        help="simulated patient motion during the scan: none (default), patient (1 mm/min "
        "drift, 0.5 mm breathing at 0.25 Hz) or drift=MM_PER_MIN,breath=MM,hz=HZ (sim only)",
    )
    parser.add_argument(
        "--lift-error",
        type=float,
        metavar="PCT",
        help="simulated lift scale error in %%, e.g. 0.5 (runs long) or -0.5 (sim only; "
        "default: the noise preset's, 0.2 %% except with --noise none)",
    )


def build_parser() -> argparse.ArgumentParser:
    """Return the command-line parser."""
    parser = argparse.ArgumentParser(prog="lamina-device", description=__doc__)
    parser.add_argument("--version", action="version", version=f"lamina-device {__version__}")
    parser.add_argument("-v", "--verbose", action="store_true", help="log to stderr")
    sub = parser.add_subparsers(dest="command", required=True)
    serve = sub.add_parser("serve", help="serve a host over a serial port or a local endpoint")
    where = serve.add_mutually_exclusive_group(required=True)
    where.add_argument("--port", help="serial port, e.g. /dev/ttyGS0")
    where.add_argument(
        "--listen",
        metavar="ENDPOINT",
        help=f"serve a host on this machine instead: socket://HOST:PORT or local "
        f"({local_url()}, what `lamina --device local` opens)",
    )
    serve.add_argument("--baud", type=int, default=115200)
    _add_hardware_options(serve)
    record = sub.add_parser("record", help="record a raw capture (grid, cylinder, object)")
    _add_hardware_options(record)
    record.add_argument(
        "--out", required=True, type=Path, help="new capture folder (absent or empty)"
    )
    record.add_argument(
        "--into-nonempty",
        action="store_true",
        help="record into an existing folder that holds other files (nothing is deleted)",
    )
    record.add_argument("--sections", type=int, default=4)
    record.add_argument("--pitch", type=float, default=2.0, help="section pitch in mm")
    record.add_argument("--views", type=int, default=8, help="views per section")
    record.add_argument("--cylinder-views", type=int, default=8)
    record.add_argument(
        "--cylinder-sections", type=int, default=3, help="heights the cylinder is scanned at"
    )
    record.add_argument(
        "--cylinder-pitch", type=float, default=3.0, help="mm between the cylinder's heights"
    )
    check = sub.add_parser("check-config", help="validate a TOML configuration file")
    check.add_argument("file", type=Path, help="the configuration file")
    return parser


def check_config_command(path: Path) -> int:
    """Print OK or every problem of the configuration at ``path``; return the exit status."""
    problems = check_config(path)
    if not problems:
        print(f"{path}: OK")
        return 0
    count = f"{len(problems)} problem" + ("s" if len(problems) != 1 else "")
    print(f"lamina-device: config {path} has {count}:", file=sys.stderr)
    for problem in problems:
        print(f"  - {problem}", file=sys.stderr)
    return EXIT_USAGE


def _ask_operator(hardware: Hardware, what: str) -> None:
    """On the scanner box, wait until the operator has put ``what`` on the turntable."""
    if hardware.kind != "pi":
        return
    # Unattended (no terminal to read): the targets are assumed to be in place.
    with contextlib.suppress(EOFError, OSError):
        input(f"Put the {what} on the turntable, then press Enter: ")


def _open_port(args: argparse.Namespace) -> serial.Serial | ListeningPort:
    """Open the serial port or the local endpoint ``serve`` was given."""
    if args.listen is None:
        return serial.Serial(args.port, baudrate=args.baud, timeout=0.05, exclusive=True)
    listener = open_listener(args.listen)
    host, port = listener.address
    print(f"lamina-device: serving on {local_url(port, host)}", file=sys.stderr, flush=True)
    return listener


def serve(args: argparse.Namespace, hardware: Hardware) -> int:
    """Serve the host on ``args.port`` (or ``args.listen``) until it asks to stop."""
    try:
        port = _open_port(args)
    except EndpointError as exc:
        print(f"lamina-device: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except (serial.SerialException, OSError) as exc:
        what = f"serial port {args.port}" if args.listen is None else f"endpoint {args.listen}"
        reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else exc
        print(f"lamina-device: cannot open {what}: {reason}", file=sys.stderr)
        return EXIT_USAGE
    with contextlib.closing(port):
        try:
            DeviceServer(Channel(port), hardware).serve()
        except PortLost as exc:
            print(f"lamina-device: {exc}; exiting so the service restarts", file=sys.stderr)
            return EXIT_PORT_LOST
    return 0


def record_plans(args: argparse.Namespace, limits: DeviceLimits) -> tuple[ScanPlan, ScanPlan]:
    """Return the object and cylinder plans ``record`` asks for; ArgsError if beyond limits."""
    problems = Problems()
    plans = []
    for name, sections, pitch_mm, views, flags in (
        ("object", args.sections, args.pitch, args.views, ("--sections", "--pitch", "--views")),
        (
            "cylinder",
            args.cylinder_sections,
            args.cylinder_pitch,
            args.cylinder_views,
            ("--cylinder-sections", "--cylinder-pitch", "--cylinder-views"),
        ),
    ):
        regular = {"sections": sections, "pitch_mm": pitch_mm, "views": views}
        found = Problems()
        plans.append(check_plan({"regular": regular}, limits, found))
        options = dict(zip(("sections", "pitch_mm", "views"), flags, strict=True))
        for text in found.items:
            for key, flag in options.items():
                text = text.replace(f"plan.regular.{key}", flag)
            problems.add(f"{name} {text.replace('plan.regular', 'plan')}")
    if problems.items or plans[0] is None or plans[1] is None:
        raise ArgsError("record", problems.items)
    return plans[0], plans[1]


def out_folder_problem(out: Path, into_nonempty: bool) -> str | None:
    """Return why ``out`` cannot take a new capture, or None if it can."""
    if out.exists() and not out.is_dir():
        return f"--out {out} is a file; name a new folder"
    if (out / "capture.json").exists():
        return f"--out {out} already holds a capture; name a new folder"
    if out.is_dir() and not into_nonempty and any(out.iterdir()):
        return (
            f"--out {out} is not empty; name a new folder, or add --into-nonempty to record "
            "beside its files (nothing is deleted)"
        )
    return None


def _progress_printer(what: str, plan: ScanPlan) -> Callable[[Progress], None]:
    """Return a progress callback printing one line on stderr per finished section."""
    ends, done = set(), 0
    for section in plan.sections:
        done += sum(1 for view in plan.views if view.section == section)
        ends.add(done)

    def show(progress: Progress) -> None:
        if progress.done in ends:
            print(
                f"recording {what}: section {progress.section} done, "
                f"{progress.done}/{progress.total} views",
                file=sys.stderr,
                flush=True,
            )

    return show


def record(args: argparse.Namespace, hardware: Hardware) -> int:
    """Record the grid image, the cylinder views and the object views into a capture."""
    try:
        plan, cylinder_plan = record_plans(args, DeviceLimits())
    except ArgsError as exc:
        print(f"lamina-device: record refused: {'; '.join(exc.problems)}", file=sys.stderr)
        return EXIT_USAGE
    problem = out_folder_problem(args.out, args.into_nonempty)
    if problem is not None:
        print(f"lamina-device: {problem}", file=sys.stderr)
        return EXIT_USAGE
    try:
        writer = CaptureWriter(
            args.out,
            hardware.camera.size,
            {"object": hardware.description, "recorded_by": "lamina-device"},
        )
    except (ValueError, OSError) as exc:
        print(f"lamina-device: {exc}", file=sys.stderr)
        return EXIT_USAGE
    try:
        if hardware.board is not None:
            _ask_operator(hardware, "calibration board")
            writer.add_grid(grab_grid(hardware), hardware.board)
        if hardware.cylinder_diameter_mm is not None:
            _ask_operator(hardware, "calibration cylinder")
            writer.set_cylinder(hardware.cylinder_diameter_mm)
            acquire(
                hardware,
                "cylinder",
                cylinder_plan,
                lambda s: None,
                _progress_printer("cylinder", cylinder_plan),
                sink=writer.add_view,
            )
        _ask_operator(hardware, "object")
        acquire(
            hardware,
            "object",
            plan,
            lambda s: None,
            _progress_printer("object", plan),
            sink=writer.add_view,
        )
    except (LaminaError, OSError) as exc:
        print(
            f"lamina-device: recording stopped: {exc} (the frames recorded so far stay in "
            f"{args.out}, without a manifest as the capture is incomplete)",
            file=sys.stderr,
        )
        return EXIT_USAGE
    path = writer.close()
    print(f"capture written: {path} ({len(plan.views)} object views)")
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; return the exit status."""
    args = build_parser().parse_args(argv)
    logging.basicConfig(
        level=logging.INFO if args.verbose else logging.WARNING, format="lamina-device: %(message)s"
    )
    if args.command == "check-config":
        return check_config_command(args.file)
    signal.signal(signal.SIGTERM, _terminate)
    watch_parent()  # a device a host started ends with it, even after kill -9 of the host
    try:
        hardware = open_hardware(
            args.hardware,
            args.object,
            args.seed,
            args.noise,
            args.config,
            rig=args.rig,
            sway=args.sway,
            lift_error_percent=args.lift_error,
        )
    except CaptureError as exc:
        # The first problems one per line, then the summary last: a host that started this
        # program shows its last line, which names the first problems and counts the rest.
        # Thousands of lines would only bury them (and fill a pipe nobody reads yet).
        for problem in exc.problems[:LISTED_PROBLEMS]:
            print(f"  - {problem}", file=sys.stderr)
        if len(exc.problems) > LISTED_PROBLEMS:
            print(f"  - ... and {len(exc.problems) - LISTED_PROBLEMS} more", file=sys.stderr)
        print(f"lamina-device: {exc}", file=sys.stderr)
        return EXIT_USAGE
    except LaminaError as exc:
        print(f"lamina-device: {exc}", file=sys.stderr)
        return EXIT_USAGE
    if hardware.kind != SIM:
        run_opencv_inline()  # a camera's or a replay's frames: extraction is all OpenCV does
    try:
        # From here SIGTERM, SIGINT and exit switch the laser off before anything else.
        with LaserShutdown(hardware.laser):
            return serve(args, hardware) if args.command == "serve" else record(args, hardware)
    except KeyboardInterrupt:
        return 130
    finally:
        hardware.close()
