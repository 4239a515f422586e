"""Choosing and assembling the hardware the device program drives.

``sim`` is the virtual rig; ``replay:DIR`` is a recorded capture standing in for
the camera. Both use gpiozero's MockFactory for the laser pin, so the laser's state
history is real gpiozero behaviour, and simulated axes for motion.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from gpiozero.pins.mock import MockFactory

from lamina_device.camera import Camera, ReplayCamera, SimCamera, Stage
from lamina_device.laser import Laser
from lamina_device.motion import Mechanics, SimLift, SimTurntable
from lamina_device.sim import NoiseModel, Rig, SimScene, parse_object
from lamina_shared.capture import load_capture
from lamina_shared.types import BoardSpec, ScanPlan

LASER_PIN = 17
DEFAULT_OBJECT = "cylinder:d=19.05"
DEFAULT_PLAN = ScanPlan.regular(sections=4, pitch_mm=2.0, views=8)
DEFAULT_CYLINDER_PLAN = ScanPlan.regular(sections=1, pitch_mm=2.0, views=8)


class HardwareError(ValueError):
    """The requested hardware cannot be set up; the message says why and what to do."""


@dataclass
class Hardware:
    """Everything the acquisition drives, plus what the device knows about its targets."""

    kind: str
    camera: Camera
    laser: Laser
    turntable: SimTurntable
    lift: SimLift
    stage: Stage
    board: BoardSpec | None
    cylinder_diameter_mm: float | None
    default_plans: dict[str, ScanPlan] = field(default_factory=dict)
    description: str = ""

    def place(self, target: str) -> None:
        """Put ``target`` on the turntable (the operator does this on a real scanner)."""
        self.stage.target = target

    def close(self) -> None:
        """Switch the laser off and release everything."""
        self.laser.close()
        self.camera.close()


def open_sim(object_spec: str | None = None, seed: int = 0, noise: str = "thesis") -> Hardware:
    """Return the simulated rig with ``object_spec`` on the turntable."""
    spec = object_spec or DEFAULT_OBJECT
    try:
        obj = parse_object(spec)
    except ValueError as exc:
        raise HardwareError(f"object {spec!r}: {exc}") from None
    noise_model = NoiseModel.thesis() if noise == "thesis" else NoiseModel.none()
    mechanics = Mechanics() if noise == "thesis" else Mechanics.ideal()
    rig = Rig()
    scene = SimScene(rig, obj, noise_model, seed)
    factory = MockFactory()
    laser = Laser(LASER_PIN, pin_factory=factory)
    turntable, lift, stage = SimTurntable(mechanics), SimLift(mechanics), Stage()
    camera = SimCamera(scene, stage, turntable, lift, laser)
    return Hardware(
        "sim",
        camera,
        laser,
        turntable,
        lift,
        stage,
        rig.board,
        rig.cylinder_diameter_mm,
        {"object": DEFAULT_PLAN, "cylinder": DEFAULT_CYLINDER_PLAN},
        f"simulated rig, object {spec}, seed {seed}, noise {noise}",
    )


def open_replay(folder: Path) -> Hardware:
    """Return a device whose camera replays the capture in ``folder`` (validated first)."""
    capture = load_capture(folder)
    laser = Laser(LASER_PIN, pin_factory=MockFactory())
    mechanics = Mechanics.ideal()
    turntable, lift, stage = SimTurntable(mechanics), SimLift(mechanics, 10_000.0), Stage()
    camera = ReplayCamera(capture, stage, turntable, lift, laser)
    plans = {t: p for t in ("cylinder", "object") if (p := capture.plan(t)) is not None}
    return Hardware(
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
    )


def open_hardware(
    spec: str, object_spec: str | None = None, seed: int = 0, noise: str = "thesis"
) -> Hardware:
    """Return the hardware named by ``spec``: ``sim`` or ``replay:DIR``."""
    if spec == "sim":
        return open_sim(object_spec, seed, noise)
    if spec.startswith("replay:"):
        folder = spec.removeprefix("replay:")
        if not folder:
            raise HardwareError("replay needs a capture folder: --hardware replay:DIR")
        return open_replay(Path(folder))
    raise HardwareError(
        f"unknown hardware {spec!r}: use 'sim' or 'replay:DIR' (a recorded capture folder)"
    )
