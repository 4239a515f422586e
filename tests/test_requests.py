"""The request/reply layer: any thread's request gets its own reply; extraction per scan."""

from __future__ import annotations

import dataclasses
import threading
import time

import numpy as np
import pytest
import serial
from hypothesis import given, settings
from hypothesis import strategies as st

from lamina_device.extract import ExtractSettings, changed_settings
from lamina_host import cli
from lamina_host.link.client import DeviceClient
from lamina_host.link.errors import RequestRefused, ScanStopped
from lamina_host.store.library import Library
from lamina_host.testing import LineFaults
from lamina_host.workflow.checks import check_extract_limits
from lamina_shared.errors import InputError
from lamina_shared.link import Channel
from lamina_shared.messages import Welcome
from lamina_shared.ops import ArgsError, ExtractChanges, parse_extract_text
from lamina_shared.protocol import Kind, encode_json
from lamina_shared.types import ScanPlan, Segment
from tests.helpers.served import link, reference
from tests.test_link import PLAN, same


def test_each_thread_gets_its_own_reply_and_events_in_any_order():
    """Two threads ask at once; the peer answers the second first, with an event between."""
    from lamina_host.link.spawn import PtyBridge

    bridge = PtyBridge()
    host_port = serial.Serial(bridge.host_port, timeout=0.02)
    peer_port = serial.Serial(bridge.device_port, timeout=0.02)
    peer = Channel(peer_port)
    client = DeviceClient(Channel(host_port), idle_timeout_s=10)
    results: dict[str, object] = {}
    events: dict[str, list[tuple[str, object]]] = {"status": [], "exposure": []}

    def ask(op: str) -> None:
        def on_event(message: object) -> None:
            events[op].append((threading.current_thread().name, message.body["n"]))  # type: ignore[attr-defined]

        results[op] = client.request(op, on_event=on_event)

    def answer() -> None:
        requests: dict[str, int] = {}
        while len(requests) < 2:
            message = peer.receive(5.0)
            assert message is not None, "a request did not arrive"
            if message.kind is Kind.REQUEST:
                requests[message.body["op"]] = message.body["id"]
        first, second = requests["status"], requests["exposure"]
        peer.send(encode_json(Kind.EVENT, {"id": second, "n": 2}))
        peer.send(encode_json(Kind.EVENT, {"id": first, "n": 1}))
        peer.send(encode_json(Kind.REPLY, {"id": second, "ok": True, "result": {"v": "e"}}))
        peer.send(encode_json(Kind.REPLY, {"id": first, "ok": True, "result": {"v": "s"}}))

    try:
        responder = threading.Thread(target=answer)
        responder.start()
        threads = [threading.Thread(target=ask, args=(op,), name=op) for op in events]
        for thread in threads:
            thread.start()
        for thread in [*threads, responder]:
            thread.join(timeout=15)
        assert results == {"status": {"v": "s"}, "exposure": {"v": "e"}}
        # Each event reached the thread that asked, on that thread.
        assert events == {"status": [("status", 1)], "exposure": [("exposure", 2)]}
        assert client.stats.request_retries == 0
    finally:
        client.close()
        host_port.close()
        peer_port.close()
        bridge.close()


def test_pause_resume_abort_and_status_from_another_thread_over_a_faulty_line():
    plan = ScanPlan.regular(3, 2.0, 8)
    expected = reference(plan, settings=ExtractSettings())
    # 3e-3: the few kilobytes that cross before the abort are damaged somewhere every time
    # (at 1e-3 a run could cross them clean and prove nothing).
    faults = LineFaults(error_rate=3e-3, delay_rate=0.02, delay_s=0.01, seed=7)
    with link(faults) as ends:
        client = ends.client
        arrived: dict[int, Segment] = {}
        first = threading.Event()
        seen: dict[str, object] = {}

        def store(seq: int, segment: Segment) -> None:
            arrived[seq] = segment
            first.set()

        def operator() -> None:
            first.wait(30)
            seen["pause"] = client.pause()
            seen["status"] = client.request("status")["state"]
            seen["resume"] = client.resume()
            count = len(arrived)
            deadline = time.monotonic() + 30
            while len(arrived) < count + 2 and time.monotonic() < deadline:
                time.sleep(0.02)
            seen["abort"] = client.abort()

        thread = threading.Thread(target=operator)
        thread.start()
        notices: list[str] = []
        with pytest.raises(ScanStopped) as info:
            client.scan("object", plan, on_segment=store, on_notice=notices.append)
        thread.join(timeout=30)
        # Each control's reply reached the operator's thread through the link's reader.
        assert seen == {
            "pause": "paused",
            "status": "paused",
            "resume": "busy",
            "abort": "aborting",
        }
        assert notices == []
        got = info.value.segments
        assert 3 <= len(got) < len(plan.views)
        assert same([got[s] for s in sorted(got)], [expected[s] for s in sorted(got)])
        damage = faults.counts["flipped"] + faults.counts["dropped"] + faults.counts["duplicated"]
        assert damage > 0, faults.counts  # the line did damage
        assert not ends.hardware.laser.is_on


def test_a_scan_uses_the_extraction_the_host_asks_for():
    thinning = reference(PLAN, settings=ExtractSettings(method="thinning"))
    default = reference(PLAN, settings=ExtractSettings())
    assert not same(thinning, default)
    with link() as ends:
        client = ends.client
        assert client.info is not None
        assert client.info.extract is not None
        assert client.info.extract.as_dict() == dataclasses.asdict(ExtractSettings())
        got = client.scan("object", PLAN, extract=ExtractChanges((("method", "thinning"),)))
        assert same(got, thinning)
        # Whole-pixel centres: the thinning method really ran on the device.
        assert all(np.array_equal(s.rows, np.round(s.rows)) for s in got)
        # The configuration's settings are reported and used when the scan changes none.
        ends.hardware.extract = ExtractSettings(method="thinning")
        info = client.hello()
        assert info.extract is not None and info.extract.as_dict()["method"] == "thinning"
        assert same(client.scan("object", PLAN), thinning)


def test_unusable_extraction_is_refused_with_every_problem_and_nothing_acquired():
    with link() as ends:
        client = ends.client
        frames = ends.hardware.camera.frames_taken
        bad = ExtractChanges((("power", 0.0), ("min_width_px", 9), ("max_width_px", 4)))
        with pytest.raises(RequestRefused) as info:
            client.scan("object", PLAN, extract=bad)
        assert info.value.code == "bad-args"
        assert "power 0.0 is not in (0, 8]" in str(info.value)
        assert "min_width_px 9 and max_width_px 4" in str(info.value)
        with pytest.raises(RequestRefused) as info:
            client.request("scan", {"target": "object", "extract": {"method": "sobel", "zz": 1}})
        assert "scan.extract: takes no argument 'zz'" in str(info.value)
        assert "scan.extract.method: one of cog, thinning is required" in str(info.value)
        assert ends.hardware.camera.frames_taken == frames
        assert client.request("status")["state"] == "idle"


def test_the_scan_identity_holds_the_effective_extraction():
    with link() as ends:
        client = ends.client
        configured = client.identity()["extract"]
        assert configured == dataclasses.asdict(ExtractSettings())
        client.extract = ExtractChanges((("method", "thinning"), ("threshold", 40.0)))
        changed = client.identity()["extract"]
        assert changed == {**configured, "method": "thinning", "threshold": 40.0}


def test_extract_option_text():
    changes = parse_extract_text("method=thinning, threshold=40,noise_gate=false,threshold=null")
    assert changes.as_dict() == {"method": "thinning", "threshold": None, "noise_gate": False}
    with pytest.raises(ArgsError) as info:
        parse_extract_text("power=big,colour=red,nothing")
    assert info.value.problems == [
        "extract: 'nothing' is not KEY=VALUE",
        "extract: takes no argument 'colour'",
        "extract.power: a number is required, found 'big'",
    ]


def test_cli_refuses_a_bad_extract_option_in_one_line(capsys, tmp_path):
    with pytest.raises(SystemExit) as info:
        cli.main(["scan", "--device", "sim", "-o", str(tmp_path / "x"), "--extract", "zz=1"])
    assert info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [  # one line, no usage (issue #24)
        "lamina scan: argument --extract: extract: takes no argument 'zz' (see lamina scan --help)"
    ]
    assert not (tmp_path / "x").exists()


# Each setting's candidates: in range, at the edges and beyond them (min/max width also
# against each other).
_CANDIDATES: dict[str, list[object]] = {
    "threshold": [None, -4.0, 0.0, 40.0, 254.0, 255.0],
    "power": [-1.0, 0.0, 0.5, 8.0, 8.5],
    "min_peak": [0.0, 1.0, 255.0, 256.0],
    "method": ["cog", "thinning"],
    "background_opening_px": [-1, 0, 1024, 1025],
    "false_points_per_frame": [0.0, 1e-12, 0.5, 1.5],
    "min_chain_px": [0, 1, 1000, 1001],
    "max_row_jump_px": [-0.5, 0.0, 100.0, 100.5],
    "min_width_px": [0, 1, 64, 70],
    "max_width_px": [0, 4, 64, 255, 256],
    "smooth_sigma_px": [-1.0, 0.0, 50.0, 51.0],
    "margin_px": [-1, 0, 16, 17],
    "bridge_px": [-1, 0, 8, 9],
}


@settings(max_examples=300, deadline=None)
@given(
    configured=st.fixed_dictionaries(
        {}, optional={k: st.sampled_from(v[1:-1] or v) for k, v in _CANDIDATES.items()}
    ),
    changes=st.dictionaries(
        st.sampled_from(sorted(_CANDIDATES)), st.none(), min_size=1, max_size=4
    ).flatmap(
        lambda keys: st.fixed_dictionaries({k: st.sampled_from(_CANDIDATES[k]) for k in keys})
    ),
)
def test_the_host_refuses_exactly_the_extraction_the_device_would(configured, changes):
    """The host's check before a scan exists and the device's at the scan agree, case by
    case, on what the device's configured settings with a scan's changes allow."""
    base, _ = changed_settings(ExtractSettings(), configured)
    if base is None:  # a configuration the device itself would not start with
        return
    device_settings, device_problems = changed_settings(base, changes)
    welcome = Welcome(protocol=1, extract=ExtractChanges(tuple(dataclasses.asdict(base).items())))
    wanted = ExtractChanges(tuple(changes.items()))
    if device_settings is not None:
        check_extract_limits(wanted, welcome)
        return
    with pytest.raises(InputError) as info:
        check_extract_limits(wanted, welcome)
    assert all(problem in str(info.value) for problem in device_problems)
    # A device that reports no settings (an older one) is left to refuse the scan itself.
    check_extract_limits(wanted, Welcome(protocol=1))


@pytest.mark.timeout(120)
def test_cli_refuses_extraction_beyond_the_device_before_a_scan_exists(capsys, tmp_path):
    """Ranges are the device's (the kinds pass the option's own check): no scan, no folder."""
    library = tmp_path / "library.sqlite"
    out = tmp_path / "x"
    argv = ["scan", "--device", "sim", "-o", str(out), "--library", str(library)]
    assert cli.main([*argv, "--extract", "threshold=-4,power=99"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert "threshold -4.0 is not in 0..254" in err[0]
    assert "power 99.0 is not in (0, 8]" in err[0]
    assert "no scan was created" in err[0]
    assert not out.exists()
    with Library(library) as opened:
        assert opened.scans() == []
