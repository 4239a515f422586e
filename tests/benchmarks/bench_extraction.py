"""Extraction speed: frames per second and cost relative to one frame subtraction.

The reference cost is one plain numpy subtraction of the two frames into a type that
can hold the difference (int16; uint8 would wrap around), i.e. touching the data once;
the target is extraction within 4 times that. The default settings (the thesis's Otsu
threshold and eq. 5.1) are measured first on a clean stripe, where every column holds
one run, then on the same stripe with reflections, where many columns hold several
and the runs must be chosen; the rows below show selectable options.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from timing import best_time_s

from lamina_device.extract import ExtractSettings, extract

TITLE = "extraction (Otsu + centre of gravity)"
RESOLUTIONS = ((640, 480), (1536, 864), (2304, 1296))
VARIANTS = {
    "default (thesis: Otsu, eq. 5.1)": (ExtractSettings(), False),
    "default, with reflections (several runs per column)": (ExtractSettings(), True),
    "run continuity, with reflections": (ExtractSettings(run_choice="continuity"), True),
    "line thinning (thesis 5.2.3)": (ExtractSettings(method="thinning"), False),
}


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


def run() -> dict[str, Any]:
    """Time extraction against one plain numpy subtraction of the same two frames."""
    rows = []
    for variant, (settings, reflections) in VARIANTS.items():
        for width, height in RESOLUTIONS:
            on, off = stripe_pair(width, height, reflections=reflections)
            extract_s = best_time_s(lambda on=on, off=off, s=settings: extract(on, off, s))
            subtract_s = best_time_s(lambda on=on, off=off: np.subtract(on, off, dtype=np.int16))
            rows.append(
                {
                    "variant": variant,
                    "resolution": f"{width}x{height}",
                    "extract_ms": 1e3 * extract_s,
                    "frames_per_s": 1.0 / extract_s,
                    "ratio_to_subtraction": extract_s / subtract_s,
                }
            )
    return {"rows": rows}


def report(results: dict[str, Any]) -> list[str]:
    """Return the table lines."""
    lines: list[str] = []
    variant = None
    for row in results["rows"]:
        if row["variant"] != variant:
            variant = row["variant"]
            lines.append(f"  {variant}")
            lines.append("    resolution    ms/frame   frames/s   x one subtraction")
        lines.append(
            f"    {row['resolution']:>10}  {row['extract_ms']:9.2f}  {row['frames_per_s']:9.1f}"
            f"  {row['ratio_to_subtraction']:10.1f}"
        )
    return lines
