"""A continuous scan's rolling shutter: each stripe point at the angle its row was exposed.

The table turns through a continuous view's exposure, and the camera exposes its rows one
after another, so the rows of one stripe were taken at different angles (0.7 degrees
across 200 rows at a turn a second). The device gives the view its median row's angle and
reports the turn per row in its WELCOME; the host turns each point by its own share.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from lamina_device.acquisition import acquire, row_turn_deg
from lamina_device.sim import open_sim
from lamina_device.sim.axes import Mechanics
from lamina_host import cli
from lamina_host.link.identity import identity_difference
from lamina_host.link.identity import row_turn_deg as scan_row_turn_deg
from lamina_host.reconstruct.assembly import to_object_frame
from lamina_host.reconstruct.axis import AxisCalibration, fit_circle
from lamina_host.reconstruct.calibration import GridCalibration, Homography
from lamina_host.reconstruct.pipeline import ProcessOptions, assemble, object_points, reconstruct
from lamina_host.store.library import Library
from lamina_shared.types import ScanPlan, Segment
from tests.helpers.campaign import CampaignPlan, _calibration

RADIUS_MM = 30.0
OFF_AXIS = "cylinder:d=60,x=40"
"""A circle 40 mm off the axis: turning a point about the axis moves it off the circle."""


HALF_LIMB = CampaignPlan("limb", sections=1, pitch_mm=10.0, views=8, noise="none", resolution=0.5)
"""The limb rig's camera binned 2x (768 x 432): the same geometry, quicker frames."""


@pytest.fixture(scope="module")
def off_axis_scans():
    """Return calibration data and the off-axis cylinder's section in either mode."""
    rig = HALF_LIMB.rig()
    taken = _calibration(HALF_LIMB)
    scans = {}
    for mode in ("stop-and-go", "continuous"):
        hardware = open_sim(OFF_AXIS, 0, "none", "limb", rig)
        segments: list = []
        try:
            acquire(hardware, "object", HALF_LIMB.scan_plan().with_mode(mode), segments.append)
        finally:
            hardware.close()
        scans[mode] = (segments, row_turn_deg(hardware))
    board, diameter = hardware.board, hardware.cylinder_diameter_mm
    return taken.grid_image, board, taken.cylinder, diameter, scans


def _circle_rms(calibration, segments, turn: float) -> tuple[float, float]:
    """Return the radius and RMS residual of a circle fitted to the section's points."""
    grid, board, cylinder, diameter, _ = calibration
    result = reconstruct(grid, board, cylinder, diameter, segments, ProcessOptions())
    by_section, _, _ = assemble(segments, result.grid, result.axis, 0.0, turn)
    fitted = fit_circle(np.concatenate(by_section[0]))
    return fitted.r, fitted.rms_mm


@pytest.mark.timeout(240)
def test_a_continuous_views_points_take_their_own_rows_angle(off_axis_scans):
    """On a circle off the axis, one angle per view bends each view's arc off the circle;
    each row's own angle brings it back to within the frame timestamps' jitter."""
    still, _ = off_axis_scans[4]["stop-and-go"]
    moving, turn = off_axis_scans[4]["continuous"]
    assert turn == pytest.approx(360.0 * 7957e-6 / 432)  # the box's speed and read-out
    r_still, rms_still = _circle_rms(off_axis_scans, still, 0.0)
    r_one, rms_one = _circle_rms(off_axis_scans, moving, 0.0)
    r_rows, rms_rows = _circle_rms(off_axis_scans, moving, turn)
    assert rms_still < 0.01 and abs(r_still - RADIUS_MM) < 0.01  # noise "none": the floor
    assert rms_one > 0.025  # one angle a view: the rolling shutter's error (measured 0.029)
    # Each row's angle: measured 0.018 mm; what is left is the 50 us timestamp jitter's
    # turn of a whole view (0.018 deg, 0.013 mm at 40 mm from the axis).
    assert rms_rows < 0.022 and rms_rows < 0.7 * rms_one
    assert abs(r_rows - RADIUS_MM) < 0.01 and abs(r_one - RADIUS_MM) < 0.01


def test_a_view_turned_point_by_point_is_each_point_turned_alone():
    rng = np.random.default_rng(3)
    points = rng.uniform(-80, 80, (50, 2))
    angles = rng.uniform(0, 360, 50)
    together = to_object_frame(points, angles, (1.5, -2.0), 1.001)
    alone = np.concatenate(
        [to_object_frame(p, a, (1.5, -2.0), 1.001) for p, a in zip(points, angles, strict=True)]
    )
    np.testing.assert_allclose(together, alone, rtol=0, atol=1e-12)


AXIS_MM, FACTOR = (1.5, -2.0), 1.001


def _calibrated(mechanics: Mechanics) -> AxisCalibration:
    """Return the host's angle calibration of ``mechanics`` as a cylinder scan measures it
    (each of 8 views' offset exact, the undershoot as its scale)."""
    commanded = np.arange(0.0, 360.0, 45.0)
    offsets = [mechanics.true_angle_deg(c) - c for c in commanded]
    return AxisCalibration(
        AXIS_MM, FACTOR, 99.8, 100.0, np.zeros((8, 2)), np.full(8, 50.0), (), "per-view",
        angle_scale=1.0 + mechanics.angle_scale_error,
        view_offsets_deg=np.column_stack([commanded, offsets]),
    )  # fmt: skip


@settings(max_examples=60, deadline=None)
@given(
    median_deg=st.floats(0.0, 720.0, exclude_max=True),
    row_turn=st.floats(0.001, 0.01),
    span=st.integers(20, 400),
)
def test_a_continuous_view_across_the_turns_count_lands_where_the_table_was(
    median_deg: float, row_turn: float, span: int
) -> None:
    """The simulator's table falls behind its count over the turns (0.2 degrees short per
    45, 1.6 a turn): a view whose rows span a whole turn of the count (the 0-degree view,
    at any frame phase) has its rows each side of it, and each row must be placed at its
    own count (the view's angle and whole turns as the device sends them, plus its row's
    share), the rows past the turn a turn's shortfall on, not back at the turn's start
    (1.6 degrees, about 1 mm, off)."""
    mechanics = Mechanics()
    rows = np.linspace(-span, span, 2 * span + 1) + 300.0
    cols = np.round(np.linspace(100.0, 140.0, len(rows)))  # whole columns, as sent
    counts = median_deg + row_turn * (rows - np.median(rows))
    true_deg = np.array([mechanics.true_angle_deg(c) for c in counts])
    plane = np.column_stack([cols, rows]) * 0.1  # the homography below: 0.1 mm a pixel
    truth = to_object_frame(plane, true_deg, AXIS_MM, FACTOR)
    turns = int(median_deg // 360.0)
    segment = Segment(
        "object", 0, 0, 0.0, median_deg - 360.0 * turns, cols.astype(np.int32), rows,
        np.full(len(rows), 200.0), np.full(len(rows), 5.0), turns=turns,
    )  # fmt: skip
    grid = GridCalibration(
        Homography(np.diag([0.1, 0.1, 1.0])), np.zeros((0, 2)), np.zeros((0, 2)),
        np.zeros(0), 0.01, 0.02, 54, (),
    )  # fmt: skip
    order = np.arange(len(rows))
    placed = object_points(segment, order, grid, _calibrated(mechanics), row_turn)
    # What is left is the table's repeatable jitter (0.01 degrees at each count, never
    # calibrated) and the runout between the calibrated views: under 0.03 degrees.
    off_deg = np.degrees(np.linalg.norm(placed - truth, axis=1) / np.linalg.norm(truth, axis=1))
    assert off_deg.max() < 0.03


def test_only_a_continuous_scan_turns_its_points_by_row():
    continuous = ScanPlan.regular(2, 10.0, 8, "continuous")
    identity = {"row_turn_deg": 0.0033}
    assert scan_row_turn_deg(identity, continuous) == 0.0033
    assert scan_row_turn_deg(identity, continuous.with_mode("stop-and-go")) == 0.0
    assert scan_row_turn_deg({}, continuous) == 0.0  # a device from before the figure
    assert scan_row_turn_deg(None, continuous) == 0.0
    assert scan_row_turn_deg({"row_turn_deg": "x"}, continuous) == 0.0
    assert scan_row_turn_deg(identity, None) == 0.0


@pytest.mark.timeout(240)
def test_a_stored_continuous_scan_is_processed_again_the_same(tmp_path: Path, capsys):
    """The figure travels with the scan (its identity), so ``lamina process`` turns its
    points as the scan did: the same outlines to the digit."""
    library = tmp_path / "library.sqlite"
    out = tmp_path / "scan"
    argv = ["scan", "--device", "sim", "--object", "cylinder:d=12,x=5", "--sections", "1"]
    argv += ["--views", "8", "--mode", "continuous", "--library", str(library), "-o", str(out)]
    assert cli.main(argv) == 0
    with Library(library) as opened:
        (scan,) = opened.scans()
        record = opened.scan(scan.id)
        assert record.identity["row_turn_deg"] == pytest.approx(360.0 * 7957e-6 / 480)
        assert opened.inputs(scan.id).row_turn_deg == record.identity["row_turn_deg"]
    first = json.loads((out / "report.json").read_text())
    again = tmp_path / "again"
    assert cli.main(["process", str(scan.id), "--library", str(library), "-o", str(again)]) == 0
    second = json.loads((again / "report.json").read_text())
    assert second["sections"] == first["sections"]
    capsys.readouterr()


def test_a_scan_recorded_before_the_figure_resumes_and_one_with_another_does_not():
    """A half-acquired scan from before the update is finished as it began (no figure,
    no turn); a scan whose device now turns another amount per row is refused."""
    before = {"software": "lamina-device 0.1.0", "hardware": "sim", "calibration": "ab"}
    now = {**before, "row_turn_deg": 0.0033}
    assert identity_difference(before, now) is None
    assert scan_row_turn_deg(before, ScanPlan.regular(1, 10.0, 8, "continuous")) == 0.0
    faster = {**before, "row_turn_deg": 0.0066}
    assert "row_turn_deg" in (identity_difference(now, faster) or "")
    assert "row_turn_deg" in (identity_difference(now, before) or "")
