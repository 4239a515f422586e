"""The device side of a scan job: one connection, its controls and the fetching of views.

Every request holds the connection's busy lock (a second caller gets :class:`Busy`),
except pause, resume and abort, which any thread may send while a scan runs.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable, Iterator
from contextlib import ExitStack, contextmanager, suppress
from dataclasses import dataclass, replace
from typing import Any

from lamina_host.link.client import DeviceClient, Preview
from lamina_host.link.connect import open_device
from lamina_host.link.errors import DeviceError
from lamina_shared.errors import InputError, LaminaError
from lamina_shared.link import LinkClosed
from lamina_shared.messages import Event, Progress, ProgressEvent, Welcome
from lamina_shared.ops import ExtractChanges
from lamina_shared.replies import ScanEstimate
from lamina_shared.types import ScanPlan, Segment

ProgressHandler = Callable[[Progress], object]
SegmentHandler = Callable[[Segment], object]
NoticeHandler = Callable[[str], object]
StoreHandler = Callable[[int, Segment], object]
"""Commits view ``seq`` of a scan before the link acknowledges it."""


class Busy(LaminaError, RuntimeError):
    """The device is already running a request."""


@dataclass(frozen=True)
class DeviceTarget:
    """What to connect to: a port path, ``sim`` or ``replay:DIR``, and the simulation's choices."""

    device: str = "sim"
    object_spec: str | None = None
    seed: int = 0
    noise: str = "thesis"
    rig: str = "thesis"


@dataclass(frozen=True)
class Pose:
    """Where the axes stand: the lift in mm, the turntable in degrees."""

    lift_mm: float = 0.0
    turntable_deg: float = 0.0

    def at(self, axis: str) -> float:
        """Return the position of ``lift`` (mm) or ``turntable`` (deg)."""
        return self.lift_mm if axis == "lift" else self.turntable_deg

    def moved(self, axis: str, position: float) -> Pose:
        """Return this pose with ``axis`` at ``position``."""
        if axis == "lift":
            return replace(self, lift_mm=position)
        return replace(self, turntable_deg=position)


class DeviceSession:
    """One device connection at a time: connect, the device's own controls, fetching views.

    It keeps what a scan asks the device for (:attr:`extract`, :attr:`colour`) and where
    the axes were last moved (:attr:`pose`).
    """

    def __init__(self, target: DeviceTarget) -> None:
        self.target = target
        self.extract: ExtractChanges | None = None
        self.colour = False
        """Ask for each object point's colour (:meth:`set_colour`)."""
        self.pose = Pose()
        self._client: DeviceClient | None = None
        self._stack: ExitStack | None = None
        self._lock = threading.Lock()

    @property
    def name(self) -> str:
        """Return the device this session connects to (port path, ``sim`` or ``replay:DIR``)."""
        return self.target.device

    @property
    def object_spec(self) -> str | None:
        """Return the simulated object the next connection asks for (sim only)."""
        return self.target.object_spec

    @object_spec.setter
    def object_spec(self, spec: str | None) -> None:
        self.target = replace(self.target, object_spec=spec)

    @property
    def info(self) -> Welcome | None:
        """Return the connected device's information, or None."""
        return self._client.info if self._client else None

    @property
    def connected(self) -> bool:
        """Return True while a device is connected."""
        return self._client is not None

    @contextmanager
    def busy(self) -> Iterator[None]:
        """Hold the connection for one request; raise :class:`Busy` if another holds it."""
        if not self._lock.acquire(blocking=False):
            raise Busy("the device is busy with another request; wait for it or abort it")
        try:
            yield
        finally:
            self._lock.release()

    def client(self) -> DeviceClient:
        """Return the connected client, or refuse when none is connected."""
        if self._client is None:
            raise InputError("no device connected: connect on the Connect screen (F2) first")
        return self._client

    @contextmanager
    def link(self) -> Iterator[DeviceClient]:
        """Yield the client; a broken link is forgotten so the next connect starts afresh."""
        try:
            yield self.client()
        except LinkClosed:
            self._close_link()
            raise

    def connect(self, device: str | None = None, on_notice: NoticeHandler | None = None) -> Welcome:
        """Connect to DEVICE (port, ``sim`` or ``replay:DIR``; default the target's)."""
        with self.busy():
            name = (device or self.target.device).strip()
            if not name:
                raise InputError(
                    "enter a device: a serial port path, local, sim, or replay:CAPTURE_DIR"
                )
            self.target = replace(self.target, device=name)
            self._reopen(on_notice)
            info = self.client().info
            assert info is not None
            return info

    def attach_for_testing(self, client: DeviceClient) -> None:
        """Test hook: use a client already handshaken elsewhere; closing leaves it open."""
        with self.busy():
            self._close_link()
            self._client = client

    def _reopen(self, on_notice: NoticeHandler | None) -> None:
        """Close and reopen the link to the same device (caller holds the busy lock)."""
        self._close_link()
        stack = ExitStack()
        t = self.target
        try:
            self._client = stack.enter_context(
                open_device(
                    t.device, t.object_spec, t.seed, t.noise, rig=t.rig, on_notice=on_notice
                )
            )
        except BaseException:
            stack.close()
            self._client = None
            raise
        self._stack = stack

    def _close_link(self) -> None:
        stack, self._stack, self._client = self._stack, None, None
        if stack is not None:
            # A broken link cannot be tidied further; closing must still forget it.
            with suppress(DeviceError, LinkClosed, OSError):
                stack.close()

    def close(self) -> None:
        """Disconnect, stopping a device program this host started."""
        with self._lock:
            self._close_link()

    def set_extract(self, changes: ExtractChanges | None) -> None:
        """Change the device's stripe extraction for this session's scans (None: its own).

        The effective settings are part of the scan identity, so set them before the
        calibration that a scan will use.
        """
        self.client().extract = changes
        self.extract = changes

    def set_colour(self, colour: bool) -> None:
        """Ask for (or stop asking for) each object point's colour in this session's scans.

        Raises:
            InputError: the device cannot sample colour.
        """
        client = self.client()
        if colour and not (client.info and client.info.colour):
            raise InputError(
                "this device cannot sample colour (a monochrome camera, the simulator without "
                "--noise harsh, or an older lamina-device): scan without colour"
            )
        self.colour = colour

    def identity(self) -> dict[str, Any]:
        """Return the connected device's identity (what a scan is recorded under)."""
        return self.client().identity()

    def preview(self, laser: bool) -> Preview:
        """Fetch one frame where the axes stand (laser on or off) and the stripe found there."""
        with self.busy(), self.link() as client:
            return client.preview(laser)

    def exposure(self) -> tuple[int, int, int]:
        """Return the camera's (exposure, min, max) in microseconds."""
        with self.busy(), self.link() as client:
            return client.exposure()

    def estimate(self, target: str, plan: ScanPlan | None) -> ScanEstimate | None:
        """Return how long ``plan`` (None: the device's default) would take, if it can say."""
        with self.busy(), self.link() as client:
            return client.estimate(target, plan)

    def set_exposure(self, exposure_us: int) -> int:
        """Set the camera's exposure; return the one the device now uses."""
        with self.busy(), self.link() as client:
            return client.set_exposure(exposure_us)

    def move(self, axis: str, position: float) -> Pose:
        """Move ``lift`` (mm) or ``turntable`` (deg) to ``position``; return the new pose."""
        with self.busy(), self.link() as client:
            position = client.move(axis, position)
        self.pose = self.pose.moved(axis, position)
        return self.pose

    def pause_scan(self) -> None:
        """Hold the running scan on the device after its current view (any thread)."""
        self.client().pause()

    def resume_scan(self) -> None:
        """Let the device go on with a paused scan (any thread)."""
        self.client().resume()

    def abort_scan(self) -> None:
        """End the running scan on the device; the views received stay kept (any thread)."""
        self.client().abort()

    def run_views(
        self,
        target: str,
        plan: ScanPlan,
        held: dict[int, Segment],
        on_store: StoreHandler | None,
        on_segment: SegmentHandler | None,
        on_progress: ProgressHandler | None,
        on_notice: NoticeHandler | None,
        limit: int | None = None,
        resumed: bool | None = None,
    ) -> list[Segment]:
        """Fetch the views of ``plan`` not in ``held``; keep each arrival in ``held``.

        ``held`` maps plan index to segment and survives an abort or a broken link, so the
        same call with the same ``held`` resumes the scan where it stopped. ``on_store``
        commits each view before the link acknowledges it. The caller holds :meth:`busy`.

        Args:
            limit: fetch only the first ``limit`` views of the plan (the device is told it
                holds the others); None: every view.
            resumed: whether this run goes on with a scan begun earlier (its progress says
                how many views are held first); None: when ``held`` is not empty.
        """
        if len(held) >= len(plan.views):
            return [held[k] for k in sorted(held)]
        start, first = time.monotonic(), len(held)
        skipped = () if limit is None else tuple(range(limit, len(plan.views)))

        def report(section: int, starting: bool = False) -> None:
            if on_progress is not None:
                elapsed, done = time.monotonic() - start, len(held)
                total = len(plan.views)
                on_progress(
                    Progress(
                        target,
                        done,
                        total,
                        section,
                        elapsed_s=elapsed,
                        done_this_run=done - first,
                        starting=starting,
                    )
                )

        def take(seq: int, segment: Segment) -> None:
            if on_store is not None:
                on_store(seq, segment)
            held[seq] = segment
            if on_segment is not None:
                on_segment(segment)

        def progress(event: Event) -> None:
            if isinstance(event, ProgressEvent):
                # The count is ours (what is held here); the device says where it is.
                report(event.progress.section)

        if first if resumed is None else resumed:
            # A resumed run: say how many views are held, and where it goes on.
            missing = min(k for k in range(len(plan.views)) if k not in held)
            report(plan.views[missing].section, starting=True)
        extra: dict[str, Any] = {} if self.extract is None else {"extract": self.extract}
        if self.colour and target == "object":  # the cylinder needs no colour
            extra["colour"] = True
        with self.link() as client:
            client.scan(
                target,
                plan,
                progress,
                have=tuple(sorted(set(held) | set(skipped))),
                on_segment=take,
                on_notice=on_notice,
                **extra,
            )
        return [held[k] for k in sorted(held)]
