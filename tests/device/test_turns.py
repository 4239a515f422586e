"""Each segment's whole turns (issue 22): the step count since power-up, as the device sends it.

A table that turns short of its count falls further behind with every turn, so the host
corrects each view at its count, ``angle_deg + 360 * turns``; these tests hold the device
to sending the count the table really reached, in both modes.
"""

from __future__ import annotations

import numpy as np
import pytest

from lamina_device.acquisition import acquire, whole_turns
from lamina_shared.types import ScanPlan, Segment, from_first_turn
from tests.device.test_continuous import tiny_sim


def scan(hardware, plan: ScanPlan, resumed: bool = False) -> list[Segment]:
    """Return the segments of ``plan`` in the order the device sent them."""
    got: list[Segment] = []
    acquire(hardware, "object", plan, got.append, resumed=resumed)
    return got


def test_a_stop_and_go_scan_counts_a_turn_a_section_and_runs_on_into_the_next_scan():
    """The table turns on the short way from the last view of a section (270) to the first
    of the next (0): one turn a section. A second scan starts where the first left the
    count, so its turns run on; counted from each scan's first they are the same."""
    plan = ScanPlan.regular(3, 2.0, 4)
    hardware = tiny_sim()
    try:
        first = scan(hardware, plan)
        count_after = hardware.turntable.count_deg
        second = scan(hardware, plan)
    finally:
        hardware.close()
    assert [s.turns for s in first] == [0] * 4 + [1] * 4 + [2] * 4
    assert [s.angle_deg for s in first] == [v.angle_deg for v in plan.views]
    assert count_after == pytest.approx(2 * 360.0 + 270.0, abs=0.01)
    assert [s.turns for s in second] == [3] * 4 + [4] * 4 + [5] * 4
    assert [s.turns for s in from_first_turn(second)] == [s.turns for s in first]


def test_a_continuous_scan_sends_the_count_its_stripe_was_exposed_at():
    """The table never stops: the counts of the views, in the order they were taken, only
    grow; each section's lie within about a turn, past the last section's; each view's
    angle is its count's within the turn."""
    plan = ScanPlan.regular(3, 2.0, 4, "continuous")
    hardware = tiny_sim()
    try:
        got = scan(hardware, plan)
        end_deg = hardware.turntable.count_deg
    finally:
        hardware.close()
    counts = [s.count_deg for s in got]
    assert counts == sorted(set(counts)), counts  # strictly growing
    assert counts[-1] <= end_deg
    for s in got:
        assert 0.0 <= s.angle_deg < 360.0 and s.turns == s.count_deg // 360.0
    by_section = {k: [s.count_deg for s in got if s.section == k] for k in range(3)}
    for k in range(3):
        assert max(by_section[k]) - min(by_section[k]) < 360.0
        if k:
            assert min(by_section[k]) > max(by_section[k - 1])
    assert max(s.turns for s in got) >= 2  # three sections, a turn or more each


@pytest.mark.parametrize(
    ("count_deg", "angle_deg", "turns"),
    [(0.0, 0.0, 0), (720.0, 0.0, 2), (359.999, 0.0, 1), (-90.0, 270.0, -1), (405.0, 45.0, 1)],
)
def test_whole_turns_take_the_views_angle_to_its_count(count_deg, angle_deg, turns):
    """A stop-and-go count sits on its commanded angle to within a microstep, either side."""
    assert whole_turns(count_deg, angle_deg) == turns


# --- a count that starts again ----------------------------------------------------------


def _box_identity(pi_kit, fake_picamera2, tmp_path) -> dict:
    """Return the scan identity a host makes of a freshly started box's WELCOME."""
    from gpiozero.pins.mock import MockFactory

    from lamina_device.backends import open_hardware
    from lamina_host.link.identity import scan_identity
    from lamina_shared.messages import DeviceIdentity, Welcome
    from lamina_shared.protocol import PROTOCOL_VERSION
    from tests.device.test_acquisition import pi_hardware

    factory = MockFactory()
    pi_hardware(pi_kit, fake_picamera2, factory)
    path = tmp_path / "box.toml"
    path.write_text(pi_kit.toml(pi_kit.config))
    hardware = open_hardware("pi", config_path=path, pin_factory=factory)
    try:
        welcome = Welcome(
            PROTOCOL_VERSION,
            image_size=hardware.camera.size,
            identity=DeviceIdentity(**hardware.identity),
        )
    finally:
        hardware.close()
    # Through the wire form, as the host receives it.
    return scan_identity(Welcome.from_wire(welcome.to_wire()))


def _view(plan: ScanPlan, seq: int) -> Segment:
    """Return a small segment labelled as view ``seq`` of ``plan``."""
    view = plan.views[seq]
    cols = np.arange(10, dtype=np.uint16)
    rows, ones = np.full(10, 20.0, np.float32), np.ones(10, np.uint8)
    return Segment("object", view.section, seq, view.z_mm, view.angle_deg, cols, rows, ones, ones)


def test_a_scan_begun_before_the_box_restarted_is_not_continued_and_keeps_its_views(
    pi_kit, fake_picamera2, tmp_path
):
    """The box's table has no index: its count starts at 0 wherever the table stands each
    time the program starts, so views counted before and after cannot be joined. The
    WELCOME says which run of the count it is; a resume on another run is refused in one
    line, the views held stay, and a resume on the same run is accepted."""
    from lamina_host.store.library import Library, StoreError

    first = _box_identity(pi_kit, fake_picamera2, tmp_path)
    again = _box_identity(pi_kit, fake_picamera2, tmp_path)
    assert len(first["count_since"]) == 16 and first["count_since"] != again["count_since"]
    assert {k: v for k, v in first.items() if k != "count_since"} == {
        k: v for k, v in again.items() if k != "count_since"
    }
    plan = ScanPlan.regular(1, 1.0, 2)
    with Library(tmp_path / "lib.sqlite") as library:
        scan_id = library.create_scan("P-1", {"object": plan}, identity=first)
        assert library.add_segment(scan_id, 0, _view(plan, 0), first)
        library.check_identity(scan_id, dict(first))  # the same run: a dropped link resumed
        with pytest.raises(StoreError) as caught:
            library.check_identity(scan_id, again)
        line = str(caught.value)
        assert "\n" not in line and "begun before the device's program last started" in line
        assert "start a new scan" in line
        with pytest.raises(StoreError, match="begun before"):
            library.add_segment(scan_id, 1, _view(plan, 1), again)
        assert list(library.held_segments(scan_id, "object")) == [0]
        # Another device altogether is named as such, whatever its count.
        with pytest.raises(StoreError, match="another device or setup"):
            library.check_identity(scan_id, {**again, "serial": "another box"})
        # A scan recorded before the WELCOME said it is compared without it.
        older = {k: v for k, v in first.items() if k != "count_since"}
        old_id = library.create_scan("P-1", {"object": plan}, identity=older)
        library.check_identity(old_id, again)


def test_a_calibration_outlives_a_restart_of_the_box_for_its_camera_not_its_table_count(
    pi_kit, fake_picamera2, tmp_path
):
    """The chessboard is the camera's: it serves after the box's program started again.
    Cylinder views counted before the restart do not, and the line says so and what to
    do; another box is named as such, with what differs."""
    from lamina_host.link.identity import calibration_mismatch

    first = _box_identity(pi_kit, fake_picamera2, tmp_path)
    again = _box_identity(pi_kit, fake_picamera2, tmp_path)
    assert calibration_mismatch(first, dict(first), counts_held=True) is None
    assert calibration_mismatch(first, again, counts_held=False) is None
    line = calibration_mismatch(first, again, counts_held=True)
    assert line is not None and "\n" not in line
    assert "started again" in line and "scan the cylinder again" in line
    other = {**again, "serial": "another box"}
    for held in (False, True):
        line = calibration_mismatch(first, other, counts_held=held)
        assert line is not None and "not the one calibrated" in line
        assert "serial" in line and "another box" in line and "calibrate again" in line
