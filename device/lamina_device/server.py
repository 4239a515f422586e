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
from a fixed table (``lamina_shared.ops``) whose typed arguments are validated, every
problem at once, against the device's limits before anything acts. A request never
ends the program: a refused one gets an error reply, and a fault inside an operation
(a bug) is logged with its traceback and answered ``internal``. A host that goes
away is not an exit either: the device switches the laser off and waits for the
next HELLO; only a port that stays unusable ends the program, with a non-zero status.
"""

from __future__ import annotations

import base64
import dataclasses
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
from lamina_device.extract import ExtractSettings, extract, to_segment
from lamina_device.hardware import Hardware
from lamina_device.motion import MotionError
from lamina_shared.capture import FrameError
from lamina_shared.limits import DeviceLimits
from lamina_shared.link import Channel, LinkClosed, Ticker, error_body, is_count, ok_body
from lamina_shared.ops import (
    OPS,
    ArgsError,
    ExposureArgs,
    FetchArgs,
    MoveArgs,
    NoArgs,
    PreviewArgs,
    Problems,
    ScanArgs,
    UnknownOp,
    check_plan,
    parse_args,
)
from lamina_shared.protocol import (
    CHUNK_BYTES,
    PROTOCOL_VERSION,
    ROW_SCALE,
    Kind,
    Message,
    ProtocolError,
    encode_chunk,
    encode_json,
    encode_segment,
    encode_segment_body,
    quantise_segment,
)
from lamina_shared.types import ScanPlan, Segment

log = logging.getLogger(__name__)


class RequestError(Exception):
    """A request the device refuses; ``code`` is machine-readable, the text is for people."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class Abandoned(Exception):
    """The host that asked for the running request has gone (a new session began)."""


class PortLost(ConnectionError):
    """The serial port stayed unusable: the program must end (non-zero) to be restarted."""


HARDWARE_FAULTS = (CameraError, MotionError, FrameError, OSError)
"""What an operation may meet on a working device (answered ``failed``); anything else
raised inside an operation is a bug (logged with its traceback, answered ``internal``)."""


@dataclass(frozen=True)
class ServerSettings:
    """Tunables of the device end; ``limits`` are the sizes the host learns from WELCOME."""

    limits: DeviceLimits = field(default_factory=DeviceLimits)
    rto_min_s: float = 0.25
    rto_max_s: float = 2.0
    ack_timeout_s: float = 60.0
    kept_transfers: int = 2
    kept_replies: int = 32
    link_retries: int = 3
    """Consecutive link failures, each 0.5 s apart, before the port counts as lost."""


@dataclass(frozen=True)
class AxisLimits:
    """Soft limits of the two axes; None means the axis has no limit that way."""

    lift_min_mm: float
    lift_max_mm: float
    turntable_min_deg: float | None = None
    turntable_max_deg: float | None = None

    @classmethod
    def of(cls, hardware: Hardware) -> AxisLimits:
        """Return the limits the hardware's axes declare."""
        lift, turntable = hardware.lift, hardware.turntable
        return cls(lift.min_mm, lift.max_mm, turntable.min_deg, turntable.max_deg)

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
        low: float | None
        high: float | None
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


Handler = Callable[[int, Any], dict[str, Any]]


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
            self.settings.limits.window_segments, self.settings.rto_min_s, self.settings.rto_max_s
        )
        self._abandon = threading.Event()
        self._worker: threading.Thread | None = None
        self._control: ScanControl | None = None
        self._running_id: int | None = None
        self._replies: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self._transfers: OrderedDict[int, bytes] = OrderedDict()
        self._next_transfer = 1
        self._heartbeat = Ticker(self.settings.limits.heartbeat_s)
        self._started_s = self._heard_s = time.monotonic()
        self._lock = threading.Lock()  # the reply cache and the running id, between threads
        self._handlers: dict[str, Handler] = {
            "grab_grid": self._grab_grid,
            "preview": self._preview,
            "scan": self._scan,
            "fetch": self._fetch,
            "move": self._move,
            "pause": self._pause,
            "resume": self._resume,
            "abort": self._abort,
            "exposure": self._exposure,
            "status": self._status,
            "shutdown": self._shutdown,
        }
        assert set(self._handlers) == set(OPS), "every operation of lamina_shared.ops is served"

    # --- the handshake ---------------------------------------------------------------

    def info(self) -> dict[str, Any]:
        """Return what the device tells the host about itself at the handshake."""
        hw = self.hardware
        width, height = hw.camera.size
        return {
            "protocol": PROTOCOL_VERSION,
            "software": f"lamina-device {__version__}",
            "hardware": hw.kind,
            "description": hw.description,
            "image_size": [width, height],
            "board": hw.board.to_dict() if hw.board else None,
            "cylinder_diameter_mm": hw.cylinder_diameter_mm,
            "default_plans": self._welcome_plans(),
            "axes": self.limits.to_dict(),
            "operations": sorted(OPS),
            "limits": self.settings.limits.to_dict(),
            "segment_encoding": {"row_scale": ROW_SCALE},
            "identity": dict(hw.identity),
            "extract": dataclasses.asdict(ExtractSettings()),
        }

    def _welcome_plans(self) -> dict[str, Any]:
        """Return the default plans in wire form, leaving out one too long for the WELCOME.

        A regular plan takes a few bytes; a replayed capture's irregular plan is listed
        and may not fit one message: the host then passes a plan, or asks ``scan`` with
        none (the device's default).
        """
        plans = {}
        budget = self.settings.limits.max_payload_bytes // 4
        for target, plan in self.hardware.default_plans.items():
            wire = plan.to_wire()
            if len(json.dumps(wire)) <= budget:
                plans[target] = wire
            else:
                log.warning("the default %s plan is too long for the WELCOME", target)
        return plans

    # --- the loop --------------------------------------------------------------------

    def serve(self) -> None:
        """Handle messages until asked to shut down.

        A host that goes away (its end stops reading, the cable is pulled) is not the
        end: the device stops what that host asked for, switches the laser off and
        waits for the next HELLO. Only a port that fails ``link_retries`` times in a
        row, with nothing received in between, raises :class:`PortLost`.
        """
        failures = 0
        try:
            while self.running:
                try:
                    message = self.channel.receive(timeout_s=0.02)
                    if message is not None:
                        failures = 0
                        self.handle(message)
                    self._tick()
                except LinkClosed as exc:
                    failures += 1
                    log.warning("host went away: %s; waiting for a new HELLO", exc)
                    self._host_lost()
                    if failures >= self.settings.link_retries:
                        raise PortLost(f"the serial port stays unusable: {exc}") from exc
                    time.sleep(0.5)
        finally:
            self._stop_worker()
            self.hardware.laser.off()

    def _host_lost(self) -> None:
        """Forget the host: stop its request, laser off, wait for a HELLO (buffer kept)."""
        self._stop_worker()
        self.hardware.laser.off()
        with self._lock:
            self._replies.clear()
            self._running_id = None
        self.greeted = False
        self.session = None

    def _tick(self) -> None:
        """Do what is due: a heartbeat, retransmissions (only to a greeted host)."""
        if not self.greeted:
            # Nobody listens: writing would only fill the line's buffer and block.
            return
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
            and len(seqs) + len(lost) <= self.settings.limits.max_ack_seqs
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
            name = body.get("op")
            args = parse_args(name, body.get("args", {}), self.settings.limits)
            assert isinstance(name, str)
            handler = self._handlers[name]
            if OPS[name].long:
                self._start(request_id, name, handler, args)
                return
            reply = ok_body(request_id, handler(request_id, args))
        except UnknownOp as exc:
            reply = error_body(request_id, "unknown-op", str(exc))
        except (RequestError, ArgsError) as exc:
            reply = error_body(request_id, exc.code, str(exc))
        except HARDWARE_FAULTS as exc:
            self.hardware.laser.off()
            reply = error_body(request_id, "failed", str(exc))
        except Exception as exc:
            reply = self._internal_error(request_id, body.get("op"), exc)
        self._finish(request_id, reply)

    def _internal_error(self, request_id: int, op: Any, exc: Exception) -> dict[str, Any]:
        """Log a fault inside an operation with its traceback; return the ``internal`` reply."""
        self.hardware.laser.off()
        log.error("internal error in request %d (%s)", request_id, str(op)[:40], exc_info=exc)
        return error_body(
            request_id,
            "internal",
            f"internal error in the device ({type(exc).__name__}): see the device log; "
            "the device stays up and the laser is off",
        )

    def _finish(self, request_id: int, reply: dict[str, Any]) -> None:
        """Keep the reply for repeated requests, mark the request done, send the reply."""
        try:
            frame = encode_json(Kind.REPLY, reply)
        except (ProtocolError, ValueError, TypeError) as exc:
            # A result that cannot travel is a bug here, not the host's doing.
            reply = self._internal_error(request_id, "reply", exc)
            frame = encode_json(Kind.REPLY, reply)
        with self._lock:
            self._replies[request_id] = reply
            while len(self._replies) > self.settings.kept_replies:
                self._replies.popitem(last=False)
            if self._running_id == request_id:
                self._running_id = None
        self.channel.send(frame)

    def _start(self, request_id: int, name: str, op: Handler, args: Any) -> None:
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

    def _work(self, request_id: int, op: Handler, args: Any) -> None:
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
        except (RequestError, ArgsError) as exc:
            reply = error_body(request_id, exc.code, str(exc))
        except HARDWARE_FAULTS as exc:
            reply = error_body(request_id, "failed", str(exc))
        except Exception as exc:
            reply = self._internal_error(request_id, "long request", exc)
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

    def _fetch(self, request_id: int, args: FetchArgs) -> dict[str, Any]:
        """Send pieces of a kept transfer again (the host asks for what it lacks)."""
        transfer = args.transfer
        if transfer not in self._transfers:
            raise RequestError("gone", f"transfer {transfer} is not kept any more: ask again")
        total = len(self._transfers[transfer])
        past = [list(r) for r in args.ranges if r[0] + r[1] > total]
        if past:
            raise RequestError("bad-args", f"range {past[0]} runs past the {total} bytes")
        for offset, length in args.ranges:
            self._send_range(request_id, transfer, offset, length)
        return {"sent": sum(length for _, length in args.ranges)}

    def _grab_grid(self, request_id: int, args: NoArgs) -> dict[str, Any]:
        result = self._offer(request_id, _png(grab_grid(self.hardware)))
        board = self.hardware.board
        return {**result, "board": board.to_dict() if board else None}

    def _preview(self, request_id: int, args: PreviewArgs) -> dict[str, Any]:
        """Capture one frame where the axes stand (laser on only during its exposure).

        With ``stripe`` the device takes the laser-off/laser-on pair a scan would, extracts
        the stripe with the scan's own extraction and returns it as a SEGMENT body.
        """
        laser, stripe = args.laser, args.stripe
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

    def _plan(self, args: ScanArgs) -> ScanPlan:
        """Return the plan to scan (the request's, or the default), within the axes' limits."""
        plan = args.plan
        if plan is None:
            plan = self.hardware.default_plans.get(args.target)
            if plan is None:
                raise RequestError("bad-args", f"no {args.target} views to scan on this device")
            problems = Problems()
            check_plan(plan.to_wire(), self.settings.limits, problems)
            if problems.items:
                # A configured or replayed default beyond the limits is refused like any plan.
                raise ArgsError("scan", problems.items, "limit")
        lifts = sorted({view.z_mm for view in plan.views})
        angles = sorted({view.angle_deg for view in plan.views})
        # The extremes decide: every height and angle between them is within limits too.
        for axis, values in (("lift", lifts), ("turntable", angles)):
            self.limits.check(axis, values[0])
            self.limits.check(axis, values[-1])
        return plan

    def _scan(self, request_id: int, args: ScanArgs) -> dict[str, Any]:
        """Send every view of the plan the host does not hold: from the buffer or acquired."""
        target = args.target
        plan = self._plan(args)
        outside = [s for s in args.have if s >= len(plan.views)]
        if outside:
            raise RequestError(
                "bad-args",
                f"have must list view indices of the plan: {outside[0]} is beyond its "
                f"{len(plan.views)} views",
            )
        have = set(args.have)
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

    def _move(self, request_id: int, args: MoveArgs) -> dict[str, Any]:
        """Move one axis within its soft limits (positioning before a preview)."""
        axis, position = args.axis, args.position
        if self._running_id is not None:
            raise RequestError("busy", f"request {self._running_id} is moving the axes")
        self.limits.check(axis, position)
        (self.hardware.lift if axis == "lift" else self.hardware.turntable).move_to(position)
        return {"axis": axis, "position": position}

    def _scan_control(self, op: str) -> ScanControl:
        control = self._control
        if control is None:
            raise RequestError("idle", f"no scan is running to {op}")
        return control

    def _pause(self, request_id: int, args: NoArgs) -> dict[str, Any]:
        """Hold the running scan after the current view, laser off."""
        self._scan_control("pause").pause()
        self._event(self._running_id or 0, "status", state="paused")
        return {"state": "paused"}

    def _resume(self, request_id: int, args: NoArgs) -> dict[str, Any]:
        """Let a paused scan go on."""
        self._scan_control("resume").resume()
        self._event(self._running_id or 0, "status", state="busy")
        return {"state": "busy"}

    def _abort(self, request_id: int, args: NoArgs) -> dict[str, Any]:
        """End the running scan at the next view; what was sent stays valid."""
        self._scan_control("abort").abort()
        return {"state": "aborting"}

    def _exposure(self, request_id: int, args: ExposureArgs) -> dict[str, Any]:
        """Set the camera's exposure (``exposure_us``) within its limits; report it and them."""
        camera = self.hardware.camera
        low, high = camera.exposure_range_us
        value = args.exposure_us
        if value is not None:
            if self._running_id is not None:
                # A scan's views must all share one exposure.
                raise RequestError("busy", f"request {self._running_id} is using the camera")
            try:
                camera.set_exposure(value)
            except ExposureRefused as exc:
                raise RequestError("limit", str(exc)) from None
        return {"exposure_us": camera.exposure_us, "min_us": low, "max_us": high}

    def _status(self, request_id: int, args: NoArgs) -> dict[str, Any]:
        return {**self._state(), "retransmissions": self.buffer.retransmissions}

    def _shutdown(self, request_id: int, args: NoArgs) -> dict[str, Any]:
        self.running = False
        return {}


def _png(image: np.ndarray) -> bytes:
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise RequestError("failed", "could not encode the image as PNG")
    return bytes(encoded.tobytes())
