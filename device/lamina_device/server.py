"""The device end of the link: answer the host's handshake and requests, lose nothing.

The server keeps reading the line while a long request (a scan, the calibration image)
runs on a worker thread, so acknowledgements, heartbeats and quick requests are
answered throughout. Every segment carries its index in the scan plan (``seq``) and
stays in a bounded buffer until the host acknowledges it: unacknowledged segments are
sent again after an adaptive timeout, and when the buffer is full the scan waits. A
host that comes back (a new session, after a cut cable or a killed process) says which
segments it already holds; the device resends the rest from its buffer and acquires
only what it never had.

Nothing received is ever evaluated or used as a file path: requests name an operation
from a fixed table and carry plain numbers, each checked against the device's limits.
"""

from __future__ import annotations

import base64
import hashlib
import json
import logging
import math
import threading
import time
import zlib
from collections import OrderedDict
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from typing import Any

import cv2
import numpy as np

from lamina_device import __version__
from lamina_device.acquisition import (
    Progress,
    ScanAborted,
    ScanControl,
    acquire,
    capture_pair,
    grab_grid,
)
from lamina_device.camera import CameraError, ExposureRefused
from lamina_device.extract import extract, to_segment
from lamina_device.hardware import Hardware
from lamina_shared.link import Channel, LinkClosed, Ticker, error_body, is_count, ok_body
from lamina_shared.protocol import (
    CHUNK_BYTES,
    MAX_ACK_SEQS,
    MAX_PAYLOAD_BYTES,
    PROTOCOL_VERSION,
    ROW_SCALE,
    Kind,
    Message,
    encode_chunk,
    encode_json,
    encode_segment,
    encode_segment_body,
    quantise_segment,
)
from lamina_shared.types import ScanPlan, Segment

log = logging.getLogger(__name__)

SIM_LIFT_TRAVEL_MM = 200.0
"""The simulated lift's travel, reported when the hardware does not say its own."""


class RequestError(Exception):
    """A request the device refuses; ``code`` is machine-readable, the text is for people."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class Abandoned(Exception):
    """The host that asked for the running request has gone (a new session began)."""


@dataclass(frozen=True)
class ServerSettings:
    """Tunable limits of the device end; the host learns them from WELCOME."""

    window_segments: int = 16
    heartbeat_s: float = 0.3
    rto_min_s: float = 0.25
    rto_max_s: float = 2.0
    ack_timeout_s: float = 60.0
    max_views: int = 10_000
    max_fetch_bytes: int = 256 * 1024
    kept_transfers: int = 2
    kept_replies: int = 32


@dataclass(frozen=True)
class AxisLimits:
    """Soft limits of the two axes; None means the axis has no limit that way."""

    lift_min_mm: float
    lift_max_mm: float
    turntable_min_deg: float | None = None
    turntable_max_deg: float | None = None

    @classmethod
    def of(cls, hardware: Hardware) -> AxisLimits:
        """Return the hardware's limits, or the simulator's where it does not expose them."""
        config = getattr(hardware.lift, "config", None)
        if config is not None and hasattr(config, "min_mm"):
            low, high = float(config.min_mm), float(config.max_mm)
        else:
            low, high = 0.0, float(getattr(hardware.lift, "travel_mm", SIM_LIFT_TRAVEL_MM))
        return cls(
            low,
            high,
            getattr(hardware.turntable, "min_deg", None),
            getattr(hardware.turntable, "max_deg", None),
        )

    def to_dict(self) -> dict[str, Any]:
        """Return the WELCOME form."""
        return {
            "lift": {"unit": "mm", "min": self.lift_min_mm, "max": self.lift_max_mm},
            "turntable": {
                "unit": "deg",
                "min": self.turntable_min_deg,
                "max": self.turntable_max_deg,
                "continuous": self.turntable_min_deg is None and self.turntable_max_deg is None,
            },
        }

    def check(self, axis: str, position: float) -> None:
        """Raise RequestError(``limit``) unless ``position`` is within ``axis``'s limits."""
        if axis == "lift":
            low, high, unit = self.lift_min_mm, self.lift_max_mm, "mm"
        else:
            low, high, unit = self.turntable_min_deg, self.turntable_max_deg, "deg"
        if not math.isfinite(position):
            raise RequestError("limit", f"{axis} position must be a finite number of {unit}")
        if (low is not None and position < low) or (high is not None and position > high):
            raise RequestError(
                "limit",
                f"{axis} position {position} {unit} is outside its soft limits {low}..{high}",
            )


@dataclass
class _Pending:
    segment: Segment
    sent_s: float
    attempts: int = 1


@dataclass
class SegmentBuffer:
    """Sent, unacknowledged segments of one scan, bounded; thread-safe.

    The retransmission timeout follows RFC 6298 (smoothed round-trip time plus four
    deviations, samples only from segments sent once, doubled on each expiry), so a
    slow UART with a full window does not provoke needless resends.
    """

    window: int
    rto_min_s: float
    rto_max_s: float
    key: tuple[str, str] | None = None
    request_id: int = 0
    _items: dict[int, _Pending] = field(default_factory=dict)
    _cond: threading.Condition = field(default_factory=threading.Condition)
    _srtt_s: float | None = None
    _rttvar_s: float = 0.0
    retransmissions: int = 0

    @property
    def rto_s(self) -> float:
        """Return the retransmission timeout of a segment sent once."""
        base = 1.0 if self._srtt_s is None else self._srtt_s + 4 * self._rttvar_s
        return min(self.rto_max_s, max(self.rto_min_s, base))

    def _timeout_s(self, pending: _Pending) -> float:
        # Each resend of the same segment waits twice as long (capped): a dead line is
        # not flooded, while other segments keep their own, shorter timeouts.
        return min(self.rto_max_s, self.rto_s * 2 ** (pending.attempts - 1))

    def __len__(self) -> int:
        with self._cond:
            return len(self._items)

    def adopt(self, key: tuple[str, str], request_id: int) -> dict[int, Segment]:
        """Start serving scan ``key`` for ``request_id``; return segments kept from before."""
        with self._cond:
            if key != self.key:
                self._items.clear()
            self.key, self.request_id = key, request_id
            return {seq: p.segment for seq, p in self._items.items()}

    def put(self, seq: int, segment: Segment, abandoned: threading.Event) -> None:
        """Hold ``segment`` until acknowledged; wait while the window is full."""
        with self._cond:
            while True:
                if abandoned.is_set():
                    raise Abandoned
                if len(self._items) < self.window:
                    break
                self._cond.wait(0.05)
            self._items[seq] = _Pending(segment, time.monotonic())

    def mark_resent(self, seqs: Iterable[int]) -> None:
        """Record that ``seqs`` went out again now (not a round-trip sample)."""
        now = time.monotonic()
        with self._cond:
            for seq in seqs:
                if seq in self._items:
                    self._items[seq].sent_s, self._items[seq].attempts = now, 2

    def ack(self, request_id: int, seqs: Iterable[int]) -> None:
        """Forget acknowledged segments; learn the round-trip time from first sends."""
        now = time.monotonic()
        with self._cond:
            if request_id != self.request_id:
                return
            for seq in seqs:
                pending = self._items.pop(seq, None)
                if pending is None:
                    continue
                if pending.attempts == 1:
                    self._sample(now - pending.sent_s)
            self._cond.notify_all()

    def _sample(self, rtt_s: float) -> None:
        if self._srtt_s is None:
            self._srtt_s, self._rttvar_s = rtt_s, rtt_s / 2
        else:
            self._rttvar_s = 0.75 * self._rttvar_s + 0.25 * abs(self._srtt_s - rtt_s)
            self._srtt_s = 0.875 * self._srtt_s + 0.125 * rtt_s

    def overdue(self) -> list[tuple[int, Segment]]:
        """Return segments whose timeout expired, marked as sent again now."""
        now = time.monotonic()
        with self._cond:
            due = [(s, p) for s, p in self._items.items() if now - p.sent_s >= self._timeout_s(p)]
            for _, pending in due:
                pending.sent_s, pending.attempts = now, pending.attempts + 1
            self.retransmissions += len(due)
            return [(s, p.segment) for s, p in sorted(due, key=lambda item: item[0])]

    def resend_lost(self, seqs: Iterable[int]) -> list[tuple[int, Segment]]:
        """Return the segments the host reports missing, unless one was just sent again.

        The host sees a gap when a later segment arrives first, so this repairs a loss
        after about one round trip instead of a whole timeout.
        """
        now = time.monotonic()
        with self._cond:
            recent_s = max(0.05, self._srtt_s or 0.0)
            out = []
            for seq in seqs:
                pending = self._items.get(seq)
                if pending is not None and now - pending.sent_s > recent_s:
                    pending.sent_s, pending.attempts = now, pending.attempts + 1
                    out.append((seq, pending.segment))
            self.retransmissions += len(out)
            return out

    def expire_all(self) -> None:
        """Make every held segment due now (the host was silent longer than a timeout)."""
        with self._cond:
            for pending in self._items.values():
                pending.sent_s, pending.attempts = -math.inf, 1

    def wait_empty(self, abandoned: threading.Event, timeout_s: float) -> bool:
        """Wait until every segment is acknowledged; False if no ack came for ``timeout_s``."""
        with self._cond:
            last = len(self._items)
            quiet_since = time.monotonic()
            while self._items:
                if abandoned.is_set():
                    raise Abandoned
                if len(self._items) != last:
                    last, quiet_since = len(self._items), time.monotonic()
                elif time.monotonic() - quiet_since > timeout_s:
                    return False
                self._cond.wait(0.05)
            return True


def plan_key(target: str, plan: ScanPlan) -> tuple[str, str]:
    """Return what identifies a scan across sessions: its target and plan fingerprint."""
    text = json.dumps(plan.to_dict(), sort_keys=True)
    return target, hashlib.sha256(text.encode()).hexdigest()[:16]


def views_in_section(plan: ScanPlan) -> list[int]:
    """Return each view's index within its section, as acquisition numbers them."""
    seen: dict[int, int] = {}
    out = []
    for view in plan.views:
        out.append(seen.get(view.section, 0))
        seen[view.section] = out[-1] + 1
    return out


def check_keys(args: dict[str, Any], allowed: set[str], op: str) -> None:
    """Refuse arguments an operation does not know (they may be a newer host's idea)."""
    unknown = sorted(set(args) - allowed)
    if unknown:
        raise RequestError("bad-args", f"{op} takes no argument {unknown[0]!r}")


class DeviceServer:
    """Serve one host at a time over ``channel`` until told to stop or the link closes."""

    def __init__(
        self, channel: Channel, hardware: Hardware, settings: ServerSettings | None = None
    ) -> None:
        self.channel = channel
        self.hardware = hardware
        self.settings = settings or ServerSettings()
        self.limits = AxisLimits.of(hardware)
        self.greeted = False
        self.running = True
        self.session: str | None = None
        self.buffer = SegmentBuffer(
            self.settings.window_segments, self.settings.rto_min_s, self.settings.rto_max_s
        )
        self._abandon = threading.Event()
        self._worker: threading.Thread | None = None
        self._control: ScanControl | None = None
        self._running_id: int | None = None
        self._replies: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self._transfers: OrderedDict[int, bytes] = OrderedDict()
        self._next_transfer = 1
        self._heartbeat = Ticker(self.settings.heartbeat_s)
        self._started_s = self._heard_s = time.monotonic()
        self._lock = threading.Lock()  # the reply cache and the running id, between threads
        self._long_ops: dict[str, Callable[[int, dict[str, Any]], dict[str, Any]]] = {
            "grab_grid": self._grab_grid,
            "preview": self._preview,
            "scan": self._scan,
        }
        self._quick_ops: dict[str, Callable[[int, dict[str, Any]], dict[str, Any]]] = {
            "fetch": self._fetch,
            "move": self._move,
            "pause": self._pause,
            "resume": self._resume,
            "abort": self._abort,
            "exposure": self._exposure,
            "status": self._status,
            "shutdown": self._shutdown,
        }

    # --- the handshake ---------------------------------------------------------------

    def info(self) -> dict[str, Any]:
        """Return what the device tells the host about itself at the handshake."""
        hw = self.hardware
        width, height = hw.camera.size
        s = self.settings
        return {
            "protocol": PROTOCOL_VERSION,
            "software": f"lamina-device {__version__}",
            "hardware": hw.kind,
            "description": hw.description,
            "image_size": [width, height],
            "board": hw.board.to_dict() if hw.board else None,
            "cylinder_diameter_mm": hw.cylinder_diameter_mm,
            "default_plans": {t: p.to_dict() for t, p in hw.default_plans.items()},
            "axes": self.limits.to_dict(),
            "operations": sorted({*self._long_ops, *self._quick_ops}),
            "limits": {
                "max_payload_bytes": MAX_PAYLOAD_BYTES,
                "chunk_bytes": CHUNK_BYTES,
                "window_segments": s.window_segments,
                "max_views": s.max_views,
                "max_fetch_bytes": s.max_fetch_bytes,
                "heartbeat_s": s.heartbeat_s,
            },
            "segment_encoding": {"row_scale": ROW_SCALE},
        }

    # --- the loop --------------------------------------------------------------------

    def serve(self) -> None:
        """Handle messages until shutdown or until the link closes."""
        try:
            while self.running:
                message = self.channel.receive(timeout_s=0.02)
                if message is not None:
                    self.handle(message)
                self._tick()
        except LinkClosed as exc:
            log.info("host went away: %s", exc)
        finally:
            self._stop_worker()
            self.hardware.laser.off()

    def _tick(self) -> None:
        """Do what is due: a heartbeat, retransmissions."""
        if self._heartbeat.due():
            self.channel.send(encode_json(Kind.HEARTBEAT, self._state()))
        resend = self.buffer.overdue()
        for seq, segment in resend:
            self.channel.send(encode_segment(self.buffer.request_id, seq, segment))

    def _state(self) -> dict[str, Any]:
        control = self._control
        busy = self._running_id is not None
        return {
            "state": "paused"
            if busy and control and control.paused
            else "busy"
            if busy
            else "idle",
            "request": self._running_id,
            "unacked": len(self.buffer),
            "uptime_s": round(time.monotonic() - self._started_s, 3),
        }

    def handle(self, message: Message) -> None:
        """Answer one message from the host."""
        silence_s = time.monotonic() - self._heard_s
        self._heard_s = time.monotonic()
        if self.hardware.watchdog is not None:
            self.hardware.watchdog.link_alive()
        if silence_s > self.buffer.rto_s:
            # The line was down (or the host busy) for longer than a timeout: whatever
            # was in flight is lost, so send it again now rather than after a backoff.
            self.buffer.expire_all()
        if message.kind is Kind.HELLO:
            self._hello(message.body)
        elif message.kind is Kind.REQUEST:
            self._request(message.body)
        elif message.kind is Kind.ACK:
            self._ack(message.body)
        elif message.kind is Kind.HEARTBEAT:
            pass
        else:
            log.warning("ignoring unexpected %s message from the host", message.kind.name)

    def _hello(self, body: dict[str, Any]) -> None:
        self.greeted = body.get("protocol") == PROTOCOL_VERSION
        session = body.get("session")
        session = session if isinstance(session, str) and len(session) <= 64 else None
        if self.greeted and session != self.session:
            # A new host process (or one that lost track): what the old one asked for is
            # abandoned, but buffered segments stay for it to resume with.
            self._stop_worker()
            self._replies.clear()
            self.session = session
        self.channel.send(encode_json(Kind.WELCOME, self.info()))

    def _ack(self, body: dict[str, Any]) -> None:
        request_id, seqs, lost = body.get("id"), body.get("seqs"), body.get("lost", [])
        if not (
            is_count(request_id)
            and isinstance(seqs, list)
            and isinstance(lost, list)
            and len(seqs) + len(lost) <= MAX_ACK_SEQS
        ):
            log.warning("ignoring a malformed acknowledgement")
            return
        assert isinstance(request_id, int)
        self.buffer.ack(request_id, [s for s in seqs if is_count(s)])
        if request_id == self.buffer.request_id:
            for seq, segment in self.buffer.resend_lost([s for s in lost if is_count(s)]):
                self.channel.send(encode_segment(request_id, seq, segment))

    # --- requests --------------------------------------------------------------------

    def _request(self, body: dict[str, Any]) -> None:
        request_id = body.get("id")
        if not is_count(request_id):
            log.warning("ignoring a request without a valid id")
            return
        assert isinstance(request_id, int)
        with self._lock:
            cached, running = self._replies.get(request_id), self._running_id
        if cached is not None:
            # The host did not get our reply (or sent its request twice): same answer again.
            self.channel.send(encode_json(Kind.REPLY, cached))
            return
        if request_id == running:
            return  # already at work on it; heartbeats tell the host so
        try:
            if not self.greeted:
                raise RequestError(
                    "handshake", f"say HELLO with protocol {PROTOCOL_VERSION} before any request"
                )
            name = str(body.get("op"))
            args = body.get("args", {})
            if not isinstance(args, dict):
                raise RequestError("bad-args", "request args must be an object")
            if name in self._long_ops:
                self._start(request_id, name, self._long_ops[name], args)
                return
            op = self._quick_ops.get(name)
            if op is None:
                raise RequestError("unknown-op", f"unknown operation {body.get('op')!r}")
            reply = ok_body(request_id, op(request_id, args))
        except RequestError as exc:
            reply = error_body(request_id, exc.code, str(exc))
        except (CameraError, ValueError, OSError) as exc:
            self.hardware.laser.off()
            reply = error_body(request_id, "failed", str(exc))
        self._finish(request_id, reply)

    def _finish(self, request_id: int, reply: dict[str, Any]) -> None:
        """Keep the reply for repeated requests, mark the request done, send the reply."""
        with self._lock:
            self._replies[request_id] = reply
            while len(self._replies) > self.settings.kept_replies:
                self._replies.popitem(last=False)
            if self._running_id == request_id:
                self._running_id = None
        self.channel.send(encode_json(Kind.REPLY, reply))

    def _start(
        self,
        request_id: int,
        name: str,
        op: Callable[[int, dict[str, Any]], dict[str, Any]],
        args: dict[str, Any],
    ) -> None:
        with self._lock:
            if self._running_id is not None:
                raise RequestError(
                    "busy", f"request {self._running_id} is still running: wait for it"
                )
            self._running_id = request_id
        self._abandon.clear()
        self._event(request_id, "status", state="busy", op=name)
        # The worker marks itself done in _finish, under the lock, with its reply cached.
        self._worker = threading.Thread(
            target=self._work, args=(request_id, op, args), name=f"device-{name}", daemon=True
        )
        self._worker.start()

    def _work(
        self,
        request_id: int,
        op: Callable[[int, dict[str, Any]], dict[str, Any]],
        args: dict[str, Any],
    ) -> None:
        try:
            reply = ok_body(request_id, op(request_id, args))
        except (Abandoned, ScanAborted) as exc:
            if isinstance(exc, ScanAborted) and not self._abandon.is_set():
                reply = error_body(request_id, "aborted", f"{exc}; the views sent so far are kept")
                self._finish(request_id, reply)
                return
            log.info("a request was abandoned by its host")
            with self._lock:
                self._running_id = None
            return
        except RequestError as exc:
            reply = error_body(request_id, exc.code, str(exc))
        except (CameraError, ValueError, OSError) as exc:
            reply = error_body(request_id, "failed", str(exc))
        finally:
            self.hardware.laser.off()
        try:
            self._finish(request_id, reply)
        except LinkClosed:
            log.info("host went away before the reply")

    def _stop_worker(self) -> None:
        worker = self._worker
        if worker is not None and worker.is_alive():
            self._abandon.set()
            if self._control is not None:
                self._control.abort()
            worker.join(timeout=30)
        self._worker = None

    def _event(self, request_id: int, event: str, **fields: Any) -> None:
        self.channel.send(encode_json(Kind.EVENT, {"id": request_id, "event": event, **fields}))

    # --- binary transfers ------------------------------------------------------------

    def _offer(self, request_id: int, data: bytes) -> dict[str, Any]:
        """Keep ``data`` for fetching, push it once, return its description."""
        transfer = self._next_transfer
        self._next_transfer += 1
        self._transfers[transfer] = data
        while len(self._transfers) > self.settings.kept_transfers:
            self._transfers.popitem(last=False)
        self._send_range(request_id, transfer, 0, len(data))
        return {"transfer": transfer, "bytes": len(data), "crc32": zlib.crc32(data)}

    def _send_range(self, request_id: int, transfer: int, offset: int, length: int) -> None:
        data = self._transfers[transfer]
        for at in range(offset, offset + length, CHUNK_BYTES):
            piece = data[at : min(at + CHUNK_BYTES, offset + length)]
            self.channel.send(encode_chunk(request_id, transfer, at, len(data), piece))

    def _fetch(self, request_id: int, args: dict[str, Any]) -> dict[str, Any]:
        """Send pieces of a kept transfer again (the host asks for what it lacks)."""
        check_keys(args, {"transfer", "ranges"}, "fetch")
        transfer, ranges = args.get("transfer"), args.get("ranges")
        if not is_count(transfer) or transfer not in self._transfers:
            raise RequestError("gone", f"transfer {transfer!r} is not kept any more: ask again")
        if not isinstance(ranges, list) or len(ranges) > 1024:
            raise RequestError("bad-args", "fetch ranges must be a list of [offset, length]")
        total = len(self._transfers[transfer])
        checked = []
        for item in ranges:
            if not (isinstance(item, list) and len(item) == 2 and all(is_count(v) for v in item)):
                raise RequestError("bad-args", "each fetch range must be [offset, length]")
            offset, length = item
            if offset + length > total:
                raise RequestError("bad-args", f"range {item} runs past the {total} bytes")
            checked.append((offset, length))
        if sum(length for _, length in checked) > self.settings.max_fetch_bytes:
            raise RequestError("bad-args", f"fetch at most {self.settings.max_fetch_bytes} bytes")
        for offset, length in checked:
            self._send_range(request_id, transfer, offset, length)
        return {"sent": sum(length for _, length in checked)}

    def _grab_grid(self, request_id: int, args: dict[str, Any]) -> dict[str, Any]:
        check_keys(args, set(), "grab_grid")
        result = self._offer(request_id, _png(grab_grid(self.hardware)))
        board = self.hardware.board
        return {**result, "board": board.to_dict() if board else None}

    def _preview(self, request_id: int, args: dict[str, Any]) -> dict[str, Any]:
        """Capture one frame where the axes stand (laser on only during its exposure).

        With ``stripe`` the device takes the laser-off/laser-on pair a scan would, extracts
        the stripe with the scan's own extraction and returns it as a SEGMENT body.
        """
        check_keys(args, {"laser", "stripe"}, "preview")
        laser, stripe = args.get("laser", False), args.get("stripe", False)
        if not isinstance(laser, bool) or not isinstance(stripe, bool):
            raise RequestError("bad-args", "preview's laser and stripe must be true or false")
        hw = self.hardware
        if not stripe:
            frame = capture_pair(hw)[0] if laser else hw.camera.capture()
            return self._offer(request_id, _png(frame))
        on, off = capture_pair(hw)
        segment = quantise_segment(
            to_segment(
                extract(on, off), hw.stage.target, 0, 0, hw.lift.z_mm, hw.turntable.angle_deg
            )
        )
        body = encode_segment_body(request_id, 0, segment)
        result = self._offer(request_id, _png(on if laser else off))
        return {**result, "stripe": base64.b64encode(body).decode("ascii")}

    # --- scanning --------------------------------------------------------------------

    def _plan(self, target: str, args: dict[str, Any]) -> ScanPlan:
        if args.get("plan") is not None:
            try:
                if not isinstance(args["plan"], dict):
                    raise TypeError("plan must be an object")
                plan = ScanPlan.from_dict(args["plan"])
            except (KeyError, TypeError, ValueError, OverflowError) as exc:
                raise RequestError("bad-args", f"invalid scan plan: {exc}") from None
        else:
            default = self.hardware.default_plans.get(target)
            if default is None:
                raise RequestError("bad-args", f"no {target} views to scan on this device")
            plan = default
        if len(plan.views) > self.settings.max_views:
            raise RequestError("limit", f"a scan has at most {self.settings.max_views} views")
        for view in plan.views:
            if not 0 <= view.section <= 65_535:
                raise RequestError("bad-args", f"section {view.section} is outside 0..65535")
            self.limits.check("lift", view.z_mm)
            self.limits.check("turntable", view.angle_deg)
        return plan

    def _scan(self, request_id: int, args: dict[str, Any]) -> dict[str, Any]:
        """Send every view of the plan the host does not hold: from the buffer or acquired."""
        check_keys(args, {"target", "plan", "have"}, "scan")
        target = args.get("target")
        if target not in ("cylinder", "object"):
            raise RequestError(
                "bad-args", f"scan target must be cylinder or object, not {target!r}"
            )
        plan = self._plan(target, args)
        have_list = args.get("have") or []
        if not isinstance(have_list, list) or not all(
            is_count(s, len(plan.views)) for s in have_list
        ):
            raise RequestError("bad-args", "have must list view indices of the plan")
        have = set(have_list)
        kept = self.buffer.adopt(plan_key(target, plan), request_id)
        self.buffer.ack(request_id, have & set(kept))
        resend = sorted(set(kept) - have)
        if kept:
            self._event(request_id, "log", message=f"resending {len(resend)} buffered segments")
        self.buffer.mark_resent(resend)
        for seq in resend:
            self.channel.send(encode_segment(request_id, seq, kept[seq]))
        todo = [s for s in range(len(plan.views)) if s not in have and s not in kept]
        if todo:
            self._acquire(request_id, target, plan, todo)
        if not self.buffer.wait_empty(self._abandon, self.settings.ack_timeout_s):
            raise RequestError(
                "unacknowledged",
                f"{len(self.buffer)} segments unacknowledged; they stay buffered for a resume",
            )
        return {
            "segments": len(plan.views),
            "acquired": len(todo),
            "resent": len(resend),
        }

    def _acquire(self, request_id: int, target: str, plan: ScanPlan, todo: list[int]) -> None:
        """Acquire the views ``todo`` (plan indices), numbering them as the full plan does."""
        index = views_in_section(plan)
        pending = iter(todo)
        held = len(plan.views) - len(todo)

        def on_segment(segment: Segment) -> None:
            seq = next(pending)
            segment = quantise_segment(replace(segment, view=index[seq]))
            self.buffer.put(seq, segment, self._abandon)
            self.channel.send(encode_segment(request_id, seq, segment))

        def on_progress(progress: Progress) -> None:
            self._event(
                request_id,
                "progress",
                target=progress.target,
                done=held + progress.done,
                total=len(plan.views),
                section=progress.section,
            )

        sub_plan = ScanPlan(tuple(plan.views[s] for s in todo))
        self._control = ScanControl()
        try:
            acquire(self.hardware, target, sub_plan, on_segment, on_progress, control=self._control)
        finally:
            self._control = None

    # --- quick operations ------------------------------------------------------------

    def _move(self, request_id: int, args: dict[str, Any]) -> dict[str, Any]:
        """Move one axis within its soft limits (positioning before a preview)."""
        check_keys(args, {"axis", "position"}, "move")
        axis, position = args.get("axis"), args.get("position")
        if axis not in ("lift", "turntable"):
            raise RequestError("bad-args", f"axis must be lift or turntable, not {axis!r}")
        if isinstance(position, bool) or not isinstance(position, int | float):
            raise RequestError("bad-args", "position must be a number")
        if self._running_id is not None:
            raise RequestError("busy", f"request {self._running_id} is moving the axes")
        self.limits.check(axis, float(position))
        (self.hardware.lift if axis == "lift" else self.hardware.turntable).move_to(float(position))
        return {"axis": axis, "position": float(position)}

    def _scan_control(self, op: str) -> ScanControl:
        control = self._control
        if control is None:
            raise RequestError("idle", f"no scan is running to {op}")
        return control

    def _pause(self, request_id: int, args: dict[str, Any]) -> dict[str, Any]:
        """Hold the running scan after the current view, laser off."""
        self._scan_control("pause").pause()
        self._event(self._running_id or 0, "status", state="paused")
        return {"state": "paused"}

    def _resume(self, request_id: int, args: dict[str, Any]) -> dict[str, Any]:
        """Let a paused scan go on."""
        self._scan_control("resume").resume()
        self._event(self._running_id or 0, "status", state="busy")
        return {"state": "busy"}

    def _abort(self, request_id: int, args: dict[str, Any]) -> dict[str, Any]:
        """End the running scan at the next view; what was sent stays valid."""
        self._scan_control("abort").abort()
        return {"state": "aborting"}

    def _exposure(self, request_id: int, args: dict[str, Any]) -> dict[str, Any]:
        """Set the camera's exposure (``exposure_us``) within its limits; report it and them."""
        check_keys(args, {"exposure_us"}, "exposure")
        camera = self.hardware.camera
        low, high = camera.exposure_range_us
        if "exposure_us" in args:
            value = args["exposure_us"]
            if isinstance(value, bool) or not isinstance(value, int):
                raise RequestError("bad-args", "exposure_us must be a whole number of us")
            if self._running_id is not None:
                # A scan's views must all share one exposure.
                raise RequestError("busy", f"request {self._running_id} is using the camera")
            try:
                camera.set_exposure(value)
            except ExposureRefused as exc:
                raise RequestError("limit", str(exc)) from None
        return {"exposure_us": camera.exposure_us, "min_us": low, "max_us": high}

    def _status(self, request_id: int, args: dict[str, Any]) -> dict[str, Any]:
        return {**self._state(), "retransmissions": self.buffer.retransmissions}

    def _shutdown(self, request_id: int, args: dict[str, Any]) -> dict[str, Any]:
        self.running = False
        return {}


def _png(image: np.ndarray) -> bytes:
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise RequestError("failed", "could not encode the image as PNG")
    return bytes(encoded.tobytes())
