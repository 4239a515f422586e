"""Capture validation: how long ``load_capture`` takes for a capture at the view limit."""

from __future__ import annotations

import json
import tempfile
import time
from pathlib import Path
from typing import Any

import cv2
import numpy as np

from lamina_shared.capture import CaptureWriter, load_capture
from lamina_shared.limits import DeviceLimits
from lamina_shared.types import ScanPlan

TITLE = "capture validation from PNG headers: a capture of max_views views"


def _write(root: Path, plan: ScanPlan, size: tuple[int, int]) -> None:
    """Write a capture of ``plan`` whose frames are distinct files of one small PNG."""
    writer = CaptureWriter(root, size)
    image = np.zeros((size[1], size[0]), np.uint8)
    image[size[1] // 2, :] = 200
    png = cv2.imencode(".png", image)[1].tobytes()
    (root / "scan").mkdir()
    views = []
    for k, view in enumerate(plan.views):
        on, off = f"scan/{k:05d}_on.png", f"scan/{k:05d}_off.png"
        (root / on).write_bytes(png)
        (root / off).write_bytes(png)
        views.append({**view.to_dict(), "laser_on": on, "laser_off": off})
    data = writer.manifest()
    data["scan"] = {"views": views}
    (root / "capture.json").write_text(json.dumps(data))


def run() -> dict[str, Any]:
    """Time header-only validation (best of three) of a max_views capture."""
    limits = DeviceLimits()
    plan = ScanPlan.regular(limits.max_sections, 0.2, limits.max_views // limits.max_sections)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "capture"
        _write(root, plan, (640, 480))
        times = []
        for _ in range(3):
            start = time.perf_counter()
            capture = load_capture(root)
            times.append(time.perf_counter() - start)
        assert len(capture.scan_views) == len(plan.views)
    return {"views": len(plan.views), "frames": 2 * len(plan.views), "validate_s": min(times)}


def report(result: dict[str, Any]) -> list[str]:
    """Return the table lines."""
    return [
        f"  {result['views']} views ({result['frames']} frames): "
        f"validated in {result['validate_s']:.2f} s (headers only, best of 3)"
    ]
