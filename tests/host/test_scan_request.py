"""The typed scan request: checked once, when it is made, in the front ends' words."""

from __future__ import annotations

import math

import pytest

from lamina_host.workflow.checks import check_mode
from lamina_host.workflow.job import ScanRequest
from lamina_shared.errors import InputError
from lamina_shared.messages import Welcome
from lamina_shared.protocol import PROTOCOL_VERSION
from lamina_shared.types import SCAN_MODES, ScanPlan


def test_a_valid_request_keeps_what_was_asked() -> None:
    plan = ScanPlan.regular(3, 1.5, 8)
    request = ScanRequest("P001-left", plan, 19.05, {"seed": 0}, {"method": "centroid"})
    assert request.plan is plan and request.cylinder_mm == 19.05
    assert request.extract == {"method": "centroid"} and dict(request.options) == {"seed": 0}
    assert ScanRequest("P001").extract is None  # the device's own settings unless set


@pytest.mark.parametrize("subject", ["", "Jane Doe", "\x1b[31mX", "a" * 33, "-lead"])
def test_a_subject_that_is_no_code_is_refused(subject: str) -> None:
    with pytest.raises(InputError, match="subject code"):
        ScanRequest(subject)


@pytest.mark.parametrize("diameter_mm", [0.0, -19.05, math.nan, math.inf, 1001.0])
def test_an_impossible_cylinder_is_refused(diameter_mm: float) -> None:
    with pytest.raises(InputError, match="cylinder diameter"):
        ScanRequest("P001", None, diameter_mm)


def test_a_scan_mode_the_device_does_not_offer_is_refused_before_the_scan_exists() -> None:
    continuous = ScanPlan.regular(3, 10.0, 8, "continuous")
    older = Welcome(PROTOCOL_VERSION)  # a device from before scan modes
    with pytest.raises(InputError, match=r"cannot scan in continuous mode .* stop-and-go"):
        check_mode(continuous, older)
    check_mode(continuous, Welcome(PROTOCOL_VERSION, modes=SCAN_MODES))
    check_mode(continuous.with_mode("stop-and-go"), older)
    with pytest.raises(InputError, match="colour needs a stop-and-go scan"):
        check_mode(continuous, Welcome(PROTOCOL_VERSION, modes=SCAN_MODES), colour=True)
    with pytest.raises(InputError, match="scan mode 'sideways'"):
        ScanRequest("P001", mode="sideways")
