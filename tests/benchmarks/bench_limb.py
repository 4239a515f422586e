"""Clinical accuracy at limb scale (issue #13 part 5): volume and circumference errors.

Three limb-scale phantoms are scanned end to end on the simulated limb rig (``lamina scan
--device sim --rig limb --noise harsh --distortion``, the real device process over the real
link), 8 views per section at 10 mm pitch, and measured with ``lamina_host.clinical`` from
the EFD sections stored in report.json:

- ``volume error %``: the contour-stack volume over the scanned range against the true
  volume over the same range (the true shape's cross-section areas integrated between the
  true heights of the first and last section, 0.5 mm Simpson steps); ``pchip %`` is
  the same with the EFD coefficients interpolated by PCHIP instead of linearly (the mesh
  and ``lamina report`` use linear);
- ``circumference error mm``: at every level, 20 mm apart from the distal end, the
  measured circumference minus the true outline's perimeter at the level's true height;
- ``mesh - stack %``: the watertight contour mesh's volume against the contour-stack
  volume (they must agree).

Targets (issue #13): volume within 0.5 %, circumference within 1 mm at every level.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from lamina_device.motion import Mechanics
from lamina_device.sim import parse_object
from lamina_host.clinical import measure_limb, sections_from_report

NOISE = "harsh"
PITCH_MM, VIEWS, SPACING_MM = 10.0, 8, 20.0
TITLE = (
    f"limb-scale phantoms, {VIEWS} views, {PITCH_MM:g} mm pitch, {NOISE} noise: clinical "
    "volume and circumference errors vs truth (targets: <= 0.5 %, <= 1 mm)"
)
OBJECTS = (
    ("cylinder", "cylinder:d=120,h=100", 8, "120 mm cylinder"),
    ("arm", "arm:scale=5", 8, "tapered oval forearm"),
    ("stump", "stump:scale=5", 11, "residual limb with a rounded distal end"),
)
TRUTH_STEP_MM = 0.5


def _polygon_area(p: np.ndarray) -> float:
    x, y = p.T
    return float(abs(0.5 * np.sum(x * np.roll(y, -1) - np.roll(x, -1) * y)))


def _polygon_length(p: np.ndarray) -> float:
    return float(np.linalg.norm(np.roll(p, -1, axis=0) - p, axis=1).sum())


def true_volume_mm3(obj: Any, z_lo: float, z_hi: float) -> float:
    """Return the true volume between two heights (Simpson on the true cross-sections)."""
    n = max(2, int(np.ceil((z_hi - z_lo) / TRUTH_STEP_MM / 2.0)) * 2)
    z = np.linspace(z_lo, z_hi, n + 1)
    area = np.array([sum(_polygon_area(p) for p in obj.section_outline(float(v))) for v in z])
    w = np.ones(n + 1)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    return float((z_hi - z_lo) / (3.0 * n) * (w @ area))


def true_circumference_mm(obj: Any, z_mm: float) -> float:
    """Return the perimeter of the largest true outline at a height (NaN above or below)."""
    return max((_polygon_length(p) for p in obj.section_outline(z_mm)), default=float("nan"))


def _scan(spec: str, sections: int, out: Path, library: Path) -> tuple[float, str]:
    """Run one simulated scan; return its wall time and the error line (empty when fine)."""
    command = [
        sys.executable, "-m", "lamina_host", "scan", "--device", "sim", "--rig", "limb",
        "-o", str(out), "--object", spec, "--noise", NOISE, "--distortion",
        "--sections", str(sections), "--pitch", str(PITCH_MM), "--views", str(VIEWS),
        "--library", str(library),
    ]  # fmt: skip
    start = time.perf_counter()
    done = subprocess.run(command, capture_output=True, text=True)
    error = "" if done.returncode == 0 else (done.stderr.strip().splitlines() or ["?"])[-1]
    return time.perf_counter() - start, error


def measure(spec: str, report: dict[str, Any]) -> dict[str, Any]:
    """Compare one scan's clinical measurements with the true shape."""
    obj = parse_object(spec)
    mechanics = Mechanics.preset(NOISE)
    m = measure_limb(sections_from_report(report), SPACING_MM)
    lo, hi = m.coverage_mm
    truth = true_volume_mm3(obj, mechanics.true_z_mm(lo), mechanics.true_z_mm(hi))
    levels = []
    for level in m.levels:
        true_c = true_circumference_mm(obj, mechanics.true_z_mm(level.z_mm))
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
    pchip = measure_limb(sections_from_report(report), SPACING_MM, interpolation="pchip")
    mesh_mm3 = report.get("mesh", {}).get("topology", {}).get("volume_mm3")
    return {
        "range_mm": [lo, hi],
        "volume_ml": m.volume_mm3 / 1000.0,
        "true_volume_ml": truth / 1000.0,
        "volume_error_percent": 100.0 * (m.volume_mm3 - truth) / truth,
        "pchip_volume_error_percent": 100.0 * (pchip.volume_mm3 - truth) / truth,
        "mesh_vs_stack_percent": (
            100.0 * (mesh_mm3 - m.volume_mm3) / m.volume_mm3 if mesh_mm3 else None
        ),
        "levels": levels,
        "max_abs_circumference_error_mm": float(np.nanmax([abs(lv["error_mm"]) for lv in levels])),
    }


def run() -> dict[str, Any]:
    """Scan every phantom and measure it against its true shape."""
    results: dict[str, Any] = {"noise": NOISE, "pitch_mm": PITCH_MM, "views": VIEWS}
    with tempfile.TemporaryDirectory() as tmp:
        for name, spec, sections, what in OBJECTS:
            out = Path(tmp) / name
            wall_s, error = _scan(spec, sections, out, Path(tmp) / "library.sqlite")
            row: dict[str, Any] = {"spec": spec, "what": what, "sections": sections}
            row["wall_s"] = wall_s
            if (out / "report.json").is_file():
                row.update(measure(spec, json.loads((out / "report.json").read_text())))
            if error:
                row["error"] = error
            results[name] = row
    return results


def report(results: dict[str, Any]) -> list[str]:
    """Return the table lines: volume error and the circumference error at every level."""
    lines = [
        "  object     range mm    volume mL  true mL   error %  pchip %  mesh-stack %  "
        "max |dC| mm  wall s"
    ]
    for name, _, _, _ in OBJECTS:
        row = results[name]
        if "volume_ml" not in row:
            lines.append(f"  {name:<9} failed: {row.get('error', '?')}")
            continue
        mesh = row["mesh_vs_stack_percent"]
        lines.append(
            f"  {name:<9} {row['range_mm'][0]:5.1f}-{row['range_mm'][1]:5.1f}  "
            f"{row['volume_ml']:9.2f} {row['true_volume_ml']:8.2f}  "
            f"{row['volume_error_percent']:+7.3f}  {row['pchip_volume_error_percent']:+7.3f}  "
            f"{'-' if mesh is None else f'{mesh:+.4f}':>12}  "
            f"{row['max_abs_circumference_error_mm']:11.3f}  {row['wall_s']:6.1f}"
        )
        per_level = ", ".join(
            f"{lv['offset_mm']:.0f}: {lv['error_mm']:+.2f}" for lv in row["levels"]
        )
        lines.append(f"            circumference error mm at each level: {per_level}")
    return lines
