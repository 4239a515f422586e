"""The scan job's parts share one scan: a new or deleted scan leaves no stale result behind."""

from __future__ import annotations

from pathlib import Path

import pytest

from lamina_host.workflow.job import DeviceTarget, ScanJob, ScanRequest
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
