"""The typed link messages: each survives its wire form, and a bad one is refused whole."""

from __future__ import annotations

import json
from typing import Any

import pytest

from lamina_shared.limits import DeviceLimits
from lamina_shared.messages import (
    MAX_LOST_SEQS,
    Ack,
    AxesInfo,
    DeviceIdentity,
    LogEvent,
    MessageError,
    Progress,
    ProgressEvent,
    StatusEvent,
    Welcome,
    parse_event,
)
from lamina_shared.ops import ExtractChanges
from lamina_shared.protocol import PROTOCOL_VERSION, ROW_SCALE
from lamina_shared.types import BoardSpec, ScanPlan

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
        identity=DeviceIdentity("sim", "sim object=x"),
        extract=ExtractChanges((("threshold", None), ("power", 1.0), ("min_chain_px", 8))),
        colour=True,
    )


def test_welcome_round_trips_through_json():
    welcome = _welcome()
    body = _json(welcome.to_wire())
    assert body["limits"]["max_views"] == 500 and body["segment_encoding"] == {"row_scale": 64}
    assert Welcome.from_wire(body) == welcome
    assert Welcome.from_wire(body).to_wire() == welcome.to_wire()


def test_an_older_welcome_reads_with_defaults_and_another_version_for_its_versions_only():
    body = {"protocol": PROTOCOL_VERSION, "hardware": "pi", "image_size": [64, 48]}
    body["segment_encoding"] = {"row_scale": ROW_SCALE}
    older = Welcome.from_wire(body)
    assert (older.colour, older.extract, older.identity, older.board) == (False, None, None, None)
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
