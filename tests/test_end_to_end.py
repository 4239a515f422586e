"""The whole product on simulated hardware: device program, pty link, host pipeline.

These run the real commands as a user would (``lamina`` starting ``lamina-device``
on a pseudo-terminal pair) and check results against the simulator's ground truth.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import cv2
import numpy as np
import pymeshlab
import pytest
import serial

from lamina_host.link.spawn import PtyBridge
from lamina_host.store.outputs import load_segments
from lamina_shared.link import Channel
from lamina_shared.protocol import PROTOCOL_VERSION, Kind, encode_json
from tests.helpers.cli import device_command

# Scans go into a library in the user's data folder: keep the tests' library out of it.
TEST_DATA_HOME = tempfile.mkdtemp(prefix="lamina-test-data-")


def lamina(*args: str) -> subprocess.CompletedProcess[str]:
    """Run the host command line in a fresh process."""
    return subprocess.run(
        [sys.executable, "-m", "lamina_host", *args],
        capture_output=True,
        text=True,
        timeout=300,
        env={**os.environ, "XDG_DATA_HOME": TEST_DATA_HOME},
    )


def record(out: Path, *args: str) -> subprocess.CompletedProcess[str]:
    """Run ``lamina-device record`` on the simulated rig."""
    return subprocess.run(
        device_command("record", "--hardware", "sim", "--out", str(out), *args),
        capture_output=True,
        text=True,
        timeout=300,
    )


def one_line_error(result: subprocess.CompletedProcess[str]) -> str:
    """Assert a clean user-facing failure and return its message."""
    assert result.returncode == 2, result.stdout + result.stderr
    assert "Traceback" not in result.stderr
    lines = [line for line in result.stderr.splitlines() if line.startswith("lamina")]
    assert len(lines) == 1, result.stderr
    return lines[0]


@pytest.fixture(scope="module")
def live_scan(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("live") / "cylinder"
    result = lamina(
        "scan",
        "--device",
        "sim",
        "-o",
        str(out),
        "--object",
        "cylinder:d=19.05",
        "--sections",
        "4",
        "--pitch",
        "2",
        "--views",
        "8",
        "--expect",
        "cylinder:d=19.05",
    )
    assert result.returncode == 0, result.stderr
    return out


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("capture") / "cylinder"
    result = record(
        out, "--object", "cylinder:d=19.05", "--sections", "4", "--pitch", "2", "--views", "8"
    )
    assert result.returncode == 0, result.stderr
    return out


def test_simulated_cylinder_meets_the_accuracy_target(live_scan):
    report = json.loads((live_scan / "report.json").read_text())
    accuracy = report["accuracy"]
    assert [row["section"] for row in accuracy["rows"]] == [0, 1, 2, 3]
    for row in accuracy["rows"]:
        # Issue #5 target: at most 0.03 mm about the mean centroid on every section.
        assert row["rms_mean_mm"] <= 0.03, row
    assert report["calibration"]["n_corners"] == 143
    assert report["calibration"]["rms_mm"] < 0.05
    assert abs(report["correction_factor"] - 1.0) < 0.05
    assert all(s["harmonics"] >= 1 for s in report["sections"])
    assert set(report["timings_s"]) >= {"calibrate_grid", "calibrate_axis", "fit_efd", "mesh"}


def test_outputs_are_readable_point_clouds_and_mesh(live_scan):
    for name in ("raw_points.ply", "points.ply", "mesh.ply"):
        meshes = pymeshlab.MeshSet()
        meshes.load_new_mesh(str(live_scan / name))
        mesh = meshes.current_mesh()
        assert mesh.vertex_number() > 100, name
        z = mesh.vertex_matrix()[:, 2]
        assert sorted(set(np.round(z, 6))) == [0.0, 2.0, 4.0, 6.0], name
    meshes.load_new_mesh(str(live_scan / "mesh.ply"))
    assert meshes.current_mesh().face_number() > 500
    # Object frame: origin on the axis, so the off-axis cylinder's centre is where the
    # simulator put it relative to the axis (about 1 mm away, never 10).
    points = pymeshlab.MeshSet()
    points.load_new_mesh(str(live_scan / "points.ply"))
    centre = points.current_mesh().vertex_matrix()[:, :2].mean(axis=0)
    assert np.hypot(*centre) < 5.0


def test_replay_of_a_recorded_capture_gives_identical_segments(live_scan, capture, tmp_path):
    out = tmp_path / "replayed"
    result = lamina(
        "scan", "--device", f"replay:{capture}", "-o", str(out), "--expect", "cylinder:d=19.05"
    )
    assert result.returncode == 0, result.stderr
    for name in ("segments.npz", "cylinder-segments.npz"):
        live, replayed = load_segments(live_scan / name), load_segments(out / name)
        assert len(live) == len(replayed) > 0
        assert all(a.same_as(b) for a, b in zip(live, replayed, strict=True)), name
    live_report = json.loads((live_scan / "report.json").read_text())
    replay_report = json.loads((out / "report.json").read_text())
    assert replay_report["accuracy"] == live_report["accuracy"]


def test_no_chessboard_in_view_stops_before_anything_is_acquired(capture, tmp_path):
    """Issue 24: the board is found before the cylinder and the object are acquired (as
    the terminal UI does), so a board out of view wastes no acquisition and records no scan."""
    broken = tmp_path / "blank-grid"
    shutil.copytree(capture, broken)
    cv2.imwrite(str(broken / "calib/grid.png"), np.full((480, 640), 30, np.uint8))
    library = tmp_path / "library.sqlite"
    out = tmp_path / "out"
    args = ["--device", f"replay:{broken}", "-o", str(out), "--library", str(library)]
    message = one_line_error(lamina("scan", *args))
    assert "no chessboard" in message
    assert not (tmp_path / "out" / "segments.npz").exists()
    assert not (tmp_path / "out" / "cylinder-segments.npz").exists()
    assert "no scans" in lamina("scans", "--library", str(library)).stdout


def test_fewer_than_four_corners(capture, tmp_path):
    broken = tmp_path / "tiny-board"
    shutil.copytree(capture, broken)
    manifest = json.loads((broken / "capture.json").read_text())
    manifest["calibration_grid"]["inner_corners"] = [3, 1]
    (broken / "capture.json").write_text(json.dumps(manifest))
    message = one_line_error(
        lamina("scan", "--device", f"replay:{broken}", "-o", str(tmp_path / "out"))
    )
    assert "at least 4" in message


def test_capture_with_missing_and_unreadable_frames(capture, tmp_path):
    broken = tmp_path / "damaged"
    shutil.copytree(capture, broken)
    (broken / "scan/s001_v03_on.png").unlink()
    data = (broken / "cyl/s000_v02_off.png").read_bytes()
    (broken / "cyl/s000_v02_off.png").write_bytes(data[:100])
    message = one_line_error(
        lamina("scan", "--device", f"replay:{broken}", "-o", str(tmp_path / "out"))
    )
    assert "scan/s001_v03_on.png is missing" in message
    assert "cyl/s000_v02_off.png is unreadable" in message


def test_port_that_does_not_exist(tmp_path):
    message = one_line_error(
        lamina("scan", "--device", "/dev/ttyNOPE9", "-o", str(tmp_path / "out"))
    )
    assert "serial port /dev/ttyNOPE9 does not exist" in message


def test_device_speaking_another_protocol_version(tmp_path):
    bridge = PtyBridge()

    def future_device() -> None:
        # A device from the future: answers HELLO with the next protocol version.
        with serial.Serial(bridge.device_port, timeout=0.05) as port:
            channel = Channel(port)
            for _ in range(200):
                message = channel.receive(0.1)
                if message is not None and message.kind is Kind.HELLO:
                    channel.send(
                        encode_json(
                            Kind.WELCOME,
                            {
                                "protocol": PROTOCOL_VERSION + 1,
                                "hardware": "pi",
                                "image_size": [640, 480],
                            },
                        )
                    )
                    return

    peer = threading.Thread(target=future_device, daemon=True)
    peer.start()
    try:
        message = one_line_error(
            lamina("scan", "--device", bridge.host_port, "-o", str(tmp_path / "out"))
        )
    finally:
        peer.join(timeout=5)
        bridge.close()
    expected = f"protocol version {PROTOCOL_VERSION + 1}"
    assert expected in message and f"speaks {PROTOCOL_VERSION}" in message


def test_replay_reads_captures_from_other_tools(live_scan, capture, tmp_path):
    """16-bit RGB frames, the laser in the red channel, views listed in another order."""
    other = tmp_path / "other-tool"
    shutil.copytree(capture, other)
    manifest = json.loads((other / "capture.json").read_text())
    for path in other.rglob("*.png"):
        grey = cv2.imread(str(path), cv2.IMREAD_UNCHANGED).astype(np.uint16) * 257
        rgb = np.zeros((*grey.shape, 3), np.uint16)
        rgb[..., 2] = grey  # red in OpenCV's BGR order; blue and green stay dark
        cv2.imwrite(str(path), rgb)
    manifest["scan"]["views"].reverse()
    manifest["meta"] = {"made_by": "another tool"}
    (other / "capture.json").write_text(json.dumps(manifest))
    out = tmp_path / "out"
    result = lamina("scan", "--device", f"replay:{other}", "-o", str(out))
    assert result.returncode == 0, result.stderr
    # Views are numbered in scan order, so compare by place (section, angle), not number.
    by_place = lambda segments: {(s.section, s.angle_deg): s for s in segments}  # noqa: E731
    live = by_place(load_segments(live_scan / "segments.npz"))
    replayed = by_place(load_segments(out / "segments.npz"))
    assert live.keys() == replayed.keys()
    for place, segment in live.items():
        # 8-bit values v stored as 257 v in 16 bits give the same 8-bit differences.
        other = replayed[place]
        for name in ("cols", "rows", "peak", "width"):
            assert np.array_equal(getattr(segment, name), getattr(other, name)), (place, name)


def test_unknown_simulated_object_is_a_one_line_error(tmp_path):
    message = one_line_error(
        lamina("scan", "--device", "sim", "--object", "pyramid:h=3", "-o", str(tmp_path / "out"))
    )
    assert "pyramid" in message
