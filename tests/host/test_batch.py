"""``lamina batch``: 20+ scans re-measured in parallel match the same scans measured serially.

The cohort is made cheaply from one simulated scan: its calibration and segments are
stored again under 22 subject codes, the object's stripe rows scaled a little more for
each (a slightly different object each time), through the library's own API.
"""

from __future__ import annotations

import csv
import math
import stat
import subprocess
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from lamina_device.sim import parse_object
from lamina_host.clinical.measures import Landmark
from lamina_host.store.library import Library
from lamina_host.workflow.batch import (
    BatchError,
    ClinicalMeasure,
    measure_scan,
    run_batch,
    select_scans,
)

COHORT = 20


def lamina(*args: str) -> subprocess.CompletedProcess[str]:
    """Run ``lamina`` in a fresh process."""
    return subprocess.run(
        [sys.executable, "-m", "lamina_host", *args], capture_output=True, text=True, timeout=900
    )


def copy_scan(source: Library, target: Library, subject: str, scale: float, whole: bool) -> int:
    """Store scan 1 of ``source`` again in ``target`` with the object's rows scaled."""
    record, inputs = source.scan(1), source.inputs(1)
    scan_id = target.create_scan(
        subject, record.plans, record.options, record.device, record.identity
    )
    target.save_calibration(
        scan_id, inputs.grid_image, inputs.board, inputs.cylinder_mm, record.identity
    )
    for seq, segment in enumerate(inputs.cylinder):
        target.add_segment(scan_id, seq, segment, record.identity)
    objects = inputs.segments if whole else inputs.segments[:-2]
    for seq, segment in enumerate(objects):
        rows = (segment.rows * np.float32(scale)).astype(np.float32)
        target.add_segment(scan_id, seq, replace(segment, rows=rows), record.identity)
    return scan_id


@pytest.fixture(scope="module")
def cohort(scanned_library: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A library of 20 complete scans of subjects P000..P019, two Q scans, one incomplete P."""
    path = tmp_path_factory.mktemp("cohort") / "cohort.sqlite"
    with Library(scanned_library) as source, Library(path) as target:
        for k in range(COHORT):
            copy_scan(source, target, f"P{k:03d}", 1.0 + 0.002 * k, whole=True)
        for k in range(2):
            copy_scan(source, target, f"Q{k:03d}", 1.0, whole=True)
        copy_scan(source, target, "P999", 1.0, whole=False)
    return path


def read_table(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as table:
        return list(csv.DictReader(table))


def test_batch_matches_serial_measurements(cohort: Path, tmp_path: Path) -> None:
    out = tmp_path / "table.csv"
    done = lamina(
        "batch", "--library", str(cohort), "--subjects", "P*", "--measure", "-o", str(out),
        "--workers", "2", "--spacing-mm", "2", "--landmark", "bottom",
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert stat.S_IMODE(out.stat().st_mode) == 0o600
    rows = read_table(out)
    with Library(cohort) as library:
        ids = select_scans(library, "P*")
        measure = ClinicalMeasure(2.0, Landmark("bottom"))
        serial = [measure_scan(library.inputs(scan_id), measure) for scan_id in ids]
        truth = parse_object(library.scan(ids[0]).options["object"])
    assert len(ids) == COHORT  # the Q scans and the incomplete P999 are left out
    expected = [{"scan": o.scan_id, "subject": o.subject, **row} for o in serial for row in o.rows]
    assert len(rows) == len(expected) >= 4 * COHORT
    assert {r["subject"] for r in rows} == {f"P{k:03d}" for k in range(COHORT)}
    for got, want in zip(rows, expected, strict=True):
        assert list(got) == list(want)
        for key, value in want.items():
            if isinstance(value, float):
                assert math.isclose(float(got[key]), value, rel_tol=1e-9), key
            else:
                assert got[key] == ("" if value is None else str(value))
    # The clinical table: levels 2 mm apart from the lowest section, each scan's volumes.
    assert [float(r["offset_mm"]) for r in rows if r["subject"] == "P000"] == [0, 2, 4, 6]
    # The unscaled scan's circumferences are the true ellipsoid's (its surface at the level).
    for row in (r for r in rows if r["subject"] == "P000"):
        outline = truth.section_outline(float(row["z_mm"]))[0]
        true_mm = np.linalg.norm(np.roll(outline, -1, axis=0) - outline, axis=1).sum()
        assert float(row["circumference_mm"]) == pytest.approx(true_mm, abs=0.1)
    # The scans really differ: the scaled rows give growing outlines.
    first = [float(r["circumference_mm"]) for r in rows if r["level"] == "0"]
    assert len(first) == COHORT and first[-1] > first[0] * 1.01
    volumes = [float(r["volume_ml"]) for r in rows if r["level"] == "0"]
    assert all(
        math.isclose(v, m, rel_tol=0.01)
        for v, m in zip(
            volumes, [float(r["mesh_volume_ml"]) for r in rows if r["level"] == "0"], strict=True
        )
    )


def test_batch_on_a_distributed_cluster_gives_the_same_rows(cohort: Path) -> None:
    distributed = pytest.importorskip("distributed", reason="dask.distributed is not installed")
    with Library(cohort) as library:
        ids = select_scans(library, "P00[0-3]")
        serial = [measure_scan(library.inputs(scan_id)) for scan_id in ids]
        with distributed.LocalCluster(
            n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
        ) as cluster:
            outcomes = run_batch(library, ids, address=cluster.scheduler_address)
    assert [o.scan_id for o in outcomes] == ids and len(ids) == 4
    for got, want in zip(outcomes, serial, strict=True):
        assert got.error is None and len(got.rows) == len(want.rows)
        for a, b in zip(got.rows, want.rows, strict=True):
            assert a.keys() == b.keys()
            for k in a:
                if isinstance(b[k], float):
                    assert math.isclose(a[k], b[k], rel_tol=1e-9), k
                else:
                    assert a[k] == b[k], k


def test_select_refuses_bad_patterns_and_empty_matches(cohort: Path) -> None:
    with Library(cohort) as library:
        for pattern in ("", "P[0", "P 1", "P/*", "x" * 65):
            with pytest.raises(BatchError, match="not usable"):
                select_scans(library, pattern)
        with pytest.raises(BatchError, match="no complete scan"):
            select_scans(library, "Z*")
        with pytest.raises(BatchError, match="1 incomplete"):
            select_scans(library, "P999")


def test_cli_refuses_bad_batch_requests_in_one_line(cohort: Path, tmp_path: Path) -> None:
    existing = tmp_path / "old.csv"
    existing.write_text("earlier")
    base = ("batch", "--library", str(cohort), "--measure")
    cases = [
        (("--subjects", "Z*", "-o", str(tmp_path / "t.csv")), "no complete scan"),
        (("--subjects", "P[0", "-o", str(tmp_path / "t.csv")), "not usable"),
        (("--subjects", "P*", "-o", str(existing)), "already exists"),
        (("--subjects", "P*", "-o", str(tmp_path / "none" / "t.csv")), "does not exist"),
        (("--subjects", "P*", "-o", str(tmp_path / "t.csv"), "--workers", "0"), "--workers"),
        (
            (
                "--subjects",
                "P000",
                "-o",
                str(tmp_path / "t.csv"),
                "--scheduler",
                "tcp://127.0.0.1:9",
            ),
            "dask scheduler",
        ),
    ]
    for args, needle in cases:
        done = lamina(*base, *args)
        assert done.returncode != 0 and done.stdout == ""
        assert done.stderr.count("\n") == 1 and needle in done.stderr, done.stderr
    done = lamina(
        "batch", "--library", str(cohort), "--subjects", "P*", "-o", str(tmp_path / "t.csv")
    )
    assert done.returncode == 2 and "--measure" in done.stderr
    assert existing.read_text() == "earlier" and not (tmp_path / "t.csv").exists()
