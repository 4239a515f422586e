"""The patient's wait (issue 22): how long plans keep a limb still, and what each mode costs.

**Time.** Each plan is modelled on the shipped configuration (``default_config.toml``: the
box's steppers, settle times and camera) by :func:`lamina_device.timing.estimate_scan_time`
in both modes: stop-and-go (view by view with the axes' own profiles; ``axes_in_turn_s``:
the lift and table one after the other, as the loop ran before) and continuous (the table
ramped up once and turning at ``continuous_speed_deg_s`` through every section, the lift
moving between sections). The mechanical minimum is the moves, settles and frames only.
The processing per view is measured here: the default extraction of a harsh
laser-off/laser-on pair from the simulated limb rig at the box's 1536x864, with its
segment's wire bytes, and for a continuous view the room light brought to the laser-on
frame's instant first; OpenCV runs on the calling thread, as the device program runs it
(an x86 host; a Pi core is roughly 2-4x slower: stop-and-go still far below a view's
mechanics, a continuous view 1-2x the 125 ms between views at the shipped speed, which
the device's queue of views takes up while the lift moves, not measured on a Pi). Rows:
the default plan of the configuration, the simulator's default (thesis) plan and a 400 mm
leg at 10 mm pitch with 8 views.

**Accuracy.** The same limb phantoms (harsh preset, limb rig: ``bench_limb``'s set,
``arm:scale=5`` 8 sections and ``stump:scale=5`` 11 sections at 10 mm, 8 views) are
scanned in both modes in this process (the simulated device's acquisition, then the host's
default processing, each continuous point at its own row's angle as the product takes it;
the calibration board and cylinder are taken once, stop-and-go, as a scan takes them)
and measured as ``bench_limb`` measures them: volume over the scanned range, and the
circumference at a level at every section (10 mm apart) against the true shape. Each
mode scans each phantom with four noise draws (the simulator's seed, ``ACCURACY_DRAWS``;
two worker processes), since a level's error moves by 0.03-0.04 mm from draw to draw, as
far as the modes stand apart; the modes are compared on each phantom's volume and worst
circumference error averaged over the draws and on the RMS circumference error over all
levels and draws (19 levels a draw in the full study). The continuous frames are
rendered with the rolling shutter, the motion blur over each exposure, the table turning
between a view's laser-off, laser-on and laser-off frames, and the frame timestamps'
jitter (``lamina_device.sim.camera``).

**Sway.** The arm is scanned again in both modes with the simulated patient's sway
(``patient``: 1 mm a minute of drift and 0.5 mm breathing at 0.25 Hz; ``strong``: 3 mm a
minute and 1.5 mm at 0.3 Hz): volume and circumference errors against the scan's time,
and the report's motion warnings (sections whose overlapping views stand apart beyond
their noise, ``reconstruct/precision.py``). Within a section the views are taken in about
11 s stop-and-go and about 1 s continuously; the sway between sections moves a section
whole, which changes no area. Within a continuous turn the limb moves the same way under
every view, and each view sees the side facing the camera, so a movement along the
camera's line of sight grows or shrinks the whole section while its views still nearly
agree: the bench shows it as a circumference error far above the views' disagreement.
The 400 mm leg's modelled times in each mode say what the patient holds for the whole leg.

**Laser-off frames a turn later.** The phantoms are smooth; random limb shapes with fine
skin relief are not (``RELIEF_SEEDS``): each is scanned stop-and-go, continuously with the
interleaved laser-off frames (the default), and continuously with each view's laser-off
frame a turn later at the same angle (``continuous_off_frames = "next-turn"``, the frame
period a turn divides), on the campaign's harsh limb plan (2 sections of 8 views) in two
worker processes; ``next_turn_rows`` gives each plan's modelled time that way. The
simulated gear turns 1.6 degrees a turn short of its count, so the frame a turn of the
count later misses the laser-on frame's angle; the last way (``next-turn geared``) scans
on a box whose ``gear_ratio`` is the one its own calibration names
(``lamina_host.reconstruct.axis.gear_advice``), as a technician would set it.

**Quick by default.** A continuous frame renders each band of rows at its own pose, three
frames a view, about 6 s of processor time a view, so ``make bench`` (and
``python tests/benchmarks/bench_scan_time.py``) runs the quick set: every plan's modelled
times, the arm's first three sections still in both modes with four noise draws each, and
its first three with the strong sway in both modes (about 10 minutes of processor time).
The full study above (both phantoms with four draws, both sways; about two hours of
processor time by the same rates; not yet run to its end) is
``python tests/benchmarks/bench_scan_time.py --full``, or ``LAMINA_SCAN_TIME_FULL=1 make
bench``.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import tempfile
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

TITLE = (
    "the patient's wait: modelled scan time of both modes on the default configuration, and "
    "each mode's limb accuracy with and without sway (issue 22)"
)
MODES = ("stop-and-go", "continuous")
NOISE, RIG, PITCH_MM, VIEWS = "harsh", "limb", 10.0, 8
OBJECTS = (
    ("arm", "arm:scale=5", 8),
    ("stump", "stump:scale=5", 11),
)
"""The phantoms compared (``bench_limb``'s set): name, object, sections."""
QUICK_OBJECTS = (("arm", "arm:scale=5", 3),)
"""The quick set: the arm's first three sections (``bench_limb``'s quick arm)."""
ACCURACY_DRAWS = (0, 1, 2, 3)
"""The noise draws (the simulator's seed) each mode scans the still phantoms with. Within
one mode a level's circumference error moves by 0.03-0.04 mm (one standard deviation) from
one draw to the next, as far as the modes ever stood apart: on one draw the comparison
ranked the draws, not the modes. A frame period 1 us longer or shorter renders other
frames, so it is another draw too: the arm's worst level measured 0.12-0.21 mm
continuously over draws 0-3 and over draw 0 at 8332, 8334 and 8335 us, and 0.13-0.20 mm
stop-and-go over draws 0-6."""
SWAY_SECTIONS = QUICK_SWAY_SECTIONS = 3
"""Sections of the arm scanned with each sway: the first three of the plan (the fewest
with an inner section, which the check of consecutive sections needs)."""
SWAYS = (
    ("patient", "patient"),
    ("strong", "drift=3,breath=1.5,hz=0.3"),
)
"""The simulated sways: name, ``--sway`` spec."""
QUICK_SWAYS = SWAYS[1:]
"""The quick set's sway: the strong one, where the warning is expected."""
FULL = os.environ.get("LAMINA_SCAN_TIME_FULL", "") not in ("", "0")
"""``LAMINA_SCAN_TIME_FULL=1``: ``make bench`` runs the full study, not the quick set."""
RELIEF_SEEDS = (97101, 97103, 97104, 97106)
"""Random limb-scale shapes nobody tuned continuous mode on: two with fine skin relief
(97101, 97104), two smooth and off the axis (97103, 97106)."""
RELIEF_WAYS = (
    ("stop-and-go", "stop-and-go", "interleaved", False),
    ("continuous", "continuous", "interleaved", False),
    ("next-turn", "continuous", "next-turn", False),
    ("next-turn geared", "continuous", "next-turn", True),
)
"""How each random shape is scanned: name, plan mode, the box's laser-off frames, and
whether the box's ``gear_ratio`` is the one its calibration names (``gear_advice``: the
simulated gear turns 1.6 degrees a turn short of the shipped ratio's count)."""
WORKERS = 2
"""Worker processes for the still scans and the random shapes (this machine's cores)."""
MOTION_WARNING = "overlapping views stand"
"""What the report's motion warning says (``store/outputs.py``)."""
JUMP_WARNING = "off the line of the sections below and above"
"""What the report's warning of a section off its neighbours says (``store/outputs.py``)."""


def _processing_s() -> dict[str, float]:
    """Return one view's processing on this machine (best of 5), by mode: stop-and-go, its
    extraction and segment encoding; continuous (interleaved laser-off frames), the room
    light brought to the laser-on frame's instant as well (``room_light``)."""
    from timing import opencv_inline

    from lamina_device.acquisition import capture_moving, capture_pair
    from lamina_device.backends import open_hardware
    from lamina_device.extract import extract, to_segment
    from lamina_device.room_light import laser_off_reference
    from lamina_shared.protocol import encode_segment, quantise_segment

    hardware = open_hardware("sim", "arm:scale=5", noise="harsh", rig="limb")
    try:
        hardware.place("object")
        hardware.lift.move_to(20.0)
        on, off = capture_pair(hardware)
        hardware.turntable.spin()
        lit, before, after = capture_moving(hardware, hardware.camera)
        hardware.turntable.stop_spin()
    finally:
        hardware.close()

    def best(view: Callable[[], Any]) -> float:
        times = []
        with opencv_inline():  # as the device program runs it on the box
            for _ in range(5):
                start = time.perf_counter()
                view()
                times.append(time.perf_counter() - start)
        return min(times)

    def encoded(points: Any) -> bytes:
        return encode_segment(1, 1, quantise_segment(to_segment(points, "object", 0, 0, 20.0, 0.0)))

    return {
        "stop-and-go": best(lambda: encoded(extract(on, off, hardware.extract))),
        "continuous": best(
            lambda: encoded(
                extract(lit.image, laser_off_reference(before, lit.image, after), hardware.extract)
            )
        ),
    }


def _time_plans(config: Any) -> dict[str, Any]:
    """Return the timed plans by name: the configured default, the thesis's, a 400 mm leg."""
    from lamina_device.sim.backend import DEFAULT_PLAN
    from lamina_shared.types import ScanPlan

    return {
        "default (config)": ScanPlan.regular(
            config.plan.sections, config.plan.pitch_mm, config.plan.views
        ),
        "thesis (sim default)": DEFAULT_PLAN,
        "leg 400 mm, 10 mm pitch": ScanPlan.regular(40, 10.0, 8),
    }


def time_rows(processing_s: dict[str, float], workers: int | None = None) -> list[dict[str, Any]]:
    """Return one row per plan and mode: the modelled time and the mechanical minimum, with
    ``workers`` continuous views processed at once (by default as the device program would
    on this machine's cores, :func:`~lamina_device.timing.view_workers`)."""
    from lamina_device.config import load_config
    from lamina_device.timing import estimate_scan_time, view_workers

    workers = view_workers() if workers is None else workers
    config = load_config()
    rows = []
    for name, plan in _time_plans(config).items():
        heights = [v.z_mm for v in plan.views]
        for mode in MODES:
            moded = plan.with_mode(mode)
            estimate = estimate_scan_time(config, moded, processing_s[mode], workers=workers)
            row: dict[str, Any] = {
                "plan": name,
                "mode": mode,
                "height_mm": round(max(heights) - min(heights), 6),
                "sections": len(plan.sections),
                "views": len(plan.views),
                "modelled_s": round(estimate.modelled_s, 3),
                "mechanical_minimum_s": round(estimate.mechanical_minimum_s, 3),
                "ratio": round(estimate.ratio, 4),
                "turntable_s": round(estimate.turntable_s, 3),
                "lift_s": round(estimate.lift_s, 3),
                "view_workers": workers if mode == "continuous" else 1,
            }
            if mode == "stop-and-go":
                in_turn = estimate_scan_time(config, moded, processing_s[mode], axes_together=False)
                row["axes_in_turn_s"] = round(in_turn.modelled_s, 3)
            rows.append(row)
    return rows


SLOWER_CORES = (2.0, 4.0)
"""How much slower than this host a Pi's cores are taken to be (a Pi 4's Cortex-A72 is
roughly 2-4x slower than an x86 core): the continuous rows are modelled again with the
processing per view so multiplied, since nothing here runs on a Pi."""
PI_CORES = 4
"""A Pi 4's or 5's cores: the device program processes ``view_workers(4)`` continuous
views at once there (one view keeps 1.9 of this host's two cores busy)."""


def slower_core_rows(processing_s: dict[str, float]) -> list[dict[str, Any]]:
    """Return each plan's continuous modelled time with its processing per view times each
    of :data:`SLOWER_CORES`, on one processing thread (a 2-core machine) and on a Pi's
    :data:`PI_CORES`: where a view's processing outlasts the table's time to the next
    view, its backlog must be taken up while the lift moves."""
    from lamina_device.timing import view_workers

    rows = []
    for factor in SLOWER_CORES:
        slower = {mode: seconds * factor for mode, seconds in processing_s.items()}
        for workers in (1, view_workers(PI_CORES)):
            for row in time_rows(slower, workers):
                if row["mode"] == "continuous":
                    per_view_s = round(slower["continuous"], 5)
                    rows.append(row | {"slower": factor, "processing_s_per_view": per_view_s})
    return rows


def next_turn_rows(
    rows: list[dict[str, Any]], processing_s: dict[str, float]
) -> list[dict[str, Any]]:
    """Return each plan's modelled time continuously with laser-off frames a turn later
    (``continuous_off_frames = "next-turn"`` and the frame period a turn divides), beside
    its interleaved time from ``rows`` (:func:`time_rows`)."""
    from lamina_device.config import load_config
    from lamina_device.timing import estimate_scan_time
    from tests.helpers.campaign import next_turn_config

    config = next_turn_config(load_config())
    plans = _time_plans(config)
    return [
        {
            "plan": row["plan"],
            "frame_duration_us": config.camera.frame_duration_us,
            "modelled_s": round(
                estimate_scan_time(
                    # A next-turn view's off frame is its room light as it stands.
                    config,
                    plans[row["plan"]].with_mode("continuous"),
                    processing_s["stop-and-go"],
                ).modelled_s,
                3,
            ),
            "interleaved_s": row["modelled_s"],
        }
        for row in rows
        if row["mode"] == "continuous"
    ]


def retime_rows(rows: list[dict[str, Any]], processing_s: dict[str, float]) -> list[dict[str, Any]]:
    """Return each plan's modelled time continuously with the table slowed during the lift's
    moves (``continuous_retime = true``, off by default), beside its time from ``rows``."""
    from lamina_device.config import load_config
    from lamina_device.timing import estimate_scan_time

    shipped = load_config()
    config = replace(shipped, turntable=replace(shipped.turntable, continuous_retime=True))
    plans = _time_plans(config)
    out = []
    for row in rows:
        if row["mode"] != "continuous":
            continue
        estimate = estimate_scan_time(
            config, plans[row["plan"]].with_mode("continuous"), processing_s["continuous"]
        )
        out.append(
            {
                "plan": row["plan"],
                "modelled_s": round(estimate.modelled_s, 3),
                "ratio": round(estimate.ratio, 4),
                "shipped_s": row["modelled_s"],
            }
        )
    return out


def relief(workers: int = WORKERS) -> list[dict[str, Any]]:
    """Scan :data:`RELIEF_SEEDS` each way of :data:`RELIEF_WAYS` (harsh, limb rig, 2 x 8)
    in the campaign's worker processes (``bench_campaign.run_scale``).

    Returns:
        One row per seed and way: mean surface distance, coverage, motion warnings.
    """
    from lamina_host.reconstruct.axis import gear_ratio_factor
    from tests.benchmarks.bench_campaign import run_scale
    from tests.helpers.campaign import CampaignPlan, calibrated_axis

    rows = []
    for name, mode, off, geared in RELIEF_WAYS:
        plan = CampaignPlan(RIG, 2, PITCH_MM, VIEWS, NOISE, mode=mode, off_frames=off)
        if geared:  # the ratio the calibration names, as a technician would set it
            plan = replace(plan, gear_ratio_factor=gear_ratio_factor(calibrated_axis(plan)) or 1.0)
        for r in run_scale(plan, list(RELIEF_SEEDS), workers, math.inf)["results"]:
            rows.append(
                {
                    "seed": r["seed"],
                    "way": name,
                    "group": r["group"],
                    "mean_distance_mm": r["mean_distance_mm"],
                    "coverage": r["coverage"],
                    "motion_warnings": len(r["motion_warnings"]),
                    "failure": f"{r['error_type']}@{r['stage']}" if r["stage"] else "",
                }
            )
    return sorted(rows, key=lambda row: row["seed"])


def scan(
    calibration: Any, spec: str, sections: int, mode: str, sway: str, draw: int = 0
) -> dict[str, Any]:
    """Scan one phantom in one mode with one sway and noise draw; return its errors, time and
    warnings."""
    from bench_limb import measure

    from lamina_device.acquisition import acquire, row_turn_deg
    from lamina_device.sim import open_sim
    from lamina_device.timing import estimate_scan_time
    from lamina_host.reconstruct.continuity import outline_jumps
    from lamina_host.reconstruct.pipeline import ProcessOptions, assemble, reconstruct
    from lamina_host.reconstruct.precision import views_disagreement_mm
    from lamina_host.store.outputs import build_report, write_outputs
    from lamina_shared.types import ScanPlan

    plan = ScanPlan.regular(sections, PITCH_MM, VIEWS, mode)
    hardware = open_sim(spec, draw, NOISE, RIG, sway=sway)
    clock = hardware.turntable.clock
    segments: list[Any] = []
    arrived_s: list[float] = []  # each segment's arrival on the clock, should frames not tell

    def keep(segment: Any) -> None:
        segments.append(segment)
        arrived_s.append(clock.now_s)

    wall = time.perf_counter()
    try:
        hardware.lift.move_to(plan.views[0].z_mm)  # homing and the first move: not the wait
        start_s = clock.now_s
        acquire(hardware, "object", plan, keep)
        # The wait: from the first move to the last view's last frame (the table then
        # slows down and the lift goes home, the patient free to move).
        scan_s = hardware.camera.last_frame_s - start_s
    finally:
        hardware.close()
    wall_s = time.perf_counter() - wall
    print(
        f"  ({spec} {mode} sway={sway} draw {draw}: {len(plan.views)} views in {wall_s:.0f} s)",
        flush=True,
    )
    assert hardware.board is not None and hardware.cylinder_diameter_mm is not None
    # As the product processes it: each continuous point at its own row's angle.
    row_turn = row_turn_deg(hardware) if plan.continuous else 0.0
    recon = reconstruct(
        calibration.grid_image,
        hardware.board,
        calibration.cylinder,
        hardware.cylinder_diameter_mm,
        segments,
        ProcessOptions(),
        row_turn_deg=row_turn,
    )
    modelled = estimate_scan_time(hardware.timing, plan, exposure_us=hardware.camera.exposure_us)
    report = build_report(recon, {"kind": "sim"}, segments, None, {})
    with tempfile.TemporaryDirectory() as tmp:
        write_outputs(Path(tmp), recon, report)
        figures = measure(spec, json.loads((Path(tmp) / "report.json").read_text()), PITCH_MM)
    warnings = [w for w in report.warnings if MOTION_WARNING in w]
    jumps = outline_jumps(recon.sections)
    trim = recon.options.trim_fraction
    by_section, _, _ = assemble(segments, recon.grid, recon.axis, trim, row_turn)
    apart = {k: round(views_disagreement_mm(v), 3) for k, v in sorted(by_section.items())}
    return {
        "spec": spec,
        "mode": mode,
        "sway": sway,
        "draw": draw,
        "sections": sections,
        "scan_s": round(scan_s, 3),
        "modelled_s": round(modelled.modelled_s, 3),
        "wall_s": round(wall_s, 1),
        "volume_error_percent": figures["volume_error_percent"],
        "volume_error_without_lift_percent": figures["volume_error_without_lift_percent"],
        "max_abs_circumference_error_mm": figures["max_abs_circumference_error_mm"],
        "circumference_errors_mm": [round(level["error_mm"], 4) for level in figures["levels"]],
        "motion_warnings": warnings,
        "views_apart_mm": apart,
        "jump_warnings": [w for w in report.warnings if JUMP_WARNING in w],
        "jumps_mm": {j.index: round(j.jump_mm, 3) for j in jumps if j.part == 0},
        "jump_limits_mm": {j.index: round(j.limit_mm, 3) for j in jumps if j.part == 0},
        **_sway_truth(hardware, segments, _exposed_s(hardware, arrived_s), sway),
    }


def _exposed_s(hardware: Any, arrived_s: list[float]) -> list[float]:
    """Return when each view's laser-on frame arrived on the virtual clock: where the sway
    had the subject. A segment reaches the bench's callback later, when the device's
    extraction thread is done with it, which the machine's load moves (the same frames
    read 0.36 and 0.19 mm of true offset two runs apart); the segments come in the order
    their frames were taken, so the camera's own record serves where it holds one frame
    a segment, the arrival times otherwise."""
    lit_s = list(hardware.camera.lit_frames_s)
    return lit_s if len(lit_s) == len(arrived_s) else arrived_s


def _sway_truth(
    hardware: Any, segments: list[Any], exposed_s: list[float], sway: str
) -> dict[str, Any]:
    """Return where the sway had the limb at each section (the mean over its views), its
    part along the camera's line of sight (which grows or shrinks a continuous section),
    and each inner section's true offset from the line of its neighbours (both figures)."""
    from lamina_device.sim.sway import parse_sway

    motion = parse_sway(sway)
    camera = np.asarray(hardware.camera.scene.rig.camera_centre_mm, dtype=float)[:2]
    toward = camera / np.linalg.norm(camera)  # from the axis to the camera, horizontal
    times: dict[int, list[float]] = {}
    for segment, t_s in zip(segments, exposed_s, strict=True):
        times.setdefault(segment.section, []).append(t_s)
    moved = {k: np.mean([motion.offset_mm(t) for t in ts], axis=0) for k, ts in times.items()}
    keys = sorted(moved)
    shift: dict[int, float] = {}
    size: dict[int, float] = {}
    for below, here, above in zip(keys, keys[1:], keys[2:], strict=False):
        off = moved[here] - 0.5 * (moved[below] + moved[above])
        shift[here], size[here] = round(float(np.linalg.norm(off)), 3), round(off @ toward, 3)
    return {
        "moved_mm": {k: [round(float(v), 3) for v in moved[k]] for k in keys},
        "toward_camera_mm": {k: round(float(moved[k] @ toward), 3) for k in keys},
        "true_jumps_mm": shift,
        "true_size_jumps_mm": size,
    }


def run(full: bool = FULL) -> dict[str, Any]:
    """Model every plan in both modes; scan the phantoms in both modes, still and swaying.

    Args:
        full: the full study (both phantoms, four draws, both sways, about 2 processor
            hours); otherwise the quick set (the arm's first sections, the strong sway, about
            10 processor minutes).
    """
    processing_s = _processing_s()
    results: dict[str, Any] = {
        "rows": time_rows(processing_s),
        "processing_s_per_view": round(processing_s["stop-and-go"], 5),
        "continuous_processing_s_per_view": round(processing_s["continuous"], 5),
        "slower_core_rows": slower_core_rows(processing_s),
    }
    calibration = _bench_calibration()
    results["set"] = "full" if full else "quick"
    jobs = [
        (name, spec, sections, mode, draw)
        for name, spec, sections in (OBJECTS if full else QUICK_OBJECTS)
        for mode in MODES
        for draw in ACCURACY_DRAWS
    ]
    # Forked workers inherit the calibration taken above (the campaign's per-process cache).
    with ProcessPoolExecutor(max_workers=WORKERS) as pool:
        results["accuracy"] = list(pool.map(_still_scan, jobs))
    name, spec, _ = OBJECTS[0]
    sway_sections = SWAY_SECTIONS if full else QUICK_SWAY_SECTIONS
    results["sway"] = [
        scan(calibration, spec, sway_sections, mode, sway) | {"name": name, "sway_name": label}
        for label, sway in (SWAYS if full else QUICK_SWAYS)
        for mode in MODES
    ]
    results["comparison"] = _comparison(results["accuracy"])
    results["next_turn_rows"] = next_turn_rows(results["rows"], processing_s)
    results["retime_rows"] = retime_rows(results["rows"], processing_s)
    results["relief"] = relief()
    return results


def _still_scan(job: tuple[str, str, int, str, int]) -> dict[str, Any]:
    """Scan one still phantom in one mode and draw (a worker's job); name the row."""
    name, spec, sections, mode, draw = job
    return scan(_bench_calibration(), spec, sections, mode, "none", draw) | {"name": name}


def _bench_calibration() -> Any:
    """Return the limb rig's board and cylinder data, taken once per process (the
    campaign's cache), stop-and-go as a scan takes them."""
    from tests.helpers.campaign import CampaignPlan, _calibration

    return _calibration(CampaignPlan(RIG, 1, PITCH_MM, VIEWS, NOISE))


def _comparison(rows: list[dict[str, Any]]) -> dict[str, Any]:
    """Return continuous mode's errors over stop-and-go's (target <= 1.2), on the same phantoms
    and noise draws (:data:`ACCURACY_DRAWS`).

    Per phantom, the volume error and the worst circumference error, each averaged over the
    draws; over every level of every phantom and draw, the RMS circumference error (the
    figure least at the mercy of one level's noise).
    """
    by: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for row in rows:
        by.setdefault((row["name"], row["mode"]), []).append(row)
    names = [n for n in dict.fromkeys(r["name"] for r in rows) if all((n, m) in by for m in MODES)]
    per_phantom = []
    pooled: dict[str, list[float]] = {mode: [] for mode in MODES}
    for name in names:
        entry: dict[str, Any] = {"name": name, "draws": len(by[(name, MODES[0])])}
        for key in ("volume_error_percent", "max_abs_circumference_error_mm"):
            still, moving = (_mean_abs(by[(name, mode)], key) for mode in MODES)
            entry[key + "_ratio"] = _ratio(moving, still)
        worst = {
            mode: [round(r["max_abs_circumference_error_mm"], 4) for r in by[(name, mode)]]
            for mode in MODES
        }
        entry["worst_circumference_by_draw_mm"] = worst
        per_phantom.append(entry)
        for mode in MODES:
            for row in by[(name, mode)]:
                pooled[mode] += row["circumference_errors_mm"]
    rms = {m: float(np.sqrt(np.mean(np.square(v)))) if v else 0.0 for m, v in pooled.items()}
    volume = {
        m: _mean_abs([r for n in names for r in by[(n, m)]], "volume_error_percent") for m in MODES
    }
    return {
        "per_phantom": per_phantom,
        "levels": len(pooled[MODES[0]]),
        "rms_circumference_error_mm": {m: round(v, 4) for m, v in rms.items()},
        "rms_circumference_ratio": _ratio(rms[MODES[1]], rms[MODES[0]]),
        "mean_abs_volume_error_percent": {m: round(v, 4) for m, v in volume.items()},
        "volume_ratio": _ratio(volume[MODES[1]], volume[MODES[0]]),
    }


def _mean_abs(rows: list[dict[str, Any]], key: str) -> float:
    """Return the mean of ``key``'s absolute value over ``rows`` (a phantom's draws)."""
    return float(np.mean([abs(row[key]) for row in rows]))


def _ratio(value: float, base: float) -> float | None:
    return round(value / base, 3) if base else None


def report(results: dict[str, Any]) -> list[str]:
    """Return the tables: times per plan and mode; errors per phantom, mode and sway."""
    lines = [
        f"  processing per view (extraction + segment, this machine): "
        f"{results['processing_s_per_view'] * 1000:.1f} ms stop-and-go, "
        f"{results['continuous_processing_s_per_view'] * 1000:.1f} ms continuous (the room "
        "light brought to the laser-on frame)",
        f"  {'plan':<26}{'mode':<13}{'views':>6}{'modelled':>11}{'minimum':>10}{'ratio':>8}"
        f"{'axes in turn':>14}",
    ]
    for row in results["rows"]:
        in_turn = f"{row['axes_in_turn_s']:>13.1f}s" if "axes_in_turn_s" in row else ""
        lines.append(
            f"  {row['plan']:<26}{row['mode']:<13}{row['views']:>6}"
            f"{row['modelled_s']:>10.1f}s{row['mechanical_minimum_s']:>9.1f}s{row['ratio']:>8.3f}"
            f"{in_turn}"
        )
    lines.append(
        "  phantom   mode         sway    draw  scan s (model)   vol %   vol-lift %  max |dC| mm  "
        "warned  views apart mm (per section, beyond noise)  jumped  "
        "section: jump mm (limit; true shift, its part toward the camera)"
    )
    for row in results.get("accuracy", []) + results.get("sway", []):
        lines.append(
            f"  {row['name']:<9} {row['mode']:<12} {row.get('sway_name', 'none'):<8}"
            f"{row.get('draw', 0):>4}  {row['scan_s']:>7.1f} ({row['modelled_s']:5.1f})  "
            f"{row['volume_error_percent']:+6.3f}  "
            f"{row['volume_error_without_lift_percent']:+9.3f}  "
            f"{row['max_abs_circumference_error_mm']:11.3f}  {len(row['motion_warnings']):>6}  "
            + " ".join(f"{v:.2f}" for v in row["views_apart_mm"].values())
            + f"  {len(row.get('jump_warnings', [])):>6}  "
            + " ".join(
                f"{k}: {v:.2f} ({row['jump_limits_mm'][k]:.2f}; "
                f"{row.get('true_jumps_mm', {}).get(k, 0.0):.2f}, "
                f"{row.get('true_size_jumps_mm', {}).get(k, 0.0):+.2f})"
                for k, v in row.get("jumps_mm", {}).items()
            )
        )
    comparison = results.get("comparison") or {}
    for entry in comparison.get("per_phantom", []):
        lines.append(
            f"  {entry['name']} ({entry['draws']} draws): continuous over stop-and-go: mean "
            f"|volume error| x{entry['volume_error_percent_ratio']}, mean worst circumference "
            f"error x{entry['max_abs_circumference_error_mm_ratio']} (worst per draw: "
            + "; ".join(
                f"{mode} " + ", ".join(f"{v:.3f}" for v in values)
                for mode, values in entry["worst_circumference_by_draw_mm"].items()
            )
            + " mm)"
        )
    if comparison:
        rms, volume = (
            comparison["rms_circumference_error_mm"],
            comparison["mean_abs_volume_error_percent"],
        )
        lines.append(
            f"  all {comparison['levels']} levels: RMS circumference error "
            f"{rms[MODES[0]]:.3f} mm stop-and-go, {rms[MODES[1]]:.3f} mm continuous "
            f"(x{comparison['rms_circumference_ratio']}); mean |volume error| "
            f"{volume[MODES[0]]:.3f} %, {volume[MODES[1]]:.3f} % (x{comparison['volume_ratio']}); "
            "target <= 1.2"
        )
    for row in results.get("slower_core_rows", []):
        lines.append(
            f"  {row['plan']}: continuous on cores {row['slower']:g}x slower than this host's "
            f"({1000 * row['processing_s_per_view']:.0f} ms a view), "
            f"{row['view_workers']} view{'s' if row['view_workers'] > 1 else ''} at once: "
            f"{row['modelled_s']:.1f} s"
        )
    for row in results.get("next_turn_rows", []):
        lines.append(
            f"  {row['plan']}: continuous with laser-off frames a turn later "
            f"({row['frame_duration_us']} us frames) {row['modelled_s']:.1f} s "
            f"(interleaved {row['interleaved_s']:.1f} s)"
        )
    for row in results.get("retime_rows", []):
        lines.append(
            f"  {row['plan']}: continuous with the table slowed during the lift's moves "
            f"(continuous_retime) {row['modelled_s']:.1f} s, ratio {row['ratio']:.3f} "
            f"(shipped {row['shipped_s']:.1f} s)"
        )
    if results.get("relief"):
        lines.append(
            "  random limb shapes (harsh, 2 x 8): mean distance mm / coverage / motion-warned "
            "outlines, per way"
        )
    by_seed: dict[str, list[str]] = {}
    for row in results.get("relief", []):
        figure = (
            f"{row['way']} failed ({row['failure']})"
            if row["failure"]
            else f"{row['way']} {row['mean_distance_mm']:.3f} / {row['coverage']:.3f} / "
            f"{row['motion_warnings']}"
        )
        by_seed.setdefault(f"seed {row['seed']} ({row['group']}):", []).append(figure)
    lines += [f"    {label} " + ", ".join(figures) for label, figures in by_seed.items()]
    return lines


def main() -> int:
    """Run the bench on its own: ``--full`` for the whole study, ``--out`` to keep the JSON."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument(
        "--full", action="store_true", default=FULL, help="the whole study (30 processor minutes)"
    )
    parser.add_argument("--out", type=Path, help="also write the figures as JSON here")
    args = parser.parse_args()
    # Run as a script: the shared test builders (tests.helpers) are found from the root.
    sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
    from run import show  # the bench runner beside this file

    show("scan_time", sys.modules[__name__], run(args.full), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
