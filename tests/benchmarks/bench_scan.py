"""End-to-end accuracy: the simulated 19.05 mm cylinder scanned through the real link."""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

TITLE = "simulated 19.05 mm cylinder, 4 sections x 8 views, thesis-like noise"


def run() -> dict[str, Any]:
    """Scan the simulated cylinder end to end and read its accuracy report."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "scan"
        start = time.perf_counter()
        command = [
            sys.executable, "-m", "lamina_host", "scan", "--device", "sim", "-o", str(out),
            "--object", "cylinder:d=19.05", "--sections", "4", "--pitch", "2", "--views", "8",
            "--expect", "cylinder:d=19.05", "--library", str(Path(tmp) / "library.sqlite"),
        ]  # fmt: skip
        subprocess.run(command, check=True, capture_output=True)
        wall_s = time.perf_counter() - start
        scan_report = json.loads((out / "report.json").read_text())
    accuracy = scan_report["accuracy"]
    return {
        "wall_s": wall_s,
        "rms_mean_centroid_mm": [r["rms_mean_mm"] for r in accuracy["rows"]],
        "rms_own_centroid_mm": [r["rms_own_mm"] for r in accuracy["rows"]],
        "mean_rms_mean_centroid_mm": accuracy["mean_mean_mm"],
        "calibration_rms_mm": scan_report["calibration"]["rms_mm"],
        "correction_factor": scan_report["correction_factor"],
        "timings_s": scan_report["timings_s"],
    }


def report(results: dict[str, Any]) -> list[str]:
    """Return the summary lines."""
    per_section = ", ".join(f"{v:.4f}" for v in results["rms_mean_centroid_mm"])
    return [
        f"  RMS radial error about the mean centroid per section (mm): {per_section}",
        f"  mean {results['mean_rms_mean_centroid_mm']:.4f} mm (thesis 0.1354 mm); "
        f"calibration residual {results['calibration_rms_mm']:.4f} mm; "
        f"scan wall time {results['wall_s']:.1f} s",
    ]
