"""The random-shape campaign (issue 18): hundreds of unseen shapes per scale, harsh preset.

Each seed's random anatomy-like object (``lamina_device.sim.random_shapes``; replay one
with ``--object random:seed=N,scale=S``) is scanned through the product path of
``tests.helpers.campaign`` (simulated device: renderer, mechanics, stripe extraction;
host: reconstruction with the defaults (lens distortion auto), report and output files;
the link left out)
on the harsh preset, at the thesis scale (thesis rig) and the limb scale (limb rig), and
judged against the simulator's truth with ``lamina_device.sim.truth``:

- ``mean dist``: mean distance of points.ply (the measured stretches of the EFD
  contours) to the true surface after the 3-parameter alignment of ``scan_accuracy``;
- ``coverage``: share of the surface the sheet's centre lit and the camera saw within
  0.25 mm of points.ply;
- ``volume``: the contour stack's volume error where the shape is closed and every
  section's outlines closed (both stacks over the true section heights: the lift's
  scale error left out);
- failures by kind (exception type and stage); a ``LaminaError`` is an honest one-line
  refusal, anything else a traceback the user would see;
- the same figures per kind of shape (``SHAPE_GROUPS``: smooth, relief, relief finer
  than the laser sheet resolves, wider than the view).

Seeds run in parallel processes (2 by default), each exception caught per seed. The
plans are small (2 sections x 6 views) to keep the time down: ``LAMINA_CAMPAIGN_SEEDS``
(or ``--seeds``) sets the seeds per scale (default 200), ``--quick`` runs 12, and
``LAMINA_CAMPAIGN_BUDGET_S`` (default 3600) stops starting seeds of a scale after that
many seconds, so ``make bench`` ends in bounded time on a slow machine (the report says
how many ran; ``inf`` lifts it). The default is twice what the limb scale's 200 seeds
take on a two-core machine (about 1800 s, the old default): issue 18 asks for 200 seeds
per scale, and a budget no longer than the run would cut its last seeds whenever the
machine is a little slower. ``python tests/benchmarks/bench_campaign.py --quick`` runs it
alone.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from concurrent.futures import FIRST_COMPLETED, Future, ProcessPoolExecutor, wait
from dataclasses import asdict
from pathlib import Path
from typing import Any

import numpy as np

if __package__ in (None, ""):  # run on its own: find the shared test builders
    sys.path[:0] = [str(Path(__file__).resolve().parents[2])]

from tests.helpers.campaign import SHAPE_GROUPS, CampaignPlan, SeedResult, scan_seed

PLANS = {
    "thesis": CampaignPlan("thesis", sections=2, pitch_mm=2.5, views=6),
    "limb": CampaignPlan("limb", sections=2, pitch_mm=12.0, views=6),
}
SEEDS = int(os.environ.get("LAMINA_CAMPAIGN_SEEDS", "200"))
QUICK_SEEDS = 12
WORKERS = int(os.environ.get("LAMINA_CAMPAIGN_WORKERS", "2"))
BUDGET_S = float(os.environ.get("LAMINA_CAMPAIGN_BUDGET_S", "3600"))
TITLE = (
    "random-shape campaign, harsh preset, per scale: mean distance (median, p95), coverage "
    "(median, p5), volume error, failures by kind, worst seeds (targets: <= 0.03 / 0.05 mm, "
    ">= 0.97 / 0.90, 0 tracebacks)"
)


def _scan(job: tuple[int, CampaignPlan]) -> tuple[SeedResult, float]:
    """Scan one seed in a worker; return its result and the CPU seconds it took."""
    cpu = time.process_time()
    result = scan_seed(*job)
    return result, time.process_time() - cpu


def run_scale(
    plan: CampaignPlan, seeds: list[int], workers: int, budget_s: float, progress: bool = False
) -> dict[str, Any]:
    """Scan ``seeds`` along ``plan`` in ``workers`` processes; return every seed's result."""
    start = time.perf_counter()
    results: list[dict[str, Any]] = []
    pending = list(seeds)
    with ProcessPoolExecutor(max_workers=workers) as pool:
        running: set[Future[tuple[SeedResult, float]]] = set()
        while pending or running:
            while pending and len(running) < 2 * workers and time.perf_counter() - start < budget_s:
                running.add(pool.submit(_scan, (pending.pop(0), plan)))
            if not running:
                break
            done, running = wait(running, return_when=FIRST_COMPLETED)
            for future in done:
                try:
                    result, cpu_s = future.result()
                except Exception as exc:
                    result, cpu_s = SeedResult(-1, plan.scale, stage="worker"), 0.0
                    result.error_type, result.error = type(exc).__name__, str(exc)[:300]
                row = asdict(result)
                row["cpu_s"] = cpu_s
                results.append(row)
                if progress:
                    what = result.failure_kind or f"coverage {result.coverage:.3f}"
                    print(
                        f"  {plan.scale} seed {result.seed}: {what} ({len(results)}/{len(seeds)})",
                        file=sys.stderr,
                        flush=True,
                    )
    return {
        "plan": asdict(plan),
        "seeds_asked": len(seeds),
        "wall_s": time.perf_counter() - start,
        "workers": workers,
        "results": sorted(results, key=lambda r: r["seed"]),
    }


def run(
    seeds: int | None = None,
    workers: int = WORKERS,
    budget_s: float = BUDGET_S,
    progress: bool = True,
    first: int = 0,
) -> dict[str, Any]:
    """Run the campaign at both scales; return the per-seed results and their summary.

    ``progress`` prints one line per finished seed on stderr (a full run takes long);
    ``first`` is the first seed, so that shapes no earlier run has seen can be scanned.
    """
    count = SEEDS if seeds is None else seeds
    out: dict[str, Any] = {"seeds_per_scale": count, "first_seed": first}
    for scale, plan in PLANS.items():
        scale_run = run_scale(plan, list(range(first, first + count)), workers, budget_s, progress)
        scale_run["summary"] = summarise(scale_run["results"])
        out[scale] = scale_run
    return out


def _pct(values: list[float], q: float) -> float:
    """Return the q-th percentile of the finite values (NaN when none)."""
    finite = [v for v in values if math.isfinite(v)]
    return float(np.percentile(finite, q)) if finite else math.nan


def figures(finished: list[dict[str, Any]]) -> dict[str, Any]:
    """Return the distance, coverage and volume distributions of finished seeds."""
    dist = [r["mean_distance_mm"] for r in finished]
    cov = [r["coverage"] for r in finished if r["lit_points"]]
    vol = [abs(r["volume_error_percent"]) for r in finished]
    return {
        "mean_distance_mm": {"median": _pct(dist, 50), "p95": _pct(dist, 95), "n": len(dist)},
        "coverage": {"median": _pct(cov, 50), "p5": _pct(cov, 5), "n": len(cov)},
        "volume_abs_error_percent": {
            "median": _pct(vol, 50),
            "p95": _pct(vol, 95),
            "n": sum(1 for v in vol if math.isfinite(v)),
        },
    }


def summarise(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Return the distribution figures of one scale's per-seed results, overall and per
    kind of shape (``SHAPE_GROUPS``: a target such as "limbs with skin relief" is read
    off its group, and relief finer than the sheet kept apart from what software can do).
    """
    finished = [r for r in rows if not r["stage"]]
    kinds: dict[str, int] = {}
    for r in rows:
        if r["stage"]:
            kind = f"{r['error_type']}@{r['stage']}" + (" (refusal)" if r["refusal"] else "")
            kinds[kind] = kinds.get(kind, 0) + 1
    statuses: dict[str, int] = {}
    for r in finished:
        for k, v in r["statuses"].items():
            statuses[k] = statuses.get(k, 0) + v

    def badness(r: dict[str, Any]) -> tuple[int, float, float]:
        crashed = (bool(r["stage"]) and not r["refusal"]) or bool(r["internal_errors"])
        cov_r = r["coverage"] if math.isfinite(r["coverage"]) else 0.0
        dist_r = r["mean_distance_mm"] if math.isfinite(r["mean_distance_mm"]) else math.inf
        return (0 if crashed else 1 if r["stage"] else 2, cov_r, -dist_r)

    worst = sorted(rows, key=badness)[:5]
    return {
        "seeds": len(rows),
        "finished": len(finished),
        "tracebacks": sum(1 for r in rows if r["stage"] and not r["refusal"]),
        "caught_internal_errors": sum(len(r["internal_errors"]) for r in rows),
        "refusals": sum(1 for r in rows if r["stage"] and r["refusal"]),
        "motion_warned": [
            {"seed": r["seed"], "outlines": r["motion_warnings"]}
            for r in finished
            if r["motion_warnings"]
        ],
        **figures(finished),
        "by_group": {
            g: figures(rows_g)
            for g in SHAPE_GROUPS
            if (rows_g := [r for r in finished if r.get("group") == g])
        },
        "failures": kinds,
        "statuses": statuses,
        "worst": [
            {
                "seed": r["seed"],
                "features": r["features"],
                "failure": f"{r['error_type']}@{r['stage']}: {r['error']}" if r["stage"] else "",
                "internal_errors": r["internal_errors"],
                "trace": r["trace"],
                "coverage": r["coverage"],
                "mean_distance_mm": r["mean_distance_mm"],
            }
            for r in worst
        ],
        "crashes": [
            {
                "seed": r["seed"],
                "kind": f"{r['error_type']}@{r['stage']}",
                "error": r["error"],
                "trace": r["trace"],
            }
            for r in rows
            if r["stage"] and not r["refusal"]
        ],
        "cpu_s_per_seed": _pct([r["cpu_s"] for r in rows], 50),
        "cpu_s_total": float(sum(r["cpu_s"] for r in rows)),
    }


def _replay(plan: dict[str, Any], seed: int) -> str:
    """Return the command that replays one seed's scan as a user would run it."""
    rig = "" if plan["scale"] == "thesis" else f" --rig {plan['scale']}"
    return (
        f"lamina scan --device sim{rig} --noise {plan['noise']} "
        f"--object random:seed={seed},scale={plan['scale']} --sections {plan['sections']} "
        f"--pitch {plan['pitch_mm']:g} --views {plan['views']} -o OUT"
    )


def _f(value: float, spec: str) -> str:
    """Format a figure, or a dash when there is none."""
    return "-" if value is None or not math.isfinite(value) else format(value, spec)


def _motion_line(summary: dict[str, Any]) -> str:
    """Return how many still shapes the report warned of as moved (issue 22: none should be)."""
    warned = summary["motion_warned"]
    outlines = [f"seed {w['seed']} " + "; ".join(w["outlines"]) for w in warned]
    listed = ", ".join(outlines[:6]) + (", ..." if len(outlines) > 6 else "")
    return f"    still shapes warned of motion: {len(warned)} of {summary['finished']}" + (
        f" ({listed})" if outlines else ""
    )


def report(results: dict[str, Any]) -> list[str]:
    """Return the table lines of both scales."""
    lines = []
    for scale in PLANS:
        if scale not in results:
            continue
        run_ = results[scale]
        s, plan = run_["summary"], run_["plan"]
        d, c, v = s["mean_distance_mm"], s["coverage"], s["volume_abs_error_percent"]
        head = (
            f"  {scale}: {s['seeds']} of {run_['seeds_asked']} seeds, {plan['sections']} "
            f"sections x {plan['views']} views, {plan['pitch_mm']:g} mm pitch; wall "
            f"{run_['wall_s']:.0f} s on {run_['workers']} workers, "
            f"{s['cpu_s_per_seed']:.1f} CPU s per seed (median)"
        )
        lines += [
            head,
            f"    finished {s['finished']}, one-line refusals {s['refusals']}, "
            f"tracebacks {s['tracebacks']}, outlines or meshes failed by a caught internal "
            f"error {s['caught_internal_errors']}",
            f"    mean distance mm: median {_f(d['median'], '.4f')}, "
            f"p95 {_f(d['p95'], '.4f')} (n={d['n']})",
            f"    coverage within 0.25 mm: median {_f(c['median'], '.3f')}, "
            f"p5 {_f(c['p5'], '.3f')} (n={c['n']})",
            "    |volume error| % (closed shapes, closed sections): "
            f"median {_f(v['median'], '.3f')}, p95 {_f(v['p95'], '.3f')} (n={v['n']})",
            "    outline statuses: "
            + ", ".join(f"{k} {n}" for k, n in sorted(s["statuses"].items())),
            _motion_line(s),
        ]
        for group, g in s["by_group"].items():
            gd, gc, gv = g["mean_distance_mm"], g["coverage"], g["volume_abs_error_percent"]
            lines.append(
                f"    {group} (n={gd['n']}): distance median {_f(gd['median'], '.4f')}, "
                f"p95 {_f(gd['p95'], '.4f')}; coverage median {_f(gc['median'], '.3f')}, "
                f"p5 {_f(gc['p5'], '.3f')}; |volume| % median {_f(gv['median'], '.3f')} "
                f"(n={gv['n']})"
            )
        for kind, n in sorted(s["failures"].items(), key=lambda kv: -kv[1]):
            lines.append(f"    failure {kind}: {n}")
        for crash in s["crashes"][:10]:
            lines.append(f"    crash seed {crash['seed']}: {crash['kind']}: {crash['error']}")
            lines.append(f"      at {crash['trace']}")
        lines.append("    worst five (replay with the command given):")
        for w in s["worst"]:
            what = w["failure"] or (
                f"coverage {_f(w['coverage'], '.3f')}, mean distance "
                f"{_f(w['mean_distance_mm'], '.4f')} mm"
            )
            lines.append(f"      seed {w['seed']}: {what} [{w['features']}]")
            lines.append(f"        {_replay(plan, w['seed'])}")
    return lines


def main() -> int:
    """Run the campaign on its own (``--quick``: 12 seeds per scale)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help=f"{QUICK_SEEDS} seeds per scale")
    parser.add_argument("--seeds", type=int, help=f"seeds per scale (default {SEEDS})")
    parser.add_argument(
        "--first", type=int, default=0, help="first seed (default 0; others: unseen shapes)"
    )
    parser.add_argument("--workers", type=int, default=WORKERS, help="worker processes")
    parser.add_argument("--scale", choices=list(PLANS), help="run one scale only")
    parser.add_argument("--out", type=Path, help="also write the results as JSON here")
    args = parser.parse_args()
    count = args.seeds or (QUICK_SEEDS if args.quick else SEEDS)
    if args.scale:
        for other in [k for k in PLANS if k != args.scale]:
            del PLANS[other]
    from run import show  # the bench runner beside this file

    show("campaign", sys.modules[__name__], run(count, args.workers, first=args.first), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
