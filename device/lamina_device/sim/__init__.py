"""Simulated light-sectioning rig: true geometry, test objects and an honest camera renderer."""

from lamina_device.sim.objects import (
    Cylinder,
    Ellipsoid,
    SceneObject,
    TriangleMesh,
    cylinder,
    ellipsoid,
    load_mesh,
    parse_object,
    sphere,
)
from lamina_device.sim.render import NOISE_PRESETS, NoiseModel, SimScene
from lamina_device.sim.rig import RIG_PRESETS, Rig

__all__ = [
    "NOISE_PRESETS",
    "RIG_PRESETS",
    "Cylinder",
    "Ellipsoid",
    "NoiseModel",
    "Rig",
    "SceneObject",
    "SimScene",
    "TriangleMesh",
    "cylinder",
    "ellipsoid",
    "load_mesh",
    "parse_object",
    "sphere",
]
