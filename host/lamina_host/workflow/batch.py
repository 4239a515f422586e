"""``lamina batch``: reprocess and measure many scans of a library in parallel with Dask.

A study re-measures its scans when the pipeline improves. The parent process selects
the scans (subject codes matching a pattern), reads each one's segments and calibration
from the library (:meth:`Library.inputs`) and hands them to Dask tasks; the tasks
reprocess with the current pipeline (the options each scan's result recorded) and
measure, and return plain rows. Only the parent touches SQLite: workers never open the
library, so the local process scheduler and a dask.distributed cluster run the same
tasks. Scans are submitted in chunks so the parent never holds a whole cohort's
segments at once.

``measure`` is any picklable ``Reconstruction -> rows`` function; the default,
:class:`ClinicalMeasure`, gives the clinical measurements of :mod:`lamina_host.clinical.measures`
(``lamina report``'s table: circumferences at levels from the landmark, segment volumes,
the scan's contour-stack, frustum and mesh volumes), one row per level.
"""

from __future__ import annotations

import csv
import io
import os
import re
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import Executor, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from contextlib import contextmanager
from dataclasses import dataclass, field
from fnmatch import fnmatchcase
from pathlib import Path
from typing import Any

import dask

from lamina_host.clinical.measures import (
    AXES,
    DEFAULT_SPACING_MM,
    Landmark,
    measure_limb,
    sections_from_reconstruction,
)
from lamina_host.reconstruct.mesh import signed_volume
from lamina_host.reconstruct.pipeline import ProcessOptions, Reconstruction, reconstruct
from lamina_host.reconstruct.workers import usable_cores, worker_context
from lamina_host.store.files import OutputError, write_new_file
from lamina_host.store.library import Library, ScanInputs, StoreError, check_new_file
from lamina_shared.errors import LaminaError

Row = dict[str, Any]
Measure = Callable[[Reconstruction], list[Row]]
"""Measurements of one reconstructed scan: one dict per table row (same keys each row)."""

PATTERN_CHARS = re.compile(r"[A-Za-z0-9._\-*?\[\]!]{1,64}")
"""A subject pattern: subject-code characters and the shell wildcards * ? [...] [!...]."""

CHUNK_PER_WORKER = 4
"""Scans held in the parent per worker at a time (bounds its memory on a large cohort)."""


class BatchError(LaminaError):
    """The batch cannot run as asked; the message says why and what to do."""


@dataclass(frozen=True)
class ScanOutcome:
    """One scan's rows, or why it could not be measured."""

    scan_id: int
    subject: str
    rows: list[Row] = field(default_factory=list)
    error: str | None = None


@dataclass(frozen=True)
class ClinicalMeasure:
    """The clinical measurements of a reconstructed limb as table rows (picklable).

    One row per level: its distance from the landmark, height, circumference, area, the
    segment volumes up to the next level and whether it rests on measured outlines; each
    row also carries the scan's volumes (mL) so one table holds the whole cohort.
    """

    spacing_mm: float = DEFAULT_SPACING_MM
    landmark: Landmark = field(default_factory=Landmark)
    axis: str = AXES[0]

    def __call__(self, result: Reconstruction) -> list[Row]:
        """Measure ``result`` (ClinicalError, one line, when it cannot be)."""
        m = measure_limb(
            sections_from_reconstruction(result), self.spacing_mm, self.landmark, self.axis
        )
        mesh_ml = (
            signed_volume(result.vertices, result.faces) / 1000.0
            if len(result.faces)
            else float("nan")
        )
        scan = {
            "range_lo_mm": m.coverage_mm[0],
            "range_hi_mm": m.coverage_mm[1],
            "volume_ml": m.volume_mm3 / 1000.0,
            "frustum_volume_ml": m.frustum_volume_mm3 / 1000.0,
            "mesh_volume_ml": mesh_ml,
        }
        return [
            {"level": k, **{key: row[key] for key in LEVEL_COLUMNS}, **scan}
            for k, row in enumerate(m.table())
        ]


LEVEL_COLUMNS = ("offset_mm", "z_mm", "circumference_mm", "area_mm2", "segment_volume_ml",
                 "segment_frustum_ml", "source", "axis", "axis_tilt_deg")  # fmt: skip
"""The columns of a clinical table row (``LimbMeasurement.table``) the batch keeps."""


def reprocess(inputs: ScanInputs, options: ProcessOptions | None = None) -> Reconstruction:
    """Reconstruct a stored scan again; ``options`` None: those its stored result recorded."""
    chosen = options or ProcessOptions.from_dict(inputs.options)
    return reconstruct(
        inputs.grid_image,
        inputs.board,
        inputs.cylinder,
        inputs.cylinder_mm,
        inputs.segments,
        chosen,
        inputs.lift_reference,
        row_turn_deg=inputs.row_turn_deg,
        laser_off_turn_later=inputs.laser_off_turn_later,
    )


def measure_scan(
    inputs: ScanInputs,
    measure: Measure = ClinicalMeasure(),
    options: ProcessOptions | None = None,
) -> ScanOutcome:
    """Reprocess one scan and measure it (runs in a worker; touches no file).

    ``options`` None reprocesses with the options the scan's result recorded.
    """
    try:
        result = reprocess(inputs, options)
        return ScanOutcome(inputs.scan_id, inputs.subject, measure(result))
    except (LaminaError, ValueError) as exc:
        return ScanOutcome(inputs.scan_id, inputs.subject, error=str(exc))


def check_pattern(pattern: str) -> str:
    """Return ``pattern`` if it is a usable subject pattern, else raise BatchError (one line)."""
    if PATTERN_CHARS.fullmatch(pattern) is None or pattern.count("[") != pattern.count("]"):
        raise BatchError(
            f"subject pattern {pattern[:40]!r} is not usable: give subject-code characters "
            "with the wildcards * ? and [...], e.g. 'P0*' or 'P00[1-5]-left'"
        )
    return pattern


def select_scans(library: Library, pattern: str) -> list[int]:
    """Return the ids of the library's fully acquired scans whose subject matches ``pattern``.

    Raises:
        BatchError: a bad pattern, or no complete scan matches it.
    """
    check_pattern(pattern)
    summaries = [s for s in library.scans() if fnmatchcase(s.subject, pattern)]
    complete = [s.id for s in summaries if s.views and s.received == s.views]
    if not complete:
        held = f" ({len(summaries)} incomplete)" if summaries else ""
        raise BatchError(
            f"no complete scan in {library.path} has a subject matching {pattern!r}{held}: "
            "see lamina scans"
        )
    return complete


def _chunks(ids: Sequence[int], size: int) -> Iterator[Sequence[int]]:
    for start in range(0, len(ids), size):
        yield ids[start : start + size]


def _inputs(library: Library, scan_id: int) -> ScanInputs | ScanOutcome:
    """Return a scan's inputs, or its outcome if the library cannot give them."""
    try:
        return library.inputs(scan_id)
    except StoreError as exc:
        return ScanOutcome(scan_id, library.scan(scan_id).subject, error=str(exc))


@contextmanager
def _scheduler(workers: int, address: str | None) -> Iterator[dict[str, Any]]:
    """Yield the ``dask.compute`` keywords of the chosen scheduler, set up for the batch.

    A process pool is created once for the whole batch; ``address`` connects to a
    dask.distributed scheduler instead.
    """
    if address is not None:
        with _client(address) as client:
            yield {"scheduler": client}
        return
    if workers == 1:
        yield {"scheduler": "synchronous"}
        return
    pool: Executor = ProcessPoolExecutor(workers, mp_context=worker_context())
    with pool:
        yield {"scheduler": "processes", "pool": pool, "num_workers": workers}


@contextmanager
def _client(address: str) -> Iterator[Any]:
    """Connect to the dask.distributed scheduler at ``address`` (BatchError if it cannot)."""
    try:
        from distributed import Client  # deferred: an optional extra
    except ImportError:
        raise BatchError(
            "--scheduler needs dask.distributed: pip install 'lamina-host[distributed]'"
        ) from None
    try:
        client = Client(address, timeout="10s", set_as_default=False)
    except (OSError, TimeoutError, ValueError, TypeError) as exc:
        raise BatchError(
            f"cannot reach a dask scheduler at {address} ({exc.__class__.__name__}): "
            "check the address, e.g. tcp://host:8786, and that the scheduler runs"
        ) from None
    try:
        yield client
    finally:
        client.close()


def run_batch(
    library: Library,
    scan_ids: Sequence[int],
    measure: Measure = ClinicalMeasure(),
    workers: int | None = None,
    address: str | None = None,
    options: ProcessOptions | None = None,
) -> list[ScanOutcome]:
    """Reprocess and measure ``scan_ids`` in parallel; return their outcomes in that order.

    Args:
        library: read by this (the parent) process only.
        scan_ids: the scans to measure.
        measure: a picklable function of a reconstruction returning table rows.
        workers: local worker processes (default: the machine's cores; 1 runs serially).
        address: a dask.distributed scheduler address; then ``workers`` is ignored.
        options: processing options for every scan (default: each scan's recorded ones).
    """
    workers = max(1, workers or usable_cores())
    outcomes: list[ScanOutcome] = []
    with _scheduler(workers, address) as keywords:
        for chunk in _chunks(scan_ids, CHUNK_PER_WORKER * workers):
            loaded = [_inputs(library, scan_id) for scan_id in chunk]
            tasks = [
                dask.delayed(measure_scan, pure=False)(item, measure, options)
                for item in loaded
                if isinstance(item, ScanInputs)
            ]
            try:
                done = iter(dask.compute(*tasks, **keywords))
            except (BrokenProcessPool, ImportError, OSError) as exc:
                raise BatchError(
                    f"the batch's workers failed ({exc.__class__.__name__}: {exc}); "
                    "check lamina-host is installed where they run"
                ) from None
            outcomes += [item if isinstance(item, ScanOutcome) else next(done) for item in loaded]
    return outcomes


def check_output(path: Path) -> Path:
    """Refuse (one line) a table path that exists, lies in no folder or cannot be written."""
    try:
        check_new_file(path)
    except StoreError as exc:
        raise OutputError(str(exc)) from None
    if not os.access(path.parent, os.W_OK | os.X_OK):
        raise OutputError(f"cannot write into folder {path.parent}: name a file in another")
    return path


def table_csv(outcomes: Sequence[ScanOutcome]) -> str:
    """Return the measured rows as CSV text: scan and subject, then the measure's columns."""
    columns: dict[str, None] = {"scan": None, "subject": None}
    for outcome in outcomes:
        for row in outcome.rows:
            columns.update(dict.fromkeys(row))
    text = io.StringIO()
    writer = csv.DictWriter(text, list(columns), lineterminator="\n")
    writer.writeheader()
    for outcome in outcomes:
        for row in outcome.rows:
            writer.writerow({"scan": outcome.scan_id, "subject": outcome.subject, **row})
    return text.getvalue()


def write_table(path: Path, outcomes: Sequence[ScanOutcome]) -> Path:
    """Write the table to the new private file ``path`` (never over an existing one)."""
    return write_new_file(path, table_csv(outcomes).encode())
