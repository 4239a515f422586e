"""The acquisition of a scan: calibration, the scan in the library, and fetching its views.

:class:`Acquisition` holds what the steps produced so far: :attr:`~Acquisition.data` (the
raw scan), :attr:`~Acquisition.grid` and :attr:`~Acquisition.axis` (the calibration shown
before scanning) and :attr:`~Acquisition.held` (the object views received, by plan index).
It talks to the device through a :class:`~lamina_host.workflow.device_session.DeviceSession`
and stores into the job's library (:class:`~lamina_host.workflow.library_access.LibraryAccess`).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from contextlib import suppress
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from lamina_host.link.client import DeviceClient
from lamina_host.link.identity import (
    calibration_mismatch,
    laser_off_turn_later,
    row_turn_deg,
)
from lamina_host.reconstruct.axis import AxisCalibration
from lamina_host.reconstruct.calibration import CalibrationError, GridCalibration, calibrate_grid
from lamina_host.reconstruct.pipeline import (
    ProcessOptions,
    assemble,
    calibrate_axis,
    camera_disc_mm,
    lift_sections,
)
from lamina_host.store.library import SIDES, Library, check_side
from lamina_host.store.subjects import check_subject
from lamina_host.workflow.checks import (
    check_extract_limits,
    check_mode,
    check_next_turn,
    check_object_fits,
    check_plan_limits,
    check_positive_mm,
)
from lamina_host.workflow.device_session import (
    DeviceSession,
    NoticeHandler,
    ProgressHandler,
    SegmentHandler,
    StoreHandler,
)
from lamina_host.workflow.library_access import LibraryAccess
from lamina_host.workflow.results import ScanData
from lamina_shared.errors import InputError
from lamina_shared.ops import ExtractChanges
from lamina_shared.types import (
    SCAN_MODES,
    BoardSpec,
    LiftReference,
    ScanPlan,
    Segment,
    from_first_turn,
)

TRIM_FRACTION = ProcessOptions().trim_fraction
"""The trim of the axis shown during calibration and of the live section plot."""


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
        mode: how the device takes the object's views (``lamina_shared.types.SCAN_MODES``;
            None: as the plan says); stored with the plan, so a resume keeps it.
    """

    subject: str
    plan: ScanPlan | None = None
    cylinder_mm: float | None = None
    options: Mapping[str, Any] = field(default_factory=dict)
    extract: ExtractChanges | None = None
    colour: bool = False
    side: str = SIDES[0]
    mode: str | None = None

    def __post_init__(self) -> None:
        check_subject(self.subject)
        check_side(self.side)
        if self.mode is not None and self.mode not in SCAN_MODES:
            raise InputError(f"scan mode {self.mode!r} is not one of {', '.join(SCAN_MODES)}")
        if self.cylinder_mm is not None:
            check_positive_mm("cylinder diameter", self.cylinder_mm, 1000.0)


class Acquisition:
    """One scan at a time: its calibration, its record in the library and its views.

    ``forget_results`` is called whenever the scan's views change, so no result of
    other views is kept as this scan's.
    """

    def __init__(
        self, device: DeviceSession, store: LibraryAccess, forget_results: Callable[[], None]
    ) -> None:
        self.device = device
        self.store = store
        self._forget_results = forget_results
        self.data = ScanData()
        self.grid: GridCalibration | None = None
        self.grid_accepted = False
        self.axis: AxisCalibration | None = None
        self.plan: ScanPlan | None = None
        self.held: dict[int, Segment] = {}
        self.cylinder_plan: ScanPlan | None = None
        self.cylinder_held: dict[int, Segment] = {}
        self.scan_id: int | None = None
        self.identity: dict[str, Any] | None = None
        """The identity the scan was recorded under (None before one exists)."""
        self.calibrated_by: dict[str, Any] | None = None
        """The identity of the device the chessboard and cylinder were captured with."""

    def _storer(self) -> StoreHandler | None:
        """Return what commits each arriving view to the open scan (None: no scan open)."""
        scan_id, identity = self.scan_id, self.identity
        if scan_id is None:
            return None
        library = self.store.library()
        return lambda seq, segment: library.add_segment(scan_id, seq, segment, identity)

    def forget_scan(self, scan_id: int) -> None:
        """Forget library scan ``scan_id`` if it is the open one (it was deleted)."""
        if self.scan_id == scan_id:
            self.scan_id, self.plan, self.held = None, None, {}
            self.data = ScanData()
            self._forget_results()

    def grab_grid(self) -> tuple[np.ndarray, BoardSpec]:
        """Fetch the calibration image and board from the device."""
        with self.device.busy(), self.device.link() as client:
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

    def board_calibration(self) -> GridCalibration:
        """Return the chessboard calibration the scan uses, finding the board now if needed.

        The terminal UI calibrates and accepts the board first; the command line has it
        found here, before anything is acquired, in the image the scan stores (grabbed from
        the device when the job holds none yet).

        Raises:
            CalibrationError: no chessboard in view (the one line says what to do).
        """
        if self.grid is None or not self.grid_accepted:
            if self.data.grid_image is None or self.data.board is None:
                self.grab_grid()
            assert self.data.grid_image is not None and self.data.board is not None
            self.grid = calibrate_grid(self.data.grid_image, self.data.board)
            self.grid_accepted = True
        return self.grid

    def find_axis(self) -> AxisCalibration | None:
        """Return the turntable axis from the cylinder views held (None if it cannot be found).

        Only what :meth:`fetch_object` needs to check the object's size: processing finds
        the axis again with its own options and says why when it cannot.
        """
        data, grid = self.data, self.grid
        if self.axis is None and grid is not None and data.cylinder and data.cylinder_mm:
            axis_views, _ = lift_sections(from_first_turn(data.cylinder), data.lift_reference)
            with suppress(CalibrationError):
                self.axis = calibrate_axis(axis_views, grid, data.cylinder_mm, TRIM_FRACTION)
        return self.axis

    def _accepted_grid(self) -> GridCalibration:
        if self.grid is None or not self.grid_accepted:
            raise InputError("calibrate and accept the chessboard first (Calibrate screen, F4)")
        return self.grid

    def _check_calibrated_here(self, client: DeviceClient, counts_held: bool) -> dict[str, Any]:
        """Return the device's identity; refuse if the calibration cannot serve it.

        Args:
            client: the connected device.
            counts_held: whether cylinder views held from the calibration are to be used
                (their step counts must be of the device's current run).
        """
        identity = client.identity()
        if self.calibrated_by is not None:
            problem = calibration_mismatch(self.calibrated_by, identity, counts_held)
            if problem is not None:
                raise InputError(problem)
        return identity

    def calibrate_axis(
        self, on_progress: ProgressHandler | None = None, on_segment: SegmentHandler | None = None
    ) -> AxisCalibration:
        """Scan the calibration cylinder afresh and find the turntable axis (shown, not stored)."""
        grid = self._accepted_grid()
        client = self.device.client()
        diameter = client.info.cylinder_diameter_mm if client.info else None
        if diameter is None:
            raise InputError("the device does not report its calibration cylinder's diameter")
        identity = self._check_calibrated_here(client, counts_held=False)
        plan = client.plan_for("cylinder", None)
        held: dict[int, Segment] = {}
        with self.device.busy():
            cylinder = self.device.run_views(
                "cylinder", plan, held, None, on_segment, on_progress, None
            )
        # The views are counted on the device's current run: later scans are checked on it.
        self.cylinder_plan, self.cylinder_held, self.calibrated_by = plan, held, identity
        self.data.cylinder, self.data.cylinder_mm = cylinder, diameter
        axis_views, _ = lift_sections(from_first_turn(cylinder), self._lift_reference())
        self.axis = calibrate_axis(axis_views, grid, diameter, TRIM_FRACTION)
        return self.axis

    def fetch_calibration(self, cylinder_mm: float | None = None) -> ScanData:
        """Give the open scan its calibration: the one stored, else the device's chessboard.

        Raises:
            InputError: no calibration cylinder diameter is known.
        """
        scan_id = self.require_scan()
        library = self.store.library()
        if library.calibration(scan_id) is None:
            image, board = self.grab_grid()
            diameter = self._cylinder_mm(cylinder_mm)
            library.save_calibration(
                scan_id, image, board, diameter, self.identity, self._lift_reference()
            )
        calibration = library.calibration(scan_id)
        assert calibration is not None
        self.data.grid_image, self.data.board = calibration.grid_image, calibration.board
        self.data.lift_reference = calibration.lift_reference
        diameter = calibration.cylinder_mm
        if diameter is None:
            diameter = self._cylinder_mm(cylinder_mm)
        if diameter is None:
            raise InputError(
                "the device does not know its calibration cylinder: pass --cylinder-mm"
            )
        self.data.cylinder_mm = diameter
        return self.data

    def _lift_reference(self) -> LiftReference | None:
        """Return the connected device's lift reference (None: it has none, or is unknown)."""
        return self.device.info.lift_reference if self.device.info else None

    def _cylinder_mm(self, given: float | None) -> float | None:
        """Return the calibration cylinder's diameter: the one given, else the device's."""
        if given is not None:
            return float(given)
        return self.device.info.cylinder_diameter_mm if self.device.info else None

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
        client = self.device.client()
        identity = self._check_calibrated_here(client, counts_held=bool(self.cylinder_held))
        limits = client.info.limits if client.info else None
        axes = client.info.axes if client.info else None
        plans = {
            "cylinder": self.cylinder_plan or client.plan_for("cylinder", None),
            "object": client.plan_for("object", request.plan),
        }
        if request.mode is not None:
            plans["object"] = plans["object"].with_mode(request.mode)
        check_mode(plans["object"], client.info, request.colour)
        check_next_turn(plans["object"], client.info, self.axis)
        check_extract_limits(request.extract, client.info)
        for target, wanted in plans.items():
            check_plan_limits(target, wanted, limits, axes)
        diameter = request.cylinder_mm
        if diameter is None:
            diameter = self.data.cylinder_mm or self._cylinder_mm(None)
        if diameter is None:
            raise InputError(
                "the device does not know its calibration cylinder: pass --cylinder-mm"
            )
        # The board is found before the scan exists: one out of view wastes no acquisition.
        self.board_calibration()
        data = self.data
        library = self.store.library()
        scan_id = library.create_scan(
            request.subject, plans, dict(request.options), data.device, identity, request.side
        )
        if data.grid_image is not None and data.board is not None:
            data.lift_reference = self._lift_reference()
            library.save_calibration(
                scan_id, data.grid_image, data.board, diameter, identity, data.lift_reference
            )
        for seq, segment in self.cylinder_held.items():
            library.add_segment(scan_id, seq, segment, identity)
        self.scan_id, self.identity, self.device.extract = scan_id, identity, request.extract
        self.cylinder_plan, self.plan, self.held = plans["cylinder"], plans["object"], {}
        data.subject_id, data.segments, data.complete = request.subject, [], False
        data.row_turn_deg = row_turn_deg(identity, plans["object"])
        data.laser_off_turn_later = laser_off_turn_later(identity, plans["object"])
        self._forget_results()
        return scan_id

    def resume(self, scan_id: int, extract: ExtractChanges | None = None) -> int:
        """Open library scan ``scan_id`` to fetch what it lacks from the connected device.

        Raises:
            StoreError: the scan was acquired by another device or setup.
            InputError: a stored plan is beyond the device's limits.
        """
        client = self.device.client()
        identity = client.identity()
        limits = client.info.limits if client.info else None
        axes = client.info.axes if client.info else None
        library = self.store.library()
        library.check_identity(scan_id, identity)
        record = library.scan(scan_id)
        for target, stored in record.plans.items():
            try:
                check_mode(stored, client.info)
                check_plan_limits(target, stored, limits, axes)
            except InputError as exc:
                # Resuming again cannot help: say so rather than advise it once more.
                raise InputError(
                    f"scan {scan_id} cannot be finished on this device: {exc}"
                ) from None
        self._load(library, scan_id)
        self.identity, self.device.extract = identity, extract
        return scan_id

    def _load(self, library: Library, scan_id: int) -> ScanData:
        """Take library scan ``scan_id`` as this job's scan (calibration, views, subject)."""
        record = library.scan(scan_id)
        calibration = library.calibration(scan_id)
        self.scan_id = scan_id
        self._forget_results()
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
            calibration.lift_reference if calibration else None,
            row_turn_deg(record.identity, self.plan),
            laser_off_turn_later(record.identity, self.plan),
        )
        return self.data

    @staticmethod
    def _held(library: Library, scan_id: int, target: str) -> dict[int, Segment]:
        return library.held_segments(scan_id, target)

    def open_scan(self, scan_id: int) -> ScanData:
        """Load a library scan so it can be processed again, exported or resumed."""
        library = self.store.library()
        if library.calibration(scan_id) is None:
            raise InputError(f"scan {scan_id} has no calibration stored; it cannot be processed")
        return self._load(library, scan_id)

    @property
    def resumable(self) -> bool:
        """Return True when a started object scan still misses views."""
        return self.plan is not None and not self.data.complete

    def fetch_cylinder(
        self, on_progress: ProgressHandler | None = None, on_notice: NoticeHandler | None = None
    ) -> list[Segment]:
        """Fetch the open scan's calibration-cylinder views it lacks, storing each."""
        self.require_scan()
        plan = self.cylinder_plan or self.device.client().plan_for("cylinder", None)
        self.cylinder_plan = plan
        with self.device.busy():
            try:
                self.device.run_views(
                    "cylinder", plan, self.cylinder_held, self._storer(), None, on_progress,
                    on_notice,
                )  # fmt: skip
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
        identity = self.device.client().identity()
        library = self.store.library()
        # Before anything changes: a scan is only ever continued by what began it.
        library.check_identity(scan_id, identity)
        info = self.device.info
        limits, axes = (info.limits, info.axes) if info else (None, None)
        check_plan_limits("object", plan, limits, axes)
        if plan.continuous:  # the cylinder's views are in by now: its axis judges the gear
            check_next_turn(plan, info, self.find_axis())
        self.identity = identity
        self.data.complete = False
        self._forget_results()
        with self.device.busy():
            try:
                checked = self._fetch_first_view(plan, on_segment, on_progress, on_notice)
                self.device.run_views(
                    "object", plan, self.held, self._storer(), on_segment, on_progress, on_notice,
                    resumed=False if checked else None,
                )  # fmt: skip
            finally:
                self.data.segments = [self.held[k] for k in sorted(self.held)]
        self.store.library().set_status(scan_id, "acquired")
        self.data.complete = True
        return self.data.segments

    def _fetch_first_view(
        self,
        plan: ScanPlan,
        on_segment: SegmentHandler | None,
        on_progress: ProgressHandler | None,
        on_notice: NoticeHandler | None,
    ) -> bool:
        """Fetch the object's first view alone and check the object fits the camera's view.

        Returns True when the view was fetched and checked (nothing is checked when the
        first view is held already, or without the calibration to place it).

        Raises:
            ObjectTooLarge: the view shows an object beyond the camera's view.
        """
        field = self.field_radius_mm()
        if self.held or field is None:
            return False
        self.device.run_views(
            "object", plan, self.held, self._storer(), on_segment, on_progress, on_notice, limit=1
        )
        first = self.held.get(0)
        if first is not None:
            check_object_fits(self.section_points([first]), field)
        return True

    def field_radius_mm(self) -> float | None:
        """Return the radius about the axis the camera sees at every angle (None: unknown).

        Known once the chessboard and the axis are: the image's border mapped into the
        laser plane (:func:`~lamina_host.reconstruct.pipeline.camera_disc_mm`).
        """
        image = self.data.grid_image
        if self.grid is None or self.axis is None or image is None:
            return None
        return camera_disc_mm(self.grid, image.shape, self.axis)

    def section_points(self, segments: list[Segment]) -> np.ndarray:
        """Return the object-frame points (mm) of one section's views so far.

        The same assembly as the final result (:func:`lamina_host.reconstruct.pipeline.assemble`,
        with the turntable's angle correction, turns counted from the first of the
        object's views held); (0, 2) before calibration.
        """
        if self.grid is None or self.axis is None or not segments:
            return np.empty((0, 2))
        held = [*self.held.values(), *self.data.segments, *segments]
        by_section, _, _ = assemble(
            from_first_turn(segments, held), self.grid, self.axis, TRIM_FRACTION
        )
        parts = [p for k in sorted(by_section) for p in by_section[k]]
        return np.vstack(parts) if parts else np.empty((0, 2))
