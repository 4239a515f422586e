"""Hostile captures: every class of bad folder is refused up front, every problem listed.

Frames are judged from their PNG header and last chunk, never decoded during
validation, so a decompression bomb costs nothing; a manifest that is nested, huge or
not UTF-8 gets one line naming the file; nothing outside the folder is read.
"""

from __future__ import annotations

import json
import os
import struct
import time
import zlib
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from lamina_shared import capture as capture_module
from lamina_shared.capture import CaptureError, CaptureWriter, load_capture, read_frame
from lamina_shared.limits import DeviceLimits
from lamina_shared.types import ScanPlan
from tests.helpers.captures import assert_reports, write_uniform_capture


def png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def png_header_only(width: int, height: int, depth: int = 8, colour: int = 0) -> bytes:
    """A PNG that declares a size and has no pixels: all a header check may look at."""
    ihdr = struct.pack(">IIBBBBB", width, height, depth, colour, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + png_chunk(b"IHDR", ihdr) + png_chunk(b"IEND", b"")


def frame(value: int = 5, dtype: Any = np.uint8) -> np.ndarray:
    image = np.full((48, 64), value, dtype)
    image[10, :] = 200
    return image


@pytest.fixture
def capture_dir(tmp_path: Path) -> Path:
    writer = CaptureWriter(tmp_path / "cap", (64, 48), {"object": "test"})
    for k, view in enumerate(ScanPlan.regular(2, 2.0, 3).views):
        writer.add_view("object", view, k % 3, frame(4 + k), frame(50))
    writer.close()
    return tmp_path / "cap"


def edit(root: Path, change: Any) -> None:
    path = root / "capture.json"
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def problems_of(root: Path, **kwargs: Any) -> list[str]:
    with pytest.raises(CaptureError) as info:
        load_capture(root, **kwargs)
    assert "Traceback" not in str(info.value)
    return info.value.problems


@pytest.fixture
def no_decoding(monkeypatch: pytest.MonkeyPatch) -> None:
    """Fail the test if validation decodes any frame."""

    def refuse(*args: Any, **kwargs: Any) -> None:
        raise AssertionError("a frame was decoded during validation")

    monkeypatch.setattr(capture_module, "read_frame", refuse)


# --- frames judged from their headers ---------------------------------------------------


@pytest.mark.parametrize(
    ("width", "height", "depth", "colour", "expected"),
    [
        (30_000, 30_000, 8, 0, "is 30000x30000, image_size says 64x48"),
        (20_000, 20_000, 16, 2, "is 20000x20000"),
        (64, 48, 16, 2, "bit depth 16"),
        (64, 48, 8, 3, "palette PNG; grayscale or RGB is required"),
        (64, 48, 8, 6, "RGB with alpha PNG"),
        (64, 48, 4, 0, "bit depth 4; 8 or 16 is required"),
        (64, 48, 8, 9, "unknown (9) PNG"),
    ],
)
def test_bad_frames_are_refused_from_the_header_alone(
    capture_dir, no_decoding, width, height, depth, colour, expected
):
    (capture_dir / "scan/s000_v01_on.png").write_bytes(
        png_header_only(width, height, depth, colour)
    )
    problems = problems_of(capture_dir)
    assert any(p.startswith("scan.views[1].laser_on:") and expected in p for p in problems), (
        problems
    )


def test_a_bomb_is_refused_without_decoding_even_when_decoding_is_asked(capture_dir, monkeypatch):
    (capture_dir / "scan/s000_v01_on.png").write_bytes(png_header_only(30_000, 30_000, 16, 2))
    decoded: list[Path] = []
    real = capture_module.read_frame

    def spy(path: Path, channel: str = "red") -> np.ndarray:
        decoded.append(path)
        return real(path, channel)

    monkeypatch.setattr(capture_module, "read_frame", spy)
    problems = problems_of(capture_dir, decode_frames=True)
    assert any("30000x30000" in p for p in problems)
    assert capture_dir / "scan/s000_v01_on.png" not in decoded


def test_a_declared_size_beyond_the_limit_is_refused_even_if_image_size_says_so(tmp_path):
    root = tmp_path / "big"
    root.mkdir()
    (root / "f.png").write_bytes(png_header_only(30_000, 30_000))
    view = {"section": 0, "z_mm": 0.0, "angle_deg": 0.0, "laser_on": "f.png"}
    manifest = {"format": "lightsection-capture", "version": 1, "image_size": [30_000, 30_000]}
    (root / "capture.json").write_text(json.dumps({**manifest, "scan": {"views": [view]}}))
    problems = problems_of(root)
    assert any(p.startswith("image_size: two whole numbers in 1..16384") for p in problems)
    (root / "f.png").write_bytes(png_header_only(16_000, 16_000))
    data = json.loads((root / "capture.json").read_text())
    (root / "capture.json").write_text(json.dumps({**data, "image_size": [16_000, 16_000]}))
    problems = problems_of(root)  # each side allowed, but 256 MP in all
    assert any("at most 20000000 pixels in all" in p for p in problems), problems
    (root / "capture.json").write_text(json.dumps({**data, "image_size": [30_000, 30_000]}))
    (root / "f.png").write_bytes(png_header_only(30_000, 30_000))
    limits = DeviceLimits(max_image_side_px=40_000, max_image_pixels=10**9)
    assert load_capture(root, limits=limits).image_size == (30_000, 30_000)


def test_one_16_bit_frame_among_8_bit_ones(capture_dir):
    cv2.imwrite(str(capture_dir / "scan/s001_v00_off.png"), frame(3, np.uint16))
    problems = problems_of(capture_dir)
    assert problems == [
        "scan.views[3].laser_off: scan/s001_v00_off.png has bit depth 16, "
        "scan.views[0].laser_on has 8: all frames of a capture share one bit depth"
    ]


def test_16_bit_captures_stay_valid(tmp_path):
    writer = CaptureWriter(tmp_path / "c16", (64, 48))
    for k, view in enumerate(ScanPlan.regular(1, 2.0, 2).views):
        writer.add_view("object", view, k, frame(1000, np.uint16), frame(20, np.uint16))
    writer.close()
    loaded = load_capture(tmp_path / "c16", decode_frames=True)
    assert read_frame(loaded.scan_views[0].laser_on).dtype == np.uint16


def test_truncated_and_non_png_frames(capture_dir, no_decoding):
    whole = (capture_dir / "scan/s000_v00_on.png").read_bytes()
    (capture_dir / "scan/s000_v00_on.png").write_bytes(whole[:-5])
    (capture_dir / "scan/s000_v01_on.png").write_bytes(b"GIF89a" + bytes(40))
    (capture_dir / "scan/s000_v02_on.png").write_bytes(b"")
    problems = problems_of(capture_dir)
    assert (
        "scan.views[0].laser_on: scan/s000_v00_on.png is unreadable (truncated PNG" in problems[0]
    )
    assert "scan.views[1].laser_on: scan/s000_v01_on.png is unreadable (not a PNG file)" in problems
    assert "scan.views[2].laser_on: scan/s000_v02_on.png is unreadable (not a PNG file)" in problems


def test_read_frame_turns_opencv_errors_into_frame_errors(tmp_path):
    path = tmp_path / "bad.png"
    path.write_bytes(png_header_only(64, 48))  # a header and no pixel data
    with pytest.raises(capture_module.FrameError):
        read_frame(path)


# --- views beyond the limits, duplicates, heights --------------------------------------


def test_every_bad_view_is_found_at_once(capture_dir):
    def break_it(data: dict[str, Any]) -> None:
        views = data["scan"]["views"]
        views[0]["z_mm"] = -2.0  # below the first section
        views[1]["z_mm"] = 1e300  # far above any lift
        views[2]["section"] = 10**400  # beyond the sections' limit, and beyond a float
        views[3]["angle_deg"] = 360.0  # the same turntable position as 0 in section 1
        views[4]["z_mm"] = 10**400  # an integer no float holds
        views[5]["section"] = 5_000

    edit(capture_dir, break_it)
    problems = problems_of(capture_dir)
    assert_reports(
        problems,
        "scan.views[0].z_mm: -2.0 is outside 0..10000",
        "scan.views[1].z_mm: 1e+300 is outside 0..10000",
        "scan.views[2].section",
        "outside 0..999",
        "scan.views[4].z_mm: a finite number is required",
        "scan.views[5].section: 5000 is outside 0..999",
        "scan.views[4].z_mm: a finite number is required, found a huge integer",
        # Section 5000 also sits at section 1's height: a second problem of the same view.
        "scan.views[5]: section 5000 is at z_mm 2.0, the height of section 1",
    )
    # views[3] at 360 deg stands for 0 deg, which section 1 no longer holds otherwise:
    # no duplicate, so only the six problems above are reported.
    assert len(problems) == 6, problems


def test_0_and_360_degrees_in_one_section_are_the_same_view(capture_dir):
    edit(capture_dir, lambda d: d["scan"]["views"][2].update(angle_deg=360.0))
    edit(capture_dir, lambda d: d["scan"]["views"][1].update(angle_deg=-240.0))
    problems = problems_of(capture_dir)
    assert problems == [
        "scan.views[2]: duplicate (section 0, angle 360.0 deg), the same view as scan.views[0]",
    ] or problems == [
        "scan.views[2]: duplicate (section 0, angle 360.0 deg), the same view as scan.views[0]",
        "scan.views[1]: duplicate (section 0, angle -240.0 deg), the same view as scan.views[2]",
    ]


def test_duplicate_heights_and_views_per_section(capture_dir):
    edit(capture_dir, lambda d: [v.update(z_mm=0.0) for v in d["scan"]["views"][3:]])
    problems = problems_of(capture_dir)
    assert problems == ["scan.views[3]: section 1 is at z_mm 0.0, the height of section 0"]
    limits = DeviceLimits(max_views_per_section=2)
    edit(capture_dir, lambda d: [v.update(z_mm=2.0) for v in d["scan"]["views"][3:]])
    problems = problems_of(capture_dir, limits=limits)
    assert problems == [
        "section 0: 3 views, at most 2 allowed",
        "section 1: 3 views, at most 2 allowed",
    ]


def test_too_many_views_is_refused_before_any_frame_is_looked_at(capture_dir, no_decoding):
    def grow(data: dict[str, Any]) -> None:
        view = data["scan"]["views"][0]
        data["scan"]["views"] = [
            {**view, "section": k // 10, "z_mm": float(k // 10), "angle_deg": float(k % 10)}
            for k in range(10_001)
        ]

    edit(capture_dir, grow)
    assert problems_of(capture_dir) == ["scan.views: 10001 views, at most 10000 allowed"]


# --- the manifest ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("content", "reason"),
    [
        (b"[" * 100_000 + b"]" * 100_000, "nested too deeply"),
        (
            b'{"format": "lightsection-capture", "version": 1, "x": '
            + b"[" * 5000
            + b"]" * 5000
            + b"}",
            "nested too deeply",
        ),
        (b'{"format": "\xff\xfe"}', "not valid JSON"),
        (b'{"version": 1' + b"9" * 5000 + b"}", "not valid JSON"),
        (b"", "not valid JSON"),
        (b"\x00" * 100, "not valid JSON"),
    ],
)
def test_a_malformed_manifest_is_one_line_naming_the_file(capture_dir, content, reason):
    (capture_dir / "capture.json").write_bytes(content)
    problems = problems_of(capture_dir)
    assert len(problems) == 1 and "\n" not in problems[0]
    assert str(capture_dir / "capture.json") in problems[0] and reason in problems[0]
    assert len(problems[0]) < 400


def test_an_oversized_manifest_is_not_read(capture_dir):
    limits = DeviceLimits(max_manifest_bytes=100)
    problems = problems_of(capture_dir, limits=limits)
    assert len(problems) == 1 and "more than 100" in problems[0]


# --- nothing outside the capture is read ------------------------------------------------


def test_frames_linked_to_files_outside_the_capture_are_refused(capture_dir, tmp_path):
    outside = tmp_path / "secret.png"
    cv2.imwrite(str(outside), frame(9))
    elsewhere = tmp_path / "elsewhere"
    elsewhere.mkdir()
    cv2.imwrite(str(elsewhere / "s000_v01_on.png"), frame(9))
    target = capture_dir / "scan/s000_v00_on.png"
    target.unlink()
    target.symlink_to(outside)
    (capture_dir / "linked").symlink_to(elsewhere, target_is_directory=True)
    edit(capture_dir, lambda d: d["scan"]["views"][1].update(laser_on="linked/s000_v01_on.png"))
    problems = problems_of(capture_dir)
    assert problems == [
        "scan.views[0].laser_on: 'scan/s000_v00_on.png' is a link to a file outside the "
        "capture folder; copy the file into the capture instead",
        "scan.views[1].laser_on: 'linked/s000_v01_on.png' is a link to a file outside the "
        "capture folder; copy the file into the capture instead",
    ]


def test_a_manifest_linked_from_outside_is_refused(tmp_path, capture_dir):
    other = tmp_path / "other"
    other.mkdir()
    (other / "capture.json").symlink_to(capture_dir / "capture.json")
    problems = problems_of(other)
    assert problems == ["capture.json is a link to a file outside the capture folder"]


def test_links_inside_the_capture_are_fine(capture_dir):
    link = capture_dir / "scan/alias.png"
    link.symlink_to(capture_dir / "scan/s000_v00_on.png")
    edit(capture_dir, lambda d: d["scan"]["views"][0].update(laser_on="scan/alias.png"))
    assert load_capture(capture_dir).scan_views[0].laser_on == link


# --- speed -------------------------------------------------------------------------------


def test_a_10000_view_capture_is_validated_from_headers(tmp_path, capsys):
    """Validity of a maximal capture; the time is reported here and by bench_capture."""
    root = tmp_path / "max"
    plan = ScanPlan.regular(1000, 0.2, 10)
    write_uniform_capture(root, plan, (64, 48))
    start = time.perf_counter()
    loaded = load_capture(root)
    elapsed_s = time.perf_counter() - start
    assert loaded.plan("object") == plan
    with capsys.disabled():
        print(f"\n10,000-view capture validated in {elapsed_s:.2f} s ({os.cpu_count()} cores)")
