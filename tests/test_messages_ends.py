"""Device and host read one schema of every message: what one end sends, the other reads back.

Each end imports its message classes from ``lamina_shared.messages`` and its reply
classes from ``lamina_shared.replies``; a copy kept on either side would fail the
identity checks, and a field one end writes differently from what the other reads would
fail the round trips against the real device's bodies and replies.
"""

from __future__ import annotations

import json
import threading
from typing import Any

import pytest

import lamina_device.operations as device_operations
import lamina_device.server as device_server
import lamina_host.link.client as host_client
import lamina_host.link.scanning as host_scanning
import lamina_host.link.transfer as host_transfer
import lamina_host.workflow.device_session as host_session
from lamina_device.hardware import Hardware
from lamina_device.server import DeviceServer
from lamina_device.sim import open_sim
from lamina_host.link.client import DeviceClient
from lamina_host.link.errors import DeviceError, RequestRefused, ScanStopped
from lamina_host.link.handshake import read_welcome
from lamina_shared import endpoint, messages, replies
from lamina_shared.limits import DeviceLimits
from lamina_shared.link import Channel
from lamina_shared.messages import (
    Ack,
    DeviceHeartbeat,
    MessageError,
    ProgressEvent,
    StatusEvent,
    parse_event,
)
from lamina_shared.ops import OPS, FetchArgs, NoArgs
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


def test_both_ends_read_each_reply_with_the_one_class():
    # The host's client reads replies through the one module (``replies.GridReply``...).
    assert host_client.replies is replies
    for name in ("GridReply", "PreviewReply", "ScanReply", "MoveReply", "ExposureReply"):
        assert getattr(device_operations, name) is getattr(replies, name)
    assert device_operations.ControlReply is replies.ControlReply
    assert device_operations.StatusReply is host_client.StatusReply is replies.StatusReply
    assert device_operations.ScanEstimate is host_client.ScanEstimate is replies.ScanEstimate
    assert endpoint.FetchReply is host_transfer.FetchReply is replies.FetchReply
    assert set(replies.REPLIES) == set(OPS)


def _recording(client: DeviceClient) -> dict[str, list[dict[str, Any]]]:
    """Keep every result the device sends ``client``, by operation, as it came."""
    raw: dict[str, list[dict[str, Any]]] = {}
    request = client.request

    def recording(op: str, args: Any = None, on_event: Any = None) -> dict[str, Any]:
        result = request(op, args, on_event)
        raw.setdefault(op, []).append(result)
        return result

    client.request = recording  # type: ignore[method-assign]
    return raw


def _control_a_scan(client: DeviceClient) -> dict[str, str | None]:
    """Pause, resume and abort a running scan from another thread; return their states."""
    first, seen = threading.Event(), {}

    def operator() -> None:
        first.wait(30)
        seen.update(pause=client.pause(), resume=client.resume(), abort=client.abort())

    thread = threading.Thread(target=operator)
    thread.start()
    with pytest.raises(ScanStopped):
        client.scan("object", ScanPlan.regular(4, 2.0, 8), on_segment=lambda *_: first.set())
    thread.join(timeout=30)
    return seen


def test_every_operations_real_reply_is_what_the_host_reads():
    """The served device's own reply to each operation parses with the host's class and
    writes back the very result it sent: no field renamed, dropped or of another kind."""
    with link() as ends:
        client = ends.client
        raw = _recording(client)
        image, board = client.grab_grid()
        assert board == ends.hardware.board and image.size
        assert client.preview(stripe=True).stripe is not None
        assert client.preview(stripe=False).stripe is None
        assert client.move("lift", 4.0) == 4.0 == ends.hardware.lift.z_mm
        exposure, low, high = client.exposure()
        assert client.set_exposure(exposure) == exposure and low <= exposure <= high
        estimate = client.estimate("object", ScanPlan.regular(1, 2.0, 4))
        assert estimate is not None and estimate.views == 4
        assert len(client.scan("object", ScanPlan.regular(1, 2.0, 2))) == 2
        assert _control_a_scan(client) == {"pause": "paused", "resume": "busy", "abort": "aborting"}
        status = client.status()
        assert status.state == "idle" and status.heartbeat.request is None
        transfer = replies.PreviewReply.from_wire(raw["preview"][-1]).offer.transfer
        client.request("fetch", FetchArgs(transfer, ((0, 16),)))
        client.request("shutdown", NoArgs())
    assert set(raw) == set(replies.REPLIES)  # every operation was asked
    for op, results in raw.items():
        for result in results:
            assert replies.REPLIES[op].from_wire(result).to_wire() == result, op
    assert replies.FetchReply.from_wire(raw["fetch"][0]) == replies.FetchReply(16)
    assert replies.ScanReply.from_wire(raw["scan"][0]) == replies.ScanReply(2, 2, 0)


MALFORMED: list[tuple[type[Any], dict[str, Any], list[str]]] = [
    (
        replies.GridReply,
        {"transfer": "1", "bytes": -1, "crc32": 2**40, "board": {"pattern": 3}},
        ["grab_grid.transfer", "grab_grid.bytes", "grab_grid.crc32", "grab_grid.board"],
    ),
    (
        replies.PreviewReply,
        {"transfer": 1.5, "bytes": 2, "crc32": None, "stripe": "not base64!"},
        ["preview.transfer", "preview.crc32", "preview.stripe"],
    ),
    (replies.PreviewReply, {"transfer": 1, "bytes": 2, "crc32": 3, "stripe": 7}, ["stripe"]),
    (replies.FetchReply, {"sent": True}, ["fetch.sent"]),
    (
        replies.ScanReply,
        {"segments": -1, "acquired": "2", "resent": 1e3},
        ["scan.segments", "scan.acquired", "scan.resent"],
    ),
    (
        replies.ScanEstimate,
        {"views": -1, "modelled_s": "soon", "mechanical_minimum_s": -2.0},
        ["estimate.views", "estimate.modelled_s", "estimate.mechanical_minimum_s"],
    ),
    (replies.ControlReply, {"state": "sleeping"}, ["control.state"]),
    (replies.MoveReply, {"axis": "roll", "position": "up"}, ["move.axis", "move.position"]),
    (
        replies.ExposureReply,
        {"exposure_us": 1.5, "min_us": -1, "max_us": "max"},
        ["exposure.exposure_us", "exposure.min_us", "exposure.max_us"],
    ),
    (
        replies.StatusReply,
        {"state": "odd", "request": "7", "unacked": -1, "uptime_s": None, "retransmissions": []},
        ["status.state", "status.request", "status.unacked", "status.uptime_s", "retransmissions"],
    ),
]


@pytest.mark.parametrize(("reply_type", "body", "named"), MALFORMED)
def test_a_malformed_reply_of_each_kind_is_refused_with_every_problem(reply_type, body, named):
    with pytest.raises(MessageError) as caught:
        reply_type.from_wire(body)
    assert len(caught.value.problems) == len(named)
    for where, problem in zip(named, caught.value.problems, strict=True):
        assert where in problem, (where, problem)


@pytest.mark.parametrize("reply_type", sorted(set(replies.REPLIES.values()), key=str))
def test_a_reply_missing_its_fields_names_each_and_a_non_object_is_refused(reply_type):
    with pytest.raises(MessageError, match="an object is required"):
        reply_type.from_wire(["not", "an", "object"])
    required = [k for k in _example(reply_type).to_wire() if k != "stripe"]
    if not required:
        assert reply_type.from_wire({}) == _example(reply_type)
        return
    with pytest.raises(MessageError) as caught:
        reply_type.from_wire({})
    assert caught.value.problems == [p for p in caught.value.problems if "is required" in p]
    assert sorted(p.split(": ")[1].split()[0] for p in caught.value.problems) == sorted(required)


def _example(reply_type: type[Any]) -> Any:
    """Return a reply of each class as a device sends it (fields all given)."""
    offer = replies.TransferOffer(1, 100, 12345)
    examples = {
        replies.GridReply: replies.GridReply(offer, None),
        replies.PreviewReply: replies.PreviewReply(offer, b"\x01\x02"),
        replies.FetchReply: replies.FetchReply(10),
        replies.ScanReply: replies.ScanReply(8, 6, 2),
        replies.ScanEstimate: replies.ScanEstimate(8, 15.2, 15.1),
        replies.ControlReply: replies.ControlReply("paused"),
        replies.MoveReply: replies.MoveReply("lift", 12.5),
        replies.ExposureReply: replies.ExposureReply(8000, 100, 10_000_000),
        replies.StatusReply: replies.StatusReply(DeviceHeartbeat("busy", 3, 2, 1.5), 4),
        replies.EmptyReply: replies.EmptyReply(),
    }
    return examples[reply_type]


@pytest.mark.parametrize("reply_type", sorted(set(replies.REPLIES.values()), key=str))
def test_each_reply_round_trips_through_json(reply_type):
    reply = _example(reply_type)
    assert reply_type.from_wire(json.loads(json.dumps(reply.to_wire()))) == reply


class _DriftedServer(DeviceServer):
    """A device whose ``move`` answers with another operation's reply class."""

    def __init__(self, channel: Channel, hardware: Hardware, settings: Any = None) -> None:
        super().__init__(channel, hardware, settings)
        self._handlers["move"] = lambda request_id, args: replies.ControlReply("busy")


def test_a_device_reply_of_the_wrong_class_is_never_sent_and_a_bad_one_never_read():
    with link(server_class=_DriftedServer) as ends:
        with pytest.raises(RequestRefused) as refused:
            ends.client.move("lift", 1.0)
        assert refused.value.code == "internal"
        assert ends.hardware.lift.z_mm == 0.0
        ends.client.request = lambda op, args=None, on_event=None: {"axis": "roll"}  # type: ignore[method-assign]
        malformed = r"move reply is malformed \(move: position is required; move\.axis: one of"
        with pytest.raises(DeviceError, match=malformed):
            ends.client.move("lift", 1.0)
