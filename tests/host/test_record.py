"""The compact follow-up record: a 40-section limb scan within 10 KB, rebuilt within 0.1 %.

The outlines are a limb-like shape (tapered, oval, with a three-lobed ripple, 60 -> 45 mm
radius over 160 mm) sampled by eight overlapping views with the harsh preset's point
noise, and fitted by the pipeline's own outline fit (harmonics by the noise rule), so the
record holds what a real limb scan gives it.
"""

from __future__ import annotations

import json
import struct
import zlib
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest

from lamina_host.clinical.measures import LimbSection, measure_limb, sections_from_reconstruction
from lamina_host.reconstruct.axis import AxisCalibration
from lamina_host.reconstruct.calibration import GridCalibration, Homography
from lamina_host.reconstruct.efd import EllipticFourier, align
from lamina_host.reconstruct.measure import perimeter, polygon_area
from lamina_host.reconstruct.mesh import signed_volume
from lamina_host.reconstruct.outliers import OutlierRules
from lamina_host.reconstruct.pipeline import (
    ProcessOptions,
    Reconstruction,
    Section,
    build_mesh,
    fit_groups,
    outline_groups,
)
from lamina_host.store.record import RecordError, load_record, record_bytes

SECTIONS = 40
PITCH_MM = 4.0
NOISE_MM = 0.05


def limb_radius_mm(phi: np.ndarray, z_mm: float) -> np.ndarray:
    """True radius of the limb-like shape at polar angle ``phi`` and height ``z_mm``."""
    taper = 60.0 - 15.0 * z_mm / (SECTIONS * PITCH_MM)
    return taper * (1.0 + 0.08 * np.cos(2.0 * phi) + 0.02 * np.sin(3.0 * phi + z_mm / 50.0))


def views(z_mm: float, rng: np.random.Generator) -> list[np.ndarray]:
    """Eight overlapping 100-degree arcs of the outline at ``z_mm`` with point noise."""
    arcs = []
    for k in range(8):
        phi = np.deg2rad(45.0 * k + np.linspace(-50.0, 50.0, 400))
        r = limb_radius_mm(phi, z_mm) + rng.normal(0.0, NOISE_MM, len(phi))
        arcs.append(np.column_stack([r * np.cos(phi), r * np.sin(phi)]))
    return arcs


def outlines(parts: list[np.ndarray], options: ProcessOptions) -> list[list[np.ndarray]]:
    """Return a section's outlines as the pipeline groups them (outliers rejected)."""
    rules = OutlierRules(working_radius_mm=options.working_radius_mm)
    return outline_groups(parts, options, rules)[0]


@pytest.fixture(scope="module")
def limb() -> Reconstruction:
    """A reconstruction of the limb-like shape: real fits, a contour mesh, stand-in calibration."""
    rng = np.random.default_rng(7)
    options = ProcessOptions()
    sections = [
        s
        for k in range(SECTIONS)
        for s in fit_groups(k, k * PITCH_MM, outlines(views(k * PITCH_MM, rng), options), options)
    ]
    vertices, faces, _ = build_mesh(sections, options)
    grid = GridCalibration(
        Homography(np.diag([0.1, 0.1, 1.0])), np.zeros((0, 2)), np.zeros((0, 2)),
        np.zeros(0), 0.01, 0.02, 54, (),
    )  # fmt: skip
    axis = AxisCalibration(
        (1.5, -2.0), 1.0021, 99.8, 100.0, np.zeros((8, 2)), np.full(8, 50.0), (), "joint",
        angle_scale=0.99556, angle_scale_sd=1.7e-5, angle_wave_deg=(0.15, 0.126),
    )  # fmt: skip
    return Reconstruction(grid, axis, sections, vertices, faces, {}, options=options)


def test_a_40_section_limb_record_fits_10_kb_and_rebuilds_within_0_1_percent(limb) -> None:
    data = record_bytes(limb, 12, "P001-left", "2026-11-29T10:00:00+00:00")
    harmonics = [s.harmonics for s in limb.sections]
    print(f"record {len(data)} bytes, harmonics {min(harmonics)}-{max(harmonics)}")
    assert len(limb.sections) == SECTIONS and len(data) <= 10 * 1024
    record = load_record(data)
    assert (record.scan_id, record.subject) == (12, "P001-left")
    assert record.axis["axis_xy_mm"] == [1.5, -2.0] and record.axis["correction_factor"] == 1.0021
    assert record.calibration["matrix"] == limb.grid.homography.matrix.tolist()
    rebuilt = record.sections()
    assert [(s.index, s.part, s.z_mm) for s in rebuilt] == [
        (s.index, s.part, s.z_mm) for s in limb.sections
    ]
    for original, again in zip(limb.sections, rebuilt, strict=True):
        assert perimeter(again.contour) == pytest.approx(perimeter(original.contour), rel=1e-3)
        assert polygon_area(again.contour) == pytest.approx(
            polygon_area(original.contour), rel=1e-3
        )
        # The same curve point for point (once started at the same place), within 20 um.
        gap = np.linalg.norm(again.efd.evaluate(720) - align(original.efd).evaluate(720), axis=1)
        assert gap.max() < 0.02
    volume = signed_volume(limb.vertices, limb.faces)
    assert record.mesh_volume_mm3() == pytest.approx(volume, rel=1e-3)
    # And against the truth: the rebuilt mesh holds the limb's volume (4 mm pitch, 0.5 %).
    assert volume > 1e6


def test_the_record_keeps_the_gear_the_calibration_fitted(limb) -> None:
    """The gear's whole fit travels with the contours (provenance): its scale over the
    count, that scale's standard error and its once-per-turn error."""
    axis = load_record(record_bytes(limb, 1, "P1", "2026-11-29T10:00:00+00:00")).axis
    assert axis["angle_scale"] == 0.99556 and axis["angle_scale_sd"] == 1.7e-5
    assert axis["angle_wave_deg"] == [0.15, 0.126]


def test_rebuilt_contours_lie_on_the_true_outline(limb) -> None:
    """Quantisation adds no visible error: the rebuilt contours stay within the noise."""
    record = load_record(record_bytes(limb, 1, "P1", "2026-11-29T10:00:00+00:00"))
    for s in record.sections():
        phi = np.arctan2(s.contour[:, 1], s.contour[:, 0])
        error = np.hypot(*s.contour.T) - limb_radius_mm(phi, s.z_mm)
        assert np.sqrt(np.mean(error**2)) < NOISE_MM


def test_the_record_keeps_the_limb_side_and_reads_older_records_as_none(limb) -> None:
    """Issue #24: no limb side in the .lrec record. It is kept now; a record written before
    (no side in its header) reads as side none."""
    data = record_bytes(limb, 3, "P1", "2026-11-29T10:00:00+00:00", "right")
    assert load_record(data).side == "right"
    payload = zlib.decompress(data[5:])
    (size,) = struct.unpack_from("<I", payload)
    header = json.loads(payload[4 : 4 + size])
    del header["side"]
    text = json.dumps(header).encode()
    older = data[:5] + zlib.compress(struct.pack("<I", len(text)) + text + payload[4 + size :])
    record = load_record(older)
    assert record.side == "none" and len(record.outlines) == len(limb.sections)


def test_damaged_or_foreign_bytes_are_refused_in_one_line(limb) -> None:
    data = record_bytes(limb, 1, "P1", "2026-11-29T10:00:00+00:00")
    for bad in (b"", b"PK\x03\x04", data[:5] + b"\x02" + data[6:], data[:-40]):
        with pytest.raises(RecordError) as info:
            load_record(bad)
        assert "\n" not in str(info.value)
    with pytest.raises(RecordError, match="newer Lamina"):
        load_record(data[:4] + b"\x09" + data[5:])


SIMULATED_SCAN = Path(__file__).resolve().parent / "data" / "arm40_sections.json"
"""The outlines of a real simulated limb scan, taken from its report.json: ``lamina scan
--device sim --rig limb --object arm:scale=5,z=20 --noise harsh --distortion --sections 40
--pitch 3 --views 8`` (each outline's EFD as the pipeline fitted it, height, status and
segment count; the scan's calibration, axis and processing options)."""


def simulated_scan() -> tuple[Reconstruction, dict]:
    """Return the simulated scan as a reconstruction (outlines and contour mesh) and its report."""
    report = json.loads(SIMULATED_SCAN.read_text())
    options = ProcessOptions.from_dict(report["options"])
    sections = []
    for row in report["sections"]:
        efd = EllipticFourier.from_dict(row["efd"])
        contour = efd.evaluate(options.outline_points)
        sections.append(
            Section(row["section"], row["z_mm"], row["segments"], np.empty((0, 2)), efd,
                    contour, row["part"], status=row["status"])
        )  # fmt: skip
    vertices, faces, _ = build_mesh(sections, options)
    grid = SimpleNamespace(to_dict=lambda: report["calibration"])
    axis = SimpleNamespace(to_dict=lambda: report["axis"])
    result = Reconstruction(grid, axis, sections, vertices, faces, {}, options=options)  # type: ignore[arg-type]
    return result, report


def test_a_real_40_section_simulated_limb_scan_fits_10_kb_and_remeasures_within_0_1_percent():
    """The record of a real simulated 40-section forearm scan: within 10 KB, and the clinical
    measurements (lamina report's) and the mesh volume rebuilt from it within 0.1 %."""
    result, report = simulated_scan()
    assert len(result.sections) == 40
    data = record_bytes(result, 40, "P040", "2026-11-29T15:30:00+00:00")
    harmonics = [s.harmonics for s in result.sections]
    print(f"simulated scan record {len(data)} bytes, harmonics {min(harmonics)}-{max(harmonics)}")
    assert len(data) <= 10 * 1024
    record = load_record(data)
    assert record.calibration["matrix"] == report["calibration"]["matrix"]
    assert record.axis["axis_xy_mm"] == report["axis"]["axis_xy_mm"]
    original = measure_limb(sections_from_reconstruction(result), 40.0)
    rebuilt = measure_limb(
        [LimbSection(s.z_mm, s.efd, s.status) for s in record.sections() if s.part == 0], 40.0
    )
    assert rebuilt.volume_mm3 == pytest.approx(original.volume_mm3, rel=1e-3)
    assert rebuilt.frustum_volume_mm3 == pytest.approx(original.frustum_volume_mm3, rel=1e-3)
    assert [lv.offset_mm for lv in rebuilt.levels] == [lv.offset_mm for lv in original.levels]
    assert len(original.levels) >= 3
    for again, first in zip(rebuilt.levels, original.levels, strict=True):
        assert again.circumference_mm == pytest.approx(first.circumference_mm, rel=1e-3)
    for again, first in zip(rebuilt.segments, original.segments, strict=True):
        assert again.volume_mm3 == pytest.approx(first.volume_mm3, rel=1e-3)
    volume = signed_volume(result.vertices, result.faces)
    assert record.mesh_volume_mm3() == pytest.approx(volume, rel=1e-3)
    # The measurements are the forearm's: the scan's own stack volume, as the pipeline stored it.
    assert volume == pytest.approx(report["mesh"]["topology"]["volume_mm3"], rel=1e-3)
