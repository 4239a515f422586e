"""Colour per point: error against the simulated patches, and what colour costs on the wire."""

from __future__ import annotations

import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

from lamina_device.acquisition import acquire
from lamina_device.sim import open_sim
from lamina_device.sim.texture import colour_errors
from lamina_host.reconstruct.mesh import load_coloured_ply
from lamina_shared.protocol import encode_segment, quantise_segment
from lamina_shared.types import ScanPlan, Segment

TITLE = "colour: error on the patches cylinder (harsh noise), bytes per point with colour"
OBJECT = "patches:d=30"
SECTIONS, VIEWS = 4, 8


def _scan_colours(folder: Path) -> tuple[Any, Any]:
    """Run ``lamina scan --colour`` on the simulator; return colour_points.ply's points, colours."""
    out = folder / "out"
    subprocess.run(
        [sys.executable, "-m", "lamina_host", "scan", "--device", "sim", "--object", OBJECT,
         "--noise", "harsh", "--colour", "--sections", str(SECTIONS), "--views", str(VIEWS),
         "--out", str(out), "--library", str(folder / "lib.db")],
        check=True, capture_output=True, timeout=1800,
    )  # fmt: skip
    points, _, colours = load_coloured_ply((out / "colour_points.ply").read_bytes())
    return points, colours


def _wire_cost() -> dict[str, float]:
    """Framed bytes per point of the same segments with and without their colour."""
    hardware = open_sim(OBJECT, noise="harsh")
    segments: list[Segment] = []
    try:
        acquire(hardware, "object", ScanPlan.regular(1, 2.0, VIEWS), segments.append, colour=True)
    finally:
        hardware.close()
    coloured = [quantise_segment(s) for s in segments]
    plain = [Segment(*(getattr(s, f) for f in ("target", "section", "view", "z_mm",
                       "angle_deg", "cols", "rows", "peak", "width", "confidence")))
             for s in coloured]  # fmt: skip
    points = sum(len(s) for s in coloured)
    with_colour = sum(len(encode_segment(1, k, s)) for k, s in enumerate(coloured))
    without = sum(len(encode_segment(1, k, s)) for k, s in enumerate(plain))
    return {"bytes_per_point": without / points, "colour_bytes_per_point": with_colour / points}


def run() -> dict[str, Any]:
    """Scan the patches cylinder with colour and measure each patch's error."""
    with tempfile.TemporaryDirectory() as tmp:
        points, colours = _scan_colours(Path(tmp))
    gain, errors = colour_errors(points, colours)
    patches = [
        {"name": e.name, "points": e.points, "truth": e.truth, "bias": e.bias, "rms": e.rms,
         "mean_delta_e": e.mean_delta_e}
        for e in errors
    ]  # fmt: skip
    rms_all = [r for e in errors for r in e.rms]
    return {
        "object": OBJECT,
        "plan": f"{SECTIONS} sections x {VIEWS} views",
        "white_gain": [float(g) for g in gain],
        "patches": patches,
        "mean_delta_e": sum(e.mean_delta_e for e in errors) / len(errors),
        "worst_rms_dn": max(rms_all),
        **_wire_cost(),
    }


def report(result: dict[str, Any]) -> list[str]:
    """Return the table lines of one run."""
    lines = [
        f"  {result['object']}, {result['plan']}, noise harsh; truth = patch reflectance x the "
        "skin's white gain",
        f"  {'patch':<14}{'points':>7}  {'bias R/G/B DN':>20}  {'RMS R/G/B DN':>18}"
        f"  {'mean dE':>7}",
    ]
    for p in result["patches"]:
        bias = "/".join(f"{b:+.1f}" for b in p["bias"])
        rms = "/".join(f"{r:.1f}" for r in p["rms"])
        lines.append(
            f"  {p['name']:<14}{p['points']:>7}  {bias:>20}  {rms:>18}  {p['mean_delta_e']:>7.2f}"
        )
    lines.append(
        f"  mean dE {result['mean_delta_e']:.2f}, worst channel RMS {result['worst_rms_dn']:.1f} DN"
    )
    lines.append(
        f"  wire: {result['bytes_per_point']:.2f} B/pt without colour, "
        f"{result['colour_bytes_per_point']:.2f} B/pt with"
    )
    return lines
