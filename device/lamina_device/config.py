"""The scanner box's configuration: one TOML file with pins, mechanics, camera and safety.

The file is validated as a whole before anything moves, and every problem is listed
at once (unknown key, missing value, wrong type, value out of range, a pin used
twice), because a wrong steps-per-revolution or a swapped pin silently distorts
scans or drives the wrong motor. The schema is the dataclasses below: each field's
type annotation is the expected TOML type and its metadata the allowed range.
"""

from __future__ import annotations

import math
import re
import tomllib
import typing
from dataclasses import MISSING, dataclass, field, fields, is_dataclass
from importlib import resources
from pathlib import Path
from typing import Any

from lamina_device.extract import ExtractSettings, changed_settings
from lamina_shared.errors import LaminaError
from lamina_shared.limits import DeviceLimits
from lamina_shared.ops import Problems, check_extract, check_plan
from lamina_shared.types import NEXT_TURN_MISMATCH_DEG, OFF_FRAMES, LiftReference

DEFAULT_CONFIG_NAME = "default_config.toml"
MAX_SPIN_STEP_HZ = 10_000
"""Highest step rate of a continuous turn: lgpio's software PWM runs from 0.1 to 10 kHz."""
BCM_PINS = range(0, 28)  # GPIO0..GPIO27 on the Pi's 40-pin header
MICROSTEPS = (1, 2, 4, 8, 16, 32, 64, 128, 256)


class ConfigError(LaminaError, ValueError):
    """The configuration file is unusable; ``problems`` lists everything wrong with it."""

    def __init__(self, source: str, problems: list[str]) -> None:
        self.source = source
        self.problems = problems
        count = f"{len(problems)} problem" + ("s" if len(problems) != 1 else "")
        super().__init__(f"config {source}: {count}: " + "; ".join(problems))


def _spec(
    low: float | None = None,
    high: float | None = None,
    choices: tuple[Any, ...] | None = None,
    pin: bool = False,
    default: Any = MISSING,
) -> Any:
    """Declare a config value with its allowed range (dataclass field metadata).

    Without ``default`` the value is required; a key added after configurations were in
    use has one, so a box's existing file stays valid (and keeps the older behaviour).
    """
    meta = {"low": low, "high": high, "choices": choices, "pin": pin}
    if default is MISSING:
        return field(metadata=meta)
    return field(default=default, metadata=meta)


@dataclass(frozen=True)
class LaserConfig:
    """The laser diode's switching transistor."""

    pin: int = _spec(pin=True)
    active_high: bool = _spec()


@dataclass(frozen=True)
class DriverConfig:
    """Pins and motor data shared by both step/dir stepper axes."""

    step_pin: int = _spec(pin=True)
    dir_pin: int = _spec(pin=True)
    enable_pin: int = _spec(pin=True)
    # A4988, DRV8825 and TMC2209 enable on a low EN line.
    enable_active_high: bool = _spec()
    # Which DIR level moves the axis the positive way (counter-clockwise, or up).
    dir_high_positive: bool = _spec()
    full_steps_per_rev: int = _spec(1, 10_000)
    microsteps: int = _spec(choices=MICROSTEPS)
    settle_s: float = _spec(0.0, 10.0)


@dataclass(frozen=True)
class TurntableConfig(DriverConfig):
    """The turntable: ``gear_ratio`` motor turns per table turn."""

    gear_ratio: float = _spec(0.01, 1000.0)
    start_speed_deg_s: float = _spec(0.01, 3600.0)
    max_speed_deg_s: float = _spec(0.01, 3600.0)
    accel_deg_s2: float = _spec(0.01, 100_000.0)
    backlash_deg: float = _spec(0.0, 30.0)
    # Continuous scans (issue 22): the table's constant speed through each section, its
    # step pulses timed by the pin factory (lgpio); 0 leaves the box stop-and-go only.
    continuous_speed_deg_s: float = _spec(0.0, 3600.0, default=0.0)
    # Where a continuous view's laser-off frames come from. "interleaved": the frames just
    # before and after its laser-on frame (one turn a section; the table has turned 6
    # degrees each way, so room light on fine relief can pass for stripe). "next-turn":
    # one frame at the same angle a turn later (a second turn a section, as exact as a
    # stop-and-go view's pair).
    continuous_off_frames: str = _spec(choices=OFF_FRAMES, default="interleaved")
    # Slow the table during each lift move so that a view of the next section comes round
    # as the lift settles (no wait for it: the 400 mm leg 86.8 -> 82.9 s). Off by default:
    # on a gear that turns short of its count it measured worse (the host's correction of
    # the shortfall depends on which turn each view falls in), though better without one.
    continuous_retime: bool = _spec(default=False)


def pulse_rate(rate_sps: float) -> float:
    """Return the step rate nearest ``rate_sps`` whose period is a whole microsecond.

    lgpio times pulses in microseconds: a rate of such a period is sent exactly, so the
    step clock that counts it is exact too.
    """
    return 1e6 / max(1, round(1e6 / rate_sps))


def continuous_turn_us(table: TurntableConfig) -> float:
    """Return how long a continuous turn takes at the step rate lgpio sends (microseconds)."""
    steps = 360.0 * turntable_steps_per_deg(table)
    return steps / pulse_rate(table.continuous_speed_deg_s * steps / 360.0) * 1e6


def next_turn_frame_us(table: TurntableConfig, frame_duration_us: int) -> int:
    """Return the frame period nearest ``frame_duration_us`` that divides a continuous turn."""
    turn_us = continuous_turn_us(table)
    return round(turn_us / max(1, round(turn_us / frame_duration_us)))


def next_turn_problem(table: TurntableConfig, camera: CameraConfig) -> str | None:
    """Return why laser-off frames a turn later would not meet their laser-on frames' angles.

    The camera streams a frame every ``frame_duration_us``; the frame a turn after a
    laser-on frame sees the same angle only when a turn (at the step rate lgpio sends) is
    a whole number of frame periods. Returns None when it is, to
    :data:`NEXT_TURN_MISMATCH_DEG`, else the ``frame_duration_us`` that makes it so
    (:func:`next_turn_frame_us`).
    """
    turn_us = continuous_turn_us(table)
    frames = turn_us / camera.frame_duration_us
    whole = max(1, round(frames))
    mismatch_deg = abs(frames - whole) * 360.0 / frames
    if mismatch_deg <= NEXT_TURN_MISMATCH_DEG:
        return None
    return (
        f'[turntable] continuous_off_frames "next-turn": a turn of the table takes '
        f"{turn_us / 1000:.1f} ms, {frames:.2f} frames of {camera.frame_duration_us} us, so a "
        f"frame a turn later misses the angle by {mismatch_deg:.2f} degrees: set [camera] "
        f"frame_duration_us = {next_turn_frame_us(table, camera.frame_duration_us)} "
        f"({whole} frames a turn)"
    )


def turntable_steps_per_deg(config: TurntableConfig) -> float:
    """Return the turntable's microsteps per table degree."""
    return config.full_steps_per_rev * config.microsteps * config.gear_ratio / 360.0


@dataclass(frozen=True)
class LiftConfig(DriverConfig):
    """The lift: a lead screw (``lead_mm`` per screw turn) behind ``gear_ratio``."""

    gear_ratio: float = _spec(0.01, 1000.0)
    lead_mm: float = _spec(0.01, 100.0)
    start_speed_mm_s: float = _spec(0.001, 200.0)
    max_speed_mm_s: float = _spec(0.001, 200.0)
    accel_mm_s2: float = _spec(0.001, 10_000.0)
    min_mm: float = _spec(-1000.0, 1000.0)
    max_mm: float = _spec(-1000.0, 1000.0)
    # The height at which the limit switch trips; the lift homes down onto it.
    home_mm: float = _spec(-1000.0, 1000.0)
    homing_speed_mm_s: float = _spec(0.001, 50.0)
    # How far above home to leave the fast move and creep onto the switch.
    homing_slow_zone_mm: float = _spec(0.0, 100.0)
    limit_pin: int = _spec(pin=True)


@dataclass(frozen=True)
class CameraConfig:
    """Camera backend, exposure at start and the range the host may set it within."""

    backend: str = _spec(choices=("picamera2",))
    width: int = _spec(64, 4608)
    height: int = _spec(48, 3456)
    exposure_us: int = _spec(10, 1_000_000)
    min_exposure_us: int = _spec(10, 1_000_000)
    max_exposure_us: int = _spec(10, 1_000_000)
    gain: float = _spec(1.0, 16.0)
    frame_duration_us: int = _spec(1000, 1_000_000)
    buffer_count: int = _spec(2, 8)
    timeout_s: float = _spec(0.05, 30.0)
    # The rolling shutter's read-out of all rows (first row to last); 0: one frame period.
    readout_us: int = _spec(0, 1_000_000, default=0)

    @property
    def readout_s(self) -> float:
        """Return the time from the first row's exposure to the last row's, in seconds."""
        return (self.readout_us or self.frame_duration_us) * 1e-6


@dataclass(frozen=True)
class SafetyConfig:
    """Automatic laser shut-off (thesis appendix A)."""

    laser_max_on_s: float = _spec(0.01, 60.0)
    link_silence_s: float = _spec(0.1, 3600.0)


@dataclass(frozen=True)
class BoardConfig:
    """The printed calibration chessboard lying in the laser plane."""

    inner_corners: tuple[int, int] = _spec(2, 100)
    square_mm: float = _spec(0.1, 100.0)
    origin_mm: tuple[float, float] = _spec(-1000.0, 1000.0)


@dataclass(frozen=True)
class CylinderConfig:
    """The calibration cylinder."""

    diameter_mm: float = _spec(1.0, 500.0)


@dataclass(frozen=True)
class PlanConfig:
    """The default scans the device offers the host."""

    sections: int = _spec(1, 10_000)
    pitch_mm: float = _spec(0.01, 100.0)
    views: int = _spec(1, 360)
    cylinder_views: int = _spec(1, 360)
    # Older files scanned the cylinder at one height: they keep doing so.
    cylinder_sections: int = _spec(1, 100, default=1)
    cylinder_pitch_mm: float = _spec(0.01, 100.0, default=3.0)


@dataclass(frozen=True)
class DeviceConfig:
    """The whole configuration file, one field per TOML table."""

    laser: LaserConfig
    turntable: TurntableConfig
    lift: LiftConfig
    camera: CameraConfig
    safety: SafetyConfig
    board: BoardConfig
    cylinder: CylinderConfig
    plan: PlanConfig
    device_id: str | None = None
    """Optional ``[device] id``: names this box in the WELCOME instead of the Pi's serial."""
    extract: ExtractSettings = field(default_factory=ExtractSettings)
    """Optional ``[extract]``: the stripe extraction's settings (a scan may change them)."""
    lift_reference: LiftReference | None = None
    """Optional ``[lift_reference]``: the calibration cylinder's grooves that calibrate the
    lift (hardware/calibration-cylinder.md); left out, the lift is trusted."""


DEVICE_ID = re.compile(r"[A-Za-z0-9._-]{1,64}")
OPTIONAL_TABLES = ("device", "extract", "lift_reference")


def default_config_path() -> Path:
    """Return the configuration shipped with the package (matches hardware/ wiring)."""
    return Path(str(resources.files("lamina_device") / DEFAULT_CONFIG_NAME))


def _type_name(kind: Any) -> str:
    names = {int: "an integer", float: "a number", bool: "true or false", str: "a string"}
    if typing.get_origin(kind) is tuple:
        item = {int: "integers", float: "numbers"}[typing.get_args(kind)[0]]
        return f"a list of {len(typing.get_args(kind))} {item}"
    return names[kind]


def _convert_scalar(value: Any, kind: Any) -> Any:
    """Return ``value`` as ``kind`` or raise TypeError (ints are accepted as floats)."""
    if kind is bool:
        if isinstance(value, bool):
            return value
    elif kind is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
    elif kind is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
    elif kind is str and isinstance(value, str):
        return value
    raise TypeError


def _convert(value: Any, kind: Any) -> Any:
    if typing.get_origin(kind) is tuple:
        items = typing.get_args(kind)
        if not isinstance(value, list) or len(value) != len(items):
            raise TypeError
        return tuple(_convert_scalar(v, k) for v, k in zip(value, items, strict=True))
    return _convert_scalar(value, kind)


def _range_problem(value: Any, meta: dict[str, Any]) -> str | None:
    """Return why ``value`` is outside the field's allowed values, or None."""
    if meta["choices"] is not None and value not in meta["choices"]:
        return f"{value!r} is not one of {', '.join(map(repr, meta['choices']))}"
    if meta["pin"] and value not in BCM_PINS:
        return f"{value} is not a GPIO pin number (BCM 0..27)"
    numbers = value if isinstance(value, tuple) else (value,)
    low, high = meta["low"], meta["high"]
    for number in numbers:
        if isinstance(number, float) and not math.isfinite(number):
            return f"{number} is not a finite number"
        if isinstance(number, bool) or low is None:
            continue
        if not low <= number <= high:
            return f"{value} is outside {low:g}..{high:g}"
    return None


def _build_table(cls: type, name: str, table: Any, problems: list[str]) -> Any:
    """Return ``cls`` built from one TOML table, appending every problem found."""
    if not isinstance(table, dict):
        problems.append(f"[{name}]: expected a table of settings")
        return None
    hints = typing.get_type_hints(cls)
    known = {f.name: f for f in fields(cls)}
    problems.extend(f"[{name}] {key}: unknown key" for key in table if key not in known)
    values: dict[str, Any] = {}
    for key, spec in known.items():
        if key not in table:
            if spec.default is MISSING:
                problems.append(f"[{name}] {key}: missing value ({_type_name(hints[key])})")
            continue
        try:
            value = _convert(table[key], hints[key])
        except TypeError:
            problems.append(
                f"[{name}] {key}: expected {_type_name(hints[key])}, got {table[key]!r}"
            )
            continue
        why = _range_problem(value, dict(spec.metadata))
        if why is not None:
            problems.append(f"[{name}] {key}: {why}")
            continue
        values[key] = value
    required = [key for key, spec in known.items() if spec.default is MISSING]
    return cls(**values) if all(key in values for key in required) else None


def _device_id(table: Any, problems: list[str]) -> str | None:
    """Return the optional ``[device] id``, appending what is wrong with the table."""
    if table is None:
        return None
    if not isinstance(table, dict) or set(table) - {"id"}:
        problems.append("[device]: only the key id is allowed")
        return None
    value = table.get("id")
    if not isinstance(value, str) or not DEVICE_ID.fullmatch(value):
        problems.append("[device] id: 1 to 64 letters, digits, '.', '_' or '-' are required")
        return None
    return value


def _extract(table: Any, problems: list[str]) -> ExtractSettings | None:
    """Return the optional ``[extract]`` settings (defaults for the keys left out).

    The keys and their kinds are the ``scan`` request's ``extract`` schema; the ranges
    are :func:`~lamina_device.extract.settings_problems`'.
    """
    if table is None:
        return ExtractSettings()
    found = Problems()
    changes = check_extract(table, "[extract]", found)
    problems.extend(found.items)
    if changes is None:
        return None
    settings, wrong = changed_settings(ExtractSettings(), changes.as_dict())
    problems.extend(f"[extract] {text}" for text in wrong)
    return settings


LIFT_REFERENCE_KEYS = ("marks_mm", "spacing_mm", "flank_slope", "depth_mm")


def _lift_reference(table: Any, problems: list[str]) -> LiftReference | None:
    """Return the optional ``[lift_reference]``, appending what is wrong with the table."""
    if table is None:
        return None
    if not isinstance(table, dict) or set(table) != set(LIFT_REFERENCE_KEYS):
        problems.append(f"[lift_reference]: the keys {', '.join(LIFT_REFERENCE_KEYS)} are required")
        return None
    try:
        return LiftReference.from_dict(table)
    except (TypeError, ValueError) as exc:
        problems.append(f"[lift_reference]: {exc}")
        return None


def _pin_problems(data: dict[str, Any]) -> list[str]:
    """Return one problem per GPIO pin claimed by more than one setting."""
    owners: dict[int, list[str]] = {}
    for cls_field in fields(DeviceConfig):
        table = data.get(cls_field.name)
        if not isinstance(table, dict):
            continue
        kind = typing.get_type_hints(DeviceConfig)[cls_field.name]
        if not is_dataclass(kind):  # [lift_reference] holds no pins
            continue
        for spec in fields(kind):
            value = table.get(spec.name)
            if spec.metadata.get("pin") and isinstance(value, int) and not isinstance(value, bool):
                owners.setdefault(value, []).append(f"[{cls_field.name}] {spec.name}")
    return [
        f"GPIO{pin} is used twice: by {' and '.join(users)}"
        for pin, users in sorted(owners.items())
        if len(users) > 1
    ]


def _consistency_problems(config: DeviceConfig) -> list[str]:
    """Return problems that involve more than one value."""
    problems = []
    lift, table, camera = config.lift, config.turntable, config.camera
    if lift.min_mm >= lift.max_mm:
        problems.append(f"[lift] min_mm {lift.min_mm} must be below max_mm {lift.max_mm}")
    if lift.home_mm > lift.min_mm:
        problems.append(f"[lift] home_mm {lift.home_mm} must not be above min_mm {lift.min_mm}")
    if lift.start_speed_mm_s > lift.max_speed_mm_s:
        problems.append("[lift] start_speed_mm_s must not exceed max_speed_mm_s")
    if table.start_speed_deg_s > table.max_speed_deg_s:
        problems.append("[turntable] start_speed_deg_s must not exceed max_speed_deg_s")
    if not camera.min_exposure_us <= camera.exposure_us <= camera.max_exposure_us:
        problems.append(
            f"[camera] exposure_us {camera.exposure_us} must lie within min_exposure_us.."
            f"max_exposure_us ({camera.min_exposure_us}..{camera.max_exposure_us})"
        )
    if camera.max_exposure_us > camera.frame_duration_us:
        problems.append(
            f"[camera] max_exposure_us {camera.max_exposure_us} must fit in frame_duration_us "
            f"{camera.frame_duration_us}"
        )
    if camera.exposure_us > camera.frame_duration_us:
        problems.append(
            f"[camera] exposure_us {camera.exposure_us} must fit in frame_duration_us "
            f"{camera.frame_duration_us}"
        )
    if camera.readout_us > camera.frame_duration_us:
        problems.append(
            f"[camera] readout_us {camera.readout_us} must fit in frame_duration_us "
            f"{camera.frame_duration_us}"
        )
    spin_hz = table.continuous_speed_deg_s * turntable_steps_per_deg(table)
    if spin_hz > MAX_SPIN_STEP_HZ:
        problems.append(
            f"[turntable] continuous_speed_deg_s {table.continuous_speed_deg_s:g} asks for "
            f"{spin_hz:.0f} steps/s, beyond the {MAX_SPIN_STEP_HZ} the pin factory times "
            "(lgpio's PWM): lower it or the microsteps"
        )
    if 0.0 < table.continuous_speed_deg_s < table.start_speed_deg_s:
        problems.append("[turntable] continuous_speed_deg_s must not be below start_speed_deg_s")
    if (
        table.continuous_off_frames == "next-turn"
        and table.continuous_speed_deg_s > 0.0
        and (problem := next_turn_problem(table, camera))
    ):
        problems.append(problem)
    plan = config.plan
    found = Problems()
    for sections, pitch_mm, views in (
        (plan.sections, plan.pitch_mm, plan.views),
        (plan.cylinder_sections, plan.cylinder_pitch_mm, plan.cylinder_views),
    ):
        regular = {"sections": sections, "pitch_mm": pitch_mm, "views": views}
        check_plan({"regular": regular}, DeviceLimits(), found)
    # The device's limits hold for its default scans too (the WELCOME advertises both).
    problems.extend(
        f"[plan] {text.replace('plan.regular.', '').replace('plan.regular', 'default scan')}"
        for text in dict.fromkeys(found.items)
    )
    reference = config.lift_reference
    if reference is not None and not all(
        lift.min_mm <= z <= lift.max_mm for z in reference.marks_mm
    ):
        problems.append(
            f"[lift_reference] marks_mm {list(reference.marks_mm)} must lie within the lift's "
            f"{lift.min_mm:g}..{lift.max_mm:g} mm"
        )
    top_mm = (config.plan.sections - 1) * config.plan.pitch_mm
    if not (lift.min_mm <= 0.0 and top_mm <= lift.max_mm):
        problems.append(
            f"[plan] the default scan spans 0..{top_mm:g} mm, outside the lift's "
            f"{lift.min_mm:g}..{lift.max_mm:g} mm"
        )
    return problems


def parse_config(data: dict[str, Any], source: str = "<config>") -> DeviceConfig:
    """Validate a parsed TOML document and return the configuration.

    Raises:
        ConfigError: listing every problem found.
    """
    problems: list[str] = []
    tables = {
        f.name: typing.get_type_hints(DeviceConfig)[f.name]
        for f in fields(DeviceConfig)
        if f.name not in ("device_id", "extract", "lift_reference")
    }
    problems.extend(
        f"[{key}]: unknown section"
        for key in data
        if key not in tables and key not in OPTIONAL_TABLES
    )
    device_id = _device_id(data.get("device"), problems)
    extract = _extract(data.get("extract"), problems)
    lift_reference = _lift_reference(data.get("lift_reference"), problems)
    built: dict[str, Any] = {}
    for name, cls in tables.items():
        if name not in data:
            problems.append(f"[{name}]: missing section")
            continue
        built[name] = _build_table(cls, name, data[name], problems)
    problems.extend(_pin_problems(data))
    if not problems:
        config = DeviceConfig(
            **built, device_id=device_id, extract=extract or ExtractSettings(),
            lift_reference=lift_reference,
        )  # fmt: skip
        problems.extend(_consistency_problems(config))
        if not problems:
            return config
    raise ConfigError(source, problems)


def load_config(path: Path | str | None = None) -> DeviceConfig:
    """Read and validate the TOML file at ``path`` (the packaged default if None).

    Raises:
        ConfigError: the file is missing, unreadable, not TOML, or has problems.
    """
    path = Path(path) if path is not None else default_config_path()
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as exc:
        raise ConfigError(str(path), [f"cannot read it: {exc.strerror or exc}"]) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(path), [f"not valid TOML: {exc}"]) from None
    return parse_config(data, str(path))


def check_config(path: Path | str) -> list[str]:
    """Return every problem with the configuration at ``path`` (empty when it is usable)."""
    try:
        load_config(path)
    except ConfigError as exc:
        return exc.problems
    return []
