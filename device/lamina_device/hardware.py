"""The hardware a device program drives, and the scanner box's own assembly of it.

:class:`Hardware` is what every backend gives: camera, laser, lift, turntable, with the
laser watchdog running. :func:`open_pi` assembles the scanner box (picamera2, the laser
on a GPIO, stepper axes, all as the TOML configuration says); the simulator and replay
backends build on this module, and :mod:`lamina_device.backends` picks one by name.
"""

from __future__ import annotations

import secrets
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

from gpiozero.pins import Factory

from lamina_device.camera import Camera, PiCamera, Stage
from lamina_device.config import DeviceConfig
from lamina_device.extract import ExtractSettings
from lamina_device.laser import Laser
from lamina_device.motion import Lift, StepperLift, StepperTurntable, Turntable
from lamina_device.safety import LaserWatchdog
from lamina_shared.errors import LaminaError
from lamina_shared.types import BoardSpec, LiftReference, ScanPlan


class HardwareError(LaminaError, ValueError):
    """The requested hardware cannot be set up; the message says why and what to do."""


@dataclass
class Hardware:
    """Everything the acquisition drives, plus what the device knows about its targets."""

    kind: str
    camera: Camera
    laser: Laser
    turntable: Turntable
    lift: Lift
    stage: Stage
    board: BoardSpec | None
    cylinder_diameter_mm: float | None
    default_plans: dict[str, ScanPlan] = field(default_factory=dict)
    description: str = ""
    settle_s: float = 0.0
    watchdog: LaserWatchdog | None = None
    identity: dict[str, str] = field(default_factory=lambda: {"serial": "", "source": ""})
    """What the host stores with a scan and checks at resume: ``serial`` names the
    device, ``source`` what it images, ``count_since`` (the box only) the run of the
    turntable's step count, new each time the program starts (WELCOME ``identity``)."""
    extract: ExtractSettings = field(default_factory=ExtractSettings)
    """The configured stripe extraction (``[extract]``; a scan request may change it)."""
    sleep: Callable[[float], None] = time.sleep
    """How the settle waits: real time on the box, the virtual clock in the simulator."""
    timing: DeviceConfig | None = None
    """The configuration whose axes and camera time a scan here (the ``estimate`` op):
    the box's own; the shipped one for the simulator and a replay (None: unknown)."""
    clock_ns: Callable[[], int] = time.monotonic_ns
    """The clock frames are stamped and the table's steps counted on (CLOCK_MONOTONIC on
    the box, the virtual clock in the simulator)."""
    lift_settle_s: float | None = None
    """The lift's own settle, which a continuous scan waits after each section's lift move
    (the table keeps turning); None: :attr:`settle_s`."""
    lift_reference: LiftReference | None = None
    """The calibration cylinder's marks that calibrate the lift (WELCOME ``lift_reference``);
    the default cylinder plan then holds a section at each (None: the lift is trusted)."""

    def place(self, target: str, again: bool = False) -> None:
        """Put ``target`` on the turntable (the operator does this on a real scanner).

        ``again``: a scan goes on with the target already standing there (a resumed scan),
        so where the table's count stood when it was put on is kept.
        """
        if not again or target != self.stage.target:
            self.stage.placed_count_deg = self.turntable.count_deg
        self.stage.target = target

    def settle(self) -> None:
        """Wait for vibration after a move to die down before exposing."""
        if self.settle_s > 0:
            self.sleep(self.settle_s)

    @property
    def lift_settle_wait_s(self) -> float:
        """Return how long :meth:`settle_lift` waits."""
        return self.settle_s if self.lift_settle_s is None else self.lift_settle_s

    def settle_lift(self) -> None:
        """Wait for the lift's vibration to die down (the table turning meanwhile)."""
        if self.lift_settle_wait_s > 0:
            self.sleep(self.lift_settle_wait_s)

    def sleep_until_ns(self, at_ns: int) -> None:
        """Wait until :attr:`clock_ns` reaches ``at_ns`` (nothing if it has passed)."""
        wait_ns = at_ns - self.clock_ns()
        if wait_ns > 0:
            self.sleep(wait_ns * 1e-9)

    def close(self) -> None:
        """Switch the laser off and release everything (the laser first)."""
        self.laser.off()
        try:
            if self.watchdog is not None:
                self.watchdog.stop()
            self.camera.close()
            self.turntable.close()
            self.lift.close()
        finally:
            self.laser.close()


def pi_serial(
    paths: tuple[Path, ...] = (Path("/proc/device-tree/serial-number"), Path("/proc/cpuinfo")),
) -> str:
    """Return the Raspberry Pi's serial number, or ``"unknown"`` where none can be read."""
    for path in paths:
        try:
            text = path.read_text(encoding="ascii", errors="replace")[:65536]
        except OSError:
            continue
        if path.name == "cpuinfo":
            for line in text.splitlines():
                key, _, value = line.partition(":")
                if key.strip() == "Serial" and value.strip():
                    return value.strip()
        elif text.strip("\0 \n"):
            return text.strip("\0 \n")
    return "unknown"


def watched(hardware: Hardware, max_on_s: float = 2.0, link_silence_s: float = 10.0) -> Hardware:
    """Start the laser watchdog of ``hardware`` and return it."""
    hardware.watchdog = LaserWatchdog(hardware.laser, max_on_s, link_silence_s)
    hardware.watchdog.start()
    return hardware


def open_pi(config: DeviceConfig, source: str, pin_factory: Factory | None = None) -> Hardware:
    """Return the scanner box's hardware as ``config`` describes it.

    Args:
        config: a validated configuration.
        source: where the configuration came from (for the description).
        pin_factory: gpiozero pin factory; None uses gpiozero's choice
            (``GPIOZERO_PIN_FACTORY``: lgpio on the Pi, ``mock`` in tests).
    """
    laser = Laser(config.laser.pin, config.laser.active_high, pin_factory)
    parts: list[StepperTurntable | StepperLift] = []
    try:
        turntable = StepperTurntable(config.turntable, pin_factory)
        parts.append(turntable)
        lift = StepperLift(config.lift, pin_factory)
        parts.append(lift)
        camera = PiCamera(config.camera, laser)
    except Exception:
        for part in parts:
            part.close()
        laser.close()
        raise
    board = config.board
    plan = config.plan
    cylinder_plan = ScanPlan.regular(
        plan.cylinder_sections, plan.cylinder_pitch_mm, plan.cylinder_views
    )
    reference = config.lift_reference
    hardware = Hardware(
        "pi",
        camera,
        laser,
        turntable,
        lift,
        Stage(),
        BoardSpec(board.inner_corners, board.square_mm, board.origin_mm),
        config.cylinder.diameter_mm,
        {
            "object": ScanPlan.regular(plan.sections, plan.pitch_mm, plan.views),
            "cylinder": reference.plan(cylinder_plan) if reference else cylinder_plan,
        },
        f"Lamina scanner box, {config.camera.width}x{config.camera.height}, config {source}",
        settle_s=max(config.turntable.settle_s, config.lift.settle_s),
        timing=config,
        lift_settle_s=config.lift.settle_s,
        identity={
            "serial": config.device_id or pi_serial(),
            "source": "camera",
            # The stepper's count starts at 0 wherever the table stands: a scan begun
            # before this program started cannot be continued on this count.
            "count_since": secrets.token_hex(8),
        },
        extract=config.extract,
        lift_reference=reference,
    )
    return watched(hardware, config.safety.laser_max_on_s, config.safety.link_silence_s)
