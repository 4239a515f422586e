"""Every operation's reply: the ``result`` of a successful REPLY, one class per shape.

:mod:`lamina_shared.ops` types the requests and :mod:`lamina_shared.messages` the other
messages; this module types what each operation answers, in the same style: a frozen
dataclass whose ``to_wire()`` the device sends and whose ``from_wire()`` the host reads
back, raising :class:`~lamina_shared.messages.MessageError` listing every problem.
:data:`REPLIES` names each operation's class: the device's endpoint refuses to send a
reply of another class, so the two ends cannot drift (``shared/PROTOCOL.md``, *Replies*).
"""

from __future__ import annotations

import base64
import binascii
from dataclasses import dataclass, fields
from typing import Any, ClassVar, Protocol, Self

from lamina_shared.limits import show
from lamina_shared.messages import (
    MAX_COUNT,
    DeviceHeartbeat,
    MessageError,
    object_body,
    require_keys,
)
from lamina_shared.ops import MISSING, Problems, check_choice, check_int, check_number
from lamina_shared.types import BoardSpec

MAX_SECONDS = 1e7
"""Longest time a reply may report (about four months)."""


class Reply(Protocol):
    """What every reply class is: its wire form, and its name in problems."""

    kind: ClassVar[str]

    def to_wire(self) -> dict[str, Any]: ...  # pragma: no cover - protocol


def _counts(
    data: dict[str, Any], keys: tuple[str, ...], where: str, problems: Problems
) -> list[int]:
    """Return the required whole numbers ``data[key]`` in 0..:data:`MAX_COUNT` (0 if bad)."""
    require_keys(data, keys, where, problems)
    found = [check_int(data.get(k, MISSING), f"{where}.{k}", 0, MAX_COUNT, problems) for k in keys]
    return [value or 0 for value in found]


def _finish(kind: str, problems: Problems) -> None:
    if problems.items:
        raise MessageError(kind, problems.items)


@dataclass(frozen=True)
class _WholeNumbers:
    """A reply of whole numbers only, each field travelling under its own name."""

    kind: ClassVar[str] = "reply"
    op: ClassVar[str] = "reply"

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON result the device sends."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def from_wire(cls, body: Any) -> Self:
        """Return the reply of a result body.

        Raises:
            MessageError: listing every problem.
        """
        data = object_body(body, cls.kind)
        problems = Problems()
        values = _counts(data, tuple(f.name for f in fields(cls)), cls.op, problems)
        _finish(cls.kind, problems)
        return cls(*values)


# --- binary transfers -------------------------------------------------------------------


@dataclass(frozen=True)
class TransferOffer:
    """A transfer the device pushed and keeps for ``fetch``: its number, size and CRC32."""

    transfer: int
    size_bytes: int
    crc32: int

    def to_wire(self) -> dict[str, Any]:
        """Return the reply's transfer fields (``transfer``, ``bytes``, ``crc32``)."""
        return {"transfer": self.transfer, "bytes": self.size_bytes, "crc32": self.crc32}

    @classmethod
    def read(cls, data: dict[str, Any], where: str, problems: Problems) -> TransferOffer:
        """Return the transfer fields of a reply, recording every problem."""
        return cls(*_counts(data, ("transfer", "bytes", "crc32"), where, problems))


@dataclass(frozen=True)
class GridReply:
    """The ``grab_grid`` reply: the board image's transfer and the board's geometry."""

    kind: ClassVar[str] = "grab_grid reply"
    offer: TransferOffer
    board: BoardSpec | None

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON result the device sends."""
        return {**self.offer.to_wire(), "board": self.board.to_dict() if self.board else None}

    @classmethod
    def from_wire(cls, body: Any) -> GridReply:
        """Return the reply of a result body (``board`` null: the device knows none).

        Raises:
            MessageError: listing every problem.
        """
        data = object_body(body, cls.kind)
        problems = Problems()
        offer = TransferOffer.read(data, "grab_grid", problems)
        require_keys(data, ("board",), "grab_grid", problems)
        board = None
        if data.get("board") is not None:
            try:
                board = BoardSpec.from_dict(data["board"])
            except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
                problems.add(f"grab_grid.board: unusable ({show(str(exc))})")
        _finish(cls.kind, problems)
        return cls(offer, board)


@dataclass(frozen=True)
class PreviewReply:
    """The ``preview`` reply: the frame's transfer and, if asked, the stripe's SEGMENT body."""

    kind: ClassVar[str] = "preview reply"
    offer: TransferOffer
    stripe: bytes | None = None
    """The stripe extracted there, a SEGMENT body (travels as base64 text)."""

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON result the device sends (``stripe`` only when extracted)."""
        body: dict[str, Any] = self.offer.to_wire()
        if self.stripe is not None:
            body["stripe"] = base64.b64encode(self.stripe).decode("ascii")
        return body

    @classmethod
    def from_wire(cls, body: Any) -> PreviewReply:
        """Return the reply of a result body.

        Raises:
            MessageError: listing every problem.
        """
        data = object_body(body, cls.kind)
        problems = Problems()
        offer = TransferOffer.read(data, "preview", problems)
        text, stripe = data.get("stripe"), None
        if "stripe" in data:
            try:
                if not isinstance(text, str):
                    raise TypeError(f"a text is required, found {show(text)}")
                stripe = base64.b64decode(text, validate=True)
            except (TypeError, binascii.Error) as exc:
                problems.add(f"preview.stripe: not base64 text ({show(str(exc))})")
        _finish(cls.kind, problems)
        return cls(offer, stripe)


@dataclass(frozen=True)
class FetchReply:
    """The ``fetch`` reply: how many bytes of the kept transfer were sent again."""

    kind: ClassVar[str] = "fetch reply"
    sent_bytes: int

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON result the device sends."""
        return {"sent": self.sent_bytes}

    @classmethod
    def from_wire(cls, body: Any) -> FetchReply:
        """Return the reply of a result body.

        Raises:
            MessageError: listing every problem.
        """
        data = object_body(body, cls.kind)
        problems = Problems()
        (sent,) = _counts(data, ("sent",), "fetch", problems)
        _finish(cls.kind, problems)
        return cls(sent)


# --- scanning ---------------------------------------------------------------------------


@dataclass(frozen=True)
class ScanReply(_WholeNumbers):
    """The ``scan`` reply: the plan's views, those acquired now and those resent."""

    kind: ClassVar[str] = "scan reply"
    op: ClassVar[str] = "scan"
    segments: int
    acquired: int
    resent: int


@dataclass(frozen=True)
class ScanEstimate:
    """The ``estimate`` reply: how long a plan keeps the subject still, on this device.

    Attributes:
        views: the plan's views.
        modelled_s: first move to last view, as the device's loop would run it.
        mechanical_minimum_s: the axes' moves (together), settles and frames alone.
    """

    kind: ClassVar[str] = "estimate reply"
    views: int
    modelled_s: float
    mechanical_minimum_s: float

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON reply the device sends."""
        return {
            "views": self.views,
            "modelled_s": round(self.modelled_s, 3),
            "mechanical_minimum_s": round(self.mechanical_minimum_s, 3),
        }

    @classmethod
    def from_wire(cls, body: Any) -> ScanEstimate:
        """Return the estimate of a reply body.

        Raises:
            MessageError: listing every problem.
        """
        data = object_body(body, cls.kind)
        problems = Problems()
        (views,) = _counts(data, ("views",), "estimate", problems)
        require_keys(data, ("modelled_s", "mechanical_minimum_s"), "estimate", problems)
        times = [
            check_number(data.get(key, MISSING), f"estimate.{key}", 0.0, MAX_SECONDS, problems)
            for key in ("modelled_s", "mechanical_minimum_s")
        ]
        _finish(cls.kind, problems)
        return cls(views, times[0] or 0.0, times[1] or 0.0)


CONTROL_STATES = ("paused", "busy", "aborting")
"""What ``pause``, ``resume`` and ``abort`` report the scan is doing now."""


@dataclass(frozen=True)
class ControlReply:
    """The ``pause``, ``resume`` and ``abort`` reply: the scan's state now."""

    kind: ClassVar[str] = "control reply"
    state: str

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON result the device sends."""
        return {"state": self.state}

    @classmethod
    def from_wire(cls, body: Any) -> ControlReply:
        """Return the reply of a result body.

        Raises:
            MessageError: listing every problem.
        """
        data = object_body(body, cls.kind)
        problems = Problems()
        require_keys(data, ("state",), "control", problems)
        state = check_choice(data.get("state", MISSING), "control.state", CONTROL_STATES, problems)
        _finish(cls.kind, problems)
        return cls(state or "")


# --- quick operations -------------------------------------------------------------------

AXES = ("lift", "turntable")


@dataclass(frozen=True)
class MoveReply:
    """The ``move`` reply: the axis moved and where it stands now (mm or deg)."""

    kind: ClassVar[str] = "move reply"
    axis: str
    position: float

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON result the device sends."""
        return {"axis": self.axis, "position": self.position}

    @classmethod
    def from_wire(cls, body: Any) -> MoveReply:
        """Return the reply of a result body.

        Raises:
            MessageError: listing every problem.
        """
        data = object_body(body, cls.kind)
        problems = Problems()
        require_keys(data, ("axis", "position"), "move", problems)
        axis = check_choice(data.get("axis", MISSING), "move.axis", AXES, problems)
        position = check_number(
            data.get("position", MISSING), "move.position", -1e300, 1e300, problems
        )
        _finish(cls.kind, problems)
        return cls(axis or "", position or 0.0)


@dataclass(frozen=True)
class ExposureReply(_WholeNumbers):
    """The ``exposure`` reply: the camera's exposure now and its range, in microseconds."""

    kind: ClassVar[str] = "exposure reply"
    op: ClassVar[str] = "exposure"
    exposure_us: int
    min_us: int
    max_us: int


@dataclass(frozen=True)
class StatusReply:
    """The ``status`` reply: what a heartbeat says, and the retransmissions so far."""

    kind: ClassVar[str] = "status reply"
    heartbeat: DeviceHeartbeat
    retransmissions: int

    @property
    def state(self) -> str:
        """Return the device's state: one of :data:`~lamina_shared.messages.DEVICE_STATES`."""
        return self.heartbeat.state

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON result the device sends."""
        return {**self.heartbeat.to_wire(), "retransmissions": self.retransmissions}

    @classmethod
    def from_wire(cls, body: Any) -> StatusReply:
        """Return the reply of a result body.

        Raises:
            MessageError: listing every problem.
        """
        data = object_body(body, cls.kind)
        problems = Problems()
        heartbeat = DeviceHeartbeat.read(data, "status", problems)
        (retransmissions,) = _counts(data, ("retransmissions",), "status", problems)
        _finish(cls.kind, problems)
        return cls(heartbeat, retransmissions)


@dataclass(frozen=True)
class EmptyReply:
    """The reply of an operation that reports nothing (``shutdown``): ``{}``."""

    kind: ClassVar[str] = "shutdown reply"

    def to_wire(self) -> dict[str, Any]:
        """Return the JSON result the device sends: an empty object."""
        return {}

    @classmethod
    def from_wire(cls, body: Any) -> EmptyReply:
        """Return the reply of a result body (any object: nothing in it is read).

        Raises:
            MessageError: the body is not an object.
        """
        object_body(body, cls.kind)
        return cls()


REPLIES: dict[str, type[Reply]] = {
    "grab_grid": GridReply,
    "preview": PreviewReply,
    "scan": ScanReply,
    "fetch": FetchReply,
    "move": MoveReply,
    "pause": ControlReply,
    "resume": ControlReply,
    "abort": ControlReply,
    "exposure": ExposureReply,
    "status": StatusReply,
    "estimate": ScanEstimate,
    "shutdown": EmptyReply,
}
"""Each operation's reply class, by name: the same operations as :data:`lamina_shared.ops.OPS`."""


__all__ = [
    "CONTROL_STATES",
    "REPLIES",
    "ControlReply",
    "EmptyReply",
    "ExposureReply",
    "FetchReply",
    "GridReply",
    "MoveReply",
    "PreviewReply",
    "Reply",
    "ScanEstimate",
    "ScanReply",
    "StatusReply",
    "TransferOffer",
]
