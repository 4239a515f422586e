"""The patient's wait (issue 22): how long plans keep a limb still, from the device's config.

Each plan is modelled on the shipped configuration (``default_config.toml``: the box's
steppers, settle times and camera) by :func:`lamina_device.timing.estimate_scan_time`,
view by view with the axes' own profiles. The processing per view is measured here: the
default extraction of a harsh laser-off/laser-on pair from the simulated limb rig at the
box's 1536x864, with its segment's wire bytes (an x86 core; a Pi core is roughly 2-4x
slower, still far below a view's mechanics). Rows: the default plan of the configuration,
the simulator's default (thesis) plan and a 400 mm leg at 10 mm pitch with 8 views, as the
loop runs (lift and table together; ``axes_in_turn_s``: one after the other, as the loop ran
before); the mechanical minimum is the moves with both axes together, settle and frames only.
"""

from __future__ import annotations

import time
from typing import Any

TITLE = "modelled scan time of stop-and-go plans on the default configuration (issue 22)"


def _processing_s() -> float:
    """Return one view's extraction and segment encoding on this machine (best of 5)."""
    from lamina_device.acquisition import capture_pair
    from lamina_device.backends import open_hardware
    from lamina_device.extract import extract, to_segment
    from lamina_shared.protocol import encode_segment, quantise_segment

    hardware = open_hardware("sim", "arm:scale=5", noise="harsh", rig="limb")
    try:
        hardware.place("object")
        hardware.lift.move_to(20.0)
        on, off = capture_pair(hardware)
    finally:
        hardware.close()
    best = float("inf")
    for _ in range(5):
        start = time.perf_counter()
        points = extract(on, off, hardware.extract)
        encode_segment(1, 1, quantise_segment(to_segment(points, "object", 0, 0, 20.0, 0.0)))
        best = min(best, time.perf_counter() - start)
    return best


def run() -> dict[str, Any]:
    """Model each plan both ways; return the rows and the processing time used."""
    from lamina_device.config import load_config
    from lamina_device.sim.backend import DEFAULT_PLAN
    from lamina_device.timing import estimate_scan_time
    from lamina_shared.types import ScanPlan

    config = load_config()
    processing_s = _processing_s()
    plans = {
        "default (config)": ScanPlan.regular(
            config.plan.sections, config.plan.pitch_mm, config.plan.views
        ),
        "thesis (sim default)": DEFAULT_PLAN,
        "leg 400 mm, 10 mm pitch": ScanPlan.regular(40, 10.0, 8),
    }
    rows = []
    for name, plan in plans.items():
        heights = [v.z_mm for v in plan.views]
        estimate = estimate_scan_time(config, plan, processing_s)
        in_turn = estimate_scan_time(config, plan, processing_s, axes_together=False)
        rows.append(
            {
                "plan": name,
                "mode": "stop-and-go",
                "height_mm": round(max(heights) - min(heights), 6),
                "sections": len(plan.sections),
                "views": len(plan.views),
                "modelled_s": round(estimate.modelled_s, 3),
                "mechanical_minimum_s": round(estimate.mechanical_minimum_s, 3),
                "ratio": round(estimate.ratio, 4),
                "axes_in_turn_s": round(in_turn.modelled_s, 3),
                "turntable_s": round(estimate.turntable_s, 3),
                "lift_s": round(estimate.lift_s, 3),
            }
        )
    return {"rows": rows, "processing_s_per_view": round(processing_s, 5)}


def report(results: dict[str, Any]) -> list[str]:
    """Return the table: one line per plan and mode."""
    lines = [
        f"  processing per view (extraction + segment, this machine): "
        f"{results['processing_s_per_view'] * 1000:.1f} ms",
        f"  {'plan':<26}{'mode':<13}{'views':>6}{'modelled':>11}{'minimum':>10}{'ratio':>8}"
        f"{'axes in turn':>14}",
    ]
    for row in results["rows"]:
        lines.append(
            f"  {row['plan']:<26}{row['mode']:<13}{row['views']:>6}"
            f"{row['modelled_s']:>10.1f}s{row['mechanical_minimum_s']:>9.1f}s{row['ratio']:>8.3f}"
            f"{row['axes_in_turn_s']:>13.1f}s"
        )
    return lines
