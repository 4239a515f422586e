"""A turntable gear whose error accumulates over the turns (issue #22): what counting the
turns mends.

A table that turns short of its step count (the thesis's motor, 0.2 degrees per 45, 8.3;
a ``gear_ratio`` that does not match the pulleys; lost steps) falls further behind with
every turn since power-up, and a stop-and-go scan turns on through a whole turn from one
section to the next (the short way, ``turntable_runs``): each section stands one turn's
shortfall (1.6 degrees) further turned than the last. The simulator's gear does this
(``Mechanics.angle_error_accumulates``, the default); the device sends each view's whole
turns and the host scales the calibrated shortfall over them. This bench scans the same
random shapes, stop-and-go on the harsh preset, with the host as it is and with the
turns dropped (the shortfall corrected within the turn only, as before the mend), and
reports mean distance and coverage against the truth and the turn the old host left at
the top section. ``python tests/benchmarks/bench_gear.py`` runs it alone.
"""

from __future__ import annotations

import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

if __package__ in (None, ""):  # run on its own: find the shared test builders
    sys.path[:0] = [str(Path(__file__).resolve().parents[2])]

from lamina_device.sim import Mechanics
from lamina_device.sim.axes import SimTurntable
from tests.helpers.campaign import CampaignPlan, scan_seed

NOISE = "harsh"
PLANS = {
    "thesis": CampaignPlan("thesis", sections=6, pitch_mm=2.5, views=6, noise=NOISE),
    "limb": CampaignPlan("limb", sections=3, pitch_mm=12.0, views=6, noise=NOISE),
}
SEEDS = {"thesis": (1, 4), "limb": (1,)}
"""Random shapes of each scale (``random:seed=N,scale=...``)."""
WORKERS = 2
TITLE = (
    "turntable gear error accumulating over the turns (issue 22): random shapes "
    f"stop-and-go, {NOISE} preset, the host correcting over each view's count (its "
    "whole turns) against correcting within the turn (mean distance mm, coverage, turn "
    "left at the top section)"
)


def top_turn_left_deg(plan: CampaignPlan) -> float:
    """Return how far the top section's first view stands from the angle a host that
    corrects within the turn takes it at: the true angle at the count the box's moves
    reach, less its whole turns and the true angle at the same angle within the turn."""
    mechanics = Mechanics.preset(plan.noise)
    table = SimTurntable(Mechanics.ideal())
    counts = []
    for view in plan.scan_plan().views:
        table.move_to(view.angle_deg)
        counts.append((view.z_mm, table.count_deg))
    top = max(z for z, _ in counts)
    count = next(c for z, c in counts if z == top)
    within = count % 360.0
    return mechanics.true_angle_deg(count) - (count - within) - mechanics.true_angle_deg(within)


def run(workers: int = WORKERS) -> dict[str, Any]:
    """Scan every seed for both hosts; return the rows and the turn left per scale."""
    start = time.perf_counter()
    jobs = [
        (seed, replace(plan, counts_turns=counts))
        for scale, plan in PLANS.items()
        for seed in SEEDS[scale]
        for counts in (False, True)
    ]
    with ProcessPoolExecutor(max_workers=workers) as pool:
        seeds, plans = zip(*jobs, strict=True)
        results = list(pool.map(scan_seed, seeds, plans))
    rows = [
        {
            "scale": plan.scale,
            "seed": seed,
            "host": "over the count" if plan.counts_turns else "within the turn",
            "mean_distance_mm": r.mean_distance_mm,
            "coverage": r.coverage,
            "failure": r.failure_kind,
        }
        for (seed, plan), r in zip(jobs, results, strict=True)
    ]
    return {
        "plans": {scale: asdict(plan) for scale, plan in PLANS.items()},
        "top_turn_left_deg": {scale: top_turn_left_deg(plan) for scale, plan in PLANS.items()},
        "rows": rows,
        "wall_s": time.perf_counter() - start,
    }


def report(results: dict[str, Any]) -> list[str]:
    """Return the table: per scale and seed, each host's mean distance and coverage."""
    lines = []
    for scale, plan in results["plans"].items():
        lines.append(
            f"  {scale}: {plan['sections']} sections x {plan['views']} views, "
            f"{plan['pitch_mm']:g} mm pitch; the top section stands "
            f"{results['top_turn_left_deg'][scale]:+.2f} deg from where a host correcting "
            "within the turn takes it"
        )
        lines.append(f"    {'seed':>6}  {'host':<15} {'mean mm':>8} {'coverage':>9}")
        for row in results["rows"]:
            if row["scale"] != scale:
                continue
            figures = (
                row["failure"]
                if row["failure"]
                else f"{row['mean_distance_mm']:8.4f} {row['coverage']:9.3f}"
            )
            lines.append(f"    {row['seed']:>6}  {row['host']:<15} {figures}")
    lines.append(f"  wall {results['wall_s']:.0f} s on {WORKERS} workers")
    return lines


def main() -> int:
    """Run the bench alone and print its table."""
    print(TITLE)
    print("\n".join(report(run())))
    return 0


if __name__ == "__main__":
    sys.exit(main())
