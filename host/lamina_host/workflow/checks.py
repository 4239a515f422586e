"""What the command line and the terminal UI check alike before and during a scan.

One place for the rules both front ends apply, so they cannot drift apart:

- :func:`check_plan`: the regular plan's three numbers, refused (never replaced by a
  default) when zero, negative, not finite or beyond the ranges below;
- :func:`check_plan_limits`: a plan against the limits the device advertised, before
  the scan exists in the library;
- :func:`check_object_fits`: the object's first view against the disc the camera sees at
  every turntable angle, before any other view of it is taken;
- :func:`check_next_turn`: a continuous scan whose laser-off frames the box takes a turn
  later, on a table the calibration cylinder finds turning short of its count, before
  any view of the object is taken;
- :data:`PLAN_PRESETS`: plans named for what they scan, made to fit the device's lift
  (:func:`preset_plan`) and refused before the first view when that kind of object is
  wider than the camera's view (:func:`check_preset_fits`).

Subject codes are the library's rule (:mod:`lamina_host.store.subjects`); the identity of
what acquires a scan is the link's (:mod:`lamina_host.link.identity`);
:class:`~lamina_shared.errors.InputError` and :func:`~lamina_shared.errors.printable` are
shared with the device.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass

import numpy as np

from lamina_host.reconstruct.axis import AxisCalibration, gear_ratio_factor, turn_miss_deg
from lamina_shared.errors import InputError
from lamina_shared.limits import DeviceLimits
from lamina_shared.messages import AxesInfo, Welcome
from lamina_shared.ops import (
    EXTRACT_FIELDS,
    ExtractChanges,
    Problems,
    check_extract,
    extract_problems,
    plan_fits,
)
from lamina_shared.types import SCAN_MODES, ScanPlan

SECTIONS_RANGE = (1, 500)
VIEWS_RANGE = (3, 360)
PITCH_MAX_MM = 50.0
PITCH_MIN_MM = 0.001
"""The finest section pitch a plan may ask for: a micrometre, finer than any lift steps
(a lead screw of 8 mm per turn at 3,200 microsteps per turn steps 2.5 um)."""
DEFAULT_SECTIONS, DEFAULT_PITCH_MM, DEFAULT_VIEWS = 4, 2.0, 8
"""The regular plan's defaults when some of its numbers are given and others not."""


def _is_number(value: object) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def check_count(name: str, value: float, low: int, high: int, hint: str = "") -> int:
    """Return ``value`` if it is a whole number in ``low..high``, else raise InputError."""
    if not (_is_number(value) and math.isfinite(value) and value == int(value)):
        raise InputError(f"{name} {value} must be a whole number between {low} and {high}{hint}")
    if not low <= value <= high:
        raise InputError(f"{name} {value} must be between {low} and {high}{hint}")
    return int(value)


def check_positive_mm(name: str, value: float, high_mm: float = math.inf) -> float:
    """Return ``value`` if it is a finite number of mm above 0 (and at most ``high_mm``)."""
    if not (_is_number(value) and math.isfinite(value) and 0 < value <= high_mm):
        limit = f" and at most {high_mm:g} mm" if math.isfinite(high_mm) else ""
        shown = f"{value:g}" if _is_number(value) else str(value)
        raise InputError(f"{name} {shown} mm must be above 0{limit}")
    return float(value)


def check_plan(sections: int | None, pitch_mm: float | None, views: int | None) -> ScanPlan:
    """Return the regular plan of the given numbers (defaults only for those not given).

    Raises:
        InputError: a number is zero, negative, not finite or out of range.
    """
    n_sections = check_count(
        "sections", DEFAULT_SECTIONS if sections is None else sections, *SECTIONS_RANGE
    )
    pitch = check_positive_mm(
        "pitch", DEFAULT_PITCH_MM if pitch_mm is None else pitch_mm, PITCH_MAX_MM
    )
    if pitch < PITCH_MIN_MM:
        raise InputError(
            f"pitch {pitch:g} mm is below {PITCH_MIN_MM:g} mm, finer than a lift can step: "
            f"enter a pitch from {PITCH_MIN_MM:g} to {PITCH_MAX_MM:g} mm"
        )
    n_views = check_count(
        "views", DEFAULT_VIEWS if views is None else views, *VIEWS_RANGE, " (the thesis uses 8)"
    )
    try:
        return ScanPlan.regular(n_sections, pitch, n_views)
    except ValueError as exc:  # what the checks above missed is still the user's input
        raise InputError(f"the plan cannot be made: {exc}") from None


def check_plan_axes(target: str, plan: ScanPlan, axes: AxesInfo) -> None:
    """Refuse a plan the axes cannot follow: heights or angles beyond their soft limits,
    or sections closer than the lift's step (limits the WELCOME does not give are not
    checked; the device checks every request again itself).

    Raises:
        InputError: naming the axis, the plan's figure and the device's limit.
    """
    heights = sorted({view.z_mm for view in plan.views})
    angles = sorted({view.angle_deg for view in plan.views})
    if not heights:
        return
    for name, unit, values, low, high in (
        ("lift", "mm", heights, axes.lift_min_mm, axes.lift_max_mm),
        ("turntable", "deg", angles, axes.turntable_min_deg, axes.turntable_max_deg),
    ):
        if (low is not None and values[0] < low) or (high is not None and values[-1] > high):
            extreme = values[-1] if high is not None and values[-1] > high else values[0]
            travel = f"{'-inf' if low is None else f'{low:g}'}.."
            travel += "inf" if high is None else f"{high:g}"
            raise InputError(
                f"the {target} plan reaches {extreme:g} {unit}, beyond the {name}'s travel of "
                f"{travel} {unit}: plan fewer sections or a smaller pitch"
            )
    step = axes.lift_step_mm
    gaps = [b - a for a, b in itertools.pairwise(heights)]
    if step is not None and gaps and min(gaps) < step * (1 - 1e-9):
        raise InputError(
            f"the {target} plan's sections are {min(gaps):g} mm apart, finer than the lift's "
            f"step of {step:g} mm: plan a pitch of at least {step:g} mm"
        )


def check_mode(plan: ScanPlan, info: Welcome | None, colour: bool = False) -> None:
    """Refuse a plan in a scan mode the connected device does not offer (its WELCOME),
    or a continuous scan with colour (its laser-off frames are taken away from the stripe).

    Raises:
        InputError: naming the mode and what the device can do.
    """
    offered = info.modes if info is not None else SCAN_MODES[:1]
    if plan.mode not in offered:
        raise InputError(
            f"this device cannot scan in {plan.mode} mode (it offers {', '.join(offered)}): "
            f"scan in {offered[0]} mode"
        )
    if colour and plan.continuous:
        raise InputError("colour needs a stop-and-go scan: scan without colour or stop-and-go")


def check_next_turn(plan: ScanPlan, info: Welcome | None, axis: AxisCalibration | None) -> None:
    """Refuse a continuous scan whose laser-off frames would miss their angle.

    A box configured with ``off_frames = "next-turn"`` takes each laser-off frame a turn
    of its step count after the laser-on frame. Where the calibration cylinder finds the
    table turning short of (or past) its count (:func:`gear_ratio_factor`), that frame
    sees the subject turned by the miss, and room light on fine relief passes for stripe
    (0.23-0.29 mm instead of 0.09 mm on random limb shapes at 1.6 degrees): a scan that
    would be warned of after the patient has stood through it is refused before.

    Args:
        plan: the object scan's plan.
        info: the connected device's WELCOME (None: nothing is known of its frames).
        axis: the calibration cylinder's axis (None: not found yet, nothing to judge).

    Raises:
        InputError: naming the miss, the factor that mends it and the way round it.
    """
    if not plan.continuous or info is None or info.off_frames != "next-turn" or axis is None:
        return
    factor = gear_ratio_factor(axis)
    if factor is None:
        return
    miss_deg = turn_miss_deg(axis)
    way = "short of" if miss_deg > 0 else "beyond"
    raise InputError(
        f"this box takes a continuous scan's laser-off frames a turn later, but the "
        f"calibration cylinder finds its turntable turning {abs(miss_deg):.2f} degrees {way} "
        f"its step count each turn, so those frames would miss their views by as much: "
        f"multiply [turntable] gear_ratio in the box's configuration by {factor:.5f}, "
        f"restart the device program, scan the calibration cylinder again and scan; or "
        f"scan in stop-and-go mode"
    )


def check_extract_limits(changes: ExtractChanges | None, info: Welcome | None) -> None:
    """Refuse extraction changes that take the device's settings out of their ranges.

    The device's configured settings (its WELCOME) with the scan's changes are checked by
    the device's own rule before the scan exists, so no scan is left half made by a
    refusal. A device that does not report every setting refuses such a scan itself.

    Args:
        changes: the scan's changes to the device's extraction (``lamina scan --extract``).
        info: the connected device's WELCOME.

    Raises:
        InputError: naming every setting out of range.
    """
    if changes is None or info is None or info.extract is None:
        return
    configured = check_extract(info.extract.to_wire(), "welcome.extract", Problems())
    if configured is None:
        return
    settings = {**configured.as_dict(), **changes.as_dict()}
    if set(settings) != set(EXTRACT_FIELDS):
        return
    problems = extract_problems(settings)
    if problems:
        raise InputError(
            f"--extract: {'; '.join(problems)} on this device: change the setting (see "
            "lamina scan --help); no scan was created"
        )


def check_plan_limits(
    target: str,
    plan: ScanPlan,
    limits: DeviceLimits | None,
    axes: AxesInfo | None = None,
) -> None:
    """Refuse a plan beyond the limits the device advertised (None: this version's).

    Args:
        target: what the plan scans (named in the refusal).
        plan: the plan to check.
        limits: the WELCOME's ``limits`` (sizes; what an older device left out is the default).
        axes: the WELCOME's ``axes`` (travel of the lift and turntable, the lift's step).

    Raises:
        InputError: naming the limit, the plan's figure and the device's.
    """
    limits = limits or DeviceLimits()
    per_section: dict[int, int] = {}
    for view in plan.views:
        per_section[view.section] = per_section.get(view.section, 0) + 1
    figures = {
        "max_views": (len(plan.views), "views in all"),
        "max_sections": (len(per_section), "sections"),
        "max_views_per_section": (max(per_section.values(), default=0), "views in one section"),
    }
    for key, (figure, what) in figures.items():
        limit = getattr(limits, key)
        if figure > limit:
            raise InputError(
                f"the {target} plan has {figure} {what}, beyond the device's limit of {limit} "
                f"({key}): plan a smaller scan"
            )
    check_plan_axes(target, plan, axes or AxesInfo())
    # The counts above name the limit; the shared check adds what only the wire knows
    # (an irregular plan too long for one request, heights and angles out of range).
    problems = plan_fits(plan, limits)
    if problems:
        raise InputError(f"the {target} plan cannot be sent to the device: {problems[0]}")


FIT_OUTSIDE_SHARE = 0.5
"""The share of the first view's points beyond the camera's disc that stops a scan: the
same share at which processing gives up on the object (fewer are outliers it rejects)."""


class ObjectTooLarge(InputError):
    """The object reaches beyond what the camera sees at every turntable angle."""


def check_object_fits(points_mm: np.ndarray, field_radius_mm: float | None) -> None:
    """Refuse an object larger than the camera's view, from its first view alone.

    Args:
        points_mm: (N, 2) object-frame points of the object's first view (axis at 0, mm).
        field_radius_mm: the radius about the axis of the disc the camera sees at every
            angle (None: unknown, nothing is checked).

    Raises:
        ObjectTooLarge: most of the view lies outside that disc (the one line names the
            figures and what to do).
    """
    pts = np.asarray(points_mm, dtype=float).reshape(-1, 2)
    if field_radius_mm is None or not len(pts):
        return
    outside = int(np.count_nonzero(np.hypot(pts[:, 0], pts[:, 1]) > field_radius_mm))
    if outside > FIT_OUTSIDE_SHARE * len(pts):
        raise ObjectTooLarge(
            f"the object does not fit the camera's view: {outside} of {len(pts)} points of "
            f"its first view lie further than {field_radius_mm:.1f} mm from the turntable "
            "axis, beyond what the camera sees at every angle; nothing more was acquired: "
            "use a rig with a wider view, or centre a smaller object on the turntable"
        )


@dataclass(frozen=True)
class PlanPreset:
    """A plan named for what it scans, with that object's usual size.

    Attributes:
        name: what the front ends offer (``arm``).
        what: the object in words, for the lines that name it (``an arm``).
        width_mm: the widest such object usually is (what must fit the camera's view).
        length_mm: how much of it a scan covers from its distal end (the lift's travel
            may cut it short).
        pitch_mm: the sections' spacing.
        views: views per section.
    """

    name: str
    what: str
    width_mm: float
    length_mm: float
    pitch_mm: float
    views: int


PLAN_PRESETS: dict[str, PlanPreset] = {
    p.name: p
    for p in (
        PlanPreset("arm", "an arm", 130.0, 400.0, 10.0, 8),
        PlanPreset("leg", "a leg", 180.0, 600.0, 10.0, 8),
        # Fingers hide each other: more views, finer sections.
        PlanPreset("hand", "a hand", 110.0, 200.0, 5.0, 12),
        PlanPreset("cast", "a cast", 150.0, 300.0, 10.0, 8),
    )
}
"""The plan presets, by name. Widths and lengths are adult sizes, on the large side: a
smaller object fits whatever these fit."""


@dataclass(frozen=True)
class PresetPlan:
    """A preset's plan on one device, and a line when the lift cut its length short."""

    sections: int
    pitch_mm: float
    views: int
    note: str = ""


def preset_plan(preset: PlanPreset, axes: AxesInfo | None = None) -> PresetPlan:
    """Return the preset's plan, its length cut to the lift's travel where the device gives it.

    Args:
        preset: one of :data:`PLAN_PRESETS`.
        axes: the connected device's axes (None: not connected; the preset's own length).
    """
    length = preset.length_mm
    note = ""
    travel = None
    if axes is not None and axes.lift_max_mm is not None:
        travel = axes.lift_max_mm - (axes.lift_min_mm or 0.0)
    if travel is not None and travel < length:
        note = f"cut to the lift's {travel:g} mm travel ({preset.what}: {length:g} mm)"
        length = travel
    sections = min(int(length // preset.pitch_mm) + 1, SECTIONS_RANGE[1])
    return PresetPlan(sections, preset.pitch_mm, preset.views, note)


def check_preset_fits(preset: PlanPreset, field_radius_mm: float | None) -> None:
    """Refuse a preset whose object is wider than the camera's view, before any view is taken.

    Args:
        preset: the chosen preset.
        field_radius_mm: the radius about the axis the camera sees at every angle (None:
            not calibrated yet, nothing is checked).

    Raises:
        ObjectTooLarge: naming the object's width and the view's.
    """
    if field_radius_mm is not None and preset.width_mm > 2 * field_radius_mm:
        raise ObjectTooLarge(
            f"{preset.what} is up to {preset.width_mm:g} mm across, and this rig sees "
            f"{2 * field_radius_mm:.0f} mm across the turntable: choose a rig with a wider "
            f"view, or type the plan's numbers for a smaller object"
        )
