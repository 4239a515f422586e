"""The link's messages other than requests and replies: HELLO, WELCOME, ACK, HEARTBEAT, EVENT.

:mod:`lamina_shared.ops` types the requests and :mod:`lamina_shared.replies` the
operations' replies; this module types what else crosses the line, in the same style:
one frozen dataclass per message, ``to_wire()`` giving the JSON body its sender sends
and ``from_wire()`` reading one back, or raising
:class:`MessageError` listing every problem found at once. Both ends use these classes,
so the device and the host cannot disagree on a field's name or kind
(``shared/PROTOCOL.md`` names the bodies).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

from lamina_shared.limits import DeviceLimits, show
from lamina_shared.ops import (
    MAX_SHOWN_PROBLEMS,
    MISSING,
    ExtractChanges,
    Problems,
    check_bool,
    check_choice,
    check_int,
    check_list,
    check_number,
    is_int,
)
from lamina_shared.protocol import PROTOCOL_VERSION, ROW_SCALE
from lamina_shared.types import OFF_FRAMES, SCAN_MODES, BoardSpec, LiftReference, ScanPlan

MAX_LOST_SEQS = 64
"""Earlier plan indices one ACK names as lost (the device resends them at once)."""
MAX_SHORT_TEXT = 1_000
"""Longest text field of a WELCOME or EVENT a reader keeps (a name, a description)."""
MAX_COUNT = 2**32 - 1
"""Largest request id, segment number or view count (they travel as u32)."""
HOST_LIMITS = DeviceLimits()
"""This version's limits: the host refuses a WELCOME beyond them (an image side)."""


class MessageError(ValueError):
    """A received message is unusable; ``problems`` lists every reason found."""

    def __init__(self, kind: str, problems: list[str]) -> None:
        self.kind, self.problems = kind, problems
        shown = problems[:MAX_SHOWN_PROBLEMS]
        more = len(problems) - len(shown)
        super().__init__("; ".join(shown) + (f"; and {more} more" if more else ""))


def check_text(data: dict[str, Any], key: str, where: str, problems: Problems, default: Any) -> Any:
    """Return the string ``data[key]`` (``default`` when absent); record any other kind."""
    value = data.get(key, MISSING)
    if value is MISSING:
        return default
    if not isinstance(value, str) or len(value) > MAX_SHORT_TEXT:
        problems.add(f"{where}.{key}: a text of at most {MAX_SHORT_TEXT} characters is required")
        return default
    return value


def _object(data: dict[str, Any], key: str, where: str, problems: Problems) -> dict[str, Any]:
    """Return the JSON object ``data[key]`` ({} when absent or null); record any other kind."""
    value = data.get(key)
    if value is None:
        return {}
    if not isinstance(value, dict):
        problems.add(f"{where}.{key}: an object is required, found {show(value)}")
        return {}
    return value


def object_body(body: Any, kind: str) -> dict[str, Any]:
    """Return ``body`` if it is a JSON object; else raise MessageError naming ``kind``."""
    if not isinstance(body, dict):
        raise MessageError(kind, [f"{kind.lower()}: an object is required, found {show(body)}"])
    return body


def require_keys(
    data: dict[str, Any], keys: tuple[str, ...], where: str, problems: Problems
) -> None:
    """Record each of ``keys`` that ``data`` lacks."""
    for key in keys:
        if key not in data:
            problems.add(f"{where}: {key} is required")


def _optional_number(
    data: dict[str, Any], key: str, where: str, problems: Problems, low: float = -math.inf
) -> float | None:
    """Return the finite number ``data[key]`` (None when absent or null); record any other."""
    value = data.get(key)
    if value is None:
        return None
    return check_number(value, f"{where}.{key}", low, math.inf, problems)


# --- HELLO and HEARTBEAT ----------------------------------------------------------------

MAX_SESSION_CHARS = 64
"""Longest session a device keeps; a longer one (or one not a text) is no session."""


@dataclass(frozen=True)
class Hello:
    """HELLO: a host (``session``, random per host process) asks for the device's WELCOME.

    A device answers a HELLO of another ``protocol`` with a WELCOME of the versions only.
    """

    session: str | None
    protocol: int = PROTOCOL_VERSION
    software: str = "lamina-host"

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON body the host sends."""
        return {"protocol": self.protocol, "software": self.software, "session": self.session}

    @classmethod
    def from_wire(cls, body: Any) -> Hello:
        """Return the HELLO a host sent.

        A ``session`` that is not a text of at most :data:`MAX_SESSION_CHARS` characters
        reads as none (the device then takes the host for a new one), never as a problem.

        Raises:
            MessageError: listing every problem (no usable ``protocol``, a bad ``software``).
        """
        data = object_body(body, "HELLO")
        problems = Problems()
        require_keys(data, ("protocol",), "hello", problems)
        protocol = check_int(
            data.get("protocol", MISSING), "hello.protocol", 0, MAX_COUNT, problems
        )
        software = check_text(data, "software", "hello", problems, "?")
        session = data.get("session")
        usable = isinstance(session, str) and len(session) <= MAX_SESSION_CHARS
        if problems.items or protocol is None:
            raise MessageError("HELLO", problems.items)
        return cls(session if usable else None, protocol, software)


DEVICE_STATES = ("idle", "busy", "paused")
"""What a device heartbeat says it is doing."""


@dataclass(frozen=True)
class DeviceHeartbeat:
    """HEARTBEAT from the device: its state, the request it runs, segments unacknowledged."""

    state: str
    request: int | None
    unacked: int
    uptime_s: float

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON body the device sends."""
        return {
            "state": self.state,
            "request": self.request,
            "unacked": self.unacked,
            "uptime_s": round(self.uptime_s, 3),
        }

    @classmethod
    def from_wire(cls, body: Any) -> DeviceHeartbeat:
        """Return the heartbeat a device sent.

        Raises:
            MessageError: listing every problem.
        """
        data = object_body(body, "HEARTBEAT")
        problems = Problems()
        beat = cls.read(data, "heartbeat", problems)
        if problems.items:
            raise MessageError("HEARTBEAT", problems.items)
        return beat

    @classmethod
    def read(cls, data: dict[str, Any], where: str, problems: Problems) -> DeviceHeartbeat:
        """Return the heartbeat's fields of ``data`` (also a ``status`` reply's), recording
        every problem in ``problems`` under ``where``."""
        require_keys(data, ("state", "request", "unacked", "uptime_s"), where, problems)
        state = check_choice(data.get("state", MISSING), f"{where}.state", DEVICE_STATES, problems)
        request = data.get("request", MISSING)
        request_id = (
            None
            if request is None
            else check_int(request, f"{where}.request", 0, MAX_COUNT, problems)
        )
        unacked = check_int(
            data.get("unacked", MISSING), f"{where}.unacked", 0, MAX_COUNT, problems
        )
        uptime = check_number(
            data.get("uptime_s", MISSING), f"{where}.uptime_s", 0.0, 1e12, problems
        )
        return cls(state or "idle", request_id, unacked or 0, uptime or 0.0)


@dataclass(frozen=True)
class HostHeartbeat:
    """HEARTBEAT from the host while a request is open: the host's ``session``."""

    session: str

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON body the host sends."""
        return {"session": self.session}

    @classmethod
    def from_wire(cls, body: Any) -> HostHeartbeat:
        """Return the heartbeat a host sent (:class:`MessageError` lists every problem)."""
        problems = Problems()
        session = _heartbeat_session(object_body(body, "HEARTBEAT"), problems)
        if problems.items:
            raise MessageError("HEARTBEAT", problems.items)
        return cls(session)


def _heartbeat_session(data: dict[str, Any], problems: Problems) -> str:
    """Return a host HEARTBEAT's ``session``, recording what is wrong with it."""
    require_keys(data, ("session",), "heartbeat", problems)
    session = data.get("session", MISSING)
    if session is not MISSING and not (
        isinstance(session, str) and len(session) <= MAX_SESSION_CHARS
    ):
        problems.add(
            f"heartbeat.session: a text of at most {MAX_SESSION_CHARS} characters is required"
        )
    return session if isinstance(session, str) else ""


# --- WELCOME ----------------------------------------------------------------------------


@dataclass(frozen=True)
class DeviceIdentity:
    """Which device it is (``serial``), what it images (``source``) and, for a turntable
    whose step count starts again when its program does, which run of the count its
    angles belong to (``count_since``); see PROTOCOL.md."""

    serial: str | None = None
    source: str | None = None
    count_since: str | None = None
    """A token new each time the device program starts, from a device whose table's
    angle is lost then (the box: no index sensor); None from one that starts its world
    afresh with it (the simulator, a replay)."""

    def to_wire(self) -> dict[str, str]:
        """Return the WELCOME ``identity`` object (fields the device knows)."""
        known = {"serial": self.serial, "source": self.source, "count_since": self.count_since}
        return {k: v for k, v in known.items() if v is not None}


@dataclass(frozen=True)
class AxesInfo:
    """The axes' soft limits (WELCOME ``axes``); None means no limit that way (or unknown).

    A device from before ``axes`` sends none: every field is then None and the host
    checks no travel (the device checks every request itself).
    """

    lift_min_mm: float | None = None
    lift_max_mm: float | None = None
    turntable_min_deg: float | None = None
    turntable_max_deg: float | None = None
    lift_step_mm: float | None = None
    """The lift's smallest move (one microstep); None for a lift without steps."""

    @property
    def continuous(self) -> bool:
        """Return True when the turntable turns without limit either way."""
        return self.turntable_min_deg is None and self.turntable_max_deg is None

    def to_wire(self) -> dict[str, Any]:
        """Return the WELCOME ``axes`` object (the lift's ``step`` only when it has one)."""
        lift: dict[str, Any] = {"unit": "mm", "min": self.lift_min_mm, "max": self.lift_max_mm}
        if self.lift_step_mm is not None:
            lift["step"] = self.lift_step_mm
        return {
            "lift": lift,
            "turntable": {
                "unit": "deg",
                "min": self.turntable_min_deg,
                "max": self.turntable_max_deg,
                "continuous": self.continuous,
            },
        }

    @classmethod
    def from_wire(cls, value: Any, problems: Problems) -> AxesInfo:
        """Return the axes a WELCOME reports, recording every problem in ``problems``.

        ``continuous`` is read for its kind only: it follows from the turntable's limits.
        """
        if value is None:
            return cls()
        if not isinstance(value, dict):
            problems.add(f"welcome.axes: an object is required, found {show(value)}")
            return cls()
        lift = _axis(value, "lift", "mm", problems)
        table = _axis(value, "turntable", "deg", problems)
        where = "welcome.axes.lift"
        step = _optional_number(lift, "step", where, problems, low=0.0)
        check_bool(table.get("continuous", MISSING), "welcome.axes.turntable.continuous", problems)
        where_t = "welcome.axes.turntable"
        return cls(
            _optional_number(lift, "min", where, problems),
            _optional_number(lift, "max", where, problems),
            _optional_number(table, "min", where_t, problems),
            _optional_number(table, "max", where_t, problems),
            step,
        )


def _axis(axes: dict[str, Any], name: str, unit: str, problems: Problems) -> dict[str, Any]:
    """Return the object ``axes[name]`` ({} when absent) if it is in ``unit``."""
    axis = _object(axes, name, "welcome.axes", problems)
    found = axis.get("unit", unit)
    if found != unit:
        problems.add(f"welcome.axes.{name}.unit: {unit} is required, found {show(found)}")
    return axis


@dataclass(frozen=True)
class Welcome:
    """What the device says about itself at the handshake (the WELCOME body).

    A device of another protocol version is read for ``protocol`` and ``software``
    only (all it sends such a peer): nothing else can be trusted to mean the same.
    """

    protocol: int
    software: str = "?"
    hardware: str = "?"
    description: str = ""
    image_size: tuple[int, int] = (0, 0)
    board: BoardSpec | None = None
    cylinder_diameter_mm: float | None = None
    default_plans: dict[str, ScanPlan] = field(default_factory=dict)
    axes: AxesInfo = AxesInfo()
    """The axes' travel as the device reports it (none known from an older device)."""
    operations: tuple[str, ...] = ()
    limits: DeviceLimits = HOST_LIMITS
    row_scale: int = ROW_SCALE
    """The segment encoding's row scale (``segment_encoding.row_scale``)."""
    identity: DeviceIdentity | None = None
    extract: ExtractChanges | None = None
    """The device's configured extraction settings, every one by name (None: not reported)."""
    colour: bool = False
    """The device samples colour per point (absent on devices before the extension)."""
    modes: tuple[str, ...] = SCAN_MODES[:1]
    """The scan modes the device can run (``stop-and-go`` only from a device before them)."""
    lift_reference: LiftReference | None = None
    """The marks on its calibration cylinder that calibrate the lift (None: it has none)."""
    row_turn_deg: float | None = None
    """In a continuous scan, the table's turn from one image row's exposure to the next's
    (degrees: its continuous speed times the rolling shutter's row time); a continuous
    view's angle is its stripe's median row's. None: a stop-and-go device, or an older one."""
    off_frames: str | None = None
    """Where its continuous views' laser-off frames come from (one of ``OFF_FRAMES``:
    ``next-turn`` takes them a turn of the step count later, which a table turning short
    of its count misses). None: a stop-and-go device, an older one, or a kind this host
    does not know."""

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON body the device sends."""
        width, height = self.image_size
        return {
            "protocol": self.protocol,
            "software": self.software,
            "hardware": self.hardware,
            "description": self.description,
            "image_size": [width, height],
            "board": self.board.to_dict() if self.board else None,
            "cylinder_diameter_mm": self.cylinder_diameter_mm,
            "default_plans": {k: plan.to_wire() for k, plan in self.default_plans.items()},
            "axes": self.axes.to_wire(),
            "operations": list(self.operations),
            "limits": self.limits.to_dict(),
            "segment_encoding": {"row_scale": self.row_scale},
            "identity": self.identity.to_wire() if self.identity else {},
            "extract": self.extract.to_wire() if self.extract else None,
            "colour": self.colour,
            "modes": list(self.modes),
            "lift_reference": self.lift_reference.to_dict() if self.lift_reference else None,
            "row_turn_deg": self.row_turn_deg,
            "off_frames": self.off_frames,
        }

    @classmethod
    def from_wire(cls, body: Any) -> Welcome:
        """Return the WELCOME a device sent.

        Fields an older device of this protocol leaves out take their defaults; a field
        present with the wrong kind or beyond this version's limits is a problem.

        Raises:
            MessageError: listing every problem.
        """
        data = object_body(body, "WELCOME")
        problems = Problems()
        protocol = check_int(
            data.get("protocol", MISSING), "welcome.protocol", 0, MAX_COUNT, problems
        )
        if "protocol" not in data:
            problems.add("welcome: protocol is required")
        software = check_text(data, "software", "welcome", problems, "?")
        if protocol is not None and protocol != PROTOCOL_VERSION:
            if problems.items:
                raise MessageError("WELCOME", problems.items)
            return cls(protocol, software)
        if "hardware" not in data:
            problems.add("welcome: hardware is required")
        welcome = cls(
            protocol or 0,
            software,
            check_text(data, "hardware", "welcome", problems, "?"),
            check_text(data, "description", "welcome", problems, ""),
            _image_size(data.get("image_size", MISSING), problems),
            _board(data.get("board"), problems),
            _diameter(data.get("cylinder_diameter_mm"), problems),
            _plans(_object(data, "default_plans", "welcome", problems), problems),
            AxesInfo.from_wire(data.get("axes"), problems),
            _operations(data.get("operations"), problems),
            DeviceLimits.from_welcome(data.get("limits")),
            _row_scale(_object(data, "segment_encoding", "welcome", problems), problems),
            _identity(data.get("identity"), problems),
            _extract(data.get("extract"), problems),
            data.get("colour") is True,
            _modes(data.get("modes"), problems),
            _lift_reference(data.get("lift_reference"), problems),
            _row_turn(data.get("row_turn_deg"), problems),
            _off_frames(data.get("off_frames"), problems),
        )
        if problems.items:
            raise MessageError("WELCOME", problems.items)
        return welcome


def _image_size(value: Any, problems: Problems) -> tuple[int, int]:
    side = HOST_LIMITS.max_image_side_px
    items = check_list(value, "welcome.image_size", 2, problems, min_items=2)
    if value is MISSING:
        problems.add("welcome: image_size is required")
    if items is None:
        return (0, 0)
    width = check_int(items[0], "welcome.image_size[0]", 1, side, problems)
    height = check_int(items[1], "welcome.image_size[1]", 1, side, problems)
    return (width or 0, height or 0)


def _board(value: Any, problems: Problems) -> BoardSpec | None:
    if not value:
        return None
    try:
        return BoardSpec.from_dict(value)
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
        problems.add(f"welcome.board: unusable ({show(str(exc))})")
        return None


def _lift_reference(value: Any, problems: Problems) -> LiftReference | None:
    if value is None:
        return None
    try:
        return LiftReference.from_dict(value)
    except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
        problems.add(f"welcome.lift_reference: unusable ({show(str(exc))})")
        return None


def _diameter(value: Any, problems: Problems) -> float | None:
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | float):
        problems.add(f"welcome.cylinder_diameter_mm: a number is required, found {show(value)}")
        return None
    try:
        return float(value)
    except OverflowError:
        problems.add("welcome.cylinder_diameter_mm: beyond any finite number")
        return None


def _plans(data: dict[str, Any], problems: Problems) -> dict[str, ScanPlan]:
    plans: dict[str, ScanPlan] = {}
    for target, wire in data.items():
        try:
            plans[str(target)] = ScanPlan.from_dict(wire)
        except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
            problems.add(f"welcome.default_plans.{show(target)}: unusable ({show(str(exc))})")
    return plans


def _operations(value: Any, problems: Problems) -> tuple[str, ...]:
    if value is None:
        return ()
    items = check_list(value, "welcome.operations", MAX_SHORT_TEXT, problems)
    if items is None:
        return ()
    if not all(isinstance(op, str) for op in items):
        problems.add("welcome.operations: a list of names is required")
        return ()
    return tuple(items)


MAX_ROW_TURN_DEG = 1.0
"""Largest turn between two rows' exposures a WELCOME may report (a turn a second is
about 0.003 degrees a row)."""


def _row_turn(value: Any, problems: Problems) -> float | None:
    """Return the continuous scan's turn per image row (None when not reported)."""
    if value is None:
        return None
    where = "welcome.row_turn_deg"
    return check_number(value, where, -MAX_ROW_TURN_DEG, MAX_ROW_TURN_DEG, problems)


def _off_frames(value: Any, problems: Problems) -> str | None:
    """Return where the device's continuous laser-off frames come from (None: not said).

    A kind this host does not know is left out, not refused, as a scan mode is.
    """
    if value is None:
        return None
    if not isinstance(value, str):
        problems.add(f"welcome.off_frames: a name is required, found {show(value)}")
        return None
    return value if value in OFF_FRAMES else None


def _modes(value: Any, problems: Problems) -> tuple[str, ...]:
    """Return the scan modes a device offers that this host knows (stop-and-go when absent).

    A mode this host does not know is left out, not refused: a newer device may offer more.
    """
    if value is None:
        return SCAN_MODES[:1]
    items = check_list(value, "welcome.modes", len(SCAN_MODES) * 8, problems)
    if items is None:
        return SCAN_MODES[:1]
    if not all(isinstance(mode, str) for mode in items):
        problems.add("welcome.modes: a list of names is required")
        return SCAN_MODES[:1]
    return tuple(mode for mode in SCAN_MODES if mode in items)


def _row_scale(encoding: dict[str, Any], problems: Problems) -> int:
    scale = encoding.get("row_scale")
    if scale != ROW_SCALE or not is_int(scale):
        problems.add(
            f"welcome.segment_encoding.row_scale: {show(scale)} is not this host's {ROW_SCALE}"
        )
    return ROW_SCALE


def _identity(value: Any, problems: Problems) -> DeviceIdentity | None:
    if value is None:
        return None
    if not isinstance(value, dict):
        problems.add(f"welcome.identity: an object is required, found {show(value)}")
        return None
    known = {}
    for key in ("serial", "source", "count_since"):
        item = value.get(key)
        if item is not None:
            # Kept as text whatever its kind: an identity is compared, never computed with.
            known[key] = str(item)[:MAX_SHORT_TEXT]
    return DeviceIdentity(**known)


def _extract(value: Any, problems: Problems) -> ExtractChanges | None:
    """Return the configured extraction as reported, values untouched (they are hashed
    into a scan's identity, so ``12`` must stay ``12``); kinds are the device's business."""
    if value is None:
        return None
    if not isinstance(value, dict):
        problems.add(f"welcome.extract: an object is required, found {show(value)}")
        return None
    scalar = (str, int, float, bool, type(None))
    bad = [k for k, v in value.items() if not isinstance(v, scalar)]
    for key in bad[:MAX_SHOWN_PROBLEMS]:
        problems.add(
            f"welcome.extract.{show(key)}: a number, text, true, false or null is required"
        )
    return None if bad else ExtractChanges(tuple(value.items()))


# --- ACK --------------------------------------------------------------------------------


@dataclass(frozen=True)
class Ack:
    """The host has stored segments ``seqs`` of scan ``request_id``; ``lost`` were missed.

    The device resends the ``lost`` plan indices at once (see PROTOCOL.md, *Segments*).
    """

    request_id: int
    seqs: tuple[int, ...]
    lost: tuple[int, ...] = ()

    @classmethod
    def stored(cls, request_id: int, seq: int, missing: list[int]) -> Ack:
        """Return the ACK of one stored segment, naming at most :data:`MAX_LOST_SEQS` lost."""
        return cls(request_id, (seq,), tuple(missing[:MAX_LOST_SEQS]))

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON body the host sends."""
        return {"id": self.request_id, "seqs": list(self.seqs), "lost": list(self.lost)}

    @classmethod
    def from_wire(cls, body: Any, limits: DeviceLimits) -> Ack:
        """Return the ACK the host sent (at most ``limits.max_ack_seqs`` numbers in all).

        Raises:
            MessageError: listing every problem.
        """
        data = object_body(body, "ACK")
        problems = Problems()
        request_id = check_int(data.get("id", MISSING), "ack.id", 0, MAX_COUNT, problems)
        if "id" not in data:
            problems.add("ack: id is required")
        if "seqs" not in data:
            problems.add("ack: seqs is required")
        seqs = _seqs(data.get("seqs", MISSING), "ack.seqs", limits, problems)
        lost = _seqs(data.get("lost", []), "ack.lost", limits, problems)
        if len(seqs) + len(lost) > limits.max_ack_seqs:
            problems.add(f"ack: {len(seqs) + len(lost)} numbers, at most {limits.max_ack_seqs}")
        if problems.items or request_id is None:
            raise MessageError("ACK", problems.items)
        return cls(request_id, seqs, lost)


def _seqs(value: Any, where: str, limits: DeviceLimits, problems: Problems) -> tuple[int, ...]:
    items = check_list(value, where, limits.max_ack_seqs, problems)
    if items is None:
        return ()
    bad = [k for k, item in enumerate(items) if not (is_int(item) and 0 <= item <= MAX_COUNT)]
    for k in bad[:MAX_SHOWN_PROBLEMS]:
        problems.add(f"{where}[{k}]: a segment number is required, found {show(items[k])}")
    return () if bad else tuple(items)


# --- EVENT and progress -----------------------------------------------------------------


@dataclass(frozen=True)
class Progress:
    """Where a scan is: ``done`` of ``total`` views, the latest in ``section``.

    The device's acquisition makes one after each view, the host one per progress EVENT
    (adding the timing it measures itself); only the first four fields travel.
    """

    target: str
    done: int
    total: int
    section: int
    state: str = "scanning"
    """``scanning``, ``paused`` (a pause is pending or held) or ``done`` (device side)."""
    elapsed_s: float = 0.0
    """Seconds since this run (a start or a resume) began."""
    done_this_run: int = 0
    """Views received since this run began: the rate comes from these."""
    starting: bool = False
    """The report made as a resumed run starts, before any view: ``done`` are held already."""

    @property
    def left_s(self) -> float | None:
        """Return the estimated seconds left (None before this run's first view)."""
        if self.done_this_run <= 0:
            return None
        return self.elapsed_s / self.done_this_run * max(self.total - self.done, 0)


@dataclass(frozen=True)
class ProgressEvent:
    """EVENT ``progress``: a view of scan ``request_id`` was sent."""

    request_id: int
    progress: Progress

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON body the device sends."""
        p = self.progress
        return {
            "id": self.request_id,
            "event": "progress",
            "target": p.target,
            "done": p.done,
            "total": p.total,
            "section": p.section,
        }


@dataclass(frozen=True)
class StatusEvent:
    """EVENT ``status``: the device's state for request ``request_id`` (and the op begun)."""

    request_id: int
    state: str
    op: str | None = None

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON body the device sends (``op`` only when a request begins)."""
        body: dict[str, Any] = {"id": self.request_id, "event": "status", "state": self.state}
        if self.op is not None:
            body["op"] = self.op
        return body


@dataclass(frozen=True)
class LogEvent:
    """EVENT ``log``: one line the device has to say about request ``request_id``."""

    request_id: int
    message: str

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON body the device sends."""
        return {"id": self.request_id, "event": "log", "message": self.message}


Event = ProgressEvent | StatusEvent | LogEvent
EVENTS = ("progress", "status", "log")
"""The EVENT kinds a device sends."""


def parse_event(body: Any) -> Event:
    """Return the typed EVENT of a received body.

    Raises:
        MessageError: listing every problem (an unknown kind is one).
    """
    data = object_body(body, "EVENT")
    problems = Problems()
    request_id = check_int(data.get("id", MISSING), "event.id", 0, MAX_COUNT, problems)
    kind = data.get("event")
    if "id" not in data:
        problems.add("event: id is required")
    if kind == "progress":
        progress = _progress(data, problems)
        if not problems.items and request_id is not None:
            return ProgressEvent(request_id, progress)
    elif kind == "status":
        state = check_text(data, "state", "event", problems, "")
        op = check_text(data, "op", "event", problems, None)
        if not problems.items and request_id is not None:
            return StatusEvent(request_id, state, op)
    elif kind == "log":
        message = check_text(data, "message", "event", problems, "")
        if not problems.items and request_id is not None:
            return LogEvent(request_id, message)
    else:
        problems.add(f"event.event: one of {', '.join(EVENTS)} is required, found {show(kind)}")
    raise MessageError("EVENT", problems.items)


def _progress(data: dict[str, Any], problems: Problems) -> Progress:
    for key in ("target", "done", "total", "section"):
        if key not in data:
            problems.add(f"event: {key} is required")
    target = check_text(data, "target", "event", problems, "")
    done = check_int(data.get("done", MISSING), "event.done", 0, MAX_COUNT, problems)
    total = check_int(data.get("total", MISSING), "event.total", 0, MAX_COUNT, problems)
    section = check_int(data.get("section", MISSING), "event.section", 0, 65_535, problems)
    return Progress(target, done or 0, total or 0, section or 0)


__all__ = [
    "DEVICE_STATES",
    "EVENTS",
    "MAX_LOST_SEQS",
    "MAX_SESSION_CHARS",
    "Ack",
    "AxesInfo",
    "DeviceHeartbeat",
    "DeviceIdentity",
    "Event",
    "Hello",
    "HostHeartbeat",
    "LogEvent",
    "MessageError",
    "Progress",
    "ProgressEvent",
    "StatusEvent",
    "Welcome",
    "parse_event",
]
