"""Nothing lost, doubled or altered between the device and the library, whatever the line does.

Full simulated scans (calibration image, cylinder, object: the device's default plans)
run through a pseudo-terminal line that flips, drops, duplicates and delays bytes and
is cut three times; the stored result must equal a clean-link scan bit for bit. The
time overhead is measured by ``tests/benchmarks/bench_link.py``, not here.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from lamina_device.sim.backend import DEFAULT_CYLINDER_PLAN
from lamina_host.link.client import DeviceClient
from lamina_host.link.connect import open_device
from lamina_host.store.library import Library
from lamina_host.testing import LineFaults
from lamina_host.workflow.job import DeviceTarget, ScanJob, ScanRequest, acquire
from lamina_shared.types import Segment
from tests.helpers.library import held_segments


@dataclass
class Stored:
    grid: np.ndarray
    cylinder: list[Segment]
    segments: list[Segment]


def _acquire(client: DeviceClient, library: Library, out: Path) -> int:
    """Run the workflow's acquisition (create, calibration, cylinder, object) on ``client``."""
    job = ScanJob(DeviceTarget("sim"), library=library)
    job.attach_for_testing(client)
    return acquire(job, ScanRequest("T-01"), out=out).scan_id


def scan_into_library(library: Library, out: Path, faults: LineFaults | None) -> int:
    """Run the CLI's acquisition (store, acknowledge) over a possibly faulty line."""
    with open_device("sim", transform=faults) as client:
        scan_id = _acquire(client, library, out)
    return scan_id


def stored(library: Library, scan_id: int) -> Stored:
    calibration = library.calibration(scan_id)
    assert calibration is not None
    return Stored(
        calibration.grid_image,
        library.segments(scan_id, "cylinder"),
        library.segments(scan_id, "object"),
    )


def identical(a: list[Segment], b: list[Segment]) -> bool:
    return len(a) == len(b) and all(x.same_as(y) for x, y in zip(a, b, strict=True))


@pytest.fixture(scope="module")
def clean(tmp_path_factory) -> Stored:
    tmp = tmp_path_factory.mktemp("clean")
    with Library(tmp / "library.sqlite") as library:
        scan_id = scan_into_library(library, tmp, None)
        result = stored(library, scan_id)
    assert len(result.segments) == 32 and len(result.cylinder) == len(DEFAULT_CYLINDER_PLAN.views)
    return result


@pytest.mark.parametrize("error_rate", [1e-4, 1e-3])
def test_faulty_line_with_three_cuts_stores_exactly_the_clean_scan(clean, tmp_path, error_rate):
    kinds = ("flipped", "dropped", "duplicated")
    # Which bytes meet a fault depends on how the line's reads split them in time (bytes
    # lost in a cut draw nothing), so at 1e-4 a run may see no byte of one kind: such a
    # run is checked all the same, and the line is tried again with the next seed.
    for seed in (7, 8, 9):
        faults = LineFaults(
            error_rate=error_rate,
            delay_rate=0.02,
            delay_s=0.02,
            cut_after_bytes=(50_000, 175_000, 190_000),
            cut_s=1.0,
            seed=seed,
        )
        folder = tmp_path / f"seed{seed}"
        folder.mkdir()
        with Library(folder / "library.sqlite") as library:
            scan_id = scan_into_library(library, folder, faults)
            got = stored(library, scan_id)
            # Primary keys make a doubled segment impossible; count what the table holds too.
            assert library.missing(scan_id, "object") == []
        assert faults.counts["cuts"] == 3
        assert np.array_equal(got.grid, clean.grid)
        assert identical(got.cylinder, clean.cylinder)
        assert identical(got.segments, clean.segments)
        if all(faults.counts[k] > 0 for k in kinds):
            break
    assert all(faults.counts[k] > 0 for k in kinds), faults.counts


def test_three_byte_errors_in_a_thousand_and_three_2s_cuts_store_exactly_the_clean_scan(
    clean, tmp_path
):
    """Issue 14: flip, drop and duplicate at 1e-3 each from the first byte (the handshake
    too), and the line dead for 2 s three times; the stored scan equals the clean one."""
    faults = LineFaults(
        error_rate=3e-3, cut_after_bytes=(50_000, 175_000, 190_000), cut_s=2.0, seed=14
    )
    with Library(tmp_path / "library.sqlite") as library:
        with open_device("sim", transform=faults) as client:
            scan_id = _acquire(client, library, tmp_path)
            sizer = client.channel.sizer
        got = stored(library, scan_id)
        assert library.missing(scan_id, "object") == []
    assert faults.counts["cuts"] == 3
    assert min(faults.counts[k] for k in ("flipped", "dropped", "duplicated")) > 300
    # The host measured the line and sent short frames.
    assert 1e-3 < sizer.error_rate < 1e-2 and sizer.fragment_bytes < 200
    assert np.array_equal(got.grid, clean.grid)
    assert identical(got.cylinder, clean.cylinder)
    assert identical(got.segments, clean.segments)


def test_host_killed_mid_scan_resumes_without_loss(clean, tmp_path):
    library_path = tmp_path / "library.sqlite"
    subject = "Doe-Jane-1970"
    command = [
        sys.executable, "-m", "lamina_host", "scan", "--device", "sim", "--library",
        str(library_path), "--subject", subject, "-o", str(tmp_path / "out"),
    ]  # fmt: skip
    first = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 120
    while held_segments(library_path) < 6 and time.monotonic() < deadline and first.poll() is None:
        time.sleep(0.05)
    os.kill(first.pid, signal.SIGKILL)
    first.wait()
    first_out = first.stdout.read() + first.stderr.read() if first.stdout and first.stderr else b""
    held = held_segments(library_path)
    assert 6 <= held < 32, held

    resumed = subprocess.run(
        [*command[:5], "sim", "--library", str(library_path), "--resume", "1"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert resumed.returncode == 0, resumed.stderr
    assert f"object: {held} of 32 views already held, fetching {32 - held}" in resumed.stderr
    # Logs name scans by number, never the subject.
    assert subject not in resumed.stdout + resumed.stderr
    assert subject.encode() not in first_out
    with Library(library_path) as library:
        got = stored(library, 1)
        summary = library.scans()[0]
        assert (summary.status, summary.received, summary.has_result) == ("processed", 32, True)
        assert summary.subject == subject
    assert np.array_equal(got.grid, clean.grid)
    assert identical(got.cylinder, clean.cylinder)
    # The views held before the kill are the clean scan's, bit for bit. The simulator ran
    # in the killed host's process: the views fetched on resume were taken by a device
    # started again, its step count from 0, so they stand at other turns of the gear's
    # shortfall (a box's device outlives its host and keeps its count): each is there,
    # labelled as planned, with the stripe it saw.
    assert identical(got.segments[:held], clean.segments[:held])
    labels = [(s.section, s.view, s.z_mm, s.angle_deg) for s in got.segments]
    assert labels == [(s.section, s.view, s.z_mm, s.angle_deg) for s in clean.segments]
    for fetched, planned in zip(got.segments[held:], clean.segments[held:], strict=True):
        assert abs(len(fetched) - len(planned)) <= 0.1 * len(planned)
    assert (tmp_path / "out" / "mesh.ply").exists()
