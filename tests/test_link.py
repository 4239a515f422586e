"""The device server and the host client over a real pseudo-terminal link.

The server runs in this process on its own thread, driving the simulated rig, so
tests can compare what crossed the link with what the rig produces directly.
"""

from __future__ import annotations

import pytest

from lamina_device.acquisition import grab_grid
from lamina_device.server import ServerSettings
from lamina_device.sim import open_sim
from lamina_host.link.client import DeviceClient
from lamina_host.link.errors import DeviceError
from lamina_host.testing import LineFaults
from lamina_shared.limits import DeviceLimits
from lamina_shared.messages import AxesInfo, Event, ProgressEvent, StatusEvent
from lamina_shared.protocol import PROTOCOL_VERSION, Kind, encode_json
from lamina_shared.types import ScanPlan, Segment, from_first_turn
from tests.helpers.served import link, reference

PLAN = ScanPlan.regular(2, 2.0, 4)


@pytest.fixture(scope="module")
def expected() -> list[Segment]:
    return reference(PLAN)


def same(a: list[Segment], b: list[Segment]) -> bool:
    """Return True when both are the same views bit for bit, their turns counted from each
    list's first (a device's turns run on from one scan to the next)."""
    return len(a) == len(b) and all(
        x.same_as(y) for x, y in zip(from_first_turn(a), from_first_turn(b), strict=True)
    )


def test_handshake_reports_capabilities():
    with link() as ends:
        info = ends.client.info
        assert info is not None
        assert info.protocol == PROTOCOL_VERSION and info.software.startswith("lamina-device")
        assert info.image_size == (640, 480)
        assert info.axes == AxesInfo(0.0, 200.0, None, None, None)
        assert info.axes.continuous
        assert {"scan", "grab_grid", "fetch", "move", "pause", "resume", "abort"} <= set(
            info.operations
        )
        assert info.limits.window_segments == DeviceLimits().window_segments


def test_clean_scan_delivers_exactly_what_the_rig_produced(expected):
    with link() as ends:
        stored: dict[int, Segment] = {}
        got = ends.client.scan("object", PLAN, on_segment=stored.__setitem__)
        assert same(got, expected)
        assert same([stored[k] for k in sorted(stored)], expected)
        assert len(ends.server.buffer) == 0


def test_resume_acquires_only_what_the_host_lacks(expected):
    have = {0, 1, 5}
    with link() as ends:
        captured_before = ends.hardware.camera.frames_taken
        got = ends.client.scan("object", PLAN, have=have)
        # Two frames (laser off, laser on) per view actually acquired.
        assert ends.hardware.camera.frames_taken - captured_before == 2 * (8 - len(have))
    assert same(got, [s for k, s in enumerate(expected) if k not in have])


def test_a_new_host_gets_buffered_segments_resent_not_reacquired(expected):
    """The first host dies after storing two segments; the rest stay in the device buffer."""

    class HostDied(Exception):
        pass

    with link(settings=ServerSettings(limits=DeviceLimits(window_segments=32))) as ends:
        stored: dict[int, Segment] = {}

        def store_then_die(seq: int, segment: Segment) -> None:
            if len(stored) == 2:
                raise HostDied  # killed before storing (so before acknowledging) this one
            stored[seq] = segment

        with pytest.raises(HostDied):
            ends.client.scan("object", PLAN, on_segment=store_then_die)
        # A new host session stops the old scan; what was sent but never acknowledged
        # stays in the device's buffer.
        second = DeviceClient(ends.client.channel, idle_timeout_s=20)
        second.hello()
        kept = len(ends.server.buffer)
        assert kept >= 1
        frames = ends.hardware.camera.frames_taken
        got = second.scan("object", PLAN, have=set(stored), on_segment=stored.__setitem__)
        acquired = (ends.hardware.camera.frames_taken - frames) // 2
        assert acquired == 8 - 2 - kept  # the buffered views were resent, not re-acquired
        assert len(got) == 6
    assert same([stored[k] for k in sorted(stored)], expected)


def test_calibration_image_survives_a_cut_mid_transfer():
    hardware = open_sim("cylinder:d=19.05", seed=3)
    truth = grab_grid(hardware)
    hardware.close()
    faults = LineFaults(cut_after_bytes=(60_000,), cut_s=0.5, error_rate=1e-4, seed=2)
    with link(faults) as ends:
        image, board = ends.client.grab_grid()
        assert faults.counts["cuts"] == 1 and faults.counts["cut_bytes"] > 0
        assert ends.client.stats.fetch_rounds >= 1
    assert (image == truth).all()
    assert board.inner_corners == (13, 11)


def test_device_refuses_what_is_outside_its_limits_and_stays_responsive():
    with link() as ends:
        client = ends.client
        with pytest.raises(DeviceError, match="soft limits"):
            client.request("move", {"axis": "lift", "position": 250.0})
        with pytest.raises(DeviceError, match="unknown operation"):
            client.request("format_disk")
        with pytest.raises(DeviceError, match="no argument 'path'"):
            client.request("scan", {"target": "object", "path": "/etc/passwd"})
        too_high = ScanPlan.regular(2, 150.0, 2)  # second section at 150 mm: fine
        higher = ScanPlan.regular(3, 150.0, 2)  # third section at 300 mm: beyond 200
        with pytest.raises(DeviceError, match="soft limits"):
            client.scan("object", higher)
        with pytest.raises(DeviceError, match="view indices"):
            client.request("scan", {"target": "object", "plan": too_high.to_dict(), "have": [9]})
        with pytest.raises(DeviceError, match="no scan is running"):
            client.request("pause")
        assert client.request("move", {"axis": "lift", "position": 12.5})["position"] == 12.5
        assert ends.hardware.lift.z_mm == 12.5
        assert client.request("status")["state"] == "idle"


def test_pause_resume_and_abort_while_scanning():
    with link() as ends:
        client = ends.client
        events: list[str] = []
        seen = {"progress": 0}

        def control(op: str) -> None:
            # Sent from within the running request: the server reads while it scans.
            frame = encode_json(Kind.REQUEST, {"id": 900 + len(events), "op": op, "args": {}})
            client.channel.send(frame)
            events.append(op)

        def on_event(event: Event) -> None:
            if isinstance(event, ProgressEvent):
                seen["progress"] += 1
                if seen["progress"] == 1:
                    control("pause")
                elif seen["progress"] == 2:
                    control("resume")
                elif seen["progress"] == 3:
                    control("abort")
            elif isinstance(event, StatusEvent):
                events.append(f"status:{event.state}")

        with pytest.raises(DeviceError, match="aborted"):
            client.scan("object", ScanPlan.regular(4, 2.0, 8), on_event)
        assert events[:3] == ["status:busy", "pause", "status:paused"]
        assert "resume" in events and "abort" in events
        assert seen["progress"] < 32
        assert not ends.hardware.laser.is_on
        assert client.request("status")["state"] == "idle"


def test_host_refuses_segments_beyond_its_limits():
    with link() as ends:
        # The device believes it scans the plan; the host checks against a different plan.
        client = ends.client
        assert client.info is not None
        client.info = type(client.info)(
            **{**client.info.__dict__, "image_size": (100, 100)}  # a smaller sensor than sent
        )
        with pytest.raises(DeviceError, match="outside the 100x100 image"):
            client.scan("object", PLAN)
