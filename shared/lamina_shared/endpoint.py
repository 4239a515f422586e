"""One request/reply layer for both ends of the link: a reader thread and per-request waiters.

As pyserial's ``serial.threaded.ReaderThread`` hands every byte it reads to one protocol
object, a :class:`Dispatcher` is the only reader of its :class:`~lamina_shared.link.Channel`
and hands every decoded message to one place: a message that belongs to an open
request (its REPLY, EVENTs, SEGMENTs, CHUNKs, or a HEARTBEAT naming it) goes to that
request's :class:`Waiter`; anything else goes to ``on_other``. Any thread may therefore
send a request and wait for its own reply, while another thread's request runs: a
scan on one thread, its pause or abort on another.

Heartbeats go to every open waiter: one naming the waiter's request says the peer is
at work on it, one naming another request (or none) says the peer never got ours, so
the requester may ask again early (see ``lamina_host.link.client.DeviceClient.request``).
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
import zlib
from collections import OrderedDict
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any

from lamina_shared.errors import LaminaError
from lamina_shared.limits import DeviceLimits
from lamina_shared.link import Channel, LinkClosed, Ticker, error_body, is_count, ok_body
from lamina_shared.messages import (
    Ack,
    DeviceHeartbeat,
    Event,
    Hello,
    HostHeartbeat,
    MessageError,
    StatusEvent,
)
from lamina_shared.ops import OPS, ArgsError, FetchArgs, UnknownOp, parse_args
from lamina_shared.protocol import (
    CHUNK_BYTES,
    PROTOCOL_VERSION,
    Chunk,
    Kind,
    Message,
    ProtocolError,
    SegmentEvent,
    encode_chunk,
    encode_json,
    encode_segment,
)
from lamina_shared.replies import REPLIES, FetchReply, Reply, TransferOffer
from lamina_shared.types import Segment

log = logging.getLogger(__name__)

POLL_S = 0.02
"""How long the reader waits for a message before it runs ``on_tick``."""


def request_id_of(message: Message) -> int | None:
    """Return the request a message belongs to (a heartbeat: the one the peer works on)."""
    body = message.body
    if isinstance(body, Chunk | SegmentEvent):
        return body.request_id
    if not isinstance(body, dict):
        return None
    if message.kind is Kind.HEARTBEAT:
        try:
            return DeviceHeartbeat.from_wire(body).request
        except MessageError:
            return None  # names no request we could trust
    found = body.get("id")
    return found if isinstance(found, int) and not isinstance(found, bool) else None


class Waiter:
    """The messages of one open request, in arrival order, for the thread that sent it."""

    def __init__(self, request_id: int, dispatcher: Dispatcher) -> None:
        self.request_id = request_id
        self._dispatcher = dispatcher
        self._queue: queue.SimpleQueue[Message] = queue.SimpleQueue()

    def put(self, message: Message) -> None:
        """Hand one message to the waiting thread (called by the reader)."""
        self._queue.put(message)

    def get(self, timeout_s: float) -> Message | None:
        """Return the next message of this request, or None after ``timeout_s``.

        Raises:
            LinkClosed: the reader met a closed link (the peer went away).
        """
        try:
            return self._queue.get(timeout=timeout_s)
        except queue.Empty:
            self._dispatcher.raise_failure()
            return None


class Dispatcher:
    """The reader thread of one end: every message goes to its request's waiter.

    ``on_other`` receives what belongs to no open request (a WELCOME, a late reply of
    a request given up, the peer's unsolicited messages); ``on_tick`` runs after each
    poll (heartbeats that fall due). Both run on the reader thread and must not block.
    """

    def __init__(
        self,
        channel: Channel,
        on_other: Callable[[Message], None] | None = None,
        on_tick: Callable[[], None] | None = None,
        poll_s: float = POLL_S,
    ) -> None:
        self.channel = channel
        self._on_other = on_other
        self._on_tick = on_tick
        self._poll_s = poll_s
        self._waiters: dict[int, Waiter] = {}
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self.failure: LinkClosed | None = None
        """Why the reader stopped, if the link closed under it."""

    def start(self) -> None:
        """Start the reader thread (once; later calls do nothing while it runs).

        A channel has one reader: another dispatcher still reading it (a host object
        given up for a new session on the same port) is stopped first.
        """
        previous = self.channel.reader
        if previous is not None and previous is not self:
            previous.stop()
        self.channel.reader = self
        with self._lock:
            if self._thread is not None and self._thread.is_alive():
                return
            self.failure = None
            self._stop.clear()
            self._thread = threading.Thread(target=self._run, name="link-reader", daemon=True)
            self._thread.start()

    def stop(self) -> None:
        """Stop the reader thread and wait for it."""
        self._stop.set()
        thread = self._thread
        if thread is not None and thread is not threading.current_thread():
            thread.join(timeout=2)

    @property
    def open_requests(self) -> int:
        """Return how many requests are waiting for their reply."""
        with self._lock:
            return len(self._waiters)

    def open(self, request_id: int) -> Waiter:
        """Register a waiter for ``request_id`` (before its request is sent)."""
        waiter = Waiter(request_id, self)
        with self._lock:
            self._waiters[request_id] = waiter
        return waiter

    def close(self, request_id: int) -> None:
        """Forget the waiter of ``request_id``; later messages of it go to ``on_other``."""
        with self._lock:
            self._waiters.pop(request_id, None)

    def raise_failure(self) -> None:
        """Raise LinkClosed if the reader stopped because the link closed."""
        if self.failure is not None:
            raise self.failure

    def dispatch(self, message: Message) -> None:
        """Hand one message to its waiter (heartbeats to all of them) or to ``on_other``."""
        with self._lock:
            if message.kind is Kind.HEARTBEAT:
                targets = list(self._waiters.values())
            else:
                request_id = request_id_of(message)
                found = self._waiters.get(request_id) if request_id is not None else None
                targets = [found] if found is not None else []
        for waiter in targets:
            waiter.put(message)
        if not targets and self._on_other is not None:
            self._on_other(message)

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                message = self.channel.receive(self._poll_s)
                if message is not None:
                    self.dispatch(message)
                if self._on_tick is not None:
                    self._on_tick()
            except LinkClosed as exc:
                self.failure = exc
                return
            except Exception:  # a bug in a handler must not silence the link
                log.exception("the link reader met an error; it goes on reading")


# --- the device's end -------------------------------------------------------------------


class RequestError(LaminaError):
    """A request the device refuses; ``code`` is machine-readable, the text is for people."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class Abandoned(Exception):
    """The host that asked for the running request has gone (a new session began)."""


class PortLost(LaminaError, ConnectionError):
    """The serial port stayed unusable: the program must end (non-zero) to be restarted."""


@dataclass(frozen=True)
class ServerSettings:
    """Tunables of the device end; ``limits`` are the sizes the host learns from WELCOME."""

    limits: DeviceLimits = field(default_factory=DeviceLimits)
    rto_min_s: float = 0.25
    """Shortest retransmission timeout of a segment, however fast the round trips."""
    rto_max_s: float = 2.0
    """Longest retransmission timeout, also the cap of the doubling on each resend."""
    ack_timeout_s: float = 60.0
    """How long a capture waits for its last segments to be acknowledged before it ends."""
    kept_transfers: int = 2
    """Binary transfers kept for the host to fetch again; older ones are dropped."""
    kept_replies: int = 32
    """Replies kept so a repeated request id is answered again instead of run twice."""
    link_retries: int = 3
    """Consecutive link failures, each 0.5 s apart, before the port counts as lost."""


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


Handler = Callable[[int, Any], Reply]
"""An operation: (request id, typed arguments) -> its typed reply
(:data:`lamina_shared.replies.REPLIES` names the class of each)."""


class DeviceEndpoint:
    """The device's end of the protocol: handshake, requests, acks, retries, heartbeats.

    It knows no hardware: a subclass gives the operations table (one :data:`Handler`
    per operation of :data:`lamina_shared.ops.OPS` except ``fetch``, which this class
    serves from its kept transfers) and the hooks :meth:`welcome`, :meth:`make_safe`,
    :meth:`link_alive`, :meth:`abort_running` and :meth:`paused`. Requests are
    answered once and their replies cached, so a repeated request (same id) gets the
    same reply and never runs twice; long operations run on a worker thread while the
    line is still read; segments stay in :attr:`buffer` until acknowledged.
    """

    faults: tuple[type[BaseException], ...] = (OSError,)
    """What an operation may meet on a working device (answered ``failed``); anything
    else raised inside an operation is a bug (logged with its traceback, ``internal``)."""
    log = log

    def __init__(
        self,
        channel: Channel,
        operations: Mapping[str, Handler],
        settings: ServerSettings | None = None,
    ) -> None:
        self.channel = channel
        self.settings = settings or ServerSettings()
        self.greeted = False
        self.running = True
        self.session: str | None = None
        self.buffer = SegmentBuffer(
            self.settings.limits.window_segments, self.settings.rto_min_s, self.settings.rto_max_s
        )
        self.abandoned = threading.Event()
        """Set when the host of the running request has gone: the operation must stop."""
        self._worker: threading.Thread | None = None
        self._running_id: int | None = None
        self._replies: OrderedDict[int, dict[str, Any]] = OrderedDict()
        self._transfers: OrderedDict[int, bytes] = OrderedDict()
        self._next_transfer = 1
        self._heartbeat = Ticker(self.settings.limits.heartbeat_s)
        self._started_s = self._heard_s = time.monotonic()
        self._lock = threading.Lock()  # the reply cache and the running id, between threads
        self._handlers: dict[str, Handler] = {**operations, "fetch": self._fetch}
        missing = set(OPS) ^ set(self._handlers)
        if missing:
            raise ValueError(f"the operations table differs from lamina_shared.ops: {missing}")
        unreplied = set(OPS) ^ set(REPLIES)
        if unreplied:
            raise ValueError(f"lamina_shared.replies differs from lamina_shared.ops: {unreplied}")

    # --- hooks of the device ---------------------------------------------------------

    def welcome(self) -> dict[str, Any]:
        """Return the WELCOME body (the device's description of itself)."""
        return {"protocol": PROTOCOL_VERSION}

    def make_safe(self) -> None:
        """Put the hardware in its safe state (laser off) after a fault or a lost host."""

    def link_alive(self) -> None:
        """Note that the host was heard (a watchdog's feed)."""

    def abort_running(self) -> None:
        """Ask the running operation to stop soon (its host has gone)."""

    def paused(self) -> bool:
        """Return True while the running operation is paused."""
        return False

    @property
    def running_id(self) -> int | None:
        """Return the id of the request running on the worker, if any."""
        return self._running_id

    # --- the loop --------------------------------------------------------------------

    def serve(self) -> None:
        """Handle messages until asked to shut down.

        A host that goes away (its end stops reading, the cable is pulled) is not the
        end: the device stops what that host asked for, puts the hardware in its safe
        state and waits for the next HELLO. Only a port that fails ``link_retries``
        times in a row, with nothing received in between, raises :class:`PortLost`.
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
                    self.log.warning("host went away: %s; waiting for a new HELLO", exc)
                    self._host_lost()
                    if failures >= self.settings.link_retries:
                        raise PortLost(f"the serial port stays unusable: {exc}") from exc
                    time.sleep(0.5)
        finally:
            self._stop_worker()
            self.make_safe()

    def _host_lost(self) -> None:
        """Forget the host: stop its request, safe state, wait for a HELLO (buffer kept)."""
        self._stop_worker()
        self.make_safe()
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
            self.channel.send(encode_json(Kind.HEARTBEAT, self.state().to_wire()))
        overdue = self.buffer.overdue()
        if overdue:
            self.channel.sizer.penalise()
        for seq, segment in overdue:
            self.channel.send(encode_segment(self.buffer.request_id, seq, segment))

    def state(self) -> DeviceHeartbeat:
        """Return what a heartbeat says: idle, busy or paused, the running request, unacked."""
        busy = self._running_id is not None
        return DeviceHeartbeat(
            "paused" if busy and self.paused() else "busy" if busy else "idle",
            self._running_id,
            len(self.buffer),
            time.monotonic() - self._started_s,
        )

    def handle(self, message: Message) -> None:
        """Answer one message from the host."""
        silence_s = time.monotonic() - self._heard_s
        self._heard_s = time.monotonic()
        self.link_alive()
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
            self._host_heartbeat(message.body)
        else:
            self.log.warning("ignoring unexpected %s message from the host", message.kind.name)

    def _hello(self, body: dict[str, Any]) -> None:
        try:
            hello: Hello | None = Hello.from_wire(body)
        except MessageError as exc:
            # Still answered, with the versions alone: the peer learns whom it talks to.
            self.log.warning("a malformed HELLO (%s)", exc)
            hello = None
        self.greeted = hello is not None and hello.protocol == PROTOCOL_VERSION
        session = hello.session if hello is not None else None
        if self.greeted and session != self.session:
            # A new host process (or one that lost track): what the old one asked for is
            # abandoned, but buffered segments stay for it to resume with.
            self._stop_worker()
            self._replies.clear()
            self.session = session
        welcome = self.welcome()
        if not self.greeted:
            # A peer of another version may not read fragments: the versions alone go
            # whole, for it to name the mismatch.
            welcome = {k: welcome[k] for k in ("protocol", "software") if k in welcome}
        self.channel.send(encode_json(Kind.WELCOME, welcome))

    def _host_heartbeat(self, body: dict[str, Any]) -> None:
        """Check a host heartbeat's form; hearing it at all is what matters (see :meth:`handle`)."""
        try:
            HostHeartbeat.from_wire(body)
        except MessageError as exc:
            self.log.warning("ignoring a malformed heartbeat (%s)", exc)

    def _ack(self, body: dict[str, Any]) -> None:
        try:
            ack = Ack.from_wire(body, self.settings.limits)
        except MessageError as exc:
            self.log.warning("ignoring a malformed acknowledgement (%s)", exc)
            return
        self.buffer.ack(ack.request_id, list(ack.seqs))
        if ack.request_id == self.buffer.request_id:
            for seq, segment in self.buffer.resend_lost(list(ack.lost)):
                self.channel.send(encode_segment(ack.request_id, seq, segment))

    # --- requests --------------------------------------------------------------------

    def _request(self, body: dict[str, Any]) -> None:
        request_id = body.get("id")
        if not is_count(request_id):
            self.log.warning("ignoring a request without a valid id")
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
            reply = ok_body(request_id, _wire_reply(name, handler(request_id, args)))
        except UnknownOp as exc:
            reply = error_body(request_id, "unknown-op", str(exc))
        except (RequestError, ArgsError) as exc:
            reply = error_body(request_id, exc.code, str(exc))
        except self.faults as exc:
            self.make_safe()
            reply = error_body(request_id, "failed", str(exc))
        except Exception as exc:
            reply = self._internal_error(request_id, body.get("op"), exc)
        self._finish(request_id, reply)

    def _internal_error(self, request_id: int, op: Any, exc: Exception) -> dict[str, Any]:
        """Log a fault inside an operation with its traceback; return the ``internal`` reply."""
        self.make_safe()
        self.log.error("internal error in request %d (%s)", request_id, str(op)[:40], exc_info=exc)
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
        self.abandoned.clear()
        self.event(StatusEvent(request_id, "busy", name))
        # The worker marks itself done in _finish, under the lock, with its reply cached.
        self._worker = threading.Thread(
            target=self._work, args=(request_id, name, op, args), name=f"device-{name}", daemon=True
        )
        self._worker.start()

    def _work(self, request_id: int, name: str, op: Handler, args: Any) -> None:
        try:
            reply = ok_body(request_id, _wire_reply(name, op(request_id, args)))
        except Abandoned:
            self.log.info("a request was abandoned by its host")
            with self._lock:
                self._running_id = None
            return
        except (RequestError, ArgsError) as exc:
            reply = error_body(request_id, exc.code, str(exc))
        except self.faults as exc:
            reply = error_body(request_id, "failed", str(exc))
        except Exception as exc:
            reply = self._internal_error(request_id, "long request", exc)
        finally:
            self.make_safe()
        try:
            self._finish(request_id, reply)
        except LinkClosed:
            self.log.info("host went away before the reply")

    def _stop_worker(self) -> None:
        worker = self._worker
        if worker is not None and worker.is_alive():
            self.abandoned.set()
            self.abort_running()
            worker.join(timeout=30)
        self._worker = None

    def event(self, event: Event) -> None:
        """Send an EVENT (progress, status, log)."""
        self.channel.send(encode_json(Kind.EVENT, event.to_wire()))

    # --- binary transfers ------------------------------------------------------------

    def offer(self, request_id: int, data: bytes) -> TransferOffer:
        """Keep ``data`` for fetching, push it once, return its description."""
        transfer = self._next_transfer
        self._next_transfer += 1
        self._transfers[transfer] = data
        while len(self._transfers) > self.settings.kept_transfers:
            self._transfers.popitem(last=False)
        self._send_range(request_id, transfer, 0, len(data))
        return TransferOffer(transfer, len(data), zlib.crc32(data))

    def _send_range(self, request_id: int, transfer: int, offset: int, length: int) -> None:
        data = self._transfers[transfer]
        for at in range(offset, offset + length, CHUNK_BYTES):
            piece = data[at : min(at + CHUNK_BYTES, offset + length)]
            self.channel.send(encode_chunk(request_id, transfer, at, len(data), piece))

    def _fetch(self, request_id: int, args: FetchArgs) -> FetchReply:
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
        return FetchReply(sum(length for _, length in args.ranges))

    def send_segment(self, request_id: int, seq: int, segment: Segment) -> None:
        """Send view ``seq`` of a scan (the caller holds it in :attr:`buffer` first)."""
        self.channel.send(encode_segment(request_id, seq, segment))


def _wire_reply(op: str, reply: Reply) -> dict[str, Any]:
    """Return the wire form of ``op``'s reply; a reply of another class is a bug here.

    Raises:
        TypeError: ``reply`` is not of the class :data:`~lamina_shared.replies.REPLIES`
            names for ``op`` (answered ``internal``: the host could not read it).
    """
    expected = REPLIES[op]
    if type(reply) is not expected:
        raise TypeError(f"{op} replied with a {type(reply).__name__}, not a {expected.__name__}")
    return reply.to_wire()


__all__ = [
    "Abandoned",
    "DeviceEndpoint",
    "Dispatcher",
    "PortLost",
    "RequestError",
    "SegmentBuffer",
    "ServerSettings",
    "Waiter",
    "request_id_of",
]
