"""The typed link messages: each survives its wire form, and a bad one is refused whole."""

from __future__ import annotations

import json
from typing import Any

import pytest

from lamina_shared.limits import DeviceLimits
from lamina_shared.messages import (
    MAX_LOST_SEQS,
    MAX_SESSION_CHARS,
    Ack,
    AxesInfo,
    DeviceHeartbeat,
    DeviceIdentity,
    Hello,
    HostHeartbeat,
    LogEvent,
    MessageError,
    Progress,
    ProgressEvent,
    StatusEvent,
    Welcome,
    parse_event,
)
from lamina_shared.ops import ExtractChanges, Problems
from lamina_shared.protocol import PROTOCOL_VERSION, ROW_SCALE
from lamina_shared.types import SCAN_MODES, BoardSpec, ScanPlan

LIMITS = DeviceLimits()


def _json(body: dict[str, Any]) -> Any:
    return json.loads(json.dumps(body))


def _welcome() -> Welcome:
    return Welcome(
        protocol=PROTOCOL_VERSION,
        software="lamina-device 9",
        hardware="sim",
        description="a test rig",
        image_size=(640, 480),
        board=BoardSpec((13, 11), 2.0, (-12.0, -10.0)),
        cylinder_diameter_mm=19.05,
        default_plans={"object": ScanPlan.regular(4, 2.0, 8)},
        axes=AxesInfo(0.0, 200.0, -90.0, 90.0, 0.0025),
        operations=("move", "scan"),
        limits=DeviceLimits(max_views=500),
        identity=DeviceIdentity("box-7", "camera", "00f1e2d3c4b5a697"),
        extract=ExtractChanges((("threshold", None), ("power", 1.0), ("min_chain_px", 8))),
        colour=True,
        modes=SCAN_MODES,
        row_turn_deg=0.0033,
        off_frames="next-turn",
    )


def test_welcome_round_trips_through_json():
    welcome = _welcome()
    body = _json(welcome.to_wire())
    assert body["limits"]["max_views"] == 500 and body["segment_encoding"] == {"row_scale": 64}
    assert Welcome.from_wire(body) == welcome
    assert Welcome.from_wire(body).to_wire() == welcome.to_wire()
    assert body["identity"]["count_since"] == "00f1e2d3c4b5a697"
    # A device that starts its world afresh (simulator, replay) leaves the key out.
    assert DeviceIdentity("sim", "sim object=x").to_wire() == {
        "serial": "sim",
        "source": "sim object=x",
    }


def test_an_older_welcome_reads_with_defaults_and_another_version_for_its_versions_only():
    body = {"protocol": PROTOCOL_VERSION, "hardware": "pi", "image_size": [64, 48]}
    body["segment_encoding"] = {"row_scale": ROW_SCALE}
    older = Welcome.from_wire(body)
    assert (older.colour, older.extract, older.identity, older.board) == (False, None, None, None)
    assert older.modes == ("stop-and-go",)  # a device from before scan modes stops at each view
    assert older.row_turn_deg is None  # nor does it say how its rows were exposed
    assert older.off_frames is None  # nor where its laser-off frames came from
    assert older.limits == DeviceLimits() and older.software == "?"
    other = Welcome.from_wire({"protocol": 3, "software": "lamina-device 0", "image_size": "x"})
    assert other == Welcome(3, "lamina-device 0")


def test_a_bad_welcome_is_refused_with_every_problem():
    body = _json(_welcome().to_wire())
    body.update(
        image_size=[640, 99_999],
        segment_encoding={"row_scale": 32},
        board={"inner_corners": "many"},
        default_plans={"object": {"regular": {"sections": "x"}}},
        operations=[1],
        extract={"power": [1]},
        cylinder_diameter_mm="wide",
    )
    del body["hardware"]
    with pytest.raises(MessageError) as info:
        Welcome.from_wire(body)
    problems = info.value.problems
    for part in (
        "hardware is required",
        "image_size[1]: 99999 is outside 1..16384",
        "row_scale: 32 is not this host's 64",
        "welcome.board",
        "welcome.default_plans.'object'",
        "welcome.operations",
        "welcome.extract.'power'",
        "welcome.cylinder_diameter_mm",
    ):
        assert sum(part in p for p in problems) == 1, (part, problems)
    assert len(problems) == 8
    with pytest.raises(MessageError, match="protocol: a whole number"):
        Welcome.from_wire({"protocol": "4"})
    with pytest.raises(MessageError, match="an object is required"):
        Welcome.from_wire([1])


def test_ack_round_trips_and_names_at_most_64_lost():
    ack = Ack(7, (3, 4), (0, 1))
    assert _json(ack.to_wire()) == {"id": 7, "seqs": [3, 4], "lost": [0, 1]}
    assert Ack.from_wire(_json(ack.to_wire()), LIMITS) == ack
    assert Ack.from_wire({"id": 7, "seqs": [2]}, LIMITS) == Ack(7, (2,))
    stored = Ack.stored(7, 200, list(range(150)))
    assert stored.seqs == (200,) and stored.lost == tuple(range(MAX_LOST_SEQS))


def test_a_bad_ack_is_refused_with_every_problem():
    with pytest.raises(MessageError) as info:
        Ack.from_wire({"id": True, "seqs": [1, -1, "3", None], "lost": {"a": 1}}, LIMITS)
    assert info.value.problems == [
        "ack.id: a whole number is required, found True",
        "ack.seqs[1]: a segment number is required, found -1",
        "ack.seqs[2]: a segment number is required, found '3'",
        "ack.seqs[3]: a segment number is required, found None",
        "ack.lost: a list is required, found {'a': 1}",
    ]
    with pytest.raises(MessageError, match="at most 1024"):
        Ack.from_wire({"id": 1, "seqs": list(range(600)), "lost": list(range(600))}, LIMITS)
    with pytest.raises(MessageError, match="seqs is required"):
        Ack.from_wire({"id": 1}, LIMITS)


def test_events_round_trip_and_progress_carries_four_fields():
    progress = Progress("object", 5, 32, 1, state="paused", elapsed_s=2.0, done_this_run=5)
    sent = ProgressEvent(9, progress)
    assert sent.to_wire() == {
        "id": 9, "event": "progress", "target": "object", "done": 5, "total": 32, "section": 1,
    }  # fmt: skip
    assert parse_event(_json(sent.to_wire())) == ProgressEvent(9, Progress("object", 5, 32, 1))
    for event in (StatusEvent(9, "busy", "scan"), StatusEvent(9, "paused"), LogEvent(9, "hi")):
        assert parse_event(_json(event.to_wire())) == event
    assert StatusEvent(9, "paused").to_wire() == {"id": 9, "event": "status", "state": "paused"}


def test_a_bad_event_is_refused_with_every_problem():
    with pytest.raises(MessageError) as info:
        parse_event({"id": -1, "event": "progress", "target": 3, "done": 1.5, "section": 70_000})
    assert info.value.problems == [
        "event.id: -1 is outside 0..4294967295",
        "event: total is required",
        "event.target: a text of at most 1000 characters is required",
        "event.done: a whole number is required, found 1.5",
        "event.section: 70000 is outside 0..65535",
    ]
    with pytest.raises(MessageError, match="one of progress, status, log"):
        parse_event({"id": 1, "event": "party"})
    with pytest.raises(MessageError, match="id is required"):
        parse_event({"event": "log", "message": "x"})


def test_progress_estimates_the_time_left_from_this_runs_rate():
    assert Progress("object", 10, 16, 1, elapsed_s=2.0, done_this_run=4).left_s == 3.0
    assert Progress("object", 6, 16, 0, elapsed_s=0.5).left_s is None


def test_hello_round_trips_and_a_hostile_session_reads_as_none():
    hello = Hello("ab12")
    assert _json(hello.to_wire()) == {
        "protocol": PROTOCOL_VERSION, "software": "lamina-host", "session": "ab12",
    }  # fmt: skip
    assert Hello.from_wire(_json(hello.to_wire())) == hello
    for session in ({"x": [1]}, "s" * (MAX_SESSION_CHARS + 1), 7, None):
        assert Hello.from_wire({"protocol": 2, "session": session}) == Hello(None, 2, "?")
    with pytest.raises(MessageError) as info:
        Hello.from_wire({"software": 3})
    assert info.value.problems == [
        "hello: protocol is required",
        "hello.software: a text of at most 1000 characters is required",
    ]
    with pytest.raises(MessageError, match=r"hello\.protocol: a huge integer is outside"):
        Hello.from_wire({"protocol": 10**400})


def test_heartbeats_round_trip_and_a_bad_one_is_refused_with_every_problem():
    beat = DeviceHeartbeat("paused", 3, 2, 1.23456)
    assert _json(beat.to_wire()) == {
        "state": "paused",
        "request": 3,
        "unacked": 2,
        "uptime_s": 1.235,
    }
    assert DeviceHeartbeat.from_wire({**beat.to_wire(), "uptime_s": 1.5}) == DeviceHeartbeat(
        "paused", 3, 2, 1.5
    )
    assert (
        DeviceHeartbeat.from_wire(DeviceHeartbeat("idle", None, 0, 0.0).to_wire()).request is None
    )
    with pytest.raises(MessageError) as info:
        DeviceHeartbeat.from_wire({"state": {"deep": []}, "request": "1", "unacked": -1})
    assert info.value.problems == [
        "heartbeat: uptime_s is required",
        "heartbeat.state: one of idle, busy, paused is required, found {'deep': []}",
        "heartbeat.request: a whole number is required, found '1'",
        "heartbeat.unacked: -1 is outside 0..4294967295",
    ]
    assert HostHeartbeat.from_wire(HostHeartbeat("ab12").to_wire()) == HostHeartbeat("ab12")
    for body, problem in (({}, "session is required"), ({"session": 10**400}, "a text of")):
        with pytest.raises(MessageError, match=problem):
            HostHeartbeat.from_wire(body)


def test_axes_round_trip_and_bad_ones_are_refused_with_every_problem():
    stepper = AxesInfo(0.0, 120.0, None, None, 0.0025)
    assert _json(stepper.to_wire()) == {
        "lift": {"unit": "mm", "min": 0.0, "max": 120.0, "step": 0.0025},
        "turntable": {"unit": "deg", "min": None, "max": None, "continuous": True},
    }
    problems = Problems()
    assert AxesInfo.from_wire(_json(stepper.to_wire()), problems) == stepper
    assert AxesInfo.from_wire(None, problems) == AxesInfo() and not problems.items
    assert not AxesInfo(0.0, 1.0, -90.0, 90.0).to_wire()["turntable"]["continuous"]
    bad = {
        "lift": {"unit": "inch", "min": "0", "max": 1e999, "step": -1.0},
        "turntable": {"min": True, "continuous": "yes"},
    }
    AxesInfo.from_wire(bad, problems)
    for part in (
        "welcome.axes.lift.unit: mm is required, found 'inch'",
        "welcome.axes.lift.min: a number is required",
        "welcome.axes.lift.max: inf is not a finite number",
        "welcome.axes.lift.step: -1.0 is outside 0..inf",
        "welcome.axes.turntable.min: a number is required",
        "welcome.axes.turntable.continuous: true or false is required",
    ):
        assert sum(part in p for p in problems.items) == 1, (part, problems.items)
    assert len(problems.items) == 6
    body = {**_json(_welcome().to_wire()), "axes": [1]}
    with pytest.raises(MessageError, match=r"welcome\.axes: an object is required"):
        Welcome.from_wire(body)


def test_scan_modes_a_welcome_offers_are_read_leaving_out_names_this_host_does_not_know():
    body = _json(_welcome().to_wire())
    assert body["modes"] == ["stop-and-go", "continuous"]
    body["modes"] = ["continuous", "helical", "stop-and-go"]  # a newer device's extra mode
    assert Welcome.from_wire(body).modes == SCAN_MODES
    body["modes"] = "continuous"
    with pytest.raises(MessageError, match=r"welcome\.modes"):
        Welcome.from_wire(body)


def test_laser_off_frames_of_a_kind_this_host_does_not_know_are_left_out_not_refused():
    body = _json(_welcome().to_wire())
    assert body["off_frames"] == "next-turn"
    for said, read in (("interleaved", "interleaved"), ("two-turns-later", None), (None, None)):
        assert Welcome.from_wire({**body, "off_frames": said}).off_frames == read
    with pytest.raises(MessageError) as info:
        Welcome.from_wire({**body, "off_frames": 2})
    assert "welcome.off_frames: a name is required, found 2" in info.value.problems


@pytest.mark.parametrize(
    ("value", "problem"),
    [
        ("fast", "welcome.row_turn_deg: a number is required, found 'fast'"),
        (True, "welcome.row_turn_deg: a number is required, found True"),
        (2.0, "welcome.row_turn_deg: 2.0 is outside -1..1"),
    ],
)
def test_a_row_turn_beyond_any_rolling_shutter_is_refused(value, problem):
    body = {**_json(_welcome().to_wire()), "row_turn_deg": value}
    with pytest.raises(MessageError) as info:
        Welcome.from_wire(body)
    assert problem in info.value.problems
