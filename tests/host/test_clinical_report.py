"""``lamina report``: one page (PDF, PNG) and a CSV from scans in a real SQLite library."""

from __future__ import annotations

import csv
import re
import sqlite3
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest

from lamina_host.cli import main
from lamina_host.clinical.measures import Landmark, compare, measure_limb, sections_from_report
from lamina_host.clinical.report import MeasureRequest, build_report_data, csv_text
from lamina_host.reconstruct.efd import efd_fit
from lamina_host.store.library import Library
from lamina_shared.types import ScanPlan

PLANS = {"object": ScanPlan.regular(2, 10.0, 4)}


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


def add_scan(library: Library, subject: str, report: dict | None, created: str) -> int:
    """Store a scan (processed when ``report`` is given) created at ``created``."""
    scan_id = library.create_scan(subject, PLANS)
    if report is not None:
        library.save_result(scan_id, report, {})
    library._db.execute("UPDATE scans SET created = ? WHERE id = ?", (created, scan_id))
    library._db.commit()
    return scan_id


@pytest.fixture()
def library_path(tmp_path: Path) -> Path:
    """A library with a right arm, a swollen left arm, a later visit and an unprocessed scan."""
    path = tmp_path / "library.sqlite"
    with Library(path) as library:
        add_scan(library, "P-007", cone_report(30.0, 45.0, 300.0, 10.0), "2026-01-10T09:00:00")
        add_scan(library, "P-007", cone_report(33.0, 48.0, 300.0, 10.0), "2026-01-10T09:30:00")
        add_scan(library, "P-007", cone_report(33.5, 48.5, 300.0, 10.0), "2026-04-02T10:00:00")
        add_scan(library, "P-008", None, "2026-04-03T10:00:00")
    return path


def pdf_pages(data: bytes) -> int:
    """Count page objects (``/Type /Page``, not ``/Pages``)."""
    return len(re.findall(rb"/Type\s*/Page(?![a-z])", data))


def pdf_text(data: bytes) -> str:
    """Return the text drawn in a PDF: the strings of each text block joined.

    matplotlib writes text as TJ arrays of literal strings between kerning numbers, in
    zlib-compressed content streams; each BT..ET block is one label.
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


def test_pdf_report_has_one_page_and_the_table_values(library_path: Path, tmp_path: Path, capsys):
    """The PDF: one page, subject code, the circumferences, volumes and the comparison."""
    out, table = tmp_path / "report.pdf", tmp_path / "table.csv"
    argv = ["report", "2", "--compare", "1", "--library", str(library_path), "-o", str(out)]
    assert main([*argv, "--csv", str(table)]) == 0
    data = out.read_bytes()
    assert data.startswith(b"%PDF") and pdf_pages(data) == 1
    text = pdf_text(data)
    assert "P-007" in text
    with Library(library_path) as library:
        m = measure_limb(sections_from_report(library.result(2) or {}))
        ref = measure_limb(sections_from_report(library.result(1) or {}))
    c = compare(m, ref)
    for level in m.levels:
        assert f"{level.circumference_mm:.2f}" in text
        # The truth: a cone of radius 33 -> 48 mm over 300 mm.
        radius = 33.0 + 15.0 * level.z_mm / 300.0
        assert level.circumference_mm == pytest.approx(2 * np.pi * radius, rel=1e-4)
    assert f"{c.difference_ml:+.1f} mL" in text
    assert f"{m.volume_mm3 / 1000:.1f} mL" in text
    # 3 mm more radius: 18.8 mm more circumference (< 20 mm); the volume flags are crossed.
    # ("difference" may be drawn with an "ff" ligature glyph, so it is not searched for.)
    assert "exceeds 200 mL" in text and "FLAG: volume" in text
    assert "circumference at" not in text
    assert "flag: volume difference" in capsys.readouterr().out
    rows = list(csv.DictReader(table.open()))
    assert [float(r["offset_mm"]) for r in rows] == [lv.offset_mm for lv in m.levels]
    for row, level, diff in zip(rows, m.levels, c.levels, strict=True):
        assert float(row["circumference_mm"]) == pytest.approx(level.circumference_mm, abs=0.005)
        assert float(row["difference_mm"]) == pytest.approx(diff.difference_mm, abs=0.005)
        assert row["source"] == "measured"
    for row, seg in zip(rows, m.segments, strict=False):
        assert float(row["segment_volume_ml"]) == pytest.approx(seg.volume_mm3 / 1000, abs=0.005)


def test_png_report_is_one_readable_page(library_path: Path, tmp_path: Path) -> None:
    """The PNG opens with OpenCV at A4 proportions."""
    out = tmp_path / "report.png"
    assert main(["report", "3", "--library", str(library_path), "-o", str(out)]) == 0
    image = cv2.imread(str(out))
    assert image is not None
    height, width = image.shape[:2]
    assert height / width == pytest.approx(11.69 / 8.27, rel=0.01)
    assert image.min() < 50 and np.median(image) > 200  # dark print on a white page


def test_history_lists_the_subjects_visits_in_time_order(library_path: Path) -> None:
    """Visits of P-007 in time order; the change is against the first (scan 1)."""
    with Library(library_path) as library:
        data = build_report_data(library, 3, MeasureRequest(landmark=Landmark("bottom")))
        visits = data.visits
        ref = measure_limb(sections_from_report(library.result(1) or {}))
    assert [v.scan_id for v in visits] == [1, 2, 3]
    assert visits[0].change_ml == 0.0
    assert visits[2].change_ml == pytest.approx(compare(data.measurement, ref).difference_ml)
    assert visits[2].volume_ml == pytest.approx(data.measurement.volume_mm3 / 1000)


def test_csv_by_suffix_matches_the_measurement(library_path: Path, tmp_path: Path) -> None:
    """``-o table.csv`` writes only the table; spacing and landmark are the user's."""
    out = tmp_path / "table.csv"
    argv = ["report", "1", "--library", str(library_path), "-o", str(out)]
    assert main([*argv, "--spacing-mm", "80", "--landmark", "100"]) == 0
    with Library(library_path) as library:
        sections = sections_from_report(library.result(1) or {})
    m = measure_limb(sections, 80.0, Landmark("height", 100.0))
    assert out.read_text() == csv_text(m)
    assert [lv.offset_mm for lv in m.levels] == [-80.0, 0.0, 80.0, 160.0]


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["report", "9"], "no scan 9"),
        (["report", "4"], "has not been processed"),
        (["report", "1", "--landmark", "400"], "outside the measured range"),
        (["report", "1", "--landmark", "elbow"], "landmark 'elbow'"),
        (["report", "1", "--spacing-mm", "0"], "--spacing-mm"),
        (["report", "1", "--compare", "1"], "not with itself"),
        (["report", "1", "--flag-change-percent", "nan"], "thresholds"),
    ],
)
def test_bad_input_is_one_line_and_a_non_zero_exit(
    library_path: Path, tmp_path: Path, capsys, argv: list[str], message: str
) -> None:
    """Unknown scan, unprocessed scan, landmark outside coverage...: one line, exit 2."""
    out = tmp_path / "r.pdf"
    assert main([*argv, "--library", str(library_path), "-o", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1 and err.startswith("lamina: ")
    assert not out.exists()


def test_existing_output_and_unknown_suffix_are_refused(library_path: Path, tmp_path: Path):
    """A report never overwrites a file; only .pdf, .png and .csv are written."""
    out = tmp_path / "r.pdf"
    out.write_bytes(b"kept")
    assert main(["report", "1", "--library", str(library_path), "-o", str(out)]) == 2
    assert out.read_bytes() == b"kept"
    assert main(["report", "1", "--library", str(library_path), "-o", str(tmp_path / "r.doc")]) == 2


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
    """Scan 1 right, 2 and 3 left: limbs compare across sides, visits within one side."""
    with Library(library_path) as library:
        library.set_side(1, "right")
        library.set_side(2, "left")
        library.set_side(3, "left")
    out = tmp_path / "report.pdf"
    argv = ["report", "2", "--compare", "1", "--library", str(library_path), "-o", str(out)]
    assert main(argv) == 0
    text = pdf_text(out.read_bytes())
    assert "side left" in text and "excess over scan 1 (right)" in text
    same = ["report", "3", "--compare", "2", "--library", str(library_path)]
    assert main([*same, "-o", str(tmp_path / "same.pdf")]) == 2
    assert "both left limbs" in capsys.readouterr().err
    assert main([*same, "--compare-as", "visits", "-o", str(tmp_path / "visit.pdf")]) == 0
    with Library(library_path) as library:
        data = build_report_data(library, 3, MeasureRequest(landmark=Landmark("bottom")))
        left_1 = measure_limb(sections_from_report(library.result(2) or {}))
        right = measure_limb(sections_from_report(library.result(1) or {}))
    visits = {v.scan_id: v for v in data.visits}
    assert visits[2].change_ml == 0.0  # the first left scan is the left baseline
    assert visits[3].change_ml == pytest.approx(compare(data.measurement, left_1).difference_ml)
    # Scan 3 (April) is compared with the only right scan (January); scan 1 with scan 2.
    assert visits[3].excess_over == 1 and visits[1].excess_over == 2
    assert visits[3].excess_ml == pytest.approx(compare(data.measurement, right).difference_ml)
