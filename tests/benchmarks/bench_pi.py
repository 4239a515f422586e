"""Host processing on the box's Pi (issue 14): a 40-section x 8-view limb scan, one thread.

The box alone runs the host on the Pi, whose numerical libraries must not take every
core (the device program and the terminal UI share them). The scan is
``bench_reconstruction``'s synthetic limb-scale one (a tapered, lobed forearm section of
55 mm on the simulated limb rig, known exactly), cut to 40 sections at 2 mm and 8 views.
It is processed (grid calibration, axis, assembly, EFD, contour mesh and its topology:
everything after acquisition), best of 3, in a fresh process whose numerical libraries get
one thread each, set before numpy is imported (``SINGLE_THREADED``, what the host gives a
device program it starts beside itself), and once more with the libraries' own thread
counts for comparison. An x86 core is faster than a Pi 4's Cortex-A72 (roughly 2-4x): read
the one-thread time as a lower bound for the Pi.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

TITLE = "host processing of a 40-section x 8-view limb scan, one thread per library (Pi core)"
SECTIONS, VIEWS, SCALE_MM = 40, 8, 55.0


def _child() -> dict[str, Any]:
    """Process the scan in this process (its thread limits already set); return the figures."""
    import cv2
    from bench_reconstruction import synthetic_scan, timed

    from lamina_device.sim import Rig
    from lamina_host.reconstruct.pipeline import ProcessOptions

    scan = synthetic_scan(Rig.limb(), SCALE_MM, sections=SECTIONS, views=VIEWS)
    row = timed(scan, ProcessOptions(), SCALE_MM)
    row["opencv_threads"] = cv2.getNumThreads()
    row["omp_num_threads"] = os.environ.get("OMP_NUM_THREADS", "unset")
    row.pop("topology", None)
    return row


def _run_child(single_thread: bool) -> dict[str, Any]:
    """Run :func:`_child` in a fresh interpreter, with or without the thread limits."""
    from lamina_host.link.spawn import SINGLE_THREADED

    env = dict(os.environ)
    for name in SINGLE_THREADED:
        env.pop(name, None)
    if single_thread:
        env.update(SINGLE_THREADED)
    here = Path(__file__).resolve().parent  # the benchmarks, and the repository for tests.*
    paths = [str(here), str(here.parents[1]), env.get("PYTHONPATH")]
    env["PYTHONPATH"] = os.pathsep.join(filter(None, paths))
    done = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--child"],
        capture_output=True,
        text=True,
        env=env,
        timeout=1800,
        check=False,
    )
    if done.returncode != 0:
        return {"error": done.stderr.strip().splitlines()[-1] if done.stderr else "failed"}
    return dict(json.loads(done.stdout.strip().splitlines()[-1]))


def run() -> dict[str, Any]:
    """Time the processing with one thread per library, then with the libraries' defaults."""
    return {
        "sections": SECTIONS,
        "views": VIEWS,
        "one thread": _run_child(single_thread=True),
        "default threads": _run_child(single_thread=False),
        "cores": os.cpu_count(),
    }


def report(results: dict[str, Any]) -> list[str]:
    """Return the table lines."""
    lines = ["  threads          points   total s  mean/max RMS mm  opencv threads  stages s"]
    for name in ("one thread", "default threads"):
        row = results[name]
        if "error" in row:
            lines.append(f"  {name:<15} failed: {row['error']}")
            continue
        stages = ", ".join(f"{k} {v:.2f}" for k, v in row["stages_s"].items())
        lines.append(
            f"  {name:<15} {row['points']:>7} {row['total_s']:9.2f}  "
            f"{row['mean_rms_mm']:.4f}/{row['max_rms_mm']:.4f}  {row['opencv_threads']:>14}  "
            f"{stages}"
        )
    lines.append(f"  (this machine: {results['cores']} cores)")
    return lines


if __name__ == "__main__" and sys.argv[1:] == ["--child"]:
    print(json.dumps(_child(), default=float))
