"""The typed scan request: checked once, when it is made, in the front ends' words."""

from __future__ import annotations

import math

import pytest

from lamina_host.workflow.job import ScanRequest
from lamina_shared.errors import InputError
from lamina_shared.types import ScanPlan


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
