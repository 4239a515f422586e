"""The one set of size limits a device enforces and advertises in its WELCOME.

Every number here is checked where input enters (a request, a capture folder, the
``record`` command) and reported to the host under ``"limits"``, so the host can
refuse an impossible scan before it creates one. Each advertised size works end to
end: a regular plan of ``max_views`` views travels in the compact form of
``shared/PROTOCOL.md`` well inside ``max_payload_bytes``, and so does the ``have``
list of a resumed scan of that size.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass, fields
from typing import Any

from lamina_shared.protocol import CHUNK_BYTES, MAX_ACK_SEQS, MAX_PAYLOAD_BYTES, MAX_TRANSFER_BYTES
from lamina_shared.types import ViewSpec


@dataclass(frozen=True)
class DeviceLimits:
    """Sizes a device accepts; the WELCOME's ``limits`` object is :meth:`to_dict`."""

    max_views: int = 10_000
    """Views in one scan plan (and in one target of a capture)."""
    max_sections: int = 1_000
    """Sections of one plan; section indices run 0..max_sections-1."""
    max_views_per_section: int = 360
    """Views of one section (one per degree)."""
    max_payload_bytes: int = MAX_PAYLOAD_BYTES
    """Largest payload of one frame on the line."""
    chunk_bytes: int = CHUNK_BYTES
    """Bytes of one pushed piece of a binary transfer."""
    max_fetch_bytes: int = 256 * 1024
    """Bytes one ``fetch`` request may ask for."""
    max_fetch_ranges: int = 1_024
    """Byte ranges one ``fetch`` request may name."""
    max_transfer_bytes: int = MAX_TRANSFER_BYTES
    """Largest binary transfer (a capture archive, a frame)."""
    max_ack_seqs: int = MAX_ACK_SEQS
    """Segment numbers one acknowledgement may carry."""
    window_segments: int = 16
    """Sent, unacknowledged segments the device holds before acquisition waits."""
    heartbeat_s: float = 0.3
    """Seconds between the device's heartbeats to a greeted host (idle, busy or paused)."""
    max_z_mm: float = 10_000.0
    """Largest section height a plan or capture may name (the axes' limits are tighter)."""
    max_abs_angle_deg: float = 3_600.0
    """Largest turntable angle magnitude a plan or capture may name (ten turns)."""
    max_exposure_us: int = 10_000_000
    """Longest exposure a request may ask for, in microseconds (ten seconds)."""
    max_image_side_px: int = 16_384
    """Largest frame side a capture may declare (frames are refused from their header)."""
    max_image_pixels: int = 20_000_000
    """Most pixels a frame may declare: above the 16 MP sensors, so a decoded 16-bit RGB
    frame stays near 120 MB."""
    max_manifest_bytes: int = 64 * 1024 * 1024
    """Largest ``capture.json`` read (10,000 views take about 2 MB)."""

    def __post_init__(self) -> None:
        if self.max_views < 1 or self.max_sections < 1 or self.max_views_per_section < 1:
            raise ValueError("device limits must allow at least one view and one section")
        if self.max_sections > 65_536 or self.max_views_per_section > 65_536:
            raise ValueError("sections and views travel as u16: at most 65,536 of each")

    def to_dict(self) -> dict[str, Any]:
        """Return the WELCOME form: every field under its own name."""
        return asdict(self)

    @classmethod
    def from_welcome(cls, limits: Any) -> DeviceLimits:
        """Return the limits a WELCOME advertised; absent or malformed fields keep defaults.

        An older device advertises fewer fields: what it does not say is taken as this
        version's default rather than refused, since the device checks every request
        again itself.
        """
        if not isinstance(limits, dict):
            return cls()
        known = {f.name: type(f.default) for f in fields(cls)}
        given = {
            key: value
            for key, value in limits.items()
            if key in known
            and not isinstance(value, bool)
            and isinstance(value, int | float)
            and (known[key] is float or isinstance(value, int))
        }
        try:
            return cls(**given)  # type: ignore[arg-type]  # types checked above
        except ValueError:
            return cls()


_SHOWN_CHARS = 40


def show(value: Any) -> str:
    """Return a short printable form of a received value (a huge one is cut)."""
    text = repr(value) if not isinstance(value, int) or abs(value) < 10**30 else "a huge integer"
    return text if len(text) <= _SHOWN_CHARS else text[: _SHOWN_CHARS - 3] + "..."


def _angle_key(angle_deg: float) -> float:
    """Return the turntable position an angle names: 0 and 360 deg are the same view."""
    return round(angle_deg % 360.0, 6) % 360.0


def plan_problems(
    views: Sequence[tuple[str, ViewSpec]], limits: DeviceLimits, min_z_mm: float | None = None
) -> list[str]:
    """Return every way the labelled ``views`` break ``limits``, one line each.

    Checks each view's section index, height and angle, then the plan as a whole:
    views per section, the same view twice (angles compared modulo 360 deg, so 0 and
    360 in one section are a duplicate) and two sections at the same height.
    ``min_z_mm`` is the lowest height allowed (captures: 0, their first section).
    """
    problems: list[str] = []
    if len(views) > limits.max_views:
        return [f"{len(views)} views, at most {limits.max_views} allowed"]
    low_z = -limits.max_z_mm if min_z_mm is None else min_z_mm
    first: dict[tuple[int, float], str] = {}
    heights: dict[int, tuple[float, str]] = {}
    counts: dict[int, int] = {}
    for where, view in views:
        if not 0 <= view.section < limits.max_sections:
            problems.append(
                f"{where}.section: {show(view.section)} is outside 0..{limits.max_sections - 1}"
            )
        if not low_z <= view.z_mm <= limits.max_z_mm:
            problems.append(
                f"{where}.z_mm: {show(view.z_mm)} is outside {low_z:g}..{limits.max_z_mm:g}"
            )
        if abs(view.angle_deg) > limits.max_abs_angle_deg:
            problems.append(
                f"{where}.angle_deg: {show(view.angle_deg)} is beyond "
                f"+-{limits.max_abs_angle_deg:g}"
            )
        key = (view.section, _angle_key(view.angle_deg))
        if key in first:
            problems.append(
                f"{where}: duplicate (section {show(view.section)}, angle {view.angle_deg} deg), "
                f"the same view as {first[key]}"
            )
        first.setdefault(key, where)
        counts[view.section] = counts.get(view.section, 0) + 1
        heights.setdefault(view.section, (view.z_mm, where))
    for section, count in counts.items():
        if count > limits.max_views_per_section:
            problems.append(
                f"section {section}: {count} views, at most {limits.max_views_per_section} allowed"
            )
    at_height: dict[float, int] = {}
    for section, (z_mm, where) in heights.items():
        if z_mm in at_height:
            problems.append(
                f"{where}: section {show(section)} is at z_mm {z_mm}, the height of section "
                f"{show(at_height[z_mm])}"
            )
        at_height.setdefault(z_mm, section)
    return problems
