"""Capture folders built on disk for the capture tests and ``bench_capture``."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from lamina_shared.capture import CaptureWriter
from lamina_shared.types import ScanPlan


def write_uniform_capture(root: Path, plan: ScanPlan, size: tuple[int, int]) -> None:
    """Write a capture of ``plan`` whose frames are distinct files of one small PNG.

    Every frame is black with one bright row at mid-height; only the headers differ
    from a real capture's, which is all validation reads.
    """
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


def assert_reports(problems: list[str], *expected: str) -> None:
    """Assert that every ``expected`` fragment stands in the problems; name all missing ones."""
    text = "\n".join(problems)
    missing = [fragment for fragment in expected if fragment not in text]
    assert not missing, f"not reported: {missing}; reported: {problems}"
