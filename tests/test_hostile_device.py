"""A hostile host cannot end the device: every class of bad request, over the real pty link.

Each test tries a whole class (every operation, every argument, several probes each)
and then checks the device is still up: a later normal request gets its answer. The
device runs in this process on its own thread, as in tests/test_link.py; the host end
sends raw frames so that it can say what no well-behaved host would.
"""

from __future__ import annotations

import json
import logging
import queue
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import serial

from lamina_device.camera import CameraError
from lamina_device.hardware import Hardware
from lamina_device.server import DeviceServer, ServerSettings
from lamina_device.sim import open_sim
from lamina_host.link.client import DeviceClient
from lamina_host.link.errors import RequestRefused
from lamina_host.link.spawn import PtyBridge
from lamina_shared.capture import load_capture
from lamina_shared.limits import DeviceLimits
from lamina_shared.link import Channel
from lamina_shared.ops import OPS, plan_fits
from lamina_shared.protocol import (
    MAX_PAYLOAD_BYTES,
    PROTOCOL_VERSION,
    Kind,
    Message,
    encode_frame,
    encode_json,
)
from lamina_shared.types import ScanPlan, ViewSpec
from tests.helpers.served import Served, SilentStream, link, reference, serve

LIMITS = DeviceLimits()
BASELINE: dict[str, dict[str, Any]] = {
    "fetch": {"transfer": 1, "ranges": [[0, 1]]},
    "move": {"axis": "lift", "position": 1.0},
    "scan": {"target": "object"},
}
"""Valid arguments of each operation with required ones (the others take ``{}``)."""
INF = object()  # stands for the JSON text 1e999, which Python's json reads as infinity
HOSTILE_VALUES: list[Any] = [
    10**400,
    -(10**400),
    INF,
    "x" * 20_000,
    {"a": {"b": {"c": {"d": [1]}}}},
    [[[[[[[]]]]]]],
    [0] * 12_000,
]
"""Wrong for every argument of every operation, whatever its type."""


@dataclass
class Ends:
    server: DeviceServer
    hardware: Hardware
    host: Channel
    inbox: queue.Queue[Message]
    thread: threading.Thread
    next_id: int = 1

    def send_raw(self, body_text: str) -> None:
        """Send a REQUEST whose JSON text is given as is."""
        self.host.send(encode_frame(bytes([Kind.REQUEST]) + body_text.encode()))

    def request(self, op: Any, args: Any = None, timeout_s: float = 20.0) -> dict[str, Any]:
        """Send one request (``INF`` anywhere in ``args`` becomes 1e999); return its reply."""
        request_id = self.next_id
        self.next_id += 1
        body: dict[str, Any] = {"id": request_id, "op": op}
        if args is not None:
            body["args"] = args
        text = json.dumps(body, default=lambda o: "__INF__").replace('"__INF__"', "1e999")
        self.send_raw(text)
        return self.reply(request_id, timeout_s)

    def reply(self, request_id: int, timeout_s: float = 20.0) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            try:
                message = self.inbox.get(timeout=0.05)
            except queue.Empty:
                continue
            if message.kind is Kind.REPLY and message.body.get("id") == request_id:
                return message.body
        raise AssertionError(f"no reply to request {request_id}")

    def assert_up(self) -> None:
        """The device answers a normal request and its program is still running."""
        assert self.thread.is_alive()
        reply = self.request("status")
        assert reply["ok"], reply
        assert reply["result"]["state"] in ("idle", "busy", "paused")

    def hello(self, session: str) -> None:
        self.host.send(encode_json(Kind.HELLO, {"protocol": PROTOCOL_VERSION, "session": session}))


@contextmanager
def device(
    settings: ServerSettings | None = None,
    transform: Callable[[bytes, str], bytes] | None = None,
    write_timeout_s: float = 10.0,
) -> Iterator[Ends]:
    """A sim device served over a pty bridge, greeted by a host that reads all the time."""
    with serve(transform, settings, write_timeout_s=write_timeout_s) as served:
        yield from _greeted(served)


def _greeted(served: Served) -> Iterator[Ends]:
    server, host = served.server, Channel(served.host_port)
    inbox: queue.Queue[Message] = queue.Queue()
    reading = threading.Event()
    reading.set()
    stop = threading.Event()

    def drain() -> None:
        while not stop.is_set():
            if not reading.is_set():
                time.sleep(0.01)
                continue
            message = host.receive(0.05)
            if message is not None:
                inbox.put(message)

    reader = threading.Thread(target=drain, daemon=True)
    reader.start()
    ends = Ends(server, served.hardware, host, inbox, served.thread)
    ends.hello("hostile")
    deadline = time.monotonic() + 10
    while not server.greeted and time.monotonic() < deadline:
        time.sleep(0.01)
    try:
        yield ends
    finally:
        stop.set()
        reader.join(timeout=5)


def _refused(reply: dict[str, Any], *codes: str) -> str:
    assert reply["ok"] is False, reply
    assert reply["error"]["code"] in codes, reply
    message = reply["error"]["message"]
    assert "\n" not in message and len(message) < 4000, message
    return message


# --- A. every argument of every operation --------------------------------------------


def test_every_argument_of_every_op_refuses_every_hostile_value():
    probes = 0
    with device() as ends:
        for name, spec in OPS.items():
            base = BASELINE.get(name, {})
            for item in fields(spec.args_type):
                wrong_type: list[Any] = [1] if item.type in ("bool", bool) else [True, "12"]
                for value in [*HOSTILE_VALUES, *wrong_type]:
                    reply = ends.request(name, {**base, item.name: value})
                    message = _refused(reply, "bad-args", "limit")
                    assert item.name in message, (name, item.name, message)
                    probes += 1
            ends.assert_up()
        assert not ends.hardware.laser.is_on
        assert ends.hardware.camera.frames_taken == 0  # nothing acted on a bad request
    assert probes > 80


def test_unknown_missing_and_malformed_arguments_of_every_op():
    with device() as ends:
        for name, spec in OPS.items():
            base = BASELINE.get(name, {})
            message = _refused(ends.request(name, {**base, "zz_extra": 1}), "bad-args")
            assert "takes no argument 'zz_extra'" in message
            # Several problems at once: every one is listed.
            message = _refused(ends.request(name, {**base, "zz_a": 1, "zz_b": 2}), "bad-args")
            assert "'zz_a'" in message and "'zz_b'" in message
            for required in base:
                partial = {k: v for k, v in base.items() if k != required}
                message = _refused(ends.request(name, partial), "bad-args")
                assert f"{required} is required" in message
            for args in ([], "args", 10**400, [[{"deep": [[[]]]}]], True):
                _refused(ends.request(name, args), "bad-args")
            if fields(spec.args_type):
                many = {f"k{i}": i for i in range(500)}
                message = _refused(ends.request(name, {**base, **many}), "bad-args")
                assert "more" in message  # 500 unknown keys: named up to a point, then counted
        ends.assert_up()


def test_unknown_ops_and_bad_request_ids():
    with device() as ends:
        for op in (
            "format_disk",
            "",
            None,
            10**400,
            ["scan"],
            {"op": "scan"},
            "scan\u0000",
            "x" * 5000,
        ):
            message = _refused(ends.request(op, {}), "unknown-op")
            assert len(message) < 400
        # A request without a usable id cannot be answered; it is ignored, harmlessly.
        for bad_id in ("10" * 300, '"1"', "true", "-1", "1.5", "null", "1e999"):
            ends.send_raw(f'{{"id": {bad_id}, "op": "move", "args": {{}}}}')
        for text in ("[1, 2]", '"scan"', "{" * 30_000, '{"id": 1e999}', "NaN", "\xff\xfe"):
            ends.send_raw(text)
        # Acknowledgements and heartbeats of any shape are ignored, harmlessly.
        for body in (
            {"id": 10**400, "seqs": [1]},
            {"id": 1, "seqs": [True, -1, 10**400, "3", None], "lost": [[1]]},
            {"id": 1, "seqs": list(range(5000))},
            {"id": 1, "seqs": "all", "lost": {"a": 1}},
        ):
            ends.host.send(encode_json(Kind.ACK, body))
        for body in ({"session": 10**400}, {"state": {"deep": [[[]]]}}, {}):
            ends.host.send(encode_json(Kind.HEARTBEAT, body))
        ends.assert_up()
        # A HELLO of another protocol, or with a hostile session, is answered, not fatal.
        for body in ({"protocol": 10**400}, {"protocol": 2, "session": {"x": [1]}}):
            ends.host.send(encode_json(Kind.HELLO, body))
        ends.hello("hostile again")
        deadline = time.monotonic() + 5
        while not ends.server.greeted and time.monotonic() < deadline:
            time.sleep(0.01)
        ends.assert_up()


def test_giant_position_from_the_issue_leaves_the_device_up():
    """The original probe: a CRC-valid move whose position has 401 digits."""
    with device() as ends:
        for position in (10**400, -(10**400), 2**1024, INF, 1e308, -1e308):
            message = _refused(
                ends.request("move", {"axis": "lift", "position": position}), "bad-args"
            )
            assert "move.position" in message
        for position in (1e308, 250.0, -1.0):
            # Finite and small enough to read, but beyond the axis: the soft limits refuse.
            reply = ends.request(
                "move", {"axis": "turntable" if position == 1e308 else "lift", "position": position}
            )
            _refused(reply, "bad-args", "limit")
        assert (
            ends.request("move", {"axis": "lift", "position": 12.5})["result"]["position"] == 12.5
        )
        assert ends.hardware.lift.z_mm == 12.5
        ends.assert_up()


def test_plans_are_validated_completely_before_anything_moves():
    views = [{"section": 0, "z_mm": 0.0, "angle_deg": float(a)} for a in (0, 90, 180, 360)]
    bad_plans = {
        "0 and 360 deg": ({"views": views}, "duplicate (section 0, angle 360.0 deg)"),
        "same height": (
            {
                "views": [
                    {"section": 0, "z_mm": 2.0, "angle_deg": 0.0},
                    {"section": 1, "z_mm": 2.0, "angle_deg": 0.0},
                ]
            },
            "the height of section 0",
        ),
        "section": ({"views": [{"section": 1000, "z_mm": 0.0, "angle_deg": 0.0}]}, "0..999"),
        "huge section": (
            {"views": [{"section": 10**400, "z_mm": 0.0, "angle_deg": 0.0}]},
            "section",
        ),
        "bool z": ({"views": [{"section": 0, "z_mm": True, "angle_deg": 0.0}]}, "z_mm"),
        "extra key": ({"views": [{"section": 0, "z_mm": 0, "angle_deg": 0, "x": 1}]}, "'x'"),
        "missing key": ({"views": [{"section": 0, "z_mm": 0}]}, "angle_deg is required"),
        "empty": ({"views": []}, "0 items"),
        "too many": ({"regular": {"sections": 101, "pitch_mm": 1.0, "views": 100}}, "10100 views"),
        "sections": ({"regular": {"sections": 1001, "pitch_mm": 0.1, "views": 1}}, "1..1000"),
        "per section": ({"regular": {"sections": 1, "pitch_mm": 1.0, "views": 361}}, "1..360"),
        "pitch": ({"regular": {"sections": 2, "pitch_mm": -1.0, "views": 2}}, "pitch_mm"),
        "nan pitch": ({"regular": {"sections": 2, "pitch_mm": INF, "views": 2}}, "pitch_mm"),
        "both forms": (
            {"regular": {"sections": 1, "pitch_mm": 1.0, "views": 1}, "views": []},
            "views",
        ),
        "above axis": ({"regular": {"sections": 3, "pitch_mm": 150.0, "views": 2}}, "soft limits"),
    }
    with device() as ends:
        for label, (plan, expected) in bad_plans.items():
            message = _refused(
                ends.request("scan", {"target": "object", "plan": plan}), "bad-args", "limit"
            )
            assert expected in message, (label, message)
        # Every bad view of a plan is named at once, and a long list is cut, not sent whole.
        many = [{"section": 0, "z_mm": -k, "angle_deg": True} for k in range(1000)]
        message = _refused(
            ends.request("scan", {"target": "object", "plan": {"views": many}}), "bad-args"
        )
        assert "plan.views[0].angle_deg" in message and "plan.views[1].angle_deg" in message
        assert message.endswith("; and 988 more")  # all counted, the first twelve named
        have = _refused(ends.request("scan", {"target": "object", "have": [40]}), "bad-args")
        assert "view indices" in have
        assert ends.hardware.camera.frames_taken == 0
        ends.assert_up()


# --- A. faults inside an operation ---------------------------------------------------


@pytest.mark.parametrize(
    "error", [ValueError, KeyError, TypeError, ZeroDivisionError, AssertionError, IndexError]
)
def test_a_bug_inside_an_op_is_logged_and_answered_internal(error, caplog):
    def broken(*args: Any, **kwargs: Any) -> None:
        raise error("a bug in the device program")

    with device() as ends, caplog.at_level(logging.ERROR, logger="lamina_device.server"):
        ends.hardware.lift.move_to = broken  # type: ignore[method-assign]
        message = _refused(ends.request("move", {"axis": "lift", "position": 3.0}), "internal")
        assert error.__name__ in message and "device log" in message
        real_capture = ends.hardware.camera.capture
        ends.hardware.camera.capture = broken  # type: ignore[method-assign]
        _refused(ends.request("preview", {"laser": True}), "internal")
        assert not ends.hardware.laser.is_on
        ends.hardware.camera.capture = real_capture  # type: ignore[method-assign]
        ends.assert_up()
        assert ends.request("preview", {"stripe": True})["ok"]
    logged = [r for r in caplog.records if r.levelno == logging.ERROR]
    assert len(logged) == 2 and all(r.exc_info and r.exc_info[0] is error for r in logged)


def test_a_hardware_fault_is_still_a_failure_not_a_bug(caplog):
    def jammed(*args: Any, **kwargs: Any) -> None:
        raise CameraError("sensor stalled")

    with device() as ends:
        ends.hardware.camera.capture = jammed  # type: ignore[method-assign]
        message = _refused(ends.request("preview", {}), "failed")
        assert "sensor stalled" in message
        ends.assert_up()
    assert not [r for r in caplog.records if r.levelno >= logging.ERROR]


# --- A. a host that stops reading --------------------------------------------------------


def test_a_host_that_stops_reading_is_forgotten_and_the_device_waits_for_hello():
    stalled = threading.Event()

    def line(data: bytes, direction: str) -> bytes:
        # A host that stops reading: nothing it sends or should receive moves on.
        while stalled.is_set():
            time.sleep(0.01)
        return data

    with device(transform=line, write_timeout_s=0.5) as ends:
        plan = ScanPlan.regular(4, 2.0, 8)
        ends.send_raw(
            json.dumps(
                {"id": 500, "op": "scan", "args": {"target": "object", "plan": plan.to_wire()}}
            )
        )
        deadline = time.monotonic() + 10
        while ends.server._running_id != 500 and time.monotonic() < deadline:
            time.sleep(0.01)
        stalled.set()
        deadline = time.monotonic() + 30
        while ends.server.greeted and time.monotonic() < deadline:
            time.sleep(0.05)
        assert not ends.server.greeted, "the device never noticed the host had gone"
        assert ends.thread.is_alive() and ends.server.running
        assert not ends.hardware.laser.is_on
        time.sleep(1.0)  # more than link_retries x 0.5 s: still no exit while it waits
        assert ends.thread.is_alive()
        stalled.clear()
        ends.hello("back again")
        deadline = time.monotonic() + 10
        while not ends.server.greeted and time.monotonic() < deadline:
            time.sleep(0.01)
        ends.assert_up()
        assert ends.request("status")["result"]["state"] == "idle"


def _serve(port: str) -> subprocess.Popen[bytes]:
    command = [sys.executable, "-m", "lamina_device", "serve", "--port", port, "--hardware", "sim"]
    return subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


@contextmanager
def _device_program() -> Iterator[tuple[PtyBridge, subprocess.Popen[bytes]]]:
    """``lamina-device serve`` on the sim rig in its own process, behind a pty bridge."""
    bridge = PtyBridge()
    process = _serve(bridge.device_port)
    try:
        yield bridge, process
    finally:
        if process.poll() is None:
            process.kill()
        process.wait()
        bridge.close()


def test_serve_exits_non_zero_when_its_port_is_gone_and_zero_on_shutdown():
    with _device_program() as (bridge, process):
        with serial.Serial(bridge.host_port, timeout=0.05) as port:
            client = DeviceClient(Channel(port), process)
            client.hello()
        bridge.close()  # the cable and the port go away for good
        assert process.wait(timeout=30) == 1
        assert client.stderr_tail is not None  # the client reads the program's stderr
        err = "\n".join(client.stderr_tail.lines())
        assert "serial port stays unusable" in err and "Traceback" not in err
    with _device_program() as (bridge, process):
        with serial.Serial(bridge.host_port, timeout=0.05) as port:
            client = DeviceClient(Channel(port), process)
            client.hello()
            client.close()  # asks the device to shut down
        assert process.returncode == 0


# --- A. every advertised size works end to end -------------------------------------------


@pytest.mark.parametrize(
    ("sections", "pitch_mm", "views"),
    [
        (LIMITS.max_sections, 0.2, LIMITS.max_views // LIMITS.max_sections),
        (LIMITS.max_views // LIMITS.max_views_per_section, 7.0, LIMITS.max_views_per_section),
    ],
)
def test_a_plan_at_the_advertised_maximum_crosses_the_link_and_resumes(sections, pitch_mm, views):
    plan = ScanPlan.regular(sections, pitch_mm, views)
    assert len(plan.views) <= LIMITS.max_views and len(plan.views) >= 0.97 * LIMITS.max_views
    assert plan_fits(plan, LIMITS) == []
    have = set(range(len(plan.views) - 2))  # a resume: the request carries ~10,000 indices
    with link() as ends:
        client, info = ends.client, ends.info
        for key in (
            "max_views",
            "max_sections",
            "max_views_per_section",
            "max_fetch_bytes",
            "max_payload_bytes",
            "chunk_bytes",
            "window_segments",
            "heartbeat_s",
        ):
            assert getattr(info.limits, key) == getattr(LIMITS, key)
        got = client.scan("object", plan, have=have)
        expected = reference(ScanPlan(plan.views[-2:]))
        assert len(got) == 2
        for segment, truth, view in zip(got, expected, plan.views[-2:], strict=True):
            assert (segment.section, segment.z_mm, segment.angle_deg) == (
                view.section,
                view.z_mm,
                view.angle_deg,
            )
            assert np.array_equal(segment.rows, truth.rows) and np.array_equal(
                segment.cols, truth.cols
            )
        # One view more is refused up front, with the limit named.
        if views < LIMITS.max_views_per_section:
            bigger = ScanPlan.regular(sections, pitch_mm, views + 1)
        else:
            bigger = ScanPlan.regular(sections + 1, pitch_mm, views)
        with pytest.raises(RequestRefused, match="allowed"):
            client.scan("object", bigger)
        assert client.request("status")["state"] == "idle"


def test_an_irregular_plan_too_long_for_one_message_is_caught_before_sending():
    irregular = ScanPlan(
        tuple(ViewSpec(s, s * 0.1, 7.3 * v + 0.01 * s) for s in range(300) for v in range(10))
    )
    problems = plan_fits(irregular, LIMITS)
    assert problems and "use a regular plan" in problems[0]
    small = ScanPlan(irregular.views[:200])
    assert plan_fits(small, LIMITS) == []


def test_a_default_plan_too_long_for_the_welcome_is_left_out_not_fatal():
    hardware = open_sim("cylinder:d=19.05")
    try:
        irregular = ScanPlan(
            tuple(ViewSpec(s, s * 0.1, 7.3 * v + 0.01 * s) for s in range(1000) for v in range(10))
        )
        hardware.default_plans["object"] = irregular
        server = DeviceServer(Channel(SilentStream()), hardware)
        info = server.info()
        assert "object" not in info.default_plans and "cylinder" in info.default_plans
        assert len(encode_json(Kind.WELCOME, server.welcome())) < MAX_PAYLOAD_BYTES
    finally:
        hardware.close()


# --- A. identity ---------------------------------------------------------------------------


def test_identity_names_the_device_and_what_it_images(tmp_path):
    def identity(**kwargs: Any) -> dict[str, str]:
        hardware = open_sim(**kwargs)
        try:
            return DeviceServer(Channel(SilentStream()), hardware).welcome()["identity"]
        finally:
            hardware.close()

    base = identity(object_spec="cylinder:d=19.05")
    assert base["serial"] == "sim"
    assert identity(object_spec="cylinder:d=19.05") == base
    variants = [
        identity(object_spec="cylinder:d=20"),
        identity(object_spec="cylinder:d=19.05", seed=1),
        identity(object_spec="cylinder:d=19.05", noise="none"),
        identity(object_spec="cylinder:d=19.05", rig_name="limb"),
        identity(object_spec="ellipsoid:a=10,b=6.5,c=20,z=-1"),
    ]
    assert len({v["source"] for v in [base, *variants]}) == 6


def test_pi_serial_is_read_from_the_device_tree_or_cpuinfo(tmp_path):
    from lamina_device.hardware import pi_serial

    tree = tmp_path / "serial-number"
    tree.write_bytes(b"10000000abcdef01\x00")
    cpuinfo = tmp_path / "cpuinfo"
    cpuinfo.write_text("processor\t: 0\nHardware\t: BCM2835\nSerial\t\t: 00000000deadbeef\n")
    assert pi_serial((tree, cpuinfo)) == "10000000abcdef01"
    assert pi_serial((tmp_path / "absent", cpuinfo)) == "00000000deadbeef"
    assert pi_serial((tmp_path / "absent",)) == "unknown"


def test_welcome_reports_the_extraction_settings():
    from lamina_device.extract import ExtractSettings

    hardware = open_sim()
    try:
        info = DeviceServer(Channel(SilentStream()), hardware).welcome()
    finally:
        hardware.close()
    assert ExtractSettings(**info["extract"]) == ExtractSettings()


# --- C. lamina-device record -----------------------------------------------------------------


def _record(capsys: pytest.CaptureFixture[str], out: Path, *args: str) -> tuple[int, list[str]]:
    from lamina_device.cli import main

    status = main(["record", "--hardware", "sim", "--noise", "none", "--out", str(out), *args])
    err = capsys.readouterr().err
    assert "Traceback" not in err
    return status, err.splitlines()


@pytest.mark.parametrize(
    ("args", "expected"),
    [
        (["--sections", "1000", "--views", "100"], ["100000 views, at most 10000 allowed"]),
        (["--sections", "1001", "--pitch", "0.1"], ["--sections: 1001 is outside 1..1000"]),
        (["--views", "361"], ["--views: 361 is outside 1..360"]),
        (["--pitch", "nan"], ["object --pitch: nan is not a finite number"]),
        (["--pitch", "-2"], ["object --pitch: -2.0 is outside 0..10000"]),
        (["--pitch", "0"], ["object --pitch: a positive number of mm is required"]),
        (
            ["--sections", "0", "--views", "0", "--cylinder-views", "400"],
            [
                "object --sections: 0 is outside",
                "object --views: 0 is outside",
                "cylinder --cylinder-views: 400 is outside 1..360",
            ],
        ),
        (
            ["--cylinder-sections", "0", "--cylinder-pitch", "-1"],
            [
                "cylinder --cylinder-sections: 0 is outside",
                "cylinder --cylinder-pitch: -1.0 is outside",
            ],
        ),
    ],
)
def test_record_refuses_plans_beyond_the_limits_up_front(capsys, tmp_path, args, expected):
    out = tmp_path / "capture"
    status, lines = _record(capsys, out, *args)
    assert status == 2 and len(lines) == 1, lines
    assert lines[0].startswith("lamina-device: record refused:")
    for text in expected:
        assert text in lines[0], lines[0]
    assert not out.exists()  # nothing written


def test_record_refuses_an_occupied_folder_and_deletes_nothing(capsys, tmp_path):
    out = tmp_path / "capture"
    out.mkdir()
    (out / "notes.txt").write_text("the operator's notes")
    status, lines = _record(capsys, out, "--sections", "1", "--views", "2")
    assert (
        status == 2
        and len(lines) == 1
        and "is not empty" in lines[0]
        and "--into-nonempty" in lines[0]
    )
    assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    file_out = tmp_path / "a-file"
    file_out.write_text("x")
    status, lines = _record(capsys, file_out, "--sections", "1", "--views", "2")
    assert status == 2 and "is a file" in lines[0] and file_out.read_text() == "x"
    status, lines = _record(
        capsys, out, "--sections", "2", "--views", "2", "--cylinder-views", "2", "--into-nonempty"
    )
    assert status == 0
    assert (out / "notes.txt").read_text() == "the operator's notes"
    assert load_capture(out).plan("object") == ScanPlan.regular(2, 2.0, 2)
    status, lines = _record(capsys, out, "--sections", "1", "--views", "2", "--into-nonempty")
    assert status == 2 and "already holds a capture" in lines[0]


def test_record_reports_progress_per_section(capsys, tmp_path):
    status, lines = _record(
        capsys, tmp_path / "capture", "--sections", "3", "--views", "2", "--cylinder-views", "2",
        "--cylinder-sections", "2",
    )  # fmt: skip
    assert status == 0
    assert lines == [
        "recording cylinder: section 0 done, 2/4 views",
        "recording cylinder: section 1 done, 4/4 views",
        "recording object: section 0 done, 2/6 views",
        "recording object: section 1 done, 4/6 views",
        "recording object: section 2 done, 6/6 views",
    ]


def test_a_hostile_capture_is_refused_by_the_device_with_every_problem(capsys, tmp_path):
    from lamina_device.cli import main

    out = tmp_path / "capture"
    status, _ = _record(capsys, out, "--sections", "2", "--views", "2", "--cylinder-views", "2")
    assert status == 0
    manifest = json.loads((out / "capture.json").read_text())
    manifest["scan"]["views"][0]["z_mm"] = -1.0
    manifest["scan"]["views"][1]["angle_deg"] = 360.0
    manifest["scan"]["views"][2]["section"] = 10**400
    (out / "capture.json").write_text(json.dumps(manifest))
    status = main(["serve", "--port", "/dev/null", "--hardware", f"replay:{out}"])
    err = capsys.readouterr().err.splitlines()
    assert status == 2 and "Traceback" not in "\n".join(err)
    assert err[-1].startswith(f"lamina-device: capture {out} is not usable (4 problem(s)): ")
    assert err[:-1] == [
        "  - scan.views[0].z_mm: -1.0 is outside 0..10000",
        "  - scan.views[1]: duplicate (section 0, angle 360.0 deg), the same view as scan.views[0]",
        "  - scan.views[2].section: a huge integer is outside 0..999",
        "  - scan.views[3]: section 1 is at z_mm 2.0, the height of section a huge integer",
    ]
    (out / "capture.json").write_text("[" * 100_000)
    status = main(["serve", "--port", "/dev/null", "--hardware", f"replay:{out}"])
    err = capsys.readouterr().err.splitlines()
    assert status == 2 and len(err) == 2 and "nested too deeply" in err[1]
    assert err[1].startswith("lamina-device: capture ")


def test_a_configured_device_id_and_default_plans_within_the_limits():
    import tomllib

    from lamina_device.config import ConfigError, default_config_path, parse_config

    data = tomllib.loads(default_config_path().read_text())
    assert parse_config(data).device_id is None
    assert parse_config({**data, "device": {"id": "box-7"}}).device_id == "box-7"
    for bad in ({"id": "no spaces"}, {"id": 7}, {"id": "x" * 65}, {"id": "a", "b": 1}, "box"):
        with pytest.raises(ConfigError, match=r"\[device\]"):
            parse_config({**data, "device": bad})
    for plan, expected in (
        ({"sections": 5000, "pitch_mm": 0.01}, "[plan] sections: 5000 is outside 1..1000"),
        ({"sections": 1000, "pitch_mm": 0.1, "views": 20}, "20000 views, at most 10000"),
    ):
        with pytest.raises(ConfigError) as info:
            parse_config({**data, "plan": {**data["plan"], **plan}})
        assert any(expected in p for p in info.value.problems), info.value.problems
