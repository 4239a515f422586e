"""The clinical report of a scan: what it holds, its words, and its table as CSV (issues #13, #24).

:func:`build_report_data` measures a processed scan, the scan it is compared with and the
subject's trend, and gathers what the page (:mod:`lamina_host.clinical.report_page`) and
the CSV show: subject code (never a name), side, date and time with the zone, the
compared scan's side and date, the whole-limb volume, the excess or change in mL and %,
the relative volume change (RVC) where both limbs were scanned at two visits, and the
flags, each naming the threshold it reached. Comparisons of two subject codes are refused
unless asked for; scans marked as tests are left out of trends and comparisons.
"""

from __future__ import annotations

import csv
import io
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Any

from lamina_host.clinical.measures import (
    AXES,
    COMPARISONS,
    DEFAULT_SPACING_MM,
    PAIR_WINDOW_H,
    WHOLE_LIMB,
    ClinicalError,
    Comparison,
    Flag,
    Landmark,
    LimbChange,
    LimbMeasurement,
    Thresholds,
    Trend,
    Visit,
    compare,
    measure_limb,
    relative_volume_change,
    sections_from_report,
    trend,
)
from lamina_host.reconstruct.status import OutlineStatus
from lamina_host.store.library import Library, ScanRecord, no_result_line
from lamina_shared.errors import printable

REPORT_SUFFIXES = (".pdf", ".png")
"""What ``lamina report -o`` writes by suffix (``.csv`` writes the table only)."""

LENGTH_UNITS = {"cm": 10.0, "mm": 1.0}
"""Units the table gives distances and girths in (mm per unit); the first is the default."""

ANONYMOUS = "anonymous"
"""The shared subject code of scans without one: many people, so no history."""


@dataclass(frozen=True)
class MeasureRequest:
    """How ``lamina report`` (and the Results screen) measure and present a scan.

    ``length_unit`` (:data:`LENGTH_UNITS`) is the unit of the table's distances and girths.
    """

    spacing_mm: float = DEFAULT_SPACING_MM
    landmark: Landmark = field(default_factory=Landmark)
    axis: str = AXES[0]
    thresholds: Thresholds = field(default_factory=Thresholds)
    length_unit: str = next(iter(LENGTH_UNITS))


@dataclass(frozen=True)
class ScanInfo:
    """Who and what a scan is: id, subject code, side, creation time, whether it is a test."""

    scan_id: int
    subject: str
    side: str
    created: str
    test: bool = False

    @classmethod
    def of(cls, record: ScanRecord) -> ScanInfo:
        """Return the information of a library record."""
        return cls(record.id, record.subject, record.side, record.created, record.test)

    @property
    def limb(self) -> str:
        """Return the limb in words: ``left limb``, ``right limb`` or ``scan N``."""
        return f"{self.side} limb" if self.side != "none" else f"scan {self.scan_id}"

    @property
    def label(self) -> str:
        """Return the legend of the scan: side and date, then its number."""
        side = f"{self.side}, " if self.side != "none" else ""
        return f"{side}{when_text(self.created)} (scan {self.scan_id})"

    def label_of(self, subject: str) -> str:
        """Return the legend, with the subject code when it is not ``subject``'s."""
        if self.subject == subject and subject != ANONYMOUS:
            return self.label
        return f"{self.label[:-1]}, {printable(self.subject)})"


@dataclass(frozen=True)
class RvcScans:
    """The four scans an RVC compares: each limb at the baseline visit and at this one."""

    affected_before: int
    other_before: int
    affected: int
    other: int


@dataclass(frozen=True, eq=False)
class ReportData:
    """Everything the page and the CSV show about one scan (and the one it is compared with).

    ``change`` is the RVC of the scan's side since the subject's first visit with both
    limbs (``rvc_scans``), whole and by segment, over the trend's range.
    """

    scan: ScanInfo
    device: dict[str, Any]
    calibration: dict[str, Any]
    measurement: LimbMeasurement
    request: MeasureRequest = field(default_factory=MeasureRequest)
    reference: ScanInfo | None = None
    reference_measurement: LimbMeasurement | None = None
    comparison: Comparison | None = None
    trend: Trend = field(default_factory=lambda: Trend((), None))
    change: LimbChange | None = None
    rvc_scans: RvcScans | None = None

    @property
    def visits(self) -> list[Visit]:
        """Return the subject's visits in time order (test scans left out)."""
        return list(self.trend.visits)

    @property
    def visit(self) -> Visit | None:
        """Return this scan's own row of the trend (None for a test scan)."""
        return self.trend.visit(self.scan.scan_id)

    @property
    def other_subject(self) -> bool:
        """Return True when the compared scan is of another subject code (asked for)."""
        return self.reference is not None and (
            self.reference.subject != self.scan.subject or self.scan.subject == ANONYMOUS
        )

    @property
    def unit(self) -> str:
        """Return the table's length unit."""
        return self.request.length_unit

    def length(self, value_mm: float, digits: int | None = None) -> str:
        """Return a length in the table's unit, as text (``digits`` decimals)."""
        scale = LENGTH_UNITS[self.unit]
        if digits is None:
            digits = 1 if self.unit == "cm" else 0
        return f"{value_mm / scale:.{digits}f}"

    def span_text(self, span_mm: tuple[float, float]) -> str:
        """Return a stretch of limb in words: ``0.0-29.0 cm from the distal end``."""
        lo, hi = (self.length(v) for v in span_mm)
        return f"{lo}-{hi} {self.unit} from the {landmark_words(self.measurement.landmark)}"


def landmark_words(landmark: Landmark) -> str:
    """Return the landmark as the page says it (``distal end``, ``mark at z = 40 mm``)."""
    if landmark.kind == "height":
        return f"mark at z = {landmark.z_mm:g} mm"
    return landmark.describe()


def when_text(created: str) -> str:
    """Return a stored time as a clinic reads it: local date, time and zone.

    A time stored without a zone is UTC (as Lamina stores them); one that cannot be read
    is shown as it is.
    """
    try:
        stamp = datetime.fromisoformat(created)
    except ValueError:
        return printable(created)[:25]
    if stamp.tzinfo is None:
        stamp = stamp.replace(tzinfo=UTC)
    local = stamp.astimezone()
    return local.strftime("%Y-%m-%d %H:%M ") + (local.tzname() or local.strftime("UTC%z"))


def date_text(created: str) -> str:
    """Return the local date of a stored time (``2026-04-02``)."""
    return when_text(created)[:10]


# --- gathering ----------------------------------------------------------------------


def measure_stored(library: Library, scan_id: int, request: MeasureRequest) -> LimbMeasurement:
    """Measure a processed scan of the library from the EFD sections in its report.

    Raises:
        StoreError: no such scan.
        ClinicalError: the scan is not processed, or cannot be measured as asked.
    """
    scan = library.scan(scan_id)
    stored = library.result(scan_id)
    if stored is None:
        raise ClinicalError(no_result_line(scan))
    return measure_limb(
        sections_from_report(stored, scan_id), request.spacing_mm, request.landmark, request.axis
    )


def _subject_scans(
    library: Library, subject: str, request: MeasureRequest
) -> tuple[list[tuple[int, str, LimbMeasurement]], dict[int, str]]:
    """Return the measured visits of a subject code (processed, not tests) and their sides."""
    if subject == ANONYMOUS:
        return [], {}
    scans, sides = [], {}
    for summary in library.scans(subject=subject):
        if not summary.has_result or summary.test:
            continue
        try:
            scans.append(
                (summary.id, summary.created, measure_stored(library, summary.id, request))
            )
        except ClinicalError:
            continue  # processed by an older Lamina, or not measurable at this landmark
        sides[summary.id] = summary.side
    return scans, sides


def subject_trend(library: Library, subject: str, request: MeasureRequest) -> Trend:
    """Return the trend of a subject code: every processed scan but tests, per side, with RVC.

    The shared code ``anonymous`` is many people, so it has no trend.
    """
    scans, sides = _subject_scans(library, subject, request)
    return trend(scans, request.thresholds, sides)


def subject_visits(library: Library, subject: str, request: MeasureRequest) -> list[Visit]:
    """Return the visits of a subject code in time order (:func:`subject_trend`'s)."""
    return list(subject_trend(library, subject, request).visits)


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


def check_reference(scan: ScanInfo, reference: ScanInfo, other_subject: bool = False) -> None:
    """Refuse (one line) a comparison of a test scan, or across subject codes unless asked.

    Two ``anonymous`` scans count as two subjects: the code is shared by many people.
    """
    if reference.scan_id == scan.scan_id:
        raise ClinicalError("compare the scan with another scan, not with itself")
    for info in (scan, reference):
        if info.test:
            raise ClinicalError(
                f"scan {info.scan_id} is marked as a test scan: compare visits, or unmark it "
                f"first (lamina scans --unset-test {info.scan_id})"
            )
    same = reference.subject == scan.subject and scan.subject != ANONYMOUS
    if not same and not other_subject:
        whose = (
            "are both anonymous (possibly two people)"
            if reference.subject == scan.subject
            else f"belong to two subjects ({printable(scan.subject)} and "
            f"{printable(reference.subject)})"
        )
        raise ClinicalError(
            f"scans {scan.scan_id} and {reference.scan_id} {whose}: compare scans of one "
            "subject, or add --compare-other-subject to compare them anyway"
        )


def _rvc(
    visit: Visit | None,
    scan_id: int,
    measured: dict[int, LimbMeasurement],
    trend_of: Trend,
    thresholds: Thresholds,
) -> tuple[LimbChange | None, RvcScans | None]:
    """Return the RVC of the scan's side since the first visit with both limbs, by segment."""
    if visit is None or visit.rvc_scans is None or visit.excess_over is None:
        return None, None
    scans = RvcScans(*visit.rvc_scans, scan_id, visit.excess_over)
    a1, u1, u2 = (measured[i] for i in (scans.affected_before, scans.other_before, scans.other))
    try:
        change = relative_volume_change(a1, u1, measured[scan_id], u2, thresholds, trend_of.span_mm)
    except ClinicalError:
        return None, None  # the trend has said why (its notes)
    since = f"{visit.side} since scan {scans.affected_before}"
    over = f"{visit.side} over {_other(visit.side)} (scan {scans.other})"
    alerts = tuple(
        replace(f, context=over if f.quantity.startswith("excess") else since)
        for f in change.alerts
    )
    return replace(change, alerts=alerts), scans


def _with_context(c: Comparison, scan: ScanInfo, reference: ScanInfo) -> Comparison:
    """Return the comparison with its flags saying which scans they compare."""
    if c.kind == "limbs" and "none" not in (scan.side, reference.side):
        context = f"{scan.side} over {reference.side} (scan {reference.scan_id})"
    elif c.kind == "limbs":
        context = f"over scan {reference.scan_id}"
    else:
        context = f"from scan {reference.scan_id} ({date_text(reference.created)})"
    return replace(c, alerts=tuple(replace(f, context=context) for f in c.alerts))


def build_report_data(
    library: Library,
    scan_id: int,
    request: MeasureRequest,
    compare_id: int | None = None,
    compare_as: str = COMPARISONS[0],
    other_subject: bool = False,
) -> ReportData:
    """Measure a scan, the one it is compared with and the subject's trend, for the report.

    Raises:
        StoreError: no such scan.
        ClinicalError: a scan cannot be measured, or the comparison is refused (itself, a
            test scan, another subject unless ``other_subject``, sides that do not fit).
    """
    record = library.scan(scan_id)
    info = ScanInfo.of(record)
    reference = ref_m = comparison = None
    if compare_id is not None:
        reference = ScanInfo.of(library.scan(compare_id))
        check_reference(info, reference, other_subject)
        check_sides(compare_as, (scan_id, info.side), (compare_id, reference.side))
    scans, sides = _subject_scans(library, info.subject, request)
    measured = {i: measurement for i, _, measurement in scans}

    def measure(i: int) -> LimbMeasurement:
        return measured[i] if i in measured else measure_stored(library, i, request)

    m = measure(scan_id)
    if reference is not None:
        ref_m = measure(reference.scan_id)
        comparison = _with_context(
            compare(m, ref_m, compare_as, request.thresholds), info, reference
        )
    trend_of = trend(scans, request.thresholds, sides)
    stored = library.result(scan_id) or {}
    change, rvc_scans = _rvc(
        trend_of.visit(scan_id), scan_id, measured, trend_of, request.thresholds
    )
    return ReportData(
        scan=info,
        device=stored.get("device") or record.device,
        calibration={"grid": stored.get("calibration", {}), "axis": stored.get("axis", {})},
        measurement=m,
        request=request,
        reference=reference,
        reference_measurement=ref_m,
        comparison=comparison,
        trend=trend_of,
        change=change,
        rvc_scans=rvc_scans,
    )


# --- words --------------------------------------------------------------------------


@dataclass(frozen=True)
class Line:
    """One line of the report's text, and how it is set (``title``, ``flag``, ``ok``, ``text``)."""

    text: str
    style: str = "text"


def headline(data: ReportData) -> list[Line]:
    """Return the lines a clinician reads first, in this order: who and when, what it is
    compared with, the whole-limb volume, the excess or change, the change from the
    side's first visit, the RVC, then the flags (or that none was reached)."""
    scan, m = data.scan, data.measurement
    lines = [
        Line(
            f"Subject {printable(scan.subject)}   {scan.limb.capitalize()}   scan "
            f"{scan.scan_id}   {when_text(scan.created)}"
            + ("   TEST SCAN (not part of the trend)" if scan.test else ""),
            "title",
        )
    ]
    ref, c = data.reference, data.comparison
    if ref is not None and c is not None:
        subject = f"subject {printable(ref.subject)}, " if data.other_subject else ""
        kind = "the other limb" if c.kind == "limbs" else f"{_when(ref, scan)} visit"
        apart = _days_apart(ref, scan)
        if c.kind == "limbs" and apart is not None and abs(apart) * 24.0 > PAIR_WINDOW_H:
            kind += f", scanned {abs(apart):.0f} days {'later' if apart > 0 else 'earlier'}"
        lines.append(
            Line(
                f"Compared with: {subject}{ref.limb}, scan {ref.scan_id}, "
                f"{when_text(ref.created)} ({kind})",
                "title",
            )
        )
        if data.other_subject:
            lines.append(
                Line(
                    f"Two subject codes compared, as asked: {printable(scan.subject)} and "
                    f"{printable(ref.subject)}",
                    "flag",
                )
            )
    lines.append(
        Line(
            f"Volume: {m.volume_mm3 / 1000:.1f} mL over the whole measured range "
            f"({data.span_text(m.offset_range_mm)})"
        )
    )
    if ref is not None and c is not None:
        what = f"Excess over the {ref.limb}" if c.kind == "limbs" else (
            f"Change from scan {ref.scan_id} ({date_text(ref.created)}, {_when(ref, scan)} "
            "visit)")  # fmt: skip
        lines.append(
            Line(
                f"{what}: {c.difference_ml:+.1f} mL ({c.difference_percent:+.1f} %) over "
                f"{data.span_text(c.span_mm)}, where both were measured "
                f"({c.volume_mm3 / 1000:.1f} against {c.reference_volume_mm3 / 1000:.1f} mL)"
            )
        )
    lines += _trend_lines(data)
    flags = headline_flags(data)
    return lines + ([Line(f"FLAG: {text}", "flag") for text in flags] or
                    [Line("No threshold reached.", "ok")])  # fmt: skip


def _days_apart(reference: ScanInfo, scan: ScanInfo) -> float | None:
    """Return how many days after ``scan`` the reference was scanned (None if unreadable)."""
    times = []
    for info in (reference, scan):
        try:
            stamp = datetime.fromisoformat(info.created)
        except ValueError:
            return None
        times.append(stamp if stamp.tzinfo else stamp.replace(tzinfo=UTC))
    return (times[0] - times[1]).total_seconds() / 86400.0


def _when(reference: ScanInfo, scan: ScanInfo) -> str:
    """Return whether the compared scan is of an ``earlier`` or a ``later`` visit."""
    earlier = (reference.created, reference.scan_id) < (scan.created, scan.scan_id)
    return "an earlier" if earlier else "a later"


def _trend_lines(data: ReportData) -> list[Line]:
    """Return the change from baseline and the RVC of the scan's own visit."""
    visit, lines = data.visit, list[Line]()
    if visit is None:
        return lines
    span = data.trend.span_mm
    over = f" over {data.span_text(span)}" if span else ""
    baseline = data.trend.visit(visit.baseline_id) if visit.baseline_id is not None else None
    if baseline is not None and baseline.scan_id != visit.scan_id:
        lines.append(
            Line(
                f"Change since the {data.scan.limb}'s first visit (scan {baseline.scan_id}, "
                f"{date_text(baseline.created)}): {visit.change_ml:+.1f} mL "
                f"({visit.change_percent:+.1f} %){over}"
            )
        )
    if data.change is not None and data.rvc_scans is not None:
        r, whole = data.rvc_scans, data.change.whole
        first = data.trend.visit(r.affected_before)
        since = date_text(first.created) if first else f"scan {r.affected_before}"
        lines.append(
            Line(
                f"RVC since {since}: {whole.rvc_percent:+.1f} % ({_side_name(data.scan.side)} "
                f"scans {r.affected_before} to {r.affected} against "
                f"{_side_name(_other(data.scan.side))} scans {r.other_before} to {r.other}{over})"
            )
        )
    elif visit.side in ("left", "right"):
        lines.append(Line("RVC: needs both limbs scanned at this visit and at an earlier one"))
    return lines


def headline_flags(data: ReportData) -> list[str]:
    """Return the flags of the first lines: whole-limb ones, then levels and segments summed up.

    Whole-limb flags come from the comparison, the RVC and the scan's trend row (the
    change from its baseline); the girth and segment flags are summed up in a line each
    and marked in the table.
    """
    alerts: list[Flag] = []
    if data.comparison is not None:
        alerts += data.comparison.alerts
    if data.change is not None:
        alerts += [f for f in data.change.alerts if f.quantity == "rvc_percent"]
    visit = data.visit
    if visit is not None:
        alerts += [f for f in visit.alerts if f.quantity == "change_percent"]
        if data.comparison is None:
            alerts += [f for f in visit.alerts if f.quantity.startswith("excess")]
    lines = [f.text for f in alerts if f.where == WHOLE_LIMB]
    girth = [f for f in alerts if f.quantity == "girth_mm"]
    if girth:
        limit = data.length(data.request.thresholds.circumference_mm)
        at = f"at {', '.join(data.length(float(f.where.split()[1])) for f in girth)} {data.unit} "
        at += f"from the {landmark_words(data.measurement.landmark)}"
        if data.comparison is not None and len(girth) == len(data.comparison.levels) > 1:
            at = "at every level compared"
        lines.append(f"girth differs by {limit} {data.unit} or more {at} (marked ! in the table)")
    segments = [f for f in alerts if f.where.startswith("segment")]
    if segments:
        names = sorted({f"{_FLAG_NAMES[f.quantity]} {f.threshold:g} %" for f in segments})
        lines.append(
            f"{len(segments)} segment value(s) reach a threshold ({', '.join(names)}; marked ! "
            "in the table)"
        )
    return lines


def _side_name(side: str) -> str:
    return side if side != "none" else "this"


def _other(side: str) -> str:
    return {"left": "right", "right": "left"}.get(side, "other")


_FLAG_NAMES = {"excess_percent": "excess", "change_percent": "change", "rvc_percent": "RVC"}


def foot(data: ReportData) -> list[str]:
    """Return the technical lines at the page's foot: device, calibration, axis, levels, notes."""
    m, device = data.measurement, data.device
    dev = " ".join(str(device.get(k, "")) for k in ("software", "hardware")).strip() or "unknown"
    grid, axis = data.calibration.get("grid", {}), data.calibration.get("axis", {})
    calibration = "not recorded"
    if grid:
        calibration = (
            f"chessboard residual {grid.get('rms_mm', float('nan')):.3f} mm "
            f"(plane map {grid.get('method', '?')})"
        )
    if axis:
        calibration += (
            f"; turntable axis by {axis.get('method', '?')}, cylinder correction "
            f"{axis.get('correction_factor', float('nan')):.4f}"
        )
    tilt = f", tilted {m.axis.tilt_deg:.1f} deg" if m.axis.method != "turntable" else ""
    lines = [
        f"Device: {printable(dev)}.  Calibration: {calibration}.",
        f"Measured along the {m.axis.method} axis{tilt}; landmark {m.landmark.describe()} at "
        f"z = {m.landmark_z_mm:.1f} mm; levels every {data.length(m.spacing_mm)} {data.unit}; "
        f"scanned z = {m.coverage_mm[0]:.1f}..{m.coverage_mm[1]:.1f} mm.",
        f"Between the first and last level: {m.levels_volume_mm3 / 1000:.1f} mL from the sections, "
        f"{m.frustum_volume_mm3 / 1000:.1f} mL by the tape formula (frustums).",
        _threshold_line(data.request.thresholds, data),
    ]
    estimated = [lv for lv in m.levels if lv.source != OutlineStatus.MEASURED]
    if estimated:
        lines.append(f"{len(estimated)} level(s) rest on outlines closed by estimation (marked *).")
    lines += [f"Note: {n}" for n in (*m.notes, *data.trend.notes)]
    return lines


def _threshold_line(t: Thresholds, data: ReportData) -> str:
    return (
        f"Thresholds: RVC {t.rvc_percent:g} % (lymphoedema), {t.subclinical_percent:g} % "
        f"(subclinical); excess {t.limb_difference_ml:g} mL or {t.limb_difference_percent:g} %; "
        f"girth {data.length(t.circumference_mm)} {data.unit}; change from baseline "
        f"{t.change_percent:g} %."
    )


# --- the table ----------------------------------------------------------------------


@dataclass(frozen=True)
class TableRow:
    """One level of the report's table, with the segment from it to the next level."""

    offset_mm: float
    z_mm: float
    girth_mm: float
    estimated: bool
    note: str
    reference_mm: float | None = None
    difference_mm: float | None = None
    difference_percent: float | None = None
    girth_flagged: bool = False
    segment_to_mm: float | None = None
    segment_ml: float | None = None
    segment_frustum_ml: float | None = None
    reference_segment_ml: float | None = None
    segment_difference_ml: float | None = None
    segment_difference_percent: float | None = None
    segment_rvc_percent: float | None = None
    flags: tuple[str, ...] = ()


def table_rows(data: ReportData) -> list[TableRow]:
    """Return the table: every level, its comparison and its segment's figures where there are."""
    m, c = data.measurement, data.comparison
    levels = {round(d.offset_mm, 6): d for d in c.levels} if c else {}
    segments = {round(s.offset_lo_mm, 6): s for s in c.segments} if c else {}
    rvc = {round(s.offset_lo_mm, 6): s for s in data.change.segments} if data.change else {}
    alerts = [*(c.alerts if c else ()), *(data.change.alerts if data.change else ())]
    rows = []
    for k, level in enumerate(m.levels):
        key = round(level.offset_mm, 6)
        d, seg = levels.get(key), m.segments[k] if k < len(m.segments) else None
        s, r = segments.get(key), rvc.get(key)
        places = {f"level {level.offset_mm:g} mm"}
        if seg is not None:
            places.add(f"segment {seg.offset_lo_mm:g}-{seg.offset_hi_mm:g} mm")
        rows.append(
            TableRow(
                level.offset_mm,
                level.z_mm,
                level.circumference_mm,
                level.source != OutlineStatus.MEASURED,
                level.note,
                d.reference_mm if d else None,
                d.difference_mm if d else None,
                d.difference_percent if d else None,
                bool(d and d.flagged),
                seg.offset_hi_mm if seg else None,
                seg.volume_mm3 / 1000.0 if seg else None,
                seg.frustum_mm3 / 1000.0 if seg else None,
                s.reference_mm3 / 1000.0 if s else None,
                s.difference_ml if s else None,
                s.difference_percent if s else None,
                r.rvc_percent if r else None,
                tuple(f.text for f in alerts if f.where in places),
            )
        )
    return rows


# --- CSV ----------------------------------------------------------------------------


def csv_fields(unit: str) -> tuple[str, ...]:
    """Return the CSV's columns, lengths named in ``unit``."""
    return (
        "row", "scan", "subject", "side", "date", "test",
        "compared_scan", "compared_subject", "compared_side", "compared_date",
        f"from_landmark_{unit}", "z_mm", f"girth_{unit}", f"compared_girth_{unit}",
        f"girth_difference_{unit}", "girth_difference_percent",
        f"segment_to_{unit}", "segment_volume_ml", "segment_frustum_ml",
        "compared_segment_volume_ml", "segment_difference_ml", "segment_difference_percent",
        "segment_rvc_percent",
        f"range_from_{unit}", f"range_to_{unit}", "volume_ml", "compared_volume_ml",
        "difference_ml", "difference_percent", "change_ml", "change_percent",
        "excess_ml", "excess_percent", "rvc_percent", "source", "note", "flags",
        "axis", "axis_tilt_deg",
    )  # fmt: skip


def _num(value: float | None, digits: int = 3) -> str:
    return "" if value is None or value != value else f"{value:.{digits}f}"


def csv_text(data: ReportData) -> str:
    """Return the report as CSV: level rows, the totals, and one row per visit of the trend.

    ``row`` says what a row is: ``level`` (one level and the segment above it), ``total``
    (the whole measured range), ``compared`` (over the range both compared scans
    measured), ``rvc`` (this scan's RVC since the first visit with both limbs) or
    ``visit`` (the subject's trend, over the range every visit measured). Level and total
    rows name the axis the distances were measured along (``axis``, ``axis_tilt_deg``).
    """
    unit, scale = data.unit, LENGTH_UNITS[data.unit]
    out = io.StringIO()
    writer = csv.DictWriter(out, fieldnames=csv_fields(unit), lineterminator="\n", restval="")
    writer.writeheader()
    ref = data.reference
    scan_fields = {
        "scan": data.scan.scan_id,
        "subject": data.scan.subject,
        "side": data.scan.side,
        "date": data.scan.created,
        "test": "yes" if data.scan.test else "no",
    }
    who = dict(scan_fields)
    if ref is not None:
        who |= {"compared_scan": ref.scan_id, "compared_subject": ref.subject,
                "compared_side": ref.side, "compared_date": ref.created}  # fmt: skip

    def length(value: float | None) -> str:
        return _num(None if value is None else value / scale, 4)

    m = data.measurement
    along = {"axis": m.axis.method, "axis_tilt_deg": _num(m.axis.tilt_deg, 2)}
    for row in table_rows(data):
        writer.writerow(
            who
            | along
            | {
                "row": "level",
                f"from_landmark_{unit}": length(row.offset_mm),
                "z_mm": _num(row.z_mm),
                f"girth_{unit}": length(row.girth_mm),
                f"compared_girth_{unit}": length(row.reference_mm),
                f"girth_difference_{unit}": length(row.difference_mm),
                "girth_difference_percent": _num(row.difference_percent),
                f"segment_to_{unit}": length(row.segment_to_mm),
                "segment_volume_ml": _num(row.segment_ml),
                "segment_frustum_ml": _num(row.segment_frustum_ml),
                "compared_segment_volume_ml": _num(row.reference_segment_ml),
                "segment_difference_ml": _num(row.segment_difference_ml),
                "segment_difference_percent": _num(row.segment_difference_percent),
                "segment_rvc_percent": _num(row.segment_rvc_percent),
                "source": "estimated" if row.estimated else "measured",
                "note": row.note,
                "flags": "; ".join(row.flags),
            }
        )
    lo, hi = m.offset_range_mm
    writer.writerow(who | along | {"row": "total", f"range_from_{unit}": length(lo),
                           f"range_to_{unit}": length(hi), "volume_ml": _num(m.volume_mm3 / 1e3),
                           "note": "; ".join(m.notes)})  # fmt: skip
    c = data.comparison
    if c is not None:
        kind = "excess" if c.kind == "limbs" else "change"
        writer.writerow(
            who | {
                "row": "compared", f"range_from_{unit}": length(c.span_mm[0]),
                f"range_to_{unit}": length(c.span_mm[1]), "volume_ml": _num(c.volume_mm3 / 1e3),
                "compared_volume_ml": _num(c.reference_volume_mm3 / 1e3),
                "difference_ml": _num(c.difference_ml), "difference_percent":
                _num(c.difference_percent), f"{kind}_ml": _num(c.difference_ml),
                f"{kind}_percent": _num(c.difference_percent),
                "flags": "; ".join(f.text for f in c.alerts if f.where == WHOLE_LIMB),
            }
        )  # fmt: skip
    if data.change is not None and data.rvc_scans is not None:
        w = data.change.whole
        other = data.trend.visit(data.rvc_scans.other)
        writer.writerow(
            scan_fields | {
                "row": "rvc", "compared_scan": data.rvc_scans.other, "compared_subject":
                data.scan.subject, "compared_side": other.side if other else "",
                "compared_date": other.created if other else "", f"range_from_{unit}":
                length(w.offset_lo_mm), f"range_to_{unit}": length(w.offset_hi_mm),
                "volume_ml": _num(w.affected_mm3 / 1e3), "compared_volume_ml":
                _num(w.other_mm3 / 1e3), "change_ml": _num(w.change_ml), "change_percent":
                _num(w.change_percent), "excess_ml": _num(w.excess_ml), "excess_percent":
                _num(w.excess_percent), "rvc_percent": _num(w.rvc_percent),
                "note": f"since scans {data.rvc_scans.affected_before} (this side) and "
                f"{data.rvc_scans.other_before} (other side)",
                "flags": "; ".join(f.text for f in data.change.alerts if f.where == WHOLE_LIMB),
            }
        )  # fmt: skip
    _write_visits(writer, data, length)
    return out.getvalue()


def _write_visits(writer: csv.DictWriter[str], data: ReportData, length: Any) -> None:
    """Write the subject's trend, one row per visit, over the range every visit measured."""
    span, unit = data.trend.span_mm, data.unit
    for v in data.trend.visits:
        writer.writerow(
            {
                "row": "visit", "scan": v.scan_id, "subject": data.scan.subject,
                "side": v.side, "date": v.created, "test": "no",
                "compared_scan": "" if v.excess_over is None else v.excess_over,
                f"range_from_{unit}": length(span[0]) if span else "",
                f"range_to_{unit}": length(span[1]) if span else "",
                "volume_ml": _num(v.volume_ml), "change_ml": _num(v.change_ml),
                "change_percent": _num(v.change_percent), "excess_ml": _num(v.excess_ml),
                "excess_percent": _num(v.excess_percent), "rvc_percent": _num(v.rvc_percent),
                "note": f"baseline scan {v.baseline_id}" + (
                    f"; RVC since scans {v.rvc_scans[0]} and {v.rvc_scans[1]}"
                    if v.rvc_scans else ""),
                "flags": "; ".join(v.flags),
            }
        )  # fmt: skip
