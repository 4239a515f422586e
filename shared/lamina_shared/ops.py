"""The device's operations: each one's name, typed arguments and their validation.

A REQUEST names an operation and carries JSON arguments. :func:`parse_args` turns
them into that operation's frozen dataclass, or raises :class:`ArgsError` listing
every problem found at once: unknown and missing keys, wrong types (a bool is not a
number here), non-finite or out-of-range numbers, integers of any size, oversize
strings and lists. Nothing is converted before its type and size are known, so no
argument can raise anything else. The host builds requests with :func:`request_args`
from the same dataclasses, so both ends agree on every name.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from typing import Any

from lamina_shared.limits import DeviceLimits, plan_problems, show
from lamina_shared.types import SCAN_MODES, ScanPlan, ViewSpec

TARGETS = ("cylinder", "object")
AXES = ("lift", "turntable")
EXTRACT_METHODS = ("cog", "thinning")
"""Stripe centre methods of the device's extraction (``ExtractSettings.method``)."""
EXTRACT_RUN_CHOICES = ("peak", "continuity")
"""Which run a column keeps (``ExtractSettings.run_choice``)."""
EXTRACT_FIELDS: dict[str, str] = {
    "threshold": "number-or-null",
    "power": "number",
    "min_peak": "number",
    "subtract_threshold": "bool",
    "method": "method",
    "run_choice": "run_choice",
    "background_opening_px": "int",
    "noise_gate": "bool",
    "false_points_per_frame": "number",
    "min_chain_px": "int",
    "max_row_jump_px": "number",
    "min_width_px": "int",
    "max_width_px": "int",
    "smooth_sigma_px": "number",
    "margin_px": "int",
    "bridge_px": "int",
}
"""The wire schema of the device's extraction settings: each field's JSON kind. Their
ranges are :func:`extract_problems`'."""
EXTRACT_FULL_SCALE = 255
"""An 8-bit frame's full scale: the top of the threshold, peak and run-width ranges."""
_MAX_OPENING_PX = 1024  # an opening taller than any frame removes nothing more
_MAX_MARGIN_PX = 16  # pixels beyond a run's ends its centre may weigh in
_MAX_BRIDGE_PX = 8  # rows between two runs of one column that may still join them
MAX_SETTING = 1_000_000
"""Largest whole-number extraction setting the schema lets through to the range check."""
MAX_SHOWN_PROBLEMS = 12
"""Problems named in one error reply; the rest are counted (a reply must fit one frame)."""
MISSING: Any = object()
"""What a parser passes for an absent key: no check reports it twice (check_keys did)."""


class UnknownOp(ValueError):
    """A request names no operation the device has."""


class ArgsError(ValueError):
    """A request's arguments are unusable; ``problems`` lists every reason found.

    ``code`` is ``limit`` when a size the device advertises was exceeded, else
    ``bad-args``.
    """

    def __init__(self, op: str, problems: list[str], code: str = "bad-args") -> None:
        self.op, self.problems, self.code = op, problems, code
        shown = problems[:MAX_SHOWN_PROBLEMS]
        more = len(problems) - len(shown)
        text = "; ".join(shown) + (f"; and {more} more" if more else "")
        super().__init__(text)


class Problems:
    """Collects problems while arguments are checked, so all of them are reported."""

    def __init__(self) -> None:
        self.items: list[str] = []
        self.over_limit = False

    def add(self, text: str, limit: bool = False) -> None:
        """Record one problem; ``limit`` marks a size beyond the device's limits."""
        self.items.append(text)
        self.over_limit |= limit


def is_int(value: Any) -> bool:
    """Return True for a JSON integer (bools are not integers here)."""
    return isinstance(value, int) and not isinstance(value, bool)


def is_number(value: Any) -> bool:
    """Return True for a JSON number (bools are not numbers here)."""
    return isinstance(value, int | float) and not isinstance(value, bool)


def check_int(value: Any, where: str, low: int, high: int, problems: Problems) -> int | None:
    """Return ``value`` if it is a whole number in ``low..high``; else record why not."""
    if value is MISSING:
        return None
    if not is_int(value):
        problems.add(f"{where}: a whole number is required, found {show(value)}")
        return None
    if not low <= value <= high:
        problems.add(f"{where}: {show(value)} is outside {low}..{high}", limit=True)
        return None
    return int(value)


def check_number(
    value: Any, where: str, low: float, high: float, problems: Problems
) -> float | None:
    """Return ``value`` as a float if it is a finite number in ``low..high``."""
    if value is MISSING:
        return None
    if not is_number(value):
        problems.add(f"{where}: a number is required, found {show(value)}")
        return None
    # Comparing before converting: float() of a 400-digit integer raises OverflowError.
    if isinstance(value, float) and not math.isfinite(value):
        problems.add(f"{where}: {show(value)} is not a finite number")
        return None
    if isinstance(value, int) and not -sys.float_info.max <= value <= sys.float_info.max:
        # Even with infinite bounds (a listed plan's heights): no float holds it.
        problems.add(f"{where}: {show(value)} is beyond any finite number")
        return None
    if not low <= value <= high:
        problems.add(f"{where}: {show(value)} is outside {low:g}..{high:g}")
        return None
    return float(value)


def check_bool(value: Any, where: str, problems: Problems) -> bool | None:
    """Return ``value`` if it is true or false."""
    if value is MISSING:
        return None
    if not isinstance(value, bool):
        problems.add(f"{where}: true or false is required, found {show(value)}")
        return None
    return value


def check_choice(
    value: Any, where: str, options: tuple[str, ...], problems: Problems
) -> str | None:
    """Return ``value`` if it is one of ``options``."""
    if value is MISSING:
        return None
    if not isinstance(value, str) or value not in options:
        problems.add(f"{where}: one of {', '.join(options)} is required, found {show(value)}")
        return None
    return value


def check_list(
    value: Any, where: str, max_items: int, problems: Problems, min_items: int = 0
) -> list[Any] | None:
    """Return ``value`` if it is a list of ``min_items..max_items`` items."""
    if value is MISSING:
        return None
    if not isinstance(value, list):
        problems.add(f"{where}: a list is required, found {show(value)}")
        return None
    if not min_items <= len(value) <= max_items:
        problems.add(f"{where}: {len(value)} items, {min_items}..{max_items} allowed", limit=True)
        return None
    return value


def check_keys(
    data: dict[str, Any], where: str, required: set[str], optional: set[str], problems: Problems
) -> bool:
    """Record unknown and missing keys of ``data``; return True if there were none."""
    unknown = [key for key in data if key not in required | optional]
    missing = sorted(required - set(data))
    for key in unknown[:MAX_SHOWN_PROBLEMS]:
        problems.add(f"{where}: takes no argument {show(key)}")
    if len(unknown) > MAX_SHOWN_PROBLEMS:
        problems.add(f"{where}: {len(unknown) - MAX_SHOWN_PROBLEMS} more unknown arguments")
    for key in missing:
        problems.add(f"{where}: {key} is required")
    return not unknown and not missing


# --- scan plans -------------------------------------------------------------------------


def _regular_plan(data: Any, limits: DeviceLimits, problems: Problems) -> ScanPlan | None:
    where = "plan.regular"
    if not isinstance(data, dict):
        problems.add(f"{where}: an object is required, found {show(data)}")
        return None
    if not check_keys(data, where, {"sections", "pitch_mm", "views"}, set(), problems):
        return None
    sections = check_int(data["sections"], f"{where}.sections", 1, limits.max_sections, problems)
    views = check_int(data["views"], f"{where}.views", 1, limits.max_views_per_section, problems)
    pitch = check_number(data["pitch_mm"], f"{where}.pitch_mm", 0.0, limits.max_z_mm, problems)
    if pitch is not None and pitch <= 0:
        problems.add(f"{where}.pitch_mm: a positive number of mm is required")
        return None
    if sections is None or views is None or pitch is None:
        return None
    if sections * views > limits.max_views:
        problems.add(
            f"{where}: {sections * views} views, at most {limits.max_views} allowed", limit=True
        )
        return None
    if (sections - 1) * pitch > limits.max_z_mm:
        problems.add(f"{where}: the top section is above {limits.max_z_mm:g} mm", limit=True)
        return None
    return ScanPlan.regular(sections, pitch, views)


def _listed_plan(data: Any, limits: DeviceLimits, problems: Problems) -> ScanPlan | None:
    items = check_list(data, "plan.views", limits.max_views, problems, min_items=1)
    if items is None:
        return None
    views: list[ViewSpec] = []
    keys = {"section", "z_mm", "angle_deg"}
    start = len(problems.items)
    for k, item in enumerate(items):
        where = f"plan.views[{k}]"
        if not isinstance(item, dict):
            problems.add(f"{where}: a view object is required, found {show(item)}")
            continue
        if not check_keys(item, where, keys, set(), problems):
            continue
        section = check_int(item["section"], f"{where}.section", 0, 65_535, problems)
        z_mm = check_number(item["z_mm"], f"{where}.z_mm", -math.inf, math.inf, problems)
        angle = check_number(item["angle_deg"], f"{where}.angle_deg", -math.inf, math.inf, problems)
        if section is not None and z_mm is not None and angle is not None:
            views.append(ViewSpec(section, z_mm, angle))
    if len(problems.items) > start:
        return None
    found = plan_problems([(f"plan.views[{k}]", v) for k, v in enumerate(views)], limits)
    for text in found:
        problems.add(text)
    return None if found else ScanPlan(tuple(views))


def check_plan(data: Any, limits: DeviceLimits, problems: Problems) -> ScanPlan | None:
    """Return the plan of a wire form (``regular`` or listed ``views``) within ``limits``.

    The optional ``mode`` is one of :data:`~lamina_shared.types.SCAN_MODES` (absent:
    stop-and-go); whether this device can scan in it is the operation's to say.
    """
    if not isinstance(data, dict):
        problems.add(f"plan: an object is required, found {show(data)}")
        return None
    form = "regular" if "regular" in data else "views"
    if not check_keys(data, "plan", {form}, {"mode"}, problems):
        return None
    mode = check_choice(data.get("mode", SCAN_MODES[0]), "plan.mode", SCAN_MODES, problems)
    if form == "regular":
        plan = _regular_plan(data["regular"], limits, problems)
    else:
        plan = _listed_plan(data["views"], limits, problems)
    return None if plan is None or mode is None else plan.with_mode(mode)


def plan_fits(plan: ScanPlan, limits: DeviceLimits) -> list[str]:
    """Return why ``plan`` cannot be sent to a device with ``limits`` (empty if it can).

    The host calls this before it creates a scan: besides the counts, a plan that is
    not regular must fit one REQUEST in its listed form.
    """
    problems = Problems()
    check_plan(plan.to_wire(), limits, problems)
    if plan.regular_form() is None:
        size = len(_json(plan.to_dict()))
        # Half the payload: the rest carries the request's other arguments (``have``).
        if size > limits.max_payload_bytes // 2:
            problems.add(
                f"plan: an irregular plan of {len(plan.views)} views takes {size} bytes, more "
                f"than one message holds: use a regular plan (sections x views)",
                limit=True,
            )
    return problems.items


def _json(data: Any) -> bytes:
    return json.dumps(data, separators=(",", ":")).encode()


# --- extraction settings ---------------------------------------------------------------


@dataclass(frozen=True)
class ExtractChanges:
    """Extraction settings to change for one scan, by name (the rest stay as configured)."""

    values: tuple[tuple[str, float | int | bool | str | None], ...] = ()

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON object form."""
        return dict(self.values)

    def as_dict(self) -> dict[str, Any]:
        """Return the changes as keyword arguments of ``ExtractSettings``."""
        return dict(self.values)


def _setting(value: Any, where: str, kind: str, problems: Problems) -> Any:
    if kind == "number-or-null" and value is None:
        return None
    if kind in ("number", "number-or-null"):
        return check_number(value, where, -math.inf, math.inf, problems)
    if kind == "int":
        return check_int(value, where, -MAX_SETTING, MAX_SETTING, problems)
    if kind == "bool":
        return check_bool(value, where, problems)
    options = EXTRACT_METHODS if kind == "method" else EXTRACT_RUN_CHOICES
    return check_choice(value, where, options, problems)


def check_extract(data: Any, where: str, problems: Problems) -> ExtractChanges | None:
    """Return the extraction changes of a JSON object (or TOML table); record every problem.

    Names and kinds are checked here; the ranges by the device against its settings.
    """
    if not isinstance(data, dict):
        problems.add(f"{where}: an object is required, found {show(data)}")
        return None
    start = len(problems.items)
    check_keys(data, where, set(), set(EXTRACT_FIELDS), problems)
    values = []
    for key, value in data.items():
        kind = EXTRACT_FIELDS.get(key) if isinstance(key, str) else None
        if kind is not None:
            values.append((key, _setting(value, f"{where}.{key}", kind, problems)))
    return None if len(problems.items) > start else ExtractChanges(tuple(values))


def parse_extract_text(text: str) -> ExtractChanges:
    """Return the changes written ``KEY=VALUE[,KEY=VALUE]`` (a command line's form).

    Values are JSON where they parse as JSON (numbers, true, false, null), else text.

    Raises:
        ArgsError: listing every problem.
    """
    problems = Problems()
    data: dict[str, Any] = {}
    for item in filter(None, (part.strip() for part in text.split(","))):
        key, sep, raw = item.partition("=")
        if not sep or not key.strip():
            problems.add(f"extract: {show(item)} is not KEY=VALUE")
            continue
        try:
            data[key.strip()] = json.loads(raw.strip())
        except ValueError:
            data[key.strip()] = raw.strip()
    changes = check_extract(data, "extract", problems)
    if problems.items or changes is None:
        raise ArgsError("extract", problems.items)
    return changes


def extract_problems(settings: Mapping[str, Any]) -> list[str]:
    """Return every value of a whole set of extraction settings that is out of its range.

    The one range check of the extraction: the device applies it to its settings (as
    configured, or changed for a scan); the host to a device's configured settings (its
    WELCOME) with a scan's changes, so a scan beyond them is refused before it exists.

    Args:
        settings: a value for every field of :data:`EXTRACT_FIELDS`, of its kind.

    Returns:
        One line per problem (empty when the settings are usable).
    """
    s, full = settings, EXTRACT_FULL_SCALE
    problems = []
    if s["threshold"] is not None and not 0 <= s["threshold"] < full:
        problems.append(f"threshold {s['threshold']} is not in 0..{full - 1} (or None for Otsu)")
    if not 0 < s["power"] <= 8:
        problems.append(f"power {s['power']} is not in (0, 8]")
    if not 1 <= s["min_peak"] <= full:
        problems.append(f"min_peak {s['min_peak']} is not in 1..{full}")
    if s["method"] not in EXTRACT_METHODS:
        problems.append(f"method {s['method']!r} is not one of {', '.join(EXTRACT_METHODS)}")
    if s["run_choice"] not in EXTRACT_RUN_CHOICES:
        choices = ", ".join(EXTRACT_RUN_CHOICES)
        problems.append(f"run_choice {s['run_choice']!r} is not one of {choices}")
    ranges = {
        "background_opening_px": (0, _MAX_OPENING_PX),
        "false_points_per_frame": (1e-12, 1),
        "min_chain_px": (1, 1000),
        "max_row_jump_px": (0, 100),
    }
    problems += [
        f"{key} {s[key]} is not in {low}..{high}"
        for key, (low, high) in ranges.items()
        if not low <= s[key] <= high
    ]
    if not 1 <= s["min_width_px"] <= s["max_width_px"] <= full:
        problems.append(
            f"min_width_px {s['min_width_px']} and max_width_px {s['max_width_px']}"
            f" do not satisfy 1 <= min_width_px <= max_width_px <= {full}"
        )
    more = {"smooth_sigma_px": 50, "margin_px": _MAX_MARGIN_PX, "bridge_px": _MAX_BRIDGE_PX}
    problems += [
        f"{key} {s[key]} is not in 0..{high}"
        for key, high in more.items()
        if not 0 <= s[key] <= high
    ]
    return problems


# --- the operations ---------------------------------------------------------------------


@dataclass(frozen=True)
class NoArgs:
    """Arguments of an operation that takes none (grab_grid, pause, status, ...)."""


@dataclass(frozen=True)
class PreviewArgs:
    """``preview``: the laser on during the frame; the stripe extracted too."""

    laser: bool = False
    stripe: bool = False


@dataclass(frozen=True)
class ExposureArgs:
    """``exposure``: report the exposure, or set it to ``exposure_us``."""

    exposure_us: int | None = None


@dataclass(frozen=True)
class FetchArgs:
    """``fetch``: send the byte ranges ``[offset, length]`` of a kept transfer again."""

    transfer: int
    ranges: tuple[tuple[int, int], ...]


@dataclass(frozen=True)
class MoveArgs:
    """``move``: put one axis at ``position`` (mm for the lift, deg for the turntable)."""

    axis: str
    position: float


@dataclass(frozen=True)
class ScanArgs:
    """``scan``: acquire ``plan`` (None: the device's default) except the indices in ``have``.

    ``extract`` changes the device's configured extraction settings for this scan.
    ``colour`` asks for each point's sRGB colour (only of a device whose WELCOME says
    ``"colour": true``; the host leaves the key out otherwise, so older devices work).
    """

    target: str
    plan: ScanPlan | None = None
    have: tuple[int, ...] = ()
    extract: ExtractChanges | None = None
    colour: bool = False


@dataclass(frozen=True)
class EstimateArgs:
    """``estimate``: how long acquiring ``plan`` (None: the device's default) would take."""

    target: str
    plan: ScanPlan | None = None


def _preview(args: dict[str, Any], limits: DeviceLimits, problems: Problems) -> PreviewArgs:
    check_keys(args, "preview", set(), {"laser", "stripe"}, problems)
    laser = check_bool(args.get("laser", False), "preview.laser", problems)
    stripe = check_bool(args.get("stripe", False), "preview.stripe", problems)
    return PreviewArgs(bool(laser), bool(stripe))


def _exposure(args: dict[str, Any], limits: DeviceLimits, problems: Problems) -> ExposureArgs:
    check_keys(args, "exposure", set(), {"exposure_us"}, problems)
    if "exposure_us" not in args:
        return ExposureArgs()
    value = check_int(
        args["exposure_us"], "exposure.exposure_us", 1, limits.max_exposure_us, problems
    )
    return ExposureArgs(value)


def _fetch(args: dict[str, Any], limits: DeviceLimits, problems: Problems) -> FetchArgs:
    check_keys(args, "fetch", {"transfer", "ranges"}, set(), problems)
    transfer = check_int(args.get("transfer", MISSING), "fetch.transfer", 0, 2**32 - 1, problems)
    items = check_list(
        args.get("ranges", MISSING), "fetch.ranges", limits.max_fetch_ranges, problems
    )
    ranges: list[tuple[int, int]] = []
    for k, item in enumerate(items or []):
        where = f"fetch.ranges[{k}]"
        if not (isinstance(item, list) and len(item) == 2):
            problems.add(f"{where}: [offset, length] is required, found {show(item)}")
            continue
        offset = check_int(item[0], f"{where}[0]", 0, limits.max_transfer_bytes, problems)
        length = check_int(item[1], f"{where}[1]", 0, limits.max_fetch_bytes, problems)
        if offset is not None and length is not None:
            ranges.append((offset, length))
    if sum(length for _, length in ranges) > limits.max_fetch_bytes:
        problems.add(f"fetch.ranges: at most {limits.max_fetch_bytes} bytes at once", limit=True)
    return FetchArgs(transfer or 0, tuple(ranges))


def _move(args: dict[str, Any], limits: DeviceLimits, problems: Problems) -> MoveArgs:
    check_keys(args, "move", {"axis", "position"}, set(), problems)
    axis = check_choice(args.get("axis", MISSING), "move.axis", AXES, problems)
    bound = limits.max_z_mm if axis == "lift" else limits.max_abs_angle_deg
    position = check_number(args.get("position", MISSING), "move.position", -bound, bound, problems)
    return MoveArgs(axis or "", position or 0.0)


def _scan(args: dict[str, Any], limits: DeviceLimits, problems: Problems) -> ScanArgs:
    check_keys(args, "scan", {"target"}, {"plan", "have", "extract", "colour"}, problems)
    target = check_choice(args.get("target", MISSING), "scan.target", TARGETS, problems)
    plan = None if args.get("plan") is None else check_plan(args["plan"], limits, problems)
    have: list[int] = []
    items = check_list(args.get("have") or [], "scan.have", limits.max_views, problems)
    for k, item in enumerate(items or []):
        if not (is_int(item) and 0 <= item < limits.max_views):
            problems.add(f"scan.have[{k}]: a view index in 0..{limits.max_views - 1} is required")
            break
        have.append(item)
    extract = (
        None
        if args.get("extract") is None
        else check_extract(args["extract"], "scan.extract", problems)
    )
    colour = check_bool(args.get("colour", False), "scan.colour", problems)
    return ScanArgs(target or "", plan, tuple(have), extract, bool(colour))


def _estimate(args: dict[str, Any], limits: DeviceLimits, problems: Problems) -> EstimateArgs:
    check_keys(args, "estimate", {"target"}, {"plan"}, problems)
    target = check_choice(args.get("target", MISSING), "estimate.target", TARGETS, problems)
    plan = None if args.get("plan") is None else check_plan(args["plan"], limits, problems)
    return EstimateArgs(target or "", plan)


def _none(op: str) -> Callable[[dict[str, Any], DeviceLimits, Problems], NoArgs]:
    def parse(args: dict[str, Any], limits: DeviceLimits, problems: Problems) -> NoArgs:
        check_keys(args, op, set(), set(), problems)
        return NoArgs()

    return parse


@dataclass(frozen=True)
class OpSpec:
    """One operation: its name, its argument type, whether it runs on the worker thread."""

    name: str
    args_type: type
    long: bool
    parse: Callable[[dict[str, Any], DeviceLimits, Problems], Any]


OPS: dict[str, OpSpec] = {
    spec.name: spec
    for spec in (
        OpSpec("grab_grid", NoArgs, True, _none("grab_grid")),
        OpSpec("preview", PreviewArgs, True, _preview),
        OpSpec("scan", ScanArgs, True, _scan),
        OpSpec("fetch", FetchArgs, False, _fetch),
        OpSpec("move", MoveArgs, False, _move),
        OpSpec("pause", NoArgs, False, _none("pause")),
        OpSpec("resume", NoArgs, False, _none("resume")),
        OpSpec("abort", NoArgs, False, _none("abort")),
        OpSpec("exposure", ExposureArgs, False, _exposure),
        OpSpec("status", NoArgs, False, _none("status")),
        OpSpec("estimate", EstimateArgs, False, _estimate),
        OpSpec("shutdown", NoArgs, False, _none("shutdown")),
    )
}
"""Every operation the device serves, by name."""


def parse_args(op: Any, args: Any, limits: DeviceLimits) -> Any:
    """Return the typed arguments of request ``op``; raise ArgsError listing every problem.

    Raises:
        UnknownOp: ``op`` is not an operation of :data:`OPS`.
        ArgsError: the arguments are unusable (``problems`` lists each reason).
    """
    spec = OPS.get(op) if isinstance(op, str) else None
    if spec is None:
        raise UnknownOp(f"unknown operation {show(op)}: the device serves {', '.join(OPS)}")
    problems = Problems()
    if not isinstance(args, dict):
        problems.add(f"{spec.name}: arguments must be an object, found {show(args)}")
        raise ArgsError(spec.name, problems.items)
    parsed = spec.parse(args, limits, problems)
    if problems.items:
        raise ArgsError(spec.name, problems.items, "limit" if problems.over_limit else "bad-args")
    return parsed


OPTIONAL_FLAGS = frozenset({"colour"})
"""Request flags added after protocol 3 first shipped: sent only when true."""


def request_args(args: Any) -> dict[str, Any]:
    """Return the JSON arguments of a request from its typed arguments (host side)."""
    out: dict[str, Any] = {}
    for item in fields(args):
        value = getattr(args, item.name)
        if value is None or (item.name in OPTIONAL_FLAGS and value is False):
            # Left out, not false: a device from before the flag would refuse the key.
            continue
        if isinstance(value, ScanPlan | ExtractChanges):
            value = value.to_wire()
        elif isinstance(value, tuple):
            value = [list(v) if isinstance(v, tuple) else v for v in value]
        out[item.name] = value
    return out
