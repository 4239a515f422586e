"""The scan job: connect, calibrate, create or resume a scan, fetch, store, process, export.

The command line runs the whole sequence at once (:func:`acquire`); the terminal UI runs
the same steps one key at a time. Both hand in a typed :class:`ScanRequest` (checked once
on construction, the plan against the device's limits when the scan is created) and get
typed results back (:mod:`lamina_host.workflow.results`). Every step blocks (serial I/O,
calibration, meshing); the UI calls them from thread workers, one at a time (a second
caller gets :class:`Busy`), except pause, resume and abort, which any thread may send
while a scan runs.
"""

from __future__ import annotations

import tempfile
import threading
import time
from collections.abc import Callable, Iterator, Mapping
from contextlib import ExitStack, contextmanager, suppress
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from lamina_host.link.client import DeviceClient, DeviceError, DeviceInfo, Preview, open_device
from lamina_host.reconstruct.axis import AxisCalibration
from lamina_host.reconstruct.calibration import GridCalibration, calibrate_grid
from lamina_host.reconstruct.expect import Expectation
from lamina_host.reconstruct.pipeline import ProcessOptions, assemble, calibrate_axis, reconstruct
from lamina_host.store.files import PRIVATE_FOLDER, OutputError, replace_file
from lamina_host.store.library import SIDES, Library, ScanSummary, check_side
from lamina_host.store.outputs import build_report, save_segments, write_outputs
from lamina_host.store.subjects import check_subject
from lamina_host.workflow.checks import check_plan_limits, check_positive_mm
from lamina_host.workflow.results import (
    Progress,
    Results,
    ScanData,
    device_summary,
    report_device,
    section_rows,
    volume_mm3,
)
from lamina_shared.errors import InputError, LaminaError
from lamina_shared.link import LinkClosed
from lamina_shared.ops import ExtractChanges
from lamina_shared.types import BoardSpec, ScanPlan, Segment

EXPORT_NAMES = ("mesh.ply", "mesh.obj", "mesh.stl", "report.json")
"""What an export writes into its folder: the mesh in three formats and the scan report."""

TRIM_FRACTION = ProcessOptions().trim_fraction
"""The trim of the axis shown during calibration and of the live section plot."""

ProgressHandler = Callable[[Progress], object]
SegmentHandler = Callable[[Segment], object]
NoticeHandler = Callable[[str], object]


class Busy(LaminaError, RuntimeError):
    """The device is already running a request."""


class ProcessingError(LaminaError):
    """Processing a scan failed; the scan is kept and the message says how to process it again."""


def process_again_hint(scan_id: int) -> str:
    """Return the advice a failed processing of library scan ``scan_id`` ends with."""
    return (
        f"scan {scan_id} is kept in the library: process it again with lamina process "
        f"{scan_id} [options] (or p on the terminal UI's Library screen)"
    )


@dataclass(frozen=True)
class DeviceTarget:
    """What to connect to: a port path, ``sim`` or ``replay:DIR``, and the simulation's choices."""

    device: str = "sim"
    object_spec: str | None = None
    seed: int = 0
    noise: str = "thesis"
    rig: str = "thesis"


@dataclass(frozen=True)
class ScanRequest:
    """A new scan as a front end asks for it; checked once, when it is made.

    Attributes:
        subject: the pseudonymous subject code (:data:`~lamina_host.store.subjects.SUBJECT_RULE`).
        plan: the object's plan; None for the device's default plan.
        cylinder_mm: the calibration cylinder's diameter; None for the device's.
        options: what the library records with the scan (what a resume must repeat).
        extract: per-scan extraction settings for the device; None leaves the device's own.
        colour: ask for each object point's colour (the device must say it can).
        side: the limb scanned, one of :data:`lamina_host.store.library.SIDES`.
    """

    subject: str
    plan: ScanPlan | None = None
    cylinder_mm: float | None = None
    options: Mapping[str, Any] = field(default_factory=dict)
    extract: ExtractChanges | None = None
    colour: bool = False
    side: str = SIDES[0]

    def __post_init__(self) -> None:
        check_subject(self.subject)
        check_side(self.side)
        if self.cylinder_mm is not None:
            check_positive_mm("cylinder diameter", self.cylinder_mm, 1000.0)


class ScanJob:
    """One device connection and one scan at a time: calibration, views, results.

    The attributes hold what the steps produced so far: :attr:`data` (the raw scan),
    :attr:`grid` and :attr:`axis` (the calibration shown before scanning), :attr:`held`
    (the object views received, by plan index) and :attr:`results`.
    """

    def __init__(
        self, target: DeviceTarget, library_path: Path | None = None, library: Library | None = None
    ) -> None:
        self.target = target
        self.library_path = library.path if library is not None else library_path
        self._given_library = library
        self._own_library: Library | None = None
        self._library_lock = threading.Lock()
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
        self.identity: dict[str, Any] | None = None
        """The identity the scan was recorded under (None before one exists)."""
        self.extract: ExtractChanges | None = None
        self.colour = False
        """Ask for each object point's colour (:meth:`set_colour`)."""
        self.pose: dict[str, float] = {"lift": 0.0, "turntable": 0.0}
        self.calibrated_by: dict[str, Any] | None = None
        """The identity of the device the chessboard and cylinder were captured with."""
        self._client: DeviceClient | None = None
        self._stack: ExitStack | None = None
        self._lock = threading.Lock()

    # -- the connection ---------------------------------------------------------------

    @property
    def device(self) -> str:
        """Return the device this job connects to (port path, ``sim`` or ``replay:DIR``)."""
        return self.target.device

    @property
    def object_spec(self) -> str | None:
        """Return the simulated object the next connection asks for (sim only)."""
        return self.target.object_spec

    @object_spec.setter
    def object_spec(self, spec: str | None) -> None:
        self.target = replace(self.target, object_spec=spec)

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
            raise InputError("no device connected: connect on the Connect screen (F2) first")
        return self._client

    def connect(
        self, device: str | None = None, on_notice: NoticeHandler | None = None
    ) -> DeviceInfo:
        """Connect to DEVICE (port, ``sim`` or ``replay:DIR``; default the target's)."""
        with self._busy():
            name = (device or self.target.device).strip()
            if not name:
                raise InputError(
                    "enter a device: a serial port path, local, sim, or replay:CAPTURE_DIR"
                )
            self.target = replace(self.target, device=name)
            self._reopen(on_notice)
            info = self._device().info
            assert info is not None
            self.data.device = device_summary(info)
            return info

    def set_extract(self, changes: ExtractChanges | None) -> None:
        """Change the device's stripe extraction for this session's scans (None: its own).

        The effective settings are part of the scan identity, so set them before the
        calibration that a scan will use.
        """
        self._device().extract = changes
        self.extract = changes

    def set_colour(self, colour: bool) -> None:
        """Ask for (or stop asking for) each object point's colour in this session's scans.

        Raises:
            InputError: the device cannot sample colour.
        """
        client = self._device()
        if colour and not (client.info and client.info.colour):
            raise InputError(
                "this device cannot sample colour (a monochrome camera, the simulator without "
                "--noise harsh, or an older lamina-device): scan without colour"
            )
        self.colour = colour

    def attach(self, client: DeviceClient) -> None:
        """Use a client already handshaken elsewhere (an in-process device); closing leaves it."""
        with self._busy():
            self._close_link()
            self._client = client
            self.data.device = device_summary(client.info)

    def _reopen(self, on_notice: NoticeHandler | None) -> None:
        """Close and reopen the link to the same device (caller holds the busy lock)."""
        self._close_link()
        stack = ExitStack()
        t = self.target
        try:
            self._client = stack.enter_context(
                open_device(
                    t.device, t.object_spec, t.seed, t.noise, rig=t.rig, on_notice=on_notice
                )
            )
        except BaseException:
            stack.close()
            self._client = None
            raise
        self._stack = stack

    def _close_link(self) -> None:
        stack, self._stack, self._client = self._stack, None, None
        if stack is not None:
            # A broken link cannot be tidied further; closing must still forget it.
            with suppress(DeviceError, LinkClosed, OSError):
                stack.close()

    def close(self) -> None:
        """Disconnect (stopping a device program this host started) and close the library.

        The job's own library is opened again if a later step needs it.
        """
        with self._lock:
            self._close_link()
        with self._library_lock:
            own, self._own_library = self._own_library, None
        if own is not None:
            own.close()

    @contextmanager
    def _link(self) -> Iterator[DeviceClient]:
        """Yield the client; a broken link is forgotten so the next connect starts afresh."""
        try:
            yield self._device()
        except LinkClosed:
            self._close_link()
            raise

    def library(self) -> Library:
        """Return the job's scan library, opened on first use and kept until :meth:`close`.

        One connection for every step and thread of the job (a :class:`Library` serialises
        its calls), so a process holds one rather than one per step; a library handed in
        at construction is used instead and left to its owner to close.
        """
        if self._given_library is not None:
            return self._given_library
        with self._library_lock:
            if self._own_library is None:
                self._own_library = Library(self.library_path)
            return self._own_library

    # -- the device's own controls ------------------------------------------------------

    def preview(self, laser: bool) -> Preview:
        """Fetch one frame where the axes stand (laser on or off) and the stripe found there."""
        with self._busy(), self._link() as client:
            return client.preview(laser)

    def exposure(self) -> tuple[int, int, int]:
        """Return the camera's (exposure, min, max) in microseconds."""
        with self._busy(), self._link() as client:
            return client.exposure()

    def set_exposure(self, exposure_us: int) -> int:
        """Set the camera's exposure; return the one the device now uses."""
        with self._busy(), self._link() as client:
            return client.set_exposure(exposure_us)

    def move(self, axis: str, position: float) -> float:
        """Move ``lift`` (mm) or ``turntable`` (deg) to ``position``; return where it went."""
        with self._busy(), self._link() as client:
            result = client.request("move", {"axis": axis, "position": position})
        self.pose[axis] = float(result.get("position", position))
        return self.pose[axis]

    def pause_scan(self) -> None:
        """Hold the running scan on the device after its current view (any thread)."""
        self._device().pause()

    def resume_scan(self) -> None:
        """Let the device go on with a paused scan (any thread)."""
        self._device().resume()

    def abort_scan(self) -> None:
        """End the running scan on the device; the views received stay kept (any thread)."""
        self._device().abort()

    # -- calibration ------------------------------------------------------------------

    def grab_grid(self) -> tuple[np.ndarray, BoardSpec]:
        """Fetch the calibration image and board from the device."""
        with self._busy(), self._link() as client:
            image, board = client.grab_grid()
        self.data.grid_image, self.data.board = image, board
        self.calibrated_by = client.identity()
        return image, board

    def calibrate_grid(self) -> GridCalibration:
        """Capture the chessboard and fit the homography; the result waits to be accepted."""
        image, board = self.grab_grid()
        self.grid = calibrate_grid(image, board)
        self.grid_accepted = False
        return self.grid

    def accept_grid(self, accept: bool) -> None:
        """Accept or reject the last grid calibration (a rejected one is forgotten)."""
        if self.grid is None:
            raise InputError("capture the chessboard first (g)")
        self.grid_accepted = accept
        if not accept:
            self.grid = None
            self.axis = None

    def _accepted_grid(self) -> GridCalibration:
        if self.grid is None or not self.grid_accepted:
            raise InputError("calibrate and accept the chessboard first (Calibrate screen, F4)")
        return self.grid

    def _check_calibrated_here(self, client: DeviceClient) -> dict[str, Any]:
        """Return the device's identity; refuse if calibration came from another device."""
        identity = client.identity()
        if self.calibrated_by is not None and identity != self.calibrated_by:
            raise InputError(
                "the connected device is not the one calibrated: calibrate again (F4) "
                "before scanning with it"
            )
        return identity

    def calibrate_axis(self, on_progress: ProgressHandler | None = None) -> AxisCalibration:
        """Scan the calibration cylinder afresh and find the turntable axis (shown, not stored)."""
        grid = self._accepted_grid()
        client = self._device()
        diameter = client.info.cylinder_diameter_mm if client.info else None
        if diameter is None:
            raise InputError("the device does not report its calibration cylinder's diameter")
        self._check_calibrated_here(client)
        plan = client.plan_for("cylinder", None)
        held: dict[int, Segment] = {}
        with self._busy():
            cylinder = self._run_views("cylinder", plan, held, False, None, on_progress, None)
        self.cylinder_plan, self.cylinder_held = plan, held
        self.data.cylinder, self.data.cylinder_mm = cylinder, diameter
        self.axis = calibrate_axis(cylinder, grid, diameter, TRIM_FRACTION)
        return self.axis

    def fetch_calibration(self, cylinder_mm: float | None = None) -> ScanData:
        """Give the open scan its calibration: the one stored, else the device's chessboard.

        Raises:
            InputError: no calibration cylinder diameter is known.
        """
        scan_id = self.require_scan()
        library = self.library()
        if library.calibration(scan_id) is None:
            image, board = self.grab_grid()
            diameter = self._cylinder_mm(cylinder_mm)
            library.save_calibration(scan_id, image, board, diameter, self.identity)
        calibration = library.calibration(scan_id)
        assert calibration is not None
        self.data.grid_image, self.data.board = calibration.grid_image, calibration.board
        diameter = calibration.cylinder_mm
        if diameter is None:
            diameter = self._cylinder_mm(cylinder_mm)
        if diameter is None:
            raise InputError(
                "the device does not know its calibration cylinder: pass --cylinder-mm"
            )
        self.data.cylinder_mm = diameter
        return self.data

    def _cylinder_mm(self, given: float | None) -> float | None:
        """Return the calibration cylinder's diameter: the one given, else the device's."""
        if given is not None:
            return float(given)
        return self.info.cylinder_diameter_mm if self.info else None

    # -- the scan in the library --------------------------------------------------------

    def require_scan(self) -> int:
        """Return the open scan's id, or refuse when no scan is open."""
        if self.scan_id is None:
            raise InputError("no scan to resume: start one (s)")
        return self.scan_id

    def create(self, request: ScanRequest) -> int:
        """Record a new scan for ``request`` (with any calibration already captured); its id.

        Raises:
            InputError: a plan beyond the device's limits, or no cylinder diameter known.
        """
        client = self._device()
        identity = self._check_calibrated_here(client)
        limits = client.info.limits if client.info else {}
        axes = client.info.axes if client.info else {}
        plans = {
            "cylinder": self.cylinder_plan or client.plan_for("cylinder", None),
            "object": client.plan_for("object", request.plan),
        }
        for target, wanted in plans.items():
            check_plan_limits(target, wanted, limits, axes)
        diameter = request.cylinder_mm
        if diameter is None:
            diameter = self.data.cylinder_mm or self._cylinder_mm(None)
        if diameter is None:
            raise InputError(
                "the device does not know its calibration cylinder: pass --cylinder-mm"
            )
        data = self.data
        library = self.library()
        scan_id = library.create_scan(
            request.subject, plans, dict(request.options), data.device, identity, request.side
        )
        if data.grid_image is not None and data.board is not None:
            library.save_calibration(scan_id, data.grid_image, data.board, diameter, identity)
        for seq, segment in self.cylinder_held.items():
            library.add_segment(scan_id, seq, segment, identity)
        self.scan_id, self.identity, self.extract = scan_id, identity, request.extract
        self.cylinder_plan, self.plan, self.held = plans["cylinder"], plans["object"], {}
        data.subject_id, data.segments, data.complete = request.subject, [], False
        self.results = None
        return scan_id

    def resume(self, scan_id: int, extract: ExtractChanges | None = None) -> int:
        """Open library scan ``scan_id`` to fetch what it lacks from the connected device.

        Raises:
            StoreError: the scan was acquired by another device or setup.
            InputError: a stored plan is beyond the device's limits.
        """
        client = self._device()
        identity = client.identity()
        limits = client.info.limits if client.info else {}
        axes = client.info.axes if client.info else {}
        library = self.library()
        library.check_identity(scan_id, identity)
        record = library.scan(scan_id)
        for target, stored in record.plans.items():
            try:
                check_plan_limits(target, stored, limits, axes)
            except InputError as exc:
                # Resuming again cannot help: say so rather than advise it once more.
                raise InputError(
                    f"scan {scan_id} cannot be finished on this device: {exc}"
                ) from None
        self._load(library, scan_id)
        self.identity, self.extract = identity, extract
        return scan_id

    def _load(self, library: Library, scan_id: int) -> ScanData:
        """Take library scan ``scan_id`` as this job's scan (calibration, views, subject)."""
        record = library.scan(scan_id)
        calibration = library.calibration(scan_id)
        self.scan_id, self.results = scan_id, None
        self.plan, self.cylinder_plan = record.plans.get("object"), record.plans.get("cylinder")
        self.held = self._held(library, scan_id, "object")
        self.cylinder_held = self._held(library, scan_id, "cylinder")
        self.identity = record.identity or None
        self.data = ScanData(
            calibration.grid_image if calibration else None,
            calibration.board if calibration else None,
            [self.cylinder_held[k] for k in sorted(self.cylinder_held)],
            calibration.cylinder_mm if calibration else None,
            [self.held[k] for k in sorted(self.held)],
            record.subject,
            {k: str(v) for k, v in record.device.items()},
            self.plan is not None and len(self.held) == len(self.plan.views),
        )
        return self.data

    @staticmethod
    def _held(library: Library, scan_id: int, target: str) -> dict[int, Segment]:
        return library.held_segments(scan_id, target)

    def open_scan(self, scan_id: int) -> ScanData:
        """Load a library scan so it can be processed again, exported or resumed."""
        library = self.library()
        if library.calibration(scan_id) is None:
            raise InputError(f"scan {scan_id} has no calibration stored; it cannot be processed")
        return self._load(library, scan_id)

    @property
    def resumable(self) -> bool:
        """Return True when a started object scan still misses views."""
        return self.plan is not None and not self.data.complete

    # -- acquisition ------------------------------------------------------------------

    def _run_views(
        self,
        target: str,
        plan: ScanPlan,
        held: dict[int, Segment],
        store: bool,
        on_segment: SegmentHandler | None,
        on_progress: ProgressHandler | None,
        on_notice: NoticeHandler | None,
    ) -> list[Segment]:
        """Fetch the views of ``plan`` not in ``held``; keep each arrival in ``held``.

        ``held`` maps plan index to segment and survives an abort or a broken link, so the
        same call with the same ``held`` resumes the scan where it stopped. With ``store``
        each view is committed to the open scan before the link acknowledges it.
        """
        if len(held) >= len(plan.views):
            return [held[k] for k in sorted(held)]
        start, first = time.monotonic(), len(held)
        scan_id, identity = self.scan_id, self.identity
        library = self.library() if store else None

        def report(section: int, starting: bool = False) -> None:
            if on_progress is not None:
                elapsed, done = time.monotonic() - start, len(held)
                total = len(plan.views)
                on_progress(Progress(target, done, total, section, elapsed, done - first, starting))

        def take(seq: int, segment: Segment) -> None:
            if library is not None and scan_id is not None:
                library.add_segment(scan_id, seq, segment, identity)
            held[seq] = segment
            self.latest_segment = segment
            if on_segment is not None:
                on_segment(segment)

        def progress(body: dict[str, Any]) -> None:
            if body.get("event") == "progress":
                report(int(body.get("section", 0)))

        if first:
            # A resumed run: say how many views are held, and where it goes on.
            missing = min(k for k in range(len(plan.views)) if k not in held)
            report(plan.views[missing].section, starting=True)
        extra: dict[str, Any] = {} if self.extract is None else {"extract": self.extract}
        if self.colour and target == "object":  # the cylinder needs no colour
            extra["colour"] = True
        with self._link() as client:
            client.scan(
                target,
                plan,
                progress,
                have=tuple(held),
                on_segment=take,
                on_notice=on_notice,
                **extra,
            )
        return [held[k] for k in sorted(held)]

    def fetch_cylinder(
        self, on_progress: ProgressHandler | None = None, on_notice: NoticeHandler | None = None
    ) -> list[Segment]:
        """Fetch the open scan's calibration-cylinder views it lacks, storing each."""
        self.require_scan()
        plan = self.cylinder_plan or self._device().plan_for("cylinder", None)
        self.cylinder_plan = plan
        with self._busy():
            try:
                self._run_views(
                    "cylinder", plan, self.cylinder_held, True, None, on_progress, on_notice
                )
            finally:
                self.data.cylinder = [self.cylinder_held[k] for k in sorted(self.cylinder_held)]
        return self.data.cylinder

    def fetch_object(
        self,
        on_segment: SegmentHandler | None = None,
        on_progress: ProgressHandler | None = None,
        on_notice: NoticeHandler | None = None,
    ) -> list[Segment]:
        """Fetch the open scan's object views it lacks, storing each; mark it acquired."""
        scan_id = self.require_scan()
        if self.plan is None:
            raise InputError("no scan to resume: start one (s)")
        plan = self.plan
        identity = self._device().identity()
        library = self.library()
        # Before anything changes: a scan is only ever continued by what began it.
        library.check_identity(scan_id, identity)
        info = self.info
        limits, axes = (info.limits, info.axes) if info else ({}, {})
        check_plan_limits("object", plan, limits, axes)
        self.identity = identity
        self.data.complete = False
        self.results = None
        with self._busy():
            try:
                self._run_views("object", plan, self.held, True, on_segment, on_progress, on_notice)
            finally:
                self.data.segments = [self.held[k] for k in sorted(self.held)]
        self.library().set_status(scan_id, "acquired")
        self.data.complete = True
        return self.data.segments

    def section_points(self, segments: list[Segment]) -> np.ndarray:
        """Return the object-frame points (mm) of one section's views so far.

        The same assembly as the final result (:func:`lamina_host.reconstruct.pipeline.assemble`,
        with the turntable's angle correction); (0, 2) before calibration.
        """
        if self.grid is None or self.axis is None or not segments:
            return np.empty((0, 2))
        by_section, _, _ = assemble(segments, self.grid, self.axis, TRIM_FRACTION)
        parts = [p for k in sorted(by_section) for p in by_section[k]]
        return np.vstack(parts) if parts else np.empty((0, 2))

    # -- results ----------------------------------------------------------------------

    def process_scan(
        self,
        options: ProcessOptions | None = None,
        expect: Expectation | None = None,
        timings_s: Mapping[str, float] | None = None,
        out: Path | None = None,
    ) -> Results:
        """Reconstruct the scan held in :attr:`data`, store the result and return it.

        The outputs are written to ``out`` when given, else only into the library.
        """
        data = self.data
        if data.grid_image is None or data.board is None or data.cylinder_mm is None:
            raise InputError("nothing to process: calibrate and scan, or open a saved scan")
        if not data.segments:
            raise InputError("nothing to process: scan the subject first (F5)")
        options = options or ProcessOptions()
        try:
            result = reconstruct(
                data.grid_image, data.board, data.cylinder, data.cylinder_mm, data.segments,
                options,
            )  # fmt: skip
        except Exception as exc:  # the acquisition must outlive any failure of processing
            if self.scan_id is None:
                raise
            why = str(exc) if isinstance(exc, LaminaError) else (
                f"internal error ({type(exc).__name__}: {exc}); please report it"
            )  # fmt: skip
            raise ProcessingError(
                f"processing failed: {why}; {process_again_hint(self.scan_id)}"
            ) from exc
        rows = section_rows(result)
        device = report_device(data.device, self.identity)
        report = build_report(result, device, data.segments, expect, dict(timings_s or {}))
        report["subject_id"] = data.subject_id
        report["volume_mm3"] = volume_mm3(rows)
        paths: dict[str, Any] = {}
        if self.scan_id is not None or out is not None:
            with tempfile.TemporaryDirectory() as tmp:
                paths = write_outputs(out or Path(tmp), result, report)
                if self.scan_id is not None:
                    self.library().save_result(self.scan_id, report, paths)
            if out is None:
                paths = {}
        self.results = Results(result, rows, report["volume_mm3"], report, options.mesh, paths)
        return self.results

    def process_stored(
        self,
        scan_id: int,
        options: ProcessOptions | None = None,
        expect: Expectation | None = None,
        out: Path | None = None,
    ) -> Results:
        """Process library scan ``scan_id`` again (acquired or processed) and store the result.

        The stored calibration and views are reconstructed with this version's pipeline
        and ``options`` (None: the defaults); the new result replaces any earlier one.

        Raises:
            InputError: the scan lacks its calibration or is not fully acquired.
            ProcessingError: the processing failed (the scan is kept as it was).
        """
        if self.library().scan(scan_id).status == "acquiring":
            raise InputError(
                f"scan {scan_id} is not fully acquired: finish it with lamina scan --resume "
                f"{scan_id} --device DEVICE (or resume it on the terminal UI's Scan screen)"
            )
        data = self.open_scan(scan_id)
        if not data.complete:
            raise InputError(
                f"scan {scan_id} is not fully acquired ({len(data.segments)} views held): "
                f"finish it with lamina scan --resume {scan_id} --device DEVICE"
            )
        return self.process_scan(options, expect, None, out)

    def export(self, folder: Path) -> list[Path]:
        """Export the current scan's mesh (PLY, OBJ, STL) and report into a new folder."""
        if self.results is None or self.scan_id is None:
            raise InputError("process the scan first (p on the Results screen)")
        return self.export_scan(self.scan_id, folder)

    def export_scan(self, scan_id: int, folder: Path) -> list[Path]:
        """Export a processed library scan into ``folder`` (new or empty)."""
        if folder.exists() and (not folder.is_dir() or any(folder.iterdir())):
            raise InputError(f"{folder} is not an empty folder; choose a new one")
        folder.mkdir(parents=True, exist_ok=True, mode=PRIVATE_FOLDER)
        library = self.library()
        return [library.export(scan_id, folder / name) for name in EXPORT_NAMES]

    def scans(self) -> list[ScanSummary]:
        """Return the library's scans, oldest first."""
        return self.library().scans()

    def delete_scan(self, scan_id: int) -> None:
        """Delete a scan from the library (forgetting it here too if it is open)."""
        self.library().delete_scan(scan_id)
        if self.scan_id == scan_id:
            self.scan_id, self.results, self.plan, self.held = None, None, None, {}
            self.data = ScanData()


@dataclass
class Acquired:
    """What :func:`acquire` leaves: the scan's id and the acquisition's timings."""

    scan_id: int
    timings_s: dict[str, float]


def acquire(
    job: ScanJob,
    request: ScanRequest | None,
    resume_id: int | None = None,
    out: Path | None = None,
    on_progress: ProgressHandler | None = None,
    on_notice: NoticeHandler | None = None,
    on_opened: Callable[[int], object] | None = None,
) -> Acquired:
    """Run the whole acquisition on a connected job: create (or resume) the scan, fetch it.

    ``out``, when given, receives the calibration image and the segments received, also
    when acquisition stops early. ``on_opened`` hears the scan's id once it exists.
    """
    if resume_id is not None:
        job.resume(resume_id, request.extract if request else None)
    elif request is not None:
        job.create(request)
    else:
        raise InputError("name a scan to resume or what to scan")
    scan_id = job.require_scan()
    if on_opened is not None:
        on_opened(scan_id)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    data = job.fetch_calibration(request.cylinder_mm if request else None)
    if out is not None:
        replace_file(out / "calibration-grid.png", lambda path: _write_image(path, data))
    try:
        job.fetch_cylinder(on_progress, on_notice)
        timings["acquire_calibration"] = time.perf_counter() - start
        start = time.perf_counter()
        job.fetch_object(None, on_progress, on_notice)
        timings["acquire_object"] = time.perf_counter() - start
    except BaseException:
        if out is not None:
            # What arrived is kept in the output folder too, also when the scan stops here;
            # if that fails as well (the same full disk), the first error is the one told.
            with suppress(OutputError):
                _save_arrived(out, job)
        raise
    if out is not None:
        _save_arrived(out, job)
    return Acquired(scan_id, timings)


def _save_arrived(out: Path, job: ScanJob) -> None:
    """Write the segments received so far into the output folder."""
    save_segments(out / "cylinder-segments.npz", job.data.cylinder)
    save_segments(out / "segments.npz", job.data.segments)


def _write_image(path: Path, data: ScanData) -> None:
    """Write the calibration image as PNG through Python's own file API.

    ``cv2.imwrite`` takes the path as text: one that is not UTF-8 (surrogate-escaped
    bytes) crashed the process inside OpenCV. Encoding in memory leaves the path to
    Python, which takes any bytes the file system does.
    """
    ok, png = (False, None) if data.grid_image is None else cv2.imencode(".png", data.grid_image)
    if not ok or png is None:
        raise OutputError(f"the calibration image could not be written to {path}")
    path.write_bytes(png.tobytes())
