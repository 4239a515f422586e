"""The acquisition pipeline: order, overlap, errors, pause, resume, abort, laser and lift."""

from __future__ import annotations

import threading
import time
from dataclasses import replace

import numpy as np
import pytest
from gpiozero.pins.mock import MockFactory

from lamina_device.acquisition import ScanAborted, ScanControl, acquire
from lamina_device.backends import open_hardware
from lamina_device.camera import CameraError
from lamina_device.cli import main
from lamina_shared.capture import load_capture
from lamina_shared.messages import Progress
from lamina_shared.types import ScanPlan

PLAN = ScanPlan.regular(sections=2, pitch_mm=2.0, views=4)


class TimedCamera:
    """Wraps a camera, recording when each capture started and with what laser state."""

    def __init__(self, camera, laser, fail_at: int | None = None) -> None:
        self.camera, self.laser, self.fail_at = camera, laser, fail_at
        self.log: list[tuple[float, bool]] = []
        self.spans: list[tuple[float, float]] = []

    @property
    def size(self):
        return self.camera.size

    def capture(self) -> np.ndarray:
        self.log.append((time.monotonic(), self.laser.is_on))
        if self.fail_at is not None and len(self.log) == self.fail_at:
            raise CameraError("camera stopped answering")
        frame = self.camera.capture()
        self.spans.append((self.log[-1][0], time.monotonic()))
        return frame

    def close(self) -> None:
        self.camera.close()


@pytest.fixture
def sim():
    hardware = open_hardware("sim", "cylinder:d=19.05", noise="none")
    hardware.camera = TimedCamera(hardware.camera, hardware.laser)
    yield hardware
    hardware.close()


def laser_levels(hardware) -> list[bool]:
    return hardware.laser.mock_pin_history()


def test_segments_arrive_in_plan_order_with_progress_and_the_lift_home(sim):
    segments, progress = [], []
    count = acquire(sim, "object", PLAN, segments.append, progress.append)
    assert count == len(segments) == 8
    assert [(s.section, s.view, s.z_mm, s.angle_deg) for s in segments] == [
        (v.section, i % 4, v.z_mm, v.angle_deg) for i, v in enumerate(PLAN.views)
    ]
    assert all(len(s.cols) > 100 for s in segments)
    assert [p.done for p in progress] == list(range(1, 9))
    assert progress[-1].state == "done" and progress[-1].left_s == 0.0
    assert all(
        p.state == "scanning" and (p.left_s is not None and p.left_s >= 0) for p in progress[:-1]
    )
    # One off frame then one on frame per view; the laser on only for the on frame.
    assert [on for _, on in sim.camera.log] == [False, True] * 8
    assert laser_levels(sim) == [False] + [True, False] * 8
    assert sim.lift.z_mm == 0.0


def test_extraction_and_sending_overlap_the_next_move_and_capture(sim):
    sending: list[tuple[float, float]] = []

    def slow_send(segment) -> None:
        start = time.monotonic()
        time.sleep(0.15)  # a slow serial line
        sending.append((start, time.monotonic()))

    acquire(sim, "object", PLAN, slow_send)
    # However slow rendering is on a busy machine, captures and sends must overlap in time.
    overlapped = sum(any(c0 < b and a < c1 for c0, c1 in sim.camera.spans) for a, b in sending)
    assert overlapped >= 3, "captures should go on while earlier segments are being sent"


def test_an_error_while_sending_ends_the_scan_with_the_laser_off(sim):
    sent = []

    def failing(segment) -> None:
        if len(sent) == 2:
            raise OSError("link closed while sending")
        sent.append(segment)

    with pytest.raises(OSError, match="link closed"):
        acquire(sim, "object", PLAN, failing)
    assert len(sent) == 2
    assert laser_levels(sim)[-1] is False and not sim.laser.is_on
    assert sim.lift.z_mm == 0.0
    # The queue is short: capture stopped soon after the failure instead of finishing the plan.
    assert len(sim.camera.log) < 16


def test_a_camera_error_still_delivers_the_views_already_captured(sim):
    sim.camera.fail_at = 8  # the laser-on frame of the fourth view
    segments = []
    with pytest.raises(CameraError):
        acquire(sim, "object", PLAN, segments.append)
    assert len(segments) == 3
    assert laser_levels(sim) == [False] + [True, False] * 4
    assert sim.lift.z_mm == 0.0


def test_pause_holds_the_scan_between_views_and_resume_continues(sim):
    control = ScanControl()
    paused_at: list[float] = []
    resumed_at: list[float] = []

    def on_progress(progress: Progress) -> None:
        if progress.done == 2:
            control.pause()
            paused_at.append(time.monotonic())

            def resume() -> None:
                time.sleep(0.5)
                resumed_at.append(time.monotonic())
                control.resume()

            threading.Thread(target=resume, daemon=True).start()

    segments = []
    acquire(sim, "object", PLAN, segments.append, on_progress, control=control)
    assert len(segments) == 8
    captures = [t for t, _ in sim.camera.log]
    # Only the pair of the view under way when the pause came can follow it before resume.
    held = [t for t in captures if paused_at[0] < t < resumed_at[0]]
    assert len(held) <= 2
    assert len([t for t in captures if t > resumed_at[0]]) >= 2
    assert not control.paused and not sim.laser.is_on


def test_abort_raises_after_the_laser_is_off_and_the_lift_is_home(sim):
    control = ScanControl()
    segments = []

    def on_progress(progress: Progress) -> None:
        if progress.done == 3:
            control.abort()

    with pytest.raises(ScanAborted, match="aborted after"):
        acquire(sim, "object", PLAN, segments.append, on_progress, control=control)
    assert 3 <= len(segments) < 8
    assert not sim.laser.is_on and sim.lift.z_mm == 0.0
    assert [s.view for s in segments] == [i % 4 for i in range(len(segments))]


def test_abort_ends_a_pause(sim):
    control = ScanControl()
    control.pause()
    threading.Timer(0.2, control.abort).start()
    with pytest.raises(ScanAborted, match="after 0 of 8 views"):
        acquire(sim, "object", PLAN, lambda s: None, control=control)
    assert sim.camera.log == []


def pi_hardware(pi_kit, fake_picamera2, factory):
    carriage = pi_kit.LiftCarriage(factory, pi_kit.config.lift, start_steps=180)
    fake_picamera2.laser_pin = lambda: factory.pin(pi_kit.config.laser.pin)
    return carriage


def test_a_scan_on_the_pi_backends(pi_kit, fake_picamera2, tmp_path):
    factory = MockFactory()
    carriage = pi_hardware(pi_kit, fake_picamera2, factory)
    path = tmp_path / "box.toml"
    path.write_text(pi_kit.toml(pi_kit.config))
    hardware = open_hardware("pi", config_path=path, pin_factory=factory)
    try:
        assert hardware.kind == "pi" and hardware.camera.size == (320, 240)
        assert hardware.default_plans["object"] == PLAN
        segments = []
        acquire(hardware, "object", PLAN, segments.append)
        # The fake stripe is centred on row 120 in every column of every view.
        assert [len(s.cols) for s in segments] == [320] * 8
        assert all(np.allclose(s.rows, 120.0, atol=1e-3) for s in segments)
        assert [s.z_mm for s in segments] == [v.z_mm for v in PLAN.views]
        # Homed before the first move and again at the end: the carriage is on its switch.
        assert carriage.position_steps == 0 and hardware.lift.homed
        assert hardware.turntable.angle_deg == 270.0
        assert pi_kit.rising_edges(factory.pin(pi_kit.config.laser.pin)) == 8
        assert hardware.watchdog is not None and hardware.watchdog.running
    finally:
        hardware.close()
    assert factory.pin(pi_kit.config.laser.pin).state is False


@pytest.mark.parametrize(("sections", "heights_mm"), [(3, [0.0, 3.0, 6.0]), (1, [0.0])])
def test_the_box_scans_the_cylinder_at_the_configured_heights(
    pi_kit, fake_picamera2, tmp_path, sections, heights_mm
):
    """The packaged configuration scans the cylinder at three heights 3 mm apart (a steadier
    turntable axis); a box's file from before the key keeps its one height."""
    factory = MockFactory()
    pi_hardware(pi_kit, fake_picamera2, factory)
    plan = replace(pi_kit.config.plan, cylinder_sections=sections)
    path = tmp_path / "box.toml"
    text = pi_kit.toml(replace(pi_kit.config, plan=plan))
    if sections == 1:  # an older file: the keys are absent
        text = "\n".join(
            line
            for line in text.splitlines()
            if "cylinder_s" not in line and "cylinder_p" not in line
        )
    path.write_text(text)
    hardware = open_hardware("pi", config_path=path, pin_factory=factory)
    try:
        views = hardware.default_plans["cylinder"].views
        assert sorted({view.z_mm for view in views}) == heights_mm
        assert len(views) == 4 * len(heights_mm)
    finally:
        hardware.close()


def test_record_on_pi_hardware(pi_kit, fake_picamera2, global_mock_factory, tmp_path):
    carriage = pi_hardware(pi_kit, fake_picamera2, global_mock_factory)
    config = tmp_path / "box.toml"
    config.write_text(pi_kit.toml(pi_kit.config))
    out = tmp_path / "capture"
    status = main(
        ["record", "--hardware", "pi", "--config", str(config), "--out", str(out),
         "--sections", "2", "--views", "4", "--cylinder-views", "4"]
    )  # fmt: skip
    assert status == 0
    capture = load_capture(out)
    assert capture.image_size == (320, 240)
    assert len(capture.views("object")) == 8
    cylinder = capture.views("cylinder")  # 4 views at each of the default 3 heights
    assert sorted({(view.spec.section, view.spec.z_mm) for view in cylinder}) == [
        (0, 0.0), (1, 3.0), (2, 6.0)
    ]  # fmt: skip
    assert len(cylinder) == 12
    assert capture.grid_image is not None
    assert carriage.position_steps == 0
    assert global_mock_factory.pin(pi_kit.config.laser.pin).state is False
