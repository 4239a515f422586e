"""Sub-pixel accuracy of the stripe centre against simulated stripes with known centres.

Two studies. The first (:func:`noise_table`) is described here; the second
(:func:`case_table`, issue 21) compares every centre finder of ``subpixel_cases`` on
stripes with an exact centre line: Gaussian and flat-topped profiles 1.5-8 px wide,
sloped lines, arcs of radius 10-500 px, speckle 0.3-0.6, saturation, brightness steps
crossing the profile and occluded stretches, under the thesis and harsh presets. Its
bias comes from each case rendered without noise or speckle (so it is the method's own,
not the luck of one noise draw), its RMS from noisy renders; time per frame is at
640x480, against one ``np.subtract`` timed alongside.

Each frame pair holds a smooth Gaussian stripe whose centre row is known in every
column (its sub-pixel phase sweeps evenly through 0..1), over a uniform ambient level,
with independent sensor noise in the laser-on and laser-off frames and optionally the
laser's multiplicative speckle (the simulated rig's own speckle model). Compared: the
thesis's centre of gravity (eq. 5.1, Otsu, p = 1), the same with the threshold
subtracted from the weights, and the thesis's line thinning (5.2.3), whose whole-pixel
output is biased toward the top of runs an even number of pixels thick (figs. 5.4-5.6).
"""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np

from lamina_device.extract import ExtractSettings, extract
from lamina_device.sim.render import speckle_field

TITLE = "sub-pixel accuracy, RMS error of the stripe centre in pixels (known truth)"
THESIS_COG = ExtractSettings(margin_px=0, bridge_px=0)
"""Eq. 5.1 over the Otsu run alone (the thesis's centre), with the noise gate and chains."""
METHODS = {
    "cog": THESIS_COG,
    "cog_minus_threshold": ExtractSettings(subtract_threshold=True, bridge_px=0),
    "thinning": ExtractSettings(method="thinning"),
    "default": ExtractSettings(),
}
NOISE_LEVELS = (
    ("0 DN", 0.0, 0.0),
    ("1 DN", 1.0, 0.0),
    ("2 DN", 2.0, 0.0),
    ("4 DN", 4.0, 0.0),
    ("8 DN", 8.0, 0.0),
    ("2 DN + speckle", 2.0, 0.5),
)


def stripe_pair(
    noise_dn: float,
    speckle_contrast: float,
    columns: int = 1000,
    height: int = 64,
    sigma_px: float = 1.2,
    peak_dn: float = 170.0,
    ambient_dn: float = 40.0,
    seed: int = 0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Return (laser-on, laser-off, true centre row per column) for one simulated view.

    Args:
        noise_dn: standard deviation of the sensor noise in each frame (DN).
        speckle_contrast: std / mean of the laser speckle (0 for none).
        columns, height: frame size in pixels.
        sigma_px: Gaussian half-thickness of the stripe.
        peak_dn: stripe peak above the ambient level.
        ambient_dn: the ambient level in both frames.
        seed: random seed.
    """
    rng = np.random.default_rng(seed)
    col = np.arange(columns)
    # A gentle ramp with a ripple: the sub-pixel phase sweeps evenly through 0..1.
    centre = height / 2 - 6.0 + 12.37 * col / columns + 0.8 * np.sin(col / 37.0)
    rows = np.arange(height, dtype=np.float64)[:, None]
    laser = peak_dn * np.exp(-0.5 * ((rows - centre[None, :]) / sigma_px) ** 2)
    if speckle_contrast > 0.0:
        laser *= speckle_field(rng, laser.shape, speckle_contrast, 1.0)
    off = ambient_dn + noise_dn * rng.standard_normal(laser.shape)
    on = ambient_dn + laser + noise_dn * rng.standard_normal(laser.shape)
    as8 = lambda a: np.clip(np.rint(a), 0, 255).astype(np.uint8)  # noqa: E731
    return as8(on), as8(off), centre


def accuracy(
    noise_dn: float, speckle_contrast: float, columns: int = 1000, seed: int = 0
) -> dict[str, dict[str, float]]:
    """Return per method the RMS and mean error (px), the even-width-run bias and coverage.

    Errors are found row minus true row: negative means toward the top of the image.
    """
    on, off, truth = stripe_pair(noise_dn, speckle_contrast, columns=columns, seed=seed)
    results = {}
    for name, settings in METHODS.items():
        points = extract(on, off, settings)
        error = points.rows.astype(np.float64) - truth[points.cols]
        even = points.width % 2 == 0
        results[name] = {
            "rms_px": float(np.sqrt(np.mean(error**2))),
            "mean_px": float(np.mean(error)),
            "mean_even_width_px": float(np.mean(error[even])) if even.any() else float("nan"),
            "mean_odd_width_px": float(np.mean(error[~even])) if (~even).any() else float("nan"),
            "found": len(points.cols) / columns,
        }
    return results


def noise_table() -> dict[str, Any]:
    """Measure the thesis's methods at every noise level (the first table)."""
    rows = []
    for label, noise_dn, speckle in NOISE_LEVELS:
        rows.append({"noise": label, **accuracy(noise_dn, speckle)})
    return {"rows": rows, "methods": list(METHODS)}


def noise_report(results: dict[str, Any]) -> list[str]:
    """Return the first table's lines: RMS per method, and thinning's even-width bias."""
    lines = [
        "  noise            COG eq.5.1   COG-threshold   thinning   thinning bias on even runs"
        "   default"
    ]
    for row in results["rows"]:
        cog, minus, thinning, default = (
            row[m] for m in ("cog", "cog_minus_threshold", "thinning", "default")
        )
        lines.append(
            f"  {row['noise']:<15} {cog['rms_px']:10.3f}  {minus['rms_px']:14.3f}"
            f"  {thinning['rms_px']:9.3f}  {thinning['mean_even_width_px']:+12.3f}"
            f"  {default['rms_px']:20.3f}"
        )
    found = {m: min(row[m]["found"] for row in results["rows"]) for m in results["methods"]}
    lines.append(
        "  (px; bias < 0 is toward the top of the image; columns with a point, worst case: "
        + ", ".join(f"{m} {100 * f:.1f}%" for m, f in found.items())
        + ")"
    )
    return lines


NOISY_SEEDS = 2


# The second study imports its sibling modules when it runs (run.py puts this folder on
# the path), so the first stays importable on its own, as tests/device loads it.


def case_table() -> dict[str, Any]:
    """Return bias (noise-free), RMS and share beyond 1 px (noisy) per preset, case, method."""
    import subpixel_cases as cases

    table: dict[str, Any] = {}
    for preset, model in cases.PRESETS.items():
        clean = dataclasses.replace(
            model, read_noise_dn=0.0, shot_gain_dn=0.0, speckle_contrast=0.0
        )
        table[preset] = {}
        for case in cases.CASES:
            exact = cases.render(case, preset, model=clean)
            noisy = [cases.render(case, preset, seed) for seed in range(NOISY_SEEDS)]
            row = {}
            for name, method in cases.METHODS.items():
                bias = cases.score(exact, method(exact.on, exact.off)).bias_px
                scores = [cases.score(f, method(f.on, f.off)) for f in noisy]
                row[name] = {
                    "bias_px": bias,
                    "noisy_bias_px": float(np.nanmean([s.bias_px for s in scores])),
                    "rms_px": float(np.nanmean([s.rms_px for s in scores])),
                    "beyond_1px": float(np.mean([s.beyond_1px for s in scores])),
                    "found": float(np.mean([s.found for s in scores])),
                }
            table[preset][case.name] = row
    return table


def method_times(rounds: int = 3) -> dict[str, dict[str, float]]:
    """Return each method's time per 640x480 frame (ms) and its ratio to one subtraction.

    The device's methods run OpenCV inline, as on the box; the Horus-style one with
    OpenCV's threads.
    """
    import subpixel_cases as cases
    from bench_extraction import stripe_pair as timing_pair
    from timing import timed_with_subtraction

    on, off = timing_pair(640, 480)
    times = {}
    for name, method in cases.METHODS.items():
        run_s, subtract_s = timed_with_subtraction(
            lambda m=method: m(on, off), on, off, rounds, inline=name != "Horus-style"
        )
        times[name] = {"ms": 1e3 * run_s, "x_subtraction": run_s / subtract_s}
    return times


def run() -> dict[str, Any]:
    """Measure both studies."""
    return {"noise": noise_table(), "cases": case_table(), "times": method_times()}


def report(results: dict[str, Any]) -> list[str]:
    """Return both studies' tables."""
    import subpixel_cases as cases

    lines = noise_report(results["noise"])
    names = list(cases.METHODS)
    short = [n[:13] for n in names]
    lines.append(
        "  known centre line: bias (noise-free) / RMS (noisy) in px per method; "
        "bias on arcs is toward the centre of curvature, on steps within the profile"
    )
    for preset, table in results["cases"].items():
        lines.append(f"  preset {preset}")
        lines.append("    case                  " + "".join(f"{n:>14}" for n in short))
        for case, row in table.items():
            cells = "".join(
                f"{row[n]['bias_px']:>7.3f}/{row[n]['rms_px']:<6.3f}"
                if row[n]["rms_px"] == row[n]["rms_px"] else f"{row[n]['bias_px']:>7.3f}/  -   "
                for n in names
            )  # fmt: skip
            lines.append(f"    {case:<22}{cells}")
    times = results["times"]
    lines.append("    ms / 640x480 frame    " + "".join(f"{times[n]['ms']:>14.2f}" for n in names))
    lines.append(
        "    x one subtraction     " + "".join(f"{times[n]['x_subtraction']:>14.1f}" for n in names)
    )
    lines.append(
        f"  (\"{cases.DEFAULT_AND_FIT}\" is the product's default: the device's default centre,"
        " then the host's adaptive quadratic fit along chains; its time includes the device's)"
    )
    for preset, table in results["cases"].items():
        noisy = ", ".join(
            f"{case} {row[cases.DEFAULT_AND_FIT]['noisy_bias_px']:.3f}"
            for case, row in table.items()
            if case.startswith(("arcs", "brightness"))
        )
        lines.append(f"  {cases.DEFAULT_AND_FIT}, bias on noisy renders ({preset}): {noisy}")
    return lines
