"""The host end of the link: handshake with the device and run requests reliably.

Requests are repeated (same id) until the device answers, and the device answers a
repeat from its reply cache, so a lost frame in either direction costs a timeout,
never a request run twice. A scan's segments are handed to the caller (who stores
them) before they are acknowledged (:mod:`lamina_host.link.scanning`); transfers are
fetched piece by piece until complete (:mod:`lamina_host.link.transfer`).

One reader thread (:class:`lamina_shared.endpoint.Dispatcher`) reads the link and hands
each message to the request it belongs to, so any thread may send a request and wait
for its own reply: a scan runs on one thread while another pauses or aborts it. The
requests are built from the typed arguments of :mod:`lamina_shared.ops`, the schemas
the device checks them with; the WELCOME is read with :mod:`lamina_shared.messages`.
Which device to open, and how, is :mod:`lamina_host.link.connect`'s.
"""

from __future__ import annotations

import dataclasses
import logging
import queue
import secrets
import subprocess
import threading
import time
from collections.abc import Callable, Collection
from contextlib import suppress
from dataclasses import dataclass
from typing import Any, Protocol, TypeVar

import cv2
import numpy as np

from lamina_host.link.errors import DeviceError, RequestRefused, ScanStopped
from lamina_host.link.handshake import hello_body, in_use, read_welcome, refusal_of
from lamina_host.link.identity import scan_identity
from lamina_host.link.scanning import EventHandler, IndexedSegmentHandler, ScanReceiver
from lamina_host.link.spawn import StderrTail
from lamina_host.link.transfer import Offering, fetch_transfer
from lamina_shared import replies
from lamina_shared.endpoint import Dispatcher, request_id_of
from lamina_shared.limits import DeviceLimits
from lamina_shared.link import Channel, LinkClosed, Ticker
from lamina_shared.messages import HostHeartbeat, MessageError, Welcome
from lamina_shared.ops import (
    EstimateArgs,
    ExposureArgs,
    ExtractChanges,
    MoveArgs,
    NoArgs,
    PreviewArgs,
    ScanArgs,
    request_args,
)
from lamina_shared.protocol import (
    PROTOCOL_VERSION,
    Kind,
    Message,
    ProtocolError,
    decode_segment_body,
    encode_json,
)
from lamina_shared.replies import ScanEstimate, StatusReply
from lamina_shared.types import BoardSpec, ScanPlan, Segment

SPAWNED_STARTUP_S = 120.0
"""How long a device program started here may take to answer (a replay validating a big
capture), as long as it is running."""
STARTUP_NOTICE_S = 5.0
"""After this long without an answer, say that the device program is still starting."""
PROCESS_CHECK_S = 0.25
"""How often a request checks that a device program started here is still running."""

log = logging.getLogger(__name__)

MessageHandler = Callable[[Message], object]
"""Receives each message of one request but its reply (events, segments, chunks, heartbeats)."""


class _Readable(Protocol):
    @classmethod
    def from_wire(cls, body: Any) -> Any: ...  # pragma: no cover - protocol


R = TypeVar("R", bound=_Readable)


@dataclass(frozen=True)
class Preview:
    """One preview frame and, when asked for, the stripe the device extracted there."""

    image: np.ndarray
    stripe: Segment | None = None


class LinkStats:
    """What the link cost: resent requests, duplicate segments, fetch rounds."""

    request_retries: int = 0
    duplicate_segments: int = 0
    fetch_rounds: int = 0


class DeviceClient:
    """Requests and replies over a :class:`Channel`, with the device's events passed on."""

    def __init__(
        self,
        channel: Channel,
        process: subprocess.Popen[bytes] | None = None,
        idle_timeout_s: float = 30.0,
        retry_s: float = 1.0,
    ) -> None:
        self.channel = channel
        self.process = process
        self.idle_timeout_s = idle_timeout_s
        self.retry_s = retry_s
        self.info: Welcome | None = None
        self.session = secrets.token_hex(8)
        self.stats = LinkStats()
        self._heartbeat = Ticker(0.5)
        self._next_id = 1
        self._id_lock = threading.Lock()  # request ids and the scan's notice, between threads
        self._scanning = False
        self._on_notice: Callable[[str], object] | None = None
        self._welcomes: queue.SimpleQueue[Message] = queue.SimpleQueue()
        self._refusal: str | None = None
        """Why the device turned this host away (a WELCOME's ``refused``), if it did."""
        self.dispatcher = Dispatcher(channel, on_other=self._unclaimed, on_tick=self._tick)
        """The link's one reader: hands each reply to the thread waiting for it."""
        self.extract: ExtractChanges | None = None
        """Extraction settings changed for this session's scans (``lamina scan --extract``)."""
        self.spawned: str | None = None
        """What a device program started here was asked to acquire
        (:func:`lamina_host.link.identity.spawned_source`)."""
        self._process_checked_s = 0.0
        self.stderr_tail = (
            StderrTail(process.stderr) if process is not None and process.stderr else None
        )
        """What a device program started here writes to stderr, read while it runs."""

    def _new_id(self) -> int:
        with self._id_lock:
            request_id = self._next_id
            self._next_id += 1
            return request_id

    def identity(self) -> dict[str, Any]:
        """Return the identity of what this device acquires (see :func:`.identity.scan_identity`).

        Its ``extract`` is the effective extraction: the device's configured settings
        (WELCOME) with this session's changes (:attr:`extract`).
        """
        welcome = self.info or Welcome(PROTOCOL_VERSION)
        if self.extract is not None:
            configured = welcome.extract.as_dict() if welcome.extract is not None else {}
            effective = {**configured, **self.extract.as_dict()}
            welcome = dataclasses.replace(welcome, extract=ExtractChanges(tuple(effective.items())))
        return scan_identity(welcome, self.spawned)

    def _device_exit_message(self) -> str | None:
        """Return one line on a device program started here that has exited, else None."""
        if self.process is None or self.process.poll() is None:
            return None
        lines = self.stderr_tail.lines() if self.stderr_tail is not None else []
        code = self.process.returncode
        how = f"was killed (signal {-code})" if code < 0 else f"exited (status {code})"
        return f"the device program {how}" + (f": {lines[-1]}" if lines else "")

    def _check_process(self, now: float) -> None:
        """Raise DeviceError soon after a device program started here has exited."""
        if self.process is None or now - self._process_checked_s < PROCESS_CHECK_S:
            return
        self._process_checked_s = now
        if (exit_message := self._device_exit_message()) is not None:
            raise DeviceError(exit_message)

    def hello(
        self, timeout_s: float = 20.0, on_notice: Callable[[str], object] | None = None
    ) -> Welcome:
        """Handshake; return the device's information or raise :class:`DeviceError`.

        A device program started here is waited for while it runs, up to
        :data:`SPAWNED_STARTUP_S` (it may be validating a big capture); ``on_notice``
        hears once that it is still starting.
        """
        start = time.monotonic()
        if self.process is not None:
            timeout_s = max(timeout_s, SPAWNED_STARTUP_S)
        deadline = start + timeout_s
        noticed = False
        hello = hello_body(self.session)
        self.dispatcher.start()
        while not self._welcomes.empty():
            self._welcomes.get_nowait()  # answers to an earlier handshake
        while time.monotonic() < deadline:
            slow = time.monotonic() - start > STARTUP_NOTICE_S
            if slow and self.process is not None and not noticed and on_notice is not None:
                on_notice(f"waiting for the device program to start (up to {timeout_s:.0f} s)")
                noticed = True
            try:
                # Repeat HELLO: a device that opened its port late flushed the earlier ones.
                self.channel.send(encode_json(Kind.HELLO, hello))
                try:
                    body = self._welcomes.get(timeout=0.5).body
                except queue.Empty:
                    body = None
                self._raise_refusal()
                if body is not None:
                    return self._welcome(body)
                self.dispatcher.raise_failure()
            except LinkClosed:
                self._await_refusal()  # a refusal came just before the device hung up
                raise
            if (exit_message := self._device_exit_message()) is not None:
                raise DeviceError(exit_message)
        if self.process is not None:
            raise DeviceError(
                f"the device program started here has not answered in {timeout_s:.0f} s: "
                "check its capture or configuration with lamina-device serve, then try again"
            )
        raise DeviceError(
            "no answer from the device: check the cable and that lamina-device serve is running"
        )

    def _welcome(self, body: dict[str, Any]) -> Welcome:
        self.info = read_welcome(body)
        return self.info

    def _unclaimed(self, message: Message) -> None:
        """Keep a WELCOME for :meth:`hello`; drop what belongs to no open request.

        A WELCOME that ``refused`` the session (a device service that already has a
        host) is remembered, so :meth:`hello` says why even after the device hung up.
        """
        if message.kind is Kind.WELCOME:
            refusal = refusal_of(message.body)
            if refusal is not None:
                self._refusal = refusal
                return
            self._welcomes.put(message)

    def _await_refusal(self, wait_s: float = 1.0) -> None:
        """Raise DeviceError if a refusal arrives before the reader meets the hang-up."""
        deadline = time.monotonic() + wait_s
        while self._refusal is None and self.dispatcher.failure is None:
            if time.monotonic() >= deadline:
                break
            time.sleep(0.02)
        self._raise_refusal()

    def _raise_refusal(self) -> None:
        """Raise DeviceError if the device turned this host away."""
        if self._refusal is not None:
            raise in_use(self._refusal)

    def _tick(self) -> None:
        """Send our heartbeat while a request is open (on the reader thread)."""
        if self.dispatcher.open_requests and self._heartbeat.due():
            self.channel.send(encode_json(Kind.HEARTBEAT, HostHeartbeat(self.session).to_wire()))

    def request(
        self, op: str, args: Any = None, on_event: MessageHandler | None = None
    ) -> dict[str, Any]:
        """Send one request until answered; pass its events on; return the reply's result.

        Any thread may call this while another thread's request runs: the link's reader
        (:attr:`dispatcher`) hands each thread the messages of its own request, and
        ``on_event`` runs on the calling thread (and also hears the device's heartbeats
        that name this request). ``args`` is the operation's typed
        arguments (a dataclass of :mod:`lamina_shared.ops`) or their JSON object.
        """
        if args is not None and not isinstance(args, dict):
            args = request_args(args)
        request_id = self._new_id()
        frame = encode_json(Kind.REQUEST, {"id": request_id, "op": op, "args": args or {}})
        self.dispatcher.start()
        waiter = self.dispatcher.open(request_id)
        try:
            self.channel.send(frame)
            last_related = time.monotonic()
            while True:
                message = waiter.get(0.05)
                now = time.monotonic()
                self._check_process(now)
                if message is None:
                    if now - self.channel.last_received_s > self.idle_timeout_s:
                        raise DeviceError(
                            self._device_exit_message()
                            or f"the device stopped answering during {op}: check the cable"
                        )
                    if now - last_related > self.retry_s:
                        # Our request or its reply was lost (or the line is down): ask again;
                        # the device answers a repeat from its reply cache, never runs it twice.
                        self._resend(frame)
                        last_related = now
                    continue
                if message.kind is Kind.HEARTBEAT:
                    if request_id_of(message) == request_id:
                        last_related = now
                        if on_event is not None:
                            on_event(message)
                    elif now - last_related > 0.3:
                        # The device says it is not working on our request: it never got
                        # it, or its reply was lost. Ask again now rather than after a timeout.
                        self._resend(frame)
                        last_related = now
                    continue
                last_related = now
                if message.kind is Kind.REPLY:
                    return _result(op, message.body)
                if on_event is not None:
                    on_event(message)
        finally:
            self.dispatcher.close(request_id)

    def call(
        self,
        op: str,
        reply_type: type[R],
        args: Any = None,
        on_event: MessageHandler | None = None,
    ) -> R:
        """Run :meth:`request` and read its result as ``op``'s typed reply.

        Raises:
            DeviceError: the device refused, or its reply is malformed (every problem named).
        """
        result = self.request(op, args, on_event)
        try:
            reply: R = reply_type.from_wire(result)
        except MessageError as exc:
            raise DeviceError(f"the device's {op} reply is malformed ({exc})") from None
        return reply

    def _resend(self, frame: bytes) -> None:
        self.channel.sizer.penalise()
        self.channel.send(frame)
        with self._id_lock:
            self.stats.request_retries += 1

    def _fetch(
        self, op: str, reply_type: type[Offering], args: Any = None
    ) -> tuple[bytes, Offering]:
        """Run a request that offers a binary transfer; fetch what did not arrive."""
        max_bytes = (self.info.limits if self.info else DeviceLimits()).max_fetch_bytes
        data, reply, rounds = fetch_transfer(self.call, op, reply_type, args, max_bytes)
        self.stats.fetch_rounds += rounds
        return data, reply

    def grab_grid(self) -> tuple[np.ndarray, BoardSpec]:
        """Fetch the calibration board image and the board's geometry."""
        data, reply = self._fetch("grab_grid", replies.GridReply)
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise DeviceError("the calibration image could not be decoded")
        if reply.board is None:
            raise DeviceError("the device does not know its calibration board: configure it")
        return image, reply.board

    def preview(self, laser: bool = False, stripe: bool = True) -> Preview:
        """Fetch one camera frame taken where the axes stand, and the stripe found there.

        Args:
            laser: show the laser-on frame rather than the laser-off one.
            stripe: also have the device take a laser-off/on pair and extract the stripe
                (the laser then flashes for one frame even when ``laser`` is False).
        """
        data, reply = self._fetch("preview", replies.PreviewReply, PreviewArgs(laser, stripe))
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise DeviceError("the preview frame could not be decoded")
        found = None
        if stripe:
            if reply.stripe is None:
                raise DeviceError("the device's preview reply holds no stripe")
            try:
                found = decode_segment_body(reply.stripe)
            except ProtocolError as exc:
                raise DeviceError(f"the device's preview stripe is malformed ({exc})") from None
            height, width = image.shape[:2]
            if len(found.segment) and (
                int(found.segment.cols[-1]) >= width or float(found.segment.rows.max()) >= height
            ):
                raise DeviceError("the device's preview stripe lies outside its frame")
        return Preview(image, found.segment if found else None)

    def set_exposure(self, exposure_us: int) -> int:
        """Set the camera's exposure; return the exposure the device now uses.

        Raises:
            DeviceError: outside the camera's range (the message names it) or a scan runs.
        """
        return self.call(
            "exposure", replies.ExposureReply, ExposureArgs(int(exposure_us))
        ).exposure_us

    def exposure(self) -> tuple[int, int, int]:
        """Return the camera's (exposure, min, max) in microseconds."""
        reply = self.call("exposure", replies.ExposureReply)
        return reply.exposure_us, reply.min_us, reply.max_us

    def move(self, axis: str, position: float) -> float:
        """Move ``lift`` (mm) or ``turntable`` (deg) to ``position``; return where it stands.

        Raises:
            DeviceError: beyond the axis's soft limits (the message names them) or a scan runs.
        """
        return self.call("move", replies.MoveReply, MoveArgs(axis, position)).position

    def status(self) -> StatusReply:
        """Return what the device is doing (its heartbeat's fields) and its retransmissions."""
        return self.call("status", StatusReply)

    def pause(self) -> str | None:
        """Ask the device to hold the running scan after the current view (thread-safe).

        Returns the state the device reports (``paused``), None if it refused.
        """
        return self._control("pause")

    def resume(self) -> str | None:
        """Ask the device to go on with a paused scan (thread-safe); return its state."""
        return self._control("resume")

    def abort(self) -> str | None:
        """Ask the device to end the running scan at the next view (thread-safe).

        :meth:`scan` then raises :class:`ScanStopped` holding what arrived. Returns the
        state the device reports (``aborting``), None if it refused.
        """
        return self._control("abort")

    def _control(self, op: str) -> str | None:
        """Send a control request and wait for its reply on this thread (the link's
        reader hands it over); a refusal goes to the scan's ``on_notice``, never raised."""
        with self._id_lock:
            scanning, on_notice = self._scanning, self._on_notice
        if not scanning:
            raise DeviceError(f"no scan is running to {op}")
        try:
            return self.call(op, replies.ControlReply, NoArgs()).state
        except RequestRefused as exc:
            log.warning("%s", exc)
            if on_notice is not None:
                on_notice(str(exc))
            return None

    def estimate(self, target: str, plan: ScanPlan | None = None) -> ScanEstimate | None:
        """Return how long the device would take to acquire ``plan`` (None: default plan).

        None from a device that cannot say (one from before the ``estimate`` operation).

        Raises:
            DeviceError: the plan is beyond the device's limits (the message names them).
        """
        if self.info is None or "estimate" not in self.info.operations:
            return None
        try:
            return ScanEstimate.from_wire(self.request("estimate", EstimateArgs(target, plan)))
        except MessageError as exc:
            log.warning("the device's estimate is unreadable: %s", exc)
            return None

    def plan_for(self, target: str, plan: ScanPlan | None) -> ScanPlan:
        """Return ``plan``, or the device's default plan for ``target``."""
        if plan is not None:
            return plan
        default = self.info.default_plans.get(target) if self.info else None
        if default is None:
            raise DeviceError(f"the device has no default {target} plan: pass one")
        return default

    def scan(
        self,
        target: str,
        plan: ScanPlan | None = None,
        on_event: EventHandler | None = None,
        *,
        have: Collection[int] = (),
        on_segment: IndexedSegmentHandler | None = None,
        on_notice: Callable[[str], object] | None = None,
        extract: ExtractChanges | None = None,
        colour: bool = False,
    ) -> list[Segment]:
        """Scan the views of ``plan`` not in ``have``; return the new segments in plan order.

        While it runs, other threads may call :meth:`pause`, :meth:`resume` and
        :meth:`abort`; each gets its own reply (a refusal goes to ``on_notice``).

        Args:
            target: ``cylinder`` or ``object``.
            plan: the views; None for the device's default plan.
            on_event: receives the scan's events: progress per view, status, log.
            have: plan indices the caller already holds (a resumed scan).
            on_segment: receives (seq, segment) and must store it before returning;
                only then is the segment acknowledged.
            on_notice: receives the one-line text of a refused pause, resume or abort.
            extract: extraction settings to change for this scan (default: :attr:`extract`);
                the device refuses the scan, naming every problem, if they are unusable.
            colour: ask for each point's colour (a device whose WELCOME offers it).

        Raises:
            ScanStopped: the scan was aborted; it holds the segments received.
        """
        plan = self.plan_for(target, plan)
        size = self.info.image_size if self.info else (65_535, 65_535)
        receiver = ScanReceiver(self.channel, target, plan, have, size, on_segment, on_event)
        if colour and not (self.info and self.info.colour):
            raise DeviceError(
                "this device cannot sample colour (its camera or an older lamina-device): "
                "scan without --colour"
            )
        held = tuple(sorted(receiver.held))
        args = ScanArgs(target, plan, held, extract or self.extract, colour)
        with self._id_lock:
            self._scanning, self._on_notice = True, on_notice
        try:
            self.call("scan", replies.ScanReply, args, on_event=receiver.take)
        except RequestRefused as exc:
            if exc.code != "aborted":
                raise
            raise ScanStopped(
                f"{target} scan aborted with {len(held) + len(receiver.received)} of "
                f"{len(plan.views)} views in; the views received are kept",
                dict(sorted(receiver.received.items())),
            ) from None
        finally:
            with self._id_lock:
                self._scanning, self._on_notice = False, None
                self.stats.duplicate_segments += receiver.duplicates
        missing = receiver.missing()
        if missing:
            raise DeviceError(f"the device finished the scan but {len(missing)} views are missing")
        return [receiver.received[s] for s in sorted(receiver.received)]

    def close(self) -> None:
        """Stop the link's reader; ask a device this host started to stop, then wait for it."""
        self.dispatcher.stop()
        if self.process is not None:
            with suppress(DeviceError, LinkClosed):
                self.channel.send(encode_json(Kind.REQUEST, {"id": 0, "op": "shutdown"}))
            try:
                self.process.wait(timeout=5)
            except subprocess.TimeoutExpired:
                self.process.kill()
                self.process.wait()


def _result(op: str, body: dict[str, Any]) -> dict[str, Any]:
    """Return a REPLY's result, or raise the device's refusal as a DeviceError."""
    if body.get("ok") is True:
        result = body.get("result", {})
        return result if isinstance(result, dict) else {}
    error = body.get("error")
    reason = error.get("message") if isinstance(error, dict) else None
    code = error.get("code") if isinstance(error, dict) else None
    raise RequestRefused(
        str(code or "unknown"), f"the device refused {op}: {reason or 'no reason given'}"
    )
