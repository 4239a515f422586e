"""The scan job: connect, calibrate, create or resume a scan, fetch, store, process, export.

The command line runs the whole acquisition at once (:func:`acquire`, then
:meth:`Processing.process_scan`); the terminal UI runs the same steps one key at a time.
Both hand in a typed :class:`ScanRequest` (checked once on construction, the plan against
the device's limits when the scan is created) and get typed results back
(:mod:`lamina_host.workflow.results`). A :class:`ScanJob` is four parts, one per concern:
the device session (:mod:`.device_session`), the acquisition (:mod:`.acquisition`), the
processing (:mod:`.processing`) and the library (:mod:`.library_access`). Every step
blocks (serial I/O, calibration, meshing); the UI calls them from thread workers, one at a
time (a second caller gets :class:`Busy`), except pause, resume and abort, which any
thread may send while a scan runs.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from contextlib import suppress
from dataclasses import dataclass
from pathlib import Path

import cv2

from lamina_host.link.client import DeviceClient
from lamina_host.store.files import OutputError, replace_file
from lamina_host.store.library import Library
from lamina_host.store.outputs import save_segments
from lamina_host.workflow.acquisition import TRIM_FRACTION, Acquisition, ScanRequest
from lamina_host.workflow.device_session import (
    Busy,
    DeviceSession,
    DeviceTarget,
    NoticeHandler,
    ProgressHandler,
    SegmentHandler,
)
from lamina_host.workflow.library_access import EXPORT_NAMES, LibraryAccess
from lamina_host.workflow.processing import Processing, ProcessingError, process_again_hint
from lamina_host.workflow.results import ScanData, device_summary
from lamina_shared.errors import InputError
from lamina_shared.messages import Welcome

__all__ = [
    "EXPORT_NAMES",
    "TRIM_FRACTION",
    "Acquired",
    "Busy",
    "DeviceTarget",
    "NoticeHandler",
    "ProcessingError",
    "ProgressHandler",
    "ScanJob",
    "ScanRequest",
    "SegmentHandler",
    "acquire",
    "process_again_hint",
]


class ScanJob:
    """One device connection and one scan at a time, as four parts that share it.

    :attr:`device` (the connection and its controls), :attr:`acquisition` (calibration,
    the scan and its views), :attr:`processing` (its result) and :attr:`store` (the
    library). The few steps that touch several parts are here. ``process_apart``
    processes scans in a process of their own (:class:`Processing`), for a user interface
    that must stay responsive meanwhile.
    """

    def __init__(
        self,
        target: DeviceTarget,
        library_path: Path | None = None,
        library: Library | None = None,
        process_apart: bool = False,
    ) -> None:
        self.store = LibraryAccess(library_path, library)
        self.device = DeviceSession(target)
        self.acquisition = Acquisition(self.device, self.store, self._forget_results)
        self.processing = Processing(self.acquisition, self.store, process_apart)

    def _forget_results(self) -> None:
        self.processing.forget()

    @property
    def scan_id(self) -> int | None:
        """Return the open scan's id (None before one is created or opened)."""
        return self.acquisition.scan_id

    @property
    def library_path(self) -> Path | None:
        """Return the library's path (None: the default library)."""
        return self.store.path

    def connect(self, device: str | None = None, on_notice: NoticeHandler | None = None) -> Welcome:
        """Connect to DEVICE (port, ``sim`` or ``replay:DIR``; default the target's)."""
        info = self.device.connect(device, on_notice)
        self.acquisition.data.device = device_summary(info)
        return info

    def attach_for_testing(self, client: DeviceClient) -> None:
        """Test hook: use a client already handshaken elsewhere; closing leaves it open."""
        self.device.attach_for_testing(client)
        self.acquisition.data.device = device_summary(client.info)

    def close(self) -> None:
        """Disconnect (stopping a device program this host started) and close the library.

        The job's own library is opened again if a later step needs it.
        """
        self.device.close()
        self.store.close()

    def delete_scan(self, scan_id: int) -> None:
        """Delete a scan from the library (forgetting it here too if it is open)."""
        self.store.library().delete_scan(scan_id)
        self.acquisition.forget_scan(scan_id)


@dataclass(frozen=True)
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
    scan = job.acquisition
    if resume_id is not None:
        scan.resume(resume_id, request.extract if request else None)
    elif request is not None:
        scan.create(request)
    else:
        raise InputError("name a scan to resume or what to scan")
    scan_id = scan.require_scan()
    if on_opened is not None:
        on_opened(scan_id)
    timings: dict[str, float] = {}
    start = time.perf_counter()
    data = scan.fetch_calibration(request.cylinder_mm if request else None)
    if out is not None:
        replace_file(out / "calibration-grid.png", lambda path: _write_image(path, data))
    scan.board_calibration()  # a resumed scan's stored board, checked before any view
    try:
        scan.fetch_cylinder(on_progress, on_notice)
        scan.find_axis()  # so the object's first view is checked against the camera's view
        timings["acquire_calibration"] = time.perf_counter() - start
        start = time.perf_counter()
        scan.fetch_object(None, on_progress, on_notice)
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
    save_segments(out / "cylinder-segments.npz", job.acquisition.data.cylinder)
    save_segments(out / "segments.npz", job.acquisition.data.segments)


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
