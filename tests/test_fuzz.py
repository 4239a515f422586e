"""Property-based fuzzing of the decoder and of message handling at both ends.

Random and mutated frames must never raise anything but ProtocolError, never make
the decoder hold more than the largest frame, and never hang; the device must answer
every request it can parse and stay responsive, and the host must turn anything odd
into a DeviceError. ``make fuzz`` runs many more examples (LAMINA_FUZZ_EXAMPLES).
"""

from __future__ import annotations

import contextlib
import os
import queue
import threading
import time
import tracemalloc
from dataclasses import fields as dataclass_fields
from datetime import timedelta

import numpy as np
import pytest
import serial
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

from lamina_device.server import DeviceServer
from lamina_device.sim import open_sim
from lamina_host.link.client import DeviceClient
from lamina_host.link.errors import DeviceError
from lamina_host.link.handshake import read_welcome
from lamina_host.link.spawn import PtyBridge
from lamina_shared.limits import DeviceLimits
from lamina_shared.link import Channel
from lamina_shared.ops import OPS as SCHEMAS
from lamina_shared.ops import (
    ArgsError,
    ExtractChanges,
    MoveArgs,
    ScanArgs,
    UnknownOp,
    parse_args,
    request_args,
)
from lamina_shared.protocol import (
    MAX_PAYLOAD_BYTES,
    PROTOCOL_VERSION,
    FrameDecoder,
    Kind,
    Message,
    ProtocolError,
    cobs_encode,
    decode_frame,
    decode_message,
    encode_chunk,
    encode_frame,
    encode_json,
    encode_segment,
)
from lamina_shared.types import ScanPlan, Segment, ViewSpec
from tests.helpers.served import SilentStream

LIMITS = DeviceLimits()

EXAMPLES = int(os.environ.get("LAMINA_FUZZ_EXAMPLES", "150"))
FUZZ = settings(
    max_examples=EXAMPLES,
    deadline=timedelta(seconds=5),  # "never hang": any example this slow is a failure
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture],
)


def _valid_payloads() -> list[bytes]:
    n = 200
    segment = Segment(
        "object",
        1,
        2,
        2.0,
        45.0,
        np.arange(100, 100 + n, dtype=np.uint16),
        (np.arange(n) * 0.25 + 100).astype(np.float32),
        np.full(n, 120, np.uint8),
        np.full(n, 4, np.uint8),
    )
    frames = [
        encode_segment(3, 4, segment),
        encode_chunk(1, 2, 0, 600, b"x" * 512),
        encode_json(Kind.REQUEST, {"id": 5, "op": "scan", "args": {"target": "object"}}),
        encode_json(Kind.ACK, {"id": 5, "seqs": [1, 2], "lost": [0]}),
    ]
    return [decode_frame(f[1:-1]) for f in frames]


VALID = _valid_payloads()


@FUZZ
@given(st.binary(max_size=4096))
def test_random_payloads_raise_only_protocol_errors(payload):
    with contextlib.suppress(ProtocolError):
        decode_message(payload)


@FUZZ
@given(
    st.sampled_from(VALID),
    st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 255)), min_size=1, max_size=8),
    st.integers(0, 64),
)
def test_mutated_valid_messages_raise_only_protocol_errors(payload, edits, cut):
    data = bytearray(payload)
    for at, value in edits:
        data[at % len(data)] = value
    data = data[: max(1, len(data) - cut)]
    tracemalloc.start()
    try:
        decode_message(bytes(data))
    except ProtocolError:
        pass
    finally:
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
    # Allocation stays within a small multiple of the largest frame, whatever the header says.
    assert peak < 16 * MAX_PAYLOAD_BYTES


@FUZZ
@given(st.lists(st.binary(max_size=3000), max_size=20), st.sampled_from(VALID))
def test_decoder_recovers_after_any_garbage(garbage, payload):
    decoder = FrameDecoder()
    for piece in garbage:
        for found in decoder.feed(piece):
            with contextlib.suppress(ProtocolError):
                decode_message(found)
        assert len(decoder._buffer) <= FrameDecoder.MAX_ENCODED
    # Whatever came before, a fresh frame gets through (its leading delimiter resyncs).
    assert payload in decoder.feed(encode_frame(payload))


@FUZZ
@given(st.binary(min_size=1, max_size=2000), st.binary(min_size=4, max_size=4))
def test_frames_with_any_content_and_crc_raise_only_protocol_errors(data, crc):
    frame = cobs_encode(data + crc)
    assert b"\0" not in frame
    with contextlib.suppress(ProtocolError):
        decode_message(decode_frame(frame))


JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=20),
    lambda inner: (
        st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4)
    ),
    max_leaves=12,
)
OPS = st.sampled_from(
    ["scan", "fetch", "move", "pause", "resume", "abort", "status", "grab_grid", "nope", ""]
)
ARG_KEYS = st.sampled_from(
    ["target", "plan", "have", "axis", "position", "transfer", "ranges", "laser"]
)


@pytest.fixture(scope="module")
def device():
    """A device server driven message by message, answering over a real pty link."""
    bridge = PtyBridge()
    hardware = open_sim(noise="none")
    device_port = serial.Serial(bridge.device_port, timeout=0.02)
    host_port = serial.Serial(bridge.host_port, timeout=0.02)
    server = DeviceServer(Channel(device_port), hardware)
    host = Channel(host_port)
    inbox: queue.Queue[Message] = queue.Queue()
    stop = threading.Event()

    def drain() -> None:
        # Read the host end all the time, as a host does, so the device never blocks.
        while not stop.is_set():
            message = host.receive(0.05)
            if message is not None:
                inbox.put(message)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    _new_session(server, inbox)  # each WELCOME is taken by the HELLO that asked for it
    yield server, inbox
    server._stop_worker()
    stop.set()
    reader.join(timeout=5)
    host_port.close()
    device_port.close()
    hardware.close()
    bridge.close()


def _replies(inbox: queue.Queue[Message], request_id: int, timeout_s: float = 10.0) -> dict:
    """Return the reply to ``request_id``, or a long request's "busy" status event."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        try:
            message = inbox.get(timeout=0.05)
        except queue.Empty:
            continue
        if message.kind not in (Kind.REPLY, Kind.EVENT):
            continue
        if message.body.get("id") != request_id:
            continue
        if message.kind is Kind.REPLY:
            return message.body
        if message.body.get("event") == "status":
            return {"ok": True, "result": message.body}
    raise AssertionError(f"no reply to request {request_id}")


def _new_session(server: DeviceServer, inbox: queue.Queue[Message]) -> None:
    """Say HELLO anew and drop what the device sent before its WELCOME (a late reply of an
    earlier example, under an id this one may draw again).

    Every HELLO to the module's device goes through here, so the WELCOME reached is this
    one's: the earlier ones were taken by their own HELLOs.
    """
    server.handle(
        Message(Kind.HELLO, {"protocol": PROTOCOL_VERSION, "session": f"fuzz-{time.monotonic()}"})
    )
    deadline = time.monotonic() + 10
    while inbox.get(timeout=max(0.0, deadline - time.monotonic())).kind is not Kind.WELCOME:
        pass


DEVICE_REFUSALS = frozenset({"bad-args", "limit", "busy", "idle", "aborted", "gone", "failed"})
"""What a device may answer a well-formed request: the state it is in ("busy", "idle"...),
or what only it knows (no default plan, a camera without colour, views beyond its plan)."""


def _schema_refusal(op: object, args: object, limits: DeviceLimits) -> tuple[str, str] | None:
    """Return the (code, message) the op schemas refuse the request with, or None."""
    try:
        parse_args(op, args, limits)
    except UnknownOp as exc:
        return "unknown-op", str(exc)
    except ArgsError as exc:
        return exc.code, str(exc)
    return None


@FUZZ
@given(
    st.integers(1, 2**31),
    OPS,
    st.dictionaries(ARG_KEYS, JSON, max_size=4),
    st.sampled_from([Kind.REQUEST, Kind.ACK, Kind.HEARTBEAT, Kind.CHUNK, Kind.REPLY]),
    JSON,
)
def test_device_answers_any_request_and_stays_responsive(device, request_id, op, args, kind, junk):
    server, host = device
    # A new session per example: request ids repeat across examples, and within one
    # session the device rightly answers a repeated id from its reply cache.
    _new_session(server, host)
    if isinstance(args.get("plan"), dict | list):
        args["plan"] = {"views": [{"section": 0, "z_mm": 0.0, "angle_deg": 0.0}]}
    # Unsolicited or malformed messages of other kinds are ignored without harm.
    server.handle(Message(kind, junk if isinstance(junk, dict) else {"junk": junk}))
    schema_refusal = _schema_refusal(op, args, server.settings.limits)
    server.handle(Message(Kind.REQUEST, {"id": request_id, "op": op, "args": args}))
    reply = _replies(host, request_id)
    assert isinstance(reply["ok"], bool)
    event("refused by its schema" if schema_refusal else f"well-formed, ok={reply['ok']}")
    if schema_refusal is not None:
        # Refused for exactly the reason its schema names, and that reason is a sentence.
        assert not reply["ok"] and set(reply["error"]) == {"code", "message"}, reply
        assert (reply["error"]["code"], reply["error"]["message"]) == schema_refusal
        assert schema_refusal[1].strip()
    elif not reply["ok"]:
        # A well-formed request may meet the device's state or its own plans and camera,
        # never a refusal of its form, and never a fault of the device.
        assert set(reply["error"]) == {"code", "message"}, reply
        assert reply["error"]["code"] in DEVICE_REFUSALS and reply["error"]["message"].strip()
    # Still responsive: a status request gets its answer.
    server.handle(Message(Kind.REQUEST, {"id": request_id + 1, "op": "status"}))
    status = _replies(host, request_id + 1)
    assert status["ok"] and status["result"]["state"] in ("idle", "busy", "paused")
    server._stop_worker()
    server.hardware.laser.off()


@FUZZ
@given(st.dictionaries(st.text(max_size=20), JSON, max_size=8), JSON, JSON, JSON)
def test_host_turns_any_welcome_into_info_or_device_error(body, image_size, plans, protocol):
    body = {**body, "image_size": image_size, "default_plans": plans, "protocol": protocol}
    for candidate in (body, {**body, "protocol": PROTOCOL_VERSION, "hardware": "x"}):
        try:
            info = read_welcome(candidate)
        except DeviceError:
            continue
        if info.protocol == PROTOCOL_VERSION:
            assert 0 < info.image_size[0] <= 16_384 and 0 < info.image_size[1] <= 16_384


@FUZZ
@given(JSON, st.integers(0, 2**32 - 1))
def test_host_refuses_odd_replies_with_device_error(result, request_id):
    client = DeviceClient(Channel(SilentStream()))
    from lamina_host.link.client import _result

    for body in (
        {"id": request_id, "ok": True, "result": result},
        {"id": request_id, "ok": False, "error": result},
        {"id": request_id, "ok": result},
    ):
        try:
            value = _result("scan", body)
        except DeviceError:
            continue
        assert isinstance(value, dict)
    assert client.stats.request_retries == 0


@pytest.mark.wall_clock
def test_a_frame_that_decodes_slowly_does_not_exist():
    """The worst case the decoder can meet: a maximal frame of the costliest kind."""
    worst = [
        bytes([Kind.SEGMENT]) + b"\xff" * (MAX_PAYLOAD_BYTES - 1),
        bytes([Kind.REQUEST]) + b"[" * (MAX_PAYLOAD_BYTES - 1),
        bytes([Kind.SEGMENT]) + bytes(31) + b"\xff\xff" + b"\x80" * (MAX_PAYLOAD_BYTES - 40),
    ]
    for payload in worst:
        start = time.perf_counter()
        with pytest.raises(ProtocolError):
            decode_message(payload)
        assert time.perf_counter() - start < 1.0


def test_fuzzing_a_live_scan_request_keeps_the_device_alive(device):
    """A scan started by fuzzed arguments is stopped cleanly by the next session."""
    server, host = device
    plan = ScanPlan.regular(1, 2.0, 2)
    server.handle(
        Message(
            Kind.REQUEST,
            {"id": 7, "op": "scan", "args": {"target": "object", "plan": plan.to_dict()}},
        )
    )
    done = threading.Event()

    def ack_all() -> None:
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not done.is_set():
            try:
                message = host.get(timeout=0.05)
            except queue.Empty:
                continue
            if message.kind is Kind.SEGMENT:
                server.handle(Message(Kind.ACK, {"id": 7, "seqs": [message.body.seq]}))
            if message.kind is Kind.REPLY and message.body.get("id") == 7:
                assert message.body["ok"], message.body
                done.set()

    ack_all()
    assert done.is_set()


# --- the typed operation schemas (lamina_shared.ops) -----------------------------------

HOSTILE = st.recursive(
    st.none()
    | st.booleans()
    | st.integers()
    | st.integers(min_value=10**300, max_value=10**400)
    | st.floats()  # NaN and infinities included
    | st.text(max_size=20)
    | st.sampled_from(["lift", "turntable", "object", "cylinder"]),
    lambda inner: (
        st.lists(inner, max_size=6) | st.dictionaries(st.text(max_size=10), inner, max_size=5)
    ),
    max_leaves=20,
)
OP_NAMES = st.sampled_from([*SCHEMAS, "nope", ""]) | HOSTILE
ARG_NAMES = st.sampled_from(
    [
        *sorted({f.name for spec in SCHEMAS.values() for f in dataclass_fields(spec.args_type)}),
        "regular",
        "views",
        "x",
    ]
)


@FUZZ
@given(OP_NAMES, st.dictionaries(ARG_NAMES, HOSTILE, max_size=4) | HOSTILE)
def test_op_schemas_return_typed_args_or_list_problems(op, args):
    """Any op name and arguments: the op's dataclass, or ArgsError/UnknownOp, nothing else."""
    try:
        parsed = parse_args(op, args, LIMITS)
    except UnknownOp as exc:
        assert not (isinstance(op, str) and op in SCHEMAS)
        assert len(str(exc)) < 400
        return
    except ArgsError as exc:
        assert exc.problems and exc.code in ("bad-args", "limit")
        # The refusal always fits one REPLY, however many problems there were.
        reply = encode_json(Kind.REPLY, {"id": 1, "ok": False, "error": {"message": str(exc)}})
        assert len(reply) < MAX_PAYLOAD_BYTES
        return
    assert isinstance(parsed, SCHEMAS[op].args_type)
    # What was accepted is plain and within the limits: it travels back unchanged.
    assert parse_args(op, request_args(parsed), LIMITS) == parsed


@FUZZ
@given(
    st.sampled_from(["lift", "turntable"]),
    st.floats(-200.0, 200.0),
    st.integers(1, 60),  # plans of the advertised maximum: tests/test_hostile_device.py
    st.floats(0.001, 3.0),
    st.integers(1, 36),
)
def test_typed_requests_round_trip(axis, position, sections, pitch_mm, views):
    move = MoveArgs(axis, position)
    assert parse_args("move", request_args(move), LIMITS) == move
    plan = ScanPlan.regular(sections, pitch_mm, views)
    wire = plan.to_wire()
    assert "regular" in wire and len(str(wire)) < 200
    assert ScanPlan.from_dict(wire) == plan
    if len(plan.views) <= LIMITS.max_views:
        scan = ScanArgs("object", plan, (0,))
        assert parse_args("scan", request_args(scan), LIMITS) == scan
        changes = ExtractChanges((("method", "thinning"), ("threshold", None), ("power", pitch_mm)))
        scan = ScanArgs("object", plan, (0,), changes)
        assert parse_args("scan", request_args(scan), LIMITS) == scan


@FUZZ
@given(
    st.lists(
        st.tuples(st.integers(0, 999), st.floats(0.0, 200.0), st.floats(-720.0, 720.0)),
        min_size=1,
        max_size=40,
    )
)
def test_listed_plans_are_accepted_or_every_problem_named(items):
    plan = ScanPlan(tuple(ViewSpec(s, z, a) for s, z, a in items))
    wire = plan.to_wire()
    try:
        args = parse_args("scan", {"target": "object", "plan": wire}, LIMITS)
    except ArgsError as exc:
        assert all("duplicate" in p or "the height of section" in p for p in exc.problems), (
            exc.problems
        )
        return
    assert args.plan == plan
