"""Repeatability at limb scale (issue #23): the same limb, taken off and put back.

A lymphoedema clinic decides whether a limb changed between visits, so the figure it needs
is how well a scan repeats when the limb is put back on the scanner. Each phantom is
scanned ``LAMINA_REPEAT_N`` times (default 10) on the simulated limb rig with the harsh
preset, each time as a patient would be put back: moved up to 10 mm off the turntable axis
(uniform over the disc), turned by any angle about its own axis, leant by up to 3 degrees
(uniform) towards any azimuth about the point of its axis at its distal landmark (a limb is
put back with its landmark at the scanner's mark, as a tape's zero on the landmark), with a
new noise seed and a new calibration (board, cylinder and lift reference acquired again,
as at each visit; once per phantom in the default size, below).

Each scan is the product's path without the link (as the random-shape campaign): the
simulated device (``open_sim``, :func:`lamina_device.acquisition.acquire`) acquires, the
host reconstructs (:func:`lamina_host.reconstruct.pipeline.reconstruct`) and measures
(:func:`lamina_host.clinical.measures.measure_limb`: levels every ``SPACING_MM`` from the
distal end, PCHIP along z, the default ``auto`` limb axis). The plan is a real limb plan
made shorter: 8 views per section, sections 10 mm apart (20 mm apart, the contour stack's
interpolation alone is 0.1-0.3 % off the true volume of these phantoms). Scans run in
``LAMINA_REPEAT_WORKERS`` processes (default 2). Nearly all of a scan's time is the
simulator rendering its frames (the host's processing takes about a second).

Two sizes. The full study (``LAMINA_REPEAT_FULL=1`` or ``--full``): 6 sections over a
50 mm band of each limb, and each repeat calibrated afresh (board, cylinder and lift
reference acquired again, as at a new visit); 72 views a scan, about 100 s of one core,
30 scans take about half an hour on two cores. The default (``make bench``): 3 sections
over a 20 mm band, and one calibration per phantom, acquired with its first scan, for all
its repeats (one box calibrated once, as in a clinic's session; the rig's geometry does
not depend on the seed, only its noise does); about 8 minutes on two cores. The repeats
are put back, leant and seeded alike in both sizes.

Figures per phantom, as Bland-Altman 95 % limits of agreement (mean difference +- 1.96 SD):

- ``volume``: the volume between the first and the last level (the taped length), in mL
  and %, each repeat against the first scan, and each scan against the truth (the placed
  phantom's true volume between the true heights of those two levels);
- ``circumference`` at each level (distance from the landmark), mm, against the first
  scan and against the truth: the phantom's own cross-section at right angles to its
  axis, where the true axis crosses the level's true height, its perimeter taken at the
  tape's resolution as the host takes it (``TAPE_RESOLUTION_MM``: folds shorter than
  10 mm round the outline left out) and (``exact``) its whole perimeter;
- the axis each scan was measured along and the fitted tilt against the true tilt, and
  the volume's limits on the turntable axis (what measuring a leant limb upright costs).

Targets (issue #23): volume within +-0.2 %, circumferences within +-0.5 mm.
``python tests/benchmarks/bench_repeat.py [--reps N] [--only NAME] [--keep DIR] [--full]``;
``--keep`` stores each scan's raw data and reuses it (reprocessing takes seconds).
"""

from __future__ import annotations

import argparse
import math
import os
import pickle
import sys
import time
from collections.abc import Callable
from concurrent.futures import Future, ProcessPoolExecutor, as_completed
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from bench_limb import true_circumference_mm, true_volume_mm3

from lamina_device.acquisition import acquire, grab_grid
from lamina_device.sim import Mechanics, open_sim, parse_object
from lamina_device.sim.objects import Placement, TriangleMesh
from lamina_host.clinical.measures import (
    OUTLINE_SAMPLES,
    TAPE_RESOLUTION_MM,
    LimbMeasurement,
    measure_limb,
    sections_from_reconstruction,
)
from lamina_host.reconstruct.efd import efd_fit
from lamina_host.reconstruct.measure import perimeter
from lamina_host.reconstruct.pipeline import ProcessOptions, Reconstruction, reconstruct
from lamina_shared.types import LiftReference, ScanPlan, Segment

if __package__ in (None, ""):  # run on its own: find the shared test builders
    sys.path[:0] = [str(Path(__file__).resolve().parents[2])]


NOISE, RIG, VIEWS, PITCH_MM, SPACING_MM = "harsh", "limb", 8, 10.0, 10.0
SHIFT_MM, TILT_DEG = 10.0, 3.0
REPS_ENV = "LAMINA_REPEAT_N"
DEFAULT_REPS = 10
WORKERS_ENV = "LAMINA_REPEAT_WORKERS"
DEFAULT_WORKERS = 2
FULL_ENV = "LAMINA_REPEAT_FULL"
QUICK_SECTIONS = 3
"""Sections of a scan in the default size (levels at 0, 10 and 20 mm from the landmark)."""
TARGET_VOLUME_PERCENT, TARGET_CIRCUMFERENCE_MM = 0.2, 0.5
TITLE = (
    f"repeatability at limb scale, {NOISE} preset, {VIEWS} views, {PITCH_MM:g} mm pitch: "
    f"limits of agreement over scans put back up to {SHIFT_MM:g} mm off the axis, turned, "
    f"leant up to {TILT_DEG:g} deg (targets: volume +-{TARGET_VOLUME_PERCENT} %, "
    f"circumference +-{TARGET_CIRCUMFERENCE_MM} mm)"
)


@dataclass(frozen=True)
class Phantom:
    """A limb phantom, where it stands and its plan.

    ``shape`` is the phantom in its own frame; ``z_mm`` lowers it so the plan's sections
    (from z = 0, ``PITCH_MM`` apart) cover the band of it that matters; ``pivot_mm`` is the
    height on its own axis of its distal end's level (the landmark), about which a repeat
    leans it: a limb is put back with its landmark at the scanner's mark, as a tape's zero
    is put on the landmark.
    """

    name: str
    shape: str
    z_mm: float
    pivot_mm: float
    sections: int
    what: str

    @property
    def spec(self) -> str:
        """Return the ``--object`` of the phantom standing upright on the axis."""
        return f"{self.shape},z={self.z_mm:g}"

    def quick(self) -> Phantom:
        """Return the phantom for the default size: ``QUICK_SECTIONS`` sections, the band
        moved to end at the full band's distal end (``pivot_mm``, the landmark), so the
        short scan keeps the part of the limb the full one is measured from."""
        distal_top = self.pivot_mm >= -self.z_mm + PITCH_MM * (self.sections - 1)
        z_mm = -(self.pivot_mm - PITCH_MM * (QUICK_SECTIONS - 1)) if distal_top else self.z_mm
        return replace(self, z_mm=z_mm, sections=QUICK_SECTIONS)


PHANTOMS = (
    Phantom("arm", "arm:scale=5,relief=0.3,wave=8", -30.0, 30.0, 6,
            "forearm with 0.3 mm skin relief, 30-80 mm from its wrist end"),
    Phantom("stump", "stump:scale=5", -40.0, 90.0, 6,
            "residual limb, 40 mm up to 15 mm below the apex of its rounded end"),
    Phantom("leg", "random:seed=101,scale=limb", -10.0, 60.0, 6,
            "random limb-scale body with a waist and 0.66 mm relief, 10-60 mm"),
)  # fmt: skip


@dataclass(frozen=True)
class Reposition:
    """How one repeat puts the limb back: shift, turn, lean and the noise seed."""

    x_mm: float
    y_mm: float
    yaw_deg: float
    tilt_deg: float
    tilt_dir_deg: float
    seed: int

    @classmethod
    def draw(cls, phantom_index: int, rep: int) -> Reposition:
        """Return repeat ``rep``'s placement (the same for the same indices)."""
        rng = np.random.default_rng([23, phantom_index, rep])
        radius = SHIFT_MM * math.sqrt(rng.uniform())
        angle = rng.uniform(0.0, 2.0 * math.pi)
        return cls(
            radius * math.cos(angle),
            radius * math.sin(angle),
            float(rng.uniform(0.0, 360.0)),
            float(rng.uniform(0.0, TILT_DEG)),
            float(rng.uniform(0.0, 360.0)),
            1000 * phantom_index + rep,
        )

    def spec(self, phantom: Phantom) -> str:
        """Return the ``--object`` of ``phantom`` put back as this repeat puts it."""
        return (
            f"{phantom.spec},x={self.x_mm:.4f},y={self.y_mm:.4f},yaw={self.yaw_deg:.4f},"
            f"tilt={self.tilt_deg:.4f},tilt_dir={self.tilt_dir_deg:.4f},"
            f"pivot={phantom.pivot_mm:g}"
        )

    def placement(self, phantom: Phantom) -> Placement:
        """Return the move from the phantom's own frame to where this repeat puts it."""
        shift = (self.x_mm, self.y_mm, phantom.z_mm)
        return Placement(1.0, self.yaw_deg, shift, self.tilt_deg, self.tilt_dir_deg,
                         phantom.pivot_mm)  # fmt: skip


@dataclass
class Raw:
    """One scan's raw data: the board, the cylinder's and the object's segments."""

    grid_image: np.ndarray
    board: Any
    cylinder_mm: float
    cylinder: list[Segment]
    segments: list[Segment]
    acquire_s: float
    lift_reference: LiftReference | None = None


def acquire_scan(
    spec: str,
    sections: int,
    seed: int,
    lift_error: float | None = None,
    pitch_mm: float = PITCH_MM,
    calibration: Raw | None = None,
) -> Raw:
    """Acquire one scan on the simulated limb rig: a fresh calibration included, or the
    object alone with ``calibration``'s board, cylinder and lift reference (taken earlier
    on the same rig, the same lift)."""
    start = time.perf_counter()
    hardware = open_sim(spec, seed, NOISE, RIG, lift_error_percent=lift_error)
    cylinder: list[Segment] = []
    segments: list[Segment] = []
    try:
        if calibration is None:
            grid = grab_grid(hardware)
            acquire(hardware, "cylinder", hardware.default_plans["cylinder"], cylinder.append)
        plan = ScanPlan.regular(sections, pitch_mm, VIEWS)
        acquire(hardware, "object", plan, segments.append)
    finally:
        hardware.close()
    seconds = time.perf_counter() - start
    if calibration is not None:
        return replace(calibration, segments=segments, acquire_s=seconds)
    assert hardware.board is not None and hardware.cylinder_diameter_mm is not None
    return Raw(grid, hardware.board, hardware.cylinder_diameter_mm, cylinder, segments,
               seconds, hardware.lift_reference)  # fmt: skip


def cached(keep: Path | None, key: str, make: Callable[[], Raw]) -> Raw:
    """Return ``make()``, stored under ``keep/key.pickle`` and reused when there."""
    if keep is None:
        return make()
    path = keep / f"{key}.pickle"
    if path.is_file():
        with path.open("rb") as f:
            return Raw(**pickle.load(f))  # stored as fields: the module may run as __main__
    raw = make()
    keep.mkdir(parents=True, exist_ok=True)
    with path.open("wb") as f:
        pickle.dump(dict(raw.__dict__), f)
    return raw


def process(raw: Raw) -> tuple[Reconstruction, float]:
    """Reconstruct a scan with the default processing; return it and its lift scale."""
    recon = reconstruct(
        raw.grid_image, raw.board, raw.cylinder, raw.cylinder_mm, raw.segments,
        ProcessOptions(), raw.lift_reference,
    )  # fmt: skip
    return recon, recon.lift_scale


def truth(
    own: Any, placement: Placement, m: LimbMeasurement, lift_scale: float, mechanics: Mechanics
) -> dict[str, Any]:
    """Return the true volume between the first and last level and each level's true
    circumference, for the scan measured as ``m`` of the phantom (``own``: in its own
    frame) put where ``placement`` puts it."""
    obj = TriangleMesh(placement.apply(own.vertices), own.faces, own.name)

    def true_z(z_host_mm: float) -> float:
        return mechanics.true_z_mm(z_host_mm / lift_scale)

    first, last = m.levels[0], m.levels[-1]
    z_lo, z_hi = sorted((true_z(first.z_mm), true_z(last.z_mm)))
    rotation = placement.rotation
    circumferences, tape = [], []
    for level in m.levels:
        # Where the phantom's own axis crosses the level's true height, in its own frame.
        own_height = (true_z(level.z_mm) - placement.offset_mm[2]) / rotation[2, 2]
        circumferences.append(true_circumference_mm(own, own_height))
        tape.append(tape_circumference_mm(own, own_height))
    return {
        "volume_ml": true_volume_mm3(obj, z_lo, z_hi) / 1000.0,
        "circumference_mm": circumferences,
        "tape_mm": tape,
    }


def tape_circumference_mm(obj: Any, z_mm: float) -> float:
    """Return the true outline's perimeter at the tape's resolution (as the host measures
    circumferences: harmonics shorter than ``TAPE_RESOLUTION_MM`` round it left out)."""
    outlines = obj.section_outline(z_mm)
    if not outlines:
        return math.nan
    outline = max(outlines, key=perimeter)
    order = max(1, int(perimeter(outline) / TAPE_RESOLUTION_MM))
    return perimeter(efd_fit(outline, order, "chord").evaluate(OUTLINE_SAMPLES))


def scan_record(
    phantom: Phantom,
    index: int,
    rep: int,
    keep: Path | None,
    mechanics: Mechanics,
    calibration: Raw | None = None,
) -> tuple[dict[str, Any], Raw]:
    """Scan (or reuse) one repeat, measure it and set it against the truth; return the
    figures and the raw scan (whose calibration the default size's later repeats share).
    With ``calibration`` only the object is acquired."""
    reposition = Reposition.draw(index, rep)
    spec = reposition.spec(phantom)
    key = f"{phantom.name}-{rep}-{reposition.seed}-{phantom.sections}x{PITCH_MM:g}x{VIEWS}-lift"
    if calibration is not None:
        key += "-shared"
    start = time.perf_counter()
    seed, sections = reposition.seed, phantom.sections

    def scan() -> Raw:
        return acquire_scan(spec, sections, seed, None, PITCH_MM, calibration)

    raw = cached(keep, key, scan)
    recon, lift_scale = process(raw)
    sections = sections_from_reconstruction(recon)
    m = measure_limb(sections, SPACING_MM)
    upright = measure_limb(sections, SPACING_MM, axis="turntable")
    own = parse_object(phantom.shape)
    placement = reposition.placement(phantom)
    true = truth(own, placement, m, lift_scale, mechanics)
    true_upright = truth(own, placement, upright, lift_scale, mechanics)
    record = {
        "spec": spec,
        "seed": reposition.seed,
        "tilt_deg": reposition.tilt_deg,
        "shift_mm": math.hypot(reposition.x_mm, reposition.y_mm),
        "axis": m.axis.method,
        "axis_choice": m.axis.choice,
        "fitted_tilt_deg": measure_limb(sections, SPACING_MM, axis="centreline").axis.tilt_deg,
        "lift_scale": lift_scale,
        "volume_ml": m.levels_volume_mm3 / 1000.0,
        "true_volume_ml": true["volume_ml"],
        "turntable_volume_ml": upright.levels_volume_mm3 / 1000.0,
        "turntable_true_volume_ml": true_upright["volume_ml"],
        "levels": [
            level_record(lv, c, t)
            for lv, c, t in zip(m.levels, true["circumference_mm"], true["tape_mm"], strict=True)
        ],
        "warnings": list(recon.warnings),
        "acquire_s": raw.acquire_s,
        "wall_s": time.perf_counter() - start,
    }
    return record, raw


def level_record(level: Any, true_mm: float, tape_mm: float) -> dict[str, Any]:
    """Return one level's figures: offset, height, circumference and its truths (the exact
    perimeter, and at the tape's resolution)."""
    return {
        "offset_mm": level.offset_mm,
        "z_mm": level.z_mm,
        "circumference_mm": level.circumference_mm,
        "true_mm": true_mm,
        "true_tape_mm": tape_mm,
        "source": level.source,
    }


def limits(differences: list[float]) -> dict[str, float]:
    """Return the Bland-Altman limits of agreement: mean +- 1.96 SD (n - 1) of differences."""
    d = np.asarray(differences, dtype=float)
    d = d[np.isfinite(d)]
    if len(d) < 2:
        return {"n": len(d), "mean": math.nan, "sd": math.nan, "lo": math.nan, "hi": math.nan}
    mean, sd = float(d.mean()), float(d.std(ddof=1))
    return {"n": len(d), "mean": mean, "sd": sd, "lo": mean - 1.96 * sd, "hi": mean + 1.96 * sd}


def summarise(reps: list[dict[str, Any]]) -> dict[str, Any]:
    """Return one phantom's limits of agreement against its first scan and the truth."""
    done = [r for r in reps if "volume_ml" in r]
    if not done:
        return {}
    first = done[0]
    v0 = first["volume_ml"]
    out: dict[str, Any] = {
        "volume_ml_vs_first": limits([r["volume_ml"] - v0 for r in done[1:]]),
        "volume_percent_vs_first": limits([100.0 * (r["volume_ml"] / v0 - 1.0) for r in done[1:]]),
        "volume_ml_vs_truth": limits([r["volume_ml"] - r["true_volume_ml"] for r in done]),
        "volume_percent_vs_truth": limits(
            [100.0 * (r["volume_ml"] / r["true_volume_ml"] - 1.0) for r in done]
        ),
        "turntable_volume_percent_vs_truth": limits(
            [100.0 * (r["turntable_volume_ml"] / r["turntable_true_volume_ml"] - 1.0) for r in done]
        ),
        "fitted_tilt_error_deg": limits([r["fitted_tilt_deg"] - r["tilt_deg"] for r in done]),
        "axes": {a: sum(r["axis"] == a for r in done) for a in ("turntable", "centreline")},
    }
    by_first = {round(lv["offset_mm"], 6): lv["circumference_mm"] for lv in first["levels"]}
    levels: dict[float, dict[str, list[float]]] = {}
    for k, r in enumerate(done):
        for lv in r["levels"]:
            key = round(lv["offset_mm"], 6)
            entry = levels.setdefault(key, {"vs_first": [], "vs_truth": [], "vs_exact": []})
            entry["vs_truth"].append(lv["circumference_mm"] - lv["true_tape_mm"])
            entry["vs_exact"].append(lv["circumference_mm"] - lv["true_mm"])
            if k and key in by_first:
                entry["vs_first"].append(lv["circumference_mm"] - by_first[key])
    out["circumference_mm"] = {
        f"{offset:g}": {name: limits(values) for name, values in entry.items()}
        for offset, entry in sorted(levels.items())
    }
    return out


def reps_wanted(given: int | None = None) -> int:
    """Return the repeats per phantom: ``given``, else ``LAMINA_REPEAT_N``, else 10."""
    if given is not None:
        return given
    text = os.environ.get(REPS_ENV, "")
    try:
        return max(2, int(text)) if text else DEFAULT_REPS
    except ValueError:
        raise SystemExit(f"{REPS_ENV}={text!r} must be a whole number of repeats") from None


def safe_record(
    phantom: Phantom, index: int, rep: int, keep: Path | None, calibration: Raw | None = None
) -> tuple[dict[str, Any], Raw | None]:
    """Return :func:`scan_record`'s figures and the scan's calibration (its raw data without
    the object), or the failure named (a figure too) and None."""
    try:
        record, raw = scan_record(phantom, index, rep, keep, Mechanics.preset(NOISE), calibration)
    except Exception as exc:
        return {"error": f"{type(exc).__name__}: {exc}"[:300]}, None
    return record, replace(raw, segments=[])


def full_wanted(given: bool | None = None) -> bool:
    """Return whether the full study is asked for: ``given``, else ``LAMINA_REPEAT_FULL``."""
    if given is not None:
        return given
    text = os.environ.get(FULL_ENV, "").strip().lower()
    if text not in ("", "0", "1", "no", "yes", "false", "true"):
        raise SystemExit(f"{FULL_ENV}={text!r} must be 1 (the full study) or 0")
    return text in ("1", "yes", "true")


def workers_wanted() -> int:
    """Return the worker processes: ``LAMINA_REPEAT_WORKERS``, else 2 (the machine's cores)."""
    text = os.environ.get(WORKERS_ENV, "")
    try:
        return max(1, int(text)) if text else DEFAULT_WORKERS
    except ValueError:
        raise SystemExit(f"{WORKERS_ENV}={text!r} must be a whole number of processes") from None


def run(
    reps: int | None = None,
    only: list[str] | None = None,
    keep: Path | None = None,
    full: bool | None = None,
) -> dict:
    """Scan every phantom ``reps`` times, put back each time; return the figures.

    The full study (``full``, else ``LAMINA_REPEAT_FULL``) calibrates every scan afresh;
    the default size scans fewer sections and gives each phantom's first scan's
    calibration to its other repeats (they are submitted once that scan is done).
    """
    count, workers, whole = reps_wanted(reps), workers_wanted(), full_wanted(full)
    start = time.perf_counter()
    results: dict[str, Any] = {
        "reps": count, "noise": NOISE, "views": VIEWS, "pitch_mm": PITCH_MM,
        "spacing_mm": SPACING_MM, "shift_mm": SHIFT_MM, "tilt_deg": TILT_DEG,
        "workers": workers, "full": whole,
        "calibration": "each scan" if whole else "once per phantom",
    }  # fmt: skip
    chosen = [
        (k, p if whole else p.quick()) for k, p in enumerate(PHANTOMS) if not only or p.name in only
    ]
    done: dict[tuple[str, int], dict[str, Any]] = {}
    with ProcessPoolExecutor(max_workers=workers) as pool:
        futures: dict[Future[Any], tuple[Phantom, int, int]] = {}

        def submit(phantom: Phantom, index: int, rep: int, calibration: Raw | None) -> None:
            future = pool.submit(safe_record, phantom, index, rep, keep, calibration)
            futures[future] = (phantom, index, rep)

        for index, phantom in chosen:  # the first scans (all of them in the full study)
            for rep in range(count if whole else 1):
                submit(phantom, index, rep, None)
        while futures:
            future = next(as_completed(futures))
            phantom, index, rep = futures.pop(future)
            done[(phantom.name, rep)], calibration = future.result()
            print(f"  {phantom.name} {rep + 1}/{count}", file=sys.stderr)
            if not whole and rep == 0:  # the others share this scan's calibration
                for later in range(1, count):
                    submit(phantom, index, later, calibration)
    for rep_key in [(p.name, r) for _, p in chosen for r in range(count)]:
        done.setdefault(rep_key, {"error": "not scanned: its phantom's first scan failed"})
    results["wall_s"] = time.perf_counter() - start
    for _, phantom in chosen:
        reps_done = [done[(phantom.name, rep)] for rep in range(count)]
        results[phantom.name] = {
            "spec": phantom.spec,
            "what": phantom.what,
            "sections": phantom.sections,
            "reps": reps_done,
            "summary": summarise(reps_done),
        }
    return results


def _loa(d: dict[str, float], unit: str = "", digits: int = 2) -> str:
    if not d or not math.isfinite(d.get("mean", math.nan)):
        return "-"
    return f"{d['mean']:+.{digits}f} [{d['lo']:+.{digits}f}, {d['hi']:+.{digits}f}]{unit}"


def report(results: dict[str, Any]) -> list[str]:
    """Return the table: limits of agreement per phantom, volume then each level."""
    size = "full study" if results.get("full") else "default size"
    lines = [
        f"  {results['reps']} scans per phantom ({size}: calibrated "
        f"{results.get('calibration', 'each scan')}; "
        f"{results.get('wall_s', math.nan) / 60:.1f} min); "
        "mean difference [95 % limits of agreement]",
        "  phantom  axes (tt/cl)  volume mL   vs first mL            vs first %"
        "               vs truth %               turntable axis vs truth %  "
        "tilt fit error deg",
    ]
    for name in (k for k in results if isinstance(results[k], dict) and "reps" in results[k]):
        row = results[name]
        s = row["summary"]
        failed = [r["error"] for r in row["reps"] if "error" in r]
        if not s:
            lines.append(f"  {name:<8} failed: {failed[:1]}")
            continue
        done = [r for r in row["reps"] if "volume_ml" in r]
        axes = f"{s['axes']['turntable']}/{s['axes']['centreline']}"
        lines.append(
            f"  {name:<8} {axes:>12}  {done[0]['volume_ml']:9.2f}  "
            f"{_loa(s['volume_ml_vs_first']):<22} {_loa(s['volume_percent_vs_first'], '', 3):<24} "
            f"{_loa(s['volume_percent_vs_truth'], '', 3):<24} "
            f"{_loa(s['turntable_volume_percent_vs_truth'], '', 3):<26} "
            f"{_loa(s['fitted_tilt_error_deg'], '', 3)}"
        )
        for offset, entry in s["circumference_mm"].items():
            lines.append(
                f"           circumference at {offset:>4} mm: vs first "
                f"{_loa(entry['vs_first']):<24} vs truth {_loa(entry['vs_truth']):<24} "
                f"vs exact perimeter {_loa(entry['vs_exact'])}"
            )
        if failed:
            lines.append(f"           {len(failed)} scan(s) failed: {failed[0]}")
        wall = sum(r["wall_s"] for r in done) / len(done)
        lines.append(f"           mean wall time per scan {wall:.0f} s")
    return lines


def main() -> int:
    """Run the bench on its own (``--reps``, ``--only``, ``--keep``, ``--out``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reps", type=int, help=f"scans per phantom (default ${REPS_ENV} or 10)")
    parser.add_argument("--only", action="append", help="only this phantom (arm, stump, leg)")
    parser.add_argument("--keep", type=Path, help="keep the raw scans here (and reuse them)")
    parser.add_argument("--out", type=Path, help="also write the figures as JSON here")
    parser.add_argument(
        "--full", action="store_true", default=None,
        help=f"the full study: 6 sections, each scan calibrated afresh (or ${FULL_ENV}=1)",
    )  # fmt: skip
    args = parser.parse_args()
    from run import show  # the bench runner beside this file

    figures = run(args.reps, args.only, args.keep, args.full)
    show("repeat", sys.modules[__name__], figures, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
