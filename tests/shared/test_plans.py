"""Scan plans and their mode on the wire: stop-and-go forms unchanged, continuous ones kept."""

from __future__ import annotations

import json

import pytest

from lamina_shared.limits import DeviceLimits
from lamina_shared.ops import Problems, check_plan
from lamina_shared.types import SCAN_MODES, ScanPlan, ViewSpec

LIMITS = DeviceLimits()


def wire(plan: ScanPlan) -> object:
    return json.loads(json.dumps(plan.to_wire()))


@pytest.mark.parametrize("mode", SCAN_MODES)
@pytest.mark.parametrize(
    "plan",
    [ScanPlan.regular(40, 10.0, 8), ScanPlan((ViewSpec(0, 0.0, 10.0), ViewSpec(3, 2.5, 200.0)))],
)
def test_a_plan_and_its_mode_survive_the_wire_and_the_store(plan, mode):
    moded = plan.with_mode(mode)
    problems = Problems()
    assert check_plan(wire(moded), LIMITS, problems) == moded and not problems.items
    assert ScanPlan.from_dict(wire(moded)) == moded
    assert ScanPlan.from_dict(json.loads(json.dumps(moded.to_dict()))) == moded
    assert moded.with_views(moded.views[:1]).mode == mode


def test_a_stop_and_go_plan_keeps_the_form_it_had_before_modes():
    plan = ScanPlan.regular(4, 2.0, 8)
    assert plan.to_wire() == {"regular": {"sections": 4, "pitch_mm": 2.0, "views": 8}}
    assert "mode" not in plan.to_dict()
    continuous = plan.with_mode("continuous")
    assert continuous.to_wire()["mode"] == "continuous" and continuous != plan


def test_an_unknown_mode_is_refused_in_words():
    problems = Problems()
    form = {"regular": {"sections": 2, "pitch_mm": 1.0, "views": 4}, "mode": "helical"}
    assert check_plan(form, LIMITS, problems) is None
    assert problems.items == [
        "plan.mode: one of stop-and-go, continuous is required, found 'helical'"
    ]
    with pytest.raises(ValueError, match="helical"):
        ScanPlan.from_dict(form)
    with pytest.raises(ValueError, match="helical"):
        ScanPlan.regular(1, 1.0, 1, "helical")


def test_a_continuous_view_may_carry_the_angle_the_table_was_at():
    planned = ScanPlan.regular(2, 10.0, 8)
    assert planned.labels(9, 1, 10.0, 45.0)
    assert not planned.labels(9, 1, 10.0, 46.2)  # stop-and-go: the planned angle exactly
    continuous = planned.with_mode("continuous")
    assert continuous.labels(9, 1, 10.0, 46.2)
    for section, z_mm, angle in ((0, 10.0, 45.0), (1, 0.0, 45.0), (1, 10.0, 360.0)):
        assert not continuous.labels(9, section, z_mm, angle)
    assert not continuous.labels(16, 1, 10.0, 45.0) and not continuous.labels(-1, 0, 0.0, 0.0)
    assert not continuous.labels(9, 1, 10.0, float("nan"))
