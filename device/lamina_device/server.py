"""The device end of the link: the shared endpoint with the scanner's operations.

:class:`DeviceServer` is :class:`lamina_shared.endpoint.DeviceEndpoint` (framing, reply
cache, acknowledgements, retransmissions, heartbeats) given the operations table of
:mod:`lamina_device.operations` and the hardware's safety hooks.

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

import dataclasses
import json
import logging
from typing import Any

from lamina_device import __version__
from lamina_device.acquisition import off_frames, row_turn_deg
from lamina_device.camera import CameraError, camera_has_colour
from lamina_device.hardware import Hardware
from lamina_device.motion import MotionError
from lamina_device.operations import Operations, scan_modes
from lamina_shared.capture import FrameError
from lamina_shared.endpoint import DeviceEndpoint, PortLost, RequestError, ServerSettings
from lamina_shared.link import Channel
from lamina_shared.messages import DeviceIdentity, Welcome
from lamina_shared.ops import OPS, ExtractChanges
from lamina_shared.protocol import PROTOCOL_VERSION, ROW_SCALE
from lamina_shared.types import ScanPlan

log = logging.getLogger(__name__)

HARDWARE_FAULTS = (CameraError, MotionError, FrameError, OSError)
"""What an operation may meet on a working device (answered ``failed``); anything else
raised inside an operation is a bug (logged with its traceback, answered ``internal``)."""


class DeviceServer(DeviceEndpoint):
    """Serve one host at a time over ``channel`` until told to stop or the link closes."""

    faults = HARDWARE_FAULTS
    log = log

    def __init__(
        self, channel: Channel, hardware: Hardware, settings: ServerSettings | None = None
    ) -> None:
        self.hardware = hardware
        self.operations = Operations(hardware, self)
        super().__init__(channel, self.operations.table(), settings)

    # --- the endpoint's hooks ------------------------------------------------------------

    def make_safe(self) -> None:
        """Switch the laser off."""
        self.hardware.laser.off()

    def link_alive(self) -> None:
        """Feed the laser watchdog: the host is there."""
        if self.hardware.watchdog is not None:
            self.hardware.watchdog.link_alive()

    def abort_running(self) -> None:
        """Abort the running scan (its host has gone)."""
        if self.operations.control is not None:
            self.operations.control.abort()

    def paused(self) -> bool:
        """Return True while the running scan is paused."""
        control = self.operations.control
        return control is not None and control.paused

    # --- the handshake ---------------------------------------------------------------

    def welcome(self) -> dict[str, Any]:
        """Return the WELCOME body: :meth:`info` in its wire form."""
        return self.info().to_wire()

    def info(self) -> Welcome:
        """Return what the device tells the host about itself at the handshake.

        ``extract`` is the configured extraction (a scan request may change it).
        """
        hw = self.hardware
        modes = scan_modes(hw)
        return Welcome(
            protocol=PROTOCOL_VERSION,
            software=f"lamina-device {__version__}",
            hardware=hw.kind,
            description=hw.description,
            image_size=hw.camera.size,
            board=hw.board,
            cylinder_diameter_mm=hw.cylinder_diameter_mm,
            default_plans=self._welcome_plans(),
            axes=self.operations.limits,
            operations=tuple(sorted(OPS)),
            limits=self.settings.limits,
            row_scale=ROW_SCALE,
            identity=DeviceIdentity(**hw.identity),
            extract=ExtractChanges(tuple(dataclasses.asdict(hw.extract).items())),
            colour=camera_has_colour(hw.camera),
            modes=modes,
            lift_reference=hw.lift_reference,
            row_turn_deg=row_turn_deg(hw) if "continuous" in modes else None,
            off_frames=off_frames(hw) if "continuous" in modes else None,
        )

    def _welcome_plans(self) -> dict[str, ScanPlan]:
        """Return the default plans, leaving out one too long for the WELCOME.

        A regular plan takes a few bytes; a replayed capture's irregular plan is listed
        and may not fit one message: the host then passes a plan, or asks ``scan`` with
        none (the device's default).
        """
        plans = {}
        budget = self.settings.limits.max_payload_bytes // 4
        for target, plan in self.hardware.default_plans.items():
            if len(json.dumps(plan.to_wire())) <= budget:
                plans[target] = plan
            else:
                log.warning("the default %s plan is too long for the WELCOME", target)
        return plans


__all__ = ["HARDWARE_FAULTS", "DeviceServer", "PortLost", "RequestError", "ServerSettings"]
