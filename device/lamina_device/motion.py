"""The two motion axes: the turntable (degrees) and the lift (millimetres).

The acquisition only sees :class:`Turntable` and :class:`Lift`. The simulated axes
below carry a mechanical error model, so the simulated scanner puts objects where
real mechanics would, not where they were asked to go: a gear-ratio error (the
thesis measured about 0.2 degrees undershoot per 45 degree step, section 8.3), a
once-per-revolution runout, and a small repeatable jitter per position.
"""

from __future__ import annotations

import hashlib
import math
import struct
from dataclasses import dataclass
from typing import Protocol


class Turntable(Protocol):
    """A rotary axis holding the subject."""

    @property
    def angle_deg(self) -> float:
        """Return the commanded angle."""
        ...  # pragma: no cover - protocol

    def move_to(self, angle_deg: float) -> None:
        """Rotate to ``angle_deg`` (counter-clockwise seen from above)."""
        ...  # pragma: no cover - protocol


class Lift(Protocol):
    """The vertical axis that moves the laser plane relative to the subject."""

    @property
    def z_mm(self) -> float:
        """Return the commanded height."""
        ...  # pragma: no cover - protocol

    def move_to(self, z_mm: float) -> None:
        """Move so the laser plane is ``z_mm`` above the first section."""
        ...  # pragma: no cover - protocol


def _repeatable_unit_noise(*key: float) -> float:
    """Return a repeatable number in [-1, 1) derived from ``key`` (not from call order)."""
    digest = hashlib.blake2b(struct.pack(f"<{len(key)}d", *key), digest_size=8).digest()
    return int.from_bytes(digest, "little") / 2**63 - 1.0


@dataclass(frozen=True)
class Mechanics:
    """Error model of the simulated axes; :meth:`ideal` has none."""

    angle_scale_error: float = -0.2 / 45.0
    angle_runout_deg: float = 0.02
    angle_jitter_deg: float = 0.01
    lift_scale_error: float = 0.002
    lift_jitter_mm: float = 0.005

    @classmethod
    def ideal(cls) -> Mechanics:
        """Return perfect mechanics (for tests that isolate other error sources)."""
        return cls(0.0, 0.0, 0.0, 0.0, 0.0)

    def true_angle_deg(self, commanded_deg: float) -> float:
        """Return where the turntable really is when told ``commanded_deg``."""
        runout = self.angle_runout_deg * math.sin(math.radians(commanded_deg))
        jitter = self.angle_jitter_deg * _repeatable_unit_noise(1.0, commanded_deg)
        return commanded_deg * (1.0 + self.angle_scale_error) + runout + jitter

    def true_z_mm(self, commanded_mm: float) -> float:
        """Return where the lift really is when told ``commanded_mm``."""
        jitter = self.lift_jitter_mm * _repeatable_unit_noise(2.0, commanded_mm)
        return commanded_mm * (1.0 + self.lift_scale_error) + jitter if commanded_mm else jitter


class SimTurntable:
    """A simulated turntable: instant moves, real positions from :class:`Mechanics`."""

    def __init__(self, mechanics: Mechanics) -> None:
        self.mechanics = mechanics
        self._angle_deg = 0.0

    @property
    def angle_deg(self) -> float:
        """Return the commanded angle."""
        return self._angle_deg

    @property
    def true_angle_deg(self) -> float:
        """Return the angle the object is really at."""
        return self.mechanics.true_angle_deg(self._angle_deg)

    def move_to(self, angle_deg: float) -> None:
        """Rotate to ``angle_deg``."""
        if not math.isfinite(angle_deg):
            raise ValueError(f"turntable angle must be finite, not {angle_deg}")
        self._angle_deg = angle_deg


class SimLift:
    """A simulated lift between soft limits."""

    def __init__(self, mechanics: Mechanics, travel_mm: float = 200.0) -> None:
        self.mechanics = mechanics
        self.travel_mm = travel_mm
        self._z_mm = 0.0

    @property
    def z_mm(self) -> float:
        """Return the commanded height."""
        return self._z_mm

    @property
    def true_z_mm(self) -> float:
        """Return the height the laser plane is really at."""
        return self.mechanics.true_z_mm(self._z_mm)

    def move_to(self, z_mm: float) -> None:
        """Move to ``z_mm``; refuse heights outside ``0..travel_mm``."""
        if not (math.isfinite(z_mm) and 0.0 <= z_mm <= self.travel_mm):
            raise ValueError(f"lift height {z_mm} mm is outside 0..{self.travel_mm} mm")
        self._z_mm = z_mm
