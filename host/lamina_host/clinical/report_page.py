"""The one-page clinical report (PDF or PNG), and the report files by suffix (issue #24).

From the top: who and what (subject code, side, date and time with the zone, the compared
scan's side and date), the whole-limb volume, the excess or change in mL and %, the RVC and
the flags, each naming its threshold; a picture of the limb (its measured sections as a
shaded surface, coloured by the girth difference to the compared scan) beside the girth
profile of both limbs; the table of levels; the outlines of both limbs at the levels; the
trend over the subject's dated visits per side, with the thresholds; and at the foot the
technical lines (device, calibration, axis, landmark). Every block takes the height its
content needs and the plots share the rest, so no part of the page is left blank.
"""

from __future__ import annotations

import io
import math
import textwrap
from collections.abc import Sequence
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import numpy as np

from lamina_host import __version__
from lamina_host.clinical.measures import LimbMeasurement, Visit
from lamina_host.clinical.report import (
    LENGTH_UNITS,
    REPORT_SUFFIXES,
    Line,
    ReportData,
    TableRow,
    csv_text,
    date_text,
    foot,
    headline,
    landmark_words,
    table_rows,
    when_text,
)
from lamina_host.reconstruct.efd import align
from lamina_host.store.files import OutputError, write_new_file

PAGE_IN = (8.27, 11.69)
"""A4 portrait in inches."""

MIN_PROFILE_RANGE_MM = 20.0
"""The profile plot spans at least this much girth (the 2 cm clinical threshold)."""

LEFT, RIGHT = 0.06, 0.96
"""The page's text margins (fractions of its width)."""

WRAP = 125
"""Characters a headline line holds before it wraps."""

MAX_OUTLINES = 8
"""Outline panels at most; a longer table shows every n-th level."""

COLOURS = {"left": "tab:blue", "right": "tab:orange", "none": "tab:green"}
"""Each side's colour in the plots."""

REFERENCE_COLOUR = "tab:red"
"""The compared scan's colour where this scan is drawn in its side's."""


def render(data: ReportData, fmt: str) -> bytes:
    """Return the one-page report as ``pdf`` or ``png`` bytes."""
    import matplotlib  # deferred: only the page needs it

    matplotlib.use("Agg")
    from matplotlib import pyplot as plt

    with matplotlib.rc_context({"pdf.fonttype": 3, "font.size": 7.5}):
        fig = compose(data)
        try:
            out = io.BytesIO()
            fig.savefig(out, format=fmt, dpi=150)
            return out.getvalue()
        finally:
            plt.close(fig)


def compose(data: ReportData) -> Any:
    """Return the page as a matplotlib figure (close it with ``pyplot.close``).

    Laid out from the top down: text, pictures, table, outlines, trend, then the foot.
    Its axes are labelled for what they show: ``limb``, ``profile``, ``table``,
    ``outline`` (one per level), ``volume`` and ``percent``.
    """
    from matplotlib import pyplot as plt

    fig = plt.figure(figsize=PAGE_IN)
    try:
        _compose(fig, data)
    except BaseException:
        plt.close(fig)
        raise
    return fig


def _compose(fig: Any, data: ReportData) -> None:
    """Fill the page: each block the height its content needs, the plots sharing the rest."""
    fig.text(LEFT, 0.972, "Lamina limb measurement report", fontsize=13, weight="bold")
    fig.text(RIGHT, 0.972, f"Lamina {__version__}", fontsize=6.5, color="grey", ha="right")
    y = _write_lines(fig, _wrapped(headline(data)), 0.952)
    foot_lines = [
        *foot(data),
        f"Printed {when_text(datetime.now(UTC).isoformat(timespec='seconds'))}; the subject "
        "is named by a pseudonymous code only.",
    ]
    foot_lines = [w for line in foot_lines for w in textwrap.wrap(line, 170)]
    bottom = 0.012 + 0.0105 * len(foot_lines)
    for k, line in enumerate(foot_lines):
        fig.text(LEFT, bottom - 0.0105 * (k + 1), line, fontsize=6, color="dimgrey")
    rows = table_rows(data)
    table_h = min(0.26, 0.016 * (len(rows) + 2)) if rows else 0.03
    free = y - 0.005 - bottom - table_h
    dated = {date_text(v.created) for v in data.trend.visits if _stamp(v.created) is not None}
    trend_h = 0.30 * free if len(dated) > 1 else 0.03  # one line says there is no trend yet
    # The outline panels are square: no taller than they are wide (and their titles).
    panel_w = (RIGHT - LEFT) / max(len(_outline_levels(data)), 5)
    outlines_h = min(0.42 * (free - trend_h), panel_w * PAGE_IN[0] / PAGE_IN[1] + 0.045)
    pictures_h = free - trend_h - outlines_h
    top = y + 0.004
    _draw_limb(fig, (LEFT - 0.02, top - pictures_h, 0.34, pictures_h), data)
    profile = fig.add_axes((0.43, top - pictures_h + 0.035, 0.53, pictures_h - 0.055))
    profile.set_label("profile")
    _draw_profile(profile, data)
    top -= pictures_h
    table = fig.add_axes((LEFT, top - table_h, RIGHT - LEFT, table_h - 0.008), label="table")
    _draw_table(table, data, rows)
    top -= table_h
    _draw_outlines(fig, (LEFT, top - outlines_h, RIGHT - LEFT, outlines_h), data)
    top -= outlines_h
    _draw_trend(fig, (LEFT, top - trend_h, RIGHT - LEFT, trend_h), data)


def _wrapped(lines: Sequence[Line]) -> list[Line]:
    """Return the lines wrapped to the page's width (continuations indented)."""
    out = []
    for line in lines:
        parts = textwrap.wrap(line.text, WRAP, subsequent_indent="    ") or [""]
        out += [Line(part, line.style) for part in parts]
    return out


STYLES = {
    "title": {"fontsize": 9, "weight": "bold", "color": "black"},
    "flag": {"fontsize": 8, "weight": "bold", "color": "darkred"},
    "ok": {"fontsize": 8, "weight": "bold", "color": "darkgreen"},
    "text": {"fontsize": 8, "weight": "normal", "color": "black"},
}
"""How each kind of headline line is set."""


def _write_lines(fig: Any, lines: Sequence[Line], y: float) -> float:
    """Write the headline from ``y`` down; return the height below its last line."""
    for line in lines:
        fig.text(LEFT, y, line.text, **STYLES[line.style])
        y -= 0.0155 if line.style == "title" else 0.0145
    return y


# --- the limb and its profile -------------------------------------------------------


def _ring(m: LimbMeasurement, offset_mm: float, samples: int) -> np.ndarray:
    """Return the outline ``offset_mm`` from the landmark, aligned (same start, same turn)."""
    return align(m.stack.section(m.z_at_offset(offset_mm))).evaluate(samples)


def _quads(rings: np.ndarray, offsets: np.ndarray) -> np.ndarray:
    """Return the (Q, 4, 3) quads joining consecutive rings (R, n, 2) at heights ``offsets``."""
    n = rings.shape[1]
    points = np.concatenate(
        [rings, np.broadcast_to(offsets[:, None, None], (*rings.shape[:2], 1))], axis=2
    )
    j, i = np.arange(n), (np.arange(n) + 1) % n
    lower, upper = points[:-1], points[1:]
    quads = np.stack([lower[:, j], lower[:, i], upper[:, i], upper[:, j]], axis=2)
    return quads.reshape(-1, 4, 3)


def _girth_difference(data: ReportData, offsets_mm: np.ndarray) -> np.ndarray:
    """Return this limb's girth minus the compared scan's at each offset (NaN outside)."""
    ref = data.reference_measurement
    if ref is None:
        return np.full(len(offsets_mm), np.nan)
    lo = max(data.measurement.offset_range_mm[0], ref.offset_range_mm[0])
    hi = min(data.measurement.offset_range_mm[1], ref.offset_range_mm[1])
    return np.array(
        [
            data.measurement.circumference_at(d) - ref.circumference_at(d)
            if lo - 1e-6 <= d <= hi + 1e-6
            else np.nan
            for d in offsets_mm
        ]
    )


def _draw_limb(fig: Any, rect: tuple[float, float, float, float], data: ReportData) -> None:
    """Draw the limb as measured: its sections as a shaded surface, coloured by the girth
    difference to the compared scan, the landmark at the bottom."""
    from matplotlib import cm, colormaps, colors
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # type: ignore[import-untyped]

    m, scale, unit = data.measurement, LENGTH_UNITS[data.unit], data.unit
    x0, y0, w, h = rect
    ax = fig.add_axes((x0, y0 + 0.005, w * 0.78, h - 0.05), projection="3d", label="limb")
    lo, hi = m.offset_range_mm
    offsets = np.linspace(lo, hi, int(np.clip((hi - lo) / 4.0, 12, 90)))
    rings = np.array([_ring(m, d, 48) for d in offsets])
    rings -= rings.reshape(-1, 2).mean(axis=0)
    diff = _girth_difference(data, 0.5 * (offsets[1:] + offsets[:-1]))
    limit = max(data.request.thresholds.circumference_mm, float(np.nanmax(np.abs(diff), initial=0)))
    norm = colors.Normalize(-limit / scale, limit / scale)
    cmap = colormaps["coolwarm"]
    polys = _quads(rings, offsets) / scale
    normal = np.cross(polys[:, 1] - polys[:, 0], polys[:, 3] - polys[:, 0])
    length = np.linalg.norm(normal, axis=1)
    light = np.abs(normal @ np.array([-0.5, -0.7, 0.5])) / np.where(length > 0, length, 1.0)
    values = np.repeat(diff, rings.shape[1]) / scale
    base = np.asarray(cmap(norm(np.nan_to_num(values))))
    base[~np.isfinite(values)] = colors.to_rgba("burlywood")
    base[:, :3] *= (0.45 + 0.55 * light)[:, None]
    surface = Poly3DCollection(polys, facecolors=base, edgecolors=base, linewidths=0.3)
    surface.set_rasterized(True)
    ax.add_collection3d(surface)
    span = np.abs(rings).max() / scale
    ax.set_xlim(-span, span)
    ax.set_ylim(-span, span)
    height = max(hi - lo, 1.0) / scale  # a scan of one section is drawn as a thin slice
    ax.set_zlim(lo / scale, lo / scale + height)
    ax.set_box_aspect((2 * span, 2 * span, height))
    ax.set_proj_type("ortho")
    ax.view_init(elev=12, azim=-60)
    ax.set_axis_off()
    caption = "The limb as measured"
    if data.reference is not None:
        caption += (
            f",\ncoloured by its girth minus the\n{data.reference.limb}'s "
            f"(scan {data.reference.scan_id})"
        )
        cax = fig.add_axes((x0 + w * 0.80, y0 + 0.12 * h, 0.012, 0.55 * h))
        bar = fig.colorbar(cm.ScalarMappable(norm, cmap), cax=cax)
        bar.set_label(f"girth difference ({unit})", fontsize=6.5)
        bar.ax.tick_params(labelsize=6)
    fig.text(x0 + 0.02, y0 + h, caption, fontsize=7.5, va="top")


def _draw_profile(ax: Any, data: ReportData) -> None:
    """Draw the girth along the limb of this scan and the compared one (legends: side, date)."""
    m, scale, unit = data.measurement, LENGTH_UNITS[data.unit], data.unit
    colour = COLOURS.get(data.scan.side, "tab:blue")
    _plot_profile(ax, m, "-", colour, data.scan.label, scale)
    ax.plot(
        [lv.offset_mm / scale for lv in m.levels],
        [lv.circumference_mm / scale for lv in m.levels],
        "o",
        color=colour,
        ms=3,
    )
    if data.reference is not None and data.reference_measurement is not None:
        ref_colour = COLOURS.get(data.reference.side, REFERENCE_COLOUR)
        if ref_colour == colour:
            ref_colour = REFERENCE_COLOUR
        label = data.reference.label_of(data.scan.subject)
        _plot_profile(ax, data.reference_measurement, "--", ref_colour, label, scale)
    low, high = ax.get_ylim()
    least = MIN_PROFILE_RANGE_MM / scale
    if high - low < least:  # scanner noise must not look like swelling
        mid = 0.5 * (low + high)
        ax.set_ylim(mid - least / 2, mid + least / 2)
    ax.set_xlabel(f"distance from the {landmark_words(m.landmark)} ({unit})")
    ax.set_ylabel(f"girth ({unit})")
    ax.set_title("Girth along the limb", fontsize=8)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6.5, loc="best")


def _plot_profile(
    ax: Any, m: LimbMeasurement, style: str, colour: str, label: str, scale: float
) -> None:
    """Plot a measurement's girth against the distance from its landmark."""
    start = m.axis.position_mm(m.landmark_z_mm)
    distance = m.direction * (m.axis.position_mm(m.profile_z_mm) - start)
    ax.plot(distance / scale, m.profile_circumference_mm / scale, style, color=colour, label=label)


# --- the table ----------------------------------------------------------------------


def _columns(data: ReportData) -> list[str]:
    """Return the table's column titles, in the report's unit."""
    u, scan, ref = data.unit, data.scan, data.reference
    this = scan.side.capitalize() if scan.side != "none" else f"Scan {scan.scan_id}"
    titles = [f"From {landmark_words(data.measurement.landmark)}\n({u})", f"{this} girth\n({u})"]
    if ref is not None:
        other = ref.side.capitalize() if ref.side not in ("none", scan.side) else (
            f"Scan {ref.scan_id}")  # fmt: skip
        titles += [f"{other} girth\n({u})", f"Difference\n({u})", "Difference\n(%)"]
    titles.append("Segment to next\nlevel (mL)")
    if data.comparison is not None:
        kind = "excess" if data.comparison.kind == "limbs" else "change"
        titles.append(f"Segment\n{kind} (%)")
    if data.change is not None:
        titles.append("Segment RVC\n(%)")
    return titles


def _cells(data: ReportData, row: TableRow) -> list[str]:
    """Return one row of the table as text: ! marks a value at a threshold, * an estimate."""

    def pct(value: float | None, quantity: str = "") -> str:
        if value is None or value != value:
            return ""
        hit = quantity and any(quantity in f and f.startswith("segment") for f in row.flags)
        return f"{value:+.1f}" + (" !" if hit else "")

    digits = 2 if data.unit == "cm" else 1
    cells = [
        data.length(row.offset_mm),
        data.length(row.girth_mm, digits) + (" *" if row.estimated else ""),
    ]
    if data.reference is not None:
        difference = ""
        if row.difference_mm is not None:
            difference = f"{row.difference_mm / LENGTH_UNITS[data.unit]:+.{digits}f}"
            difference += " !" if row.girth_flagged else ""
        reference = "" if row.reference_mm is None else data.length(row.reference_mm, digits)
        cells += [reference, difference, pct(row.difference_percent)]
    cells.append("" if row.segment_ml is None else f"{row.segment_ml:.1f}")
    if data.comparison is not None:
        kind = "excess" if data.comparison.kind == "limbs" else "change"
        cells.append(pct(row.segment_difference_percent, kind))
    if data.change is not None:
        cells.append(pct(row.segment_rvc_percent, "RVC"))
    return cells


def _draw_table(ax: Any, data: ReportData, rows: Sequence[TableRow]) -> None:
    """Draw the table of levels to fill its axes, the titles two lines high."""
    ax.axis("off")
    if not rows:
        ax.text(0.0, 0.5, "no level inside the measured range", fontsize=8)
        return
    titles = _columns(data)
    table = ax.table(
        cellText=[_cells(data, r) for r in rows], colLabels=titles, loc="upper center",
        cellLoc="center",
    )  # fmt: skip
    table.auto_set_font_size(False)
    size = 7 if len(rows) <= 16 else 6 if len(rows) <= 24 else 5
    table.set_fontsize(size)
    unit_h = 1.0 / (len(rows) + 2)
    for (r, _), cell in table.get_celld().items():
        cell.set_height(2 * unit_h if r == 0 else unit_h)
        cell.set_linewidth(0.4)
        if r == 0:
            cell.set_facecolor("#eeeeee")
        elif "!" in cell.get_text().get_text():
            cell.get_text().set_color("darkred")
            cell.get_text().set_weight("bold")


# --- outlines and the trend ---------------------------------------------------------


def _draw_outlines(fig: Any, rect: tuple[float, float, float, float], data: ReportData) -> None:
    """Draw both limbs' outlines at the levels (centred, same scale), one panel per level."""
    m, ref, scale = data.measurement, data.reference_measurement, LENGTH_UNITS[data.unit]
    shown = _outline_levels(data)
    x0, y0, w, h = rect
    fig.text(
        x0, y0 + h - 0.022,
        f"Outlines at the levels (centred; {data.scan.label} solid"
        + (f", {data.reference.label_of(data.scan.subject)} dashed)" if data.reference else ")"),
        fontsize=8,
    )  # fmt: skip
    if not shown:
        return
    pairs = []
    for d in shown:
        own = _centred(_ring(m, d, 180)) / scale
        other = None
        if ref is not None and ref.offset_range_mm[0] - 1e-6 <= d <= ref.offset_range_mm[1] + 1e-6:
            other = _centred(_ring(ref, d, 180)) / scale
        pairs.append((d, own, other))
    reach = max(
        np.abs(np.vstack([p for _, o, r in pairs for p in (o, r) if p is not None])).max(), 1e-3
    )
    panel_w = w / max(len(pairs), 5)
    colour = COLOURS.get(data.scan.side, "tab:blue")
    ref_colour = REFERENCE_COLOUR
    if data.reference is not None and COLOURS.get(data.reference.side, colour) != colour:
        ref_colour = COLOURS[data.reference.side]
    for k, (d, own, other) in enumerate(pairs):
        ax = fig.add_axes(
            (x0 + k * panel_w + 0.004, y0 + 0.004, panel_w - 0.008, h - 0.042), label="outline"
        )
        ax.plot(*np.vstack([own, own[:1]]).T, "-", color=colour, lw=1.0)
        if other is not None:
            ax.plot(*np.vstack([other, other[:1]]).T, "--", color=ref_colour, lw=1.0)
        ax.set_xlim(-reach * 1.05, reach * 1.05)
        ax.set_ylim(-reach * 1.05, reach * 1.05)
        ax.set_aspect("equal")
        ax.set_xticks([])
        ax.set_yticks([])
        ax.set_title(f"{data.length(d)} {data.unit}", fontsize=7, pad=2)


def _outline_levels(data: ReportData) -> list[float]:
    """Return the levels whose outlines are drawn: those both limbs have, every n-th if many."""
    levels = [lv.offset_mm for lv in data.measurement.levels]
    ref = data.reference_measurement
    if ref is not None:
        lo, hi = ref.offset_range_mm
        levels = [d for d in levels if lo - 1e-6 <= d <= hi + 1e-6] or levels
    return levels[:: max(1, math.ceil(len(levels) / MAX_OUTLINES))]


def _centred(points: np.ndarray) -> np.ndarray:
    return points - points.mean(axis=0)


def _stamp(created: str) -> datetime | None:
    """Return a stored time as a local datetime for the plot (None if unreadable)."""
    try:
        stamp = datetime.fromisoformat(created)
    except ValueError:
        return None
    return (stamp if stamp.tzinfo else stamp.replace(tzinfo=UTC)).astimezone()


def _draw_trend(fig: Any, rect: tuple[float, float, float, float], data: ReportData) -> None:
    """Draw the trend over the dated visits: volume per side, and the % figures with thresholds.

    With fewer than two visit dates there is no trend yet: one line says so.
    """
    x0, y0, _, h = rect
    visits = [v for v in data.trend.visits if _stamp(v.created) is not None]
    if len({date_text(v.created) for v in visits}) < 2:
        words = "no visit of this subject yet (test scans are not visits)"
        if visits:
            words = (
                f"one visit so far ({date_text(visits[0].created)}): the trend over the "
                "visits starts with the next"
            )
        fig.text(x0, y0 + h / 2, f"Trend: {words}.", fontsize=8, va="center")
        return
    volume_ax = fig.add_axes((x0 + 0.03, y0 + 0.03, 0.40, h - 0.055), label="volume")
    percent_ax = fig.add_axes((x0 + 0.53, y0 + 0.03, 0.37, h - 0.055), label="percent")
    span = data.trend.span_mm
    over = f" over {data.span_text(span)}" if span else ""
    volume_ax.set_title(f"Volume at each visit (mL){over}", fontsize=7.5)
    percent_ax.set_title(f"Change, excess and RVC of the {data.scan.limb} (%)", fontsize=7.5)
    for side, colour in COLOURS.items():
        own = [v for v in visits if v.side == side]
        if own:
            when, volume = [_stamp(v.created) for v in own], [v.volume_ml for v in own]
            label = side if side != "none" else "no side"
            volume_ax.plot(when, volume, "o-", color=colour, ms=3, label=label)
    this = data.visit
    if this is not None:
        volume_ax.plot([_stamp(this.created)], [this.volume_ml], "o", ms=8, mfc="none",
                       mec="black", label=f"scan {this.scan_id}")  # fmt: skip
    _draw_percent(percent_ax, data, [v for v in visits if v.side == data.scan.side])
    for ax in (volume_ax, percent_ax):
        ax.grid(alpha=0.3)
        ax.tick_params(labelsize=6)
        _date_axis(ax, [s for v in visits if (s := _stamp(v.created)) is not None])
        if ax.get_legend_handles_labels()[0]:
            ax.legend(fontsize=6, loc="best")


def _draw_percent(ax: Any, data: ReportData, own: Sequence[Visit]) -> None:
    """Plot this side's change from baseline, excess and RVC, with the thresholds as lines."""
    t = data.request.thresholds
    series = (
        ("RVC", [v.rvc_percent for v in own], "-", "black"),
        ("excess over the other limb", [v.excess_percent for v in own], "--", "tab:purple"),
        ("change from its first visit", [v.change_percent for v in own], ":", "tab:brown"),
    )
    when = [_stamp(v.created) for v in own]
    for label, values, style, colour in series:
        if any(math.isfinite(v) for v in values):
            ax.plot(when, values, style, marker="o", ms=3, color=colour, label=label)
    lines: dict[float, list[str]] = {}
    for value, name in (
        (t.rvc_percent, "RVC lymphoedema"),
        (t.subclinical_percent, "RVC subclinical"),
        (t.limb_difference_percent, "excess"),
        (t.change_percent, "change"),
    ):
        lines.setdefault(value, []).append(name)
    for k, (value, names) in enumerate(sorted(lines.items(), reverse=True)):
        colour = ("darkred", "darkorange", "grey")[min(k, 2)]
        ax.axhline(value, color=colour, lw=0.8, ls=(0, (4, 2)))
        ax.text(1.0, value, f"{value:g} %: {', '.join(names)} ", color=colour, fontsize=5.5,
                ha="right", va="bottom", transform=ax.get_yaxis_transform())  # fmt: skip
    ax.axhline(0.0, color="black", lw=0.4)


def _date_axis(ax: Any, stamps: Sequence[datetime]) -> None:
    """Label a time axis with the visits' dates (local time), or by months when they are many.

    Both trend plots span every visit (with a margin), whichever of them a plot shows.
    """
    from matplotlib import dates

    days = sorted({s.replace(hour=12, minute=0, second=0, microsecond=0) for s in stamps})
    if not days:
        return
    margin = max((days[-1] - days[0]) * 0.06, timedelta(days=2))
    ax.set_xlim(days[0] - margin, days[-1] + margin)
    if len(days) <= 6:
        ax.set_xticks(days, [d.strftime("%Y-%m-%d") for d in days])
        return
    locator = dates.AutoDateLocator(minticks=2, maxticks=6)
    ax.xaxis.set_major_locator(locator)
    ax.xaxis.set_major_formatter(dates.ConciseDateFormatter(locator))


# --- files --------------------------------------------------------------------------


def write_report(path: Path, data: ReportData) -> Path:
    """Write the report (PDF, PNG or CSV by suffix) to a new file ``path``.

    Raises:
        OutputError: an unknown suffix, an existing file or a missing folder.
    """
    suffix = path.suffix.lower()
    if suffix == ".csv":
        payload = csv_text(data).encode()
    elif suffix in REPORT_SUFFIXES:
        payload = render(data, suffix.lstrip("."))
    else:
        raise OutputError(f"cannot write a report to {path.name}: name the file .pdf, .png or .csv")
    return write_new_file(path, payload)
