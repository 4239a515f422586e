"""A simulated patient's sway: its model, its spec, and frames that follow it in time."""

from __future__ import annotations

import math

import numpy as np
import pytest

from lamina_device.acquisition import capture_pair
from lamina_device.backends import open_hardware
from lamina_device.extract import extract
from lamina_device.hardware import HardwareError
from lamina_device.sim.sway import Sway, parse_sway


def test_drift_grows_with_time_and_breathing_stays_within_its_amplitude():
    drift = Sway(drift_mm_per_min=2.0, seed=3)
    assert drift.offset_mm(0.0) == (0.0, 0.0)
    assert math.hypot(*drift.offset_mm(30.0)) == pytest.approx(1.0)
    assert math.hypot(*drift.offset_mm(90.0)) == pytest.approx(3.0)
    breath = Sway(breathing_mm=0.4, breathing_hz=0.25, seed=3)
    radii = [math.hypot(*breath.offset_mm(t)) for t in np.linspace(0.0, 8.0, 200)]
    assert max(radii) == pytest.approx(0.4, abs=1e-3) and min(radii) < 0.01
    # Four seconds is one breath: back where it was.
    np.testing.assert_allclose(breath.offset_mm(1.3), breath.offset_mm(5.3), atol=1e-12)
    assert Sway().still and Sway().offset_mm(100.0) == (0.0, 0.0)


def test_sway_specs_and_their_refusals():
    patient = parse_sway("patient", seed=7)
    assert (patient.drift_mm_per_min, patient.breathing_mm, patient.seed) == (1.0, 0.5, 7)
    assert parse_sway("drift=2,breath=0.3,hz=0.2") == Sway(2.0, 0.3, 0.2)
    for bad, words in (("wobble", "not one of"), ("drift=x", "not a number"),
                       ("hz=9", "out of range"), ("", "empty")):  # fmt: skip
        with pytest.raises(ValueError, match=words):
            parse_sway(bad)
    with pytest.raises(HardwareError, match="sway"):
        open_hardware("sim", "cylinder:d=19.05", sway="drift=-1")


def stripe_rows(sway: str, wait_s: float) -> np.ndarray:
    hardware = open_hardware("sim", "cylinder:d=19.05", noise="none", sway=sway)
    try:
        hardware.place("object")
        hardware.turntable.clock.advance(wait_s)
        on, off = capture_pair(hardware)
        points = extract(on, off, hardware.extract)
        return np.interp(np.arange(200, 440), points.cols, points.rows)
    finally:
        hardware.close()


def test_frames_follow_the_sway_on_the_virtual_clock():
    still = stripe_rows("none", 0.0)
    assert np.array_equal(still, stripe_rows("none", 30.0))  # a still object: time is nothing
    # 45 mm a minute for 3 s: the cylinder is 2.25 mm off its place, its stripe moves.
    moved = np.median(np.abs(stripe_rows("drift=45", 3.0) - still))
    assert moved > 1.0
    # At the start only the two frames' 33 ms have passed: 0.02 mm, a small fraction of a
    # pixel, as much as the drift over 3 s scaled to 33 ms (the stripe moves steadily).
    start = np.median(np.abs(stripe_rows("drift=45", 0.0) - still))
    assert 0.7 < start / (moved * 0.033 / 3.033) < 1.3 and start < 0.25
