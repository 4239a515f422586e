"""The simulated camera: renders what the virtual rig shows, as the Pi camera would see it.

It answers :class:`lamina_device.camera.Camera`. Each frame is rendered from the real
(error-laden) axis positions and the laser's actual pin state, so the extraction and
the host meet the same errors as on a real scanner.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from lamina_device.camera import (
    LASER_LATENCY_NS,
    CameraError,
    FrameTiming,
    Stage,
    TimedFrame,
    check_exposure,
)
from lamina_device.laser import Laser
from lamina_device.sim.axes import SimLift, SimTurntable
from lamina_device.sim.render import Exposure, SimScene
from lamina_device.sim.sway import Sway

__all__ = ["SIM_EXPOSURE_RANGE_US", "SIM_EXPOSURE_US", "TIMESTAMP_JITTER_US", "SimCamera"]

SIM_EXPOSURE_US = 4000
"""The simulated camera's nominal exposure: frames at it are the simulator's reference."""
SIM_EXPOSURE_RANGE_US = (100, 20_000)
"""Exposures the simulated camera accepts (a Camera Module 3 in its 120 fps mode)."""
TIMESTAMP_JITTER_US = 50.0
"""Standard deviation of a streamed frame's reported timestamp about its true one: the
CSI-2 receiver stamps the frame-start interrupt, tens of microseconds late and not always
by the same amount."""


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
    last_frame_s: float = field(default=0.0, init=False)
    """When the last frame arrived on the virtual clock (the end of a scan's wait)."""
    lit_frames_s: list[float] = field(default_factory=list, init=False)
    """When each laser-on frame arrived on the virtual clock, in the order taken: where a
    swaying subject was for each view (a segment reaches its receiver later, when the
    device's extraction thread is done with it, which the machine's load moves)."""
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
        self._arrived(self.turntable.clock.now_s)
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
        self._arrived(self.turntable.clock.now_s)
        return self._render(self.scene.render), self._render(self.scene.render_rgb)

    def _arrived(self, now_s: float) -> None:
        """Note a frame's arrival at ``now_s`` (and a laser-on frame's among the lit ones)."""
        self.last_frame_s = now_s
        if self.laser.is_on:
            self.lit_frames_s.append(now_s)

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

    @property
    def frame_timing(self) -> FrameTiming:
        """Return the box's frame period and read-out (shipped configuration), this exposure."""
        camera = self.turntable.clock.config.camera
        period_s = max(camera.frame_duration_us, self.exposure_us) * 1e-6
        return FrameTiming(period_s, self.exposure_us * 1e-6, camera.readout_s, self.size[1])

    def capture_timed(self) -> TimedFrame:
        """Return the next streamed frame exposed wholly after the laser's last switch.

        The sensor streams from power-up (frame ``k`` starts at ``k`` periods on the
        virtual clock); the call returns the first frame still to arrive whose first
        row started after the laser's last switch, the clock then at its arrival (its
        last row read). The frame is rendered with the target where it really is while
        each row is exposed (:meth:`~lamina_device.sim.render.SimScene.render_exposure`);
        its reported timestamp is off by the receiver's jitter.
        """
        clock = self.turntable.clock
        timing = self.frame_timing
        period, span = timing.period_s, timing.span_s
        after_s = max((self.laser.changed_ns + LASER_LATENCY_NS) * 1e-9, clock.now_s - span)
        index = math.ceil(after_s / period - 1e-9)
        start_s = index * period
        clock.advance(start_s + span - clock.now_s)
        self.frames_taken += 1
        self._arrived(clock.now_s)

        def pose(when_s: float, around_s: float) -> tuple[float, tuple[float, float]]:
            reference = self.turntable.angle_at(round(around_s * 1e9))
            true = self.turntable.true_angle_near(round(when_s * 1e9), reference)
            return true, self.sway.offset_mm(when_s)

        exposure = Exposure(start_s, timing.exposure_s, timing.row_s, pose)
        image, _ = self.scene.render_exposure(
            self.stage.target,
            self.lift.true_z_mm,
            self.laser.is_on,
            exposure,
            ("frame", index),
            exposure_scale=self.exposure_us / SIM_EXPOSURE_US,
        )
        jitter_s = TIMESTAMP_JITTER_US * 1e-6 * self._jitter(index)
        return TimedFrame(
            image,
            round((start_s + jitter_s) * 1e9),
            round(timing.exposure_s * 1e9),
            timing.row_s * 1e9,
        )

    def _jitter(self, index: int) -> float:
        """Return frame ``index``'s timestamp error in standard deviations (repeatable)."""
        digest = hashlib.blake2b(f"{self.scene.seed}:{index}".encode(), digest_size=8).digest()
        return float(np.random.default_rng(int.from_bytes(digest, "little")).standard_normal())

    def close(self) -> None:
        """Nothing to release."""
