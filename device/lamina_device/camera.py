"""Cameras: where frames come from. All of them answer :class:`Camera`.

The simulated camera renders what the virtual rig would show given the real
(error-laden) axis positions and the laser's actual pin state; the replay camera
serves a recorded capture's frame for the commanded view. Either way the frame
then goes through the same extraction as a live one.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from lamina_device.laser import Laser
from lamina_device.motion import SimLift, SimTurntable
from lamina_device.sim import SimScene
from lamina_shared.capture import Capture, read_frame


class CameraError(RuntimeError):
    """A frame could not be produced."""


class Camera(Protocol):
    """Anything that returns one luminance frame per call."""

    @property
    def size(self) -> tuple[int, int]:
        """Return (width, height) in pixels."""
        ...  # pragma: no cover - protocol

    def capture(self) -> np.ndarray:
        """Expose and return one frame (H, W), uint8 or uint16."""
        ...  # pragma: no cover - protocol

    def close(self) -> None:
        """Release the camera."""
        ...  # pragma: no cover - protocol


@dataclass
class Stage:
    """What currently stands on the turntable: ``grid``, ``cylinder`` or ``object``."""

    target: str = "object"


@dataclass
class SimCamera:
    """Renders the virtual rig as it really is: true axis positions, real laser state."""

    scene: SimScene
    stage: Stage
    turntable: SimTurntable
    lift: SimLift
    laser: Laser
    frames_taken: int = field(default=0, init=False)

    @property
    def size(self) -> tuple[int, int]:
        """Return (width, height) in pixels."""
        return self.scene.rig.image_size

    def capture(self) -> np.ndarray:
        """Render one frame of the current scene."""
        self.frames_taken += 1
        return self.scene.render(
            self.stage.target,
            self.turntable.true_angle_deg,
            self.lift.true_z_mm,
            self.laser.is_on,
        )

    def close(self) -> None:
        """Nothing to release."""


@dataclass
class ReplayCamera:
    """Serves the recorded frame of a capture for the commanded view and laser state."""

    capture_set: Capture
    stage: Stage
    turntable: SimTurntable
    lift: SimLift
    laser: Laser

    @property
    def size(self) -> tuple[int, int]:
        """Return (width, height) in pixels."""
        return self.capture_set.image_size

    def capture(self) -> np.ndarray:
        """Return the recorded frame matching the stage, angle, height and laser state."""
        channel = self.capture_set.laser_channel
        if self.stage.target == "grid":
            if self.capture_set.grid_image is None:
                raise CameraError("the capture holds no calibration grid image")
            return read_frame(self.capture_set.grid_image, channel)
        z_mm, angle = self.lift.z_mm, self.turntable.angle_deg
        for view in self.capture_set.views(self.stage.target):
            if abs(view.spec.z_mm - z_mm) < 1e-6 and abs(view.spec.angle_deg - angle) < 1e-6:
                if self.laser.is_on:
                    return read_frame(view.laser_on, channel)
                if view.laser_off is None:
                    # No laser-off frame recorded: a black frame makes the difference
                    # image equal to the laser-on frame, as the capture spec allows.
                    width, height = self.size
                    return np.zeros((height, width), np.uint8)
                return read_frame(view.laser_off, channel)
        raise CameraError(
            f"the capture has no {self.stage.target} view at z={z_mm} mm, angle={angle} deg"
        )

    def close(self) -> None:
        """Nothing to release."""
