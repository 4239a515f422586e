"""The lift calibrated, not trusted (issue #23): volumes with a lift 0.5 % short and long.

The simulated lift runs ``--lift-error`` % off its commanded travel; the host measures its
scale on the calibration cylinder's two grooves (``LiftReference``: a section on the lower
flank of each groove, 140 mm apart on the limb rig's cylinder, 8 views each) and multiplies
every section height by it. Each limb phantom of ``bench_repeat`` is scanned upright on the
limb rig, harsh preset, with the lift 0.5 % short and 0.5 % long (the same plans and the
same two sizes: 8 views, 3 sections 10 mm apart by default, with one calibration per lift
error shared by the phantoms; 6 sections and a calibration per scan in the full study,
``LAMINA_REPEAT_FULL=1`` or ``--full``), in ``LAMINA_REPEAT_WORKERS`` processes, and its
volume between the first and last section is set against the truth between the true
heights of those sections:

- ``lift %``: the simulated lift error and the one measured;
- ``vol %``: the volume error with the lift calibrated, and (``trusted``) as it would be with
  the commanded heights (the volume divided by the measured scale).

Target (issue #23): volumes within 0.1 % of the truth. ``python
tests/benchmarks/bench_lift.py [--keep DIR] [--full]`` runs it alone.
"""

from __future__ import annotations

import argparse
import sys
import time
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import replace
from pathlib import Path
from typing import Any

from bench_limb import true_volume_mm3
from bench_repeat import (
    FULL_ENV,
    PHANTOMS,
    PITCH_MM,
    Phantom,
    Raw,
    acquire_scan,
    cached,
    full_wanted,
    process,
    workers_wanted,
)

from lamina_device.sim import Mechanics, parse_object
from lamina_host.clinical.measures import measure_limb, sections_from_reconstruction

NOISE = "harsh"
LIFT_ERRORS_PERCENT = (-0.5, 0.5)
TARGET_PERCENT = 0.1
TITLE = (
    f"lift calibration on the cylinder's grooves, limb rig, {NOISE} preset: volume error with "
    f"the lift {LIFT_ERRORS_PERCENT[0]:+g} % and {LIFT_ERRORS_PERCENT[1]:+g} % off (target: "
    f"within {TARGET_PERCENT} %)"
)


def scan_row(
    phantom: Phantom, error: float, keep: Path | None, calibration: Raw | None = None
) -> tuple[dict[str, Any], Raw]:
    """Scan one phantom upright with the lift ``error`` % off (the object alone with
    ``calibration``, taken with the same lift error); measure it against the truth; return
    the figures and the raw scan."""
    seed = 77
    key = f"lift-{phantom.name}-{error:+g}-{phantom.sections}x{PITCH_MM:g}"
    if calibration is not None:
        key += "-shared"

    def scan() -> Raw:
        return acquire_scan(phantom.spec, phantom.sections, seed, error, PITCH_MM, calibration)

    raw = cached(keep, key, scan)
    recon, scale = process(raw)
    m = measure_limb(sections_from_reconstruction(recon))
    mechanics = Mechanics.preset(NOISE).with_lift_error(error)
    lo, hi = m.coverage_mm
    true_lo, true_hi = (mechanics.true_z_mm(z / scale) for z in (lo, hi))
    truth = true_volume_mm3(parse_object(phantom.spec), true_lo, true_hi) / 1000.0
    volume = m.volume_mm3 / 1000.0
    lift = recon.lift.to_dict() if recon.lift is not None else {}
    return {
        "lift_error_percent": error,
        "measured_percent": lift.get("error_percent"),
        "applied": lift.get("applied", False),
        "lift_warnings": lift.get("warnings", []),
        "volume_ml": volume,
        "true_volume_ml": truth,
        "volume_error_percent": 100.0 * (volume / truth - 1.0),
        "trusted_error_percent": 100.0 * (volume / scale / truth - 1.0),
        "acquire_s": raw.acquire_s,
    }, raw


def safe_row(
    phantom: Phantom, error: float, keep: Path | None, calibration: Raw | None
) -> tuple[dict[str, Any], Raw | None]:
    """Return :func:`scan_row`'s figures and the scan's calibration, or the failure named
    (a failure is a figure: named in the table) and None."""
    try:
        row, raw = scan_row(phantom, error, keep, calibration)
    except Exception as exc:
        return {"lift_error_percent": error, "error": f"{type(exc).__name__}: {exc}"}, None
    return row, replace(raw, segments=[])


def run(keep: Path | None = None, full: bool | None = None) -> dict[str, Any]:
    """Scan every phantom with each lift error; return the figures.

    The full study (``full``, else ``LAMINA_REPEAT_FULL``) calibrates every scan; the
    default size calibrates once per lift error, with the first phantom's scan.
    """
    whole, start = full_wanted(full), time.perf_counter()
    phantoms = list(PHANTOMS) if whole else [p.quick() for p in PHANTOMS]
    results: dict[str, Any] = {
        "noise": NOISE, "lift_errors_percent": list(LIFT_ERRORS_PERCENT), "full": whole,
        "calibration": "each scan" if whole else "once per lift error",
    }  # fmt: skip
    rows: dict[tuple[str, float], dict[str, Any]] = {}
    with ProcessPoolExecutor(max_workers=workers_wanted()) as pool:
        futures: dict[Future[Any], tuple[Phantom, float]] = {}

        def submit(phantom: Phantom, error: float, calibration: Raw | None) -> None:
            futures[pool.submit(safe_row, phantom, error, keep, calibration)] = (phantom, error)

        for error in LIFT_ERRORS_PERCENT:
            for phantom in phantoms if whole else phantoms[:1]:
                submit(phantom, error, None)
        while futures:
            future = next(as_completed(futures))
            phantom, error = futures.pop(future)
            rows[(phantom.name, error)], calibration = future.result()
            if not whole and phantom is phantoms[0]:
                for other in phantoms[1:]:
                    submit(other, error, calibration)
    for phantom in phantoms:
        results[phantom.name] = {
            "spec": phantom.spec,
            "sections": phantom.sections,
            "rows": [
                rows.get((phantom.name, e), {"lift_error_percent": e, "error": "not scanned"})
                for e in LIFT_ERRORS_PERCENT
            ],
        }
    results["wall_s"] = time.perf_counter() - start
    return results


def report(results: dict[str, Any]) -> list[str]:
    """Return the table: per phantom and lift error, the lift measured and the volume error."""
    size = "full study" if results.get("full") else "default size"
    lines = [
        f"  {size}: calibrated {results.get('calibration', 'each scan')}; "
        f"{results.get('wall_s', float('nan')) / 60:.1f} min",
        "  phantom  lift %  measured %  volume mL  true mL   vol %   trusted vol %",
    ]
    for name in (k for k in results if isinstance(results[k], dict) and "rows" in results[k]):
        for row in results[name]["rows"]:
            if "error" in row:
                lines.append(
                    f"  {name:<8} {row['lift_error_percent']:+5.2f}  failed: {row['error']}"
                )
                continue
            measured = row["measured_percent"]
            shown = f"{measured:+10.4f}" if measured is not None else f"{'-':>10}"
            lines.append(
                f"  {name:<8} {row['lift_error_percent']:+6.2f}  {shown}  "
                f"{row['volume_ml']:9.2f} {row['true_volume_ml']:8.2f}  "
                f"{row['volume_error_percent']:+6.3f}  {row['trusted_error_percent']:+13.3f}"
                + ("" if row["applied"] else f"  NOT APPLIED: {row['lift_warnings'][:1]}")
            )
    return lines


def main() -> int:
    """Run the bench on its own (``--keep DIR`` keeps and reuses the raw scans)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keep", type=Path, help="keep the raw scans here (and reuse them)")
    parser.add_argument("--out", type=Path, help="also write the figures as JSON here")
    parser.add_argument(
        "--full", action="store_true", default=None,
        help=f"6 sections, each scan calibrated afresh (or ${FULL_ENV}=1)",
    )  # fmt: skip
    args = parser.parse_args()
    from run import show  # the bench runner beside this file

    show("lift", sys.modules[__name__], run(args.keep, args.full), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
