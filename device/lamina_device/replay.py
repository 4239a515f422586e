"""Replay: a recorded capture folder standing in for the scanner's camera.

:class:`ReplayCamera` serves the capture's frame for the commanded view and laser
state; :func:`open_replay` assembles a device around it (a gpiozero mock laser pin,
ideal simulated axes that just record where they were sent), so a recording runs
through the same acquisition, extraction and link as a live scan.
"""

from __future__ import annotations

import hashlib
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np
from gpiozero.pins.mock import MockFactory

from lamina_device.camera import CameraError, ExposureRefused, Stage
from lamina_device.hardware import Hardware, watched
from lamina_device.laser import MOCK_LASER_PIN, Laser
from lamina_device.motion import Lift, Turntable
from lamina_device.sim.axes import Mechanics, SimLift, SimTurntable
from lamina_device.sim.camera import SIM_EXPOSURE_US
from lamina_shared.capture import MANIFEST, Capture, load_capture, read_colour, read_frame
from lamina_shared.limits import DeviceLimits

__all__ = ["ReplayCamera", "open_replay"]


@dataclass
class ReplayCamera:
    """Serves the recorded frame of a capture for the commanded view and laser state."""

    capture_set: Capture
    stage: Stage
    turntable: Turntable
    lift: Lift
    laser: Laser

    @property
    def size(self) -> tuple[int, int]:
        """Return (width, height) in pixels."""
        return self.capture_set.image_size

    @property
    def exposure_us(self) -> int:
        """Return the nominal exposure (the recorded frames' own is not known here)."""
        return SIM_EXPOSURE_US

    @property
    def exposure_range_us(self) -> tuple[int, int]:
        """Return the one exposure a replay has: the one it was recorded with."""
        return (SIM_EXPOSURE_US, SIM_EXPOSURE_US)

    def set_exposure(self, exposure_us: int) -> None:
        """Refuse any change: recorded frames cannot be exposed again."""
        if exposure_us != self.exposure_us:
            raise ExposureRefused(
                "a replayed capture cannot change its exposure (the frames are recorded); "
                "set the exposure on the live scanner or simulator instead"
            )

    def capture(self) -> np.ndarray:
        """Return the recorded frame matching the stage, angle, height and laser state."""
        channel = self.capture_set.laser_channel
        path = self._frame_path()
        if path is None:
            # No laser-off frame recorded: a black frame makes the difference
            # image equal to the laser-on frame, as the capture spec allows.
            width, height = self.size
            return np.zeros((height, width), np.uint8)
        return read_frame(path, channel)

    def _frame_path(self) -> Path | None:
        """Return the recorded frame's file for the stage, view and laser state (None: absent)."""
        if self.stage.target == "grid":
            if self.capture_set.grid_image is None:
                raise CameraError("the capture holds no calibration grid image")
            return self.capture_set.grid_image
        z_mm, angle = self.lift.z_mm, self.turntable.angle_deg
        for view in self.capture_set.views(self.stage.target):
            if abs(view.spec.z_mm - z_mm) < 1e-6 and abs(view.spec.angle_deg - angle) < 1e-6:
                return view.laser_on if self.laser.is_on else view.laser_off
        raise CameraError(
            f"the capture has no {self.stage.target} view at z={z_mm} mm, angle={angle} deg"
        )

    @cached_property
    def has_colour(self) -> bool:
        """Return True when the capture's laser-off frames are colour PNGs."""
        for target in ("object", "cylinder"):
            for view in self.capture_set.views(target):
                if view.laser_off is not None:
                    return read_colour(view.laser_off) is not None
        return False

    def capture_colour(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the recorded frame as :meth:`capture` does and the same file's sRGB."""
        path = self._frame_path()
        rgb = None if path is None else read_colour(path)
        if path is None or rgb is None:
            raise CameraError("this capture's frame is not a colour image: scan it without colour")
        return read_frame(path, self.capture_set.laser_channel), rgb

    def close(self) -> None:
        """Nothing to release."""


def open_replay(folder: Path) -> Hardware:
    """Return a device whose camera replays the capture in ``folder`` (validated first)."""
    capture = load_capture(folder)
    manifest_sha = hashlib.sha256((capture.root / MANIFEST).read_bytes()).hexdigest()
    laser = Laser(MOCK_LASER_PIN, pin_factory=MockFactory())
    mechanics = Mechanics.ideal()
    turntable, stage = SimTurntable(mechanics), Stage()
    # The lift goes wherever a valid capture may have recorded a view.
    lift = SimLift(mechanics, DeviceLimits().max_z_mm)
    camera = ReplayCamera(capture, stage, turntable, lift, laser)
    plans = {t: p for t in ("cylinder", "object") if (p := capture.plan(t)) is not None}
    hardware = Hardware(
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
        identity={"serial": "replay", "source": f"{folder.resolve().name} sha256={manifest_sha}"},
        timing=turntable.clock.config,
    )
    return watched(hardware)
