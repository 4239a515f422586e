"""The scan-time estimate over the link: the device's model, asked by the host before a scan."""

from __future__ import annotations

import dataclasses

import pytest

from lamina_device.config import load_config
from lamina_device.timing import estimate_scan_time
from lamina_host.link.errors import RequestRefused
from lamina_shared.messages import MessageError
from lamina_shared.replies import ScanEstimate
from lamina_shared.types import ScanPlan
from tests.helpers.served import link


def test_the_host_gets_the_devices_model_of_a_plan_and_of_its_default():
    plan = ScanPlan.regular(sections=3, pitch_mm=5.0, views=8)
    with link() as ends:
        assert "estimate" in ends.info.operations
        estimate = ends.client.estimate("object", plan)
        default = ends.client.estimate("object")
        exposure = ends.hardware.camera.exposure_us
    truth = estimate_scan_time(load_config(), plan, exposure_us=exposure)
    assert estimate is not None and estimate.views == 24
    assert estimate.modelled_s == pytest.approx(truth.modelled_s, abs=1e-3)
    assert estimate.mechanical_minimum_s == pytest.approx(truth.mechanical_minimum_s, abs=1e-3)
    assert default is not None and default.views == 32  # the sim's default: 4 x 8 views


def test_a_plan_beyond_the_devices_reach_is_refused_and_an_old_device_says_nothing():
    too_high = ScanPlan.regular(sections=2, pitch_mm=400.0, views=4)
    with link() as ends:
        with pytest.raises(RequestRefused, match="lift"):
            ends.client.estimate("object", too_high)
        assert ends.client.info is not None
        operations = tuple(op for op in ends.client.info.operations if op != "estimate")
        ends.client.info = dataclasses.replace(ends.client.info, operations=operations)
        assert ends.client.estimate("object") is None


def test_an_estimate_reply_is_checked_whole():
    good = ScanEstimate(8, 15.2, 15.1)
    assert ScanEstimate.from_wire(good.to_wire()) == good
    with pytest.raises(MessageError) as info:
        ScanEstimate.from_wire({"views": -1, "modelled_s": "soon"})
    problems = " ".join(info.value.problems)
    assert "views" in problems and "modelled_s" in problems and "mechanical_minimum_s" in problems


def test_a_continuous_plan_is_timed_in_its_mode_and_refused_by_a_device_without_it():
    plan = ScanPlan.regular(sections=3, pitch_mm=10.0, views=8, mode="continuous")
    with link() as ends:
        assert ends.info.modes == ("stop-and-go", "continuous")
        estimate = ends.client.estimate("object", plan)
        exposure = ends.hardware.camera.exposure_us
        clock = ends.hardware.turntable.clock
        config = clock.config
        # The same box set up without a continuous speed: stop-and-go only.
        table = dataclasses.replace(config.turntable, continuous_speed_deg_s=0.0)
        clock.config = dataclasses.replace(config, turntable=table)
        with pytest.raises(RequestRefused, match="cannot scan continuously"):
            ends.client.estimate("object", plan)
    truth = estimate_scan_time(load_config(), plan, exposure_us=exposure)
    still = estimate_scan_time(load_config(), plan.with_mode("stop-and-go"), exposure_us=exposure)
    assert estimate is not None and estimate.views == 24
    assert estimate.modelled_s == pytest.approx(truth.modelled_s, abs=1e-3)
    assert estimate.modelled_s < still.modelled_s / 2
