"""Half-block rendering and the adapter's measurements, against known truth."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lamina_host.ui.tui.adapter import (
    Progress,
    SectionRow,
    UserError,
    check_subject,
    parse_plan,
    radius_profile,
    roundness,
    volume_mm3,
)
from lamina_host.ui.tui.render import STRIPE_RGB, UPPER_HALF, cell_grid, fit_size, grid_text


def test_fit_size_keeps_the_aspect_ratio() -> None:
    """640 x 480 in 80 x 24 cells is limited by height: 48 pixel rows, 64 columns."""
    assert fit_size((640, 480), 80, 24) == (64, 48)
    assert fit_size((640, 480), 40, 100) == (40, 30)


def test_cell_grid_places_a_bright_square_and_the_stripe() -> None:
    """A white quarter and a stripe row land in the cells they cover."""
    image = np.zeros((480, 640), np.uint8)
    image[:240, :320] = 255  # top-left quarter
    stripe = np.array([[u, 400.0] for u in range(640)])
    grid = cell_grid(image, 64, 24, stripe)
    assert (grid.cols, grid.rows) == (64, 24)
    gray = grid.pixels[:, :, 1]
    assert gray[:24, :32].min() == 255 and gray[:24, 32:].max() == 0
    stripe_row = int(400.5 * 48 / 480)
    assert (grid.pixels[stripe_row] == STRIPE_RGB).all()
    assert not (grid.pixels[stripe_row - 1] == STRIPE_RGB).all(axis=1).any()


def test_cell_grid_reads_16_bit_colour_frames() -> None:
    """A 16-bit BGR frame is shown by its top byte."""
    image = np.full((10, 10, 3), 0x8000, np.uint16)
    assert (cell_grid(image, 10, 5).pixels == 128).all()


def test_grid_text_has_one_half_block_per_cell() -> None:
    """Rows x cols half blocks, top pixel as foreground, bottom as background."""
    image = np.zeros((4, 3), np.uint8)
    image[1] = 200  # the bottom half of the first cell row
    text = grid_text(cell_grid(image, 3, 2))
    assert text.plain == "\n".join([UPPER_HALF * 3] * 2)
    style = text.spans[0].style
    assert not isinstance(style, str) and style.color and style.bgcolor
    assert style.color.triplet == (0, 0, 0) and style.bgcolor.triplet == (200, 200, 200)


def test_roundness_is_one_for_a_circle_and_less_for_an_ellipse() -> None:
    """4 pi A / P^2: a circle 1, a 2:1 ellipse about 0.84."""
    t = np.linspace(0, 2 * np.pi, 2000, endpoint=False)
    circle = np.column_stack([np.cos(t), np.sin(t)]) * 9.5
    ellipse = np.column_stack([2 * np.cos(t), np.sin(t)])
    assert roundness(circle) == pytest.approx(1.0, abs=1e-5)
    # Ramanujan's perimeter of the 2:1 ellipse: 9.6884; area 2 pi.
    assert roundness(ellipse) == pytest.approx(4 * math.pi * 2 * math.pi / 9.6884**2, rel=1e-4)


def test_volume_and_profile_of_a_cylinder_by_sections() -> None:
    """Areas of a cylinder integrate to area x height; the profile gives the radius back."""
    rows = [SectionRow(k, 2.0 * k, 100, 0.0, math.pi * 25.0, 1.0, 5) for k in range(4)]
    assert volume_mm3(rows) == pytest.approx(math.pi * 25.0 * 6.0)
    assert radius_profile(rows) == ([0.0, 2.0, 4.0, 6.0], pytest.approx([5.0] * 4))
    assert volume_mm3(rows[:1]) == 0.0


def test_time_left_uses_this_runs_rate() -> None:
    """4 views in 2 s of this run, 10 of 16 done: 6 more take 3 s."""
    assert Progress("object", 10, 16, 1, elapsed_s=2.0, done_this_run=4).left_s == pytest.approx(
        3.0
    )
    assert Progress("object", 6, 16, 0, elapsed_s=0.5, done_this_run=0).left_s is None


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        (("x", "2", "8"), "Sections is 'x': enter a whole number"),
        (("2", "two", "8"), "Pitch mm is 'two': enter a number of mm"),
        # Issue #24: an empty Sections field blamed the valid Views field too.
        (("", "2", "8"), "Sections is empty: enter a whole number"),
        (("4", "2", "eight"), "Views is 'eight': enter a whole number"),
        (("2", "nan", "8"), "pitch nan mm must be above 0"),
        (("501", "2", "8"), "sections 501 must be between 1 and 500"),
    ],
)
def test_parse_plan_names_the_bad_field(fields: tuple[str, str, str], message: str) -> None:
    """Every bad plan field is refused with its value in the message."""
    with pytest.raises(UserError, match=message.replace("(", r"\(").replace(")", r"\)")):
        parse_plan(*fields)


def test_parse_plan_builds_the_regular_plan() -> None:
    """2 sections x 8 views, 2 mm apart."""
    plan = parse_plan("2", "2.5", "8")
    assert plan.sections == [0, 1] and len(plan.views) == 16
    assert plan.views[8].z_mm == 2.5 and plan.views[1].angle_deg == 45.0


def test_subject_ids_are_safe_codes() -> None:
    """Letters, digits, - and _ only."""
    assert check_subject(" P001-left_leg ") == "P001-left_leg"
    for bad in ("", "a/b", "x" * 65, "Jane Doe"):
        with pytest.raises(UserError):
            check_subject(bad)


def test_harmonics_field_takes_a_count_a_rule_or_nothing():
    from lamina_host.ui.tui.adapter import UserError
    from lamina_host.ui.tui.screens.results import parse_harmonics

    assert parse_harmonics("") == (None, None)
    assert parse_harmonics(" auto ") == (None, None)
    assert parse_harmonics("7") == (7, None)
    assert parse_harmonics("Thesis") == (None, "thesis")
    with pytest.raises(UserError, match="noise, power, thesis, nyquist"):
        parse_harmonics("lots")


def test_processing_again_with_a_harmonic_rule(scanned_library, tmp_path):
    import shutil

    from lamina_host.ui.tui.adapter import DeviceTarget, ScanJob, process

    # A copy: the shared library feeds the snapshots, and processing stores a new result.
    library = tmp_path / "library.sqlite"
    shutil.copy(scanned_library, library)
    job = ScanJob(DeviceTarget("sim"), library)
    try:
        scan_id = job.store.scans()[0].id
        job.acquisition.open_scan(scan_id)
        fixed = process(job, harmonics=9)
        thesis = process(job, harmonic_rule="thesis")
    finally:
        job.close()
    assert {s.harmonics for s in fixed.reconstruction.sections} == {9}
    # The thesis HN formula gives perimeter / (4 pi) = 4.76 -> 5 for the 19.05 mm cylinder.
    assert {s.harmonics for s in thesis.reconstruction.sections} == {5}
