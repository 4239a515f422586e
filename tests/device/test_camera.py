"""The picamera2 backend against a fake picamera2 module with a real-time sensor timeline."""

from __future__ import annotations

import sys
import time
from dataclasses import replace

import numpy as np
import pytest
from gpiozero.pins.mock import MockFactory

from lamina_device.acquisition import capture_pair
from lamina_device.backends import open_hardware
from lamina_device.camera import CameraError, PiCamera, exposure_window_ns
from lamina_device.hardware import HardwareError
from lamina_device.laser import Laser


@pytest.fixture
def pi_camera(pi_kit, fake_picamera2):
    factory = MockFactory()
    laser = Laser(17, pin_factory=factory)
    fake_picamera2.laser_pin = lambda: factory.pin(17)
    camera = PiCamera(pi_kit.config.camera, laser)
    yield camera, laser, fake_picamera2.cameras[0]
    camera.close()
    laser.close()


def band(frame: np.ndarray) -> np.ndarray:
    h = frame.shape[0]
    return frame[h // 2 - 2 : h // 2 + 3]


def test_camera_runs_at_fixed_exposure_and_gain_confirmed_from_metadata(pi_camera, pi_kit):
    _, _, fake = pi_camera
    cfg = pi_kit.config.camera
    assert fake.config["main"] == {"format": "YUV420", "size": (cfg.width, cfg.height)}
    assert fake.control_log[-1] == {
        "AeEnable": False,
        "AwbEnable": False,
        "ExposureTime": 5000,
        "AnalogueGain": 2.0,
        "FrameDurationLimits": (10000, 10000),
    }
    # Controls lag three frames: start-up waited for the first frame that reports them.
    assert [f.exposure_us for f in fake.frames] == [20000, 20000, 20000, 5000]
    assert all(f.released for f in fake.frames)


def test_frames_match_the_laser_state_and_straddling_frames_are_dropped(pi_camera, pi_kit):
    camera, laser, fake = pi_camera
    hardware = type("Rig", (), {"laser": laser, "camera": camera})()
    profile = np.round(pi_kit.STRIPE * np.array([0.3, 0.8, 1.0, 0.8, 0.3])).astype(int)
    straddled = pairs = 0
    # A frame straddles the switch-on only if it is read out before its buffer is reused:
    # a busy machine may pause this thread for longer than the buffers last, so a pair
    # may see none. Each pair must be clean; one of a few must have dropped a straddler.
    while not straddled and pairs < 5:
        pairs += 1
        before, dropped = len(fake.frames), camera.frames_dropped
        on, off = capture_pair(hardware)
        assert on.shape == off.shape == (240, 320) and on.dtype == np.uint8
        # Off frame: no stripe at all; on frame: every stripe row fully lit.
        assert np.all(off == pi_kit.BACKGROUND)
        np.testing.assert_array_equal(band(on)[:, 0], pi_kit.BACKGROUND + profile)
        handed_out = fake.frames[before:]
        straddling = [f for f in handed_out if f.lit_max > 0.0 and f.lit_min < 1.0]
        assert camera.frames_dropped - dropped >= len(straddling)
        straddled += len(straddling)
    assert straddled, "the fake sensor must have exposed a frame across the switch-on"
    assert all(f.released for f in fake.frames)
    assert laser.mock_pin_history() == [False] + [True, False] * pairs


@pytest.mark.wall_clock
def test_a_stalled_camera_ends_the_capture_in_time_with_the_laser_off(pi_kit, fake_picamera2):
    factory = MockFactory()
    laser = Laser(17, pin_factory=factory)
    fake_picamera2.laser_pin = lambda: factory.pin(17)
    camera = PiCamera(replace(pi_kit.config.camera, timeout_s=0.3), laser)
    hardware = type("Rig", (), {"laser": laser, "camera": camera})()
    fake_picamera2.stall_when_lit = True
    started = time.monotonic()
    try:
        with pytest.raises(CameraError, match=r"no frame within 0.3 s .*ribbon cable"):
            capture_pair(hardware)
        assert time.monotonic() - started < 1.5  # bounded by timeout_s, not hung
        assert fake_picamera2.cameras[0].cancellations == 1
        assert laser.mock_pin_history() == [False, True, False]
        fake_picamera2.stall_when_lit = False  # the cable is reseated: frames come again
        assert camera.capture().shape == (240, 320)
    finally:
        camera.close()
        laser.close()


def test_frame_window_uses_the_end_of_the_first_rows_exposure():
    start, end = exposure_window_ns(
        {"SensorTimestamp": 1_000_000_000, "ExposureTime": 5000, "FrameDuration": 10000}
    )
    assert (start, end) == (995_000_000, 1_010_000_000)


def test_resolution_is_configurable(pi_kit, fake_picamera2):
    factory = MockFactory()
    laser = Laser(17, pin_factory=factory)
    fake_picamera2.laser_pin = lambda: factory.pin(17)
    camera = PiCamera(replace(pi_kit.config.camera, width=640, height=480), laser)
    try:
        frame = camera.capture()
        assert camera.size == (640, 480) and frame.shape == (480, 640)
        # Only the Y plane within the row stride comes back, not the padding or chroma.
        assert np.all(frame == pi_kit.BACKGROUND)
    finally:
        camera.close()
        laser.close()


def test_controls_that_never_apply_are_reported(pi_kit, fake_picamera2):
    fake_picamera2.max_gain = 8.0  # the sensor clamps the gain
    laser = Laser(17, pin_factory=MockFactory())
    cfg = replace(pi_kit.config.camera, gain=12.0, timeout_s=0.2)
    with pytest.raises(CameraError, match=r"did not apply exposure 5000 us and gain 12.*gain 8"):
        PiCamera(cfg, laser)
    assert fake_picamera2.cameras[0].closed
    assert all(f.released for f in fake_picamera2.cameras[0].frames)


def test_missing_picamera2_names_how_to_install_it(monkeypatch, pi_kit):
    monkeypatch.setitem(sys.modules, "picamera2", None)  # import picamera2 raises ImportError
    with pytest.raises(CameraError, match=r"python3-picamera2.*--system-site-packages"):
        PiCamera(pi_kit.config.camera, Laser(17, pin_factory=MockFactory()))
    factory = MockFactory()
    with pytest.raises(HardwareError, match="python3-picamera2"):
        open_hardware("pi", pin_factory=factory)
    # Nothing stays claimed and the laser pin was left low (off).
    assert factory.pin(17).state is False


def test_colour_frames_come_from_the_same_yuv420_buffer(pi_camera, pi_kit):
    camera, _, fake = pi_camera
    assert camera.has_colour
    luma, rgb = camera.capture_colour()
    assert luma.shape == (240, 320) and rgb.shape == (240, 320, 3) and rgb.dtype == np.uint8
    assert np.all(luma == pi_kit.BACKGROUND)  # the Y plane capture() returns
    # BT.601 (video range, as OpenCV converts I420) of Y = 30, U = 90, V = 160.
    y, u, v = pi_kit.BACKGROUND - 16.0, pi_kit.CHROMA_UV[0] - 128.0, pi_kit.CHROMA_UV[1] - 128.0
    expected = np.array(
        [1.164 * y + 1.596 * v, 1.164 * y - 0.391 * u - 0.813 * v, 1.164 * y + 2.018 * u]
    )
    expected = np.clip(expected, 0, 255)
    # Every pixel alike: the row padding (zeros) never leaks into the chroma.
    assert np.all(np.abs(rgb.reshape(-1, 3) - expected) <= 2.0)
    assert all(f.released for f in fake.frames)
