"""Stand-ins for the parts of the Pi that cannot run here, behind their real interfaces.

gpiozero runs for real under its own MockFactory. What a MockFactory cannot do by
itself is move: :class:`LiftCarriage` gives the lift's STEP pin a carriage that
counts steps by the DIR level and opens the normally-closed limit switch at its trip
point. picamera2 cannot be imported off the Pi: :func:`fake_picamera2` injects a
module with the same API subset (Picamera2, MappedArray, requests with metadata),
whose frames come from a real-time sensor timeline and show the laser stripe as
bright as the laser pin's recorded history says it was during each row's exposure.
"""

from __future__ import annotations

import itertools
import json
import sys
import time
import types
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pytest
from gpiozero import Device
from gpiozero.pins.mock import MockFactory, MockPin

from lamina_device.config import DeviceConfig, LiftConfig, load_config

BACKGROUND = 30
STRIPE = 200
CHROMA_UV = (90, 160)  # the fake sensor's U and V everywhere: a reddish, slightly green-poor hue


def small_config() -> DeviceConfig:
    """Return the packaged config scaled down so motion tests run in well under a second."""
    config = load_config()
    turntable = replace(
        config.turntable,
        microsteps=2,
        gear_ratio=1.0,
        start_speed_deg_s=90.0,
        max_speed_deg_s=900.0,
        accel_deg_s2=20_000.0,
        backlash_deg=4.5,
        settle_s=0.0,
    )
    lift = replace(
        config.lift,
        microsteps=1,
        lead_mm=2.0,  # 100 steps per mm
        start_speed_mm_s=5.0,
        max_speed_mm_s=20.0,
        accel_mm_s2=400.0,
        min_mm=0.0,
        max_mm=20.0,
        home_mm=-1.0,
        homing_speed_mm_s=10.0,
        homing_slow_zone_mm=1.0,
        settle_s=0.0,
    )
    camera = replace(
        config.camera,
        width=320,
        height=240,
        exposure_us=5000,
        frame_duration_us=10000,
        gain=2.0,
        timeout_s=2.0,
    )
    plan = replace(config.plan, sections=2, views=4, cylinder_views=4)
    return replace(config, turntable=turntable, lift=lift, camera=camera, plan=plan)


def config_toml(config: DeviceConfig) -> str:
    """Return ``config`` as TOML text (for the command-line tests)."""
    lines = []
    for table, values in config.__dict__.items():
        if table == "device_id":  # the optional [device] table, not a table field
            if values is not None:
                lines.append(f'[device]\nid = "{values}"')
            continue
        if table == "lift_reference":  # the optional [lift_reference] table
            if values is not None:
                lines.append("[lift_reference]")
                lines += [f"{k} = {json.dumps(v)}" for k, v in values.to_dict().items()]
            continue
        lines.append(f"[{table}]")
        for key, value in values.__dict__.items():
            if value is None:  # TOML has no null: left out ([extract] threshold: Otsu's)
                continue
            if isinstance(value, bool):
                text = "true" if value else "false"
            elif isinstance(value, str):
                text = f'"{value}"'
            elif isinstance(value, tuple):
                text = "[" + ", ".join(map(str, value)) + "]"
            else:
                text = repr(value)
            lines.append(f"{key} = {text}")
    return "\n".join(lines) + "\n"


def rising_edges(pin: MockPin) -> int:
    """Return how many low-to-high changes a mock pin went through."""
    states = [s.state for s in pin.states]
    return sum(1 for a, b in itertools.pairwise(states) if b and not a)


def change_times_s(pin: MockPin) -> np.ndarray:
    """Return the absolute monotonic time of every recorded state of ``pin``."""
    deltas = np.array([s.timestamp for s in pin.states])
    # Each entry holds the time since the previous change; the last change is _last_change.
    return pin._last_change - (deltas.sum() - np.cumsum(deltas))


class LiftCarriage:
    """The lift's nut on its screw: STEP edges move it, the switch opens at the trip point."""

    def __init__(self, factory: MockFactory, config: LiftConfig, start_steps: int) -> None:
        self.position_steps = start_steps  # relative to the switch's trip point
        self.connected = True
        self.config = config
        self.dir_pin = factory.pin(config.dir_pin)
        self.switch_pin = factory.pin(config.limit_pin, pin_class=_SwitchPin, carriage=self)
        self.step_pin = factory.pin(config.step_pin, pin_class=_StepPin, carriage=self)

    def switch_open(self) -> bool:
        """Return True when the normally-closed switch is open (pressed, or wire broken)."""
        return not self.connected or self.position_steps <= 0

    def stepped(self) -> None:
        """Move one step the way the DIR pin says."""
        up = self.dir_pin.state == self.config.dir_high_positive
        self.position_steps += 1 if up else -1
        self.switch_pin.follow()


class _StepPin(MockPin):
    def __init__(self, factory: MockFactory, info: Any, carriage: LiftCarriage) -> None:
        super().__init__(factory, info)
        self.carriage = carriage

    def _change_state(self, value: bool) -> bool:
        changed = super()._change_state(value)
        if changed and value:
            self.carriage.stepped()
        return changed


class _SwitchPin(MockPin):
    def __init__(self, factory: MockFactory, info: Any, carriage: LiftCarriage) -> None:
        self.carriage = carriage
        super().__init__(factory, info)

    def _set_pull(self, value: str) -> None:
        super()._set_pull(value)
        self.follow()

    def follow(self) -> None:
        """Read high (pulled up) when the switch is open, low when it connects to ground."""
        if self._function != "input":
            return
        if self.carriage.switch_open():
            self.drive_high()
        else:
            self.drive_low()


@dataclass
class _Frame:
    index: int
    end_first_row_ns: int
    exposure_us: int
    gain: float
    lit_min: float = 0.0
    lit_max: float = 0.0
    released: bool = False


@dataclass
class FakeCameraWorld:
    """What the fake camera sees: the laser pin, and a log of every frame it handed out."""

    laser_pin: Callable[[], MockPin] | None = None
    laser_active_high: bool = True
    max_gain: float = 16.0
    control_latency_frames: int = 3
    stall_when_lit: bool = False  # no frame comes once the laser is on (a loose cable)
    cameras: list[Any] = field(default_factory=list)

    def lit_fraction(self, start_ns: np.ndarray, end_ns: np.ndarray) -> np.ndarray:
        """Return the fraction of each [start, end] interval the laser was on."""
        if self.laser_pin is None:
            return np.zeros_like(start_ns, dtype=float)
        pin = self.laser_pin()
        times_ns = (change_times_s(pin) * 1e9).astype(np.int64)
        on = np.array([s.state == self.laser_active_high for s in pin.states])
        # Laser-on time up to t: integrate the piecewise-constant level.
        durations = np.diff(np.append(times_ns, np.iinfo(np.int64).max // 2))
        cumulative = np.concatenate([[0], np.cumsum(np.where(on, durations, 0))[:-1]])

        def on_time_until(t: np.ndarray) -> np.ndarray:
            i = np.searchsorted(times_ns, t, side="right") - 1
            i = np.clip(i, 0, len(times_ns) - 1)
            before = t < times_ns[0]
            value = cumulative[i] + np.where(on[i], t - times_ns[i], 0)
            return np.where(before, 0, value)

        span = np.maximum(end_ns - start_ns, 1)
        return (on_time_until(end_ns) - on_time_until(start_ns)) / span


class FakeRequest:
    """A completed request: a YUV420 buffer and its metadata, to be released."""

    def __init__(self, camera: FakePicamera2, frame: _Frame, buffer: np.ndarray) -> None:
        self._camera, self.frame, self.buffer = camera, frame, buffer

    def get_metadata(self) -> dict[str, Any]:
        """Return the frame's metadata as libcamera reports it."""
        return {
            "SensorTimestamp": self.frame.end_first_row_ns,
            "ExposureTime": self.frame.exposure_us,
            "AnalogueGain": self.frame.gain,
            "FrameDuration": self._camera.frame_us,
        }

    def release(self) -> None:
        """Give the buffer back to the camera."""
        assert not self.frame.released, "request released twice"
        self.frame.released = True


class FakeJob:
    """What ``capture_request(wait=False)`` returns: the request, once it completes."""

    def __init__(self, camera: FakePicamera2) -> None:
        self._camera = camera

    def get_result(self, timeout: float | None = None) -> FakeRequest:
        """Return the request, or raise TimeoutError as a Future does when none comes."""
        world = self._camera.world
        lit = world.laser_pin is not None and world.laser_pin().state == world.laser_active_high
        if world.stall_when_lit and lit:
            time.sleep(timeout or 0.0)
            raise TimeoutError
        return self._camera.next_request()


class FakeMappedArray:
    """``with MappedArray(request, "main") as m: m.array`` over the request's buffer."""

    def __init__(self, request: FakeRequest, stream: str) -> None:
        assert stream == "main"
        assert not request.frame.released, "mapped a released request"
        self.array = request.buffer

    def __enter__(self) -> FakeMappedArray:
        return self

    def __exit__(self, *exc: object) -> None:
        return None


class FakePicamera2:
    """A sensor streaming frames on a real-time timeline with a rolling shutter."""

    world: FakeCameraWorld

    def __init__(self) -> None:
        self.world.cameras.append(self)
        self.frames: list[_Frame] = []
        self.control_log: list[dict[str, Any]] = []
        self.config: dict[str, Any] | None = None
        self.frame_us = 33_333
        self.exposure_us, self.gain = 20_000, 1.0  # auto values until controls apply
        self._pending: tuple[int, dict[str, Any]] | None = None
        self._start_ns = 0
        self._next = 0
        self.cancellations = 0
        self.started = self.closed = False

    def create_video_configuration(
        self, main: dict[str, Any], controls: dict[str, Any] | None = None, buffer_count: int = 6
    ) -> dict[str, Any]:
        return {"main": dict(main), "controls": dict(controls or {}), "buffer_count": buffer_count}

    def configure(self, config: dict[str, Any]) -> None:
        assert config["main"]["format"] == "YUV420"
        self.config = config
        limits = config["controls"].get("FrameDurationLimits")
        if limits:
            self.frame_us = limits[1]

    def set_controls(self, controls: dict[str, Any]) -> None:
        self.control_log.append(dict(controls))
        self._pending = (self._next + self.world.control_latency_frames, dict(controls))

    def start(self) -> None:
        self._start_ns = time.monotonic_ns()
        self.started = True

    def stop(self) -> None:
        self.started = False

    def close(self) -> None:
        self.closed = True

    def _end_ns(self, index: int) -> int:
        return self._start_ns + (index + 1) * self.frame_us * 1000

    def capture_request(self, wait: bool | None = None) -> FakeRequest | FakeJob:
        """Return the next completed request, or with ``wait=False`` a job that will."""
        job = FakeJob(self)
        return job if wait is False else job.get_result()

    def cancel_all_and_flush(self) -> None:
        self.cancellations += 1

    def next_request(self) -> FakeRequest:
        """Block until the next frame is read out and return it (one frame per call)."""
        assert self.started and self.config is not None
        buffers = self.config["buffer_count"]
        frame_ns = self.frame_us * 1000
        # Frames finish (all rows read) one frame period after their first row ends exposure.
        finished = (time.monotonic_ns() - self._start_ns) // frame_ns - 2
        index = max(self._next, finished - buffers + 1)  # older buffers were reused
        while time.monotonic_ns() < self._end_ns(index) + frame_ns:
            time.sleep(0.0005)
        self._next = index + 1
        if self._pending is not None and index >= self._pending[0]:
            controls = self._pending[1]
            self.exposure_us = controls["ExposureTime"]
            self.gain = min(controls["AnalogueGain"], self.world.max_gain)
            self._pending = None
        frame = _Frame(index, self._end_ns(index), self.exposure_us, self.gain)
        self.frames.append(frame)
        return FakeRequest(self, frame, self._render(frame))

    def _render(self, frame: _Frame) -> np.ndarray:
        width, height = self.config["main"]["size"] if self.config else (0, 0)
        stride = (width + 63) // 64 * 64 + 64  # padded rows, as real buffers have
        buffer = np.full((height * 3 // 2, stride), 77, np.uint8)
        buffer[:height, :width] = BACKGROUND
        for k, level in enumerate(CHROMA_UV):
            plane = buffer[height + k * height // 4 : height + (k + 1) * height // 4]
            chroma = plane.reshape(height // 2, stride // 2)  # a view: writes reach the buffer
            chroma[:, : width // 2] = level
            chroma[:, width // 2 :] = 0  # padding: never part of the image
        line_ns = self.frame_us * 1000 / height
        rows = np.arange(height)
        end = frame.end_first_row_ns + (rows * line_ns).astype(np.int64)
        lit = self.world.lit_fraction(end - frame.exposure_us * 1000, end)
        band = slice(height // 2 - 2, height // 2 + 3)
        frame.lit_min, frame.lit_max = float(lit[band].min()), float(lit[band].max())
        profile = np.array([0.3, 0.8, 1.0, 0.8, 0.3])
        level = BACKGROUND + np.round(STRIPE * profile * lit[band]).astype(np.uint8)
        buffer[band, :width] = level[:, None]
        return buffer


@pytest.fixture
def fake_picamera2(monkeypatch: pytest.MonkeyPatch) -> Iterator[FakeCameraWorld]:
    """Install a fake ``picamera2`` module for one test; yield the world it films."""
    world = FakeCameraWorld()
    module = types.ModuleType("picamera2")
    camera_class = type("Picamera2", (FakePicamera2,), {"world": world})
    module.Picamera2 = camera_class  # type: ignore[attr-defined]
    module.MappedArray = FakeMappedArray  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "picamera2", module)
    yield world


@pytest.fixture
def global_mock_factory(monkeypatch: pytest.MonkeyPatch) -> Iterator[MockFactory]:
    """Make gpiozero's default pin factory a fresh MockFactory (GPIOZERO_PIN_FACTORY=mock)."""
    factory = MockFactory()
    monkeypatch.setenv("GPIOZERO_PIN_FACTORY", "mock")
    monkeypatch.setattr(Device, "pin_factory", factory)
    yield factory
    factory.reset()


@pytest.fixture
def pi_kit() -> types.SimpleNamespace:
    """Return the helpers above for tests (conftest modules cannot be imported directly)."""
    return types.SimpleNamespace(
        config=small_config(),
        toml=config_toml,
        rising_edges=rising_edges,
        change_times_s=change_times_s,
        LiftCarriage=LiftCarriage,
        BACKGROUND=BACKGROUND,
        STRIPE=STRIPE,
        CHROMA_UV=CHROMA_UV,
    )
