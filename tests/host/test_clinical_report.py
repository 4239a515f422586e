"""``lamina report``: one page (PDF, PNG) and a CSV from scans in a real SQLite library.

The scans are circular cone frustums (their EFD sections as the pipeline stores them), so
every volume, excess, change and RVC has an exact value to check against. Each problem
issue #24 found in the report has a test here that reproduces it.
"""

from __future__ import annotations

import csv
import io
import math
import re
import sqlite3
import zlib
from contextlib import redirect_stdout
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import pytest
from matplotlib import pyplot as plt

from lamina_host.cli import main
from lamina_host.clinical.measures import (
    Landmark,
    compare,
    frustum_volume_mm3,
    measure_limb,
    rvc_percent,
    sections_from_report,
)
from lamina_host.clinical.report import (
    MeasureRequest,
    ReportData,
    build_report_data,
    csv_text,
    foot,
    headline,
    when_text,
)
from lamina_host.clinical.report_page import compose, render
from lamina_host.reconstruct.efd import efd_fit
from lamina_host.store.library import Library
from lamina_shared.types import ScanPlan

PLANS = {"object": ScanPlan.regular(2, 10.0, 4)}
CONES = {1: (30.0, 45.0), 2: (33.0, 48.0), 3: (33.5, 48.5), 5: (30.2, 45.2), 7: (33.0, 48.0)}
"""Each processed scan's radii (mm) at z = 0 and z = 300 (scan 6 is a 10 mm test cylinder)."""


def cone_report(r0: float, r1: float, length: float, pitch: float) -> dict:
    """A report.json as the pipeline writes it, for a circular cone frustum."""
    sections = []
    t = np.linspace(0.0, 2 * np.pi, 720, endpoint=False)
    for k, z in enumerate(np.arange(0.0, length + 1e-9, pitch)):
        r = r0 + (r1 - r0) * z / length
        efd = efd_fit(np.column_stack([r * np.cos(t), r * np.sin(t)]), 4)
        sections.append({"section": k, "part": 0, "z_mm": float(z), "efd": efd.to_dict()})
    return {
        "device": {"software": "lamina-device 0.1.0", "hardware": "sim"},
        "calibration": {"method": "ml", "rms_mm": 0.0123},
        "axis": {"method": "joint", "correction_factor": 1.0001},
        "options": {"interpolation": "linear"},
        "sections": sections,
    }


def add_scan(
    library: Library, subject: str, report: dict | None, created: str, side: str = "none"
) -> int:
    """Store a scan (processed when ``report`` is given) of ``side`` created at ``created``."""
    scan_id = library.create_scan(subject, PLANS, side=side)
    if report is not None:
        library.save_result(scan_id, report, {})
    library._db.execute("UPDATE scans SET created = ? WHERE id = ?", (created, scan_id))
    return scan_id


def cone_volume_ml(r0: float, r1: float, length: float = 300.0) -> float:
    """The exact volume of a circular cone frustum in mL."""
    return frustum_volume_mm3(2 * np.pi * r0, 2 * np.pi * r1, length) / 1000.0


def make_library(path: Path) -> Path:
    """P-007's arms at two visits (right 1 and 5, left 2 and 3), an unprocessed scan of P-008,
    a 10 mm test cylinder scanned under P-007 (scan 6, marked as a test) and P-009's left arm."""
    with Library(path) as library:
        add_scan(library, "P-007", cone_report(*CONES[1], 300.0, 10.0), "2026-01-10T09:00:00+00:00",
                 "right")  # fmt: skip
        add_scan(library, "P-007", cone_report(*CONES[2], 300.0, 10.0), "2026-01-10T09:30:00+00:00",
                 "left")  # fmt: skip
        add_scan(library, "P-007", cone_report(*CONES[3], 300.0, 10.0), "2026-04-02T10:00:00+00:00",
                 "left")  # fmt: skip
        add_scan(library, "P-008", None, "2026-04-03T10:00:00+00:00")
        add_scan(library, "P-007", cone_report(*CONES[5], 300.0, 10.0), "2026-04-02T10:20:00+00:00",
                 "right")  # fmt: skip
        add_scan(library, "P-007", cone_report(4.0, 4.0, 10.0, 2.0), "2026-04-02T10:40:00+00:00",
                 "left")  # fmt: skip
        library.set_test(6)
        add_scan(library, "P-009", cone_report(*CONES[7], 300.0, 10.0), "2026-04-05T10:00:00+00:00",
                 "left")  # fmt: skip
    return path


@pytest.fixture(scope="module")
def library_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The library of :func:`make_library`, shared by the tests that only read it."""
    return make_library(tmp_path_factory.mktemp("clinic") / "library.sqlite")


@dataclass
class Page:
    """The left arm's report against the right (scan 3 against 5), made once and looked at."""

    data: ReportData
    pdf: bytes
    text: str
    rows: list[dict[str, str]]
    printed: str
    texts: list[tuple[float, str]]
    legend: list[str]
    outline_lines: list[int]
    limb_colours: np.ndarray


@pytest.fixture(scope="module")
def page(library_path: Path, tmp_path_factory: pytest.TempPathFactory) -> Page:
    """``lamina report 3 --compare 5 -o report.pdf --csv table.csv``, and the page's figure."""
    folder = tmp_path_factory.mktemp("page")
    out, table = folder / "report.pdf", folder / "table.csv"
    printed = io.StringIO()
    with redirect_stdout(printed):
        assert report(library_path, "3", "--compare", "5", "-o", str(out), "--csv", str(table)) == 0
    with Library(library_path) as library:
        data = build_report_data(library, 3, MeasureRequest(), 5)
    fig = compose(data)
    try:
        texts = [(t.get_position()[1], t.get_text()) for t in fig.texts]
        (profile,) = [ax for ax in fig.axes if ax.get_label() == "profile"]
        (limb,) = [ax for ax in fig.axes if ax.get_label() == "limb"]
        (surface,) = limb.collections
        page = Page(
            data, out.read_bytes(), pdf_text(out.read_bytes()),
            list(csv.DictReader(table.open())), printed.getvalue(), texts,
            [t.get_text() for t in profile.get_legend().get_texts()],
            [len(ax.lines) for ax in fig.axes if ax.get_label() == "outline"],
            np.asarray(surface.get_facecolor())[:, :3],
        )  # fmt: skip
    finally:
        plt.close(fig)
    return page


def report(library_path: Path, *argv: str) -> int:
    """Run ``lamina report`` on the fixture's library."""
    return main(["report", *argv, "--library", str(library_path)])


def pdf_pages(data: bytes) -> int:
    """Count page objects (``/Type /Page``, not ``/Pages``)."""
    return len(re.findall(rb"/Type\s*/Page(?![a-z])", data))


def pdf_text(data: bytes) -> str:
    """Return the text drawn in a PDF: the strings of each text block joined.

    matplotlib writes text as TJ arrays of literal strings between kerning numbers, in
    zlib-compressed content streams; each BT..ET block is one label (an "ff" or "fi" may
    be drawn as one ligature glyph, so words with them are not searched for).
    """
    texts = []
    for stream in re.findall(rb"stream\r?\n(.*?)\r?\nendstream", data, re.S):
        try:
            content = zlib.decompress(stream)
        except zlib.error:
            continue
        for block in re.findall(rb"BT(.*?)ET", content, re.S):
            pieces = re.findall(rb"\(((?:\\.|[^\\)])*)\)", block)
            texts.append(b"".join(re.sub(rb"\\(.)", rb"\1", p) for p in pieces).decode("latin-1"))
    return "\n".join(texts)


def measured(library_path: Path, scan_id: int, spacing_mm: float = 40.0):
    """Measure a stored scan as lamina report does by default."""
    with Library(library_path) as library:
        return measure_limb(sections_from_report(library.result(scan_id) or {}), spacing_mm)


def test_pdf_report_has_one_page_and_the_table_values(library_path: Path, page: Page) -> None:
    """The PDF: one page, subject code, the girths (cm), volumes, the comparison and flags."""
    assert page.pdf.startswith(b"%PDF") and pdf_pages(page.pdf) == 1
    text = page.text
    assert "Subject P-007" in text
    m, ref = measured(library_path, 3), measured(library_path, 5)
    c = compare(m, ref)
    for level in m.levels:
        assert f"{level.circumference_mm / 10:.2f}" in text
        radius = 33.5 + 15.0 * level.z_mm / 300.0  # the truth
        assert level.circumference_mm == pytest.approx(2 * np.pi * radius, rel=1e-4)
    truth = cone_volume_ml(*CONES[3]) - cone_volume_ml(*CONES[5])
    assert c.difference_ml == pytest.approx(truth, rel=1e-4)
    assert f"{c.difference_ml:+.1f} mL" in text
    assert f"Volume: {m.volume_mm3 / 1000:.1f} mL" in text
    # 3.3 mm more radius: 20.7 mm more girth at the distal end (>= 20 mm), and > 200 mL.
    assert "reaches the 200 mL threshold" in text and "FLAG: whole limb, left over right" in text
    assert "flag: girth differs by 2.0 cm or more at every level compared" in page.printed
    rows = [r for r in page.rows if r["row"] == "level"]
    assert [float(r["from_landmark_cm"]) * 10 for r in rows] == [lv.offset_mm for lv in m.levels]
    for row, level, diff in zip(rows, m.levels, c.levels, strict=True):
        assert float(row["girth_cm"]) * 10 == pytest.approx(level.circumference_mm, abs=1e-3)
        assert float(row["girth_difference_cm"]) * 10 == pytest.approx(diff.difference_mm, abs=1e-3)
        assert row["source"] == "measured"
    for row, seg in zip(rows, m.segments, strict=False):
        assert float(row["segment_volume_ml"]) == pytest.approx(seg.volume_mm3 / 1000, abs=1e-3)


def test_the_page_has_no_blank_band(library_path: Path, page: Page) -> None:
    """Issue #24: "a large blank area mid-page". Between the title and the foot no band of
    the page is empty for more than 5 % of its height, with a comparison and without (the
    PNG is one A4 page of dark print on white)."""
    with Library(library_path) as library:
        alone = build_report_data(library, 1, MeasureRequest(10.0))
    for name, data in (("compared", page.data), ("alone, 31 levels", alone)):
        image = cv2.imdecode(np.frombuffer(render(data, "png"), np.uint8), cv2.IMREAD_GRAYSCALE)
        assert image is not None and image.min() < 50 and np.median(image) > 200
        assert image.shape[0] / image.shape[1] == pytest.approx(11.69 / 8.27, rel=0.01)
        ink = (image < 200).any(axis=1)
        rows = np.flatnonzero(ink)
        blank, longest = 0, 0
        for has_ink in ink[rows[0] : rows[-1]]:
            blank = 0 if has_ink else blank + 1
            longest = max(longest, blank)
        assert longest < 0.05 * len(ink), (name, longest / len(ink))


def test_the_first_lines_say_who_when_what_and_the_technical_lines_are_at_the_foot(
    page: Page,
) -> None:
    """Issue #24: technical lines first ("plane map ml, RMS 0.011 mm; axis joint"), the date
    without its zone and not the compared scan's. Now: subject, side, date and time with
    the zone, the compared scan's side and date, volume, excess, change, RVC, flags; the
    calibration and axis in the foot, the lowest text on the page."""
    lines = [line.text for line in headline(page.data)]
    assert lines[0].startswith("Subject P-007   Left limb   scan 3   2026-04-02 10:00 ")
    assert re.search(r"2026-04-02 10:00 [A-Z+\-0-9]+$", lines[0])  # time with zone
    assert lines[1].startswith("Compared with: right limb, scan 5, 2026-04-02 10:20 ")
    assert lines[2].startswith("Volume: ")
    assert lines[3].startswith("Excess over the right limb: ")
    assert lines[4].startswith("Change since the left limb's first visit (scan 2, 2026-01-10)")
    assert lines[5].startswith("RVC since 2026-01-10: ")
    assert all("calibration" not in line.lower() and "plane map" not in line for line in lines)
    assert any("chessboard residual 0.012 mm" in line for line in foot(page.data))
    calibration_y = min(y for y, text in page.texts if "chessboard residual" in text)
    subject_y = max(y for y, text in page.texts if text.startswith("Subject P-007"))
    assert subject_y > 0.9 and calibration_y < 0.1
    assert calibration_y < min(y for y, text in page.texts if "FLAG" in text or "Volume:" in text)


def test_legends_and_outlines_name_both_limbs_by_side_and_date(page: Page) -> None:
    """Issue #24: legends "scan 5 / scan 4" and outlines of one limb only. Now the profile's
    legend names each limb's side and date, and every outline panel draws both limbs."""
    assert page.legend == [
        f"left, {when_text('2026-04-02T10:00:00+00:00')} (scan 3)",
        f"right, {when_text('2026-04-02T10:20:00+00:00')} (scan 5)",
    ]
    assert page.outline_lines == [2] * len(page.data.measurement.levels)


def test_the_limb_picture_is_coloured_by_the_girth_difference(
    library_path: Path, page: Page
) -> None:
    """The rendered limb: its faces take the colour of the girth difference to the compared
    scan (the left limb is 20.7 mm larger in girth all along: red, not blue), and one skin
    colour without a comparison."""
    compared = page.limb_colours
    assert len(compared) > 500
    hue = compared / compared.max(axis=1, keepdims=True)
    assert (hue[:, 0] > hue[:, 2] + 0.3).all()  # red over blue: this limb is the larger
    with Library(library_path) as library:
        alone = build_report_data(library, 3, MeasureRequest())
    fig = compose(alone)
    try:
        (limb,) = [ax for ax in fig.axes if ax.get_label() == "limb"]
        plain = np.asarray(limb.collections[0].get_facecolor())[:, :3]
    finally:
        plt.close(fig)
    plain = plain / plain.max(axis=1, keepdims=True)
    assert np.allclose(plain, plain[0], atol=1e-6)  # one colour, shaded


def test_two_subject_codes_are_refused_unless_asked(library_path: Path, tmp_path: Path, capsys):
    """Issue #24: "change from scan 4 (left): +0.0 mL" comparing P-0077 with P-0042, naming
    neither. Now refused in one line naming both codes; asked for, both are printed."""
    out = tmp_path / "r.csv"
    argv = ["3", "--compare", "7", "--compare-as", "visits", "-o", str(out)]
    assert report(library_path, *argv) == 2
    err = capsys.readouterr().err
    assert "two subjects (P-007 and P-009)" in err and "--compare-other-subject" in err
    assert err.count("\n") == 1 and not out.exists()
    assert report(library_path, *argv, "--compare-other-subject") == 0
    rows = list(csv.DictReader(out.open()))
    assert {(r["subject"], r["compared_subject"]) for r in rows if r["row"] == "level"} == {
        ("P-007", "P-009")
    }
    with Library(library_path) as library:
        data = build_report_data(library, 3, MeasureRequest(), 7, "visits", other_subject=True)
    lines = [line.text for line in headline(data)]
    assert lines[1].startswith("Compared with: subject P-009, left limb, scan 7")
    assert lines[2] == "Two subject codes compared, as asked: P-007 and P-009"


def test_the_headline_excess_is_over_the_common_range_at_any_spacing(
    library_path: Path, tmp_path: Path
) -> None:
    """Issue #24: the headline excess depended on --spacing-mm (+18.9 % at 40 mm, +16.6 %
    at 10 mm). Now it is over the whole range both scans measured, the cones' exact excess."""
    truth = 100 * (cone_volume_ml(*CONES[3]) / cone_volume_ml(*CONES[5]) - 1)
    found = []
    for spacing in ("40", "70", "10"):
        out = tmp_path / f"s{spacing}.csv"
        assert (
            report(library_path, "3", "--compare", "5", "--spacing-mm", spacing, "-o", str(out))
            == 0
        )
        (row,) = [r for r in csv.DictReader(out.open()) if r["row"] == "compared"]
        assert (row["range_from_cm"], row["range_to_cm"]) == ("0.0000", "30.0000")
        found.append(float(row["excess_percent"]))
    assert found == pytest.approx([truth] * 3, abs=2e-3)


def test_the_table_titles_say_what_and_in_which_unit(
    library_path: Path, tmp_path: Path, page: Page
) -> None:
    """Issue #24: columns "other mm" and "difference mm", no % per level, volumes in mm3.
    Now titled by side and unit (cm by default, mm if asked), with % per level, in mL."""
    text = page.text
    for title in ("From distal end", "(cm)", "Left girth", "Right girth", "(%)", "Segment RVC",
                  "level (mL)"):  # fmt: skip
        assert title in text, title
    assert "other mm" not in text and "mm3" not in text and "mm^3" not in text
    for unit in ("cm", "mm"):
        table = tmp_path / f"t-{unit}.csv"
        argv = ["3", "--compare", "5", "--length-unit", unit, "-o", str(table)]
        assert report(library_path, *argv) == 0
        header = table.read_text().splitlines()[0].split(",")
        assert f"girth_{unit}" in header and "girth_difference_percent" in header
        (row,) = [r for r in csv.DictReader(table.open()) if r["row"] == "level"][:1]
        girth = float(row[f"girth_{unit}"]) * (10.0 if unit == "cm" else 1.0)
        assert girth == pytest.approx(2 * np.pi * CONES[3][0], rel=1e-4)


def test_csv_has_scan_subject_side_date_levels_totals_and_the_trend(page: Page) -> None:
    """Issue #24: the CSV without scan, subject, side, date or totals. Now every row names
    them; the totals, the comparison, the RVC and each visit of the trend have their rows."""
    data, rows = page.data, page.rows
    assert rows == list(csv.DictReader(csv_text(data).splitlines()))
    kinds = [r["row"] for r in rows]
    assert (
        kinds
        == ["level"] * len(data.measurement.levels) + ["total", "compared", "rvc"] + ["visit"] * 4
    )
    for r in rows[: kinds.index("visit")]:
        assert (r["scan"], r["subject"], r["side"], r["date"]) == (
            "3", "P-007", "left", "2026-04-02T10:00:00+00:00"
        )  # fmt: skip
    total = rows[kinds.index("total")]
    assert float(total["volume_ml"]) == pytest.approx(cone_volume_ml(*CONES[3]), rel=5e-5)
    visits = [r for r in rows if r["row"] == "visit"]
    assert [(r["scan"], r["side"]) for r in visits] == [
        ("1", "right"), ("2", "left"), ("3", "left"), ("5", "right")
    ]  # fmt: skip


def test_rvc_excess_and_change_in_the_csv_match_the_cones(library_path: Path) -> None:
    """Issue #23 part 3: the RVC of the left arm since January, (A2 U1) / (U2 A1) - 1, its
    excess and change, whole and per segment, as the exact cone volumes give them."""
    with Library(library_path) as library:
        data = build_report_data(library, 3, MeasureRequest())
    rows = list(csv.DictReader(csv_text(data).splitlines()))
    (rvc,) = [r for r in rows if r["row"] == "rvc"]
    a1, u1, a2, u2 = (cone_volume_ml(*CONES[k]) for k in (2, 1, 3, 5))
    assert float(rvc["rvc_percent"]) == pytest.approx(rvc_percent(a1, u1, a2, u2), abs=1e-3)
    assert float(rvc["rvc_percent"]) == pytest.approx(100 * ((a2 * u1) / (u2 * a1) - 1), abs=1e-3)
    assert float(rvc["excess_ml"]) == pytest.approx(a2 - u2, abs=1e-2)
    assert float(rvc["change_percent"]) == pytest.approx(100 * (a2 / a1 - 1), abs=1e-3)
    assert rvc["compared_scan"] == "5" and "since scans 2 (this side) and 1" in rvc["note"]

    def segment(r0: float, r1: float, lo: float) -> float:
        ra, rb = (r0 + (r1 - r0) * z / 300.0 for z in (lo, lo + 40.0))
        return frustum_volume_mm3(2 * np.pi * ra, 2 * np.pi * rb, 40.0)

    levels = [r for r in rows if r["row"] == "level" and r["segment_rvc_percent"]]
    assert len(levels) == 7
    for r in levels:
        lo = float(r["from_landmark_cm"]) * 10
        v = [segment(*CONES[k], lo) for k in (2, 1, 3, 5)]
        assert float(r["segment_rvc_percent"]) == pytest.approx(rvc_percent(*v), abs=1e-3)
    (visit,) = [r for r in rows if r["row"] == "visit" and r["scan"] == "3"]
    assert float(visit["rvc_percent"]) == pytest.approx(float(rvc["rvc_percent"]), abs=1e-6)


def test_a_test_scan_is_kept_but_out_of_the_trend_and_comparisons(tmp_path: Path, capsys) -> None:
    """Issue #24: "a 0.6 mL test cylinder under the same code plotted among the visits".
    Marked as a test (lamina scans --set-test), it stays in the library but out of the
    trend, and a comparison with it is refused; unmarked, it is a visit again (and, being
    10 mm long, cuts the trend's range, which the trend says)."""
    library_path = make_library(tmp_path / "library.sqlite")  # this test changes it
    with Library(library_path) as library:
        data = build_report_data(library, 3, MeasureRequest())
        assert [v.scan_id for v in data.visits] == [1, 2, 3, 5]
        assert data.trend.span_mm == (0.0, 300.0) and not data.trend.notes
        assert library.scan(6).test and library.result(6) is not None
    fig = compose(data)
    try:
        (volume,) = [ax for ax in fig.axes if ax.get_label() == "volume"]
        plotted = sorted(round(float(y), 3) for line in volume.lines for y in line.get_ydata())
    finally:
        plt.close(fig)
    assert min(plotted) > 100  # no 0.5 mL cylinder among the arms
    assert report(library_path, "3", "--compare", "6", "--compare-as", "visits",
                  "-o", str(tmp_path / "r.pdf")) == 2  # fmt: skip
    assert "scan 6 is marked as a test scan" in capsys.readouterr().err
    assert report(library_path, "6", "--compare", "3", "--compare-as", "visits",
                  "-o", str(tmp_path / "r.pdf")) == 2  # fmt: skip
    assert "scan 6 is marked as a test scan" in capsys.readouterr().err
    assert main(["scans", "--library", str(library_path), "--unset-test", "6"]) == 0
    assert re.search(r"\n\s+6  P-007 .* yes\s*\n", capsys.readouterr().out)
    with Library(library_path) as library:
        again = build_report_data(library, 3, MeasureRequest())
    assert [v.scan_id for v in again.visits] == [1, 2, 3, 5, 6]
    assert "scan 6 covers only 0..10 mm" in again.trend.notes[0]
    assert "mark it as a test scan" in again.trend.notes[0]


def test_history_lists_the_subjects_visits_in_time_order(library_path: Path) -> None:
    """Visits of P-007 in time order; each side's change is against its own first scan."""
    with Library(library_path) as library:
        data = build_report_data(library, 3, MeasureRequest(landmark=Landmark("bottom")))
    visits = {v.scan_id: v for v in data.visits}
    assert list(visits) == [1, 2, 3, 5]
    assert visits[2].change_ml == 0.0 and visits[1].change_ml == 0.0
    assert visits[3].change_ml == pytest.approx(
        cone_volume_ml(*CONES[3]) - cone_volume_ml(*CONES[2]), rel=1e-4
    )
    assert visits[3].volume_ml == pytest.approx(data.measurement.volume_mm3 / 1000)


def test_csv_by_suffix_matches_the_measurement(library_path: Path, tmp_path: Path) -> None:
    """``-o table.csv`` writes only the table; spacing and landmark are the user's."""
    out = tmp_path / "table.csv"
    assert report(library_path, "1", "-o", str(out), "--spacing-mm", "80", "--landmark", "100") == 0
    with Library(library_path) as library:
        data = build_report_data(
            library, 1, MeasureRequest(80.0, Landmark("height", 100.0), length_unit="cm")
        )
    assert out.read_text() == csv_text(data)
    assert [lv.offset_mm for lv in data.measurement.levels] == [-80.0, 0.0, 80.0, 160.0]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["report", "9"], "no scan 9"),
        (["report", "4"], "scan 4 has no result yet"),
        (["report", "1", "--landmark", "400"], "outside the measured range"),
        (["report", "1", "--landmark", "elbow"], "landmark 'elbow'"),
        (["report", "1", "--spacing-mm", "0"], "--spacing-mm"),
        (["report", "1", "--compare", "1"], "not with itself"),
        (["report", "1", "--compare", "4"], "belong to two subjects (P-007 and P-008)"),
        (["report", "1", "--flag-change-percent", "nan"], "thresholds"),
        (["report", "1", "--flag-rvc-percent", "-1"], "thresholds"),
        (["report", "1", "--compare-as", "visit"], "did you mean visits?"),
        (["report", "1", "--length-unit", "inch"], "choose from cm, mm"),
    ],
)
def test_bad_input_is_one_line_and_a_non_zero_exit(
    library_path: Path, tmp_path: Path, capsys, argv: list[str], message: str
) -> None:
    """Unknown scan, unprocessed scan, landmark outside coverage...: one line, exit 2."""
    out = tmp_path / "r.pdf"
    assert exit_status([*argv, "--library", str(library_path), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and err.startswith("lamina")
    assert not out.exists()


def exit_status(argv: list[str]) -> int:
    """Run the command line; return its exit status (argparse's refusals exit)."""
    try:
        return main(argv)
    except SystemExit as exc:
        return int(exc.code or 0)


def test_existing_output_and_unknown_suffix_are_refused(library_path: Path, tmp_path: Path):
    """A report never overwrites a file; only .pdf, .png and .csv are written."""
    out = tmp_path / "r.pdf"
    out.write_bytes(b"kept")
    assert report(library_path, "1", "-o", str(out)) == 2
    assert out.read_bytes() == b"kept"
    assert report(library_path, "1", "-o", str(tmp_path / "r.doc")) == 2


def test_report_from_an_older_library_asks_for_reprocessing(tmp_path: Path, capsys) -> None:
    """A report.json without EFD coefficients: one line asking to process the scan again."""
    path = tmp_path / "old.sqlite"
    with Library(path) as library:
        add_scan(library, "P-001", {"sections": [{"z_mm": 0.0, "part": 0}]}, "2025-01-01")
    assert main(["report", "1", "--library", str(path), "-o", str(tmp_path / "r.pdf")]) == 2
    assert "process it again" in capsys.readouterr().err
    with sqlite3.connect(path) as db:
        assert db.execute("SELECT COUNT(*) FROM scans").fetchone()[0] == 1


def test_sides_steer_the_comparison_and_the_history(library_path: Path, tmp_path: Path, capsys):
    """Scans 1 and 5 right, 2 and 3 left: limbs compare across sides, visits within one side;
    each visit's excess is over the other limb scanned at the same visit."""
    with Library(library_path) as library:
        lines = [line.text for line in headline(build_report_data(library, 2, MeasureRequest(), 1))]
    assert "Left limb" in lines[0] and lines[1].startswith("Compared with: right limb, scan 1")
    assert report(library_path, "3", "--compare", "2", "-o", str(tmp_path / "same.pdf")) == 2
    assert "both left limbs" in capsys.readouterr().err
    visit_csv = tmp_path / "visit.csv"
    assert (
        report(library_path, "3", "--compare", "2", "--compare-as", "visits", "-o", str(visit_csv))
        == 0
    )
    (compared,) = [r for r in csv.DictReader(visit_csv.open()) if r["row"] == "compared"]
    assert float(compared["change_ml"]) == pytest.approx(
        cone_volume_ml(*CONES[3]) - cone_volume_ml(*CONES[2]), rel=1e-4
    )
    with Library(library_path) as library:
        lines = [
            line.text
            for line in headline(build_report_data(library, 3, MeasureRequest(), 2, "visits"))
        ]
    assert lines[3].startswith("Change from scan 2 (2026-01-10, an earlier visit)")
    with Library(library_path) as library:
        data = build_report_data(library, 3, MeasureRequest(landmark=Landmark("bottom")))
    visits = {v.scan_id: v for v in data.visits}
    assert visits[2].change_ml == 0.0  # the first left scan is the left baseline
    assert (visits[3].excess_over, visits[1].excess_over, visits[5].excess_over) == (5, 2, 3)
    assert visits[3].excess_ml == pytest.approx(
        cone_volume_ml(*CONES[3]) - cone_volume_ml(*CONES[5]), rel=1e-4
    )
    assert math.isclose(visits[1].rvc_percent, 0.0, abs_tol=1e-9)  # the baseline visit
