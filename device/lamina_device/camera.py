"""Cameras: the interface every frame source answers, and the Raspberry Pi camera.

The acquisition only sees :class:`Camera`. The Pi camera (picamera2) captures the
luminance plane at fixed exposure and gain and returns only frames exposed entirely
under the laser's current state; for colour scans (:class:`ColourCamera`) it also
converts the frame's YUV420 chroma to sRGB. The simulated camera lives with the rest of the
virtual rig in ``lamina_device/sim/``, the replay of a recorded capture in
``lamina_device/replay.py``; whichever produced it, a frame goes through the same
extraction as a live one.
"""

from __future__ import annotations

import importlib
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, Protocol, runtime_checkable

import numpy as np

from lamina_device.config import CameraConfig
from lamina_device.laser import Laser
from lamina_shared.errors import LaminaError

log = logging.getLogger(__name__)

PICAMERA2_HELP = (
    "the Pi camera needs picamera2, which comes from Raspberry Pi OS, not PyPI: "
    "run 'sudo apt install python3-picamera2' and create the venv with "
    "'python3 -m venv --system-site-packages'"
)


class CameraError(LaminaError, RuntimeError):
    """A frame could not be produced."""


class ExposureRefused(CameraError):
    """An exposure the camera does not accept; the text names what it accepts."""


class Camera(Protocol):
    """Anything that returns one luminance frame per call."""

    @property
    def size(self) -> tuple[int, int]:
        """Return (width, height) in pixels."""
        ...  # pragma: no cover - protocol

    def capture(self) -> np.ndarray:
        """Expose and return one frame (H, W), uint8 or uint16."""
        ...  # pragma: no cover - protocol

    @property
    def exposure_us(self) -> int:
        """Return the exposure time now in use, in microseconds."""
        ...  # pragma: no cover - protocol

    @property
    def exposure_range_us(self) -> tuple[int, int]:
        """Return the (min, max) exposure time this camera accepts, in microseconds."""
        ...  # pragma: no cover - protocol

    def set_exposure(self, exposure_us: int) -> None:
        """Expose later frames for ``exposure_us``; ExposureRefused outside the range."""
        ...  # pragma: no cover - protocol

    def close(self) -> None:
        """Release the camera."""
        ...  # pragma: no cover - protocol


@runtime_checkable
class ColourCamera(Camera, Protocol):
    """A camera that can also return the sRGB colour of a frame (colour scans)."""

    @property
    def has_colour(self) -> bool:
        """Return True when :meth:`capture_colour` can give colour now."""
        ...  # pragma: no cover - protocol

    def capture_colour(self) -> tuple[np.ndarray, np.ndarray]:
        """Return one frame as :meth:`capture` would and its (H, W, 3) uint8 sRGB image."""
        ...  # pragma: no cover - protocol


@dataclass(frozen=True)
class FrameTiming:
    """How a streaming camera's frames follow each other (seconds).

    Attributes:
        period_s: from one frame's start to the next (the sensor streams without pause).
        exposure_s: each row's exposure.
        readout_s: from the first row's exposure to the last row's (the rolling shutter).
        rows: the frame's height in rows.
    """

    period_s: float
    exposure_s: float
    readout_s: float
    rows: int

    @property
    def row_s(self) -> float:
        """Return the delay from one row's exposure to the next one's."""
        return self.readout_s / max(1, self.rows)

    @property
    def span_s(self) -> float:
        """Return a frame's first row's exposure start to its last row's end."""
        return self.exposure_s + self.readout_s


@dataclass(frozen=True, eq=False)
class TimedFrame:
    """A frame and when its rows were exposed, from the sensor's own timestamp.

    Row ``r`` was exposed from ``start_ns + r * row_ns`` for ``exposure_ns`` (monotonic
    ns, the clock the step clock runs on).
    """

    image: np.ndarray
    start_ns: int
    exposure_ns: int
    row_ns: float

    def row_middle_ns(self, row: float) -> int:
        """Return the middle of ``row``'s exposure."""
        return self.start_ns + round(row * self.row_ns + 0.5 * self.exposure_ns)


@runtime_checkable
class TimedCamera(Camera, Protocol):
    """A streaming camera that tells when each frame was exposed (continuous scans)."""

    @property
    def frame_timing(self) -> FrameTiming:
        """Return the stream's frame period, exposure and rolling read-out."""
        ...  # pragma: no cover - protocol

    def capture_timed(self) -> TimedFrame:
        """Return the next frame exposed wholly after the laser's last switch, with its timing."""
        ...  # pragma: no cover - protocol


def camera_has_colour(camera: Camera) -> bool:
    """Return True when ``camera`` can sample colour (WELCOME ``colour``)."""
    return isinstance(camera, ColourCamera) and camera.has_colour


def check_exposure(exposure_us: int, range_us: tuple[int, int]) -> None:
    """Raise CameraError naming the allowed range unless ``exposure_us`` lies within it."""
    low, high = range_us
    if not low <= exposure_us <= high:
        raise ExposureRefused(
            f"exposure {exposure_us} us is outside this camera's {low}..{high} us"
        )


@dataclass
class Stage:
    """What currently stands on the turntable: ``grid``, ``cylinder`` or ``object``."""

    target: str = "object"
    placed_count_deg: float = 0.0
    """The turntable's step count (unwrapped degrees) when the target was put on: a
    simulated target's own frame starts at the whole turn nearest it."""


# The sensor timestamps a frame when its first row ends exposure; the last row ends up
# to one frame period later (rolling shutter). GPIO and driver latency is well below this.
LASER_LATENCY_NS = 100_000
# Exposure is quantised to sensor lines: accept the metadata within this fraction.
_EXPOSURE_TOLERANCE = 0.05
_GAIN_TOLERANCE = 0.05


def import_picamera2() -> Any:
    """Return the picamera2 module, or raise CameraError saying how to install it."""
    try:
        return importlib.import_module("picamera2")
    except ImportError as exc:
        raise CameraError(f"{PICAMERA2_HELP} ({exc})") from None


def exposure_window_ns(metadata: dict[str, Any]) -> tuple[int, int]:
    """Return when a frame's first row started and its last row could have ended exposing.

    ``SensorTimestamp`` (ns, CLOCK_MONOTONIC) marks the end of the first row's
    exposure; the rolling shutter reads the last row at most one frame later.
    """
    end_first_ns = int(metadata["SensorTimestamp"])
    exposure_ns = int(metadata["ExposureTime"]) * 1000
    frame_ns = int(metadata.get("FrameDuration", metadata["ExposureTime"])) * 1000
    return end_first_ns - exposure_ns, end_first_ns + frame_ns


class PiCamera:
    """A Raspberry Pi camera (picamera2) returning the Y plane at fixed exposure and gain.

    Every frame is matched to the laser state it was exposed under: frames whose
    exposure began before the laser's last switch (stale or straddling ones) are
    released and skipped, so the caller gets a frame lit exactly as the laser is now.
    """

    def __init__(self, config: CameraConfig, laser: Laser, picamera2: Any | None = None) -> None:
        self.config = config
        self.laser = laser
        module = picamera2 if picamera2 is not None else import_picamera2()
        self._mapped_array = module.MappedArray
        self.frames_dropped = 0
        self.exposure_us = config.exposure_us
        self._cam = module.Picamera2()
        try:
            self._start()
        except Exception:
            self._cam.close()
            raise

    @property
    def size(self) -> tuple[int, int]:
        """Return (width, height) in pixels."""
        return (self.config.width, self.config.height)

    @property
    def exposure_range_us(self) -> tuple[int, int]:
        """Return the configured [camera] min_exposure_us..max_exposure_us."""
        return (self.config.min_exposure_us, self.config.max_exposure_us)

    def set_exposure(self, exposure_us: int) -> None:
        """Set the exposure time and wait until frames report it (CameraError if they do not)."""
        check_exposure(exposure_us, self.exposure_range_us)
        previous, self.exposure_us = self.exposure_us, int(exposure_us)
        self._cam.set_controls({"ExposureTime": self.exposure_us})
        try:
            self._confirm_controls()
        except CameraError:
            self.exposure_us = previous
            self._cam.set_controls({"ExposureTime": previous})
            raise

    def _controls(self) -> dict[str, Any]:
        cfg = self.config
        return {
            "AeEnable": False,
            "AwbEnable": False,
            "ExposureTime": self.exposure_us,
            "AnalogueGain": cfg.gain,
            "FrameDurationLimits": (cfg.frame_duration_us, cfg.frame_duration_us),
        }

    def _start(self) -> None:
        cfg = self.config
        # YUV420's first plane is the luminance: no colour conversion, no extra copy.
        camera_config = self._cam.create_video_configuration(
            main={"format": "YUV420", "size": (cfg.width, cfg.height)},
            controls=self._controls(),
            buffer_count=cfg.buffer_count,
        )
        self._cam.configure(camera_config)
        self._cam.set_controls(self._controls())
        self._cam.start()
        self._confirm_controls()

    def _controls_applied(self, metadata: dict[str, Any]) -> bool:
        cfg = self.config
        exposure = metadata.get("ExposureTime", 0)
        gain = metadata.get("AnalogueGain", 0.0)
        return (
            abs(exposure - self.exposure_us) <= _EXPOSURE_TOLERANCE * self.exposure_us
            and abs(gain - cfg.gain) <= _GAIN_TOLERANCE * cfg.gain
        )

    def _confirm_controls(self) -> None:
        """Wait until frames report the requested exposure and gain (they lag a few frames)."""
        deadline = time.monotonic() + self.config.timeout_s
        metadata: dict[str, Any] = {}
        while time.monotonic() < deadline:
            request = self._next_request(deadline)
            try:
                metadata = request.get_metadata()
            finally:
                request.release()
            if self._controls_applied(metadata):
                return
        raise CameraError(
            f"the camera did not apply exposure {self.exposure_us} us and gain "
            f"{self.config.gain:g} within {self.config.timeout_s:g} s (it reports "
            f"{metadata.get('ExposureTime')} us, gain {metadata.get('AnalogueGain')}); "
            "check [camera] exposure_us, gain and frame_duration_us against the sensor's limits"
        )

    def _next_request(self, deadline: float) -> Any:
        """Return the camera's next completed request; CameraError if none comes by ``deadline``."""
        job = self._cam.capture_request(wait=False)
        try:
            return job.get_result(timeout=max(deadline - time.monotonic(), 0.0))
        except TimeoutError:
            # A stalled sensor (a loose ribbon cable) must not hang the scan; cancelling
            # the pending job leaves the camera usable once it recovers.
            self._cam.cancel_all_and_flush()
            raise CameraError(
                f"the camera delivered no frame within {self.config.timeout_s:g} s "
                "([camera] timeout_s): check its ribbon cable and that no other program "
                "is using it"
            ) from None

    def _luminance(self, request: Any) -> np.ndarray:
        width, height = self.size
        with self._mapped_array(request, "main") as mapped:
            return np.array(mapped.array[:height, :width], dtype=np.uint8, copy=True)

    def _yuv420(self, request: Any) -> np.ndarray:
        """Return a frame's planes packed as a stride-free I420 buffer (H * 3/2, W).

        The mapped buffer is (H * 3/2, stride): H rows of Y, then U and V, each H/2 rows
        of stride/2 bytes laid two to a buffer row. Padding beyond the width is dropped.
        """
        width, height = self.size
        with self._mapped_array(request, "main") as mapped:
            buffer = mapped.array
            stride = buffer.shape[1]
            y = np.array(buffer[:height, :width], dtype=np.uint8, copy=True)
            quarter = height // 4
            chroma = [
                buffer[height + k * quarter : height + (k + 1) * quarter]
                .reshape(height // 2, stride // 2)[:, : width // 2]
                .copy()
                for k in (0, 1)
            ]
        return np.concatenate([y.ravel(), chroma[0].ravel(), chroma[1].ravel()]).reshape(
            height * 3 // 2, width
        )

    @property
    def has_colour(self) -> bool:
        """Return True: the YUV420 stream carries the chroma planes."""
        return True

    def capture_colour(self) -> tuple[np.ndarray, np.ndarray]:
        """Return the Y plane of the next frame and its sRGB image (from the same buffer).

        The chroma planes travel with every frame, so colour costs a conversion (OpenCV's
        BT.601 ``COLOR_YUV2RGB_I420``), not another exposure; the Y plane returned is the
        one :meth:`capture` would return, so the stripe is found exactly as without colour.
        """
        import cv2  # the device installs opencv; only colour scans need it here

        i420 = self._read(self._yuv420)[0]
        height = self.size[1]
        return np.ascontiguousarray(i420[:height]), cv2.cvtColor(i420, cv2.COLOR_YUV2RGB_I420)

    def capture(self) -> np.ndarray:
        """Return the next frame exposed entirely under the laser's current state."""
        return self._read(self._luminance)[0]

    @property
    def frame_timing(self) -> FrameTiming:
        """Return the configured frame period and read-out with the exposure now in use."""
        cfg = self.config
        period_s = max(cfg.frame_duration_us, self.exposure_us) * 1e-6
        return FrameTiming(period_s, self.exposure_us * 1e-6, cfg.readout_s, cfg.height)

    def capture_timed(self) -> TimedFrame:
        """Return the next frame exposed under the laser's current state, with its timing.

        ``SensorTimestamp`` marks the end of the first row's exposure (field notes), so
        the first row started one exposure (as the frame reports it) before it.
        """
        frame, metadata = self._read(self._luminance)
        start_ns, _ = exposure_window_ns(metadata)
        exposure_ns = int(metadata["ExposureTime"]) * 1000
        return TimedFrame(frame, start_ns, exposure_ns, self.frame_timing.row_s * 1e9)

    def _read(self, read: Callable[[Any], np.ndarray]) -> tuple[np.ndarray, dict[str, Any]]:
        """Return ``read(request)`` of the next frame exposed under the laser's current state,
        and the frame's metadata."""
        state, changed_ns = self.laser.is_on, self.laser.changed_ns
        deadline = time.monotonic() + self.config.timeout_s
        while time.monotonic() < deadline:
            request = self._next_request(deadline)
            try:
                metadata = request.get_metadata()
                start_ns, _ = exposure_window_ns(metadata)
                fresh = start_ns >= changed_ns + LASER_LATENCY_NS
                frame: np.ndarray | None = read(request) if fresh else None
            finally:
                request.release()
            # The frame was read out before capture_request returned, so if the laser has
            # not switched since, every row of it was exposed under ``state``.
            if self.laser.changed_ns != changed_ns or self.laser.is_on != state:
                raise CameraError("the laser switched while a frame was exposed")
            if frame is not None:
                return frame, metadata
            self.frames_dropped += 1
            log.debug("dropped a frame whose exposure began before the laser switched")
        raise CameraError(
            f"no frame exposed after the laser switched arrived within {self.config.timeout_s:g} s"
        )

    def close(self) -> None:
        """Stop and release the camera."""
        try:
            self._cam.stop()
        finally:
            self._cam.close()
