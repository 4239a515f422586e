"""Batch re-measurement speed-up: ``lamina batch`` serial vs the local process scheduler.

The library holds 20 short simulated scans (cylinders and ellipsoids of several sizes,
3 sections x 6 views); it is made once and cached in ``out/bench-batch`` (delete the
folder to remake it). Each run re-measures all of them with one worker (Dask's
synchronous scheduler, in this process) and with one worker process per core, pool start
included, and checks both give the same rows. CPU time and the load average are reported
beside the wall times: on a shared machine the speed-up is bounded by the cores free.
"""

from __future__ import annotations

import os
import resource
import shutil
import subprocess
import time
from pathlib import Path
from typing import Any

from lamina_host.store.library import Library
from lamina_host.workflow.batch import run_batch, select_scans
from tests.helpers.cli import host_command

TITLE = "lamina batch: 20 short simulated scans re-measured, 1 worker vs all cores"
CACHE = Path("out/bench-batch")
SCANS = 20
AT_ONCE = 4
"""Simulated scans made at a time (each mostly waits on its simulated motion)."""


def _objects() -> list[str]:
    cylinders = [f"cylinder:d={d:.1f}" for d in (12.0, 14.0, 16.0, 18.0, 19.05, 20.0, 22.0)]
    ellipsoids = [f"ellipsoid:a={a:.1f},b={0.65 * a:.2f},c=20,z=-1" for a in (8, 9, 10, 11)]
    return (cylinders + ellipsoids) * 2


def _make_library(library: Path) -> None:
    """Scan ``SCANS`` short simulated objects into ``library``, a few at a time."""
    CACHE.mkdir(parents=True, exist_ok=True)
    pending = list(enumerate(_objects()[:SCANS]))
    while pending:
        batch, pending = pending[:AT_ONCE], pending[AT_ONCE:]
        runs = [
            subprocess.Popen(
                host_command(
                    *("scan", "--device", "sim", "--object", spec, "--seed", str(k)),
                    *("--sections", "3", "--pitch", "2", "--views", "6", "--subject", f"B{k:03d}"),
                    *("--library", str(library), "-o", str(CACHE / f"scan{k:02d}")),
                ),
                stdout=subprocess.DEVNULL,
                stderr=subprocess.DEVNULL,
            )
            for k, spec in batch
        ]
        for process in runs:
            if process.wait() != 0:
                raise RuntimeError(f"a simulated scan failed: {process.args}")


def _cpu_s() -> float:
    """Return the CPU time of this process and its ended children (the pool's workers)."""
    own, children = (
        resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)
    )
    return own.ru_utime + own.ru_stime + children.ru_utime + children.ru_stime


def run() -> dict[str, Any]:
    """Time the batch serially and on every core."""
    library_path = CACHE / "library.sqlite"
    done = (CACHE / "complete").exists()
    if not done:
        shutil.rmtree(CACHE, ignore_errors=True)  # a half-made library is made again
        _make_library(library_path)
        (CACHE / "complete").touch()
    cores = os.cpu_count() or 1
    with Library(library_path) as library:
        ids = select_scans(library, "B*")
        times: dict[int, float] = {}
        rows: dict[int, list[Any]] = {}
        cpu: dict[int, float] = {}
        load = os.getloadavg()[0]
        for workers in (1, cores):
            start, used = time.perf_counter(), _cpu_s()
            outcomes = run_batch(library, ids, workers=workers)
            times[workers] = time.perf_counter() - start
            cpu[workers] = _cpu_s() - used
            rows[workers] = [o.rows for o in outcomes]
            assert all(o.error is None for o in outcomes), [o.error for o in outcomes]
    assert rows[1] == rows[cores], "parallel rows differ from serial ones"
    return {
        "scans": len(ids),
        "cores": cores,
        "serial_s": times[1],
        "parallel_s": times[cores],
        "speedup": times[1] / times[cores],
        "serial_cpu_s": cpu[1],
        "parallel_cpu_s": cpu[cores],
        "load_average": load,
        "library_cached": done,
    }


def report(results: dict[str, Any]) -> list[str]:
    """Return the summary lines."""
    return [
        f"  {results['scans']} scans: 1 worker {results['serial_s']:.1f} s, "
        f"{results['cores']} worker processes {results['parallel_s']:.1f} s "
        f"(speed-up {results['speedup']:.2f}x, pool start included)",
        f"  CPU time {results['serial_cpu_s']:.1f} s serial, {results['parallel_cpu_s']:.1f} s "
        f"parallel; machine load average {results['load_average']:.1f} when it started "
        "(a busy machine leaves the workers less than a core each)",
    ]
