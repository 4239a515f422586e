"""Device and host read one schema of every message: what one end sends, the other reads back.

Each end imports its message classes from ``lamina_shared.messages``; a copy kept on
either side would fail the identity checks, and a field one end writes differently from
what the other reads would fail the round trips against the real device's bodies.
"""

from __future__ import annotations

import lamina_device.operations as device_operations
import lamina_device.server as device_server
import lamina_host.link.client as host_client
import lamina_host.link.scanning as host_scanning
import lamina_host.workflow.device_session as host_session
from lamina_device.server import DeviceServer
from lamina_device.sim import open_sim
from lamina_host.link.handshake import read_welcome
from lamina_shared import messages
from lamina_shared.limits import DeviceLimits
from lamina_shared.link import Channel
from lamina_shared.messages import Ack, ProgressEvent, StatusEvent, parse_event
from lamina_shared.types import ScanPlan
from tests.helpers.served import SilentStream, link


def test_both_ends_import_the_one_schema():
    assert device_server.Welcome is messages.Welcome is host_client.Welcome
    assert device_operations.ProgressEvent is messages.ProgressEvent
    assert device_operations.Progress is messages.Progress is host_session.Progress
    assert host_scanning.Ack is messages.Ack


def test_the_devices_welcome_is_what_the_host_reads():
    hardware = open_sim()
    try:
        server = DeviceServer(Channel(SilentStream()), hardware)
        body = server.welcome()
        info = read_welcome(body)
    finally:
        hardware.close()
    assert info == server.info()
    assert info.to_wire() == body
    assert info.limits == DeviceLimits() and info.image_size == hardware.camera.size


def test_a_scans_progress_events_and_acks_cross_the_link_typed():
    with link() as ends:
        events: list[object] = []
        plan = ScanPlan.regular(2, 2.0, 2)
        got = ends.client.scan("object", plan, events.append)
        progress = [e.progress for e in events if isinstance(e, ProgressEvent)]
        assert [p.done for p in progress] == list(range(1, len(plan.views) + 1))
        assert {p.total for p in progress} == {len(plan.views)} and len(got) == len(plan.views)
        assert [p.section for p in progress] == [v.section for v in plan.views]
        assert any(isinstance(e, StatusEvent) and e.op == "scan" for e in events)
        # Every segment was acknowledged in the form the device reads.
        assert len(ends.server.buffer) == 0
    body = Ack.stored(1, 5, [2, 3]).to_wire()
    assert Ack.from_wire(body, DeviceLimits()) == Ack(1, (5,), (2, 3))
    assert parse_event(ProgressEvent(1, progress[0]).to_wire()) == ProgressEvent(1, progress[0])
