"""A patient who does not hold quite still: slow drift and breathing during a scan.

A limb on the turntable moves with the person it belongs to. Over the minutes of a scan
a standing or seated patient drifts by a millimetre or two and breathes at a quarter of
a hertz, moving the limb by a few tenths of a millimetre each breath. The simulator
moves the object by :meth:`Sway.offset_mm` at each frame's time on its virtual clock
(:class:`lamina_device.sim.axes.SimClock`), so a longer scan meets more of it, as a
patient would. The motion is horizontal (the turntable's plane): the limb's own weight
keeps it on the table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["SWAY_PRESETS", "Sway", "parse_sway"]


@dataclass(frozen=True)
class Sway:
    """Drift at a constant rate plus breathing, each along its own horizontal direction.

    Attributes:
        drift_mm_per_min: how far the limb drifts in a minute.
        breathing_mm: the breathing motion's amplitude (half its peak-to-peak travel).
        breathing_hz: the breathing rate.
        seed: picks the two directions and the breathing's phase.
    """

    drift_mm_per_min: float = 0.0
    breathing_mm: float = 0.0
    breathing_hz: float = 0.25
    seed: int = 0

    def offset_mm(self, t_s: float) -> tuple[float, float]:
        """Return the limb's horizontal displacement (x, y) ``t_s`` seconds into the scan."""
        if self.still:
            return (0.0, 0.0)
        drift_dir, breath_dir, phase = np.random.default_rng(self.seed).uniform(0, 2 * math.pi, 3)
        drift = self.drift_mm_per_min * t_s / 60.0
        breath = self.breathing_mm * math.sin(2 * math.pi * self.breathing_hz * t_s + phase)
        return (
            drift * math.cos(drift_dir) + breath * math.cos(breath_dir),
            drift * math.sin(drift_dir) + breath * math.sin(breath_dir),
        )

    @property
    def still(self) -> bool:
        """Return True when the limb does not move at all."""
        return self.drift_mm_per_min == 0.0 and self.breathing_mm == 0.0


SWAY_PRESETS = {
    "none": Sway(),
    "patient": Sway(drift_mm_per_min=1.0, breathing_mm=0.5, breathing_hz=0.25),
}
"""``none``: a cast or a model; ``patient``: a seated patient holding still as asked."""

_KEYS = {"drift": "drift_mm_per_min", "breath": "breathing_mm", "hz": "breathing_hz"}


def parse_sway(spec: str, seed: int = 0) -> Sway:
    """Return the sway named by ``spec``: a preset or ``drift=MM_PER_MIN,breath=MM,hz=HZ``.

    Raises:
        ValueError: naming the key or value that is wrong and the accepted forms.
    """
    form = "none, patient, or drift=1.0,breath=0.5,hz=0.25 (mm per minute, mm, Hz)"
    text = spec.strip().lower()
    if text in SWAY_PRESETS:
        sway = SWAY_PRESETS[text]
        return Sway(sway.drift_mm_per_min, sway.breathing_mm, sway.breathing_hz, seed)
    values: dict[str, float] = {}
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, eq, value = (s.strip() for s in part.partition("="))
        if not eq or key not in _KEYS:
            raise ValueError(
                f"sway {spec!r}: {part!r} is not one of {', '.join(_KEYS)}; use {form}"
            )
        try:
            number = float(value)
        except ValueError:
            raise ValueError(
                f"sway {spec!r}: {key}={value!r} is not a number; use {form}"
            ) from None
        if not (math.isfinite(number) and 0.0 <= number <= (5.0 if key == "hz" else 50.0)):
            raise ValueError(f"sway {spec!r}: {key}={value} is out of range; use {form}")
        values[_KEYS[key]] = number
    if not values:
        raise ValueError(f"sway {spec!r} is empty; use {form}")
    return Sway(**values, seed=seed)
