"""Live control over the real pty link: exposure, the preview's stripe, pause/resume/abort."""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

from lamina_device.acquisition import capture_pair
from lamina_device.camera import CameraError
from lamina_device.extract import extract, to_segment
from lamina_device.replay import ReplayCamera
from lamina_device.sim import SIM_EXPOSURE_US, open_sim
from lamina_host.link.errors import DeviceError, ScanStopped
from lamina_shared.protocol import quantise_segment
from lamina_shared.types import ScanPlan, Segment
from tests.helpers.served import link


def stripe_peak_dn(exposure_us: int) -> float:
    """Return the median stripe peak (laser-on frame) the simulated rig shows at an exposure."""
    hardware = open_sim("cylinder:d=19.05", seed=3)
    try:
        hardware.place("object")
        hardware.camera.set_exposure(exposure_us)
        on, off = capture_pair(hardware)
        cols = extract(on, off).cols
        assert len(cols) > 50, "no stripe found"
        return float(np.median(on[:, cols].max(axis=0)))
    finally:
        hardware.close()


def test_sim_stripe_grows_with_exposure_and_saturates():
    low, nominal, high = (stripe_peak_dn(us) for us in (1000, SIM_EXPOSURE_US, 20_000))
    assert low < nominal < 255
    assert high == 255  # five times the nominal light clips the 8-bit sensor
    assert low < 0.5 * nominal  # a quarter of the light, plus ambient and noise


def test_exposure_refused_outside_the_range_and_device_stays_responsive():
    with link() as ends:
        client = ends.client
        assert client.exposure() == (SIM_EXPOSURE_US, 100, 20_000)
        with pytest.raises(DeviceError, match=r"outside this camera's 100\.\.20000 us"):
            client.set_exposure(50_000)
        with pytest.raises(DeviceError, match="whole number"):
            client.request("exposure", {"exposure_us": 1.5})
        assert client.request("status")["state"] == "idle"
        assert client.set_exposure(8000) == 8000
        assert ends.hardware.camera.exposure_us == 8000


def test_replay_camera_refuses_a_new_exposure():
    camera = ReplayCamera(None, None, None, None, None)  # type: ignore[arg-type]
    camera.set_exposure(SIM_EXPOSURE_US)  # no change: accepted
    with pytest.raises(CameraError, match="cannot change its exposure"):
        camera.set_exposure(2 * SIM_EXPOSURE_US)


def test_preview_returns_the_stripe_the_device_extracts():
    with link() as ends:
        client = ends.client
        client.request("move", {"axis": "turntable", "position": 90.0})
        preview = client.preview(laser=True)
        # The same rig, unlinked, at the same place: the scan's own extraction.
        reference = open_sim("cylinder:d=19.05", seed=3)
        try:
            reference.turntable.move_to(90.0)
            on, off = capture_pair(reference)
            expected = quantise_segment(to_segment(extract(on, off), "object", 0, 0, 0.0, 90.0))
        finally:
            reference.close()
        assert np.array_equal(preview.image, on)
        assert preview.stripe is not None and len(preview.stripe) > 50
        assert preview.stripe.same_as(expected)
        assert not ends.hardware.laser.is_on
        dark = client.preview(laser=False, stripe=False)
        assert dark.stripe is None and np.array_equal(dark.image, off)


def test_pause_resume_abort_from_another_thread():
    plan = ScanPlan.regular(4, 2.0, 8)
    with link() as ends:
        client = ends.client
        arrived: dict[int, float] = {}
        notices: list[str] = []
        first = threading.Event()

        def store(seq: int, segment: Segment) -> None:
            arrived[seq] = time.monotonic()
            first.set()

        def operator() -> None:
            first.wait(20)
            client.pause()
            time.sleep(1.5)
            paused_count = len(arrived)
            time.sleep(1.0)
            held_still.append(len(arrived) == paused_count)
            assert ends.server.state().state == "paused"
            client.resume()
            deadline = time.monotonic() + 20
            while len(arrived) < paused_count + 3 and time.monotonic() < deadline:
                time.sleep(0.02)
            resumed.append(len(arrived) > paused_count)
            client.abort()

        held_still: list[bool] = []
        resumed: list[bool] = []
        thread = threading.Thread(target=operator)
        thread.start()
        with pytest.raises(ScanStopped, match="views received are kept") as info:
            client.scan("object", plan, on_segment=store, on_notice=notices.append)
        thread.join()
        assert held_still == [True] and resumed == [True]
        got = info.value.segments
        assert set(got) == set(arrived) and 4 <= len(got) < len(plan.views)
        assert not ends.hardware.laser.is_on
        assert ends.hardware.lift.z_mm == 0.0
        assert client.request("status")["state"] == "idle"
        assert notices == []
        with pytest.raises(DeviceError, match="no scan is running to pause"):
            client.pause()
        rest = client.scan("object", plan, have=set(got))
        assert len(rest) == len(plan.views) - len(got)
