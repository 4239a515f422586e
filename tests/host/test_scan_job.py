"""The scan job's parts share one scan: a new or deleted scan leaves no stale result behind."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from lamina_host.reconstruct.workers import call_apart
from lamina_host.workflow import processing
from lamina_host.workflow.job import DeviceTarget, ScanJob, ScanRequest
from lamina_host.workflow.processing import ProcessingError
from lamina_shared.errors import InputError
from lamina_shared.types import ScanPlan

PLAN = ScanPlan.regular(2, 2.0, 4)
"""Small enough to scan in seconds, enough for a volume (two sections)."""


@pytest.fixture
def job(tmp_path: Path):
    """Return a job connected to the simulated device, its cylinder axis found."""
    job = ScanJob(DeviceTarget("sim"), tmp_path / "library.sqlite")
    try:
        job.connect()
        job.acquisition.calibrate_grid()
        job.acquisition.accept_grid(True)
        job.acquisition.calibrate_axis()
        yield job
    finally:
        job.close()


def _scan(job: ScanJob, subject: str) -> int:
    """Create, fetch and process one scan; return its id."""
    scan_id = job.acquisition.create(ScanRequest(subject, PLAN))
    job.acquisition.fetch_object()
    job.processing.process_scan()
    return scan_id


def test_a_new_scan_forgets_the_last_ones_result(job: ScanJob) -> None:
    # One device, one library, one scan for every part.
    assert job.acquisition.device is job.device and job.processing.acquisition is job.acquisition
    assert job.acquisition.store is job.store is job.processing.store
    assert job.acquisition.data.device["software"]  # what the scan records of the device
    first = _scan(job, "P001")
    results = job.processing.results
    assert results is not None and results.report.subject_id == "P001"
    assert results.volume_mm3 > 0
    second = job.acquisition.create(ScanRequest("P002", PLAN))
    assert second != first and job.scan_id == second
    assert job.processing.results is None  # the result was the first scan's


def test_deleting_the_open_scan_forgets_it_and_its_result(job: ScanJob) -> None:
    scan_id = _scan(job, "P001")
    assert [s.id for s in job.store.scans()] == [scan_id]
    job.delete_scan(scan_id)
    assert job.store.scans() == []
    assert job.scan_id is None and job.processing.results is None
    assert job.acquisition.held == {} and job.acquisition.data.segments == []
    with pytest.raises(InputError, match="nothing to process"):
        job.processing.process_scan()


def test_a_scan_processed_apart_is_the_scan_processed_here(
    job: ScanJob, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The terminal UI's processing runs in a process of its own: the same result bit for
    bit, stored the same way, and a failure still names the command that processes again."""
    scan_id = _scan(job, "P001")
    here = job.processing.results
    assert here is not None
    apart_pids: list[int] = []

    def counted(*args: Any, **kwargs: Any) -> Any:
        apart_pids.append(os.getpid())
        return call_apart(*args, **kwargs)

    monkeypatch.setattr(processing, "call_apart", counted)
    job.processing.apart = True
    apart = job.processing.process_scan()
    assert apart_pids == [os.getpid()]  # one reconstruction, through call_apart
    assert apart.rows == here.rows
    assert apart.volume_mm3 == here.volume_mm3 > 0
    assert apart.reconstruction.warnings == here.reconstruction.warnings
    for name in ("vertices", "faces"):
        assert np.array_equal(
            getattr(apart.reconstruction, name), getattr(here.reconstruction, name)
        )
    assert job.store.library().scan(scan_id).status == "processed"
    job.acquisition.data.cylinder_mm = -1.0  # a calibration processing refuses, over there
    with pytest.raises(ProcessingError, match=f"lamina process {scan_id}"):
        job.processing.process_scan()
