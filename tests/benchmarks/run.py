"""``make bench``: speed and accuracy figures, printed as a table and saved as JSON.

Figures come from here, never from timed tests. Run with ``python tests/benchmarks/run.py
--out out/bench.json``.
"""

from __future__ import annotations

import argparse
import json
import platform
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from lamina_device.extract import extract

RESOLUTIONS = ((640, 480), (1536, 864), (2304, 1296))


def best_time_s(run: Callable[[], object], repeats: int = 7) -> float:
    """Return the fastest of ``repeats`` runs (the least disturbed by the machine)."""
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        times.append(time.perf_counter() - start)
    return min(times)


def stripe_pair(width: int, height: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Return a laser-on/laser-off pair with a wavy Gaussian stripe and sensor noise."""
    rng = np.random.default_rng(seed)
    rows = np.arange(height, dtype=np.float32)[:, None]
    centre = height / 2 + height / 8 * np.sin(np.linspace(0, 6, width, dtype=np.float32))
    ambient = 30 + 40 * np.linspace(0, 1, width, dtype=np.float32)[None, :]
    stripe = 170 * np.exp(-0.5 * ((rows - centre) / 2.0) ** 2)
    noise_on = rng.normal(0, 2, (height, width)).astype(np.float32)
    noise_off = rng.normal(0, 2, (height, width)).astype(np.float32)
    on = np.clip(ambient + stripe + noise_on, 0, 255).astype(np.uint8)
    off = np.clip(ambient + noise_off, 0, 255).astype(np.uint8)
    return on, off


def bench_extraction() -> list[dict[str, Any]]:
    """Time extraction against one plain numpy subtraction of the same two frames."""
    rows = []
    for width, height in RESOLUTIONS:
        on, off = stripe_pair(width, height)
        extract_s = best_time_s(lambda on=on, off=off: extract(on, off))
        subtract_s = best_time_s(lambda on=on, off=off: np.subtract(on, off, dtype=np.int16))
        rows.append(
            {
                "resolution": f"{width}x{height}",
                "extract_ms": 1e3 * extract_s,
                "frames_per_s": 1.0 / extract_s,
                "ratio_to_subtraction": extract_s / subtract_s,
            }
        )
    return rows


def bench_cylinder_scan() -> dict[str, Any]:
    """Scan the simulated 19.05 mm cylinder end to end and read its accuracy report."""
    with tempfile.TemporaryDirectory() as tmp:
        out = Path(tmp) / "scan"
        start = time.perf_counter()
        subprocess.run(
            [
                sys.executable,
                "-m",
                "lamina_host",
                "scan",
                "--device",
                "sim",
                "-o",
                str(out),
                "--object",
                "cylinder:d=19.05",
                "--sections",
                "4",
                "--pitch",
                "2",
                "--views",
                "8",
                "--expect",
                "cylinder:d=19.05",
            ],
            check=True,
            capture_output=True,
        )
        wall_s = time.perf_counter() - start
        report = json.loads((out / "report.json").read_text())
    accuracy = report["accuracy"]
    return {
        "wall_s": wall_s,
        "rms_mean_centroid_mm": [r["rms_mean_mm"] for r in accuracy["rows"]],
        "rms_own_centroid_mm": [r["rms_own_mm"] for r in accuracy["rows"]],
        "mean_rms_mean_centroid_mm": accuracy["mean_mean_mm"],
        "calibration_rms_mm": report["calibration"]["rms_mm"],
        "correction_factor": report["correction_factor"],
        "timings_s": report["timings_s"],
    }


def main() -> int:
    """Run every benchmark, print a table, write the JSON file."""
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--out", type=Path, default=Path("out/bench.json"))
    args = parser.parse_args()
    results: dict[str, Any] = {"machine": platform.platform(), "python": platform.python_version()}
    results["extraction"] = bench_extraction()
    print("extraction (Otsu + centre of gravity, on the machine running this)")
    print("  resolution    ms/frame   frames/s   x one subtraction")
    for row in results["extraction"]:
        print(
            f"  {row['resolution']:>10}  {row['extract_ms']:9.2f}  {row['frames_per_s']:9.1f}"
            f"  {row['ratio_to_subtraction']:10.1f}"
        )
    results["cylinder_scan"] = scan = bench_cylinder_scan()
    print("simulated 19.05 mm cylinder, 4 sections x 8 views, thesis-like noise")
    print(
        "  RMS radial error about the mean centroid per section (mm): "
        + ", ".join(f"{v:.4f}" for v in scan["rms_mean_centroid_mm"])
    )
    print(
        f"  mean {scan['mean_rms_mean_centroid_mm']:.4f} mm (thesis 0.1354 mm); calibration "
        f"residual {scan['calibration_rms_mm']:.4f} mm; scan wall time {scan['wall_s']:.1f} s"
    )
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
