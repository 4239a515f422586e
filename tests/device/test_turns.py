"""Each segment's whole turns (issue 22): the step count since power-up, as the device sends it.

A table that turns short of its count falls further behind with every turn, so the host
corrects each view at its count, ``angle_deg + 360 * turns``; these tests hold the device
to sending the count the table really reached, in both modes.
"""

from __future__ import annotations

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
