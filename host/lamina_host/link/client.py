"""The host end of the link: find or start the device, handshake, run requests reliably.

A DEVICE is a serial port path, ``sim`` or ``replay:CAPTURE_DIR``. For the last two
the host starts ``lamina-device serve`` itself and joins the two programs with a
:class:`PtyBridge`: two real pseudo-terminal pairs and a relay, so both ends use
pyserial on a real tty exactly as they would over a USB cable.

Requests are repeated (same id) until the device answers, and the device answers a
repeat from its reply cache, so a lost frame in either direction costs a timeout,
never a request run twice. Each segment is handed to the caller (who stores it)
before it is acknowledged; transfers are fetched piece by piece until complete.

One reader thread (:class:`lamina_shared.endpoint.Dispatcher`) reads the link and hands
each message to the request it belongs to, so any thread may send a request and wait
for its own reply: a scan runs on one thread while another pauses or aborts it. The
requests are built from the typed arguments of :mod:`lamina_shared.ops`, the schemas
the device checks them with.
"""

from __future__ import annotations

import base64
import binascii
import logging
import os
import queue
import secrets
import select
import subprocess
import sys
import threading
import time
import tty
import zlib
from collections import deque
from collections.abc import Callable, Collection, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from typing import IO, Any

import cv2
import numpy as np
import serial

from lamina_host.link.identity import scan_identity, spawned_source
from lamina_host.link.local_box import is_endpoint, open_endpoint
from lamina_shared.device_specs import spawns_device
from lamina_shared.endpoint import Dispatcher, request_id_of
from lamina_shared.errors import LaminaError, printable
from lamina_shared.link import Channel, LinkClosed, Ticker
from lamina_shared.ops import (
    ExposureArgs,
    ExtractChanges,
    FetchArgs,
    NoArgs,
    PreviewArgs,
    ScanArgs,
    request_args,
)
from lamina_shared.protocol import (
    CHUNK_BYTES,
    MAX_TRANSFER_BYTES,
    PROTOCOL_VERSION,
    ROW_SCALE,
    Chunk,
    Kind,
    Message,
    ProtocolError,
    SegmentEvent,
    decode_segment_body,
    encode_json,
)
from lamina_shared.spawned import PARENT_PID_ENV
from lamina_shared.types import BoardSpec, ScanPlan, Segment

MAX_IMAGE_SIDE = 16_384
"""Largest image side the host accepts from a device."""
SPAWNED_STARTUP_S = 120.0
"""How long a device program started here may take to answer (a replay validating a big
capture), as long as it is running."""
STARTUP_NOTICE_S = 5.0
"""After this long without an answer, say that the device program is still starting."""
REACK_SEQS = 16
"""Segments acknowledged again when a heartbeat says the device still holds some (its
window)."""
PROCESS_CHECK_S = 0.25
"""How often a request checks that a device program started here is still running."""

log = logging.getLogger(__name__)


class DeviceError(LaminaError, RuntimeError):
    """The device is missing, incompatible or refused a request; the text says what to do."""


class RequestRefused(DeviceError):
    """The device answered a request with an error; ``code`` is its machine-readable reason."""

    def __init__(self, code: str, message: str) -> None:
        super().__init__(message)
        self.code = code


class ScanStopped(DeviceError):
    """The scan was aborted on the device; ``segments`` maps plan index to what arrived.

    Every segment in it was handed to ``on_segment`` (stored) and acknowledged; the
    scan resumes with ``have`` = what the caller holds.
    """

    def __init__(self, message: str, segments: dict[int, Segment]) -> None:
        super().__init__(message)
        self.segments = segments


@dataclass(frozen=True)
class Preview:
    """One preview frame and, when asked for, the stripe the device extracted there."""

    image: np.ndarray
    stripe: Segment | None = None


@dataclass(frozen=True)
class DeviceInfo:
    """What the device reported about itself at the handshake."""

    protocol: int
    software: str
    hardware: str
    description: str
    image_size: tuple[int, int]
    board: BoardSpec | None
    cylinder_diameter_mm: float | None
    default_plans: dict[str, ScanPlan]
    axes: dict[str, Any] = field(default_factory=dict)
    limits: dict[str, Any] = field(default_factory=dict)
    operations: tuple[str, ...] = ()
    welcome: dict[str, Any] = field(default_factory=dict)
    """The WELCOME body as received (for :func:`lamina_host.link.identity.scan_identity`)."""
    colour: bool = False
    """The device samples colour per point (WELCOME ``colour``; absent on older devices)."""

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> DeviceInfo:
        """Build from the WELCOME body; raise DeviceError if it is malformed or out of range."""
        try:
            protocol = int(data["protocol"])
            if protocol != PROTOCOL_VERSION:
                # Nothing else can be trusted to mean the same: report the versions only.
                return cls(
                    protocol, str(data.get("software", "?")), "?", "", (0, 0), None, None, {}
                )
            width, height = (int(v) for v in data["image_size"])
            if not (0 < width <= MAX_IMAGE_SIDE and 0 < height <= MAX_IMAGE_SIDE):
                raise ValueError(f"image size {width}x{height} is beyond this host's limits")
            if int(data.get("segment_encoding", {}).get("row_scale", 0)) != ROW_SCALE:
                raise ValueError("segment row scale differs from this host's")
            board = BoardSpec.from_dict(data["board"]) if data.get("board") else None
            plans = {k: ScanPlan.from_dict(v) for k, v in (data.get("default_plans") or {}).items()}
            diameter = data.get("cylinder_diameter_mm")
            return cls(
                protocol,
                str(data.get("software", "?")),
                str(data["hardware"]),
                str(data.get("description", "")),
                (width, height),
                board,
                float(diameter) if diameter is not None else None,
                plans,
                dict(data.get("axes") or {}),
                dict(data.get("limits") or {}),
                tuple(str(op) for op in data.get("operations") or ()),
                dict(data),
                data.get("colour") is True,
            )
        except (KeyError, TypeError, ValueError, AttributeError, OverflowError) as exc:
            raise DeviceError(f"the device's handshake is malformed ({exc})") from None


class PtyBridge:
    """A software null-modem cable: two pseudo-terminal pairs joined by a relay thread.

    ``host_port`` and ``device_port`` are tty paths each end opens with pyserial.
    ``transform`` (for fault-injection tests, e.g. ``lamina_host.testing.LineFaults``)
    may alter bytes in flight.
    """

    def __init__(self, transform: Callable[[bytes, str], bytes] | None = None) -> None:
        self._a_master, self._a_slave = os.openpty()
        self._b_master, self._b_slave = os.openpty()
        for fd in (self._a_master, self._a_slave, self._b_master, self._b_slave):
            # Raw from the start: a cooked slave would echo and mangle binary frames
            # before pyserial has configured it.
            tty.setraw(fd)
        self.host_port = os.ttyname(self._a_slave)
        self.device_port = os.ttyname(self._b_slave)
        self._transform = transform
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._relay, name="pty-bridge", daemon=True)
        self._thread.start()

    def _relay(self) -> None:
        route = {
            self._a_master: (self._b_master, "to-device"),
            self._b_master: (self._a_master, "to-host"),
        }
        while not self._stop.is_set():
            ready, _, _ = select.select(list(route), [], [], 0.05)
            for fd in ready:
                try:
                    data = os.read(fd, 65536)
                except OSError:
                    time.sleep(0.01)  # the other end closed (EIO): do not spin
                    continue
                out, direction = route[fd]
                if self._transform is not None:
                    data = self._transform(data, direction)
                with suppress(OSError):
                    os.write(out, data)

    def close(self) -> None:
        """Stop relaying and close all four descriptors."""
        self._stop.set()
        self._thread.join(timeout=2)
        for fd in (self._a_master, self._a_slave, self._b_master, self._b_slave):
            with suppress(OSError):
                os.close(fd)


EventHandler = Callable[[Message], None]
IndexedSegmentHandler = Callable[[int, Segment], object]
"""Receives (seq, segment) for each new segment; it must have stored it when it returns."""


class _Assembly:
    """One binary transfer being put together from pieces that arrive in any order."""

    def __init__(self, total: int) -> None:
        if total > MAX_TRANSFER_BYTES:
            raise DeviceError(f"the device offered {total} bytes, beyond this host's limit")
        self.total = total
        self.data = bytearray(total)
        self.have = np.zeros(-(-total // CHUNK_BYTES), bool)

    def take(self, chunk: Chunk) -> None:
        """Keep a piece if it is one this transfer expects."""
        index, expected = divmod(chunk.offset, CHUNK_BYTES)
        size = min(CHUNK_BYTES, self.total - chunk.offset)
        if chunk.total == self.total and expected == 0 and len(chunk.data) == size:
            self.data[chunk.offset : chunk.offset + size] = chunk.data
            self.have[index] = True

    def missing(self, max_bytes: int) -> list[list[int]]:
        """Return up to ``max_bytes`` of missing pieces as merged [offset, length] ranges."""
        ranges: list[list[int]] = []
        budget = max_bytes
        for index in np.flatnonzero(~self.have).tolist():
            offset = index * CHUNK_BYTES
            size = min(CHUNK_BYTES, self.total - offset)
            if size > budget:
                break
            budget -= size
            if ranges and ranges[-1][0] + ranges[-1][1] == offset:
                ranges[-1][1] += size
            else:
                ranges.append([offset, size])
        return ranges


@dataclass
class StderrTail:
    """Read a device program's stderr while it runs, keeping its last lines.

    A pipe holds about 64 KB: a program that writes more to a pipe nobody reads blocks,
    and the host would wait for an answer that cannot come.
    """

    KEEP_LINES = 50
    LINE_BYTES = 64 * 1024

    def __init__(self, stream: IO[bytes]) -> None:
        self._lines: deque[str] = deque(maxlen=self.KEEP_LINES)
        self._thread = threading.Thread(
            target=self._read, args=(stream,), name="device-stderr", daemon=True
        )
        self._thread.start()

    def _read(self, stream: IO[bytes]) -> None:
        with suppress(OSError, ValueError):  # the stream closed under us: nothing more to read
            # Empty at the end of the stream, whether it yields bytes or (a caller's) text.
            while raw := stream.readline(self.LINE_BYTES):
                line = raw.decode(errors="replace") if isinstance(raw, bytes) else raw
                self._lines.append(line.strip())

    def lines(self, wait_s: float = 2.0) -> list[str]:
        """Return the last non-empty lines, after up to ``wait_s`` for an exited program's rest.

        Args:
            wait_s: how long to wait for the stream's end (call it once the program exited).

        Returns:
            The kept lines, oldest first.
        """
        self._thread.join(wait_s)
        return [line for line in self._lines if line]


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
        self.info: DeviceInfo | None = None
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
        welcome = dict(self.info.welcome) if self.info else {}
        if self.extract is not None:
            configured = welcome.get("extract")
            base = configured if isinstance(configured, dict) else {}
            welcome["extract"] = {**base, **self.extract.as_dict()}
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
    ) -> DeviceInfo:
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
        hello = {"protocol": PROTOCOL_VERSION, "software": "lamina-host", "session": self.session}
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

    def _welcome(self, body: dict[str, Any]) -> DeviceInfo:
        info = DeviceInfo.from_dict(body)
        if info.protocol != PROTOCOL_VERSION:
            raise DeviceError(
                f"the device speaks protocol version {info.protocol}, this host speaks "
                f"{PROTOCOL_VERSION}: install matching lamina-device and lamina-host versions"
            )
        self.info = info
        return info

    def _unclaimed(self, message: Message) -> None:
        """Keep a WELCOME for :meth:`hello`; drop what belongs to no open request.

        A WELCOME that ``refused`` the session (a device service that already has a
        host) is remembered, so :meth:`hello` says why even after the device hung up.
        """
        if message.kind is Kind.WELCOME:
            refusal = message.body.get("refused") if isinstance(message.body, dict) else None
            if refusal is not None:
                reason = refusal.get("message") if isinstance(refusal, dict) else None
                self._refusal = printable(str(reason or "no reason given"))[:200]
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
            raise DeviceError(
                f"the device is in use by another host ({self._refusal}): close the other "
                "terminal UI, browser tab or scan using it, or wait for it to finish, then "
                "connect again"
            )

    def _tick(self) -> None:
        """Send our heartbeat while a request is open (on the reader thread)."""
        if self.dispatcher.open_requests and self._heartbeat.due():
            self.channel.send(encode_json(Kind.HEARTBEAT, {"session": self.session}))

    def request(
        self, op: str, args: Any = None, on_event: EventHandler | None = None
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

    def _resend(self, frame: bytes) -> None:
        self.channel.sizer.penalise()
        self.channel.send(frame)
        with self._id_lock:
            self.stats.request_retries += 1

    def _fetch(self, op: str, args: Any = None) -> tuple[bytes, dict[str, Any]]:
        """Run a request that offers a binary transfer; fetch what did not arrive."""
        assemblies: dict[int, _Assembly] = {}

        def take(message: Message) -> None:
            chunk = message.body
            if isinstance(chunk, Chunk):
                if chunk.transfer not in assemblies:
                    assemblies[chunk.transfer] = _Assembly(chunk.total)
                assemblies[chunk.transfer].take(chunk)

        result = self.request(op, args, on_event=take)
        transfer, total = result.get("transfer"), result.get("bytes")
        if not isinstance(transfer, int) or not isinstance(total, int):
            raise DeviceError(f"the device's {op} reply names no transfer")
        assembly = assemblies.get(transfer) or _Assembly(total)
        assemblies = {transfer: assembly}
        max_bytes = int(self.info.limits.get("max_fetch_bytes", 65536)) if self.info else 65536
        while not assembly.have.all():
            before = int(assembly.have.sum())
            ranges = tuple((offset, length) for offset, length in assembly.missing(max_bytes))
            self.request("fetch", FetchArgs(transfer, ranges), take)
            self.stats.fetch_rounds += 1
            if int(assembly.have.sum()) == before and self.stats.fetch_rounds > 1000:
                raise DeviceError(f"the {op} transfer makes no progress: check the cable")
        data = bytes(assembly.data)
        if len(data) != total or zlib.crc32(data) != result.get("crc32"):
            raise DeviceError(f"the {op} transfer arrived damaged: try again")
        return data, result

    def grab_grid(self) -> tuple[np.ndarray, BoardSpec]:
        """Fetch the calibration board image and the board's geometry."""
        data, result = self._fetch("grab_grid")
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise DeviceError("the calibration image could not be decoded")
        if result.get("board") is None:
            raise DeviceError("the device does not know its calibration board: configure it")
        return image, BoardSpec.from_dict(result["board"])

    def preview(self, laser: bool = False, stripe: bool = True) -> Preview:
        """Fetch one camera frame taken where the axes stand, and the stripe found there.

        Args:
            laser: show the laser-on frame rather than the laser-off one.
            stripe: also have the device take a laser-off/on pair and extract the stripe
                (the laser then flashes for one frame even when ``laser`` is False).
        """
        data, result = self._fetch("preview", PreviewArgs(laser, stripe))
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
        if image is None:
            raise DeviceError("the preview frame could not be decoded")
        found = None
        if stripe:
            try:
                found = decode_segment_body(base64.b64decode(result["stripe"], validate=True))
            except (KeyError, TypeError, binascii.Error, ProtocolError) as exc:
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
        return int(self.request("exposure", ExposureArgs(int(exposure_us)))["exposure_us"])

    def exposure(self) -> tuple[int, int, int]:
        """Return the camera's (exposure, min, max) in microseconds."""
        result = self.request("exposure")
        return int(result["exposure_us"]), int(result["min_us"]), int(result["max_us"])

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
            return str(self.request(op, NoArgs()).get("state"))
        except RequestRefused as exc:
            log.warning("%s", exc)
            if on_notice is not None:
                on_notice(str(exc))
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
        on_progress: Callable[[dict[str, Any]], None] | None = None,
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
            on_progress: receives each progress event's body.
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
        held = set(have)
        received: dict[int, Segment] = {}
        expected = [s for s in range(len(plan.views)) if s not in held]
        size = self.info.image_size if self.info else (65_535, 65_535)

        def take(message: Message) -> None:
            body = message.body
            if isinstance(body, SegmentEvent):
                if body.seq not in held and body.seq not in received:
                    _check_segment(body, target, plan, size)
                    if on_segment is not None:
                        on_segment(body.seq, body.segment)
                    received[body.seq] = body.segment
                else:
                    self.stats.duplicate_segments += 1
                # Stored (or already held): acknowledge, also a repeat whose ack was lost.
                # Views come in plan order, so earlier ones still missing were lost.
                lost = [s for s in expected if s < body.seq and s not in received]
                ack = {"id": body.request_id, "seqs": [body.seq], "lost": lost[:64]}
                self.channel.send(encode_json(Kind.ACK, ack))
            elif message.kind is Kind.HEARTBEAT:
                # The device still holds segments: if it is one we stored, our ACK was
                # lost; acknowledging the latest again now beats the device's backoff.
                unacked = message.body.get("unacked")
                if isinstance(unacked, int) and unacked > 0 and received:
                    recent = list(received)[-REACK_SEQS:]
                    ack = {"id": request_id_of(message), "seqs": recent, "lost": []}
                    self.channel.send(encode_json(Kind.ACK, ack))
            elif message.kind is Kind.EVENT and on_progress is not None:
                on_progress(message.body)

        if colour and not (self.info and self.info.colour):
            raise DeviceError(
                "this device cannot sample colour (its camera or an older lamina-device): "
                "scan without --colour"
            )
        args = ScanArgs(target, plan, tuple(sorted(held)), extract or self.extract, colour)
        with self._id_lock:
            self._scanning, self._on_notice = True, on_notice
        try:
            self.request("scan", args, on_event=take)
        except RequestRefused as exc:
            if exc.code != "aborted":
                raise
            raise ScanStopped(
                f"{target} scan aborted with {len(held) + len(received)} of "
                f"{len(plan.views)} views in; the views received are kept",
                dict(sorted(received.items())),
            ) from None
        finally:
            with self._id_lock:
                self._scanning, self._on_notice = False, None
        missing = set(range(len(plan.views))) - held - set(received)
        if missing:
            raise DeviceError(f"the device finished the scan but {len(missing)} views are missing")
        return [received[s] for s in sorted(received)]

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


def _check_segment(
    event: SegmentEvent, target: str, plan: ScanPlan, image_size: tuple[int, int]
) -> None:
    """Refuse a segment that does not belong where it claims or lies outside the image."""
    segment, seq = event.segment, event.seq
    problem = None
    if seq >= len(plan.views):
        problem = f"view {seq} of a {len(plan.views)}-view plan"
    else:
        view = plan.views[seq]
        if (segment.target, segment.section, segment.z_mm, segment.angle_deg) != (
            target,
            view.section,
            view.z_mm,
            view.angle_deg,
        ):
            problem = f"view {seq} labelled differently from the plan"
        elif len(segment) and (
            int(segment.cols[-1]) >= image_size[0] or float(segment.rows.max()) >= image_size[1]
        ):
            problem = f"view {seq} has points outside the {image_size[0]}x{image_size[1]} image"
    if problem:
        raise DeviceError(f"the device sent a segment beyond this host's limits ({problem})")


SINGLE_THREADED = {
    "OMP_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENCV_FOR_THREADS_NUM": "1",
}
"""Thread limits for a device program started on the host's own machine."""


def device_environment() -> dict[str, str]:
    """Return the environment for a simulated or replaying device started here.

    The real device is a computer of its own. One started beside the host stands in
    for it, so its numerical libraries get one thread each: left to themselves they
    take every core while rendering, and the host (its terminal UI above all) then
    answers keys late. It is told this process's id, so that it ends when the host does
    (:mod:`lamina_shared.spawned`).
    """
    return {**os.environ, **SINGLE_THREADED, PARENT_PID_ENV: str(os.getpid())}


def device_command(
    hardware: str, port: str, object_spec: str | None, seed: int, noise: str, rig: str = "thesis"
) -> list[str]:
    """Return the command line that starts a device program on ``port``."""
    command = [
        sys.executable,
        "-m",
        "lamina_device",
        "serve",
        "--port",
        port,
        "--hardware",
        hardware,
        "--seed",
        str(seed),
        "--noise",
        noise,
    ]
    if object_spec:
        command += ["--object", object_spec]
    if rig != "thesis":
        command += ["--rig", rig]
    return command


@contextmanager
def open_device(
    device: str,
    object_spec: str | None = None,
    seed: int = 0,
    noise: str = "thesis",
    transform: Callable[[bytes, str], bytes] | None = None,
    rig: str = "thesis",
    on_notice: Callable[[str], object] | None = None,
) -> Iterator[DeviceClient]:
    """Connect to DEVICE (a port path, ``local``, ``socket://HOST:PORT``, ``sim`` or
    ``replay:DIR``) and handshake.

    ``rig`` picks the simulated rig's geometry (``thesis`` or ``limb``; sim only).
    ``on_notice`` hears about a slow start of a device program started here.
    """
    if spawns_device(device):
        with _spawned_device(device, object_spec, seed, noise, transform, rig, on_notice) as client:
            yield client
        return
    if object_spec:
        raise DeviceError("--object only applies to the simulated device (--device sim)")
    if is_endpoint(device):
        with open_endpoint(device, DeviceError) as port:
            client = DeviceClient(Channel(port))
            try:
                client.hello()
                yield client
            finally:
                client.close()  # the reader stops before its port closes under it
        return
    if not os.path.exists(device):
        raise DeviceError(
            f"serial port {device} does not exist: connect the scanner's USB cable or name its "
            "port (e.g. /dev/ttyACM0), or use --device sim"
        )
    try:
        port = serial.Serial(device, baudrate=115200, timeout=0.05, exclusive=True)
    except (serial.SerialException, OSError) as exc:
        raise DeviceError(f"cannot open serial port {device}: {exc}") from None
    with port:
        client = DeviceClient(Channel(port))
        try:
            client.hello()
            yield client
        finally:
            client.close()  # the reader stops before its port closes under it


@contextmanager
def _spawned_device(
    device: str,
    object_spec: str | None,
    seed: int,
    noise: str,
    transform: Callable[[bytes, str], bytes] | None,
    rig: str = "thesis",
    on_notice: Callable[[str], object] | None = None,
) -> Iterator[DeviceClient]:
    try:
        bridge = PtyBridge(transform)
    except OSError as exc:
        raise DeviceError(
            f"cannot open a pseudo-terminal to run the device program here "
            f"({exc.strerror or exc}): mount /dev/pts, or connect a scanner by its serial port"
        ) from None
    command = device_command(device, bridge.device_port, object_spec, seed, noise, rig)
    process = subprocess.Popen(
        command,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.DEVNULL,
        stderr=subprocess.PIPE,
        env=device_environment(),
    )
    client: DeviceClient | None = None
    try:
        port = serial.Serial(bridge.host_port, baudrate=115200, timeout=0.05)
        with port:
            client = DeviceClient(Channel(port), process)
            client.spawned = spawned_source(device, object_spec, seed, noise, rig)
            client.hello(on_notice=on_notice)
            yield client
            client.close()
    finally:
        if process.poll() is None:
            process.kill()
        process.wait()
        if client is not None and client.stderr_tail is not None:
            client.stderr_tail.lines()  # the reader is done before its stream closes
        if process.stderr:
            process.stderr.close()
        bridge.close()
