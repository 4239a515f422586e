"""The printable calibration chessboard: exact millimetre geometry, checked from the SVG itself."""

import importlib.util
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import cv2
import numpy as np
import pytest

SCRIPT = Path(__file__).resolve().parents[2] / "hardware" / "calibration_board.py"
SVG = "{http://www.w3.org/2000/svg}"


def _module():
    spec = importlib.util.spec_from_file_location("calibration_board", SCRIPT)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


board = _module()


def write_sheet(tmp_path, *args):
    """Run the generator as a user would; return the parsed SVG root."""
    out = tmp_path / "board.svg"
    result = subprocess.run(
        [sys.executable, str(SCRIPT), *args, "-o", str(out)], capture_output=True, text=True
    )
    assert result.returncode == 0, result.stderr
    return ET.parse(out).getroot()


def rects(group):
    """Return (x, y, width, height, fill) of every rectangle in an SVG group."""
    return [
        (*(float(r.get(k)) for k in ("x", "y", "width", "height")), r.get("fill"))
        for r in group.iter(f"{SVG}rect")
    ]


def group(root, name):
    return next(g for g in root.iter(f"{SVG}g") if g.get("id") == name)


@pytest.mark.parametrize(
    ("args", "corners", "square_mm"),
    [([], (13, 11), 2.0), (["--preset", "limb"], (13, 9), 12.0),
     (["--inner-corners", "11x8", "--square-mm", "7.25"], (11, 8), 7.25)],
)  # fmt: skip
def test_page_is_at_exact_millimetre_scale_and_squares_sit_on_the_grid(
    tmp_path, args, corners, square_mm
):
    root = write_sheet(tmp_path, *args)
    assert (root.get("width"), root.get("height")) == ("210mm", "297mm")
    assert root.get("viewBox") == "0 0 210 297"  # one user unit is one millimetre
    chess = group(root, "board")
    assert chess.get("data-inner-corners") == f"{corners[0]} {corners[1]}"
    assert float(chess.get("data-square-mm")) == square_mm
    x0, y0 = (float(v) for v in chess.get("data-origin-mm").split())
    field, *squares = rects(chess)
    nx, ny = corners[0] + 1, corners[1] + 1
    assert field[:4] == pytest.approx((x0, y0, nx * square_mm, ny * square_mm), abs=1e-9)
    assert len(squares) == (nx * ny + 1) // 2
    seen = set()
    for x, y, w, h, fill in squares:
        assert fill == "black"
        assert abs(w - square_mm) < 1e-9 and abs(h - square_mm) < 1e-9
        i, j = (x - x0) / square_mm, (y - y0) / square_mm
        assert abs(i - round(i)) * square_mm < 1e-9 and abs(j - round(j)) * square_mm < 1e-9
        i, j = round(i), round(j)
        assert 0 <= i < nx and 0 <= j < ny and (i + j) % 2 == 0
        seen.add((i, j))
    assert len(seen) == len(squares)
    # The board is centred across the page and lies inside the printable margin.
    assert abs(x0 + nx * square_mm / 2 - 105.0) < 1e-9
    assert x0 >= board.MARGIN_MM and y0 + ny * square_mm <= 297 - board.MARGIN_MM


def test_check_square_measures_fifty_millimetres_and_the_ruler_one_hundred(tmp_path):
    root = write_sheet(tmp_path)
    (ox, oy, ow, oh, ofill), (ix, iy, iw, ih, ifill) = rects(group(root, "check-square"))
    assert (ow, oh, ofill) == (50.0, 50.0, "black")
    assert (ifill, iw, ih) == ("white", 48.0, 48.0) and (ix - ox, iy - oy) == (1.0, 1.0)
    ticks = rects(group(root, "ruler"))[1:]
    centres = sorted(x + w / 2 for x, y, w, h, fill in ticks)
    assert len(centres) == 101
    assert np.allclose(np.diff(centres), 1.0, atol=1e-9)
    assert centres[-1] - centres[0] == pytest.approx(100.0, abs=1e-9)


def test_the_specification_is_printed_on_the_sheet(tmp_path):
    root = write_sheet(tmp_path, "--preset", "limb")
    text = " ".join(t.text for t in group(root, "spec").iter(f"{SVG}text"))
    assert "13 x 9 inner corners" in text and "12 mm squares" in text
    assert "board 168 x 120 mm" in text
    assert "inner_corners = [13, 9], square_mm = 12" in text
    assert "100 %" in text and "50 mm" in text


def rasterise(root, px_per_mm):
    """Paint the sheet's rectangles (document order) into a grey image."""
    width_mm, height_mm = (float(v) for v in root.get("viewBox").split()[2:])
    image = np.zeros((round(height_mm * px_per_mm), round(width_mm * px_per_mm)), np.uint8)
    for x, y, w, h, fill in rects(root):
        c0, r0 = round(x * px_per_mm), round(y * px_per_mm)
        c1, r1 = round((x + w) * px_per_mm), round((y + h) * px_per_mm)
        image[r0:r1, c0:c1] = 255 if fill == "white" else 0
    return image


def test_opencv_finds_every_inner_corner_at_the_square_pitch(tmp_path):
    root = write_sheet(tmp_path, "--preset", "limb")
    px_per_mm = 4.0
    image = rasterise(root, px_per_mm)
    found, corners = cv2.findChessboardCorners(image, (13, 9))
    assert found
    corners = corners.reshape(9, 13, 2)
    pitch_px = np.linalg.norm(np.diff(corners, axis=1), axis=2)
    assert np.allclose(pitch_px, 12.0 * px_per_mm, atol=0.5)


def test_the_sim_board_matches_the_simulated_rig():
    from lamina_device.sim.rig import Rig

    sheet = board.BoardSheet(*board.PRESETS["sim"])
    spec = Rig().board
    assert sheet.inner_corners == tuple(spec.inner_corners)
    assert sheet.square_mm == spec.square_mm


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--square-mm", "40"], "does not fit on a4"),
        (["--inner-corners", "7x7"], "orientation"),
        (["--inner-corners", "1x5"], "at least 2x2"),
        (["--page", "b5"], "page 'b5'"),
        (["--inner-corners", "nine"], "not NxM"),
    ],
)
def test_bad_requests_end_in_one_clear_line(tmp_path, args, message):
    out = tmp_path / "board.svg"
    result = subprocess.run(
        [sys.executable, str(SCRIPT), *args, "-o", str(out)], capture_output=True, text=True
    )
    assert result.returncode == 2
    assert message in result.stderr.strip().splitlines()[-1]
    assert "Traceback" not in result.stderr
    assert not out.exists()
