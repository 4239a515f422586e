"""The one-page clinical report (PDF or PNG) and the measurement table as CSV (issue #13).

The page names the subject by code only, never by name; it gives the scan date, the device
and its calibration state, the circumference table with segment volumes, the volumes, the
comparison with another scan and its flags, and three plots: the circumference profile
along the axis (both limbs), the outlines at the levels, and the volume over the visits.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from lamina_host.clinical.measures import (
    AXES,
    COMPARISONS,
    DEFAULT_SPACING_MM,
    ClinicalError,
    Comparison,
    Landmark,
    LimbMeasurement,
    Thresholds,
    Visit,
    compare,
    history,
    measure_limb,
    sections_from_report,
)
from lamina_host.reconstruct.status import OutlineStatus
from lamina_host.store.files import OutputError, write_new_file
from lamina_host.store.library import Library
from lamina_shared.errors import printable

REPORT_SUFFIXES = (".pdf", ".png")
"""What ``lamina report -o`` writes by suffix (``.csv`` writes the table only)."""

PAGE_IN = (8.27, 11.69)
"""A4 portrait in inches."""

MIN_PROFILE_RANGE_MM = 20.0
"""The profile plot spans at least this much circumference (the 2 cm clinical threshold)."""

CSV_FIELDS = (
    "offset_mm", "z_mm", "circumference_mm", "area_mm2", "segment_volume_ml",
    "segment_frustum_ml", "source", "note", "reference_circumference_mm", "difference_mm",
    "flagged", "axis", "axis_tilt_deg",
)  # fmt: skip


@dataclass(frozen=True, eq=False)
class ReportData:
    """Everything the page shows about one scan (and the one it is compared with)."""

    scan_id: int
    subject: str
    created: str
    device: dict[str, Any]
    calibration: dict[str, Any]
    measurement: LimbMeasurement
    reference_id: int | None = None
    reference: LimbMeasurement | None = None
    comparison: Comparison | None = None
    visits: list[Visit] = field(default_factory=list)
    side: str = "none"
    reference_side: str = "none"


def table_rows(m: LimbMeasurement, comparison: Comparison | None = None) -> list[dict[str, Any]]:
    """Return the measurement table with the comparison's columns where it has the level."""
    by_offset = {round(d.offset_mm, 6): d for d in comparison.levels} if comparison else {}
    rows = []
    for row in m.table():
        d = by_offset.get(round(row["offset_mm"], 6))
        rows.append(
            {
                **row,
                "reference_circumference_mm": round(d.reference_mm, 2) if d else None,
                "difference_mm": round(d.difference_mm, 2) if d else None,
                "flagged": d.flagged if d else None,
            }
        )
    return rows


def csv_text(m: LimbMeasurement, comparison: Comparison | None = None) -> str:
    """Return the measurement table as CSV (one row per level, blank where not compared)."""
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=CSV_FIELDS, lineterminator="\n")
    writer.writeheader()
    for row in table_rows(m, comparison):
        writer.writerow({k: "" if v is None else v for k, v in row.items()})
    return out.getvalue()


def _calibration_line(data: ReportData) -> str:
    grid, axis = data.calibration.get("grid", {}), data.calibration.get("axis", {})
    parts = []
    if grid:
        parts.append(
            f"plane map {grid.get('method', '?')}, RMS {grid.get('rms_mm', float('nan')):.3f} mm"
        )
    if axis:
        parts.append(
            f"axis {axis.get('method', '?')}, correction factor "
            f"{axis.get('correction_factor', float('nan')):.4f}"
        )
    return "calibration: " + ("; ".join(parts) if parts else "not recorded")


def _header_lines(data: ReportData) -> list[str]:
    m = data.measurement
    device = data.device
    dev = " ".join(str(device.get(k, "")) for k in ("software", "hardware")).strip() or "unknown"
    lines = [
        f"subject {printable(data.subject)}    side {data.side}    scan {data.scan_id}    "
        f"date {printable(data.created)[:19]}",
        f"device: {printable(dev)}",
        _calibration_line(data),
        f"axis: {m.axis.method}"
        + (f" (tilt {m.axis.tilt_deg:.1f} deg)" if m.axis.method != "turntable" else "")
        + f"    landmark: {m.landmark.describe()} at z = {m.landmark_z_mm:.1f} mm"
        + f"    spacing {m.spacing_mm:g} mm",
        f"measured range z = {m.coverage_mm[0]:.1f} .. {m.coverage_mm[1]:.1f} mm: "
        f"volume {m.volume_mm3 / 1000:.1f} mL; "
        f"between the levels {m.levels_volume_mm3 / 1000:.1f} mL "
        f"(frustum from circumferences {m.frustum_volume_mm3 / 1000:.1f} mL)",
    ]
    c = data.comparison
    if c is not None:
        what = "excess over" if c.kind == "limbs" else "change from"
        other = f" ({data.reference_side})" if data.reference_side != "none" else ""
        lines.append(
            f"{what} scan {data.reference_id}{other} "
            f"(levels {c.span_mm[0]:g}..{c.span_mm[1]:g} mm): "
            f"{c.difference_ml:+.1f} mL ({c.difference_percent:+.2f} %), "
            f"{c.volume_mm3 / 1000:.1f} vs {c.reference_volume_mm3 / 1000:.1f} mL"
        )
        lines += [f"FLAG: {f}" for f in c.flags if not f.startswith("circumference")]
        crossed = [f"{d.offset_mm:g}" for d in c.levels if d.flagged]
        if crossed:
            lines.append(
                f"FLAG: circumference differs by the threshold or more at {', '.join(crossed)} "
                "mm from the landmark (marked ! in the table)"
            )
        if not c.flags:
            lines.append("no threshold crossed")
    lines += [f"note: {n}" for n in m.notes]
    estimated = [r for r in m.levels if r.source != OutlineStatus.MEASURED]
    if estimated:
        lines.append(
            f"{len(estimated)} level(s) rest on estimated outlines (marked * in the table)"
        )
    return lines


def _draw_table(ax: Any, data: ReportData) -> None:
    ax.axis("off")
    compared = data.comparison is not None
    labels = ["from landmark mm", "z mm", "circumference mm", "segment mL", "frustum mL"]
    if compared:
        labels += ["other mm", "difference mm"]
    cells = []
    for row in table_rows(data.measurement, data.comparison):
        mark = "" if row["source"] == OutlineStatus.MEASURED else " *"
        line = [
            f"{row['offset_mm']:.0f}",
            f"{row['z_mm']:.1f}",
            f"{row['circumference_mm']:.2f}{mark}",
            "" if row["segment_volume_ml"] is None else f"{row['segment_volume_ml']:.2f}",
            "" if row["segment_frustum_ml"] is None else f"{row['segment_frustum_ml']:.2f}",
        ]
        if compared:
            ref, diff = row["reference_circumference_mm"], row["difference_mm"]
            line += ["" if ref is None else f"{ref:.2f}", "" if diff is None else f"{diff:+.2f}"]
            if row["flagged"]:
                line[-1] += " !"
        cells.append(line)
    if not cells:
        ax.text(0.0, 0.5, "no level inside the measured range", fontsize=9)
        return
    table = ax.table(cellText=cells, colLabels=labels, loc="upper center", cellLoc="center")
    table.auto_set_font_size(False)
    table.set_fontsize(7 if len(cells) <= 20 else 5)
    table.scale(1.0, 1.1 if len(cells) <= 20 else 0.8)


def _draw_profile(ax: Any, data: ReportData) -> None:
    m = data.measurement
    _plot_profile(ax, m, "-", "tab:blue", f"scan {data.scan_id}")
    ax.plot(
        [lv.offset_mm for lv in m.levels],
        [lv.circumference_mm for lv in m.levels],
        "o",
        color="tab:blue",
        ms=3,
    )
    if data.reference is not None:
        _plot_profile(ax, data.reference, "--", "tab:orange", f"scan {data.reference_id}")
    low, high = ax.get_ylim()
    if high - low < MIN_PROFILE_RANGE_MM:  # scanner noise must not look like swelling
        mid = 0.5 * (low + high)
        ax.set_ylim(mid - MIN_PROFILE_RANGE_MM / 2, mid + MIN_PROFILE_RANGE_MM / 2)
    ax.set_xlabel("distance from landmark mm")
    ax.set_ylabel("circumference mm")
    ax.set_title("circumference along the axis", fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)


def _plot_profile(ax: Any, m: LimbMeasurement, style: str, colour: str, label: str) -> None:
    """Plot a measurement's circumference against the distance from its landmark."""
    offsets_mm = m.axis.position_mm(m.profile_z_mm) - m.axis.position_mm(m.landmark_z_mm)
    distance_mm = _direction(m) * offsets_mm
    ax.plot(distance_mm, m.profile_circumference_mm, style, color=colour, label=label)


def _direction(m: LimbMeasurement) -> float:
    """Return +1 when offsets grow with z, -1 when the levels run downwards."""
    if len(m.levels) > 1:
        return 1.0 if m.levels[-1].z_mm > m.levels[0].z_mm else -1.0
    return 1.0


def _draw_outlines(ax: Any, data: ReportData) -> None:
    m = data.measurement
    for lv in m.levels:
        pts = m.outline(lv.z_mm)
        pts = np.vstack([pts, pts[:1]]) - pts.mean(axis=0)
        ax.plot(pts[:, 0], pts[:, 1], lw=0.8, label=f"{lv.offset_mm:.0f} mm")
    ax.set_aspect("equal")
    ax.set_title("outlines at the levels (centred)", fontsize=9)
    ax.set_xlabel("x mm")
    if 0 < len(m.levels) <= 10:
        ax.legend(fontsize=6, loc="upper right")


def _draw_visits(ax: Any, data: ReportData) -> None:
    ax.set_title("volume over visits", fontsize=9)
    ax.set_ylabel("volume mL")
    if not data.visits:
        ax.text(0.5, 0.5, "no other visit", ha="center", va="center", transform=ax.transAxes)
        return
    x = np.arange(len(data.visits))
    colours = {"left": "tab:blue", "right": "tab:orange", "none": "tab:green"}
    for side, colour in colours.items():
        at = [k for k, v in enumerate(data.visits) if v.side == side]
        if at:
            volumes = [data.visits[k].volume_ml for k in at]
            ax.plot(x[at], volumes, "o-", color=colour, label=side)
    ax.set_xticks(x, [f"{v.created[:10]}\n#{v.scan_id}" for v in data.visits], fontsize=6)
    if len({v.side for v in data.visits}) > 1:
        ax.legend(fontsize=6, loc="best")
    ax.grid(alpha=0.3)


def render(data: ReportData, fmt: str) -> bytes:
    """Return the one-page report as ``pdf`` or ``png`` bytes."""
    import matplotlib  # deferred: only the report needs it

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    with matplotlib.rc_context({"pdf.fonttype": 3, "font.size": 8}):
        fig = plt.figure(figsize=PAGE_IN)
        try:
            fig.text(0.06, 0.965, "Lamina limb measurement report", fontsize=13, weight="bold")
            header = _header_lines(data)
            for k, line in enumerate(header):
                colour = "darkred" if line.startswith("FLAG") else "black"
                fig.text(0.06, 0.94 - 0.014 * k, line, fontsize=7.5, color=colour)
            top = min(0.80, 0.93 - 0.014 * len(header))
            _draw_table(fig.add_axes((0.06, 0.40, 0.88, top - 0.40)), data)
            _draw_profile(fig.add_axes((0.08, 0.06, 0.40, 0.27)), data)
            _draw_outlines(fig.add_axes((0.56, 0.20, 0.38, 0.16)), data)
            _draw_visits(fig.add_axes((0.56, 0.04, 0.38, 0.11)), data)
            out = io.BytesIO()
            fig.savefig(out, format=fmt, dpi=150)
            return out.getvalue()
        finally:
            plt.close(fig)


def write_report(path: Path, data: ReportData) -> Path:
    """Write the report (PDF, PNG or CSV by suffix) to a new file ``path``.

    Raises:
        OutputError: an unknown suffix, an existing file or a missing folder.
    """
    suffix = path.suffix.lower()
    if suffix == ".csv":
        payload = csv_text(data.measurement, data.comparison).encode()
    elif suffix in REPORT_SUFFIXES:
        payload = render(data, suffix.lstrip("."))
    else:
        raise OutputError(f"cannot write a report to {path.name}: name the file .pdf, .png or .csv")
    return write_new_file(path, payload)


@dataclass(frozen=True)
class MeasureRequest:
    """How ``lamina report`` (and the Results screen) measure a scan."""

    spacing_mm: float = DEFAULT_SPACING_MM
    landmark: Landmark = field(default_factory=Landmark)
    axis: str = AXES[0]
    thresholds: Thresholds = field(default_factory=Thresholds)


def measure_stored(library: Library, scan_id: int, request: MeasureRequest) -> LimbMeasurement:
    """Measure a processed scan of the library from the EFD sections in its report.

    Raises:
        StoreError: no such scan.
        ClinicalError: the scan is not processed, or cannot be measured as asked.
    """
    library.scan(scan_id)
    stored = library.result(scan_id)
    if stored is None:
        raise ClinicalError(
            f"scan {scan_id} has not been processed: finish it with lamina scan --resume {scan_id}"
        )
    return measure_limb(
        sections_from_report(stored, scan_id), request.spacing_mm, request.landmark, request.axis
    )


def subject_visits(library: Library, subject: str, request: MeasureRequest) -> list[Visit]:
    """Return the visits of a subject code: every processed, measurable scan, oldest first.

    The shared code ``anonymous`` is many people, so it has no history.
    """
    if subject == "anonymous":
        return []
    scans, sides = [], {}
    for summary in library.scans():
        if summary.subject != subject or not summary.has_result:
            continue
        try:
            scans.append(
                (summary.id, summary.created, measure_stored(library, summary.id, request))
            )
        except ClinicalError:
            continue  # processed by an older Lamina, or not measurable at this landmark
        sides[summary.id] = summary.side
    return history(scans, request.thresholds, sides)


def check_sides(kind: str, scan: tuple[int, str], reference: tuple[int, str]) -> None:
    """Refuse (one line) comparing limbs of one side, or visits of two sides.

    ``scan`` and ``reference`` are (scan id, side); side ``none`` is never refused.
    """
    (a_id, a_side), (b_id, b_side) = scan, reference
    if "none" in (a_side, b_side):
        return
    if kind == "limbs" and a_side == b_side:
        raise ClinicalError(
            f"scans {a_id} and {b_id} are both {a_side} limbs: compare with a scan of the "
            "other side, or use --compare-as visits"
        )
    if kind == "visits" and a_side != b_side:
        raise ClinicalError(
            f"scan {a_id} is a {a_side} limb and scan {b_id} a {b_side} one: compare visits "
            "of one side, or use --compare-as limbs"
        )


def build_report_data(
    library: Library,
    scan_id: int,
    request: MeasureRequest,
    compare_id: int | None = None,
    compare_as: str = COMPARISONS[0],
) -> ReportData:
    """Measure a scan (and the one it is compared with) and gather the page's contents."""
    record = library.scan(scan_id)
    m = measure_stored(library, scan_id, request)
    stored = library.result(scan_id) or {}
    reference = comparison = None
    reference_side = "none"
    if compare_id is not None:
        if compare_id == scan_id:
            raise ClinicalError("compare the scan with another scan, not with itself")
        reference_side = library.scan(compare_id).side
        check_sides(compare_as, (scan_id, record.side), (compare_id, reference_side))
        reference = measure_stored(library, compare_id, request)
        comparison = compare(m, reference, compare_as, request.thresholds)
    return ReportData(
        scan_id=scan_id,
        subject=record.subject,
        created=record.created,
        device=stored.get("device") or record.device,
        calibration={"grid": stored.get("calibration", {}), "axis": stored.get("axis", {})},
        measurement=m,
        reference_id=compare_id,
        reference=reference,
        comparison=comparison,
        visits=subject_visits(library, record.subject, request),
        side=record.side,
        reference_side=reference_side,
    )
