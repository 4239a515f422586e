"""The device's operations table: what each request does to the scanner's hardware.

The shared endpoint (:class:`lamina_shared.endpoint.DeviceEndpoint`) frames, caches,
acknowledges and retries; it hands each request's typed arguments (validated by
:mod:`lamina_shared.ops`) to one method here. Nothing received is ever evaluated or
used as a file path. Views are numbered in one place,
:func:`lamina_device.acquisition.views_in_section`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import itertools
import json
import math
import threading
from typing import Any, Protocol

import cv2
import numpy as np

from lamina_device.acquisition import (
    ScanAborted,
    ScanControl,
    acquire,
    capture_pair,
    continuous_problem,
    grab_grid,
    views_in_section,
)
from lamina_device.camera import ExposureRefused, camera_has_colour
from lamina_device.extract import ExtractSettings, changed_settings, extract, to_segment
from lamina_device.hardware import Hardware
from lamina_device.timing import estimate_scan_time
from lamina_shared.endpoint import Abandoned, Handler, RequestError, SegmentBuffer, ServerSettings
from lamina_shared.messages import (
    AxesInfo,
    DeviceHeartbeat,
    Event,
    LogEvent,
    Progress,
    ProgressEvent,
    StatusEvent,
)
from lamina_shared.ops import (
    ArgsError,
    EstimateArgs,
    ExposureArgs,
    MoveArgs,
    NoArgs,
    PreviewArgs,
    Problems,
    ScanArgs,
    check_plan,
)
from lamina_shared.protocol import encode_segment_body, quantise_segment
from lamina_shared.replies import (
    ControlReply,
    EmptyReply,
    ExposureReply,
    GridReply,
    MoveReply,
    PreviewReply,
    ScanEstimate,
    ScanReply,
    StatusReply,
    TransferOffer,
)
from lamina_shared.types import SCAN_MODES, ScanPlan, Segment

"""The simulated lift's travel, reported when the hardware does not say its own."""


class Link(Protocol):
    """What the operations use of the endpoint that runs them."""

    settings: ServerSettings
    buffer: SegmentBuffer
    running: bool

    @property
    def running_id(self) -> int | None: ...  # pragma: no cover - protocol

    @property
    def abandoned(self) -> threading.Event: ...  # pragma: no cover - protocol

    def offer(self, request_id: int, data: bytes) -> TransferOffer: ...  # pragma: no cover

    def event(self, event: Event) -> None: ...  # pragma: no cover

    def send_segment(
        self, request_id: int, seq: int, segment: Segment
    ) -> None: ...  # pragma: no cover

    def state(self) -> DeviceHeartbeat: ...  # pragma: no cover - protocol


def axes_of(hardware: Hardware) -> AxesInfo:
    """Return the soft limits the hardware's axes declare (what the WELCOME reports)."""
    lift, turntable = hardware.lift, hardware.turntable
    step = getattr(lift, "step_mm", None)  # only stepper lifts have one
    return AxesInfo(
        lift.min_mm,
        lift.max_mm,
        turntable.min_deg,
        turntable.max_deg,
        float(step) if isinstance(step, int | float) else None,
    )


def check_position(limits: AxesInfo, axis: str, position: float) -> None:
    """Raise RequestError(``limit``) unless ``position`` is within ``axis``'s limits."""
    low: float | None
    high: float | None
    if axis == "lift":
        low, high, unit = limits.lift_min_mm, limits.lift_max_mm, "mm"
    else:
        low, high, unit = limits.turntable_min_deg, limits.turntable_max_deg, "deg"
    if not math.isfinite(position):
        raise RequestError("limit", f"{axis} position must be a finite number of {unit}")
    if (low is not None and position < low) or (high is not None and position > high):
        raise RequestError(
            "limit",
            f"{axis} position {position} {unit} is outside its soft limits {low}..{high}",
        )


def check_section_gaps(limits: AxesInfo, heights: list[float]) -> None:
    """Raise RequestError(``limit``) if sorted ``heights`` are closer than the lift's step.

    Two sections less than a microstep apart would be scanned at one lift position.
    """
    step = limits.lift_step_mm
    gaps = [b - a for a, b in itertools.pairwise(heights)]
    if step is not None and gaps and min(gaps) < step * (1 - 1e-9):
        raise RequestError(
            "limit",
            f"sections {min(gaps):g} mm apart are finer than the lift's step of {step:g} mm",
        )


def plan_key(
    target: str, plan: ScanPlan, settings: ExtractSettings, colour: bool = False
) -> tuple[str, str]:
    """Return what identifies a scan across sessions: its target, plan, extraction, colour."""
    parts: list[Any] = [plan.to_dict(), dataclasses.asdict(settings)]
    if colour:  # left out without colour: keys of scans buffered before colour stay valid
        parts.append({"colour": True})
    text = json.dumps(parts, sort_keys=True)
    return target, hashlib.sha256(text.encode()).hexdigest()[:16]


class Operations:
    """Every operation of the scanner, bound to its hardware and the link that asks."""

    def __init__(self, hardware: Hardware, link: Link) -> None:
        self.hardware = hardware
        self.link = link
        self.limits = axes_of(hardware)
        self.control: ScanControl | None = None
        """The running scan's pause/resume/abort, while one runs."""
        """False once the host asked the device to shut down."""

    def table(self) -> dict[str, Handler]:
        """Return the handler of each operation (``fetch`` is the endpoint's own)."""
        return {
            "grab_grid": self.grab_grid,
            "preview": self.preview,
            "scan": self.scan,
            "move": self.move,
            "pause": self.pause,
            "resume": self.resume,
            "abort": self.abort,
            "exposure": self.exposure,
            "status": self.status,
            "estimate": self.estimate,
            "shutdown": self.shutdown,
        }

    def grab_grid(self, request_id: int, args: NoArgs) -> GridReply:
        """Offer a PNG of the calibration board (laser off) and the board's geometry."""
        offer = self.link.offer(request_id, _png(grab_grid(self.hardware)))
        return GridReply(offer, self.hardware.board)

    def preview(self, request_id: int, args: PreviewArgs) -> PreviewReply:
        """Capture one frame where the axes stand (laser on only during its exposure).

        With ``stripe`` the device takes the laser-off/laser-on pair a scan would, extracts
        the stripe with the scan's own extraction and returns it as a SEGMENT body.
        """
        laser, stripe = args.laser, args.stripe
        hw = self.hardware
        if not stripe:
            frame = capture_pair(hw)[0] if laser else hw.camera.capture()
            return PreviewReply(self.link.offer(request_id, _png(frame)))
        on, off = capture_pair(hw)
        points = extract(on, off, hw.extract)
        segment = quantise_segment(
            to_segment(points, hw.stage.target, 0, 0, hw.lift.z_mm, hw.turntable.angle_deg)
        )
        body = encode_segment_body(request_id, 0, segment)
        return PreviewReply(self.link.offer(request_id, _png(on if laser else off)), body)

    # --- scanning --------------------------------------------------------------------

    def _plan(self, args: ScanArgs, colour: bool = False) -> ScanPlan:
        """Return the plan to scan (the request's, or the default), within the axes' limits,
        in a mode this device can take it in (with ``colour`` if asked)."""
        plan = args.plan
        if plan is None:
            plan = self.hardware.default_plans.get(args.target)
            if plan is None:
                raise RequestError("bad-args", f"no {args.target} views to scan on this device")
            problems = Problems()
            check_plan(plan.to_wire(), self.link.settings.limits, problems)
            if problems.items:
                # A configured or replayed default beyond the limits is refused like any plan.
                raise ArgsError("scan", problems.items, "limit")
        lifts = sorted({view.z_mm for view in plan.views})
        angles = sorted({view.angle_deg for view in plan.views})
        # The extremes decide: every height and angle between them is within limits too.
        for axis, values in (("lift", lifts), ("turntable", angles)):
            check_position(self.limits, axis, values[0])
            check_position(self.limits, axis, values[-1])
        check_section_gaps(self.limits, lifts)
        if plan.continuous and (problem := continuous_problem(self.hardware, plan, colour)):
            raise RequestError("unsupported", f"this device cannot scan continuously: {problem}")
        return plan

    def scan(self, request_id: int, args: ScanArgs) -> ScanReply:
        """Send every view of the plan the host does not hold: from the buffer or acquired."""
        target = args.target
        settings = self.extract_settings(args)
        plan = self._plan(args, args.colour)
        outside = [s for s in args.have if s >= len(plan.views)]
        if outside:
            raise RequestError(
                "bad-args",
                f"have must list view indices of the plan: {outside[0]} is beyond its "
                f"{len(plan.views)} views",
            )
        if args.colour and not camera_has_colour(self.hardware.camera):
            raise RequestError(
                "bad-args", "this device's camera gives no colour: scan without colour"
            )
        have = set(args.have)
        kept = self.link.buffer.adopt(plan_key(target, plan, settings, args.colour), request_id)
        self.link.buffer.ack(request_id, have & set(kept))
        resend = sorted(set(kept) - have)
        if kept:
            self.link.event(LogEvent(request_id, f"resending {len(resend)} buffered segments"))
        self.link.buffer.mark_resent(resend)
        for seq in resend:
            self.link.send_segment(request_id, seq, kept[seq])
        todo = [s for s in range(len(plan.views)) if s not in have and s not in kept]
        if todo:
            self._acquire(request_id, target, plan, todo, settings, args.colour)
        if not self.link.buffer.wait_empty(self.link.abandoned, self.link.settings.ack_timeout_s):
            raise RequestError(
                "unacknowledged",
                f"{len(self.link.buffer)} segments unacknowledged; they stay buffered for a resume",
            )
        return ScanReply(len(plan.views), len(todo), len(resend))

    def extract_settings(self, args: ScanArgs) -> ExtractSettings:
        """Return the configured extraction with the request's changes; refuse bad ones."""
        if args.extract is None:
            return self.hardware.extract
        settings, problems = changed_settings(self.hardware.extract, args.extract.as_dict())
        if settings is None:
            raise ArgsError("scan", [f"scan.extract: {text}" for text in problems])
        return settings

    def _acquire(
        self,
        request_id: int,
        target: str,
        plan: ScanPlan,
        todo: list[int],
        settings: ExtractSettings,
        colour: bool = False,
    ) -> None:
        """Acquire the views ``todo`` (plan indices), numbering them as the full plan does."""
        index = views_in_section(plan)
        # A continuous scan sends its views in the order the table brings them round:
        # each segment's section and number in it say which view of the plan it is.
        seqs = {(plan.views[s].section, index[s]): s for s in todo}
        held = len(plan.views) - len(todo)

        def on_segment(segment: Segment) -> None:
            seq = seqs[(segment.section, segment.view)]
            segment = quantise_segment(segment)
            self.link.buffer.put(seq, segment, self.link.abandoned)
            self.link.send_segment(request_id, seq, segment)

        def on_progress(progress: Progress) -> None:
            # The sub-plan's count, told as the whole plan's (held views included).
            whole = dataclasses.replace(progress, done=held + progress.done, total=len(plan.views))
            self.link.event(ProgressEvent(request_id, whole))

        sub_plan = plan.with_views(tuple(plan.views[s] for s in todo))
        self.control = ScanControl()
        try:
            acquire(
                self.hardware,
                target,
                sub_plan,
                on_segment,
                on_progress,
                settings,
                control=self.control,
                numbers=[index[s] for s in todo],
                colour=colour,
                resumed=held > 0,
            )
        except ScanAborted as exc:
            if self.link.abandoned.is_set():
                raise Abandoned from None
            raise RequestError("aborted", f"{exc}; the views sent so far are kept") from None
        finally:
            self.control = None

    # --- quick operations ------------------------------------------------------------

    def move(self, request_id: int, args: MoveArgs) -> MoveReply:
        """Move one axis within its soft limits (positioning before a preview)."""
        axis, position = args.axis, args.position
        if self.link.running_id is not None:
            raise RequestError("busy", f"request {self.link.running_id} is moving the axes")
        check_position(self.limits, axis, position)
        (self.hardware.lift if axis == "lift" else self.hardware.turntable).move_to(position)
        return MoveReply(axis, position)

    def _scan_control(self, op: str) -> ScanControl:
        control = self.control
        if control is None:
            raise RequestError("idle", f"no scan is running to {op}")
        return control

    def pause(self, request_id: int, args: NoArgs) -> ControlReply:
        """Hold the running scan after the current view, laser off."""
        self._scan_control("pause").pause()
        self.link.event(StatusEvent(self.link.running_id or 0, "paused"))
        return ControlReply("paused")

    def resume(self, request_id: int, args: NoArgs) -> ControlReply:
        """Let a paused scan go on."""
        self._scan_control("resume").resume()
        self.link.event(StatusEvent(self.link.running_id or 0, "busy"))
        return ControlReply("busy")

    def abort(self, request_id: int, args: NoArgs) -> ControlReply:
        """End the running scan at the next view; what was sent stays valid."""
        self._scan_control("abort").abort()
        return ControlReply("aborting")

    def exposure(self, request_id: int, args: ExposureArgs) -> ExposureReply:
        """Set the camera's exposure (``exposure_us``) within its limits; report it and them."""
        camera = self.hardware.camera
        low, high = camera.exposure_range_us
        value = args.exposure_us
        if value is not None:
            if self.link.running_id is not None:
                # A scan's views must all share one exposure.
                raise RequestError("busy", f"request {self.link.running_id} is using the camera")
            try:
                camera.set_exposure(value)
            except ExposureRefused as exc:
                raise RequestError("limit", str(exc)) from None
        return ExposureReply(camera.exposure_us, low, high)

    def estimate(self, request_id: int, args: EstimateArgs) -> ScanEstimate:
        """Return how long the plan would keep the subject still (``lamina_device.timing``)."""
        plan = self._plan(ScanArgs(args.target, args.plan))
        config = self.hardware.timing
        if config is None:
            raise RequestError("unsupported", "this device cannot time a scan: no axis profiles")
        # Frames wait for the exposure now in use, as the scan's would.
        exposure_us = self.hardware.camera.exposure_us
        modelled = estimate_scan_time(config, plan, exposure_us=exposure_us)
        return ScanEstimate(len(plan.views), modelled.modelled_s, modelled.mechanical_minimum_s)

    def status(self, request_id: int, args: NoArgs) -> StatusReply:
        """Report what a heartbeat says, and the retransmissions so far."""
        return StatusReply(self.link.state(), self.link.buffer.retransmissions)

    def shutdown(self, request_id: int, args: NoArgs) -> EmptyReply:
        """End the device program after this reply (the host started it)."""
        self.link.running = False
        return EmptyReply()


def scan_modes(hardware: Hardware) -> tuple[str, ...]:
    """Return the scan modes ``hardware`` can take a plan in (what the WELCOME offers).

    Continuous mode is offered when the default object plan could be taken continuously
    (the table turns by itself, the camera streams timed frames, the watchdog accepts
    the laser pulses); a plan the host sends is checked again when it comes.
    """
    plan = hardware.default_plans.get("object")
    sample = (plan or ScanPlan.regular(1, 1.0, 8)).with_mode("continuous")
    return SCAN_MODES if continuous_problem(hardware, sample) is None else SCAN_MODES[:1]


def _png(image: np.ndarray) -> bytes:
    ok, encoded = cv2.imencode(".png", image)
    if not ok:
        raise RequestError("failed", "could not encode the image as PNG")
    return bytes(encoded.tobytes())
