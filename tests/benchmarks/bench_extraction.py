"""Extraction: speed against one frame subtraction, and accuracy on rendered views.

Speed: the reference cost is one plain numpy subtraction of the two frames into a type
that can hold the difference (int16; uint8 would wrap around), i.e. touching the data
once; the targets (issue 10) are extraction within 6 times that at 640x480 and within
4 times at 1536x864 and 2304x1296. The default settings (Otsu, eq. 5.1 over each run
with 3 pixels beyond either end and its speckle gaps bridged, the noise gate and
chains) are measured on a clean stripe, where every column holds one run, then on the
same stripe with reflections, where many columns hold several and the runs must be
chosen; the rows below show selectable options and a Horus-style pipeline.

Accuracy: the views of ``harsh_frames`` against the renderer's own truth: weak, short
and grazing stripes (issue 10's hard cases for noise), long well-lit ones, and the
anatomy-like phantoms (issue 21), under the harsh preset (weak red laser in the luma
frame, strong noise, speckle and uneven light) and the thesis preset: how many points
are noise (off every true stripe band), how many lie more than 1 px from the true
centre, how much of the stripe is found, the RMS error of the points within 1 px (px
and mm in the laser plane), the points beyond 1 mm and the good points (within 0.25 mm
in the laser plane) with their RMS.

Issue 21's acceptance compares the default as the product runs it (the device's points
fitted along their chains by the host, ``lamina_shared.centreline.refine_many``; its
time is device plus host) with the Horus-style baseline: good points, their RMS over
every view and over the columns both keep (the same frames and columns, so neither
gains by dropping hard points), points beyond 1 mm, and time.

The Horus-style baseline (the open 3D scanner Ciclop's software, as issue 10 describes
it) lives here only, for comparison: saturating subtraction, a fixed threshold of 50 DN,
a 5x5 box blur, a window of +-8 rows about each column's peak, the centre of mass in
it, and a Gaussian smoothing (sigma 2 columns) along each run of neighbouring columns.
"""

from __future__ import annotations

import math
from typing import Any

import cv2
import harsh_frames
import numpy as np
from timing import timed_with_subtraction

from lamina_device.extract import ExtractSettings, extract
from lamina_shared.centreline import refine_many, refine_rows

TITLE = "speed (x one subtraction) and noise points on harsh frames"
RESOLUTIONS = ((640, 480), (1536, 864), (2304, 1296))
SPEED_LIMITS = {"640x480": 6.0, "1536x864": 4.0, "2304x1296": 4.0}
DEFAULT = ExtractSettings()
RUN_ALONE = ExtractSettings(margin_px=0, bridge_px=0)
"""Eq. 5.1 over the Otsu run alone, with the gate and chains: the default before issue 21."""
VARIANTS = {
    "default (Otsu, eq. 5.1 with 3 px margins and bridged runs, noise gate, chains)": (
        DEFAULT, False,
    ),
    "default, with reflections (several runs per column)": (DEFAULT, True),
    "eq. 5.1 over the run alone (margin_px=0, bridge_px=0; the default before issue 21)": (
        RUN_ALONE, False,
    ),
    "thesis's method alone (no gate, no chains)": (ExtractSettings.thesis(), False),
    "run continuity, with reflections": (ExtractSettings(run_choice="continuity"), True),
    "default + smoothing along chains (sigma 2)": (ExtractSettings(smooth_sigma_px=2.0), False),
    "line thinning (thesis 5.2.3)": (ExtractSettings(method="thinning"), False),
}  # fmt: skip
HORUS_THRESHOLD_DN = 50
HORUS_BLUR_PX = 5
HORUS_WINDOW_PX = 8
HORUS_SMOOTH_PX = 2.0


def stripe_pair(
    width: int, height: int, seed: int = 0, reflections: bool = False
) -> tuple[np.ndarray, np.ndarray]:
    """Return a laser-on/laser-off pair with a wavy Gaussian stripe and sensor noise.

    With ``reflections``, bright patches sit above and below the stripe over a third of
    the columns: a second run in each of those columns.
    """
    rng = np.random.default_rng(seed)
    rows = np.arange(height, dtype=np.float32)[:, None]
    centre = height / 2 + height / 8 * np.sin(np.linspace(0, 6, width, dtype=np.float32))
    ambient = 30 + 40 * np.linspace(0, 1, width, dtype=np.float32)[None, :]
    stripe = 170 * np.exp(-0.5 * ((rows - centre) / 2.0) ** 2)
    noise_on = rng.normal(0, 2, (height, width)).astype(np.float32)
    noise_off = rng.normal(0, 2, (height, width)).astype(np.float32)
    if reflections:
        band = slice(height // 12, height // 12 + 3), slice(width // 3, 2 * width // 3)
        stripe[band] += 200
        stripe[height - height // 12 - 3 : height - height // 12, : width // 6] += 120
    on = np.clip(ambient + stripe + noise_on, 0, 255).astype(np.uint8)
    off = np.clip(ambient + noise_off, 0, 255).astype(np.uint8)
    return on, off


def horus_extract(
    on: np.ndarray, off: np.ndarray, threshold_dn: int = HORUS_THRESHOLD_DN
) -> tuple[np.ndarray, np.ndarray]:
    """Return (cols, rows) by the Horus-style pipeline described in the module docstring."""
    diff = cv2.subtract(on, off)
    diff = cv2.threshold(diff, threshold_dn, 255, cv2.THRESH_TOZERO)[1]
    diff = cv2.blur(diff, (HORUS_BLUR_PX, HORUS_BLUR_PX))
    diff = cv2.threshold(diff, threshold_dn, 255, cv2.THRESH_TOZERO)[1].astype(np.float64)
    height = diff.shape[0]
    peak_row = np.argmax(diff, axis=0)
    rows = np.arange(height)[:, None]
    window = np.abs(rows - peak_row[None, :]) <= HORUS_WINDOW_PX
    weights = np.where(window, diff, 0.0)
    total = weights.sum(axis=0)
    cols = np.flatnonzero(total > 0)
    centre = (weights[:, cols] * rows).sum(axis=0) / total[cols]
    return cols, _smooth_runs(cols, centre, HORUS_SMOOTH_PX)


def _smooth_runs(cols: np.ndarray, rows: np.ndarray, sigma_px: float) -> np.ndarray:
    """Return ``rows`` smoothed by a normalised Gaussian within each run of neighbour columns."""
    if cols.size == 0:
        return rows
    radius = int(np.ceil(3 * sigma_px))
    kernel = np.exp(-0.5 * (np.arange(-radius, radius + 1) / sigma_px) ** 2)
    out = np.empty_like(rows)
    starts = np.flatnonzero(np.diff(cols, prepend=-2) != 1)
    for start, stop in zip(starts, [*starts[1:], cols.size], strict=True):
        run = rows[start:stop]
        inside = slice(radius, radius + run.size)  # "full" convolution, centred
        norm = np.convolve(np.ones_like(run), kernel)[inside]
        out[start:stop] = np.convolve(run, kernel)[inside] / norm
    return out


SCAN_SEGMENTS = 32
"""Segments the host fits together in the product's timing (a few sections' views)."""
HOST_FIT = (
    "default + the host's fit along chains, a scan's segments together (device + host per frame)"
)
HOST_FIT_ALONE = "default + the host's fit of this segment alone (device + host time)"
HORUS = "Horus-style (threshold 50, 5x5 blur, window, smoothing)"


def host_fitted(
    on: np.ndarray, off: np.ndarray, settings: ExtractSettings = DEFAULT
) -> tuple[np.ndarray, np.ndarray]:
    """Return the extraction's points with the host's fit along their chains."""
    points = extract(on, off, settings)
    return points.cols, refine_rows(points.cols, points.rows, points.width)


def speed(rounds: int = 3) -> list[dict[str, Any]]:
    """Time every variant and the Horus-style pipeline against one subtraction.

    Each variant and its subtraction are timed in turn, ``rounds`` times, keeping the
    best of each: on a shared machine the ratio then compares like with like. The
    product's default is timed as it runs: the device's extraction of the frame plus
    its share of the host's fit of a scan's segments together (:data:`SCAN_SEGMENTS`).
    The device's variants run OpenCV inline, as the device program on the box does; the
    Horus-style pipeline with OpenCV's threads, as Horus runs.
    """
    rows = []
    for width, height in RESOLUTIONS:
        for reflections in (False, True):
            on, off = stripe_pair(width, height, reflections=reflections)
            runs: dict[str, Any] = {
                variant: lambda on=on, off=off, s=settings: extract(on, off, s)
                for variant, (settings, with_reflections) in VARIANTS.items()
                if with_reflections == reflections
            }
            if not reflections:
                runs[HOST_FIT_ALONE] = lambda on=on, off=off: host_fitted(on, off)
                runs[HORUS] = lambda on=on, off=off: horus_extract(on, off)
            times = {
                variant: timed_with_subtraction(run, on, off, rounds, inline=variant != HORUS)
                for variant, run in runs.items()
            }
            if not reflections:
                points = extract(on, off, DEFAULT)
                scan = [(points.cols, points.rows, points.width)] * SCAN_SEGMENTS
                host_s, _ = timed_with_subtraction(
                    lambda scan=scan: refine_many(scan), on, off, rounds
                )
                device_s, subtract_s = times[next(iter(VARIANTS))]
                times[HOST_FIT] = (device_s + host_s / SCAN_SEGMENTS, subtract_s)
            for variant, (run_s, subtract_s) in times.items():
                rows.append(
                    {
                        "variant": variant,
                        "resolution": f"{width}x{height}",
                        "extract_ms": 1e3 * run_s,
                        "frames_per_s": 1.0 / run_s,
                        "ratio_to_subtraction": run_s / subtract_s,
                    }
                )
    return rows


OURS = "default + host fit"
BASELINE = "Horus-style, 50 DN"


def _methods() -> dict[str, Any]:
    """Return the extractors compared on rendered views: name -> (on, off) -> (cols, rows)."""

    def ours(settings: ExtractSettings) -> Any:
        def run(on: np.ndarray, off: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            points = extract(on, off, settings)
            return points.cols, points.rows.astype(np.float64)

        return run

    return {
        "thesis alone": ours(ExtractSettings.thesis()),
        "eq. 5.1, run alone": ours(RUN_ALONE),
        "default (device)": ours(DEFAULT),
        "default + smoothing": ours(ExtractSettings(smooth_sigma_px=2.0)),
        OURS: host_fitted,
        BASELINE: horus_extract,
        "Horus-style, 25 DN": lambda on, off: horus_extract(on, off, 25),
    }


ACCURACY_PRESETS = ("harsh", "thesis")
SCORED_SETS = ("weak", "good", "anatomical")
"""The sets with a stripe, whose points issue 21's figures pool."""


def view_sets(preset: str, free_views: int = 20) -> dict[str, list[harsh_frames.View]]:
    """Return the rendered views by set: weak, good, anatomical and stripe-free."""
    return {
        "weak": harsh_frames.weak_views(preset),
        "good": harsh_frames.good_views(preset),
        "anatomical": harsh_frames.anatomical_views(preset),
        "free": harsh_frames.stripe_free_views(free_views, preset),
    }


def same_columns(
    views: list[harsh_frames.View],
    ours: list[tuple[np.ndarray, np.ndarray]],
    base: list[tuple[np.ndarray, np.ndarray]],
) -> dict[str, float]:
    """Return both methods' RMS (mm) over the columns where each has a good point."""
    squares: list[list[np.ndarray]] = [[], []]
    for view, *found in zip(views, ours, base, strict=True):
        kept = []
        for cols, rows in found:
            distance = harsh_frames.distances_mm(view, cols, rows)
            good = distance <= harsh_frames.GOOD_MM
            kept.append((cols[good], distance[good]))
        common = np.intersect1d(kept[0][0], kept[1][0])
        for k, (cols, distance) in enumerate(kept):
            squares[k].append(distance[np.isin(cols, common)] ** 2)
    ours_sq, base_sq = (np.concatenate(s) if s else np.zeros(0) for s in squares)
    return {
        "points": int(ours_sq.size),
        "ours_rms_mm": float(np.sqrt(ours_sq.mean())) if ours_sq.size else math.nan,
        "base_rms_mm": float(np.sqrt(base_sq.mean())) if base_sq.size else math.nan,
    }


def accuracy(preset: str = harsh_frames.DEFAULT_PRESET, free_views: int = 20) -> dict[str, Any]:
    """Score every method on every set of views of one preset."""
    sets = view_sets(preset, free_views)
    table: dict[str, Any] = {}
    found: dict[str, dict[str, list[tuple[np.ndarray, np.ndarray]]]] = {}
    for method, run in _methods().items():
        table[method], found[method] = {}, {}
        for name, views in sets.items():
            found[method][name] = [run(v.on, v.off) for v in views]
            scored = harsh_frames.score(views, found[method][name])
            table[method][name] = {
                "points": scored.points,
                "noise_fraction": scored.off_stripe_fraction,
                "beyond_1px_fraction": scored.outlier_fraction,
                "found_fraction": scored.found_fraction,
                "rms_px": scored.rms_px,
                "rms_mm": scored.rms_mm,
                "points_per_view": scored.points / len(views),
                "beyond_1mm_fraction": scored.beyond_1mm / scored.points if scored.points else 0.0,
                "good_mm": scored.good_mm,
                "rms_good_mm": scored.rms_good_mm,
            }
    common = {
        name: same_columns(sets[name], found[OURS][name], found[BASELINE][name])
        for name in SCORED_SETS
    }
    return {"preset": preset, "methods": table, "same_columns": common}


def run() -> dict[str, Any]:
    """Measure speed and harsh-frame accuracy."""
    return {"speed": speed(), "accuracy": [accuracy(p) for p in ACCURACY_PRESETS]}


def report(results: dict[str, Any]) -> list[str]:
    """Return the table lines."""
    lines: list[str] = []
    by_variant: dict[str, list[dict[str, Any]]] = {}
    for row in results["speed"]:
        by_variant.setdefault(row["variant"], []).append(row)
    for variant, rows in by_variant.items():
        lines.append(f"  {variant}")
        lines.append("    resolution    ms/frame   frames/s   x one subtraction")
        for row in rows:
            limit = SPEED_LIMITS[row["resolution"]] if variant == next(iter(VARIANTS)) else None
            mark = "" if limit is None else f"   (limit {limit:g})"
            lines.append(
                f"    {row['resolution']:>10}  {row['extract_ms']:9.2f}  {row['frames_per_s']:9.1f}"
                f"  {row['ratio_to_subtraction']:10.1f}{mark}"
            )
    default = {r["resolution"]: r["extract_ms"] for r in by_variant[next(iter(VARIANTS))]}
    horus = next(v for k, v in by_variant.items() if k.startswith("Horus"))
    slower = (f"{r['resolution']} {r['extract_ms'] / default[r['resolution']]:.0f}x" for r in horus)
    lines.append("  Horus-style / default: " + ", ".join(slower))
    for accuracy_table in results["accuracy"]:
        lines += _accuracy_lines(accuracy_table)
    lines += _acceptance_lines(results)
    return lines


def _accuracy_lines(accuracy_table: dict[str, Any]) -> list[str]:
    """Return one preset's accuracy table."""
    lines = [
        f"  harsh frames (preset {accuracy_table['preset']}): noise = points off every true "
        "stripe band; >1px includes speckle scatter; good = within 0.25 mm in the laser plane",
        "    method                 set         points  noise %   >1px %  found %   RMS px   RMS mm"
        "   >1mm %    good  RMS good mm",
    ]
    for method, sets in accuracy_table["methods"].items():
        for name, s in sets.items():
            has_rms = s["rms_px"] == s["rms_px"]
            rms = f"{s['rms_px']:8.3f} {s['rms_mm']:8.4f}" if has_rms else " " * 17
            if name == "free":
                lines.append(
                    f"    {method:<22} {name:<10} {s['points']:7d}  "
                    f"({s['points_per_view']:.3g} false points per stripe-free view)"
                )
                continue
            lines.append(
                f"    {method:<22} {name:<10} {s['points']:7d} {100 * s['noise_fraction']:8.2f}"
                f" {100 * s['beyond_1px_fraction']:8.2f} {100 * s['found_fraction']:8.1f} {rms}"
                f" {100 * s['beyond_1mm_fraction']:8.2f} {s['good_mm']:7d} {s['rms_good_mm']:12.4f}"
            )
    return lines


def pooled(sets: dict[str, dict[str, Any]], names: tuple[str, ...] = SCORED_SETS) -> dict[str, Any]:
    """Return one method's good points, their RMS (mm) and the share beyond 1 mm, pooled."""
    chosen = [sets[n] for n in names]
    good = sum(s["good_mm"] for s in chosen)
    points = sum(s["points"] for s in chosen)
    squares = sum(s["good_mm"] * s["rms_good_mm"] ** 2 for s in chosen if s["good_mm"])
    beyond = sum(s["beyond_1mm_fraction"] * s["points"] for s in chosen)
    return {
        "good": good,
        "rms_good_mm": math.sqrt(squares / good) if good else math.nan,
        "beyond_1mm_fraction": beyond / points if points else 0.0,
    }


def _acceptance_lines(results: dict[str, Any]) -> list[str]:
    """Return issue 21's figures: the default with the host's fit against Horus-style."""
    lines = [
        f"  issue 21: {OURS} against {BASELINE}; RMS of good points (mm) pooled over "
        + ", ".join(SCORED_SETS)
        + " views, then per set, then over the columns both keep (target <= 0.7x)"
    ]
    for table in results["accuracy"]:
        ours, base = (pooled(table["methods"][m]) for m in (OURS, BASELINE))
        ratio = ours["rms_good_mm"] / base["rms_good_mm"]
        lines.append(
            f"    {table['preset']:<7} good points {ours['good']} vs {base['good']}; RMS"
            f" {ours['rms_good_mm']:.4f} vs {base['rms_good_mm']:.4f} mm ({ratio:.2f}x);"
            f" beyond 1 mm {100 * ours['beyond_1mm_fraction']:.2f} % vs"
            f" {100 * base['beyond_1mm_fraction']:.2f} %"
        )
        cells = []
        for name in SCORED_SETS:
            ours_set, base_set = (pooled(table["methods"][m], (name,)) for m in (OURS, BASELINE))
            common = table["same_columns"][name]
            cells.append(
                f"{name} {ours_set['rms_good_mm'] / base_set['rms_good_mm']:.2f}x"
                f" (same {common['points']} columns"
                f" {common['ours_rms_mm'] / common['base_rms_mm']:.2f}x)"
            )
        lines.append("            " + "; ".join(cells))
    by_variant: dict[str, dict[str, float]] = {}
    ratios: dict[str, dict[str, float]] = {}
    for row in results["speed"]:
        by_variant.setdefault(row["variant"], {})[row["resolution"]] = row["extract_ms"]
        ratios.setdefault(row["variant"], {})[row["resolution"]] = row["ratio_to_subtraction"]
    horus, fitted, alone = (by_variant[k] for k in (HORUS, HOST_FIT, HOST_FIT_ALONE))
    lines.append(
        "    Horus-style / (default + host fit) time: "
        + ", ".join(f"{r} {horus[r] / fitted[r]:.0f}x" for r in fitted)
        + " (target >= 10x; one segment fitted alone: "
        + ", ".join(f"{r} {horus[r] / alone[r]:.0f}x" for r in alone)
        + "); device default: "
        + ", ".join(
            f"{r} {x:.1f}x one subtraction (limit {SPEED_LIMITS[r]:g})"
            for r, x in ratios[next(iter(VARIANTS))].items()
        )
    )
    return lines
