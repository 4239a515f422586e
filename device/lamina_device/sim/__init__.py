"""Simulated light-sectioning rig: true geometry, test objects and an honest camera renderer.

Every simulated backend lives here, as gpiozero keeps its mock pins in one module: the
axes with their mechanical error model (``axes``), the camera (``camera``) and the
assembled ``sim`` hardware (``backend.open_sim``). The replay of a recorded capture is
``lamina_device.replay``.
"""

from lamina_device.sim.axes import SIM_LIFT_TRAVEL_MM, Mechanics, SimLift, SimTurntable
from lamina_device.sim.backend import open_sim
from lamina_device.sim.camera import SIM_EXPOSURE_RANGE_US, SIM_EXPOSURE_US, SimCamera
from lamina_device.sim.objects import (
    Cylinder,
    Ellipsoid,
    SceneObject,
    TriangleMesh,
    cylinder,
    ellipsoid,
    load_mesh,
    sphere,
)
from lamina_device.sim.render import NOISE_PRESETS, NoiseModel, SimScene
from lamina_device.sim.rig import RIG_PRESETS, Rig
from lamina_device.sim.specs import parse_object

__all__ = [
    "NOISE_PRESETS",
    "RIG_PRESETS",
    "SIM_EXPOSURE_RANGE_US",
    "SIM_EXPOSURE_US",
    "SIM_LIFT_TRAVEL_MM",
    "Cylinder",
    "Ellipsoid",
    "Mechanics",
    "NoiseModel",
    "Rig",
    "SceneObject",
    "SimCamera",
    "SimLift",
    "SimScene",
    "SimTurntable",
    "TriangleMesh",
    "cylinder",
    "ellipsoid",
    "load_mesh",
    "open_sim",
    "parse_object",
    "sphere",
]
