"""The simulated camera: renders what the virtual rig shows, as the Pi camera would see it.

It answers :class:`lamina_device.camera.Camera`. Each frame is rendered from the real
(error-laden) axis positions and the laser's actual pin state, so the extraction and
the host meet the same errors as on a real scanner.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from lamina_device.camera import CameraError, Stage, check_exposure
from lamina_device.laser import Laser
from lamina_device.sim.axes import SimLift, SimTurntable
from lamina_device.sim.render import SimScene
from lamina_device.sim.sway import Sway

__all__ = ["SIM_EXPOSURE_RANGE_US", "SIM_EXPOSURE_US", "SimCamera"]

SIM_EXPOSURE_US = 4000
"""The simulated camera's nominal exposure: frames at it are the simulator's reference."""
SIM_EXPOSURE_RANGE_US = (100, 20_000)
"""Exposures the simulated camera accepts (a Camera Module 3 in its 120 fps mode)."""


@dataclass
class SimCamera:
    """Renders the virtual rig as it really is: true axis positions, real laser state."""

    scene: SimScene
    stage: Stage
    turntable: SimTurntable
    lift: SimLift
    laser: Laser
    sway: Sway = field(default_factory=Sway)
    """How the object moves while it is scanned (a patient's drift and breathing)."""
    frames_taken: int = field(default=0, init=False)
    exposure_us: int = field(default=SIM_EXPOSURE_US, init=False)
    exposure_range_us: tuple[int, int] = field(default=SIM_EXPOSURE_RANGE_US, init=False)

    @property
    def size(self) -> tuple[int, int]:
        """Return (width, height) in pixels."""
        return self.scene.rig.image_size

    def set_exposure(self, exposure_us: int) -> None:
        """Expose later frames for ``exposure_us``: the light scales with it, noise does not."""
        check_exposure(exposure_us, self.exposure_range_us)
        self.exposure_us = int(exposure_us)

    def capture(self) -> np.ndarray:
        """Render one frame of the current scene."""
        self.frames_taken += 1
        self.turntable.clock.frame(self.exposure_us)
        return self._render(self.scene.render)

    @property
    def has_colour(self) -> bool:
        """Return True for colour noise models (``harsh``): the thesis camera is monochrome."""
        return self.scene.noise.laser_rgb is not None

    def capture_colour(self) -> tuple[np.ndarray, np.ndarray]:
        """Render one frame and the RGB it was formed from (the Pi's Y plane and its colour).

        Both come from one exposure: the scene draws a frame's noise from the frame's own
        key, so the luma and the RGB carry the same noise.
        """
        if not self.has_colour:
            raise CameraError(
                "the simulated camera is monochrome under this noise model: use --noise harsh "
                "for colour"
            )
        self.frames_taken += 1
        self.turntable.clock.frame(self.exposure_us)
        return self._render(self.scene.render), self._render(self.scene.render_rgb)

    def _render(self, render: Callable[..., np.ndarray]) -> np.ndarray:
        """Return ``render`` of the scene at the true axis positions and laser state."""
        return render(
            self.stage.target,
            self.turntable.true_angle_deg,
            self.lift.true_z_mm,
            self.laser.is_on,
            exposure_scale=self.exposure_us / SIM_EXPOSURE_US,
            shift_mm=self.sway.offset_mm(self.turntable.clock.now_s),
        )

    def close(self) -> None:
        """Nothing to release."""
