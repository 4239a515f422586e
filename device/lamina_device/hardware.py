"""Choosing and assembling the hardware the device program drives.

``pi`` is the scanner box: picamera2, the laser on a GPIO, stepper axes, all as the
TOML configuration says. ``sim`` is the virtual rig; ``replay:DIR`` is a recorded
capture standing in for the camera. Sim and replay use gpiozero's MockFactory for
the laser pin, so the laser's state history is real gpiozero behaviour, and
simulated axes for motion. Every kind comes with its laser watchdog running.
"""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass, field
from pathlib import Path

from gpiozero.exc import GPIOZeroError
from gpiozero.pins import Factory
from gpiozero.pins.mock import MockFactory

from lamina_device.camera import Camera, CameraError, PiCamera, ReplayCamera, SimCamera, Stage
from lamina_device.config import ConfigError, DeviceConfig, load_config
from lamina_device.extract import ExtractSettings
from lamina_device.laser import Laser
from lamina_device.motion import (
    Lift,
    Mechanics,
    SimLift,
    SimTurntable,
    StepperLift,
    StepperTurntable,
    Turntable,
)
from lamina_device.safety import LaserWatchdog
from lamina_device.sim import NoiseModel, Rig, SimScene, parse_object
from lamina_shared.capture import MANIFEST, load_capture
from lamina_shared.errors import LaminaError
from lamina_shared.types import BoardSpec, ScanPlan

LASER_PIN = 17
DEFAULT_OBJECT = "cylinder:d=19.05"
DEFAULT_PLAN = ScanPlan.regular(sections=4, pitch_mm=2.0, views=8)
DEFAULT_CYLINDER_PLAN = ScanPlan.regular(sections=1, pitch_mm=2.0, views=8)


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
    device, ``source`` what it images (WELCOME ``identity``)."""
    extract: ExtractSettings = field(default_factory=ExtractSettings)
    """The configured stripe extraction (``[extract]``; a scan request may change it)."""

    def place(self, target: str) -> None:
        """Put ``target`` on the turntable (the operator does this on a real scanner)."""
        self.stage.target = target

    def settle(self) -> None:
        """Wait for vibration after a move to die down before exposing."""
        if self.settle_s > 0:
            time.sleep(self.settle_s)

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


def sim_source(
    object_spec: str, obj: object, rig: Rig, noise: NoiseModel, mechanics: Mechanics, seed: int
) -> str:
    """Return the canonical text of what a simulated device images.

    The same configuration gives the same text; a different object, rig, noise model,
    mechanics or seed a different one (the parameters' full values are hashed in).
    """
    detail = repr((object_spec, obj, rig, noise, mechanics, seed))
    digest = hashlib.sha256(detail.encode()).hexdigest()[:16]
    return f"sim object={object_spec} seed={seed} params={digest}"


def _watched(hardware: Hardware, max_on_s: float = 2.0, link_silence_s: float = 10.0) -> Hardware:
    """Start the laser watchdog of ``hardware`` and return it."""
    hardware.watchdog = LaserWatchdog(hardware.laser, max_on_s, link_silence_s)
    hardware.watchdog.start()
    return hardware


def open_sim(
    object_spec: str | None = None, seed: int = 0, noise: str = "thesis", rig_name: str = "thesis"
) -> Hardware:
    """Return the simulated rig (``Rig.preset(rig_name)``) with ``object_spec`` on it."""
    spec = object_spec or DEFAULT_OBJECT
    try:
        obj = parse_object(spec)
    except ValueError as exc:
        raise HardwareError(f"object {spec!r}: {exc}") from None
    try:
        noise_model = NoiseModel.preset(noise)
        mechanics = Mechanics.preset(noise)
        rig = Rig.preset(rig_name)
    except ValueError as exc:
        raise HardwareError(str(exc)) from None
    source = sim_source(spec, obj, rig, noise_model, mechanics, seed)
    scene = SimScene(rig, obj, noise_model, seed)
    factory = MockFactory()
    laser = Laser(LASER_PIN, pin_factory=factory)
    turntable, lift, stage = SimTurntable(mechanics), SimLift(mechanics), Stage()
    camera = SimCamera(scene, stage, turntable, lift, laser)
    hardware = Hardware(
        "sim",
        camera,
        laser,
        turntable,
        lift,
        stage,
        rig.board,
        rig.cylinder_diameter_mm,
        {"object": DEFAULT_PLAN, "cylinder": DEFAULT_CYLINDER_PLAN},
        f"simulated {rig_name} rig, object {spec}, seed {seed}, noise {noise}",
        identity={"serial": "sim", "source": source},
    )
    return _watched(hardware)


def open_replay(folder: Path) -> Hardware:
    """Return a device whose camera replays the capture in ``folder`` (validated first)."""
    capture = load_capture(folder)
    manifest_sha = hashlib.sha256((capture.root / MANIFEST).read_bytes()).hexdigest()
    laser = Laser(LASER_PIN, pin_factory=MockFactory())
    mechanics = Mechanics.ideal()
    turntable, lift, stage = SimTurntable(mechanics), SimLift(mechanics, 10_000.0), Stage()
    camera = ReplayCamera(capture, stage, turntable, lift, laser)
    plans = {t: p for t in ("cylinder", "object") if (p := capture.plan(t)) is not None}
    hardware = Hardware(
        "replay",
        camera,
        laser,
        turntable,
        lift,
        stage,
        capture.board,
        capture.cylinder_diameter_mm,
        plans,
        f"replay of {folder}",
        identity={"serial": "replay", "source": f"{folder.resolve().name} sha256={manifest_sha}"},
    )
    return _watched(hardware)


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
            "cylinder": ScanPlan.regular(1, plan.pitch_mm, plan.cylinder_views),
        },
        f"Lamina scanner box, {config.camera.width}x{config.camera.height}, config {source}",
        settle_s=max(config.turntable.settle_s, config.lift.settle_s),
        identity={"serial": config.device_id or pi_serial(), "source": "camera"},
        extract=config.extract,
    )
    return _watched(hardware, config.safety.laser_max_on_s, config.safety.link_silence_s)


def open_hardware(
    spec: str,
    object_spec: str | None = None,
    seed: int = 0,
    noise: str = "thesis",
    config_path: Path | str | None = None,
    pin_factory: Factory | None = None,
    rig: str = "thesis",
) -> Hardware:
    """Return the hardware named by ``spec``: ``sim``, ``replay:DIR`` or ``pi``.

    Args:
        spec: which hardware.
        object_spec: the simulated object (sim only).
        seed: simulation noise seed (sim only).
        noise: one of ``NOISE_PRESETS``: ``thesis``, ``harsh`` or ``none`` (sim only).
        config_path: the TOML configuration (pi only; the packaged default if None).
        pin_factory: gpiozero pin factory for ``pi`` (None: gpiozero's own choice).
        rig: the simulated rig's geometry, ``thesis`` or ``limb`` (sim only).

    Raises:
        HardwareError: naming what is wrong and what to do.
    """
    if spec == "sim":
        return open_sim(object_spec, seed, noise, rig)
    if spec.startswith("replay:"):
        folder = spec.removeprefix("replay:")
        if not folder:
            raise HardwareError("replay needs a capture folder: --hardware replay:DIR")
        return open_replay(Path(folder))
    if spec == "pi":
        try:
            config = load_config(config_path)
            return open_pi(config, str(config_path or "(default)"), pin_factory)
        except (ConfigError, CameraError) as exc:
            raise HardwareError(str(exc)) from None
        except GPIOZeroError as exc:
            raise HardwareError(
                f"cannot drive the GPIO pins: {exc}; on the Pi install python3-lgpio "
                "(GPIOZERO_PIN_FACTORY=lgpio), off the Pi use GPIOZERO_PIN_FACTORY=mock"
            ) from None
    raise HardwareError(
        f"unknown hardware {spec!r}: use 'sim', 'replay:DIR' (a recorded capture folder) or 'pi'"
    )
