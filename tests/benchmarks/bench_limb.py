"""Clinical accuracy at limb scale (issue #13 part 5): volume, circumference, surface distance.

Three limb-scale phantoms are scanned end to end on the simulated limb rig (``lamina scan
--device sim --rig limb --noise harsh`` with the default processing, which finds the lens
distortion on the board; the real device process over the real link), 8 views per
section at 10 mm pitch, and measured with ``lamina_host.clinical.measures`` from
the EFD sections stored in report.json (PCHIP along z, the clinical default):

- ``vol %``: the contour-stack volume over the scanned range against the true volume
  over the same range (the true shape's cross-section areas integrated between the true
  heights of the first and last section, 0.5 mm Simpson steps); ``linear %`` is the same
  with the EFD coefficients interpolated linearly (straight joins between sections);
- ``lift %``: the scanned range as the host knows it (the commanded heights times the
  lift's scale it measured on the calibration cylinder's grooves) against the true range:
  what is left of the lift's 0.2 % scale error (``cal %``: the scale error the host
  measured); ``vol - lift %`` is the volume error with that share taken out;
- ``max |dC| mm``: at every level, 20 mm apart from the distal end, the measured
  circumference minus the true outline's perimeter at the level's true height;
- ``surf mm``: mean distance of points.ply (the EFD contours) to the true surface after
  the 3-parameter alignment of ``truth.scan_accuracy`` (``direct``: without it);
- ``mesh-stack %``: the watertight contour mesh's volume against the contour-stack volume.

Targets (issue #13): volume within 0.5 %, circumference within 1 mm at every level, mean
surface distance within 0.08 mm. ``python tests/benchmarks/bench_limb.py --quick`` runs a
smaller set (fewer sections, the stump moved down so its rounded end is still scanned)
that finishes under load; ``--keep DIR`` keeps (and reuses) the scans.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from lamina_device.sim import Mechanics, parse_object
from lamina_device.sim.truth import TrueSurface, align_about_axis
from lamina_host.clinical.measures import measure_limb, sections_from_report
from lamina_host.reconstruct.measure import perimeter, polygon_area
from lamina_host.reconstruct.mesh import load_ply

NOISE = "harsh"
PITCH_MM, VIEWS, SPACING_MM = 10.0, 8, 20.0
TITLE = (
    f"limb-scale phantoms, {VIEWS} views, {PITCH_MM:g} mm pitch, {NOISE} noise: clinical "
    "volume, circumference and surface errors vs truth (targets: <= 0.5 %, <= 1 mm, "
    "<= 0.08 mm)"
)
CONFIGS: dict[str, tuple[tuple[str, str, int, str], ...]] = {
    "full": (
        ("cylinder", "cylinder:d=120,h=100", 8, "120 mm cylinder"),
        ("arm", "arm:scale=5", 8, "tapered oval forearm"),
        ("stump", "stump:scale=5", 11, "residual limb with a rounded distal end"),
    ),
    "quick": (
        ("cylinder", "cylinder:d=120,h=100", 3, "120 mm cylinder"),
        ("arm", "arm:scale=5", 3, "tapered oval forearm"),
        ("stump", "stump:scale=5,z=-50", 6, "the stump's rounded end and 10 mm below it"),
    ),
}
TRUTH_STEP_MM = 0.5


def true_volume_mm3(obj: Any, z_lo: float, z_hi: float) -> float:
    """Return the true volume between two heights (Simpson on the true cross-sections)."""
    n = max(2, int(np.ceil((z_hi - z_lo) / TRUTH_STEP_MM / 2.0)) * 2)
    z = np.linspace(z_lo, z_hi, n + 1)
    area = np.array([sum(polygon_area(p) for p in obj.section_outline(float(v))) for v in z])
    w = np.ones(n + 1)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    return float((z_hi - z_lo) / (3.0 * n) * (w @ area))


def true_circumference_mm(obj: Any, z_mm: float) -> float:
    """Return the perimeter of the largest true outline at a height (NaN above or below)."""
    return max((perimeter(p) for p in obj.section_outline(z_mm)), default=float("nan"))


def _scan(spec: str, sections: int, out: Path, library: Path) -> tuple[float, str]:
    """Run one simulated scan; return its wall time and the error line (empty when fine)."""
    command = [
        sys.executable, "-m", "lamina_host", "scan", "--device", "sim", "--rig", "limb",
        "-o", str(out), "--object", spec, "--noise", NOISE,
        "--sections", str(sections), "--pitch", str(PITCH_MM), "--views", str(VIEWS),
        "--library", str(library),
    ]  # fmt: skip
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True)
    error = "" if done.returncode == 0 else (done.stderr.strip().splitlines() or ["?"])[-1]
    return time.perf_counter() - start, error


def points_ply(out: Path) -> np.ndarray:
    """Return the contour points (points.ply) of a scan's output folder."""
    return load_ply((out / "points.ply").read_bytes())[0].astype(float)


def surface_distance(obj: Any, points: np.ndarray) -> dict[str, float]:
    """Return the contours' mean distance to the true surface, direct and aligned."""
    surface = TrueSurface(obj)
    alignment = align_about_axis(surface, points)
    return {
        "direct_mm": float(np.mean(surface.distance_mm(points))),
        "aligned_mm": float(np.mean(surface.distance_mm(alignment.apply(points)))),
    }


def measure(spec: str, report: dict[str, Any], spacing_mm: float = SPACING_MM) -> dict[str, Any]:
    """Compare one scan's clinical measurements (levels ``spacing_mm`` apart) with the truth."""
    obj = parse_object(spec)
    mechanics = Mechanics.preset(NOISE)
    lift = report.get("lift", {})
    scale = lift["scale"] if lift.get("applied") else 1.0

    def true_z(z_mm: float) -> float:  # the host's height back to the commanded one
        return mechanics.true_z_mm(z_mm / scale)

    m = measure_limb(sections_from_report(report), spacing_mm)
    lo, hi = m.coverage_mm
    true_lo, true_hi = true_z(lo), true_z(hi)
    truth = true_volume_mm3(obj, true_lo, true_hi)
    levels = []
    for level in m.levels:
        true_c = true_circumference_mm(obj, true_z(level.z_mm))
        levels.append(
            {
                "offset_mm": level.offset_mm,
                "z_mm": level.z_mm,
                "circumference_mm": level.circumference_mm,
                "true_mm": true_c,
                "error_mm": level.circumference_mm - true_c,
                "source": level.source,
            }
        )
    linear = measure_limb(sections_from_report(report), spacing_mm, interpolation="linear")
    mesh_mm3 = report.get("mesh", {}).get("topology", {}).get("volume_mm3")
    span = (hi - lo) / (true_hi - true_lo) - 1.0
    return {
        "range_mm": [lo, hi],
        "volume_ml": m.volume_mm3 / 1000.0,
        "true_volume_ml": truth / 1000.0,
        "volume_error_percent": 100.0 * (m.volume_mm3 - truth) / truth,
        "linear_volume_error_percent": 100.0 * (linear.volume_mm3 - truth) / truth,
        "lift_span_error_percent": 100.0 * span,
        "lift_measured_percent": 100.0 * (scale - 1.0),
        "volume_error_without_lift_percent": 100.0 * (m.volume_mm3 / (1.0 + span) - truth) / truth,
        "mesh_vs_stack_percent": (
            100.0 * (mesh_mm3 - m.volume_mm3) / m.volume_mm3 if mesh_mm3 else None
        ),
        "levels": levels,
        "max_abs_circumference_error_mm": float(np.nanmax([abs(lv["error_mm"]) for lv in levels])),
    }


def run(config: str = "full", keep: Path | None = None) -> dict[str, Any]:
    """Scan every phantom of ``config`` and measure it against its true shape.

    ``keep``: a folder to keep the scans in; a scan already there is measured again, not
    rescanned.
    """
    results: dict[str, Any] = {"noise": NOISE, "pitch_mm": PITCH_MM, "views": VIEWS}
    results["config"] = config
    with tempfile.TemporaryDirectory() as tmp:
        base = keep or Path(tmp)
        base.mkdir(parents=True, exist_ok=True)
        for name, spec, sections, what in CONFIGS[config]:
            out = base / f"{config}-{name}"
            row: dict[str, Any] = {"spec": spec, "what": what, "sections": sections}
            if not (out / "report.json").is_file():
                row["wall_s"], error = _scan(spec, sections, out, base / "library.sqlite")
                if error:
                    row["error"] = error
            if (out / "report.json").is_file():
                row.update(measure(spec, json.loads((out / "report.json").read_text())))
                distance = surface_distance(parse_object(spec), points_ply(out))
                row["surface_distance"] = distance
            results[name] = row
    return results


def report(results: dict[str, Any]) -> list[str]:
    """Return the table lines: volume, circumference and surface errors per phantom."""
    lines = [
        f"  {results.get('config', 'full')} set",
        "  object     range mm   volume mL  true mL   vol %  linear %  cal %   lift %  "
        "vol-lift %  max |dC| mm  surf mm (direct)  mesh-stack %",
    ]
    for name in (k for k in results if isinstance(results[k], dict)):
        row = results[name]
        if "volume_ml" not in row:
            lines.append(f"  {name:<9} failed: {row.get('error', '?')}")
            continue
        mesh = row["mesh_vs_stack_percent"]
        surf = row["surface_distance"]
        lines.append(
            f"  {name:<9} {row['range_mm'][0]:5.1f}-{row['range_mm'][1]:5.1f}  "
            f"{row['volume_ml']:9.2f} {row['true_volume_ml']:8.2f}  "
            f"{row['volume_error_percent']:+6.3f}  {row['linear_volume_error_percent']:+7.3f}  "
            f"{row.get('lift_measured_percent', 0.0):+6.3f}  "
            f"{row['lift_span_error_percent']:+6.3f}  "
            f"{row['volume_error_without_lift_percent']:+9.3f}  "
            f"{row['max_abs_circumference_error_mm']:11.3f}  "
            f"{surf['aligned_mm']:7.4f} ({surf['direct_mm']:.4f})  "
            f"{'-' if mesh is None else f'{mesh:+.4f}':>12}"
        )
        per_level = ", ".join(
            f"{lv['offset_mm']:.0f}: {lv['error_mm']:+.2f}" for lv in row["levels"]
        )
        lines.append(f"            circumference error mm at each level: {per_level}")
    return lines


def main() -> int:
    """Run the bench on its own: ``--quick`` for the small set, ``--keep DIR`` to keep scans."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="the small set (runs under load)")
    parser.add_argument("--keep", type=Path, help="keep the scans here (and reuse them)")
    parser.add_argument("--out", type=Path, help="also write the figures as JSON here")
    args = parser.parse_args()
    from run import show  # the bench runner beside this file

    show("limb", sys.modules[__name__], run("quick" if args.quick else "full", args.keep), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
