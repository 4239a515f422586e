"""Limbs with skin relief on the limb rig: EFD order per section, coverage, surface distance.

The ``arm`` phantom at limb scale with skin relief (``relief=``, ``wave=``: oblique folds
of 0.1-0.5 mm at 5-10 mm round the outline and two longer scales) is scanned end to end
on the simulated limb rig (``lamina scan --device sim --rig limb --noise harsh
--distortion``, 8 views, 8 mm pitch) and reprocessed with each harmonic rule from the
same segments (the library's inputs):

- ``N``: the harmonics each section got (the order should follow the relief and stay
  about the same from one section to the next, issue #18);
- ``cover``: the share of the lit-and-seen true surface within 0.25 mm of the contours
  (``truth.coverage``), after the 3-parameter alignment of ``truth.scan_accuracy``;
- ``dist mm``: the contours' mean distance to the true surface, aligned.

``residual`` is the default rule (the measured points' residual reaches their noise);
``noise`` the earlier spectral floor; ``fixed 40`` a generous fixed order, for scale.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

from lamina_device.sim import Mechanics, NoiseModel, Rig, SimScene, parse_object
from lamina_device.sim.truth import (
    coverage,
    lit_and_seen_points,
    scan_accuracy,
    segment_views,
)
from lamina_host.reconstruct.pipeline import ProcessOptions
from lamina_host.store.library import Library
from lamina_host.store.outputs import measured_cloud
from lamina_host.workflow.batch import reprocess

NOISE, VIEWS, PITCH_MM, SECTIONS = "harsh", 8, 8.0, 8
OBJECTS = (
    ("arm:scale=5,relief=0.3,wave=8", "forearm, 0.3 mm folds at 8 mm"),
    ("arm:scale=5,relief=0.15,wave=5", "forearm, 0.15 mm folds at 5 mm"),
)
RULES: tuple[tuple[str, dict[str, Any]], ...] = (
    ("residual", {}),
    ("noise", {"harmonic_rule": "noise"}),
    ("fixed 40", {"harmonics": 40}),
)
TITLE = (
    f"limb-scale arm with skin relief, {VIEWS} views, {PITCH_MM:g} mm pitch, {NOISE}: EFD "
    "harmonics per section, coverage within 0.25 mm and mean surface distance by rule"
)


def _scan(spec: str, out: Path, library: Path) -> str:
    """Run one simulated limb scan; return the error line (empty when fine)."""
    command = [
        sys.executable, "-m", "lamina_host", "scan", "--device", "sim", "--rig", "limb",
        "-o", str(out), "--object", spec, "--noise", NOISE, "--distortion",
        "--sections", str(SECTIONS), "--pitch", str(PITCH_MM), "--views", str(VIEWS),
        "--library", str(library),
    ]  # fmt: skip
    done = subprocess.run(command, capture_output=True, text=True)
    return "" if done.returncode == 0 else (done.stderr.strip().splitlines() or ["?"])[-1]


def _measure(spec: str, library: Path) -> dict[str, Any]:
    """Reprocess the scan with every rule and compare the contours with the truth."""
    obj = parse_object(spec)
    rig, mechanics = Rig.limb(), Mechanics.preset(NOISE)
    scene = SimScene(rig, obj, NoiseModel.preset(NOISE))
    inputs = Library(library).inputs(1)
    lit = lit_and_seen_points(scene, segment_views(inputs.segments), mechanics)
    base = ProcessOptions.from_dict(inputs.options)
    rows: dict[str, Any] = {}
    for name, change in RULES:
        result = reprocess(inputs, replace(base, **change))
        points, _ = measured_cloud(result)
        raw = np.vstack([np.column_stack([s.raw, np.full(len(s.raw), s.z_mm)])
                         for s in result.sections])  # fmt: skip
        acc = scan_accuracy(obj, raw, points, lit)
        per_section = []
        for s in result.sections:
            near = np.abs(lit[:, 2] - mechanics.true_z_mm(s.z_mm)) < 0.5 * PITCH_MM
            mine = acc.alignment.apply(
                np.column_stack([s.measured_contour, np.full(len(s.measured_contour), s.z_mm)])
            )
            per_section.append(
                {"index": s.index, "harmonics": s.harmonics, "status": s.status,
                 "coverage": coverage(lit[near], mine) if near.any() else float("nan")}
            )  # fmt: skip
        rows[name] = {
            "coverage": acc.aligned.coverage_percent / 100.0,
            "mean_distance_mm": acc.aligned.mean_distance_mm,
            "sections": per_section,
            "fit_efd_s": result.timings_s.get("fit_efd", float("nan")),
        }
    return rows


def run() -> dict[str, Any]:
    """Scan every relief phantom once and measure it with every rule."""
    out: dict[str, Any] = {}
    with tempfile.TemporaryDirectory() as tmp:
        for k, (spec, what) in enumerate(OBJECTS):
            library = Path(tmp) / f"lib{k}.sqlite"
            error = _scan(spec, Path(tmp) / f"scan{k}", library)
            out[spec] = {"what": what, "error": error}
            if not error:
                out[spec]["rules"] = _measure(spec, library)
    return out


def report(results: dict[str, Any]) -> list[str]:
    """Return the table lines."""
    lines = []
    for spec, row in results.items():
        lines.append(f"  {spec} ({row['what']})")
        if row["error"]:
            lines.append(f"    scan failed: {row['error']}")
            continue
        for name, r in row["rules"].items():
            orders = " ".join(f"{s['harmonics']:3d}" for s in r["sections"])
            covers = " ".join(f"{s['coverage']:.2f}" for s in r["sections"])
            lines.append(
                f"    {name:<9} cover {r['coverage']:.3f}  dist {r['mean_distance_mm']:.4f} mm"
                f"  N: {orders}  section cover: {covers}"
            )
    return lines


if __name__ == "__main__":
    print(f"relief: {TITLE}")
    print("\n".join(report(run())))
