"""Extraction: speed against one frame subtraction, and noise points on harsh frames.

Speed: the reference cost is one plain numpy subtraction of the two frames into a type
that can hold the difference (int16; uint8 would wrap around), i.e. touching the data
once; the targets (issue 10) are extraction within 6 times that at 640x480 and within
4 times at 1536x864 and 2304x1296. The default settings (Otsu, eq. 5.1, the noise gate
and chains) are measured on a clean stripe, where every column holds one run, then on
the same stripe with reflections, where many columns hold several and the runs must be
chosen; the rows below show selectable options and a Horus-style pipeline.

Accuracy: the harsh views of ``harsh_frames`` (issue 10's camera: weak red laser in the
luma frame, strong noise, speckle and uneven light) against the renderer's own truth:
how many points are noise (off every true stripe band), how many lie more than 1 px
from the true centre (noise plus speckle scatter), how much of the stripe is found,
and the RMS error of the points within 1 px, in px and in mm in the laser plane.

Issue 21's rows: the default with the host's fit along chains
(``lamina_shared.centreline.refine_rows``; its time is device plus host), the same with
``margin_px=3``, and against the Horus-style baseline the good points (within 0.25 mm
in the laser plane), their RMS, the RMS of the points within 1 px and the points beyond
1 mm, on the harsh and the thesis presets.

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
from timing import best_time_s

from lamina_device.extract import ExtractSettings, extract
from lamina_shared.centreline import refine_rows

TITLE = "speed (x one subtraction) and noise points on harsh frames"
RESOLUTIONS = ((640, 480), (1536, 864), (2304, 1296))
SPEED_LIMITS = {"640x480": 6.0, "1536x864": 4.0, "2304x1296": 4.0}
DEFAULT = ExtractSettings()
VARIANTS = {
    "default (Otsu, eq. 5.1, noise gate, chains)": (DEFAULT, False),
    "default, with reflections (several runs per column)": (DEFAULT, True),
    "thesis's method alone (no gate, no chains)": (ExtractSettings.thesis(), False),
    "run continuity, with reflections": (ExtractSettings(run_choice="continuity"), True),
    "default + smoothing along chains (sigma 2)": (ExtractSettings(smooth_sigma_px=2.0), False),
    "default + 3 px margin beyond each run (margin_px=3)": (ExtractSettings(margin_px=3), False),
    "line thinning (thesis 5.2.3)": (ExtractSettings(method="thinning"), False),
}
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


HOST_FIT = "default + the host's fit along chains (device + host time)"
HOST_FIT_MARGIN = "margin_px=3 + the host's fit along chains (device + host time)"


MARGIN = ExtractSettings(margin_px=3)


def host_fitted(
    on: np.ndarray, off: np.ndarray, settings: ExtractSettings = DEFAULT
) -> tuple[np.ndarray, np.ndarray]:
    """Return the extraction's points with the host's fit along their chains."""
    points = extract(on, off, settings)
    return points.cols, refine_rows(points.cols, points.rows, points.width)


def speed(rounds: int = 3) -> list[dict[str, Any]]:
    """Time every variant and the Horus-style pipeline against one subtraction.

    Each variant and its subtraction are timed in turn, ``rounds`` times, keeping the
    best of each: on a shared machine the ratio then compares like with like.
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
                runs[HOST_FIT] = lambda on=on, off=off: host_fitted(on, off)
                runs[HOST_FIT_MARGIN] = lambda on=on, off=off: host_fitted(on, off, MARGIN)
                runs["Horus-style (threshold 50, 5x5 blur, window, smoothing)"] = (
                    lambda on=on, off=off: horus_extract(on, off)
                )
            for variant, run in runs.items():
                subtract_s = extract_s = math.inf
                for _ in range(rounds):
                    subtract_s = min(
                        subtract_s,
                        best_time_s(lambda on=on, off=off: np.subtract(on, off, dtype=np.int16)),
                    )
                    extract_s = min(extract_s, best_time_s(run))
                rows.append(
                    {
                        "variant": variant,
                        "resolution": f"{width}x{height}",
                        "extract_ms": 1e3 * extract_s,
                        "frames_per_s": 1.0 / extract_s,
                        "ratio_to_subtraction": extract_s / subtract_s,
                    }
                )
    return rows


def _methods() -> dict[str, Any]:
    """Return the extractors compared on harsh frames: name -> (on, off) -> (cols, rows)."""

    def ours(settings: ExtractSettings) -> Any:
        def run(on: np.ndarray, off: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            points = extract(on, off, settings)
            return points.cols, points.rows.astype(np.float64)

        return run

    return {
        "thesis alone": ours(ExtractSettings.thesis()),
        "default": ours(DEFAULT),
        "default + smoothing": ours(ExtractSettings(smooth_sigma_px=2.0)),
        "default + host fit": host_fitted,
        "margin 3 + host fit": lambda on, off: host_fitted(on, off, MARGIN),
        "Horus-style, 50 DN": horus_extract,
        "Horus-style, 25 DN": lambda on, off: horus_extract(on, off, 25),
    }


ACCURACY_PRESETS = ("harsh", "thesis")


def accuracy(preset: str = harsh_frames.DEFAULT_PRESET, free_views: int = 20) -> dict[str, Any]:
    """Score every method on the weak, good and stripe-free harsh views."""
    sets = {
        "weak": harsh_frames.weak_views(preset),
        "good": harsh_frames.good_views(preset),
        "free": harsh_frames.stripe_free_views(free_views, preset),
    }
    table: dict[str, Any] = {}
    for method, run in _methods().items():
        table[method] = {}
        for name, views in sets.items():
            scored = harsh_frames.score(views, [run(v.on, v.off) for v in views])
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
    return {"preset": preset, "methods": table}


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
        "    method                 set    points  noise %   >1px %  found %   RMS px   RMS mm"
        "   >1mm %    good  RMS good mm",
    ]
    for method, sets in accuracy_table["methods"].items():
        for name, s in sets.items():
            has_rms = s["rms_px"] == s["rms_px"]
            rms = f"{s['rms_px']:8.3f} {s['rms_mm']:8.4f}" if has_rms else " " * 17
            if name == "free":
                lines.append(
                    f"    {method:<22} {name:<5} {s['points']:7d}  "
                    f"({s['points_per_view']:.3g} false points per stripe-free view)"
                )
                continue
            lines.append(
                f"    {method:<22} {name:<5} {s['points']:7d} {100 * s['noise_fraction']:8.2f}"
                f" {100 * s['beyond_1px_fraction']:8.2f} {100 * s['found_fraction']:8.1f} {rms}"
                f" {100 * s['beyond_1mm_fraction']:8.2f} {s['good_mm']:7d} {s['rms_good_mm']:12.4f}"
            )
    return lines


def _acceptance_lines(results: dict[str, Any]) -> list[str]:
    """Return issue 21's figures: the default with the host's fit against Horus-style."""
    lines = ["  issue 21: ours against Horus-style (50 DN), weak + good sets"]
    for table, ours_name in (
        (t, m) for m in ("default + host fit", "margin 3 + host fit") for t in results["accuracy"]
    ):
        ours, horus = (table["methods"][m] for m in (ours_name, "Horus-style, 50 DN"))
        figures = []
        for m in (ours, horus):
            sets = [m["weak"], m["good"]]
            good = sum(s["good_mm"] for s in sets)
            points = sum(s["points"] for s in sets)
            squares = sum(s["good_mm"] * s["rms_good_mm"] ** 2 for s in sets if s["good_mm"])
            beyond = sum(s["beyond_1mm_fraction"] * s["points"] for s in sets)
            px = [s for s in sets if s["rms_px"] == s["rms_px"]]
            within = sum(s["points"] * (1 - s["beyond_1px_fraction"]) for s in px)
            px_squares = sum(
                s["points"] * (1 - s["beyond_1px_fraction"]) * s["rms_px"] ** 2 for s in px
            )
            figures.append(
                (good, math.sqrt(squares / good) if good else math.nan,
                 beyond / points if points else 0.0,
                 math.sqrt(px_squares / within) if within else math.nan)
            )  # fmt: skip
        (g0, r0, b0, p0), (g1, r1, b1, p1) = figures
        lines.append(
            f"    {ours_name:<20} {table['preset']:<7} good points {g0} vs {g1};"
            f" RMS of good points {r0:.4f} vs"
            f" {r1:.4f} mm ({r0 / r1:.2f}x); RMS within 1 px {p0:.3f} vs {p1:.3f} px"
            f" ({p0 / p1:.2f}x); beyond 1 mm {100 * b0:.2f} % vs {100 * b1:.2f} %"
        )
    by_variant: dict[str, dict[str, float]] = {}
    for row in results["speed"]:
        by_variant.setdefault(row["variant"], {})[row["resolution"]] = row["extract_ms"]
    horus = next(v for k, v in by_variant.items() if k.startswith("Horus"))
    for name in (HOST_FIT, HOST_FIT_MARGIN):
        fitted = by_variant[name]
        lines.append(
            f"    Horus-style / ({name.split(' (')[0]}) time: "
            + ", ".join(f"{r} {horus[r] / fitted[r]:.0f}x" for r in fitted)
        )
    return lines
