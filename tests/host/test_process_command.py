"""A section that cannot be processed fails alone; no acquisition is lost (issue 18, part 1).

Faults are injected where processing runs (an outline's fit, the whole reconstruction)
into real scans of the simulator, so what is checked is the product's answer to a shape
it cannot process: the status ``failed`` with its reason in ``report.json``, the summary
and the Results rows, every other section processed and meshed, the scan kept in the
library and processed again by ``lamina process``.
"""

from __future__ import annotations

import json
import subprocess
from dataclasses import replace
from pathlib import Path

import pytest

import lamina_host.reconstruct.pipeline as pipeline
import lamina_host.workflow.processing as processing
from lamina_host.cli import main, print_summary
from lamina_host.reconstruct.calibration import CalibrationError
from lamina_host.reconstruct.pipeline import ProcessOptions
from lamina_host.reconstruct.status import OutlineStatus
from lamina_host.store.library import Library
from lamina_host.store.outputs import build_report
from lamina_host.ui.tui.screens.results import summary_text
from lamina_host.workflow.batch import reprocess
from lamina_host.workflow.results import Results, section_rows, volume_mm3
from lamina_shared.types import ScanPlan
from tests.helpers.cli import host_command

ELLIPSOID = "ellipsoid:a=10,b=6.5,c=20,z=-1"
"""The shared library's object (tests/host/conftest.py): 4 sections at 2 mm pitch."""


def failing_fit(broken: dict[int, Exception]):
    """Return ``fit_section`` raising ``broken[index]`` for those sections' outlines."""
    original = pipeline.fit_section

    def fit(index: int, *args, **kwargs):
        if index in broken:
            raise broken[index]
        return original(index, *args, **kwargs)

    return fit


def test_an_outline_that_cannot_be_processed_fails_alone(
    scanned_library: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    with Library(scanned_library) as library:
        inputs = library.inputs(1)
    clean = reprocess(inputs, ProcessOptions())
    assert len(clean.sections) == 4 and not clean.failed
    monkeypatch.setattr(
        pipeline,
        "fit_section",
        failing_fit({1: CalibrationError("injected refusal"), 2: ZeroDivisionError("injected")}),
    )
    result = reprocess(inputs, ProcessOptions())

    assert [s.index for s in result.sections] == [0, 3]
    assert [(f.index, f.part, f.status) for f in result.failed] == [
        (1, 0, OutlineStatus.FAILED),
        (2, 0, OutlineStatus.FAILED),
    ]
    assert result.failed[0].reason == "injected refusal"
    assert result.failed[1].reason.startswith("internal error (ZeroDivisionError: injected)")
    assert result.failed[0].points == len(clean.sections[1].raw)  # all its stripe points
    # The other outlines are processed as before and meshed (a closed tube from 0 to 3).
    for kept in result.sections:
        same = next(s for s in clean.sections if s.index == kept.index)
        assert kept.efd.coeffs == pytest.approx(same.efd.coeffs)
    assert (
        len(result.faces) and result.mesh_topology is not None and result.mesh_topology.watertight
    )
    assert min(result.vertices[:, 2]) == pytest.approx(clean.sections[0].z_mm)
    assert max(result.vertices[:, 2]) == pytest.approx(clean.sections[3].z_mm)
    assert any("1.0, 2.0 could not be processed" in w for w in result.warnings)

    typed = build_report(result, {}, inputs.segments, None, {})
    report = json.loads(json.dumps(typed.to_json()))
    assert [(s["section"], s["status"]) for s in report["sections"]] == [
        (0, "measured"), (1, "failed"), (2, "failed"), (3, "measured"),
    ]  # fmt: skip
    assert report["sections"][1]["reason"] == "injected refusal"
    print_summary(typed, {})
    printed = capsys.readouterr().out.splitlines()
    assert any(line.split()[:1] == ["1"] and "failed" in line and "injected refusal" in line
               for line in printed)  # fmt: skip

    rows = section_rows(result)
    assert [(r.index, r.status) for r in rows] == [
        (0, "measured"), (1, "failed"), (2, "failed"), (3, "measured"),
    ]  # fmt: skip
    assert rows[1].reason == "injected refusal"
    assert volume_mm3(rows) > 0
    shown = summary_text(Results(result, rows, replace(typed, volume_mm3=volume_mm3(rows))))
    assert "outline 1.0 (z 2.00) failed: injected refusal" in shown


def test_a_scan_whose_processing_fails_stays_and_lamina_process_processes_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    library = tmp_path / "library.sqlite"

    def broken(*args, **kwargs):
        raise ZeroDivisionError("injected")

    monkeypatch.setattr(processing, "reconstruct", broken)
    status = main(
        ["scan", "--device", "sim", "--object", ELLIPSOID, "--sections", "3", "--pitch", "2",
         "--views", "6", "--subject", "P9", "--expect", "ellipsoid:a=10,b=6.5,c=20,z=-1",
         "--library", str(library), "-o", str(tmp_path / "scan")]
    )  # fmt: skip
    err = capsys.readouterr().err.strip().splitlines()
    assert status == 2
    assert err[-1].startswith("lamina: processing failed: internal error (ZeroDivisionError")
    assert "lamina process 1" in err[-1]
    with Library(library) as lib:
        (summary,) = lib.scans()
        assert (summary.status, summary.has_result, summary.received) == ("acquired", False, 18)
    monkeypatch.undo()

    done = subprocess.run(
        host_command("process", "1", "--library", str(library), "--mesh", "contours",
                     "-o", str(tmp_path / "again")),
        capture_output=True, text=True, timeout=300,
    )  # fmt: skip
    assert done.returncode == 0, done.stderr
    assert "scan 1 processed" in done.stdout
    report = json.loads((tmp_path / "again" / "report.json").read_text())
    assert [s["status"] for s in report["sections"]] == ["measured"] * 3
    # The scan's own expectation came along: accuracy against the true ellipsoid.
    assert report["accuracy"]["mean_own_mm"] < 0.1
    with Library(library) as lib:
        (summary,) = lib.scans()
        assert (summary.status, summary.has_result) == ("processed", True)
        assert lib.result(1)["sections"] == report["sections"]


def test_lamina_process_refuses_what_it_cannot_process(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    library = tmp_path / "library.sqlite"
    assert main(["process", "4", "--library", str(library)]) == 2
    assert capsys.readouterr().err.strip() == (
        f"lamina: there is no scan library at {library}: check the --library path "
        "(lamina scan makes the library the first time it records into it)"
    )
    assert not library.exists()  # nothing made where the user mistyped
    Library(library).close()
    assert main(["process", "4", "--library", str(library)]) == 2
    assert capsys.readouterr().err.strip() == (
        f"lamina: there is no scan 4 in {library}: see lamina scans"
    )


def test_lamina_process_sends_a_scan_being_acquired_to_resume(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    library = tmp_path / "library.sqlite"
    with Library(library) as lib:
        scan_id = lib.create_scan("P-01", {"object": ScanPlan.regular(1, 2.0, 4)})
    assert main(["process", str(scan_id), "--library", str(library)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith(f"lamina: scan {scan_id} is not fully acquired")
    assert f"lamina scan --resume {scan_id}" in err and "\n" not in err
