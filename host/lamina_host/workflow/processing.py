"""Processing a scan: reconstruct it, store and write the result, export it."""

from __future__ import annotations

import tempfile
from collections.abc import Mapping
from functools import partial
from pathlib import Path

from lamina_host.reconstruct.expect import Expectation
from lamina_host.reconstruct.pipeline import ProcessOptions, reconstruct
from lamina_host.reconstruct.workers import call_apart, usable_cores
from lamina_host.store.outputs import build_report, write_outputs
from lamina_host.workflow.acquisition import Acquisition
from lamina_host.workflow.library_access import LibraryAccess
from lamina_host.workflow.results import Results, report_device, section_rows, volume_mm3
from lamina_shared.errors import InputError, LaminaError


class ProcessingError(LaminaError):
    """Processing a scan failed; the scan is kept and the message says how to process it again."""


def process_again_hint(scan_id: int) -> str:
    """Return the advice a failed processing of library scan ``scan_id`` ends with."""
    return (
        f"scan {scan_id} is kept in the library: process it again with lamina process "
        f"{scan_id} [options] (or p on the terminal UI's Library screen)"
    )


class Processing:
    """The processing of the acquisition's scan, and its latest result (:attr:`results`).

    With ``apart`` the reconstruction runs in a process of its own
    (:func:`~lamina_host.reconstruct.workers.call_apart`), as the terminal UI needs: its
    keys are answered from this process, which the processing then leaves free.
    """

    def __init__(self, acquisition: Acquisition, store: LibraryAccess, apart: bool = False) -> None:
        self.acquisition = acquisition
        self.store = store
        self.apart = apart
        self.results: Results | None = None

    def forget(self) -> None:
        """Drop the result: the scan it came from has changed."""
        self.results = None

    def process_scan(
        self,
        options: ProcessOptions | None = None,
        expect: Expectation | None = None,
        timings_s: Mapping[str, float] | None = None,
        out: Path | None = None,
    ) -> Results:
        """Reconstruct the acquisition's scan, store the result and return it.

        The outputs are written to ``out`` when given, else only into the library.
        """
        data = self.acquisition.data
        if data.grid_image is None or data.board is None or data.cylinder_mm is None:
            raise InputError("nothing to process: calibrate and scan, or open a saved scan")
        if not data.segments:
            raise InputError("nothing to process: scan the subject first (F5)")
        options = options or ProcessOptions()
        run = partial(
            reconstruct, data.grid_image, data.board, data.cylinder, data.cylinder_mm,
            data.segments, options, data.lift_reference, row_turn_deg=data.row_turn_deg,
            laser_off_turn_later=data.laser_off_turn_later,
        )  # fmt: skip
        try:
            # Apart, its sections are still shared among the cores, as they are here.
            result = call_apart(run, workers=usable_cores()) if self.apart else run()
        except Exception as exc:  # the acquisition must outlive any failure of processing
            if self.acquisition.scan_id is None:
                raise
            why = str(exc) if isinstance(exc, LaminaError) else (
                f"internal error ({type(exc).__name__}: {exc}); please report it"
            )  # fmt: skip
            raise ProcessingError(
                f"processing failed: {why}; {process_again_hint(self.acquisition.scan_id)}"
            ) from exc
        rows = section_rows(result)
        device = report_device(data.device, self.acquisition.identity)
        report = build_report(
            result, device, data.segments, expect, dict(timings_s or {}), data.subject_id,
            volume_mm3(rows),
        )  # fmt: skip
        paths: dict[str, Path] = {}
        if self.acquisition.scan_id is not None or out is not None:
            with tempfile.TemporaryDirectory() as tmp:
                paths = write_outputs(out or Path(tmp), result, report)
                if self.acquisition.scan_id is not None:
                    self.store.library().save_result(
                        self.acquisition.scan_id, report.to_json(), paths
                    )
            if out is None:
                paths = {}
        self.results = Results(result, rows, report, paths)
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
        if self.store.library().scan(scan_id).status == "acquiring":
            raise InputError(
                f"scan {scan_id} is not fully acquired: finish it with lamina scan --resume "
                f"{scan_id} --device DEVICE (or resume it on the terminal UI's Scan screen)"
            )
        data = self.acquisition.open_scan(scan_id)
        if not data.complete:
            raise InputError(
                f"scan {scan_id} is not fully acquired ({len(data.segments)} views held): "
                f"finish it with lamina scan --resume {scan_id} --device DEVICE"
            )
        return self.process_scan(options, expect, None, out)

    def export(self, folder: Path) -> list[Path]:
        """Export the current scan's mesh (PLY, OBJ, STL) and report into a new folder."""
        scan_id = self.acquisition.scan_id
        if self.results is None or scan_id is None:
            raise InputError("process the scan first (p on the Results screen)")
        return self.store.export_scan(scan_id, folder)
