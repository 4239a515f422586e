"""The simulated scanner assembled: the virtual rig, its object, camera, laser and axes.

:func:`open_sim` builds the ``sim`` hardware the device program drives: a
:class:`~lamina_device.sim.render.SimScene` rendered by a simulated camera, the laser
on a gpiozero mock pin (so its state history is real gpiozero behaviour) and simulated
axes with the mechanical error model of the chosen noise preset.
"""

from __future__ import annotations

import hashlib

from gpiozero.pins.mock import MockFactory

from lamina_device.camera import Stage
from lamina_device.config import DeviceConfig, load_config
from lamina_device.hardware import Hardware, HardwareError, watched
from lamina_device.laser import MOCK_LASER_PIN, Laser
from lamina_device.sim.axes import Mechanics, SimClock, SimLift, SimTurntable
from lamina_device.sim.camera import SimCamera
from lamina_device.sim.render import NoiseModel, SimScene
from lamina_device.sim.rig import Rig
from lamina_device.sim.specs import parse_object
from lamina_device.sim.sway import parse_sway
from lamina_shared.types import ScanPlan

__all__ = [
    "DEFAULT_CYLINDER_PLAN",
    "DEFAULT_OBJECT",
    "DEFAULT_PLAN",
    "open_sim",
    "sim_source",
]

DEFAULT_OBJECT = "cylinder:d=19.05"
DEFAULT_PLAN = ScanPlan.regular(sections=4, pitch_mm=2.0, views=8)
# Three heights of the cylinder, not one: each height's arcs give the turntable axis with
# their own noise, and the axis's error along the camera's line of sight grows or shrinks
# every outline of a scan (eight seeds: spread 0.012 mm from one height, 0.005 mm from three).
DEFAULT_CYLINDER_PLAN = ScanPlan.regular(sections=3, pitch_mm=3.0, views=8)


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


def open_sim(
    object_spec: str | None = None,
    seed: int = 0,
    noise: str = "thesis",
    rig_name: str = "thesis",
    rig: Rig | None = None,
    sway: str = "none",
    lift_error_percent: float | None = None,
    config: DeviceConfig | None = None,
) -> Hardware:
    """Return the simulated rig (``Rig.preset(rig_name)``) with ``object_spec`` on it.

    ``rig``, when given, replaces the preset (tests scan small, low-resolution variants).
    ``sway`` moves the object during the scan (:func:`lamina_device.sim.sway.parse_sway`).
    ``lift_error_percent`` replaces the preset's lift scale error (``--lift-error``).
    ``config`` replaces the shipped configuration the simulated box runs on (its speeds,
    settle times, frame timing and continuous settings; ``--config``).
    """
    spec = object_spec or DEFAULT_OBJECT
    try:
        obj = parse_object(spec)
    except ValueError as exc:
        raise HardwareError(f"object {spec!r}: {exc}") from None
    try:
        noise_model = NoiseModel.preset(noise)
        mechanics = Mechanics.preset(noise)
        if lift_error_percent is not None:
            mechanics = mechanics.with_lift_error(lift_error_percent)
        rig = rig if rig is not None else Rig.preset(rig_name)
        motion = parse_sway(sway, seed)
    except ValueError as exc:
        raise HardwareError(str(exc)) from None
    source = sim_source(spec, obj, rig, noise_model, mechanics, seed)
    if not motion.still:
        source += f" sway={sway}"
    scene = SimScene(rig, obj, noise_model, seed)
    clock = SimClock() if config is None else SimClock(config=config)
    if config is not None:  # the pulleys are the shipped box's, whatever the file says
        mechanics = mechanics.on_box(config.turntable, load_config().turntable.gear_ratio)
    laser = Laser(MOCK_LASER_PIN, pin_factory=MockFactory(), clock_ns=clock.now_ns)
    stage = Stage()
    turntable, lift = SimTurntable(mechanics, clock, stage), SimLift(mechanics, clock=clock)
    camera = SimCamera(scene, stage, turntable, lift, laser, motion)
    reference = rig.lift_reference()
    cylinder_plan = reference.plan(DEFAULT_CYLINDER_PLAN) if reference else DEFAULT_CYLINDER_PLAN
    hardware = Hardware(
        "sim",
        camera,
        laser,
        turntable,
        lift,
        stage,
        rig.board,
        rig.cylinder_diameter_mm,
        {"object": DEFAULT_PLAN, "cylinder": cylinder_plan},
        f"simulated {rig_name} rig, object {spec}, seed {seed}, noise {noise}",
        settle_s=clock.settle_s,
        timing=clock.config,
        identity={"serial": "sim", "source": source},
        sleep=clock.advance,
        clock_ns=clock.now_ns,
        lift_settle_s=clock.config.lift.settle_s,
        lift_reference=reference,
    )
    return watched(hardware)
