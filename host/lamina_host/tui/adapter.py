"""The terminal UI's one door to the device and to processing.

Every call here blocks (serial I/O, calibration, meshing), so the UI calls it only from
thread workers. Keeping it in one module means a change of the link, store or pipeline
APIs touches this file and none of the screens. Errors a user can act on leave as
:data:`USER_ERRORS`; the UI shows their text in one line.
"""

from __future__ import annotations

import math
import sqlite3
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager, suppress
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np
import pymeshlab  # noqa: F401 - see below
import serial.tools.list_ports

from lamina_host.assembly import to_object_frame
from lamina_host.axis import AxisCalibration
from lamina_host.calibration import CalibrationError, GridCalibration, calibrate_grid
from lamina_host.efd import HARMONIC_RULES
from lamina_host.files import PRIVATE_FOLDER, OutputError
from lamina_host.link import (
    DeviceClient,
    DeviceError,
    DeviceInfo,
    Preview,
    open_device,
)
from lamina_host.measure import perimeter, polygon_area
from lamina_host.mesh import MESH_METHODS
from lamina_host.pipeline import (
    ProcessOptions,
    Reconstruction,
    calibrate_axis,
    reconstruct,
    world_points,
)
from lamina_host.report import build_report, write_outputs
from lamina_host.store import Library, ScanSummary, StoreError
from lamina_host.workflow import (
    InputError,
    check_plan,
    check_plan_limits,
)
from lamina_host.workflow import check_subject as check_subject_code
from lamina_shared.link import LinkClosed
from lamina_shared.protocol import ProtocolError
from lamina_shared.types import BoardSpec, ScanPlan, Segment

# pymeshlab must be first imported on the main thread: when its first import happens in a
# worker thread (as meshing here does), the process aborts at exit with heap corruption
# ("malloc_consolidate(): unaligned fastbin chunk detected"), seen with pymeshlab 2025.7.


UserError = InputError
"""Bad input typed into the UI; the text names the field and what to enter (the same
refusals as the command line's, from :mod:`lamina_host.workflow`)."""


class Busy(RuntimeError):
    """The device is already running a request."""


USER_ERRORS: tuple[type[Exception], ...] = (
    UserError,
    Busy,
    DeviceError,
    CalibrationError,
    LinkClosed,
    StoreError,
    OutputError,
    ProtocolError,
    sqlite3.Error,
    OSError,
)
"""What a worker reports as a one-line message instead of failing."""

EXPORT_NAMES = ("mesh.ply", "mesh.obj", "mesh.stl", "report.json")
"""What an export writes into its folder: the mesh in three formats and the scan report."""

TRIM_FRACTION = ProcessOptions().trim_fraction


def user_message(exc: BaseException) -> str:
    """Return the one line the UI shows for an error a worker caught."""
    if isinstance(exc, LinkClosed):
        return f"the link to the device broke ({exc}); check the cable, then reconnect (c)"
    if isinstance(exc, OSError) and not isinstance(exc, DeviceError):
        return f"file error: {exc.strerror or exc} ({exc.filename or 'no file'})"
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
    try:
        n_sections = int(sections)
        n_views = int(views)
    except ValueError:
        raise UserError(
            f"sections ({sections!r}) and views ({views!r}) must be whole numbers"
        ) from None
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


@dataclass(frozen=True)
class Progress:
    """How far a scan has come, for the progress bar and the time left."""

    target: str
    done: int
    total: int
    section: int
    elapsed_s: float
    done_this_run: int
    """Views received since this run (a start or a resume) began: the rate comes from these."""

    @property
    def left_s(self) -> float | None:
        """Return the estimated seconds left (None before this run's first view)."""
        if self.done_this_run <= 0:
            return None
        return self.elapsed_s / self.done_this_run * max(self.total - self.done, 0)


@dataclass(frozen=True)
class SectionRow:
    """One row of the Results table."""

    index: int
    z_mm: float
    points: int
    perimeter_mm: float
    area_mm2: float
    roundness: float
    harmonics: int


@dataclass
class Results:
    """A processed scan as Results shows it."""

    reconstruction: Reconstruction
    rows: list[SectionRow]
    volume_mm3: float
    report: dict[str, Any]
    mesh_method: str


def roundness(contour: np.ndarray) -> float:
    """Return the isoperimetric quotient 4*pi*A/P^2: 1 for a circle, less for any other shape."""
    p = perimeter(contour)
    return 4.0 * math.pi * polygon_area(contour) / (p * p) if p > 0 else 0.0


def section_rows(result: Reconstruction) -> list[SectionRow]:
    """Measure every section's EFD contour."""
    return [
        SectionRow(
            s.index,
            s.z_mm,
            len(s.raw),
            perimeter(s.contour),
            polygon_area(s.contour),
            roundness(s.contour),
            s.harmonics,
        )
        for s in result.sections
    ]


def volume_mm3(rows: list[SectionRow]) -> float:
    """Return the volume between the first and last section (trapezoid rule over areas)."""
    if len(rows) < 2:
        return 0.0
    z = np.array([r.z_mm for r in rows])
    area = np.array([r.area_mm2 for r in rows])
    order = np.argsort(z)
    return float(np.trapezoid(area[order], z[order]))


def radius_profile(rows: list[SectionRow]) -> tuple[list[float], list[float]]:
    """Return (z_mm, equivalent radius sqrt(A/pi) in mm) per section, for the profile plot."""
    return [r.z_mm for r in rows], [math.sqrt(r.area_mm2 / math.pi) for r in rows]


@dataclass
class ScanData:
    """The raw data of one scan: what processing needs and what the library keeps."""

    grid_image: np.ndarray | None = None
    board: BoardSpec | None = None
    cylinder: list[Segment] = field(default_factory=list)
    cylinder_mm: float | None = None
    segments: list[Segment] = field(default_factory=list)
    subject_id: str = ""
    device: dict[str, str] = field(default_factory=dict)
    complete: bool = False


class Session:
    """One technician's session: a device connection, calibration, a scan and its results.

    Methods block; call them from worker threads. One request runs at a time: a second
    caller gets :class:`Busy` at once rather than waiting behind a scan.
    """

    def __init__(
        self,
        device: str = "sim",
        library_path: Path | None = None,
        object_spec: str | None = None,
        seed: int = 0,
    ) -> None:
        self.device = device
        self.library_path = library_path
        self.object_spec = object_spec
        self.seed = seed
        self.data = ScanData()
        self.grid: GridCalibration | None = None
        self.grid_accepted = False
        self.axis: AxisCalibration | None = None
        self.results: Results | None = None
        self.latest_segment: Segment | None = None
        self.plan: ScanPlan | None = None
        self.held: dict[int, Segment] = {}
        self.cylinder_plan: ScanPlan | None = None
        self.cylinder_held: dict[int, Segment] = {}
        self.scan_id: int | None = None
        self.pose: dict[str, float] = {"lift": 0.0, "turntable": 0.0}
        self.calibrated_by: dict[str, Any] | None = None
        """The identity of the device the chessboard and cylinder were captured with."""
        self._client: DeviceClient | None = None
        self._stack: ExitStack | None = None
        self._lock = threading.Lock()

    @property
    def info(self) -> DeviceInfo | None:
        """Return the connected device's information, or None."""
        return self._client.info if self._client else None

    @property
    def connected(self) -> bool:
        """Return True while a device is connected."""
        return self._client is not None

    @contextmanager
    def _busy(self) -> Iterator[None]:
        if not self._lock.acquire(blocking=False):
            raise Busy("the device is busy with another request; wait for it or abort it")
        try:
            yield
        finally:
            self._lock.release()

    def _device(self) -> DeviceClient:
        if self._client is None:
            raise UserError("no device connected: connect on the Connect screen (F2) first")
        return self._client

    def connect(self, device: str | None = None) -> DeviceInfo:
        """Connect to DEVICE (port, ``sim`` or ``replay:DIR``) and handshake."""
        with self._busy():
            self.device = (device or self.device).strip()
            if not self.device:
                raise UserError("enter a device: a serial port path, sim, or replay:CAPTURE_DIR")
            self._reopen()
            client = self._device()
            assert client.info is not None
            self.data.device = {
                "software": client.info.software,
                "hardware": client.info.hardware,
                "description": client.info.description,
            }
            return client.info

    def _close_link(self) -> None:
        stack, self._stack, self._client = self._stack, None, None
        if stack is not None:
            # A broken link cannot be tidied further; closing must still forget it.
            with suppress(DeviceError, LinkClosed, OSError):
                stack.close()

    def close(self) -> None:
        """Disconnect (stopping a device program this host started)."""
        with self._lock:
            self._close_link()

    def _link_failed(self) -> None:
        """Forget a broken link so the next connect starts afresh (data is kept)."""
        self._close_link()

    def grab_grid(self) -> tuple[np.ndarray, BoardSpec]:
        """Fetch the calibration image and board from the device."""
        with self._busy():
            client = self._device()
            try:
                image, board = client.grab_grid()
            except LinkClosed:
                self._link_failed()
                raise
        self.data.grid_image, self.data.board = image, board
        self.calibrated_by = client.identity()
        return image, board

    def _check_calibrated_here(self, client: DeviceClient) -> dict[str, Any]:
        """Return the device's identity; refuse if calibration came from another device."""
        identity = client.identity()
        if self.calibrated_by is not None and identity != self.calibrated_by:
            raise UserError(
                "the connected device is not the one calibrated: calibrate again (F4) "
                "before scanning with it"
            )
        return identity

    def preview(self, laser: bool) -> Preview:
        """Fetch one frame where the axes stand (laser on or off) and the stripe found there."""
        with self._busy():
            try:
                return self._device().preview(laser)
            except LinkClosed:
                self._link_failed()
                raise

    def exposure(self) -> tuple[int, int, int]:
        """Return the camera's (exposure, min, max) in microseconds."""
        with self._busy():
            try:
                return self._device().exposure()
            except LinkClosed:
                self._link_failed()
                raise

    def set_exposure(self, exposure_us: int) -> int:
        """Set the camera's exposure; return the one the device now uses.

        Raises:
            DeviceError: outside the camera's range (the device names it).
        """
        with self._busy():
            try:
                return self._device().set_exposure(exposure_us)
            except LinkClosed:
                self._link_failed()
                raise

    def pause_scan(self) -> None:
        """Hold the running scan on the device after its current view (any thread)."""
        self._device().pause()

    def resume_scan(self) -> None:
        """Let the device go on with a paused scan (any thread)."""
        self._device().resume()

    def abort_scan(self) -> None:
        """End the running scan on the device; the views received stay kept (any thread)."""
        self._device().abort()

    def move(self, axis: str, position: float) -> float:
        """Move ``lift`` (mm) or ``turntable`` (deg) to ``position``; return where it went.

        Raises:
            DeviceError: the position is outside the axis's soft limits (the device says which).
        """
        with self._busy():
            try:
                result = self._device().request("move", {"axis": axis, "position": position})
            except LinkClosed:
                self._link_failed()
                raise
        self.pose[axis] = float(result.get("position", position))
        return self.pose[axis]

    def calibrate_grid(self) -> GridCalibration:
        """Capture the chessboard and fit the homography; the result waits to be accepted."""
        image, board = self.grab_grid()
        self.grid = calibrate_grid(image, board)
        self.grid_accepted = False
        return self.grid

    def accept_grid(self, accept: bool) -> None:
        """Accept or reject the last grid calibration (a rejected one is forgotten)."""
        if self.grid is None:
            raise UserError("capture the chessboard first (g)")
        self.grid_accepted = accept
        if not accept:
            self.grid = None
            self.axis = None

    def _accepted_grid(self) -> GridCalibration:
        if self.grid is None or not self.grid_accepted:
            raise UserError("calibrate and accept the chessboard first (Calibrate screen, F4)")
        return self.grid

    def _run_scan(
        self,
        target: str,
        plan: ScanPlan,
        held: dict[int, Segment],
        store: Callable[[int, Segment], object] | None,
        on_segment: Callable[[Segment], object] | None,
        on_progress: Callable[[Progress], object] | None,
        on_notice: Callable[[str], object] | None = None,
    ) -> list[Segment]:
        """Scan the views of ``plan`` not in ``held``; store each arrival in ``held``.

        ``held`` maps plan index to segment and survives an abort or a broken link, so the
        same call with the same ``held`` resumes the scan where it stopped.

        Raises:
            ScanStopped: the scan was aborted (:meth:`abort_scan`); ``held`` keeps its views.
        """
        client = self._device()
        start = time.monotonic()
        first = len(held)

        def take(seq: int, segment: Segment) -> None:
            # Stored before returning: the link acknowledges the segment only afterwards.
            if store is not None:
                store(seq, segment)
            held[seq] = segment
            self.latest_segment = segment
            if on_segment is not None:
                on_segment(segment)

        def progress(body: dict[str, Any]) -> None:
            if on_progress is not None and body.get("event") == "progress":
                on_progress(
                    Progress(
                        target,
                        len(held),
                        len(plan.views),
                        int(body.get("section", 0)),
                        time.monotonic() - start,
                        len(held) - first,
                    )
                )

        try:
            client.scan(
                target, plan, progress, have=tuple(held), on_segment=take, on_notice=on_notice
            )
        except LinkClosed:
            self._link_failed()
            raise
        return [held[k] for k in sorted(held)]

    def _reopen(self) -> None:
        """Close and reopen the link to the same device (caller holds the busy lock)."""
        self._close_link()
        stack = ExitStack()
        try:
            self._client = stack.enter_context(
                open_device(self.device, self.object_spec, self.seed)
            )
        except BaseException:
            stack.close()
            self._client = None
            raise
        self._stack = stack

    def calibrate_axis(
        self,
        on_progress: Callable[[Progress], object] | None = None,
    ) -> AxisCalibration:
        """Scan the calibration cylinder and find the turntable axis and correction factor."""
        grid = self._accepted_grid()
        client = self._device()
        diameter = client.info.cylinder_diameter_mm if client.info else None
        if diameter is None:
            raise UserError("the device does not report its calibration cylinder's diameter")
        self._check_calibrated_here(client)
        with self._busy():
            plan = client.plan_for("cylinder", None)
            held: dict[int, Segment] = {}
            cylinder = self._run_scan("cylinder", plan, held, None, None, on_progress)
        self.cylinder_plan, self.cylinder_held = plan, held
        self.data.cylinder, self.data.cylinder_mm = cylinder, diameter
        self.axis = calibrate_axis(cylinder, grid, diameter, TRIM_FRACTION)
        return self.axis

    def scan_object(
        self,
        subject_id: str,
        plan: ScanPlan,
        on_segment: Callable[[Segment], object] | None = None,
        on_progress: Callable[[Progress], object] | None = None,
        on_notice: Callable[[str], object] | None = None,
    ) -> list[Segment]:
        """Start scanning the subject along ``plan``; every view received is kept."""
        subject = check_subject(subject_id)
        if self.axis is None:
            raise UserError("scan the calibration cylinder first (Calibrate screen, F4)")
        client = self._device()
        identity = self._check_calibrated_here(client)
        limits = client.info.limits if client.info else {}
        check_plan_limits("object", plan, limits)
        if self.cylinder_plan is not None:
            check_plan_limits("cylinder", self.cylinder_plan, limits)
        self.data.subject_id = subject
        with self._library() as library:
            self.scan_id = self._store_new_scan(library, subject, plan, identity)
        self.plan, self.held = plan, {}
        return self.resume_object(on_segment, on_progress, on_notice)

    @property
    def resumable(self) -> bool:
        """Return True when a started object scan still misses views."""
        return self.plan is not None and not self.data.complete

    def resume_object(
        self,
        on_segment: Callable[[Segment], object] | None = None,
        on_progress: Callable[[Progress], object] | None = None,
        on_notice: Callable[[str], object] | None = None,
    ) -> list[Segment]:
        """Scan the views of the current plan not received yet (after an abort or a drop)."""
        if self.plan is None or self.scan_id is None:
            raise UserError("no scan to resume: start one (s)")
        scan_id, plan = self.scan_id, self.plan
        identity = self._device().identity()
        with self._library() as library:
            # Before anything changes: a scan is only ever continued by what began it.
            library.check_identity(scan_id, identity)
            check_plan_limits("object", plan, self.info.limits if self.info else {})
        self.data.complete = False
        self.results = None
        with self._busy(), self._library() as library:
            try:
                segments = self._run_scan(
                    "object",
                    plan,
                    self.held,
                    lambda seq, segment: library.add_segment(scan_id, seq, segment, identity),
                    on_segment,
                    on_progress,
                    on_notice,
                )
            finally:
                self.data.segments = [self.held[k] for k in sorted(self.held)]
            library.set_status(scan_id, "acquired")
        self.data.complete = True
        return segments

    def section_points(self, segment: Segment) -> np.ndarray:
        """Return a segment's points in the object frame (mm), or (0, 2) before calibration."""
        if self.grid is None or self.axis is None:
            return np.empty((0, 2))
        points = world_points(segment, self.grid, TRIM_FRACTION)
        if not len(points):
            return np.empty((0, 2))
        return to_object_frame(
            points, segment.angle_deg, self.axis.axis_xy_mm, self.axis.correction_factor
        )

    def process(
        self,
        harmonics: int | None = None,
        mesh_method: str = MESH_METHODS[0],
        harmonic_rule: str | None = None,
    ) -> Results:
        """Reconstruct the scan held in :attr:`data` with the chosen harmonics and mesh method.

        Args:
            harmonics: a fixed EFD order for every section, or None to let the rule choose.
            mesh_method: one of ``MESH_METHODS``.
            harmonic_rule: one of ``HARMONIC_RULES``, or None for the pipeline's default.
        """
        data = self.data
        if data.grid_image is None or data.board is None or data.cylinder_mm is None:
            raise UserError("nothing to process: calibrate and scan, or open a saved scan")
        if not data.segments:
            raise UserError("nothing to process: scan the subject first (F5)")
        if harmonics is not None and not 1 <= harmonics <= 100:
            raise UserError(f"harmonics {harmonics} must be between 1 and 100, or blank for auto")
        if mesh_method not in MESH_METHODS:
            raise UserError(f"mesh method {mesh_method!r} is not one of {', '.join(MESH_METHODS)}")
        if harmonic_rule is not None and harmonic_rule not in HARMONIC_RULES:
            rules = ", ".join(HARMONIC_RULES)
            raise UserError(f"harmonic rule {harmonic_rule!r} is not one of {rules}")
        options = ProcessOptions(harmonics=harmonics, mesh=mesh_method)
        if harmonic_rule is not None:
            options = replace(options, harmonic_rule=harmonic_rule)
        result = reconstruct(
            data.grid_image, data.board, data.cylinder, data.cylinder_mm, data.segments, options
        )
        rows = section_rows(result)
        report = build_report(result, data.device, data.segments, None, {})
        report["subject_id"] = data.subject_id
        report["volume_mm3"] = volume_mm3(rows)
        if self.scan_id is not None:
            with tempfile.TemporaryDirectory() as tmp, self._library() as library:
                library.save_result(self.scan_id, report, write_outputs(Path(tmp), result, report))
        self.results = Results(result, rows, report["volume_mm3"], report, mesh_method)
        return self.results

    def _library(self) -> Library:
        """Open the scan library (one connection per call: each worker is its own thread)."""
        return Library(self.library_path)

    def _store_new_scan(
        self, library: Library, subject: str, plan: ScanPlan, identity: dict[str, Any]
    ) -> int:
        """Record a new scan with the calibration it uses; return its id."""
        data = self.data
        assert data.grid_image is not None and data.board is not None
        plans = {"object": plan}
        if self.cylinder_plan is not None:
            plans["cylinder"] = self.cylinder_plan
        scan_id = library.create_scan(
            subject,
            plans,
            {"device": self.device, "object": self.object_spec},
            data.device,
            identity,
        )
        library.save_calibration(scan_id, data.grid_image, data.board, data.cylinder_mm, identity)
        for seq, segment in self.cylinder_held.items():
            library.add_segment(scan_id, seq, segment, identity)
        return scan_id

    def export(self, folder: Path) -> list[Path]:
        """Export the current scan's mesh (PLY, OBJ, STL) and report into a new folder."""
        if self.results is None or self.scan_id is None:
            raise UserError("process the scan first (p on the Results screen)")
        return self.export_scan(self.scan_id, folder)

    def export_scan(self, scan_id: int, folder: Path) -> list[Path]:
        """Export a processed library scan into ``folder`` (new or empty)."""
        if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
            raise UserError(f"{folder} is not an empty folder; choose a new one")
        folder.mkdir(parents=True, exist_ok=True, mode=PRIVATE_FOLDER)
        with self._library() as library:
            return [library.export(scan_id, folder / name) for name in EXPORT_NAMES]

    def scans(self) -> list[ScanSummary]:
        """Return the library's scans, oldest first."""
        with self._library() as library:
            return library.scans()

    def delete_scan(self, scan_id: int) -> None:
        """Delete a scan from the library (forgetting it here too if it is open)."""
        with self._library() as library:
            library.delete_scan(scan_id)
        if self.scan_id == scan_id:
            self.scan_id, self.results, self.plan, self.held = None, None, None, {}
            self.data = ScanData()

    def open_scan(self, scan_id: int) -> ScanData:
        """Load a library scan so it can be processed again, exported or resumed."""
        with self._library() as library:
            record = library.scan(scan_id)
            calibration = library.calibration(scan_id)
            if calibration is None:
                raise UserError(f"scan {scan_id} has no calibration stored; it cannot be processed")
            object_plan = record.plans.get("object")
            self.held = {
                seq: segment
                for seq, segment in zip(
                    sorted(library.held(scan_id, "object")),
                    library.segments(scan_id, "object"),
                    strict=True,
                )
            }
            cylinder = library.segments(scan_id, "cylinder")
        self.scan_id, self.plan, self.results = scan_id, object_plan, None
        self.data = ScanData(
            calibration.grid_image,
            calibration.board,
            cylinder,
            calibration.cylinder_mm,
            [self.held[k] for k in sorted(self.held)],
            record.subject,
            {k: str(v) for k, v in record.device.items()},
            object_plan is not None and len(self.held) == len(object_plan.views),
        )
        return self.data
