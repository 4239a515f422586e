"""Names of the simulated scanner's presets, shared by the device and host command lines.

The host spawns the simulated device and must offer the same choices without importing
the device package, so the names live here, once.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import TypeVar

__all__ = ["NOISE_PRESETS", "RIG_PRESETS", "make_preset"]

T = TypeVar("T")

NOISE_PRESETS = ("thesis", "harsh", "wide", "none")
"""Simulated camera noise and mechanical error: ``thesis`` (the thesis-like rig, default),
``harsh`` (a Pi camera at raised analog gain in a lit room, a real lens, an eccentric
turntable gear), ``wide`` (``harsh`` through a wide lens's stronger barrel distortion) and
``none`` (noise-free camera, perfect mechanics)."""

RIG_PRESETS = ("thesis", "limb")
"""Simulated rig geometries (``lamina_device.sim.Rig.preset``): ``thesis`` (the thesis
prototype's scale, 640x480 camera) and ``limb`` (objects up to ~150 mm, 1536x864)."""


def make_preset(kind: str, name: str, makers: Mapping[str, Callable[[], T]]) -> T:
    """Return what ``makers[name]`` makes; an unknown name is a ValueError naming the choices."""
    if name not in makers:
        raise ValueError(f"unknown {kind} {name!r}; use one of {', '.join(makers)}")
    return makers[name]()
