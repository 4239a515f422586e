"""Capture validation: how long ``load_capture`` takes for a capture at the view limit."""

from __future__ import annotations

import tempfile
import time
from pathlib import Path
from typing import Any

from lamina_shared.capture import load_capture
from lamina_shared.limits import DeviceLimits
from lamina_shared.types import ScanPlan
from tests.helpers.captures import write_uniform_capture

TITLE = "capture validation from PNG headers: a capture of max_views views"


def run() -> dict[str, Any]:
    """Time header-only validation (best of three) of a max_views capture."""
    limits = DeviceLimits()
    plan = ScanPlan.regular(limits.max_sections, 0.2, limits.max_views // limits.max_sections)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(tmp) / "capture"
        write_uniform_capture(root, plan, (640, 480))
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
