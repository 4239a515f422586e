"""Reading, validating and writing the raw capture format (docs/capture-format.md)."""

import json

import cv2
import numpy as np
import pytest

from lamina_shared.capture import CaptureError, CaptureWriter, load_capture, read_frame
from lamina_shared.types import BoardSpec, ScanPlan
from tests.helpers.captures import assert_reports

BOARD = BoardSpec((9, 7), 3.0, (-12.0, -9.0))


def frame(value: int) -> np.ndarray:
    image = np.full((48, 64), value, np.uint8)
    image[10, :] = 200
    return image


@pytest.fixture
def capture_dir(tmp_path):
    writer = CaptureWriter(tmp_path / "cap", (64, 48), {"object": "test"})
    writer.add_grid(frame(1), BOARD)
    writer.set_cylinder(19.05)
    for k, view in enumerate(ScanPlan.regular(1, 2.0, 4).views):
        writer.add_view("cylinder", view, k, frame(2), frame(3))
    for k, view in enumerate(ScanPlan.regular(2, 2.0, 3).views):
        writer.add_view("object", view, k % 3, frame(4 + k), frame(50))
    writer.close()
    return tmp_path / "cap"


def test_written_capture_reads_back(capture_dir):
    capture = load_capture(capture_dir)
    assert capture.image_size == (64, 48)
    assert capture.board == BOARD
    assert capture.cylinder_diameter_mm == 19.05
    assert len(capture.cylinder_views) == 4
    assert capture.plan("object") == ScanPlan.regular(2, 2.0, 3)
    third = capture.scan_views[2]
    assert np.array_equal(read_frame(third.laser_on), frame(6))


def test_writer_refuses_to_overwrite_a_capture(capture_dir):
    with pytest.raises(FileExistsError):
        CaptureWriter(capture_dir, (64, 48))


def edit(capture_dir, change):
    path = capture_dir / "capture.json"
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def test_every_problem_is_reported_at_once(capture_dir):
    def break_it(data):
        views = data["scan"]["views"]
        views[0]["laser_on"] = "scan/missing.png"
        views[1]["angle_deg"] = "NaN"
        views[4]["section"], views[4]["angle_deg"] = views[2]["section"], views[2]["angle_deg"]
        data["calibration_grid"]["pattern"] = "circles"
        views[3]["laser_off"] = "../outside.png"

    edit(capture_dir, break_it)
    (capture_dir / "scan/s001_v02_on.png").write_bytes(b"\x89PNG\r\n\x1a\nbroken")
    with pytest.raises(CaptureError) as info:
        load_capture(capture_dir)
    problems = info.value.problems
    assert_reports(
        problems,
        "scan.views[0].laser_on: file scan/missing.png is missing",
        "scan.views[1].angle_deg",
        "scan.views[4]: duplicate (section 0, angle 240.0 deg)",
        "calibration_grid.pattern: unknown pattern 'circles'",
        "scan.views[3].laser_off: '../outside.png' must stay inside",
        "scan.views[5].laser_on: scan/s001_v02_on.png is unreadable",
    )
    assert len(problems) == 6, problems


def test_wrong_image_size_and_truncated_frame(capture_dir):
    cv2.imwrite(str(capture_dir / "cyl/s000_v01_on.png"), np.zeros((10, 10), np.uint8))
    good = (capture_dir / "cyl/s000_v02_off.png").read_bytes()
    (capture_dir / "cyl/s000_v02_off.png").write_bytes(good[: len(good) // 2])
    with pytest.raises(CaptureError) as info:
        load_capture(capture_dir)
    text = str(info.value)
    assert "calibration_cylinder.views[1].laser_on: cyl/s000_v01_on.png is 10x10" in text
    assert "calibration_cylinder.views[2].laser_off: cyl/s000_v02_off.png is unreadable" in text


def test_unknown_version_is_named(capture_dir):
    edit(capture_dir, lambda d: d.update(version=7))
    with pytest.raises(CaptureError, match="capture version 7 is not supported"):
        load_capture(capture_dir)


def test_missing_manifest_and_folder(tmp_path):
    with pytest.raises(CaptureError, match="does not exist"):
        load_capture(tmp_path / "nope")
    with pytest.raises(CaptureError, match=r"capture\.json is missing"):
        load_capture(tmp_path)


def test_rgb_frames_use_the_laser_channel(tmp_path):
    image = np.zeros((4, 5, 3), np.uint8)
    image[..., 2] = 200  # red in OpenCV's BGR order
    image[..., 1] = 10
    cv2.imwrite(str(tmp_path / "f.png"), image)
    assert read_frame(tmp_path / "f.png", "red").max() == 200
    assert read_frame(tmp_path / "f.png", "green").max() == 10


def test_unknown_keys_are_ignored_and_laser_off_is_optional(capture_dir):
    def change(data):
        data["future_field"] = {"x": 1}
        del data["scan"]["views"][0]["laser_off"]

    edit(capture_dir, change)
    capture = load_capture(capture_dir)
    assert capture.scan_views[0].laser_off is None
